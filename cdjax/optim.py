"""The optimisers: Adam per parameter group, each with its own learning rate and gradient clipping."""

from __future__ import annotations

import jax
import optax

from cdjax.config import Config, HParams


def clipped_adam(lr, hp: HParams) -> optax.GradientTransformation:
    """Adam (epsilon hp.adam_eps) after clipping the gradient's global norm at hp.max_grad_norm."""
    return optax.chain(optax.clip_by_global_norm(hp.max_grad_norm), optax.adam(lr, eps=hp.adam_eps))


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
    return optax.apply_if_finite(tx, max_consecutive_errors=1_000_000)
