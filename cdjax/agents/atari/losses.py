"""A2C's losses and the latent model's loss as module-level pure functions; shapes time-major [T, B, ...].

`mask` is True where a transition counts (False for a non-finite transition the environment replaced).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from cdjax.agents.atari.networks import entropy
from cdjax.numerics import backward_linear_recurrence, masked_mean


def n_step_returns(reward, next_value, terminated, ended, valid, gamma):
    """A2C's bootstrapped n-step returns of one rollout, time-major [T, B].

    R_t = r_t + gamma * (0 if terminated_t, else V(s'_t) if the sequence stops after t, else R_{t+1}).
    The sequence stops after t when the episode ended there (termination, time-out or a reset after a
    non-finite step), at the rollout's last step, and before an invalid transition (its state was replaced).
    next_value [T, B] is V of the true next observation s'_t (before any reset), so a time-out bootstraps
    from the state the episode was cut at. The return of an invalid transition is 0 (mask it out).
    """
    valid = valid.astype(bool)
    next_invalid = jnp.concatenate([~valid[1:], jnp.ones_like(valid[:1])])
    stop = ended.astype(bool) | next_invalid
    keep = (1.0 - terminated.astype(jnp.float32)) * valid
    cont = jnp.where(stop | ~valid, 0.0, gamma)
    base = jnp.where(valid, reward + gamma * keep * stop * next_value, 0.0)
    return backward_linear_recurrence(cont, base)


def a2c_loss(logits, values, actions, returns, mask, hp) -> tuple[jax.Array, dict]:
    """Policy gradient + value_coef * value MSE - ent_coef * entropy (OpenAI baselines' A2C).

    logits [T, B, A], values [T, B] (with gradients); actions [T, B] int; returns [T, B] targets.
    The advantage R - V is not normalised and carries no gradient into the policy term.
    """
    advantage = jax.lax.stop_gradient(returns - values)
    logp = jnp.take_along_axis(jax.nn.log_softmax(logits), actions[..., None], axis=-1)[..., 0]
    policy = -masked_mean(logp * advantage, mask)
    value = masked_mean((returns - values) ** 2, mask)
    ent = masked_mean(entropy(logits), mask)
    loss = policy + hp.value_coef * value - hp.ent_coef * ent
    return loss, {"loss/policy": policy, "loss/value": value, "policy/entropy": ent,
                  "value/mean": masked_mean(values, mask), "value/advantage": masked_mean(advantage, mask)}


def latent_model_loss(pred_z, pred_reward, target_z, reward, mask) -> tuple[jax.Array, dict]:
    """One-step loss of the latent model: mean squared error of z' (against a stop-gradient target, averaged
    over features) plus the squared error of the reward. pred_z, target_z [..., D]; the rest [...]."""
    latent = masked_mean(((pred_z - jax.lax.stop_gradient(target_z)) ** 2).mean(-1), mask)
    rew = masked_mean((pred_reward - reward) ** 2, mask)
    return latent + rew, {"model/latent_mse": latent, "model/reward_mse": rew}
