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

import functools

import jax

from cdjax.agents.atari.config import ALE_PREFIX, ARMS, HP_RANGES, AtariConfig, AtariHParams
from cdjax.agents.atari.learner import A2C, learner, make_env
from cdjax.agents.atari.minatar import GAMES, MinAtarEnv
from cdjax.consistency import collapse_warning
from cdjax.protocol import ConfigError, Metrics, Preset, Setting, Trainer

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


def make_trainer(config: AtariConfig) -> Trainer:
    agent = learner(config)

    @functools.cache
    def eval_env(num_envs: int):
        """The evaluation env of `num_envs` episodes, one per size: an ALE env's emulators are made once, not at every
        evaluation."""
        return make_env(config, num_envs, training=False)

    def saved_leaves():
        """MinAtar: every leaf. ALE: not the environments (the emulators live outside JAX; a resumed run starts
        fresh games from init's) nor the running returns of the episodes in flight."""
        every = jax.tree.map(lambda _: True, jax.eval_shape(agent.init, jax.random.key(0), AtariHParams()))
        if not config.is_ale:
            return every
        stats = every.stats.replace(ret=False, disc_ret=False, disc=False)
        return every.replace(env_state=jax.tree.map(lambda _: False, every.env_state), stats=stats)

    return Trainer(config=config, init=agent.init, update=agent.update, policy=lambda state: state.params["agent"],
                   act=agent.act, eval_env=eval_env,
                   saved_leaves=saved_leaves, inner=agent)


# RMSprop rates of the MinAtar presets, checked per game with the a2c arm on an H200 (5 seeds, 5M env steps, evaluation
# IQM over 100 sampled-action episodes; experiments/atari/RESULTS.md). Space Invaders at 1e-2: AUC 50.0 / 68.0 / 56.5 /
# 49.0 and evaluation 82.6 / 100.2 / 82.8 / 59.0 at 5e-3 / 1e-2 / 2e-2 / 4e-2, and at 2e-2 the 10-seed, 10M-step run
# split its seeds (final training return [15, 102]) where 1e-2 gave 108.5 [94.6, 117.0].
RATES = {"space_invaders": 1e-2}


def _minatar(game: str, steps: int = 10_000_000, lr: float = 2e-2) -> Preset:
    """A MinAtar game at a GPU budget: 10 seeds vmapped, a2c vs a2c-cd (alpha 1), 100 evaluation episodes.

    RMSprop at 2e-2 rather than A2C's Atari 7e-4: each update here averages 1024 transitions (A2C's Atari batch is
    80). Measured on an H200 (a2c, 5 seeds, 5M env steps, evaluation IQM over 100 sampled-action episodes;
    experiments/atari/RESULTS.md): Breakout 5.0 / 5.4 / 10.8 / 16.9 / 17.1 and Seaquest 0.73 / 0.76 / 1.97 / 5.4 /
    13.9 at 7e-4 / 2e-3 / 5e-3 / 1e-2 / 2e-2 (2e-3, the earlier default, came from one CPU seed at 400k steps);
    Asterix 12.3 / 19.8 / 19.9 / 14.2 and Freeway 20.3 / 22.6 / 23.0 / 23.3 at 5e-3 / 1e-2 / 2e-2 / 4e-2 (2e-2 at or
    near the best); Space Invaders is the exception (`RATES`: 1e-2)."""
    return Preset(
        about=f"MinAtar {game}: a2c vs a2c-cd, 10 seeds, {steps / 1e6:g}M env steps, 64 envs x 16 steps, RMSprop {lr:g}",
        config=dict(env=game, num_envs=64, rollout_len=16, horizon=5),
        hparams=dict(alpha=(1.0,), lr=(lr,)),
        sweep=dict(arms=("a2c", "a2c-cd"), seeds=10, total_env_steps=steps, eval_episodes=100))


PRESETS = {f"minatar-{game}": _minatar(game, lr=RATES.get(game, 2e-2)) for game in GAMES}
# Measured on a shared 2-core CPU with an empty compilation cache: 80 s end to end (compile 33 s, training 28 s,
# evaluation 6 s); Breakout's training return rose from ~0.4 (random play) to ~2.5-2.7 in both arms.
PRESETS["cpu-minatar"] = Preset(
    about="2-core CPU, 1.5 minutes: MinAtar breakout, a2c vs a2c-cd, 2 seeds, small nets",
    config=dict(env="breakout", num_envs=16, rollout_len=8, horizon=4, conv_channels=8, latent=64, model_hidden=64,
                encoder_dim=16, episode_length=500),
    hparams=dict(lr=(3e-3,)),
    sweep=dict(arms=("a2c", "a2c-cd"), seeds=2, total_env_steps=400 * 16 * 8, chunk_updates=100, eval_episodes=10))


def _ale(game: str, steps: int = 10_000_000) -> Preset:
    """A real game (ale-py, the optional extra `atari`) at A2C's published setting (Mnih et al. 2016; OpenAI baselines:
    16 envs x 5 steps, RMSprop 7e-4, 10M agent steps = 40M frames), sticky actions 0.25 (Machado et al. 2018),
    k = 4 (two windows per env per update); 3 seeds per arm, their 48 emulators one ale-py vector environment
    (cdjax.agents.atari.ale). Chunks of 250 updates (60k agent steps of the 3 runs), so that a time limit stops a run
    close to it. At this budget a game is hours of a 16-core host (experiments/atari/RESULTS.md): the GPU units run it
    with --steps (experiments/atari/device.sh)."""
    return Preset(
        about=f"ALE {game} (needs pip install -e \".[atari]\"): a2c vs a2c-cd, 3 seeds, {steps / 1e6:g}M agent steps",
        config=dict(env=f"ale-{game}", num_envs=16, rollout_len=5, horizon=4, latent=512, sticky_prob=0.25,
                    episode_length=27_000),
        hparams=dict(alpha=(1.0,)),
        sweep=dict(arms=("a2c", "a2c-cd"), seeds=3, total_env_steps=steps, chunk_updates=250, eval_episodes=100))


PRESETS.update({game: _ale(game) for game in ("breakout", "seaquest", "mspacman", "frostbite")})


def default_preset(given) -> str | None:
    """Without --preset, the preset of the game given (`--env seaquest` gets minatar-seaquest, `--env ale-seaquest`
    gets seaquest)."""
    env = given.get("env", AtariConfig.env)
    name = env[len(ALE_PREFIX):] if env.startswith(ALE_PREFIX) else f"minatar-{env}"
    return name if name in PRESETS else None


SETTING = Setting(
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

__all__ = ["A2C", "AtariConfig", "AtariHParams", "MinAtarEnv", "SETTING", "make_env", "make_trainer"]
