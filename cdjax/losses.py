"""Losses as module-level pure functions of network outputs and data: (..., hp) -> (scalar, metrics).

Shapes are time-major: [T, B, ...]. A `mask` is 1 where a sample counts and 0 where it must not
(non-finite physics, windows crossing an episode end).
"""

from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp

from cdjax.networks import action_distribution


def masked_mean(x: jax.Array, mask: jax.Array) -> jax.Array:
    mask = mask.astype(x.dtype)
    return (x * mask).sum() / jnp.maximum(mask.sum(), 1.0)


def safe_norm(x: jax.Array, axis: int = -1) -> jax.Array:
    """Euclidean norm whose value AND gradient are exactly 0 at x = 0 (plain norm: NaN gradient)."""
    sq = jnp.sum(x**2, axis=axis)
    positive = sq > 0
    return jnp.where(positive, jnp.sqrt(jnp.where(positive, sq, 1.0)), 0.0)


def gae(reward, value, next_value, bootstrap, ended, gamma, lam):
    """Generalised advantage estimation, time-major [T, B].

    bootstrap: 1 where V(next_obs) is used (not terminated; time-outs DO bootstrap), ended: 1 where the
    episode ended after the step (terminated, timed out or reset after a non-finite state); the
    advantage recursion stops there. Returns (advantages, value targets).
    """
    bootstrap = bootstrap.astype(jnp.float32)
    cont = 1.0 - ended.astype(jnp.float32)
    delta = reward + gamma * bootstrap * next_value - value

    def step(next_adv, inp):
        d, c = inp
        adv = d + gamma * lam * c * next_adv
        return adv, adv

    _, adv = jax.lax.scan(step, jnp.zeros_like(value[0]), (delta, cont), reverse=True)
    return adv, adv + value


def ppo_loss(mean, log_std, value, raw_action, log_prob_old, advantages, returns, mask, hp):
    """Clipped-surrogate PPO with value loss and entropy bonus, from current network outputs.

    mean [T, B, A] and log_std [A] are the current policy's outputs on the rollout's observations,
    value [T, B] the current value estimates; raw_action [T, B, A] is the executed pre-squash action,
    whose log-probability is re-evaluated under the current policy. Advantages are normalised over
    the unmasked samples. Returns (loss, metrics).
    """
    dist = action_distribution(mean, log_std)
    return policy_terms(dist.log_prob(raw_action), dist.entropy(), value, log_prob_old, advantages,
                        returns, mask, hp)


def policy_terms(log_prob, entropy, value, log_prob_old, advantages, returns, mask, hp):
    """PPO terms given new log-probabilities/entropy/values of the executed actions. All [T, B]."""
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
    metrics = {
        "loss/policy": policy_loss,
        "loss/value": value_loss,
        "loss/entropy": ent,
        "ppo/approx_kl": masked_mean((ratio - 1.0) - log_ratio, mask),
        "ppo/clip_fraction": masked_mean((jnp.abs(ratio - 1.0) > hp.clip_eps).astype(jnp.float32), mask),
    }
    return loss, metrics


def model_loss(pred_mean, pred_log_std, target, mask):
    """Gaussian negative log-likelihood of the normalised (delta-s, reward) targets.

    pred_mean, pred_log_std, target: [..., O+1]; mask [...]. Returns (loss, metrics).
    """
    z = (target - pred_mean) * jnp.exp(-pred_log_std)
    nll = (0.5 * z**2 + pred_log_std + 0.5 * jnp.log(2.0 * jnp.pi)).sum(-1)
    loss = masked_mean(nll, mask)
    sq = (target - pred_mean) ** 2
    metrics = {
        "loss/model_nll": loss,
        "model/onestep_mse": masked_mean(sq[..., :-1].mean(-1), mask),
        "model/reward_mse": masked_mean(sq[..., -1], mask),
    }
    return loss, metrics


