"""The observation-space agent's static configuration (what fixes shapes and loop lengths) and traced
hyper-parameters.

`Config` is a frozen dataclass: it is hashed into the compiled program, so changing any field
recompiles. `HParams` is a pytree of float32 scalars: it is an argument of the compiled program, so
it can be vmapped alongside the seeds (alpha grids, learning-rate grids) without recompiling.
"""

from __future__ import annotations

import dataclasses
from typing import Literal

import jax
import jax.numpy as jnp
from flax import struct

from cdjax.checks import INT32_MAX, POSITIVE, UNIT, Choice, Count, Fields, HParamRanges, Range, Real
from cdjax.consistency import KINDS, windows_per_sequence
from cdjax.protocol import ConfigError

Arm = Literal["model-free", "mbmf", "cd"]
Encoder = Literal["grounded-gru", "gru", "frozen-gru", "l2"]
ResetMode = Literal["cached", "fresh"]
PhysicsBackend = Literal["auto", "jax", "warp"]  # cdjax.envs.playground.BACKENDS
PolicyStd = Literal["state", "global"]
Entropy = Literal["squashed", "gaussian"]
Init = Literal["orthogonal", "lecun"]
ClipScope = Literal["group", "policy-value"]
ENCODERS = KINDS  # the consistency term's encoders (cdjax.consistency)


