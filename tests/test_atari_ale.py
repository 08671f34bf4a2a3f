"""The ALE tier (optional extra `atari`): a real game stepped inside a jitted lax.scan through ale-py's XLA
interface gives the observations, rewards and ends of ale-py's own Python-side stepping for the same seeds and
actions, and life losses end learning episodes only; runs vmapped together (folded into one vector environment)
step the same games as each run alone; the emulators get one thread per core the process may run on (its CPU
affinity); `cdjax sweep` of 2 seeds trains, is cut, resumed and evaluated, resumes alike where it was cut and
elsewhere from its packed state (experiments/atari/ale40m.py), and its first updates equal each seed's alone; the
throughput benchmark reports cdjax's rate and ale-py's."""

from __future__ import annotations

import dataclasses
import json
import pathlib
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

pytest.importorskip("ale_py", reason="ale-py is the optional extra `atari`: pip install -e \".[atari]\"")

from ale_py.vector_env import AtariVectorEnv  # noqa: E402

from cdjax import io  # noqa: E402
from cdjax.agents.atari import AtariConfig, AtariHParams, make_trainer  # noqa: E402
from cdjax.agents.atari.ale import ONE_DEVICE, ONE_PROCESS, AleEnv, usable_cores, vector_env  # noqa: E402
from cdjax.cli import main  # noqa: E402
from cdjax.protocol import ConfigError  # noqa: E402
from cdjax.runner import Interrupted, restore_arms, resume_spec, run_sweep  # noqa: E402

from _shared import logged_rows  # noqa: E402

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))  # `benchmarks` is not installed
from benchmarks import ale as bench  # noqa: E402
from experiments.atari import ale40m  # noqa: E402

CONFIG = AtariConfig(env="ale-breakout", num_envs=3, sticky_prob=0.25, episode_length=27000, latent=512)
STEPS = 300


def _player(env: AleEnv, with_lives: bool = False):
    """(key, actions [S, B]) -> (first obs, per-step outputs): reset, then a scan of env.step."""

    def play(key, actions):
        state = env.reset(key)

        def step(state, action):
            state, out = env.step(state, action)
            extra = (state.lives,) if with_lives else ()
            return state, (out.next_obs, out.reward, out.terminated, out.game_over, out.valid) + extra

        return state.obs, jax.lax.scan(step, state, actions)[1]

    return play


def test_a_jitted_scan_steps_the_games_ale_py_steps():
    env = AleEnv(CONFIG, 3, episodic_life=True)
    actions = jnp.asarray(np.random.RandomState(0).randint(0, env.num_actions, (STEPS, 3)), jnp.int32)
    key = jax.random.key(5)
    first, (obs, reward, terminated, game_over, valid, lives) = jax.jit(_player(env, with_lives=True))(key, actions)
    seeds = np.asarray(jax.random.randint(jax.random.split(key)[0], (3,), 0, 2**31 - 1, jnp.int32))

    python = vector_env(AtariVectorEnv, CONFIG, 3)
    assert env.num_actions == python.single_action_space.n
    py_obs, _ = python.reset(seed=seeds)
    np.testing.assert_array_equal(np.moveaxis(py_obs, 1, -1), first)
    life_losses = 0
    for t in range(STEPS):
        py_obs, py_reward, py_term, py_trunc, info = python.step(np.asarray(actions[t]))
        np.testing.assert_array_equal(np.moveaxis(py_obs, 1, -1), obs[t], err_msg=f"step {t}")
        np.testing.assert_array_equal(np.where(valid[t], py_reward, 0), reward[t])
        np.testing.assert_array_equal(py_term & valid[t], game_over[t] & ~py_trunc)
        np.testing.assert_array_equal(info["lives"], lives[t])
        life_losses += int((terminated[t] & ~game_over[t]).sum())
    assert life_losses > 0 and np.asarray(obs).any()  # lives were lost without the games ending
    assert np.asarray(game_over).any() and not np.asarray(valid).all()  # games ended; ale-py reset them a step later
    assert np.asarray(reward).sum() > 0  # random play scores in Breakout


