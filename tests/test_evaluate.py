"""evaluate / make_evaluator on the point env (hand-worked returns), eval records, videos."""

import dataclasses
import functools
import json
import os
import subprocess
import sys
import textwrap

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cdjax import HParams, io, plots
from cdjax.envs import BatchedEnv
from cdjax.envs.point import PointMass
from cdjax.evaluate import eval_records, evaluate, make_evaluator, render_video

from _shared import POINT, compiled, host_trainer


def gain_policy(trainer, episode_length):
    """The trainer with a hand-set linear policy a = clip(gain * x) (policy = {"gain": scalar}), on point
    masses that time out after `episode_length` steps."""
    act = lambda policy, obs, key: jnp.clip(policy["gain"] * obs[:, :2], -1.0, 1.0)  # noqa: E731
    return dataclasses.replace(trainer, act=act, eval_env=lambda n: BatchedEnv(PointMass(), n, episode_length))


def hand_returns(obs0, gain, gamma, episode_length):
    """Per-episode (return, discounted return, length, terminated) by stepping the point mass in numpy."""
    out = []
    for obs in np.asarray(obs0, np.float64):
        ret = disc = 0.0
        for t in range(episode_length):
            a = np.clip(gain * obs[:2], -1, 1)
            v = 0.9 * obs[2:] + 0.1 * a
            x = obs[:2] + 0.1 * v
            obs = np.concatenate([x, v])
            r = 1.0 - np.sum(x**2) - 0.01 * np.sum(a**2)
            ret += r
            disc += gamma**t * r
            if np.max(np.abs(x)) > 2.0:
                out.append((ret, disc, t + 1, True))
                break
        else:
            out.append((ret, disc, episode_length, False))
    return np.array(out)


def _run(trainer, policy, key, **kw):
    return jax.jit(functools.partial(evaluate, trainer, **kw))(policy, key)


def test_deterministic_evaluation_repeats_and_has_one_result_per_episode():
    _, init, _ = compiled(POINT)
    trainer = host_trainer(POINT)
    state = init(jax.random.key(0), HParams())
    ev = jax.jit(functools.partial(evaluate, trainer, episodes=6, hp=HParams(), deterministic=True))
    a = ev(trainer.policy(state), jax.random.key(1))
    b = ev(trainer.policy(state), jax.random.key(1))
    for name in ("return", "discounted_return", "length", "terminated", "finished", "valid"):
        assert a[name].shape == (6,), name
        np.testing.assert_array_equal(a[name], b[name], err_msg=name)
    assert a["initial_obs"].shape == (6, 4) and bool(a["finished"].all())
    assert ((a["length"] >= 1) & (a["length"] <= POINT.episode_length)).all()
    assert float(a["return_mean"]) == pytest.approx(float(a["return"].mean()))
    # sampled actions change the returns; a different key gives different starts
    stoch = jax.jit(functools.partial(evaluate, trainer, episodes=6, hp=HParams(), deterministic=False))
    c = stoch(trainer.policy(state), jax.random.key(1))
    np.testing.assert_array_equal(c["initial_obs"], a["initial_obs"])
    assert not np.allclose(c["return"], a["return"])


def test_returns_equal_hand_computation():
    trainer = host_trainer(POINT)
    hp = HParams(gamma=0.9)
    # toward the origin for 6 steps: every episode times out
    res = _run(gain_policy(trainer, 6), {"gain": jnp.float32(-3.0)}, jax.random.key(2), episodes=4, hp=hp,
               deterministic=True)
    hand = hand_returns(res["initial_obs"], -3.0, 0.9, 6)
    np.testing.assert_allclose(res["return"], hand[:, 0], rtol=1e-5)
    np.testing.assert_allclose(res["discounted_return"], hand[:, 1], rtol=1e-5)
    np.testing.assert_array_equal(res["length"], 6)
    assert not bool(res["terminated"].any())
    # away from the origin: episodes terminate at different steps, nothing after the end is counted
    res = _run(gain_policy(trainer, 60), {"gain": jnp.float32(3.0)}, jax.random.key(3), episodes=5, hp=hp,
               deterministic=True)
    hand = hand_returns(res["initial_obs"], 3.0, 0.9, 60)
    assert hand[:, 3].all() and len(set(hand[:, 2])) > 1  # really different termination steps
    np.testing.assert_allclose(res["return"], hand[:, 0], rtol=1e-5)
    np.testing.assert_allclose(res["discounted_return"], hand[:, 1], rtol=1e-5)
    np.testing.assert_array_equal(res["length"], hand[:, 2])
    assert bool(res["terminated"].all())


