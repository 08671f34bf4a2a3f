"""Fixed-size datasets inside jitted programs: a ring buffer, and epochs of shuffled minibatches over it.

Used by the Mb-Mf phase (model and distillation data); any setting that fits a network to a growing,
statically shaped dataset (imitation from expert trajectories, say) can use the same two pieces.
"""

from __future__ import annotations

from typing import Any, Callable

import jax
import jax.numpy as jnp
import optax
from flax import struct


@struct.dataclass
class RingBuffer:
    """A fixed-size dataset (static shapes): `data` leaves [N, ...], the oldest items overwritten first.

    Slots never written hold zeros with valid=False (every item type here has a `valid` field).
    """

    data: Any  # pytree with leaves [N, ...]
    count: jax.Array  # [] int32 items ever added

    @classmethod
    def create(cls, example: Any, size: int) -> "RingBuffer":
        """`example`: one item (leaves without the leading axis) giving shapes and dtypes."""
        data = jax.tree.map(lambda x: jnp.zeros((size,) + jnp.shape(x), jnp.asarray(x).dtype), example)
        return cls(data, jnp.zeros((), jnp.int32))

    @property
    def size(self) -> int:
        return jax.tree.leaves(self.data)[0].shape[0]

    @property
    def filled(self) -> jax.Array:
        return jnp.minimum(self.count, self.size)

    def add(self, items: Any) -> "RingBuffer":
        n = jax.tree.leaves(items)[0].shape[0]
        assert n <= self.size, (n, self.size)
        idx = (self.count + jnp.arange(n)) % self.size
        data = jax.tree.map(lambda d, x: d.at[idx].set(x.astype(d.dtype)), self.data, items)
        return RingBuffer(data, self.count + n)


def fit(loss_fn: Callable, params, opt_state, tx: optax.GradientTransformation, buffer: RingBuffer,
        epochs: int, minibatch: int, key: jax.Array):
    """`epochs` shuffled passes of minibatches over the filled part of `buffer`.

    loss_fn(params, batch) -> (loss, metrics); batch leaves [minibatch, ...]. An epoch is
    ceil(filled / minibatch) gradient steps (a traced trip count: the data grows between calls), the
    last minibatch wrapping around to the start of the permutation. Returns (params, opt_state, mean
    metrics of the last epoch).
    """
    size = buffer.size
    filled = buffer.filled
    n_steps = (filled + minibatch - 1) // minibatch
    take = lambda idx: jax.tree.map(lambda d: d[idx], buffer.data)  # noqa: E731
    shapes = jax.eval_shape(lambda p: loss_fn(p, take(jnp.arange(minibatch)))[1], params)
    zeros = jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype), shapes)

    def epoch(carry, key):
        params, opt_state = carry
        # A random permutation of the filled slots first, the empty slots after them.
        order = jnp.argsort(jnp.where(jnp.arange(size) < filled, jax.random.uniform(key, (size,)), 2.0))

        def step(i, inner):
            params, opt_state, acc = inner
            idx = order[(i * minibatch + jnp.arange(minibatch)) % jnp.maximum(filled, 1)]
            grads, metrics = jax.grad(loss_fn, has_aux=True)(params, take(idx))
            updates, opt_state = tx.update(grads, opt_state, params)
            return optax.apply_updates(params, updates), opt_state, jax.tree.map(jnp.add, acc, metrics)

        params, opt_state, acc = jax.lax.fori_loop(0, n_steps, step, (params, opt_state, zeros))
        mean = jax.tree.map(lambda a: a / jnp.maximum(n_steps, 1).astype(a.dtype), acc)
        return (params, opt_state), mean

    (params, opt_state), metrics = jax.lax.scan(epoch, (params, opt_state), jax.random.split(key, epochs))
    return params, opt_state, jax.tree.map(lambda m: m[-1], metrics)