def test_runs_vmapped_together_step_the_games_each_run_steps_alone(monkeypatch):
    """Two runs (their own keys and actions) vmapped, and vmapped twice, step one vector env of 2 x 3 emulators and
    give what each run gives alone; tracing for shapes makes no emulators; several devices are refused."""
    keys = jax.random.split(jax.random.key(1), 2)
    actions = jnp.asarray(np.random.RandomState(1).randint(0, 4, (2, 120, 3)), jnp.int32)
    env = AleEnv(CONFIG, 3)
    assert jax.eval_shape(jax.vmap(_player(env)), keys, actions)[0].shape == (2, 3, 84, 84, 4) and not env._vectors
    together = jax.jit(jax.vmap(_player(env)))(keys, actions)
    assert list(env._vectors) == [6]  # one vector env of runs x envs
    nested = jax.jit(jax.vmap(jax.vmap(_player(env))))(keys[None], actions[None])
    alone_env = AleEnv(CONFIG, 3)
    alone = [jax.jit(_player(alone_env))(keys[r], actions[r]) for r in range(2)]
    assert list(alone_env._vectors) == [3] and list(env._vectors) == [6]
    for r in range(2):
        for a, b, c in zip(jax.tree.leaves(alone[r]), jax.tree.leaves(together), jax.tree.leaves(nested)):
            np.testing.assert_array_equal(a, b[r])
            np.testing.assert_array_equal(a, c[0, r])
    assert not np.array_equal(together[0][0], together[0][1])  # the two runs play their own games
    monkeypatch.setattr(jax, "device_count", lambda *a: 2)
    with pytest.raises(ConfigError, match="one device"):
        AleEnv(CONFIG, 3)
    monkeypatch.setattr(jax, "process_count", lambda *a: 2)  # one device in each of two processes: --distributed
    with pytest.raises(ConfigError, match="without --distributed"):
        AleEnv(CONFIG, 3)
    assert ONE_DEVICE.endswith(".") and ONE_PROCESS.endswith(".")


@pytest.mark.skipif(usable_cores() < 2, reason="one core: every thread count is 1")
def test_the_emulators_get_one_thread_per_core_the_process_may_run_on():
    """Under a CPU affinity of one core (as `taskset -c` or ale40m's `pin` gives a piece), the vector env steps its
    emulators with one thread on that core, not one per core of the host (ale-py's own default)."""
    import os

    tasks = lambda: set(os.listdir("/proc/self/task"))  # noqa: E731
    cores = sorted(os.sched_getaffinity(0))
    before = tasks()
    wide = vector_env(AtariVectorEnv, CONFIG, 8)
    assert len(tasks() - before) == min(8, len(cores))
    del wide
    os.sched_setaffinity(0, cores[:1])  # this thread's: the threads it starts inherit it
    try:
        before = tasks()
        narrow = vector_env(AtariVectorEnv, CONFIG, 8)
        new = tasks() - before
        assert usable_cores() == 1 and len(new) == 1
        allowed = pathlib.Path(f"/proc/self/task/{new.pop()}/status").read_text()
        assert f"Cpus_allowed_list:\t{cores[0]}\n" in allowed
        del narrow
    finally:
        os.sched_setaffinity(0, cores)


# 2 seeds x 2 envs of the breakout preset with small networks and short games (benchmarks.ale's tiny config, so that
# the benchmark's chunk program is this sweep's): 4 updates of 2 envs x 5 steps, chunks of 2.
CHUNK, UPDATES = 2, 4
ARGS = ["sweep", "--setting", "atari", "--preset", "breakout", "--arms", "a2c-cd", "--seeds", "2",
        *[x for k, v in bench.TINY_CONFIG.items() for x in (f"--{k.replace('_', '-')}", str(v))],
        "--steps", str(UPDATES * 10), "--chunk-updates", str(CHUNK), "--eval-episodes", "2", "--bootstrap-reps", "20",
        "--no-progress"]


@pytest.fixture(scope="module")
def whole(tmp_path_factory):
    out = tmp_path_factory.mktemp("ale") / "whole"
    main(ARGS + ["--out", str(out)])
    return out


