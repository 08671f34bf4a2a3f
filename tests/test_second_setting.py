"""A second setting written only here (a continuous bandit learnt by REINFORCE or by evolution strategies, with
a warm-up phase) runs through cdjax's sweep, checkpoints, resume, evaluation, plots and command line, none of
which knows it: the host side depends on cdjax.protocol alone."""

from __future__ import annotations

import dataclasses
import json
from typing import Literal

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import struct

from cdjax import agents, io
from cdjax.cli import main
from cdjax.envs import Step
from cdjax.protocol import ConfigError, Metrics, Phase, Preset, Setting, Trainer
from cdjax.runner import Interrupted, SweepSpec, restore_arms, resume_spec, run_sweep

from _shared import logged_rows


@dataclasses.dataclass(frozen=True)
class BanditConfig:
    """A bandit whose best action is `target` in every coordinate."""

    dim: int = 2  # action size
    batch: int = 8  # actions pulled per update
    num_updates: int = 10  # updates of one run
    target: float = 0.5  # the best action, in every coordinate
    learner: Literal["reinforce", "es"] = "reinforce"  # REINFORCE with a mean baseline, or antithetic ES

    @property
    def env_steps_per_update(self) -> int:
        return self.batch


@struct.dataclass
class BanditHParams:
    lr: float = 0.2  # step size on the mean action
    noise: float = 0.3  # standard deviation of the exploration noise
    gamma: float = 1.0  # discount (one-step episodes: unused)


@dataclasses.dataclass(frozen=True)
class Warmup:
    pulls: int = 4  # uniform random pulls; the best becomes the initial mean


@struct.dataclass
class BanditState:
    mean: jax.Array  # [dim] the policy's mean action
    noise: jax.Array  # [] exploration noise (from the HParams, for acting)
    scratch: jax.Array  # [batch] the last rewards: written by every update, read by none (left out of checkpoints)
    key: jax.Array
    step: jax.Array  # [] int32


@struct.dataclass
class EnvState:
    obs: jax.Array  # [B, 1] a constant observation
    key: jax.Array


class BanditEnv:
    """B one-pull episodes at once, in cdjax.envs.BatchedEnv's interface (reset, step, episode_length)."""

    episode_length = 1

    def __init__(self, config: BanditConfig, num_envs: int):
        self.config, self.num_envs = config, num_envs

    def reset(self, key):
        return EnvState(jnp.zeros((self.num_envs, 1), jnp.float32), key)

    def step(self, state, action):
        reward = reward_of(self.config, action)
        true = jnp.ones((self.num_envs,), bool)
        return state, Step(next_obs=state.obs, reward=reward, terminated=true, truncated=~true, valid=true)


def reward_of(config: BanditConfig, action):
    return 1.0 - jnp.sum((jnp.clip(action, -1, 1) - config.target) ** 2, axis=-1)


