"""Small array operations every setting uses: the masked mean and the backward linear recurrence behind
discounted returns and GAE. Time-major: [T, ...]."""

from __future__ import annotations

import jax
import jax.numpy as jnp


def masked_mean(x: jax.Array, mask: jax.Array) -> jax.Array:
    """The mean of x over the entries where mask is true (0 where none is)."""
    mask = mask.astype(x.dtype)
    return (x * mask).sum() / jnp.maximum(mask.sum(), 1.0)


def masked_share(x: jax.Array, mask: jax.Array) -> jax.Array:
    """Each entry's share of `masked_mean(x, mask)`, an array of x's shape whose sum is that mean.

    For a diagnostic averaged over many minibatches in a loop: adding the shares up elementwise and reducing once
    after the loop gives the mean of the minibatches' means without a full reduction in every step. (On a GPU,
    XLA fused one such scalar reduction with the loss's backward into a kernel of a single thread block, a large
    share of an Mb-Mf update's time.)
    """
    mask = mask.astype(x.dtype)
    return x * mask / jnp.maximum(mask.sum(), 1.0)


# Up to this many steps the recurrence is solved as one [T, T] weighting (`_dense_backward`), beyond it by an
# associative scan: T^3 x batch products against about 2 T log T x batch, in 2 kernels against about 20.
DENSE_MAX_STEPS = 32


def backward_linear_recurrence(a: jax.Array, b: jax.Array) -> jax.Array:
    """x_t = b_t + a_t * x_{t+1} with x_T = 0, along axis 0 (a, b: [T, ...]).

    The same numbers as a reverse `lax.scan`, without its loop: on a GPU a scan's loop costs a host round trip
    per step, which made GAE recomputed in every minibatch the largest part of it. Short sequences (the PPO
    minibatches' 20-step segments) are solved in closed form, longer ones by an associative scan; on a GPU each
    level of the scan is a few small kernels, in each of the epochs x minibatches steps of an update.
    """
    if a.shape[0] <= DENSE_MAX_STEPS:
        return _dense_backward(a, b)
    return _scan_backward(a, b)


def _dense_backward(a: jax.Array, b: jax.Array) -> jax.Array:
    """x_t = sum_{s >= t} (prod_{t <= j < s} a_j) b_s: the unrolled recurrence, as a [T, T] weighting per column."""
    T = a.shape[0]
    t, s, j = jnp.arange(T)[:, None, None], jnp.arange(T)[None, :, None], jnp.arange(T)[None, None, :]
    inside = ((t <= j) & (j < s)).reshape((T, T, T) + (1,) * (a.ndim - 1))
    weight = jnp.prod(jnp.where(inside, a[None, None], 1.0), axis=2)  # [t, s, ...]: 1 on the diagonal
    later = (t <= s).reshape((T, T) + (1,) * (a.ndim - 1))  # a select, not a zero weight: b_s of s < t never enters
    return jnp.where(later, weight * b[None], 0.0).sum(axis=1)


def _scan_backward(a: jax.Array, b: jax.Array) -> jax.Array:
    """The recurrence by `lax.associative_scan` (any T)."""

    def combine(later, earlier):  # compose x -> b_e + a_e * (b_l + a_l * x)
        a_l, b_l = later
        a_e, b_e = earlier
        return a_e * a_l, b_e + a_e * b_l

    _, x = jax.lax.associative_scan(combine, (a[::-1], b[::-1]))
    return x[::-1]


def orthogonal(scale: float = 1.0):
    """Flax's orthogonal initializer (`flax.linen.initializers.orthogonal(scale)`), the same values bit for bit,
    whose `vmap` draws one matrix after another (`jax.lax.map`) instead of factoring the whole batch in one QR.

    jaxlib's batched QR on a CPU splits the batch over XLA's thread pool and waits for its parts inside the pool: where
    the program runs two such QRs at once on a machine of two cores, both threads of the pool wait and nothing runs
    them (a sweep's vmapped init of the Atari network hung on a 2-core machine, every thread idle). Drawn one run at a
    time, each QR is a single matrix and runs where it is. Only the initial weights are drawn so: once per run."""
    from flax import linen as nn

    draw_one = nn.initializers.orthogonal(scale)

    def init(key, shape, dtype=jnp.float32):
        @jax.custom_batching.custom_vmap
        def draw(key):
            return draw_one(key, shape, dtype)

        @draw.def_vmap
        def _one_after_another(axis_size, in_batched, key):
            if not in_batched[0]:  # one key for the whole batch: one matrix
                return draw(key), False
            return jax.lax.map(draw, key), True

        return draw(key)

    return init