def test_policy_toward_origin_beats_policy_away_and_max_steps_cuts():
    trainer = gain_policy(host_trainer(POINT), POINT.episode_length)
    kw = dict(episodes=8, hp=HParams(), deterministic=True)
    good = _run(trainer, {"gain": jnp.float32(-5.0)}, jax.random.key(4), **kw)
    bad = _run(trainer, {"gain": jnp.float32(5.0)}, jax.random.key(4), **kw)
    assert float(good["return_mean"]) > float(bad["return_mean"]) + 5.0
    assert float(good["discounted_return_mean"]) > float(bad["discounted_return_mean"])
    cut = _run(trainer, {"gain": jnp.float32(-5.0)}, jax.random.key(4), max_steps=5, **kw)
    np.testing.assert_array_equal(cut["length"], 5)
    assert not bool(cut["finished"].any())


def test_make_evaluator_vmaps_over_runs_and_records_round_trip(tmp_path):
    _, init, _ = compiled(POINT)
    trainer = host_trainer(POINT)
    keys = jax.random.split(jax.random.key(5), 2)
    hps = jax.tree.map(lambda x: jnp.stack([x, x]), HParams(gamma=0.95).as_float32())
    states = [init(k, HParams()) for k in keys]
    policy = jax.tree.map(lambda *x: jnp.stack(x), *[trainer.policy(s) for s in states])
    eval_keys = jax.random.split(jax.random.key(6), 2)
    results = make_evaluator(trainer, episodes=3, deterministic=True)(policy, eval_keys, hps)
    assert results["return"].shape == (2, 3) and results["return_mean"].shape == (2,)
    alone = jax.jit(functools.partial(evaluate, trainer, episodes=3, hp=HParams(gamma=0.95), deterministic=True))(
        trainer.policy(states[1]), eval_keys[1])
    np.testing.assert_allclose(results["discounted_return"][1], alone["discounted_return"], rtol=1e-6)

    records = eval_records(results, arm="cd-a1", hp_labels=["alpha=1.0"], seeds=[0, 1], deterministic=True,
                           update=7, env_steps=123)
    path = io.append_jsonl(tmp_path / "eval.jsonl", records)
    lines = [json.loads(line) for line in path.read_text().splitlines()]
    assert len(lines) == 2 and lines[1]["seed"] == 1 and lines[1]["update"] == 7 and len(lines[1]["returns"]) == 3
    assert lines[1]["eval/return"] == pytest.approx(float(results["return"][1].mean()), rel=1e-6)
    loaded = plots.load_eval(tmp_path)[("cd-a1", "alpha=1.0", True)]
    np.testing.assert_allclose(loaded["return"], np.asarray(results["return"]).mean(1), rtol=1e-6)


def test_make_evaluator_compiles_once_per_input_kind_in_the_compile_mode_it_was_made_in(monkeypatch):
    """The evaluator compiles as cdjax's other programs do (compile_fitting, the mode in force when it was made), once
    per kind of input, and computes what the plain jit(vmap) does; inside a trace it is that jit."""
    from cdjax import runtime
    from cdjax.runner import budget

    trainer = host_trainer(POINT)
    _, init, _ = compiled(POINT)
    policy = jax.tree.map(lambda x: jnp.stack([x, x]), trainer.policy(init(jax.random.key(1), HParams())))
    hps = jax.tree.map(lambda x: jnp.stack([x, x]), HParams().as_float32())
    keys = jax.random.split(jax.random.key(2), 2)
    calls = []
    real = budget.compile_fitting
    monkeypatch.setattr(budget, "compile_fitting", lambda lowered, room=None, mode=None: calls.append(mode) or real(
        lowered, room, mode))
    monkeypatch.setattr(runtime, "_mode", "deterministic")
    evaluator = make_evaluator(trainer, episodes=2, deterministic=True)
    monkeypatch.setattr(runtime, "_mode", "fast")  # a later change of mode does not reach an evaluator made before
    first = evaluator(policy, keys, hps)
    second = evaluator(policy, jax.random.split(jax.random.key(3), 2), hps)
    assert calls == ["deterministic"]  # one compile for both calls, in the mode of its making
    evaluator(jax.tree.map(lambda x: x[:1], policy), keys[:1], jax.tree.map(lambda x: x[:1], hps))
    assert calls == ["deterministic", "deterministic"]  # another run count: another program

    def one(p, k, hp):
        return evaluate(trainer, p, k, episodes=2, hp=hp, deterministic=True)

    plain = jax.jit(jax.vmap(one))(policy, keys, hps)
    for name in ("return", "discounted_return", "length"):
        np.testing.assert_array_equal(first[name], plain[name])
    assert not np.array_equal(first["initial_obs"], second["initial_obs"])  # the keys were used
    traced = jax.jit(lambda p, k, h: evaluator(p, k, h)["return"])(policy, keys, hps)
    np.testing.assert_array_equal(traced, plain["return"])
    assert len(calls) == 2


def test_render_video_without_a_model_says_why(tmp_path, capsys):
    _, init, _ = compiled(POINT)
    trainer = host_trainer(POINT)
    state = init(jax.random.key(0), HParams())
    assert render_video(trainer, trainer.policy(state), jax.random.key(0), tmp_path / "v.mp4", steps=5) is None
    out = capsys.readouterr().out
    assert "No video" in out and "no MuJoCo model" in out and out.strip().count("\n") == 0


