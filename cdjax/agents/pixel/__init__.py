"""The paper's second setting as a `Setting`: a "Learning to Query" state-space model of 64x64x3 frames of expert
trajectories, a policy trained by imitation from the model's state, with (ltq-cd) and without (ltq) the
consistency term between the open and the closed loop.

    cdjax sweep --setting pixel --preset pixel-halfcheetah --expert experts/halfcheetah.msgpack --out runs/px

Arms `ltq` and `ltq-cd` are one code path with a switch (`PixelConfig.arm`); `ltq-cdK` sets the horizon
(e.g. ltq-cd5). Pieces: `config` (PixelConfig, PixelHParams), `model` (the state-space model), `data` (expert
trajectories rendered in jit, the evaluation env), `expert` (the model-free expert's file), `learner` (the
update), `strips` (PNG image strips). The sweep's "env steps" are training frames (batch x sequence length per
update). The host's "return" metric is the held-out open-loop log-likelihood at k (nats per frame) and its
"discounted return" the same at `eval_horizon` steps: both higher is better. Evaluation episodes play the
imitation policy from pixels in the task (eval/return is the task's return).
"""

from __future__ import annotations

import re

from cdjax.agents.pixel.config import HP_RANGES, Config, HParams, PixelConfig, PixelHParams
from cdjax.agents.pixel.learner import PixelLearner, TrainState, make_train, make_trainer, trainer_of
from cdjax.agents.pixel.presets import ARMS, PRESETS, preset_of_env
from cdjax.consistency import collapse_warning
from cdjax.protocol import ConfigError, Metrics, Setting
CONSISTENCY_ONLY = ("alpha", "cc_model", "cc_policy", "enc_aux_coef")


def arm_config(name: str, base: PixelConfig) -> PixelConfig:
    """An arm name -> its Config: "ltq", "ltq-cd", or "ltq-cdK" (ltq-cd with horizon K, e.g. ltq-cd5)."""
    match = re.fullmatch(r"(ltq|ltq-cd)(\d+)?", name)
    if match is None:
        raise ConfigError(f"Unknown arm {name!r}; choose ltq or ltq-cd (ltq-cd optionally with a horizon, e.g. "
                          "ltq-cd5).")
    arm, k = match.groups()
    if k is not None and arm == "ltq":
        raise ConfigError(f"Arm {name!r}: only ltq-cd takes a horizon in its name (e.g. ltq-cd5); ltq's k (of its "
                          "\"at k\" likelihood) is --horizon.")
    try:
        return base.replace(arm=arm, **({"horizon": int(k)} if k else {}))
    except ConfigError as err:
        raise ConfigError(f"Arm {name!r}: {err}") from None


check_hparam = HP_RANGES.check_one


SETTING = Setting(
    make_train=make_train,
    name="pixel", about="pixel state-space models (Learning to Query) with imitation (the paper's second setting)",
    config_type=PixelConfig, hparams_type=PixelHParams, make_trainer=make_trainer, arm_config=arm_config,
    arm_fields=("arm",), arms_help="ltq, ltq-cd, or ltq-cdN for ltq-cd with horizon N", default_arms=ARMS,
    unused_hparams=lambda config, phase: {} if config.use_consistency else {n: None for n in CONSISTENCY_ONLY},
    shown_hparams=lambda config: ("alpha",) if config.use_consistency else (),
    check_hparam=check_hparam,
    metrics=Metrics(ret="heldout/loglik_k", discounted_ret="heldout/loglik_50", skipped="train/skipped_steps",
                    ret_field="horizon", panels=(
        ("heldout/imitation", "held-out imitation loss", True),
        ("loss/imitation", "imitation loss", True),
        ("model/elbo_per_frame", "ELBO per frame (nats)", False),
        ("loss/consistency", "consistency loss", True),
        ("encoder/spread_real", "encoder spread (real)", False))),
    presets=PRESETS, default_preset=preset_of_env, watch=collapse_warning)

__all__ = ["ARMS", "Config", "HParams", "PRESETS", "SETTING", "PixelConfig", "PixelHParams", "PixelLearner", "TrainState",
           "arm_config", "make_train", "make_trainer", "trainer_of"]
