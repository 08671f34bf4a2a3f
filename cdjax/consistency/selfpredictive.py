"""The self-predictive consistency term (SPR, TD-MPC2, MR.Q) and what it shares with the paper's term when both are
computed on replayed sequences.

Self-prediction: from the latent z_0 = enc(s_0) of a real state, the latent transition is rolled out k steps under
the real actions, and each predicted latent is pulled towards the target encoder's latent of the real state reached,

    l_sp = sum_j rho^j mean_w || f^j(z_0, a_0..a_{j-1}) - sg(enc_target(s_j)) ||^2 / sum_j rho^j,

with the target encoder an exponential moving average of the online one (or the online one under stop_gradient).
The target gets no gradient: it is the fixed point the online encoder and transition chase, which is what keeps the
pair from collapsing to a constant under a BYOL-style objective.

Shared with the paper's term (`cdjax.consistency.consistency_loss`) off-policy: windows of replayed sequences stop at
the first episode end (`cdjax.consistency.window_mask` on time-major [k, W] data), and the policy path through the
actions, which replay holds as constants chosen by older policies, is a straight-through path (`policy_path`).
"""

from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp

from cdjax.numerics import masked_mean


def latent_rollout(transition: Callable, z0: jax.Array, actions: jax.Array) -> jax.Array:
    """transition(z [W, D], a [W, A]) -> z'; z0 [W, D], actions [k, W, A] -> the predicted latents [k, W, D]."""
    def step(z, a):
        z = transition(z, a)
        return z, z

    return jax.lax.scan(step, z0, actions)[1]


def self_predictive_loss(predicted: jax.Array, target: jax.Array, mask: jax.Array, rho) -> tuple[jax.Array, dict]:
    """l_sp of predicted latents [k, W, D] against target latents [k, W, D] (stop-gradient here), windows mask [W]
    -> (loss, metrics). Step j (from 1) weighs rho^(j-1), normalised to sum to one."""
    k = predicted.shape[0]
    err = ((predicted - jax.lax.stop_gradient(target)) ** 2).mean(-1)  # [k, W]
    weights = jnp.asarray(rho, jnp.float32) ** jnp.arange(k, dtype=jnp.float32)
    per_step = jnp.stack([masked_mean(err[j], mask) for j in range(k)])
    loss = (weights * per_step).sum() / weights.sum()
    cos = (predicted * target).sum(-1) / jnp.maximum(
        jnp.linalg.norm(predicted, axis=-1) * jnp.linalg.norm(target, axis=-1), 1e-8)
    return loss, {"loss/self_predictive": loss, "self_pred/first_mse": per_step[0], "self_pred/last_mse": per_step[-1],
                  "self_pred/cosine": masked_mean(jax.lax.stop_gradient(cos[-1]), mask)}


def polyak(target, online, tau):
    """The target parameters moved a step tau towards the online ones (exponential moving average)."""
    tau = jnp.asarray(tau, jnp.float32)
    return jax.tree.map(lambda t, o: t + tau * (o - t), target, online)


def policy_path(buffered: jax.Array, current: jax.Array) -> jax.Array:
    """Replayed actions on the policy path: the value of `buffered` (what was done, so the window is the real one), the
    gradient of `current` (the current policy's action at the same states). A term differentiated through the result
    sends dL/da to the current policy as if it had chosen the replayed actions: the on-policy path's gradient at the
    states the data visited."""
    return jax.lax.stop_gradient(buffered) + (current - jax.lax.stop_gradient(current))


__all__ = ["latent_rollout", "policy_path", "polyak", "self_predictive_loss"]
