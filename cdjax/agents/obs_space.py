"""The observation-space setting (PPO + Gaussian dynamics model + consistency loss) as a `Setting`.

This module adapts `cdjax.train.make_trainer` (and the Mb-Mf phase of `cdjax.mbmf`) to the protocol the
host side runs; the learner itself is untouched. Arms are `model-free`, `mbmf` and `cd`, optionally with a
horizon: `cd-k5` is the cd arm with k = 5 (the paper's k ablation runs `cd-k5` and `cd-k20` side by side).
"""

from __future__ import annotations

import functools
import math
import re
import warnings
from typing import Mapping

import jax
import numpy as np

from cdjax import envs, presets
from cdjax.config import Config, ConfigError, HParams
from cdjax.envs.resume import needed_leaves
from cdjax.mbmf import MbMfPhase, make_mbmf_phase, total_env_steps, validate_phase
from cdjax.protocol import Metrics, Phase, Setting, Trainer
from cdjax.train import make_trainer as make_agent

ARMS = ("model-free", "mbmf", "cd")
RETURN = "episode/return"
DISC_RETURN = "episode/discounted_return"
SPREAD = "encoder/spread_real"
# Below this output spread (std of the encodings across windows, averaged over features) a trainable GRU maps
# every window to nearly one point: l_cc then vanishes without the model becoming consistent. A fresh GRU
# spreads ~0.1-1; the collapsed ant runs of experiments/paper_obs_space ended at 5e-5 to 3e-4.
COLLAPSE_SPREAD = 1e-3
TRAINED_ENCODERS = ("gru", "grounded-gru")
# Hyper-parameters an arm does not use, and the value they take there (None: the default). lr_distill is
# the Mb-Mf phase's, unused without it.
CONSISTENCY_ONLY = ("alpha", "cc_model", "cc_policy", "enc_aux_coef")
UNUSED = {"model-free": CONSISTENCY_ONLY + ("lr_model", "model_coef", "lr_distill"),
          "mbmf": CONSISTENCY_ONLY + ("lr_distill",), "cd": ("lr_distill",)}
UNUSED_WITH_PHASE = {"model-free": UNUSED["model-free"], "mbmf": CONSISTENCY_ONLY, "cd": ()}
FIXED = {"alpha": 0.0}


def parse_arm(name: str) -> tuple[str, dict]:
    """An arm name -> (arm, Config overrides): "cd" -> ("cd", {}), "cd-k5" -> ("cd", {"horizon": 5})."""
    match = re.fullmatch(r"(model-free|mbmf|cd)(?:-k(\d+))?", name)
    if match is None:
        raise ConfigError(f"Unknown arm {name!r}; choose from: {', '.join(ARMS)} (optionally with a horizon, "
                          "e.g. cd-k5).")
    arm, k = match.groups()
    if k is not None and arm == "model-free":
        raise ConfigError(f"Arm {name!r}: the model-free arm has no horizon.")
    if k is not None and int(k) <= 0:
        raise ConfigError(f"Arm {name!r}: the horizon must be a positive integer.")
    return arm, ({"horizon": int(k)} if k is not None else {})


def arm_config(name: str, base: Config) -> Config:
    arm, overrides = parse_arm(name)
    try:
        return base.replace(arm=arm, **overrides)  # validated there (e.g. --cc-windows against the windows)
    except ConfigError as err:
        raise ConfigError(f"Arm {name!r}: {err}") from None


def unused_hparams(config: Config, with_phase: bool) -> dict[str, float | None]:
    return {name: FIXED.get(name) for name in (UNUSED_WITH_PHASE if with_phase else UNUSED)[config.arm]}


def check_hparam(name: str, value: float) -> None:
    flag = "--" + name.replace("_", "-")
    if not math.isfinite(value):
        raise ConfigError(f"{flag} must be finite, got {value}.")
    if name in ("gamma", "gae_lambda") and not 0.0 <= value <= 1.0:
        raise ConfigError(f"{flag} must be between 0 and 1, got {value}.")
    if name != "init_log_std" and value < 0:
        raise ConfigError(f"{flag} must not be negative, got {value}.")


