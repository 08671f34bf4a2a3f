"""Running mean/variance statistics (Welford, merged batch-wise with Chan's formula).

They are data, not parameters: updated from rollouts outside the loss and never differentiated.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import struct

STD_FLOOR = 1e-3  # smallest standard deviation used when normalising (constant features stay finite)
CLIP = 10.0  # normalised values are clipped to [-CLIP, CLIP]


@struct.dataclass
class RunningStats:
    count: jax.Array  # [] float32 number of samples seen
    mean: jax.Array  # [D]
    m2: jax.Array  # [D] sum of squared deviations from the mean

    @classmethod
    def create(cls, dim: int) -> "RunningStats":
        return cls(jnp.zeros((), jnp.float32), jnp.zeros((dim,), jnp.float32), jnp.zeros((dim,), jnp.float32))

    @property
    def std(self) -> jax.Array:
        var = jnp.where(self.count > 1, self.m2 / jnp.maximum(self.count, 1.0), 1.0)
        return jnp.maximum(jnp.sqrt(var), STD_FLOOR)


def update(stats: RunningStats, x: jax.Array, mask: jax.Array | None = None) -> RunningStats:
    """Merge a batch x [..., D] (rows where mask is False are ignored) into the statistics."""
    x = jax.lax.stop_gradient(x.reshape(-1, x.shape[-1]).astype(jnp.float32))
    w = jnp.ones((x.shape[0],), jnp.float32) if mask is None else mask.reshape(-1).astype(jnp.float32)
    x = jnp.where(w[:, None] > 0, x, 0.0)  # masked rows may hold garbage (never NaN into the sums)
    n_b = w.sum()
    mean_b = (w[:, None] * x).sum(0) / jnp.maximum(n_b, 1.0)
    m2_b = (w[:, None] * (x - mean_b) ** 2).sum(0)
    n = stats.count + n_b
    delta = mean_b - stats.mean
    safe_n = jnp.maximum(n, 1.0)
    mean = stats.mean + delta * n_b / safe_n
    m2 = stats.m2 + m2_b + delta**2 * stats.count * n_b / safe_n
    return RunningStats(n, mean, m2)


def normalize(stats: RunningStats, x: jax.Array) -> jax.Array:
    stats = jax.lax.stop_gradient(stats)
    return jnp.clip((x - stats.mean) / stats.std, -CLIP, CLIP)


def denormalize(stats: RunningStats, z: jax.Array) -> jax.Array:
    stats = jax.lax.stop_gradient(stats)
    return z * stats.std + stats.mean


@struct.dataclass
class Norms:
    """All running statistics of one agent."""

    obs: RunningStats  # observations (policy, value, model inputs, encoder inputs)
    delta: RunningStats  # observation change s' - s (model target)
    reward: RunningStats  # reward (model target)

    @classmethod
    def create(cls, obs_dim: int) -> "Norms":
        return cls(RunningStats.create(obs_dim), RunningStats.create(obs_dim), RunningStats.create(1))
