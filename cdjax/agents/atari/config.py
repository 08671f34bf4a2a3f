"""Static Config and traced HParams of the Atari setting (A2C, optionally a latent dynamics model and the
consistency term).

Arms are switches of one code path: `a2c` (no model), `a2c-model` (the latent model is trained beside the
agent, consistency weight 0) and `a2c-cd` (the model, and alpha x the consistency term).
"""

from __future__ import annotations

import dataclasses
from typing import Literal

from flax import struct

from cdjax.checks import INT32_MAX, POSITIVE, PROBABILITY_BELOW_1, UNIT, Choice, Count, Fields, HParamRanges, Real, Text
from cdjax.consistency import KINDS, windows_per_sequence
from cdjax.protocol import ConfigError

from cdjax.agents.atari import ale
from cdjax.agents.atari.minatar import GAMES

ARMS = ("a2c", "a2c-model", "a2c-cd")
ALE_PREFIX = "ale-"  # env names of the real games: ale-breakout, ale-seaquest, ale-mspacman, ale-frostbite, ...
ALE_INSTALL = ale.INSTALL


def ale_available() -> bool:
    try:
        import ale_py  # noqa: F401
    except ImportError:
        return False
    return True


@dataclasses.dataclass(frozen=True)
class AtariConfig:
    """What fixes shapes or the graph; every field is a command-line option of `cdjax sweep --setting atari`."""

    env: str = "breakout"  # MinAtar game (breakout, seaquest, asterix, freeway, space_invaders) or ALE game (ale-breakout, ...)
    arm: Literal["a2c", "a2c-model", "a2c-cd"] = "a2c-cd"  # set by the arm name
    num_envs: int = 64  # parallel environments per run
    rollout_len: int = 16  # steps per environment per update: n of the n-step returns, and the windows' sequence
    horizon: int = 5  # k: open-loop steps of a consistency window
    cc_windows: int = 0  # consistency windows per environment per update (0: all rollout_len - horizon + 1)
    cc_unroll: int = 1  # unroll of the k-step imagination scan
    episode_length: int = 1000  # time-out of an episode in agent steps (a truncation: the value is bootstrapped)
    sticky_prob: float = 0.1  # probability that an environment repeats its previous action (MinAtar and ALE v5: 0.1 / 0.25)
    frame_skip: int = 4  # ALE only: emulator frames per agent step (the last two max-pooled)
    clip_rewards: bool = True  # learn from sign(reward) (the returns reported are always the raw scores)
    conv_channels: int = 16  # MinAtar torso: channels of its one 3x3 convolution (ALE: the Nature CNN's 32-64-64)
    latent: int = 128  # torso output size: the latent space of the dynamics model (Nature CNN: 512)
    model_hidden: int = 256  # width of the latent dynamics model's two hidden layers
    encoder: Literal["grounded-gru", "gru", "frozen-gru", "l2"] = "grounded-gru"  # consistency encoder (cdjax.consistency)
    encoder_dim: int = 64  # GRU encoder width
    num_updates: int = 1000  # updates of one run (the sweep sets it from --steps)

    def __post_init__(self):
        FIELDS.check(self)  # every field's type and range (cdjax.checks); what follows relates fields
        if self.is_ale:
            if self.env not in ale.GAMES:  # a name no extra would make known: said before the extra is asked for
                raise ConfigError(f"Unknown ALE game {self.env!r}; choose one of {', '.join(ale.GAMES)}.")
            if not ale_available():
                raise ConfigError(f"env={self.env!r}: {ALE_INSTALL}")
        elif self.env not in GAMES:
            raise ConfigError(f"Unknown env {self.env!r}; choose a MinAtar game ({', '.join(GAMES)}) or "
                              "ale-<game> (e.g. ale-breakout).")
        elif self.frame_skip != AtariConfig.frame_skip:
            raise ConfigError(f"frame_skip={self.frame_skip} is the ALE's (emulator frames per agent step); a MinAtar "
                              f"game such as {self.env!r} steps once per action, so leave it at "
                              f"{AtariConfig.frame_skip}.")
        if self.horizon > self.rollout_len:
            raise ConfigError(f"horizon={self.horizon} must not exceed rollout_len={self.rollout_len}: a "
                              "consistency window lies inside one rollout.")
        if self.cc_windows > self.rollout_len - self.horizon + 1:
            raise ConfigError(f"cc_windows={self.cc_windows} is more than the {self.rollout_len - self.horizon + 1} "
                              f"k-step windows a rollout of {self.rollout_len} steps holds (k={self.horizon}); use 0 "
                              "for all of them.")

    def replace(self, **changes) -> "AtariConfig":
        return dataclasses.replace(self, **changes)

    @property
    def is_ale(self) -> bool:
        return self.env.startswith(ALE_PREFIX)

    # The arm switches: every setting has them, each with its own arm names.
    @property
    def use_model(self) -> bool:
        return self.arm != "a2c"

    @property
    def use_consistency(self) -> bool:
        return self.arm == "a2c-cd"

    @property
    def num_windows(self) -> int:
        """Windows per environment per update."""
        return windows_per_sequence(self.rollout_len, self.horizon, self.cc_windows)

    @property
    def env_steps_per_update(self) -> int:
        return self.num_envs * self.rollout_len


# The kind and range of every Config field (cdjax.checks; the Literal and bool fields take theirs from their
# annotations), checked when a Config is built.
FIELDS = Fields(
    AtariConfig, env=Text(), num_envs=Count(1), rollout_len=Count(1), horizon=Count(1),
    cc_windows=Count(1, zero="all windows"), cc_unroll=Count(1), episode_length=Count(1, INT32_MAX),
    sticky_prob=Real(PROBABILITY_BELOW_1), frame_skip=Count(1), conv_channels=Count(1), latent=Count(1),
    model_hidden=Count(1), encoder=Choice(KINDS), encoder_dim=Count(1), num_updates=Count(1))


@struct.dataclass
class AtariHParams:
    """Floats that can be vmapped with the seeds (float32 scalars in a sweep)."""

    lr: float = 7e-4  # RMSprop learning rate of the agent (torso, actor, critic), as A2C (Mnih et al. 2016; baselines)
    rms_decay: float = 0.99  # RMSprop decay of the squared-gradient average
    rms_eps: float = 1e-5  # RMSprop epsilon (inside the square root, as baselines' TensorFlow RMSProp)
    gamma: float = 0.99  # discount of the n-step returns
    ent_coef: float = 0.01  # weight of the entropy bonus
    value_coef: float = 0.5  # weight of the value loss (mean squared error of V against the n-step return)
    max_grad_norm: float = 0.5  # global-norm clip of each parameter group's gradient
    lr_model: float = 1e-3  # Adam learning rate of the latent dynamics model and the encoder
    model_coef: float = 1.0  # weight of the model's one-step loss (latent and reward squared errors)
    alpha: float = 1.0  # weight of the consistency loss (0: the a2c-model baseline)
    cc_model: float = 1.0  # multiplier of alpha on the consistency gradient reaching the model and the encoder
    cc_policy: float = 0.1  # multiplier of alpha on the consistency gradient reaching the policy (via the actions)
    enc_aux_coef: float = 1.0  # weight of the grounded-gru encoder's auxiliary loss (encoder only)


# The range of every HParams field (the rest: not negative), checked on the command line's grid and by `init`.
HP_RANGES = HParamRanges(AtariHParams, rms_decay=UNIT, rms_eps=POSITIVE, gamma=UNIT, max_grad_norm=POSITIVE)


Config, HParams = AtariConfig, AtariHParams  # the face every setting shares: cdjax.agents.<setting>.Config, HParams
