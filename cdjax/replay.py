"""Fixed-size datasets inside jitted programs: a ring buffer, and epochs of shuffled minibatches over it.

Used by the Mb-Mf phase (model and distillation data); any setting that fits a network to a growing,
statically shaped dataset (imitation from expert trajectories, say) can use the same two pieces. The off-policy
setting's replay buffer is a RingBuffer of time steps of parallel environments, read by `sample_sequences`.
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


def sample_sequences(buffer: RingBuffer, key: jax.Array, batch: int, length: int) -> Any:
    """`batch` sequences of `length` consecutive items of a buffer whose items are batches of streams (leaves
    [N, E, ...]: one time step of E parallel environments per item), time-major: leaves [length, batch, ...].

    Each sequence is one stream e (uniform over E) read from item t to t + length - 1, t uniform over the starts
    whose whole sequence lies among the items held (oldest first, never across the write position where the
    newest item meets the oldest). The caller makes sure at least `length` items are held.
    """
    size = buffer.size
    streams = jax.tree.leaves(buffer.data)[0].shape[1]
    filled = buffer.filled
    oldest = buffer.count - filled
    key_t, key_e = jax.random.split(key)
    start = jax.random.randint(key_t, (batch,), 0, jnp.maximum(filled - length + 1, 1))
    t = (oldest + start[None, :] + jnp.arange(length)[:, None]) % size  # [length, batch]
    e = jax.random.randint(key_e, (batch,), 0, streams)
    return jax.tree.map(lambda d: d[t, e[None, :]], buffer.data)


def fit(loss_fn: Callable, params, opt_state, tx: optax.GradientTransformation, buffer: RingBuffer,
        epochs: int, minibatch: int, key: jax.Array, split: int = 0, fraction: float = 0.0):
    """`epochs` shuffled passes of minibatches over the filled part of `buffer`.

    loss_fn(params, batch) -> (loss, metrics); batch leaves [minibatch, ...]. An epoch is
    ceil(filled / minibatch) gradient steps (a traced trip count: the data grows between calls), the
    last minibatch wrapping around to the start of the permutation. Returns (params, opt_state, mean
    metrics of the last epoch).

    With `fraction` > 0 (static) the buffer is two datasets: slots [0, split) ("old", e.g. random-action
    data, added first and never overwritten) and [split, filled) ("new"); every minibatch then holds
    round(fraction * minibatch) items of a shuffled pass over the new part and the rest of one over the old
    part (each wrapping around on its own), as long as the new part holds anything; before that, all of it
    comes from the old part. An epoch is still ceil(filled / minibatch) steps.
    """
    size = buffer.size
    filled = buffer.filled
    n_steps = (filled + minibatch - 1) // minibatch
    take = lambda idx: jax.tree.map(lambda d: d[idx], buffer.data)  # noqa: E731
    shapes = jax.eval_shape(lambda p: loss_fn(p, take(jnp.arange(minibatch)))[1], params)
    zeros = jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype), shapes)
    slots = jnp.arange(size)
    n_new = round(fraction * minibatch) if fraction > 0 else 0
    n_old = minibatch - n_new
    old_size = jnp.minimum(filled, split) if n_new else filled
    new_size = filled - old_size

    def shuffled(key, first, count):
        """A random permutation of slots [first, first + count), the other slots after them."""
        inside = (slots >= first) & (slots < first + count)
        return jnp.argsort(jnp.where(inside, jax.random.uniform(key, (size,)), 2.0))

    def epoch(carry, key):
        params, opt_state = carry
        key_old, key_new = jax.random.split(key) if n_new else (key, key)  # fraction 0: the one pass as before
        order_old = shuffled(key_old, 0, old_size)
        order_new = shuffled(key_new, old_size, new_size) if n_new else None

        def step(i, inner):
            params, opt_state, acc = inner
            idx = order_old[(i * minibatch + jnp.arange(minibatch)) % jnp.maximum(old_size, 1)]
            if n_new:  # the last n_new items from the new part, once it holds any
                fresh = order_new[(i * n_new + jnp.arange(n_new)) % jnp.maximum(new_size, 1)]
                idx = jnp.concatenate([idx[:n_old], jnp.where(new_size > 0, fresh, idx[n_old:])])
            grads, metrics = jax.grad(loss_fn, has_aux=True)(params, take(idx))
            updates, opt_state = tx.update(grads, opt_state, params)
            return optax.apply_updates(params, updates), opt_state, jax.tree.map(jnp.add, acc, metrics)

        params, opt_state, acc = jax.lax.fori_loop(0, n_steps, step, (params, opt_state, zeros))
        mean = jax.tree.map(lambda a: a / jnp.maximum(n_steps, 1).astype(a.dtype), acc)
        return (params, opt_state), mean

    (params, opt_state), metrics = jax.lax.scan(epoch, (params, opt_state), jax.random.split(key, epochs))
    return params, opt_state, jax.tree.map(lambda m: m[-1], metrics)
