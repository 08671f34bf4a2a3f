"""Flax modules (policy, value, dynamics model, sequence encoder) and the action distribution.

All modules take normalised inputs. Actions live in [-1, 1]: the policy is a diagonal Gaussian over
the pre-squash action u, and the executed action is tanh(u). `action_distribution` is the one place
that builds that distribution.
"""

from __future__ import annotations

from typing import Sequence

import distrax
import flax.linen as nn
import jax
import jax.numpy as jnp

MODEL_LOG_STD_MIN = -6.0  # bounds of the dynamics model's predicted log standard deviation
MODEL_LOG_STD_MAX = 1.0


def action_distribution(mean: jax.Array, log_std: jax.Array) -> distrax.MultivariateNormalDiag:
    """Diagonal Gaussian over the pre-squash action u; the executed action is squash(u)."""
    return distrax.MultivariateNormalDiag(mean, jnp.exp(log_std) * jnp.ones_like(mean))


def squash(u: jax.Array) -> jax.Array:
    return jnp.tanh(u)


def act_from_noise(mean: jax.Array, log_std: jax.Array, noise: jax.Array) -> jax.Array:
    """The action a = squash(mean + std * noise): differentiable in the policy's outputs."""
    return squash(mean + jnp.exp(log_std) * noise)


class MLP(nn.Module):
    widths: Sequence[int]
    out: int
    activation: str = "tanh"
    out_scale: float = 1.0  # orthogonal init scale of the last layer

    @nn.compact
    def __call__(self, x):
        act = getattr(nn, self.activation)
        for w in self.widths:
            x = act(nn.Dense(w, kernel_init=nn.initializers.orthogonal(jnp.sqrt(2.0)))(x))
        return nn.Dense(self.out, kernel_init=nn.initializers.orthogonal(self.out_scale))(x)


class Policy(nn.Module):
    """obs [..., O] -> (mean [..., A], log_std [A]); log_std is state-independent."""

    action_size: int
    hidden: Sequence[int]

    @nn.compact
    def __call__(self, obs):
        mean = MLP(self.hidden, self.action_size, "tanh", out_scale=0.01)(obs)
        log_std = self.param("log_std", nn.initializers.zeros, (self.action_size,))
        return mean, log_std


class Value(nn.Module):
    """obs [..., O] -> value [...]."""

    hidden: Sequence[int]

    @nn.compact
    def __call__(self, obs):
        return MLP(self.hidden, 1, "tanh", out_scale=1.0)(obs)[..., 0]


class DynamicsModel(nn.Module):
    """(normalised obs [..., O], action [..., A]) -> Gaussian over the normalised (delta-s, reward).

    Returns (mean [..., O+1], log_std [..., O+1]); the last entry is the reward.
    """

    obs_size: int
    hidden: Sequence[int]

    @nn.compact
    def __call__(self, obs, action):
        x = jnp.concatenate([obs, action], axis=-1)
        for w in self.hidden:
            x = nn.relu(nn.Dense(w)(x))
        mean = nn.Dense(self.obs_size + 1)(x)
        raw = nn.Dense(self.obs_size + 1)(x)
        log_std = MODEL_LOG_STD_MIN + 0.5 * (MODEL_LOG_STD_MAX - MODEL_LOG_STD_MIN) * (jnp.tanh(raw) + 1.0)
        return mean, log_std


class Encoder(nn.Module):
    """One GRU step: (h [..., H], x [..., O]) -> h'. Scanned over a sequence by the caller."""

    features: int

    @nn.compact
    def __call__(self, h, x):
        h, _ = nn.GRUCell(self.features)(h, x)
        return h


def build(config, obs_size: int, action_size: int) -> dict[str, nn.Module]:
    """The modules an arm of `config` uses, by parameter-group name."""
    modules = {
        "policy": Policy(action_size, tuple(config.policy_hidden)),
        "value": Value(tuple(config.value_hidden)),
    }
    if config.use_model:
        modules["model"] = DynamicsModel(obs_size, tuple(config.model_hidden))
    if config.use_consistency and config.encoder != "l2":
        modules["encoder"] = Encoder(config.encoder_dim)
    return modules


def init_params(modules: dict[str, nn.Module], key: jax.Array, obs_size: int, action_size: int,
                init_log_std) -> dict:
    keys = dict(zip(modules, jax.random.split(key, len(modules))))
    obs = jnp.zeros((1, obs_size), jnp.float32)
    act = jnp.zeros((1, action_size), jnp.float32)
    params = {}
    for name, module in modules.items():
        if name == "model":
            params[name] = module.init(keys[name], obs, act)
        elif name == "encoder":
            params[name] = module.init(keys[name], jnp.zeros((1, module.features), jnp.float32), obs)
        else:
            params[name] = module.init(keys[name], obs)
    log_std = params["policy"]["params"]["log_std"]
    params["policy"]["params"]["log_std"] = jnp.full_like(log_std, init_log_std)
    return params