def window_indices(offsets: jax.Array, horizon: int) -> jax.Array:
    """Time indices [k, n] of n windows of length k starting at `offsets` [n]."""
    return offsets[None, :] + jnp.arange(horizon)[:, None]


def window_mask(ended: jax.Array, valid: jax.Array, idx: jax.Array) -> jax.Array:
    """[n, B] True for windows that stay inside one episode.

    A window starting at o uses obs[o], actions o..o+k-1 and next_obs[o..o+k-1]. It is broken if an
    episode ends after any of its first k-1 steps (auto-reset replaced the next state) or if any of
    its k transitions is invalid. An episode ending after the window's last step is fine: next_obs
    holds the true final observation.
    """
    crosses = ended[idx[:-1]].any(axis=0)
    invalid = (~valid[idx]).any(axis=0)
    return ~crosses & ~invalid


def _masked_spread(x: jax.Array, mask: jax.Array) -> jax.Array:
    """Mean over features of the standard deviation across the unmasked rows of x [W, D]."""
    m = mask.astype(jnp.float32)[:, None]
    mean = (x * m).sum(0) / jnp.maximum(m.sum(), 1.0)
    var = (((x - mean) ** 2) * m).sum(0) / jnp.maximum(m.sum(), 1.0)
    return jnp.sqrt(var + 1e-12).mean()


def consistency_loss(model_step: Callable, normalize: Callable, s0, actions, real_next, mask, *,
                     encoder: str, encode_step: Callable | None = None, h0=None, unroll: int = 1):
    """l_cc: distance between the encodings of the real and the imagined k-step sequences.

    s0 [W, O] real start states; actions [k, W, A] (differentiable in the policy); real_next [k, W, O]
    the real states s_1..s_k; mask [W]. model_step(s, a) -> s' imagines in raw observation space;
    normalize maps raw states to the encoder's input space. One scan computes the imagined states and
    both encodings (the encoder is shared, real and imagined rows go through it as one batch).

    encoder: "gru" / "frozen-gru": || GRU(s_1..s_k) - GRU(s^I_1..s^I_k) ||_2 with encode_step(h, x) -> h
             and initial state h0 [W, H];
             "l2": mean over the k steps of || norm(s_t) - norm(s^I_t) ||_2.
    Returns (loss averaged over unmasked windows, metrics).
    """
    k, W = actions.shape[:2]
    assert s0.shape[0] == W and real_next.shape[:2] == (k, W) and mask.shape == (W,), (
        s0.shape, actions.shape, real_next.shape, mask.shape)
    use_gru = encoder != "l2"
    h = jnp.concatenate([h0, h0], axis=0) if use_gru else jnp.zeros((2 * W, 1), jnp.float32)

    def step(carry, inp):
        s_im, h, acc = carry
        a, s_re = inp
        s_im = model_step(s_im, a)
        x_re, x_im = normalize(s_re), normalize(s_im)
        if use_gru:
            h = encode_step(h, jnp.concatenate([x_re, x_im], axis=0))
        else:
            acc = acc + safe_norm(x_re - x_im)
        return (s_im, h, acc), None

    (s_im, h, acc), _ = jax.lax.scan(step, (s0, h, jnp.zeros((W,), jnp.float32)), (actions, real_next),
                                     unroll=unroll)
    if use_gru:
        e_re, e_im = h[:W], h[W:]
        per_window = safe_norm(e_re - e_im)
    else:
        e_re, e_im = normalize(real_next[-1]), normalize(s_im)
        per_window = acc / k
    loss = masked_mean(per_window, mask)
    final_err = ((normalize(real_next[-1]) - normalize(s_im)) ** 2).mean(-1)
    metrics = {
        "loss/consistency": loss,
        "encoder/spread_real": _masked_spread(e_re, mask),
        "encoder/spread_imagined": _masked_spread(e_im, mask),
        "consistency/masked_fraction": (~mask).astype(jnp.float32).mean(),
        "consistency/final_mse": masked_mean(final_err, mask),
    }
    return loss, metrics
