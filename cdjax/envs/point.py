"""A tiny deterministic point mass in pure JAX, with the Brax `Env` interface.

It compiles in a second on a CPU, so the plumbing tests (losses, masking, vmap, compile-once) use it
instead of an MJX task. Dynamics (dt = 0.1, action in [-1, 1]^2):

    v' = 0.9 v + 0.1 a,   x' = x + 0.1 v',   obs = (x, v),
    reward = 1 - |x'|^2 - 0.01 |a|^2,   terminated when |x'|_inf > 2.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
from flax import struct


@struct.dataclass
class State:
    """The fields of Brax's `envs.base.State`, which Brax's training wrappers read and replace, without importing
    Brax (and MJX) for a task that needs neither."""

    pipeline_state: Any
    obs: jax.Array
    reward: jax.Array
    done: jax.Array
    metrics: dict = dataclasses.field(default_factory=dict)
    info: dict = dataclasses.field(default_factory=dict)


class PointMass:
    observation_size = 4
    action_size = 2
    backend = "jax"

    def __init__(self, start_range: float = 1.0):
        self.start_range = start_range

    @staticmethod
    def dynamics(obs: jax.Array, action: jax.Array) -> jax.Array:
        """The exact next observation: obs [..., 4], action [..., 2] -> [..., 4]."""
        x, v = obs[..., :2], obs[..., 2:]
        v = 0.9 * v + 0.1 * jnp.clip(action, -1.0, 1.0)
        x = x + 0.1 * v
        return jnp.concatenate([x, v], axis=-1)

    def reset(self, rng: jax.Array) -> State:
        x = jax.random.uniform(rng, (2,), minval=-self.start_range, maxval=self.start_range)
        obs = jnp.concatenate([x, jnp.zeros((2,))]).astype(jnp.float32)
        zero = jnp.zeros((), jnp.float32)
        return State(pipeline_state=None, obs=obs, reward=zero, done=zero)

    def step(self, state: State, action: jax.Array) -> State:
        obs = self.dynamics(state.obs, action)
        x = obs[:2]
        reward = 1.0 - jnp.sum(x**2) - 0.01 * jnp.sum(jnp.clip(action, -1.0, 1.0) ** 2)
        done = (jnp.max(jnp.abs(x)) > 2.0).astype(jnp.float32)
        return state.replace(obs=obs, reward=reward.astype(jnp.float32), done=done)
