"""The off-policy setting's static configuration (shapes, buffer sizes, loop lengths) and traced hyper-parameters.

`Config` is hashed into the compiled update: changing a field recompiles. `HParams` are float32 scalars, arguments
of the compiled program, vmapped with the seeds (learning rates, tau, gamma, the consistency weights).
"""

from __future__ import annotations

import dataclasses
from typing import Literal

import jax.numpy as jnp
from flax import struct

from cdjax.checks import INT32_MAX, POSITIVE, UNIT, Choice, Count, Fields, HParamRanges
from cdjax.consistency import KINDS
from cdjax.protocol import ConfigError

Arm = Literal["model-free", "model", "paper-cd", "self-pred"]
ARMS = ("model-free", "model", "paper-cd", "self-pred")
ResetMode = Literal["cached", "fresh"]
PhysicsBackend = Literal["auto", "jax", "warp"]  # cdjax.envs.playground.BACKENDS
Inputs = Literal["latent", "obs", "obs+latent"]


@dataclasses.dataclass(frozen=True)
class Config:
    """Everything that fixes a shape, a loop length or the graph of the compiled update."""

    env: str = "point"  # task name (cdjax.envs.available_envs())
    arm: Arm = "model-free"  # which auxiliary losses train the latent model (the package docstring)
    num_envs: int = 16  # environments stepped in parallel per seed, all feeding one replay buffer
    steps_per_update: int = 1  # batched env steps collected by one update
    updates_per_step: int = 1  # gradient steps per batched env step: the update-to-data ratio (Brax's grad_updates_per_step)
    num_updates: int = 100  # updates run by train(key, hp)
    buffer_steps: int = 4096  # batched env steps the replay buffer holds (x num_envs transitions)
    batch_size: int = 256  # sequences per gradient step
    learning_starts: int = 1024  # env steps (all envs) of uniform random actions before any gradient step
    n_step: int = 3  # n of the n-step returns of the critic's target
    horizon: int = 3  # k: steps of the self-predictive latent rollout and of the paper's consistency windows
    num_critics: int = 2  # Q ensemble; the target takes the minimum over it (clipped double Q at 2)
    actor_hidden: tuple[int, ...] = (256, 256)
    critic_hidden: tuple[int, ...] = (256, 256)
    layer_norm: bool = True  # LayerNorm after every hidden layer of the critics (and of the model's MLPs)
    inputs: Inputs = "obs+latent"  # what the actor and critic read: obs and latent, latent, or obs (model-free only)
    latent_dim: int = 64  # size of the encoder's latent
    encoder_hidden: tuple[int, ...] = (256,)
    model_hidden: tuple[int, ...] = (256,)  # the latent transition, reward head and observation decoder
    cc_encoder: str = "grounded-gru"  # paper-cd: the consistency encoder (cdjax.consistency.KINDS)
    cc_dim: int = 64  # paper-cd: GRU hidden size
    episode_length: int = 1000  # time-out in physics steps: a truncation (bootstrapped)
    action_repeat: int = 1
    reset_mode: ResetMode = "cached"
    physics_backend: PhysicsBackend = "auto"  # Playground (dmc-*) tasks: MJX's jax, MuJoCo warp, or auto (warp where it runs)
    # Diagnostics (off: nothing computed): each update also reports, on one batch sampled beside its gradient steps,
    # every loss term's gradient norm per parameter group it reaches ("grad/<term>/<group>"), the spread of the
    # online and target latents ("latent/*"), and the model's open-loop error at each of the horizon's steps on the
    # newest window of heldout_envs environments that the same policy steps beside the training ones and whose
    # transitions are never replayed ("heldout/open_loop_mse_<j>"). It changes no training number.
    diagnostics: bool = False
    heldout_envs: int = 8

    def __post_init__(self):
        validate(self)

    @property
    def use_model(self) -> bool:
        return self.arm != "model-free"

    @property
    def use_encoder(self) -> bool:
        return self.inputs != "obs"

    @property
    def use_consistency(self) -> bool:
        return self.arm in ("paper-cd", "self-pred")

    @property
    def seq_len(self) -> int:
        """Length of the buffered sequences a gradient step samples: the n-step return's and the k-step terms'."""
        return max(self.n_step, self.horizon if self.use_consistency else 1)

    @property
    def grad_steps(self) -> int:
        return self.steps_per_update * self.updates_per_step

    @property
    def env_steps_per_update(self) -> int:
        return self.num_envs * self.steps_per_update * self.action_repeat

    @property
    def random_steps(self) -> int:
        """Batched env steps taken with uniform random actions (learning_starts over the envs, rounded up)."""
        return -(-self.learning_starts // self.num_envs)

    def replace(self, **changes) -> "Config":
        return dataclasses.replace(self, **changes)


def validate(config: Config) -> None:
    """ConfigError (one sentence) for a configuration that cannot run; compiles nothing."""
    from cdjax import envs  # local import: envs imports brax, the config stays light

    FIELDS.check(config)
    if config.env not in envs.available_envs():
        raise ConfigError(f"Unknown env {config.env!r}; choose one of: {', '.join(sorted(envs.available_envs()))}.")
    if envs.playground.is_playground(config.env):
        envs.playground.check(config.physics_backend)  # the extra installed, the backend one that runs here
    if config.use_model and not config.use_encoder:
        raise ConfigError(f"The {config.arm} arm trains an encoder's latent for the actor and critic to read; it "
                          "needs inputs latent or obs+latent.")
    if config.random_steps < config.seq_len:
        raise ConfigError(f"learning_starts={config.learning_starts} env steps fill fewer than the {config.seq_len} "
                          f"batched steps one sampled sequence needs (num_envs={config.num_envs}); raise it.")
    if config.buffer_steps < config.random_steps or config.buffer_steps < config.steps_per_update + config.seq_len:
        raise ConfigError(f"buffer_steps={config.buffer_steps} cannot hold the random-action steps "
                          f"({config.random_steps}) and one update's steps plus a sequence; raise it.")


FIELDS = Fields(
    Config, cc_encoder=Choice(KINDS), num_envs=Count(1), steps_per_update=Count(1), updates_per_step=Count(1),
    num_updates=Count(1), buffer_steps=Count(2, INT32_MAX), batch_size=Count(1), learning_starts=Count(1),
    n_step=Count(1), horizon=Count(1), num_critics=Count(2), latent_dim=Count(1), cc_dim=Count(1),
    episode_length=Count(1, INT32_MAX), action_repeat=Count(1), heldout_envs=Count(1))


@struct.dataclass
class HParams:
    """Float hyper-parameters: traced, so any of them can be vmapped with the seeds."""

    lr_actor: float = 3e-4
    lr_critic: float = 3e-4  # the critics and the encoder
    lr_alpha: float = 3e-4  # the entropy temperature's log
    lr_model: float = 3e-4  # latent transition, reward head, decoder, consistency encoder
    gamma: float = 0.99
    tau: float = 0.005  # Polyak step of the target critics and the target encoder
    reward_scale: float = 1.0  # reward multiplier seen by the critic (returns are logged unscaled)
    init_alpha: float = 1.0  # initial entropy temperature
    target_entropy_scale: float = 0.5  # the entropy target is -scale x action size (Brax SAC: 0.5)
    model_coef: float = 1.0  # weight of the model's one-step loss (decoded next observation + reward)
    alpha: float = 1.0  # weight of the consistency term (paper-cd, self-pred); 0: the model arm's gradients
    cc_model: float = 1.0  # paper-cd: multiplier of alpha on the gradient into the model and its encoder
    cc_policy: float = 0.1  # paper-cd: multiplier of alpha on the gradient into the actor (straight-through actions)
    enc_aux_coef: float = 1.0  # paper-cd, grounded-gru: weight of the GRU encoder's reconstruction and spread floor
    rho: float = 0.5  # self-pred: weight rho^j of the j-th predicted latent (TD-MPC2's temporal decay)
    max_grad_norm: float = 10.0  # global-norm clipping per parameter group

    def as_float32(self) -> "HParams":
        return HParams(**{f.name: jnp.asarray(getattr(self, f.name), jnp.float32) for f in dataclasses.fields(self)})


HP_RANGES = HParamRanges(HParams, gamma=UNIT, tau=UNIT, rho=UNIT, init_alpha=POSITIVE, reward_scale=POSITIVE,
                         max_grad_norm=POSITIVE)
