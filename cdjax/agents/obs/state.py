"""The observation-space setting's state: the TrainState of one run, its diagnostics history and the SGD's batch."""

from __future__ import annotations

import warnings
from typing import Any, Callable

import jax
import jax.numpy as jnp
from flax import struct

from cdjax import envs
from cdjax import normalize as nz
from cdjax.agents.obs.rollout import Transition
from cdjax.envs import EnvState, EpisodeStats
from cdjax.envs.resume import needed_leaves


@struct.dataclass
class History:
    """The last H transitions of the first `eval_envs` environments (for open-loop error at k and 50)."""

    obs: jax.Array  # [H, E, O]
    next_obs: jax.Array  # [H, E, O]
    action: jax.Array  # [H, E, A]
    ended: jax.Array  # [H, E] bool
    valid: jax.Array  # [H, E] bool
    filled: jax.Array  # [] int32 how many of the H slots hold real data

    @classmethod
    def create(cls, length: int, envs: int, obs_size: int, action_size: int) -> "History":
        z = lambda *s: jnp.zeros(s, jnp.float32)  # noqa: E731
        return cls(z(length, envs, obs_size), z(length, envs, obs_size), z(length, envs, action_size),
                   jnp.zeros((length, envs), bool), jnp.zeros((length, envs), bool), jnp.zeros((), jnp.int32))

    def push(self, traj: Transition) -> "History":
        H, E = self.ended.shape
        cat = lambda old, new: jnp.concatenate([old, new[:, :E]], axis=0)[-H:]  # noqa: E731
        return History(cat(self.obs, traj.obs), cat(self.next_obs, traj.next_obs), cat(self.action, traj.action),
                       cat(self.ended, traj.ended), cat(self.valid, traj.valid),
                       jnp.minimum(self.filled + traj.obs.shape[0], H).astype(jnp.int32))


@struct.dataclass
class TrainState:
    params: dict  # {"policy", "value"[, "model"][, "encoder"]} flax variable dicts
    opt_state: Any  # optax state
    norms: nz.Norms  # running statistics of observations, deltas and rewards
    env_state: EnvState  # batched environment state
    episodes: EpisodeStats  # running returns per environment
    history: History  # recent transitions of a few environments (model diagnostics)
    last_return: jax.Array  # [] mean return of the latest finished episodes (NaN before any)
    last_disc_return: jax.Array  # [] same, discounted
    key: jax.Array  # PRNG key
    update_step: jax.Array  # [] int32 updates done


@struct.dataclass
class Batch:
    """What the SGD phase needs of a rollout; leaves [T, B, ...] (minibatches: [L, Bs, ...])."""

    obs: jax.Array
    next_obs: jax.Array
    action: jax.Array
    raw_action: jax.Array
    noise: jax.Array
    log_prob: jax.Array
    reward: jax.Array
    terminated: jax.Array
    ended: jax.Array
    valid: jax.Array
    next_value: jax.Array  # V(next_obs) at acting time: the bootstrap of time-outs inside a sequence
    advantages: jax.Array | None  # GAE over the whole rollout at acting time (None when gae_in_loss)
    returns: jax.Array | None


def refresh_norms(norms: nz.Norms, obs, next_obs, reward, valid) -> nz.Norms:
    """Merge a batch of transitions (leaves [..., D], valid [...]) into the running statistics."""
    return nz.Norms(obs=nz.update(norms.obs, obs, valid), delta=nz.update(norms.delta, next_obs - obs, valid),
                    reward=nz.update(norms.reward, reward[..., None], valid))


def to_segments(x: jax.Array, segment: int) -> jax.Array:
    """[T, B, ...] -> [L, (T / L) * B, ...]: the rollout cut into sequences of L steps (column s * B + b)."""
    T, B = x.shape[:2]
    S = T // segment
    return jnp.swapaxes(x.reshape((S, segment, B) + x.shape[2:]), 0, 1).reshape((segment, S * B) + x.shape[2:])


def _needed_env_leaves(env_name: str, num_envs: int, episode_length: int, action_repeat: int, reset_mode: str,
                       physics_backend: str = "auto"):
    """The env-state leaves a resume needs; every leaf (a bigger checkpoint, never a wrong one) when the
    analysis of the traced step fails on a JAX release whose primitives it does not know."""
    env = envs.batched(env_name, num_envs, episode_length, action_repeat, reset_mode,
                       physics_backend=physics_backend)
    try:
        return needed_leaves(env)
    except Exception as err:  # noqa: BLE001 - an optimisation of the checkpoint's size must not end a run
        warnings.warn(f"checkpoints keep the whole {env_name} state: the analysis of which leaves a resume needs "
                      f"failed ({type(err).__name__}: {err})", stacklevel=2)
        return jax.tree.map(lambda _: True, jax.eval_shape(env.reset, jax.random.key(0)))


def saved_leaves(config, init: Callable, hparams) -> TrainState:
    """Every leaf of the TrainState `init(key, hparams)` builds but the environment's derived physics data
    (cdjax.envs.resume) and its reset targets: True where a checkpoint keeps the leaf."""
    every = jax.tree.map(lambda _: True, jax.eval_shape(init, jax.random.key(0), hparams))
    env = _needed_env_leaves(config.env, config.num_envs, config.episode_length, config.action_repeat,
                             config.reset_mode, config.physics_backend)
    # Each env's reset target (`first`) is set by init and never changes (the Mb-Mf phase acts in its own
    # environments): a restore fills it from the fresh init of the same keys, so it is not stored.
    env = env.replace(first=jax.tree.map(lambda _: False, env.first))
    return every.replace(env_state=env)
