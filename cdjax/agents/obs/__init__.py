"""The observation-space setting (the paper's first): PPO + a Gaussian dynamics model + the consistency loss
on MuJoCo-MJX, with the Mb-Mf phase of Nagabandi et al. before PPO.

    from cdjax.agents.obs import Config, HParams, make_train       # also importable from cdjax itself

The package: `config` (Config, HParams), `learner` (ObsAgent: rollout, losses and the one jitted update;
`make_agent`, `make_train`, `make_trainer`), `state` (TrainState), `networks`, `losses`, `rollout`, `optim` (Adam per
parameter group),
`mbmf/` (the Mb-Mf phase: spec, data, the phase program), `mpc` (random-shooting MPC), `presets`.
This module adapts them to the protocol the host side runs (`SETTING`). Arms are `model-free`, `mbmf` and
`cd`, optionally with a horizon: `cd-k5` is the cd arm with k = 5 (the paper's k ablation runs `cd-k5` and
`cd-k20` side by side).
"""

from __future__ import annotations

import functools
import math
import re
from typing import Mapping

from cdjax.agents.obs.learner import ObsAgent, TrainState, make_agent, make_train, make_trainer
from cdjax.agents.obs.config import HP_RANGES, Config, HParams, stack_hparams
from cdjax.agents.obs.mbmf import MbMfPhase, make_mbmf_phase, total_env_steps, validate_phase
from cdjax.agents.obs.presets import PRESETS
from cdjax.consistency import collapse_warning
from cdjax.protocol import ConfigError, Metrics, Phase, Setting

ARMS = ("model-free", "mbmf", "cd")
RETURN = "episode/return"
DISC_RETURN = "episode/discounted_return"
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


check_hparam = HP_RANGES.check_one


def _describe_phase(info: Mapping[str, float]) -> str:
    return (f"reward per step: random actions {info.get('random/reward_mean', math.nan):.3g}, MPC "
            f"{info.get('mpc/reward_mean_last', math.nan):.3g}, distilled policy "
            f"{info.get('dagger/reward_mean_last', math.nan):.3g}; the policy's distance to the mean MPC label "
            f"{info.get('distill/abs_error_mean', math.nan):.3g} (zero action: "
            f"{info.get('distill/abs_error_zero', math.nan):.3g}, one label: {info.get('labels/self_error', math.nan):.3g})"
            + (f"; PPO starts (reward per step, sampled): distilled {info['handover/sampled_reward_mean']:.3g}, untrained "
               f"{info['fresh/sampled_reward_mean']:.3g}" if "handover/sampled_reward_mean" in info else "") + ".")


def preset_of_env(given: Mapping) -> str | None:
    """Without --preset, the preset named like the env (e.g. `cdjax sweep --env ant` gets the ant settings)."""
    env = given.get("env", Config.env)
    return env if env in PRESETS else None


MBMF_PHASE = Phase(
    title="Mb-Mf phase", flag="mbmf-phase", spec_type=MbMfPhase, applies=lambda config: config.use_model,
    validate=validate_phase, env_steps=total_env_steps,
    make=lambda trainer, spec: make_mbmf_phase(trainer.config, spec, trainer.inner), describe=_describe_phase,
    as_metrics={"dagger/episode_return": RETURN})

SETTING = Setting(
    make_train=make_train,
    name="obs", about="observation-space models with PPO on MuJoCo-MJX (the paper's first setting)",
    config_type=Config, hparams_type=HParams, make_trainer=make_trainer, arm_config=arm_config, arm_fields=("arm",),
    arms_help="model-free, mbmf, cd, or cd-kN for cd with horizon N", default_arms=("mbmf", "cd"),
    unused_hparams=unused_hparams, shown_hparams=lambda config: ("alpha",) if config.arm == "cd" else (),
    check_hparam=check_hparam,
    metrics=Metrics(ret=RETURN, discounted_ret=DISC_RETURN, skipped="train/skipped_steps", panels=(
        ("model/openloop_mse_k", "open-loop MSE at k steps", True),
        ("model/openloop_mse_50", "open-loop MSE at eval_horizon (50 unless set)", True),
        ("loss/consistency", "consistency loss", True),
        ("encoder/spread_real", "encoder spread (real)", False),
        ("encoder/spread_imagined", "encoder spread (imagined)", False))),
    presets=PRESETS, default_preset=preset_of_env, phase=MBMF_PHASE, watch=collapse_warning)

__all__ = ["Config", "HParams", "MbMfPhase", "ObsAgent", "PRESETS", "SETTING", "TrainState", "make_agent",
           "make_mbmf_phase", "make_train", "make_trainer", "stack_hparams", "total_env_steps"]
