"""The Atari setting's presets: the MinAtar games at a GPU budget, the ALE games at A2C's published setting, and
`cpu-minatar` for a 2-core CPU."""

from __future__ import annotations

from cdjax.agents.atari.config import ALE_PREFIX, AtariConfig
from cdjax.agents.atari.minatar import GAMES
from cdjax.protocol import Preset

# RMSprop rates of the MinAtar presets, checked per game with the a2c arm (5 seeds, 5M env steps, evaluation IQM
# over 100 sampled-action episodes; experiments/atari/RESULTS.md): Space Invaders learnt best and most evenly across
# seeds at 1e-2 (at 2e-2 a 10-seed run split its seeds).
RATES = {"space_invaders": 1e-2}


def _minatar(game: str, steps: int = 10_000_000, lr: float = 2e-2) -> Preset:
    """A MinAtar game at a GPU budget: 10 seeds vmapped, a2c vs a2c-cd (alpha 1), 100 evaluation episodes.

    RMSprop at 2e-2 rather than A2C's Atari 7e-4: each update here averages 1024 transitions (A2C's Atari batch is
    80). Of the rates swept on Breakout, Seaquest, Asterix and Freeway (a2c, 5 seeds; experiments/atari/RESULTS.md)
    2e-2 was at or near the best; Space Invaders is the exception (`RATES`: 1e-2)."""
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
    with --steps (`python -m experiments.atari run ale-GAME`)."""
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
