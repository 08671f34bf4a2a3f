"""The Mb-Mf phase's data: what one acting stage records, the model's transitions, the labelled states, and
the model's training objective."""

from __future__ import annotations

import jax
from flax import struct

from cdjax.agents.obs import losses
from cdjax.agents.obs.mbmf.spec import ModelObjective
from cdjax.numerics import masked_mean


@struct.dataclass
class Rollout:
    """One stage of acting in the phase's environments; leaves time-major [L, B, ...]."""

    obs: jax.Array  # [L, B, O] observation acted on
    action: jax.Array  # [L, B, A] executed action
    label: jax.Array  # [L, B, A] the MPC's action at obs (distillation target; = action when MPC acts)
    next_obs: jax.Array  # [L, B, O] true observation after the action (before any reset)
    reward: jax.Array  # [L, B]
    terminated: jax.Array  # [L, B] bool
    ended: jax.Array  # [L, B] bool: terminated, timed out or invalid
    valid: jax.Array  # [L, B] bool


def _flat(x: jax.Array) -> jax.Array:
    """[L, B, ...] -> [L * B, ...]."""
    return x.reshape((-1,) + x.shape[2:])


@struct.dataclass
class Transitions:
    """Model data; leaves [N, ...]."""

    obs: jax.Array
    action: jax.Array
    next_obs: jax.Array
    reward: jax.Array
    valid: jax.Array

    @classmethod
    def of(cls, traj: Rollout) -> "Transitions":
        return cls(*map(_flat, (traj.obs, traj.action, traj.next_obs, traj.reward, traj.valid)))


@struct.dataclass
class Labelled:
    """Distillation data: visited states and the MPC's action there; leaves [N, ...]."""

    obs: jax.Array
    action: jax.Array
    valid: jax.Array

    @classmethod
    def of(cls, traj: Rollout) -> "Labelled":
        return cls(*map(_flat, (traj.obs, traj.label, traj.valid)))


def model_objective(pred_mean, pred_log_std, target, mask, kind: ModelObjective):
    """The model's training loss on normalised (delta-s, reward) targets [..., O+1] -> (loss, metrics).

    nll: the Gaussian NLL of losses.model_loss. Its per-dimension weights are 1/sigma^2, so the model
         spends its capacity on the dimensions it already predicts well (the state deltas, whose sigma
         reaches the floor) and starves the reward, which the MPC needs most.
    mse: the mean by the squared error summed over dimensions (Nagabandi et al.: MSE), every dimension
         weighted alike; log_std by the NLL at the stopped mean, so it is calibrated for the NLL that
         the PPO phase goes on training with.
    """
    if kind == "nll":
        return losses.model_loss(pred_mean, pred_log_std, target, mask)
    nll, metrics = losses.model_loss(jax.lax.stop_gradient(pred_mean), pred_log_std, target, mask)
    mse = masked_mean(((target - pred_mean) ** 2).sum(-1), mask)
    metrics["loss/model_mse"] = mse
    return mse + nll, metrics