def make_trainer(config: BanditConfig) -> Trainer:
    def init(key, hp):
        return BanditState(jnp.zeros((config.dim,), jnp.float32), jnp.asarray(hp.noise, jnp.float32),
                           jnp.zeros((config.batch,), jnp.float32), key, jnp.zeros((), jnp.int32))

    def update(state, hp):
        key, key_noise = jax.random.split(state.key)
        eps = jax.random.normal(key_noise, (config.batch, config.dim))
        if config.learner == "es":
            eps = jnp.concatenate([eps[: config.batch // 2], -eps[: config.batch // 2]])
        reward = reward_of(config, state.mean + hp.noise * eps)
        grad = ((reward - reward.mean())[:, None] * eps).mean(0) / hp.noise
        mean = state.mean + hp.lr * grad
        metrics = {"bandit/return": reward.mean(), "bandit/error": jnp.abs(mean - config.target).max()}
        return state.replace(mean=mean, scratch=reward, key=key, step=state.step + 1), metrics

    def act(policy, obs, key):
        mean = jnp.broadcast_to(policy["mean"], (obs.shape[0], config.dim))
        return mean if key is None else mean + policy["noise"] * jax.random.normal(key, mean.shape)

    def saved_leaves():
        every = jax.tree.map(lambda _: True, jax.eval_shape(init, jax.random.key(0), BanditHParams()))
        return every.replace(scratch=False)

    return Trainer(config=config, init=init, update=update, policy=lambda s: {"mean": s.mean, "noise": s.noise},
                   act=act, eval_env=lambda n: BanditEnv(config, n), saved_leaves=saved_leaves)


def warmup(trainer: Trainer, spec: Warmup):
    def run(state, hp):
        key, key_pulls = jax.random.split(state.key)
        pulls = jax.random.uniform(key_pulls, (spec.pulls, trainer.config.dim), minval=-1.0, maxval=1.0)
        reward = reward_of(trainer.config, pulls)
        info = {"env_steps": jnp.asarray(spec.pulls, jnp.int32), "warmup/best": reward.max()}
        return state.replace(mean=pulls[jnp.argmax(reward)], key=key), info

    return run


def arm_config(name: str, base: BanditConfig) -> BanditConfig:
    if name not in ("reinforce", "es"):
        raise ConfigError(f"Unknown arm {name!r}; choose reinforce or es.")
    return dataclasses.replace(base, learner=name)


BANDIT = Setting(
    name="bandit", about="a continuous bandit (tests only)", config_type=BanditConfig, hparams_type=BanditHParams,
    make_trainer=make_trainer, arm_config=arm_config, arm_fields=("learner",), arms_help="reinforce or es",
    default_arms=("reinforce", "es"), unused_hparams=lambda config, phase: {}, shown_hparams=lambda config: (),
    check_hparam=lambda name, value: None,
    metrics=Metrics(ret="bandit/return", discounted_ret="bandit/return",
                    panels=(("bandit/error", "distance of the mean to the best action", True),)),
    presets={"tiny": Preset(about="2 seeds, 12 updates", config={"dim": 3}, hparams={"noise": (0.3,)},
                            sweep={"seeds": 2, "total_env_steps": 96, "chunk_updates": 4, "eval_episodes": 3})},
    default_preset=lambda given: None,
    phase=Phase(title="warm-up", flag="warmup", spec_type=Warmup, applies=lambda config: config.learner == "es",
                validate=lambda config, spec: None, env_steps=lambda config, spec: spec.pulls, make=warmup,
                describe=lambda info: f"best pull {info['warmup/best']:.2f}."))
agents.register(BANDIT)

SPEC = SweepSpec(out="unset", setting="bandit", config=BanditConfig(), grid={"lr": (0.1, 0.3)}, seeds=2, seed=3,
                 total_env_steps=12 * 8, chunk_updates=4, eval_episodes=3, phase=Warmup(pulls=4), progress=False,
                 bootstrap_reps=50)


@pytest.fixture(scope="module")
def whole(tmp_path_factory):
    out = tmp_path_factory.mktemp("bandit") / "whole"
    run_sweep(dataclasses.replace(SPEC, out=out))
    return out


def test_the_sweep_runs_a_setting_it_does_not_know(whole):
    run = json.loads((whole / "run.json").read_text())
    assert run["setting"] == "bandit" and run["metrics"]["return"] == "bandit/return"
    arms = {a["name"]: a for a in run["arms"]}
    assert arms["reinforce"]["num_updates"] == 12 and arms["reinforce"]["phase_env_steps"] == 0
    assert arms["es"]["phase_env_steps"] == 4 and arms["es"]["num_updates"] == round((96 - 4) / 8) == 12
    assert arms["es"]["config"]["learner"] == "es" and arms["es"]["hp_labels"] == ["lr=0.1", "lr=0.3"]
    rows = logged_rows(whole)
    assert len([r for r in rows if r["update"] > 0]) == 2 * 2 * 2 * 12  # arms x lr x seeds x updates
    assert {r["arm"] for r in rows if r["update"] == 0} == {"es"}  # the phase, as update 0 of its arm
    runs = {(r["arm"], r["hp"], r["seed"]) for r in rows}
    first = {k: np.mean([r["bandit/return"] for r in rows if (r["arm"], r["hp"], r["seed"]) == k and r["update"] == 1])
             for k in runs}
    late = {k: np.mean([r["bandit/return"] for r in rows if (r["arm"], r["hp"], r["seed"]) == k and r["update"] > 8])
            for k in runs}
    assert all(late[k] > first[k] + 0.3 for k in runs), (first, late)  # every run learnt
    evals = io.read_jsonl(whole / "eval.jsonl")
    assert len(evals) == 8 and all(e["update"] == 12 and e["episodes"] == 3 for e in evals)
    # the deterministic evaluation plays the learnt mean: its return is the reward of the final mean
    _, arms_state = restore_arms(whole)
    for arm in arms_state:
        mean = np.asarray(arm.state.mean)[: arm.num_runs]
        for e, m in zip([e for e in evals if e["arm"] == arm.name], mean):
            np.testing.assert_allclose(e["eval/return"], 1 - np.sum((np.clip(m, -1, 1) - 0.5) ** 2), rtol=1e-5)
    assert "reinforce" in (whole / "summary.md").read_text() and (whole / "plots" / "model.png").exists()


def test_interrupted_and_resumed_is_the_same_run(whole, tmp_path):
    out = tmp_path / "cut"
    with pytest.raises(Interrupted):
        run_sweep(dataclasses.replace(SPEC, out=out), after_chunk=lambda chunks, updates: chunks >= 1)
    run_sweep(resume_spec(out, progress=False), resume=True)
    assert logged_rows(out) == logged_rows(whole)
    assert logged_rows(out, "eval.jsonl") == logged_rows(whole, "eval.jsonl")
    cut, straight = restore_arms(out)[1], restore_arms(whole)[1]
    for a, b in zip(cut, straight):
        np.testing.assert_array_equal(np.asarray(a.state.mean), np.asarray(b.state.mean))
        np.testing.assert_array_equal(jax.random.key_data(a.state.key), jax.random.key_data(b.state.key))
        assert not np.asarray(a.state.scratch).any()  # not in the checkpoint: init's value


def test_the_command_line_takes_its_options_from_the_setting(tmp_path, capsys):
    out = tmp_path / "cli"
    main(["sweep", "--setting", "bandit", "--preset", "tiny", "--lr", "0.2", "--target", "0.25", "--arms", "es",
          "--warmup", "--bootstrap-reps", "50", "--no-progress", "--out", str(out)])
    run = json.loads((out / "run.json").read_text())
    assert run["base_config"]["dim"] == 3 and run["base_config"]["target"] == 0.25  # preset, then flag
    assert run["grid"] == {"noise": [0.3], "lr": [0.2]} and run["phase"] == {"pulls": 4} and run["seeds"] == 2
    main(["sweep", "--out", str(out), "--resume", "--steps", "128", "--no-progress"])  # the setting from run.json
    assert max(r["update"] for r in io.read_jsonl(out / "metrics.jsonl")) == round((128 - 4) / 8)
    capsys.readouterr()
    main(["eval", str(out), "--episodes", "2"])
    assert "es / default" in capsys.readouterr().out  # one value of each hyper-parameter: one label
    (out / "summary.md").unlink()
    main(["plot", str(out), "--bootstrap-reps", "50"])
    assert "| es |" in (out / "summary.md").read_text().replace("| 1 | es", "| es |")
    assert (out / "plots" / "return.csv").read_text().count("bandit/return") > 0
