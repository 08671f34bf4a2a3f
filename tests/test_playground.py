"""MuJoCo Playground's DM Control tasks in cdjax's env layer (cdjax.envs.playground), on its cheapest task to compile
(PendulumSwingup). Everything but the first test needs the `playground` extra and is skipped without it."""

from __future__ import annotations

import dataclasses
import importlib.util
import json
import os
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cdjax import envs
from cdjax.envs import playground as pg, rewards

HAVE_PLAYGROUND = importlib.util.find_spec("mujoco_playground") is not None
needs_playground = pytest.mark.skipif(not HAVE_PLAYGROUND, reason="the playground extra is not installed")
TASK = "dmc-pendulum-swingup"


def test_names_and_the_missing_extra_in_one_sentence(monkeypatch, capsys, tmp_path):
    from cdjax.cli import main
    from cdjax.protocol import ConfigError
    from _shared import fail_in_one_sentence

    assert pg.cdjax_name("CheetahRun") == "dmc-cheetah-run" and pg.cdjax_name("BallInCup") == "dmc-ball-in-cup"
    assert pg.NAMES["dmc-swimmer-swimmer6"] == "SwimmerSwimmer6" and len(pg.NAMES) == len(pg.TASKS) == 25
    assert set(pg.NAMES) <= set(envs.available_envs())
    monkeypatch.setitem(sys.modules, "mujoco_playground", None)  # what an install without the extra sees
    with pytest.raises(ConfigError) as info:
        envs.make_single_env(TASK)
    assert str(info.value) == pg.MISSING and 'pip install -e ".[playground]"' in str(info.value)
    said = fail_in_one_sentence(capsys, main, ["sweep", "--env", TASK, "--out", str(tmp_path), "--no-progress"])
    assert said == f"cdjax: {pg.MISSING}"
    with pytest.raises(ConfigError, match="choose one of auto, jax, warp"):
        pg.resolve_backend("cuda")
    # the Mb-Mf phase's MPC refuses, in one sentence, the tasks whose reward is not a function of the observation
    assert rewards.reward_fn("dmc-cheetah-run") is None
    assert "observation does not hold" in rewards.why_not("dmc-cheetah-run")
    assert all(rewards.reward_fn(name) is not None for name in WITH_REWARDS + (TASK,))
    with pytest.raises(ValueError, match="needs action_repeat = 1"):
        rewards.reward_fn(TASK)(jnp.zeros(3), jnp.zeros(1), jnp.zeros(3), action_repeat=2)
    assert rewards.needs_action_repeat_one(TASK) and not rewards.needs_action_repeat_one("halfcheetah")


# The tasks whose reward cdjax.envs.rewards writes from observations, besides the pendulum (checked below); each
# compiles for about half a minute on a CPU, so they are checked only where CDJAX_PLAYGROUND_REWARDS is set.
WITH_REWARDS = ("dmc-cartpole-balance", "dmc-cartpole-balance-sparse", "dmc-cartpole-swingup",
                "dmc-cartpole-swingup-sparse", "dmc-reacher-easy", "dmc-reacher-hard", "dmc-point-mass")


@needs_playground
@pytest.mark.skipif(not os.environ.get("CDJAX_PLAYGROUND_REWARDS"), reason="set CDJAX_PLAYGROUND_REWARDS=1")
@pytest.mark.parametrize("name", WITH_REWARDS)
def test_rewards_of_observations_are_playgrounds(name):
    env = pg.PlaygroundEnv(name, backend="jax")
    reset, step = envs.physics(env)
    state = reset(jax.random.split(jax.random.key(0), 64))
    key, reward_of_obs, earned = jax.random.key(1), rewards.reward_fn(name), 0.0
    for _ in range(30):
        key, k = jax.random.split(key)
        action = jax.random.uniform(k, (64, env.action_size), minval=-1, maxval=1)
        after = step(state, action)
        np.testing.assert_allclose(reward_of_obs(state.obs, action, after.obs), after.reward, atol=1e-6)
        earned, state = max(earned, float(after.reward.max())), after
    assert earned > 0 or name.endswith("swingup-sparse")  # the sparse swing-up earns nothing in 30 random steps


