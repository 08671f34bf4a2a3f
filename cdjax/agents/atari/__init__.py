"""The Atari setting (the paper's section 5.3): A2C against A2C + consistency, as a `cdjax.protocol.Setting`.

    cdjax sweep --setting atari --preset cpu-minatar --out runs/minatar       # a 2-core CPU, 1.5 minutes
    cdjax sweep --setting atari --preset minatar-breakout --out runs/breakout # a GPU, 10 seeds vmapped
    cdjax sweep --setting atari --preset breakout --out runs/ale-breakout     # the real game (extra `atari`)

Arms (one code path, cdjax.agents.atari.learner): `a2c` (no model), `a2c-model` (the latent dynamics model
trained beside the agent, alpha = 0) and `a2c-cd` (the model and alpha x the consistency term). Environments,
two tiers behind one interface: the MinAtar games through gymnax (fully in JAX, vmapped with the seeds), and
the ALE games through ale-py's XLA interface (cdjax.agents.atari.ale: inside jit; a sweep's runs are folded into one
ale-py vector environment of runs x envs emulators).
"""

from __future__ import annotations

from cdjax.agents.atari.config import ARMS, HP_RANGES, AtariConfig, AtariHParams, Config, HParams
from cdjax.agents.atari.learner import A2C, TrainState, make_env, make_train, make_trainer
from cdjax.agents.atari.minatar import MinAtarEnv
from cdjax.agents.atari.presets import PRESETS, default_preset
from cdjax.consistency import collapse_warning
from cdjax.protocol import ConfigError, Metrics, Setting

RETURN = "episode/return"
DISC_RETURN = "episode/discounted_return"
MODEL_HPS = ("lr_model", "model_coef")
CONSISTENCY_HPS = ("alpha", "cc_model", "cc_policy", "enc_aux_coef")
# Hyper-parameters an arm does not use, and the value they take there (None: the default).
UNUSED = {"a2c": {name: None for name in MODEL_HPS + CONSISTENCY_HPS} | {"alpha": 0.0},
          "a2c-model": {name: None for name in CONSISTENCY_HPS} | {"alpha": 0.0},
          "a2c-cd": {}}


def arm_config(name: str, base: AtariConfig) -> AtariConfig:
    if name not in ARMS:
        raise ConfigError(f"Unknown arm {name!r}; choose from: {', '.join(ARMS)}.")
    return base.replace(arm=name)


check_hparam = HP_RANGES.check_one


SETTING = Setting(
    make_train=make_train,
    name="atari", about="A2C with and without consistency on MinAtar and ALE games (the paper's third setting)",
    config_type=AtariConfig, hparams_type=AtariHParams, make_trainer=make_trainer, arm_config=arm_config,
    arm_fields=("arm",), arms_help="a2c, a2c-model (alpha = 0) or a2c-cd", default_arms=("a2c", "a2c-cd"),
    unused_hparams=lambda config, with_phase: UNUSED[config.arm],
    shown_hparams=lambda config: ("alpha",) if config.arm == "a2c-cd" else (), check_hparam=check_hparam,
    metrics=Metrics(ret=RETURN, discounted_ret=DISC_RETURN, skipped="train/skipped_step", panels=(
        ("policy/entropy", "policy entropy", False),
        ("model/latent_mse", "latent model one-step MSE", True),
        ("loss/consistency", "consistency loss", True),
        ("encoder/spread_real", "encoder spread (real)", False))),
    presets=PRESETS, default_preset=default_preset, watch=collapse_warning,
    eval_sampled=True)  # a greedy policy under sticky actions can stall (e.g. never FIRE); A2C reports sampling

__all__ = ["A2C", "AtariConfig", "AtariHParams", "Config", "HParams", "MinAtarEnv", "PRESETS", "SETTING", "TrainState",
           "make_env", "make_train", "make_trainer"]
