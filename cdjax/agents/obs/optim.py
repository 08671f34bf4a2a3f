"""The observation-space agent's optimiser: Adam per parameter group, each with its own learning rate and
gradient clipping."""

from __future__ import annotations

import optax

from cdjax.agents.obs.config import Config, HParams
from cdjax.optim import clipped_adam, per_group_vectors, skip_if_not_finite


def make_optimizer(config: Config, params: dict, hp: HParams) -> optax.GradientTransformation:
    """Adam per parameter group with its own learning rate and gradient clipping, on one vector per group
    (`per_group_vectors`).

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
    labels = lambda p: {name: name for name in p}  # noqa: E731  (p: {group: vector})
    tx = optax.multi_transform(transforms, labels)
    if config.clip_scope == "policy-value":  # one clip over policy and value together, then Adam per group
        transforms.update(policy=adam(hp.lr_policy), value=adam(hp.lr_value))
        joint = lambda p: {name: "ppo" if name in ("policy", "value") else "rest" for name in p}  # noqa: E731
        clip = optax.multi_transform({"ppo": optax.clip_by_global_norm(hp.max_grad_norm),
                                      "rest": optax.identity()}, joint)
        tx = optax.chain(clip, optax.multi_transform(transforms, labels))
    return per_group_vectors(skip_if_not_finite(tx))