def test_a_sweep_of_seeds_is_cut_resumed_and_evaluated(whole, tmp_path):
    run = json.loads((whole / "run.json").read_text())
    assert run["seeds"] == 2 and run["base_config"]["env"] == "ale-breakout"
    rows = logged_rows(whole)
    assert sorted((r["seed"], r["update"]) for r in rows) == [(s, u) for s in range(2) for u in range(1, UPDATES + 1)]
    assert all(np.isfinite(r["loss/consistency"]) for r in rows)
    evals = io.read_jsonl(whole / "eval.jsonl")
    assert sorted(e["seed"] for e in evals) == [0, 1] and all(e["episodes"] == 2 for e in evals)

    spec = dataclasses.replace(resume_spec(whole, progress=False), out=tmp_path / "cut")
    with pytest.raises(Interrupted):
        run_sweep(spec, after_chunk=lambda chunks, updates: chunks >= 1)
    # the 40M-frame tier's way to the next machine (experiments/atari/ale40m.py): packed, unpacked elsewhere
    parts = ale40m.pack(tmp_path / "cut", tmp_path / "outbox", "ale40m-breakout-a2c-cd", part_bytes=200_000, every=1)
    assert ale40m.unpack(parts, tmp_path / "moved") == CHUNK
    run_sweep(resume_spec(tmp_path / "cut", progress=False), resume=True)
    cut = logged_rows(tmp_path / "cut")
    # resumed elsewhere it is the run resumed where it was cut: the checkpoint's parameters, optimiser state and keys,
    # and the same new games (a resumed run's emulators start from init's, wherever it resumes)
    run_sweep(resume_spec(tmp_path / "moved", progress=False), resume=True)
    assert logged_rows(tmp_path / "moved") == cut
    for a, b in zip(restore_arms(tmp_path / "moved")[1], restore_arms(tmp_path / "cut")[1]):
        for x, y in zip(jax.tree.leaves(a.state), jax.tree.leaves(b.state)):
            x, y = (jax.random.key_data(v) if jax.dtypes.issubdtype(v.dtype, jax.dtypes.prng_key) else v
                    for v in (x, y))
            np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    first = lambda rows: [r for r in rows if r["update"] <= CHUNK]  # noqa: E731
    # the first chunk is the same run; after the resume the emulators play new games (they are not checkpointed)
    assert [r["train/reward"] for r in first(cut)] == [r["train/reward"] for r in first(rows)]
    assert sorted((r["seed"], r["update"]) for r in cut) == sorted((r["seed"], r["update"]) for r in rows)
    evals = io.read_jsonl(tmp_path / "cut" / "eval.jsonl")  # the resumed sweep's final evaluation
    assert sorted(e["seed"] for e in evals) == [0, 1] and all(e["update"] == UPDATES for e in evals)


def test_the_sweeps_seeds_equal_each_seed_alone(whole):
    """Each seed's first updates, trained alone (its own 2 emulators) with the sweep's key, give the sweep's rewards
    and losses: the runs folded into one vector env played each seed's own games."""
    run = json.loads((whole / "run.json").read_text())
    (arm,) = run["arms"]
    config, hp = AtariConfig(**arm["config"]), AtariHParams(**arm["hparams"][0])
    trainer = make_trainer(config)
    rows = logged_rows(whole)
    init, update = jax.jit(trainer.init), jax.jit(trainer.update)
    for seed, key in enumerate(jax.random.split(jax.random.key(run["seed"]), run["seeds"])):
        state = init(key, hp)
        for u in range(1, CHUNK + 1):
            state, metrics = update(state, hp)
            row = next(r for r in rows if r["seed"] == seed and r["update"] == u)
            assert row["train/reward"] == pytest.approx(float(metrics["train/reward"]), abs=0), (seed, u)
            for name in ("loss/policy", "loss/value", "policy/entropy", "model/latent_mse"):
                np.testing.assert_allclose(row[name], metrics[name], rtol=2e-4, atol=1e-6, err_msg=name)


def test_the_benchmark_reports_cdjax_and_ale_py(tmp_path):
    result = bench.main(["--tiny", "--totals", "4", "--arms", "a2c-cd", "--chunk-updates", str(CHUNK), "--seconds",
                         "0.1", "--out", str(tmp_path)])
    cases = {r["case"]: r for r in result["rows"]}
    assert set(cases) == {"ale-py", "in jit", "cdjax a2c-cd"}
    assert all(r["status"] == "ok" and r["agent_steps_per_s"] > 0 for r in cases.values()), cases
    assert cases["cdjax a2c-cd"]["seeds"] == 2 and cases["ale-py"]["total_envs"] == 4
    text = (tmp_path / "results.md").read_text()
    assert "| 4 | 2 x 2 | cdjax a2c-cd |" in text and "| 4 | 1 x 4 | ale-py |" in text
    assert json.loads((tmp_path / "results.json").read_text())["meta"]["cpu_count"] >= 1