def collapse_warning(arm_name: str, config: Config, metrics: Mapping) -> str | None:
    """A sentence when the trained encoder of some runs has collapsed, else None: when a run's median spread over
    the second half of the chunk is below COLLAPSE_SPREAD.

    metrics: {name: [R, n]} on the host (one chunk). One update's spread is a noisy sample: it is measured on the
    windows of one rollout, and when they look alike (e.g. many Atari games restarting on the same screen) it dips
    by orders of magnitude for that update alone (ALE Breakout: 2e-4 between values of 0.5-0.9). A collapse
    stays, so the median over the chunk's later updates tells the two apart. Only the trained encoders (gru,
    grounded-gru) are checked: `frozen-gru` does not train and `l2` has no encoder.
    """
    if config.encoder not in TRAINED_ENCODERS or SPREAD not in metrics:
        return None
    spread = np.asarray(metrics[SPREAD], float)
    later = spread[:, spread.shape[1] // 2:]
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # a run with no finite value: NaN, not low
        typical = np.nanmedian(later, axis=1)
    low = np.isfinite(typical) & (typical < COLLAPSE_SPREAD)
    if not low.any():
        return None
    return (f"Arm {arm_name}: the {config.encoder} encoder's output spread stayed below {COLLAPSE_SPREAD:g} over the "
            f"last {later.shape[1]} updates in {int(low.sum())} of {typical.size} runs (median {np.median(typical[low]):.1e}); "
            "the encoder may have collapsed, which makes l_cc vanish without making the model consistent. The "
            "frozen-gru and l2 encoders (--encoder) cannot collapse.")


@functools.lru_cache(maxsize=None)
def _needed_env_leaves(env_name: str, num_envs: int, episode_length: int, action_repeat: int, reset_mode: str):
    """The env-state leaves a resume needs; every leaf (a bigger checkpoint, never a wrong one) when the
    analysis of the traced step fails on a JAX release whose primitives it does not know."""
    env = envs.BatchedEnv(envs.make_single_env(env_name), num_envs, episode_length, action_repeat, reset_mode)
    try:
        return needed_leaves(env)
    except Exception as err:  # noqa: BLE001 - an optimisation of the checkpoint's size must not end a run
        warnings.warn(f"checkpoints keep the whole {env_name} state: the analysis of which leaves a resume needs "
                      f"failed ({type(err).__name__}: {err})", stacklevel=2)
        return jax.tree.map(lambda _: True, jax.eval_shape(env.reset, jax.random.key(0)))


def make_trainer(config: Config) -> Trainer:
    agent = make_agent(config)

    @functools.cache
    def saved_leaves():
        """Every leaf of the TrainState but the environment's derived physics data (cdjax.envs.resume) and its
        reset targets."""
        shapes = jax.eval_shape(agent.init, jax.random.key(0), HParams())
        every = jax.tree.map(lambda _: True, shapes)
        env = _needed_env_leaves(config.env, config.num_envs, config.episode_length, config.action_repeat,
                                 config.reset_mode)
        # Each env's reset target (`first`) is set by init and never changes (the Mb-Mf phase acts in its own
        # environments): a restore fills it from the fresh init of the same keys, so it is not stored.
        env = env.replace(first=jax.tree.map(lambda _: False, env.first))
        return every.replace(env_state=env)

    def eval_env(num_envs: int) -> envs.BatchedEnv:
        return envs.BatchedEnv(agent.env.env, num_envs, config.episode_length, config.action_repeat,
                               config.reset_mode)

    return Trainer(
        config=config, init=agent.init, update=agent.update,
        policy=lambda state: {"params": {"policy": state.params["policy"]}, "norms": state.norms},
        act=lambda policy, obs, key: agent.act(policy["params"], policy["norms"], obs, key),
        eval_env=eval_env, saved_leaves=saved_leaves, inner=agent)


def _describe_phase(info: Mapping[str, float]) -> str:
    return (f"episode return: random actions {info.get('random/episode_return', math.nan):.1f}, MPC "
            f"{info.get('mpc/episode_return', math.nan):.1f}, distilled policy "
            f"{info.get('dagger/episode_return', math.nan):.1f}.")


def preset_of_env(given: Mapping) -> str | None:
    """Without --preset, the preset named like the env (e.g. `cdjax sweep --env ant` gets the ant settings)."""
    env = given.get("env", Config.env)
    return env if env in presets.PRESETS else None


MBMF_PHASE = Phase(
    title="Mb-Mf phase", flag="mbmf-phase", spec_type=MbMfPhase, applies=lambda config: config.use_model,
    validate=validate_phase, env_steps=total_env_steps,
    make=lambda trainer, spec: make_mbmf_phase(trainer.config, spec, trainer.inner), describe=_describe_phase,
    as_metrics={"dagger/episode_return": RETURN})

SETTING = Setting(
    name="obs", about="observation-space models with PPO on MuJoCo-MJX (the paper's first setting)",
    config_type=Config, hparams_type=HParams, make_trainer=make_trainer, arm_config=arm_config, arm_fields=("arm",),
    arms_help="model-free, mbmf, cd, or cd-kN for cd with horizon N", default_arms=("mbmf", "cd"),
    unused_hparams=unused_hparams, shown_hparams=lambda config: ("alpha",) if config.arm == "cd" else (),
    check_hparam=check_hparam,
    metrics=Metrics(ret=RETURN, discounted_ret=DISC_RETURN, panels=(
        ("model/openloop_mse_k", "open-loop MSE at k steps", True),
        ("model/openloop_mse_50", "open-loop MSE at 50 steps", True),
        ("loss/consistency", "consistency loss", True),
        ("encoder/spread_real", "encoder spread (real)", False),
        ("encoder/spread_imagined", "encoder spread (imagined)", False))),
    presets=presets.PRESETS, default_preset=preset_of_env, phase=MBMF_PHASE, watch=collapse_warning)
