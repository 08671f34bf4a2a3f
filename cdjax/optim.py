"""Optimiser pieces every setting may use: clipped Adam, skipping non-finite steps, one vector per parameter group."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import optax
from jax.flatten_util import ravel_pytree



def clipped_adam(lr, hp) -> optax.GradientTransformation:
    """Adam (epsilon hp.adam_eps) after clipping the gradient's global norm at hp.max_grad_norm (any setting's
    HParams with those two fields)."""
    return optax.chain(optax.clip_by_global_norm(hp.max_grad_norm), optax.adam(lr, eps=hp.adam_eps))


def skip_if_not_finite(inner: optax.GradientTransformation) -> optax.GradientTransformation:
    """`inner`, except that a step whose gradients are not all finite leaves the parameters and the inner
    state as they were (zero updates) and counts itself in `total_notfinite`: optax.apply_if_finite with no
    limit on consecutive skips, and the same state, but choosing by a select instead of a `lax.cond`. On a
    GPU a conditional reads its predicate back on the host, once in each of the epochs x minibatches steps
    of an unbatched update (a vmapped one turns it into a select anyway)."""
    def init(params):
        zero = jnp.zeros((), jnp.int32)
        return optax.ApplyIfFiniteState(notfinite_count=zero, last_finite=jnp.array(True), total_notfinite=zero,
                                        inner_state=inner.init(params))

    def update(updates, state, params=None):
        finite = jnp.all(jnp.array([jnp.all(jnp.isfinite(u)) for u in jax.tree.leaves(updates)]))
        new_updates, new_inner = inner.update(updates, state.inner_state, params)
        keep = lambda new, old: jnp.where(finite, new, old)  # noqa: E731
        return jax.tree.map(lambda u: jnp.where(finite, u, 0.0), new_updates), optax.ApplyIfFiniteState(
            notfinite_count=jnp.where(finite, 0, state.notfinite_count + 1).astype(jnp.int32),
            last_finite=finite,
            total_notfinite=jnp.where(finite, state.total_notfinite, state.total_notfinite + 1).astype(jnp.int32),
            inner_state=jax.tree.map(keep, new_inner, state.inner_state))

    return optax.GradientTransformation(init, update)


def per_group_vectors(inner: optax.GradientTransformation) -> optax.GradientTransformation:
    """`inner` applied to {group: one flat vector} instead of {group: tree of arrays}: each group's leaves are
    raveled into one vector before `inner` and the updates unraveled after it, and `inner`'s state (Adam's
    moments, the finite check) holds one vector per group.

    The numbers are those of `inner` on the trees (clipping by a group's global norm and Adam are elementwise or
    group-wide); only the sums inside the norms are taken in another order. What changes is the program: on a
    GPU every leaf of every step of the optimiser (the finite check, the norm, the moments, the select) is a
    small kernel of its own, in each of the epochs x minibatches steps of an update; on vectors they are a few.
    """

    def flat(tree):
        return {group: ravel_pytree(sub)[0] for group, sub in tree.items()}

    def init(params):
        return inner.init(flat(params))

    def update(updates, state, params=None):
        raveled = {group: ravel_pytree(sub) for group, sub in updates.items()}  # (vector, unravel) per group
        vectors = {group: vector for group, (vector, _) in raveled.items()}
        new, state = inner.update(vectors, state, None if params is None else flat(params))
        return {group: raveled[group][1](vector) for group, vector in new.items()}, state

    return optax.GradientTransformation(init, update)