@needs_playground
def test_the_names_are_playgrounds_tasks():
    from mujoco_playground import dm_control_suite

    assert pg.TASKS == tuple(dm_control_suite.ALL_ENVS)
    assert pg.resolve_backend("auto") == ("warp" if pg.warp_available() else "jax")


def test_a_dict_observation_is_flattened_in_sorted_key_order():
    obs = {"b": jnp.array([[1.0, 2.0]]), "a": jnp.array(3.0), "c": jnp.array([4, 5], jnp.int32)}
    np.testing.assert_array_equal(pg.flat_obs(obs), [3.0, 1.0, 2.0, 4.0, 5.0])
    assert pg.flat_obs(obs).dtype == jnp.float32


class _EndsAtSecondStep:
    """The raw task, its step saying `done` once the physics has run two control steps since the reset (the DM
    Control tasks end only at their time limit or on NaN, so a termination is made here)."""

    def __init__(self, raw):
        self.raw = raw

    def __getattr__(self, name):
        return getattr(self.raw, name)

    def step(self, state, action):
        s = self.raw.step(state, action)
        ended = s.data.time >= 1.5 * self.raw.dt
        return s.replace(done=jnp.where(ended, 1.0, s.done))


@needs_playground
def test_final_observations_are_kept_at_time_outs_and_terminations():
    from mujoco_playground import State

    env = pg.PlaygroundEnv(TASK, backend="jax")
    env.raw = _EndsAtSecondStep(env.raw)
    batch = envs.BatchedEnv(env, num_envs=2, episode_length=3)
    state = batch.reset(jax.random.key(0))
    state = state.replace(t=jnp.array([0, 2], jnp.int32))  # env 1 one step before its time limit
    # env 0's pole near upright, env 1's hanging: one earns the swing-up's reward on the first step, the other not
    core = state.core
    state = state.replace(core=core.replace(data=core.data.replace(qpos=jnp.array([[0.05], [jnp.pi - 0.05]]))))
    own_step = jax.jit(jax.vmap(env.raw.step))  # Playground's own step of the same states
    step = jax.jit(batch.step)
    action = jnp.array([[0.5], [-0.5]])
    ends, reward_of_obs = [], rewards.reward_fn(TASK)
    for i in range(3):
        core = state.core
        raw = own_step(State(core.data, core.obs, core.reward, core.done, core.metrics, core.info), action)
        state, out = step(state, action)
        np.testing.assert_allclose(out.next_obs, raw.obs, rtol=1e-6, atol=1e-6)
        np.testing.assert_allclose(out.reward, raw.reward, rtol=1e-6, atol=1e-6)
        np.testing.assert_allclose(reward_of_obs(core.obs, action, out.next_obs), out.reward, atol=1e-6)
        if i == 0:
            assert out.reward.tolist() == [1.0, 0.0]
        ended = np.asarray(out.terminated | out.truncated)
        restart = np.asarray(state.first.obs)  # cached resets: each env's own first start
        np.testing.assert_array_equal(np.asarray(state.obs)[ended], restart[ended])
        assert not np.allclose(np.asarray(out.next_obs)[ended], restart[ended])  # not the reset observation
        ends.append((out.terminated.tolist(), out.truncated.tolist()))
        assert bool(out.valid.all())
    # env 1 times out at its first step and ends its next episode at that episode's second step (done); env 0 at
    # its second step
    assert ends == [([False, False], [False, True]), ([True, False], [False, False]), ([False, True], [False, False])]

    # a non-finite state (env 0's) is masked and reset, not a termination; the other env steps on
    core = state.core
    state = state.replace(core=core.replace(data=core.data.replace(qvel=core.data.qvel.at[0].set(jnp.nan))))
    t = np.asarray(state.t)
    state, out = step(state, action)
    assert out.valid.tolist() == [False, True] and not bool(out.terminated.any() | out.truncated.any())
    assert bool(jnp.isfinite(out.next_obs).all()) and float(out.reward[0]) == 0.0
    np.testing.assert_array_equal(state.obs[0], state.first.obs[0])
    assert state.t.tolist() == [0, int(t[1]) + 1]