@pytest.mark.filterwarnings("ignore")  # GLFW warns that it cannot initialise without a display
def test_render_video_in_this_process_renders_or_says_how_to_fix(tmp_path, capsys):
    """Without a usable OpenGL backend (MUJOCO_GL unset here: GLFW, no display) the answer is None and a
    sentence naming MUJOCO_GL; the renderer is tried before anything is compiled, so this is cheap."""
    import types

    from cdjax.envs import make_single_env

    single = make_single_env("inverted_pendulum")
    trainer = types.SimpleNamespace(act=lambda policy, obs, key: jnp.zeros((obs.shape[0], 1)),
                                    eval_env=lambda n: BatchedEnv(single, n, 20))
    path = render_video(trainer, None, jax.random.key(0), tmp_path / "v.gif", steps=3, width=32, height=24)
    if path is None:
        out = capsys.readouterr().out
        assert "No video: no OpenGL context" in out and "MUJOCO_GL=egl" in out
    else:
        assert path.exists()


_RENDER_SCRIPT = textwrap.dedent("""
    import sys, types, jax, jax.numpy as jnp
    from cdjax import runtime
    runtime.configure(cache_dir=sys.argv[2])
    from cdjax.envs import BatchedEnv, make_single_env
    from cdjax.evaluate import render_video
    # render_video uses trainer.act and trainer.eval_env only; a stand-in skips building the agent
    single = make_single_env("inverted_pendulum")
    act = lambda policy, obs, key: jnp.zeros((obs.shape[0], 1)) + policy
    trainer = types.SimpleNamespace(act=act, eval_env=lambda n: BatchedEnv(single, n, 50))
    path = render_video(trainer, jnp.float32(0.0), jax.random.key(0), sys.argv[1], steps=12, width=96, height=64)
    print("RESULT", path)
""")


def test_render_video_mjx(tmp_path):
    """A real offscreen render of an MJX task, in a fresh process (MUJOCO_GL is read when mujoco is imported)."""
    import imageio.v3 as iio

    env = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
    cache = os.environ.get("CDJAX_JAX_CACHE", os.path.join(os.path.dirname(__file__), "..", ".jax_cache"))
    proc = subprocess.run([sys.executable, "-c", _RENDER_SCRIPT, str(tmp_path / "pendulum.mp4"), cache], env=env,
                          capture_output=True, text=True, timeout=400)
    assert proc.returncode == 0, proc.stderr[-3000:]
    result = [line for line in proc.stdout.splitlines() if line.startswith("RESULT")][-1].split(" ", 1)[1]
    if result == "None":
        reason = [line for line in proc.stdout.splitlines() if line.startswith("No video")]
        pytest.skip(reason[-1] if reason else "render_video returned None")
    frames = iio.imread(result)
    assert frames.shape[0] == 13 and frames.shape[1:3] == (64, 96)  # the reset frame + 12 steps
    assert frames.std() > 1.0  # not a blank image


def test_evaluators_of_the_same_program_share_one_compile_and_a_different_network_compiles_its_own(monkeypatch):
    """Two arms' evaluators (the model-free and cd configs: policies that differ only in values) lower to one module
    and share one compiled program, whose results equal, bit for bit, each evaluator's compiled alone; an arm whose
    policy network is narrower lowers to another module and compiles its own."""
    import cdjax.evaluate

    monkeypatch.setattr(cdjax.evaluate, "_PROGRAMS", {})
    hps = jax.tree.map(lambda x: jnp.stack([x, x]), HParams().as_float32())
    keys = jax.random.split(jax.random.key(8), 2)

    def inputs(config, seed):  # a trainer and two runs' untrained policies
        trainer = host_trainer(config)
        return trainer, jax.vmap(trainer.fresh_policy)(jax.random.split(jax.random.key(seed), 2))

    arms = [inputs(dataclasses.replace(POINT, arm="model-free"), 1), inputs(POINT, 2)]
    shared = [make_evaluator(trainer, episodes=2, deterministic=True) for trainer, _ in arms]
    results = [ev(policy, keys, hps) for ev, (_, policy) in zip(shared, arms)]
    assert [ev.compiles for ev in shared] == [1, 0] and len(cdjax.evaluate._PROGRAMS) == 1
    assert not np.array_equal(results[0]["return"], results[1]["return"])  # different policies
    for (trainer, policy), got in zip(arms, results):
        monkeypatch.setattr(cdjax.evaluate, "_PROGRAMS", {})
        alone = make_evaluator(trainer, episodes=2, deterministic=True)
        want = alone(policy, keys, hps)
        assert alone.compiles == 1
        for name in ("return", "discounted_return", "length", "initial_obs"):
            np.testing.assert_array_equal(got[name], want[name])
    narrow = inputs(dataclasses.replace(POINT, policy_hidden=(8,)), 3)
    evaluator = make_evaluator(narrow[0], episodes=2, deterministic=True)
    evaluator(narrow[1], keys, hps)
    assert evaluator.compiles == 1 and len(cdjax.evaluate._PROGRAMS) == 2
