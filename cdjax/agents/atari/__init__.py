"""The Atari setting (the paper's section 5.3): A2C against A2C + consistency, as a `cdjax.protocol.Setting`.

    cdjax sweep --setting atari --preset cpu-minatar --out runs/minatar       # a 2-core CPU, about a minute
    cdjax sweep --setting atari --preset minatar-breakout --out runs/breakout # a GPU

Arms (one code path, cdjax.agents.atari.learner): `a2c` (no model), `a2c-model` (the latent dynamics model
trained beside the agent, alpha = 0) and `a2c-cd` (the model and alpha x the consistency term). Environments:
the MinAtar games through gymnax (fully in JAX, vmapped with the seeds).
"""

from __future__ import annotations

import math

from cdjax.agents.atari.config import ARMS, AtariConfig, AtariHParams
from cdjax.agents.atari.learner import A2C, learner, make_env
from cdjax.agents.atari.minatar import GAMES, MinAtarEnv
from cdjax.agents.obs_space import collapse_warning
from cdjax.presets import Preset
from cdjax.protocol import ConfigError, Metrics, Setting, Trainer

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


def check_hparam(name: str, value: float) -> None:
    flag = "--" + name.replace("_", "-")
    if not math.isfinite(value):
        raise ConfigError(f"{flag} must be finite, got {value}.")
    if name in ("gamma", "rms_decay") and not 0.0 <= value <= 1.0:
        raise ConfigError(f"{flag} must be between 0 and 1, got {value}.")
    if value < 0:
        raise ConfigError(f"{flag} must not be negative, got {value}.")


def make_trainer(config: AtariConfig) -> Trainer:
    agent = learner(config)
    return Trainer(config=config, init=agent.init, update=agent.update, policy=lambda state: state.params["agent"],
                   act=agent.act, eval_env=lambda num_envs: make_env(config, num_envs, training=False), inner=agent)


def _minatar(game: str, steps: int = 10_000_000) -> Preset:
    """A MinAtar game at a GPU budget: 10 seeds vmapped, a2c vs a2c-cd (alpha 1), 100 evaluation episodes."""
    return Preset(
        about=f"MinAtar {game}: a2c vs a2c-cd, 10 seeds, {steps / 1e6:g}M env steps, 64 envs x 16 steps",
        config=dict(env=game, num_envs=64, rollout_len=16, horizon=5),
        hparams=dict(alpha=(1.0,)),
        sweep=dict(arms=("a2c", "a2c-cd"), seeds=10, total_env_steps=steps, eval_episodes=100))


PRESETS = {f"minatar-{game}": _minatar(game) for game in GAMES}
# A 2-core CPU in about a minute: Breakout's return rises from ~0.5 (random) to several points.
PRESETS["cpu-minatar"] = Preset(
    about="2-core CPU, about a minute: MinAtar breakout, a2c vs a2c-cd, 2 seeds, small nets",
    config=dict(env="breakout", num_envs=16, rollout_len=8, horizon=4, conv_channels=8, latent=64, model_hidden=64,
                encoder_dim=16, episode_length=500),
    hparams=dict(lr=(3e-3,)),
    sweep=dict(arms=("a2c", "a2c-cd"), seeds=2, total_env_steps=400 * 16 * 8, chunk_updates=100, eval_episodes=10))


def default_preset(given) -> str | None:
    """Without --preset, the preset of the game given (`--env seaquest` gets minatar-seaquest)."""
    name = f"minatar-{given.get('env', AtariConfig.env)}"
    return name if name in PRESETS else None


SETTING = Setting(
    name="atari", about="A2C with and without consistency on MinAtar games (the paper's third setting)",
    config_type=AtariConfig, hparams_type=AtariHParams, make_trainer=make_trainer, arm_config=arm_config,
    arm_fields=("arm",), arms_help="a2c, a2c-model (alpha = 0) or a2c-cd", default_arms=("a2c", "a2c-cd"),
    unused_hparams=lambda config, with_phase: UNUSED[config.arm],
    shown_hparams=lambda config: ("alpha",) if config.arm == "a2c-cd" else (), check_hparam=check_hparam,
    metrics=Metrics(ret=RETURN, discounted_ret=DISC_RETURN, panels=(
        ("policy/entropy", "policy entropy", False),
        ("model/latent_mse", "latent model one-step MSE", True),
        ("loss/consistency", "consistency loss", True),
        ("encoder/spread_real", "encoder spread (real)", False))),
    presets=PRESETS, default_preset=default_preset, watch=collapse_warning)

__all__ = ["A2C", "AtariConfig", "AtariHParams", "MinAtarEnv", "SETTING", "make_env", "make_trainer"]
