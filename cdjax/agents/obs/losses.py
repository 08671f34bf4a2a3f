"""Losses as module-level pure functions of network outputs and data: (..., hp) -> (scalar, metrics).

Shapes are time-major: [T, B, ...]. A `mask` is 1 where a sample counts and 0 where it must not
(non-finite physics, windows crossing an episode end).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from cdjax import normalize as nz

from cdjax.agents.obs.networks import action_distribution, squashed_entropy
from cdjax.numerics import backward_linear_recurrence, masked_mean, masked_share


def gae(reward, value, next_value, bootstrap, ended, gamma, lam, valid=None):
    """Generalised advantage estimation, time-major [T, B].

    bootstrap: 1 where V(next_obs) is used (not terminated; time-outs DO bootstrap), ended: 1 where the
    episode ended after the step (terminated, timed out or reset after a non-finite state); the
    advantage recursion stops there. valid: 0 for a non-finite transition, whose TD error is set to 0
    so that nothing of it (-V(s)) reaches the step before. Returns (advantages, value targets).
    """
    bootstrap = bootstrap.astype(jnp.float32)
    cont = 1.0 - ended.astype(jnp.float32)
    delta = reward + gamma * bootstrap * next_value - value
    if valid is not None:
        delta = jnp.where(valid, delta, 0.0)

    adv = backward_linear_recurrence(gamma * lam * cont, delta)
    return adv, adv + value


def ppo_loss(mean, std, value, raw_action, log_prob_old, advantages, returns, mask, hp, entropy_noise=None,
             shares: bool = False):
    """Clipped-surrogate PPO with value loss and entropy bonus, from current network outputs.

    mean, std [T, B, A] are the current policy's outputs on the rollout's observations, value [T, B]
    the current value estimates; raw_action [T, B, A] is the executed pre-squash action, whose
    log-probability is re-evaluated under the current policy (the tanh Jacobian cancels in the
    ratio). The entropy is the Gaussian's, or with `entropy_noise` [T, B, A] the one-sample estimate of
    the squashed action's (`networks.squashed_entropy`). Advantages are normalised over the unmasked
    samples. Returns (loss, metrics); `shares` as in `policy_terms`.
    """
    dist = action_distribution(mean, std)
    entropy = dist.entropy() if entropy_noise is None else squashed_entropy(mean, std, entropy_noise)
    return policy_terms(dist.log_prob(raw_action), entropy, value, log_prob_old, advantages, returns, mask, hp,
                        shares)


def policy_terms(log_prob, entropy, value, log_prob_old, advantages, returns, mask, hp, shares: bool = False):
    """PPO terms given new log-probabilities/entropy/values of the executed actions. All [T, B].

    The metrics (the loss and its parts, and the diagnostics ppo/approx_kl and ppo/clip_fraction) are masked means,
    or with `shares` their per-sample shares [T, B] (`numerics.masked_share`: summed, the same means), for a caller
    that averages them over minibatches and reduces once. The loss itself is the scalar either way; with `shares`
    its value is used by nothing but a gradient, so its reductions drop out of the compiled step."""
    diagnostic = masked_share if shares else masked_mean
    mask = mask.astype(jnp.float32)
    adv_mean = masked_mean(advantages, mask)
    adv_std = jnp.sqrt(masked_mean((advantages - adv_mean) ** 2, mask) + 1e-8)
    adv = (advantages - adv_mean) / adv_std
    log_ratio = log_prob - log_prob_old
    ratio = jnp.exp(log_ratio)
    surrogate = jnp.minimum(ratio * adv, jnp.clip(ratio, 1.0 - hp.clip_eps, 1.0 + hp.clip_eps) * adv)
    policy_loss = -masked_mean(surrogate, mask)
    value_loss = 0.5 * masked_mean((returns - value) ** 2, mask)
    ent = masked_mean(entropy, mask)
    loss = policy_loss + hp.vf_coef * value_loss - hp.ent_coef * ent
    if shares:
        policy_loss = -masked_share(surrogate, mask)
        value_loss = 0.5 * masked_share((returns - value) ** 2, mask)
        ent = masked_share(entropy, mask)
    metrics = {
        "loss/policy": policy_loss,
        "loss/value": value_loss,
        "loss/entropy": ent,
        "loss/ppo": policy_loss + hp.vf_coef * value_loss - hp.ent_coef * ent,
        "ppo/approx_kl": diagnostic((ratio - 1.0) - log_ratio, mask),
        "ppo/clip_fraction": diagnostic((jnp.abs(ratio - 1.0) > hp.clip_eps).astype(jnp.float32), mask),
    }
    return loss, metrics


def model_loss(pred_mean, pred_log_std, target, mask, shares: bool = False):
    """Gaussian negative log-likelihood of the normalised (delta-s, reward) targets.

    pred_mean, pred_log_std, target: [..., O+1]; mask [...]. Returns (loss, metrics). The metrics (loss/model_nll
    and the diagnostics model/onestep_mse and model/reward_mse) are masked means, or with `shares` per-sample shares
    [...] as in `policy_terms`.
    """
    diagnostic = masked_share if shares else masked_mean
    z = (target - pred_mean) * jnp.exp(-pred_log_std)
    nll = (0.5 * z**2 + pred_log_std + 0.5 * jnp.log(2.0 * jnp.pi)).sum(-1)
    loss = masked_mean(nll, mask)
    sq = (target - pred_mean) ** 2
    metrics = {
        "loss/model_nll": diagnostic(nll, mask),
        "model/onestep_mse": diagnostic(sq[..., :-1].mean(-1), mask),
        "model/reward_mse": diagnostic(sq[..., -1], mask),
    }
    return loss, metrics


def model_target(norms: nz.Norms, obs, next_obs, reward) -> jax.Array:
    """The dynamics model's target [..., O+1]: the normalised change of state and the normalised reward."""
    return jnp.concatenate([nz.normalize(norms.delta, next_obs - obs), nz.normalize(norms.reward, reward[..., None])],
                           axis=-1)


# The parameter groups each loss term can reach (the gradient-norm metrics report these pairs). Each group is reached
# by at most one term besides l_cc (`rest_gradient` relies on it).
TERM_GROUPS = {"ppo": ("policy", "value"), "model_nll": ("model",), "consistency": ("model", "encoder", "policy"),
               "encoder_aux": ("encoder",)}
# The loss terms whose metric `loss_terms(shares=True)` gives as per-sample shares (the others are scalars there).
# In the SGD no scalar of these terms is then used, so XLA drops their per-step reductions (under vmap it had fused
# them with the losses' backward into a slow kernel).
SHARED_TERMS = {"ppo": "loss/ppo", "model_nll": "loss/model_nll"}


def term_weights(hp) -> dict[str, jax.Array]:
    """The weight of each named loss term in the total."""
    return {"ppo": jnp.ones((), jnp.float32), "model_nll": hp.model_coef, "consistency": hp.alpha,
            "encoder_aux": hp.enc_aux_coef}
