"""The consistency gradient's two paths: the weights of each (`PathWeights`), and the identity that scales a gradient."""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
from flax import struct


@struct.dataclass
class PathWeights:
    """Multipliers of the consistency gradient on each of its two paths (traced floats), and of the model path's
    share that trains the encoder."""

    model: Any  # into the model's and the encoder's parameters
    policy: Any  # into the actions, hence the policy's parameters
    encoder: Any = 1.0  # times `model` on the encoder's parameters alone (`path_weights`: 1 / alpha)

    @property
    def to_encoder(self) -> Any:
        """The multiplier of l_cc's gradient into the encoder's parameters (before the caller's alpha)."""
        return self.model * self.encoder


def path_weights(hp) -> PathWeights:
    """The path weights of hyper-parameters with alpha, cc_model and cc_policy: l_cc's gradient reaches the model at
    alpha x cc_model and the policy at alpha x cc_policy, the encoder at cc_model alone (alpha = 0: not at all).

    alpha weighs the term against the model's and the policy's other losses; the grounded encoder's balance is
    between l_cc and its own loss (`enc_aux_coef`), which alpha must not tip. With alpha on the encoder's share, at
    the pixel presets' alpha 100 every encoder of 20 halfcheetah runs shrank its output ~10,000x by 10,000 updates
    (spread 0.12 to 5e-5, the spread floor's hinge at its maximum, experiments/pixel/RESULTS.md), so l_cc vanished:
    l_cc and the active hinge are both linear in the encodings' scale, and shrinking wins whenever alpha x cc_model
    x l_cc / spread exceeds enc_aux_coef. At alpha 1 (the observation and Atari presets) this is the weighting of
    before."""
    alpha = jnp.asarray(hp.alpha, jnp.float32)
    return PathWeights(model=hp.cc_model, policy=hp.cc_policy,
                       encoder=jnp.where(alpha > 0, 1.0 / jnp.where(alpha > 0, alpha, 1.0), 0.0))


@jax.custom_vjp
def _scale(x, s):
    return x


def _scale_fwd(x, s):
    return x, s


def _scale_bwd(s, g):
    # where(s == 0): a weight of 0 gives exactly zero, even if g is not finite.
    return jnp.where(s == 0, jnp.zeros_like(g), g * s.astype(g.dtype)), jnp.zeros_like(s)


_scale.defvjp(_scale_fwd, _scale_bwd)


def scale_gradient(tree, scale):
    """Identity on the values of `tree`; multiplies the gradient flowing back through it by `scale`."""
    scale = jnp.asarray(scale, jnp.float32)
    return jax.tree.map(lambda x: _scale(x, scale), tree)


def safe_norm(x: jax.Array, axis: int = -1) -> jax.Array:
    """Euclidean norm whose value AND gradient are exactly 0 at x = 0 (plain norm: NaN gradient)."""
    sq = jnp.sum(x**2, axis=axis)
    positive = sq > 0
    return jnp.where(positive, jnp.sqrt(jnp.where(positive, sq, 1.0)), 0.0)
