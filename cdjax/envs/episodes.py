"""Running episode returns of a batch of environments, the same for every setting."""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import struct


@struct.dataclass
class EpisodeStats:
    """Per-env running returns and the totals of episodes finished during a rollout."""

    ret: jax.Array  # [B] undiscounted return so far
    disc_ret: jax.Array  # [B] discounted return so far
    disc: jax.Array  # [B] gamma^t
    done_count: jax.Array  # [] episodes finished in this rollout
    done_ret: jax.Array  # [] sum of their returns
    done_disc_ret: jax.Array  # [] sum of their discounted returns
    skip: jax.Array  # [B] bool: the env's current episode is not counted when it ends (a staggered, shortened first one)

    @classmethod
    def create(cls, batch: int, skip: jax.Array | None = None) -> "EpisodeStats":
        """Fresh statistics; `skip` [B] bool marks envs whose current episode must not be counted (e.g.
        `env_state.t > 0` after a staggered reset: that episode was started part-way into its time limit)."""
        z = jnp.zeros((batch,), jnp.float32)
        s = jnp.zeros((), jnp.float32)
        skip = jnp.zeros((batch,), bool) if skip is None else jnp.asarray(skip, bool)
        assert skip.shape == (batch,), skip.shape
        return cls(z, z, jnp.ones((batch,), jnp.float32), s, s, s, skip)

    def start_rollout(self) -> "EpisodeStats":
        s = jnp.zeros((), jnp.float32)
        return self.replace(done_count=s, done_ret=s, done_disc_ret=s)

    def mean_returns(self, previous: jax.Array | float = jnp.nan) -> tuple[jax.Array, jax.Array]:
        """(mean return, mean discounted return) of the episodes finished in this rollout; `previous` when none."""
        n = jnp.maximum(self.done_count, 1.0)
        finished = self.done_count > 0
        return (jnp.where(finished, self.done_ret / n, previous),
                jnp.where(finished, self.done_disc_ret / n, previous))

    def record(self, reward, ended, counted, gamma) -> "EpisodeStats":
        """Add one step; `counted` marks episode ends whose return is reported (not NaN resets, not the
        episodes marked `skip`, whose mark an end clears)."""
        ret = self.ret + reward
        disc_ret = self.disc_ret + self.disc * reward
        counted = (counted & ~self.skip).astype(jnp.float32)
        return EpisodeStats(
            ret=jnp.where(ended, 0.0, ret),
            disc_ret=jnp.where(ended, 0.0, disc_ret),
            disc=jnp.where(ended, 1.0, self.disc * gamma),
            done_count=self.done_count + counted.sum(),
            done_ret=self.done_ret + (counted * ret).sum(),
            done_disc_ret=self.done_disc_ret + (counted * disc_ret).sum(),
            skip=self.skip & ~ended,
        )
