"""The optimisers: Adam per parameter group, each with its own learning rate and gradient clipping."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import optax

from cdjax.config import Config, HParams


def clipped_adam(lr, hp: HParams) -> optax.GradientTransformation:
    """Adam (epsilon hp.adam_eps) after clipping the gradient's global norm at hp.max_grad_norm."""
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


def make_optimizer(config: Config, params: dict, hp: HParams) -> optax.GradientTransformation:
    """Adam per parameter group with its own learning rate and gradient clipping.

    The frozen-GRU encoder gets zero updates. A step whose gradients are not finite is skipped.
    """

    def adam(lr):
        return optax.adam(lr, eps=hp.adam_eps)

    def group(lr):
        return clipped_adam(lr, hp)

    lrs = {"policy": hp.lr_policy, "value": hp.lr_value, "model": hp.lr_model, "encoder": hp.lr_model}
    transforms = {}
    for name in params:
        frozen = name == "encoder" and config.encoder == "frozen-gru"
        transforms[name] = optax.set_to_zero() if frozen else group(lrs[name])
    labels = lambda p: {name: jax.tree.map(lambda _: name, sub) for name, sub in p.items()}  # noqa: E731
    tx = optax.multi_transform(transforms, labels)
    if config.clip_scope == "policy-value":  # one clip over policy and value together, then Adam per group
        transforms.update(policy=adam(hp.lr_policy), value=adam(hp.lr_value))
        joint = lambda p: {name: jax.tree.map(lambda _: "ppo" if name in ("policy", "value") else "rest", sub)  # noqa: E731
                           for name, sub in p.items()}
        clip = optax.multi_transform({"ppo": optax.clip_by_global_norm(hp.max_grad_norm),
                                      "rest": optax.identity()}, joint)
        tx = optax.chain(clip, optax.multi_transform(transforms, labels))
    return skip_if_not_finite(tx)
