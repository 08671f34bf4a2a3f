"""The pixel setting's losses as pure functions: the Gaussian log-likelihood and KL of the ELBO, and the imitation
error of the policy (the consistency term is `cdjax.consistency`'s)."""

from __future__ import annotations

import math

import jax.numpy as jnp

LOG_2PI = math.log(2 * math.pi)


def gaussian_log_prob(x, mean, std):
    """Elementwise log N(x; mean, std^2), nats."""
    return -0.5 * ((x - mean) / std) ** 2 - jnp.log(std) - 0.5 * LOG_2PI


def gaussian_kl(mean_q, std_q, mean_p, std_p):
    """Elementwise KL(N(mean_q, std_q^2) || N(mean_p, std_p^2)), nats."""
    return jnp.log(std_p / std_q) + (std_q**2 + (mean_q - mean_p) ** 2) / (2 * std_p**2) - 0.5


def imitation_loss(predicted, actions):
    """The policy's imitation loss: the mean squared error of its actions against the expert's (every element)."""
    return ((predicted - actions) ** 2).mean()