@dataclasses.dataclass(frozen=True)
class Config:
    """Everything that fixes a shape, a loop length or the graph of the compiled update."""

    env: str = "ant"  # task name (see cdjax.envs.available_envs())
    arm: Arm = "cd"  # model-free: no model; mbmf: model trained, no consistency term; cd: consistency term built
    num_envs: int = 2048  # environments stepped in parallel per seed
    rollout_len: int = 32  # T: closed-loop steps per environment per update
    horizon: int = 20  # k: open-loop length of the consistency windows
    num_updates: int = 100  # updates run by train(key, hp)
    num_epochs: int = 4  # PPO epochs over each rollout
    num_minibatches: int = 32  # minibatches per epoch, drawn from shuffled (env, segment) sequences
    segment_len: int = 0  # minibatch sequence length: the rollout is cut into T/segment_len segments; 0 = T
    gae_in_loss: bool = True  # recompute GAE in every minibatch with the current value net (as Brax), else once
    episode_length: int = 1000  # time-out in physics steps (agent steps x action_repeat, as Brax); a truncation
    action_repeat: int = 1  # physics control steps per agent step
    reset_mode: ResetMode = "cached"  # cached: each env resets to its own first start (as Brax); fresh: new random start
    stagger_resets: bool = False  # each env starts at a random point of its time limit (that first episode is not logged)
    physics_backend: PhysicsBackend = "auto"  # Playground (dmc-*) tasks: MJX's jax, MuJoCo warp, or auto (warp where it runs)
    activation: str = "swish"  # activation of the policy and value MLPs (a flax.linen name: swish, tanh, ...)
    policy_std: PolicyStd = "state"  # policy std: state (softplus head, as Brax) or global (one log-std per dim)
    entropy: Entropy = "squashed"  # entropy bonus: of the tanh-squashed action (one-sample) or of the Gaussian
    weight_init: Init = "lecun"  # policy/value weights: lecun-uniform (Brax) or orthogonal (gain sqrt 2, small policy head)
    policy_head_scale: float = 0.1  # lecun: the policy's last layer's initial weights (mean and std heads) x this; 1 = Brax's
    clip_scope: ClipScope = "group"  # gradient clipping: per parameter group, or policy and value together (Brax)
    policy_hidden: tuple[int, ...] = (64, 64)  # policy MLP widths
    value_hidden: tuple[int, ...] = (256, 256)  # value MLP widths
    model_hidden: tuple[int, ...] = (500,)  # dynamics model MLP widths (relu; Mb-Mf uses one layer of 500)
    encoder: Encoder = "grounded-gru"  # consistency encoder: grounded-gru (GRU + reconstruction + spread floor), gru (paper), frozen-gru, l2
    encoder_dim: int = 128  # GRU hidden size
    cc_windows: int = 0  # consistency windows per env per minibatch, random start offsets; 0 = all T-k+1
    cc_unroll: int = 1  # lax.scan unroll factor of the scanned k-step term (the obs agent's fused chain is unrolled)
    cc_epochs: int = 0  # PPO epochs (the first ones) whose minibatches include the consistency term; 0 = all
    eval_horizon: int = 50  # longer open-loop horizon for the compounding-error metric (paper: 50)
    eval_envs: int = 8  # environments whose recent history is kept for the open-loop error metrics
    yardstick: str = ""  # held-out real trajectories (.npz) the model is also scored on each update (yardstick.py); "": none

    def __post_init__(self):
        validate(self)

    # The arm switches: every setting has them, each with its own arm names.
    @property
    def use_model(self) -> bool:
        return self.arm != "model-free"

    @property
    def use_consistency(self) -> bool:
        return self.arm == "cd"

    @property
    def segment(self) -> int:
        """L: the length of the sequences minibatches are made of."""
        return self.segment_len or self.rollout_len

    @property
    def num_segments(self) -> int:
        """Sequences per update: num_envs x (T / L)."""
        return self.num_envs * (self.rollout_len // self.segment)

    @property
    def minibatch_seqs(self) -> int:
        """Sequences of L steps per minibatch."""
        return self.num_segments // self.num_minibatches

    @property
    def num_windows(self) -> int:
        """Consistency windows per sequence per minibatch."""
        return windows_per_sequence(self.segment, self.horizon, self.cc_windows)

    @property
    def env_steps_per_update(self) -> int:
        return self.num_envs * self.rollout_len * self.action_repeat

    @property
    def history_len(self) -> int:
        """Observations kept per eval env for open-loop error: enough for both horizons."""
        return max(self.eval_horizon, self.horizon) + 1

    def replace(self, **changes) -> "Config":
        return dataclasses.replace(self, **changes)


def validate(config: Config) -> None:
    """Raise ConfigError (one sentence) for a configuration that cannot run; never compiles anything."""
    from cdjax import envs  # local import: envs imports brax, config must stay light

    FIELDS.check(config)  # every field's type and range (cdjax.checks); what follows relates fields
    if config.env not in envs.available_envs():
        raise ConfigError(
            f"Unknown env {config.env!r}; choose one of: {', '.join(sorted(envs.available_envs()))}."
        )
    if envs.playground.is_playground(config.env):
        envs.playground.check(config.physics_backend)  # the extra installed, the backend one that runs here
    if not _is_activation(getattr(_linen(), config.activation, None)):
        raise ConfigError(f"Unknown activation {config.activation!r}; use a flax.linen activation such as swish, "
                          "tanh or relu.")
    if config.weight_init == "orthogonal" and config.policy_head_scale != Config.policy_head_scale:
        raise ConfigError(f"policy_head_scale scales lecun-uniform's policy head; orthogonal weights have their own (gain "
                          f"0.01), so leave it at {Config.policy_head_scale} with weight_init='orthogonal', got "
                          f"{config.policy_head_scale!r}.")
    if config.action_repeat > config.episode_length:
        raise ConfigError(f"action_repeat={config.action_repeat} is more than episode_length={config.episode_length} "
                          "physics steps, so every episode would end at its first agent step.")
    episode = -(-config.episode_length // config.action_repeat)  # agent steps of an episode that times out
    if config.use_model and config.eval_horizon > episode:
        raise ConfigError(f"eval_horizon={config.eval_horizon} is longer than an episode ({episode} agent steps), so "
                          "the model's open-loop error at it would never be measured; make it at most that.")
    if config.cc_epochs > config.num_epochs:
        raise ConfigError(f"cc_epochs must be between 0 (all epochs) and num_epochs={config.num_epochs}, got {config.cc_epochs!r}.")
    if config.rollout_len % config.segment != 0:
        raise ConfigError(f"segment_len={config.segment_len} does not divide rollout_len={config.rollout_len}.")
    if config.horizon > config.segment:
        raise ConfigError(
            f"horizon (k={config.horizon}) is longer than the minibatch sequences (segment_len={config.segment}); "
            "each sequence must hold at least one k-step window."
        )
    if config.cc_windows > config.segment - config.horizon + 1:
        raise ConfigError(
            f"cc_windows={config.cc_windows} is more than the {config.segment - config.horizon + 1} k-step windows a "
            f"sequence of {config.segment} steps holds (k={config.horizon}); use 0 for all of them."
        )
    if config.num_segments % config.num_minibatches != 0:
        raise ConfigError(
            f"num_minibatches={config.num_minibatches} does not divide the {config.num_segments} sequences of an "
            f"update (num_envs={config.num_envs} x rollout_len/segment_len={config.rollout_len // config.segment})."
        )
    if config.eval_envs > config.num_envs:
        raise ConfigError(f"eval_envs={config.eval_envs} is larger than num_envs={config.num_envs}.")


# The kind and range of every Config field (cdjax.checks; the Literal, tuple and bool fields take theirs from
# their annotations), checked when a Config is built.
FIELDS = Fields(
    Config, encoder=Choice(ENCODERS), num_envs=Count(1), rollout_len=Count(1), horizon=Count(1), num_updates=Count(1),
    num_epochs=Count(1), num_minibatches=Count(1), segment_len=Count(1, zero="the whole rollout"),
    episode_length=Count(1, INT32_MAX), action_repeat=Count(1), encoder_dim=Count(1), cc_windows=Count(1, zero="all windows"),
    cc_unroll=Count(1), cc_epochs=Count(1, zero="all epochs"), eval_horizon=Count(1), eval_envs=Count(1),
    policy_head_scale=Real(POSITIVE))


def _linen():
    import flax.linen as nn

    return nn


def _is_activation(fn) -> bool:
    """Whether fn maps a float array to a float array of its shape (flax.linen's relu, swish, ...), not a module
    class such as Dense nor a function that wants more arguments (one_hot): checked on shapes alone, nothing runs."""
    if not callable(fn) or isinstance(fn, type):
        return False
    x = jax.ShapeDtypeStruct((2, 3), jnp.float32)
    try:
        y = jax.eval_shape(fn, x)
    except Exception:  # noqa: BLE001 - whatever fn raises on one float array, it is not an activation
        return False
    return getattr(y, "shape", None) == x.shape and jnp.issubdtype(y.dtype, jnp.floating)


@struct.dataclass
class HParams:
    """Float hyper-parameters: traced, so any of them can be vmapped alongside the seeds."""

    alpha: float = 1.0  # weight of the consistency loss (0 = Mb-Mf baseline)
    cc_model: float = 1.0  # multiplier of alpha on the consistency gradient reaching the model and the encoder
    cc_policy: float = 0.1  # multiplier of alpha on the consistency gradient reaching the policy (via the actions)
    enc_aux_coef: float = 1.0  # weight of the grounded-gru encoder's auxiliary loss: reconstruction + spread floor (encoder only)
    lr_policy: float = 3e-4  # Adam learning rate of the policy
    lr_value: float = 3e-4  # Adam learning rate of the value function
    lr_model: float = 1e-3  # Adam learning rate of the dynamics model and the encoder (Mb-Mf: 1e-3)
    lr_distill: float = 1e-3  # Adam learning rate of the Mb-Mf phase's behaviour cloning (Nagabandi: 1e-3)
    max_grad_norm: float = 1.0  # global-norm clipping, applied per parameter group
    adam_eps: float = 1e-8  # Adam's epsilon (every parameter group)
    gamma: float = 0.99  # discount
    gae_lambda: float = 0.95  # GAE lambda
    clip_eps: float = 0.2  # PPO ratio clipping
    vf_coef: float = 0.5  # value loss weight
    ent_coef: float = 0.0  # entropy bonus weight
    model_coef: float = 1.0  # dynamics model NLL weight
    reward_scale: float = 1.0  # reward multiplier seen by PPO (returns are logged unscaled)
    init_log_std: float = -0.5  # initial log standard deviation of the policy (pre-squash)

    def as_float32(self) -> "HParams":
        return HParams(**{f.name: jnp.asarray(getattr(self, f.name), jnp.float32) for f in dataclasses.fields(self)})


# The initial log standard deviation's range: exp() of it must stay finite in float32 (it overflows above about 88.7,
# and the std head's bias is softplus's inverse of it), so +-20 (a std from 2e-9 to 5e8) bounds it well inside.
LOG_STD = Range(-20.0, 20.0)

# The range of every HParams field (the rest: not negative), checked on the command line's grid and by `init`.
HP_RANGES = HParamRanges(HParams, gamma=UNIT, gae_lambda=UNIT, init_log_std=LOG_STD, max_grad_norm=POSITIVE,
                         adam_eps=POSITIVE, clip_eps=POSITIVE, reward_scale=POSITIVE)


def stack_hparams(hps: list[HParams]) -> HParams:
    """Stack HParams into one with leaves [len(hps)], to vmap over (e.g. an alpha grid)."""
    if not hps:
        raise ConfigError("stack_hparams was given no HParams; pass at least one.")
    return HParams(**{f.name: jnp.asarray([getattr(h, f.name) for h in hps], jnp.float32)
                      for f in dataclasses.fields(HParams)})