# A tiny model-free sweep of the observation-space setting on the pendulum, 2 updates per chunk.
CHUNK, UPDATES = 2, 4
ARGS = ["sweep", "--env", TASK, "--arms", "model-free", "--num-envs", "4", "--rollout-len", "8", "--horizon", "4",
        "--num-epochs", "1", "--num-minibatches", "2", "--episode-length", "20", "--policy-hidden", "8",
        "--value-hidden", "8", "--model-hidden", "8", "--encoder-dim", "4", "--eval-horizon", "4", "--eval-envs", "2",
        "--seeds", "2", "--chunk-updates", str(CHUNK), "--steps", str(UPDATES * 32), "--eval-episodes", "2",
        "--bootstrap-reps", "20", "--physics-backend", "jax", "--no-progress"]


@pytest.fixture(scope="module")
def whole(tmp_path_factory):
    from cdjax.cli import main

    out = tmp_path_factory.mktemp("playground") / "whole"
    main(ARGS + ["--out", str(out)])
    return out


@needs_playground
def test_a_sweep_runs_resumes_exactly_and_evaluates(whole, tmp_path):
    from cdjax import io
    from cdjax.runner import Interrupted, resume_spec, run_sweep
    from _shared import logged_rows

    run = json.loads((whole / "run.json").read_text())
    assert run["base_config"]["env"] == TASK and run["base_config"]["physics_backend"] == "jax"
    assert [c["physics_backend"] for c in run["code"]] == ["jax"]  # which ran
    rows = logged_rows(whole)
    assert sorted((r["seed"], r["update"]) for r in rows) == [(s, u) for s in range(2) for u in range(1, UPDATES + 1)]
    assert all(np.isfinite(r["loss/value"]) and r["env/invalid_fraction"] == 0 for r in rows)
    evals = io.read_jsonl(whole / "eval.jsonl")
    assert sorted(e["seed"] for e in evals) == [0, 1] and all(e["episodes"] == 2 for e in evals)
    assert all(e["lengths"] == [20, 20] for e in evals)  # the DM Control tasks end at their time limit

    spec = dataclasses.replace(resume_spec(whole, progress=False), out=tmp_path / "cut")
    with pytest.raises(Interrupted):
        run_sweep(spec, after_chunk=lambda chunks, updates: chunks >= 1)
    run_sweep(resume_spec(tmp_path / "cut", progress=False), resume=True)
    key = lambda r: (r["seed"], r["update"])  # noqa: E731
    cut = sorted(logged_rows(tmp_path / "cut"), key=key)
    assert [key(r) for r in cut] == sorted(key(r) for r in rows)
    for a, b in zip(cut, sorted(rows, key=key)):  # the resumed run is the same run, number for number
        assert all(a[m] == b[m] for m in ("env/reward_mean", "loss/policy", "loss/value")), key(a)
    evals = io.read_jsonl(tmp_path / "cut" / "eval.jsonl")
    assert sorted(e["seed"] for e in evals) == [0, 1] and all(e["update"] == UPDATES for e in evals)


@needs_playground
def test_the_mbmf_phase_takes_the_true_reward_only_where_it_is_written():
    from cdjax import Config
    from cdjax.agents.obs.mbmf import MbMfPhase, validate_phase
    from cdjax.protocol import ConfigError

    true = MbMfPhase(mpc_reward="true")
    with pytest.raises(ConfigError, match="dmc-cheetah-run has none: its reward reads"):
        validate_phase(Config(env="dmc-cheetah-run"), true)
    with pytest.raises(ConfigError, match=f"on {TASK} needs action_repeat = 1"):
        validate_phase(Config(env=TASK, action_repeat=2), true)
    validate_phase(Config(env=TASK), true)
