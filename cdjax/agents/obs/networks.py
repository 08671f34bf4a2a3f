"""Flax modules of the observation-space agent (policy, value, dynamics model) and the action distribution;
the sequence encoder is the consistency term's (`cdjax.consistency.SequenceEncoder`).

All modules take normalised inputs. Actions live in [-1, 1]: the policy is a diagonal Gaussian over
the pre-squash action u, and the executed action is tanh(u). `action_distribution` is the one place
that builds that distribution; `squashed_entropy` the one place that estimates its entropy after tanh.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp

from cdjax.agents.obs.config import Config
from cdjax.consistency import SequenceEncoder, init_encoder
from cdjax.numerics import orthogonal

if TYPE_CHECKING:
    import distrax

MODEL_LOG_STD_MIN = -6.0  # bounds of the dynamics model's predicted log standard deviation
MODEL_LOG_STD_MAX = 1.0
MIN_POLICY_STD = 1e-3  # floor of the state-dependent policy standard deviation (softplus(x) + floor)
Dense = nn.Dense  # the dense layer of the agent's MLPs (policy, value, dynamics model)


def action_distribution(mean: jax.Array, std: jax.Array) -> distrax.MultivariateNormalDiag:
    """Diagonal Gaussian over the pre-squash action u; the executed action is squash(u). distrax (with TensorFlow
    Probability, most of a second to import) is imported here, at the first trace that needs it, not with cdjax."""
    import distrax

    return distrax.MultivariateNormalDiag(mean, std * jnp.ones_like(mean))


def squash(u: jax.Array) -> jax.Array:
    return jnp.tanh(u)


def squash_log_det(u: jax.Array) -> jax.Array:
    """log |d tanh(u) / du| summed over the last axis, in a form that stays finite for large |u|."""
    return (2.0 * (jnp.log(2.0) - u - jax.nn.softplus(-2.0 * u))).sum(-1)


def squashed_entropy(mean: jax.Array, std: jax.Array, noise: jax.Array) -> jax.Array:
    """One-sample estimate of the entropy of the squashed action tanh(u), u ~ N(mean, std).

    H[tanh(u)] = H[u] + E[log |d tanh/du|]; the expectation is estimated at u = mean + std * noise
    (reparameterised, so it is differentiable in mean and std). Unlike the Gaussian entropy alone, it
    falls when the policy saturates the action box, so an entropy bonus does not reward that.
    """
    gaussian = action_distribution(mean, std).entropy()
    return gaussian + squash_log_det(mean + std * noise)


def act_from_noise(mean: jax.Array, std: jax.Array, noise: jax.Array) -> jax.Array:
    """The action a = squash(mean + std * noise): differentiable in the policy's outputs."""
    return squash(mean + std * noise)


class MLP(nn.Module):
    widths: Sequence[int]
    out: int
    activation: str = "swish"  # any flax.linen activation name (swish, tanh, relu, ...)
    out_scale: float = 1.0  # the last layer's initial weights: orthogonal's gain, or the factor on lecun-uniform's
    weight_init: str = Config.weight_init  # lecun-uniform (Brax); orthogonal: gain sqrt(2) hidden, out_scale last

    @nn.compact
    def __call__(self, x):
        act = getattr(nn, self.activation)
        if self.weight_init == "lecun":  # variance_scaling(1, fan_in, uniform) is lecun-uniform itself
            hidden = nn.initializers.lecun_uniform()
            last = nn.initializers.variance_scaling(self.out_scale ** 2, "fan_in", "uniform")
        else:
            hidden, last = orthogonal(jnp.sqrt(2.0)), orthogonal(self.out_scale)
        for w in self.widths:
            x = act(Dense(w, kernel_init=hidden)(x))
        return Dense(self.out, kernel_init=last)(x)


class Policy(nn.Module):
    """obs [..., O] -> (mean [..., A], std [..., A] or [A]).

    std_mode "state": std = softplus(head(obs)) + MIN_POLICY_STD, a second head of the last layer (as
    Brax's PPO); "global": std = exp(log_std), one parameter per action dimension, independent of the
    state. `set_initial_std` sets the initial std in either mode (through the head's bias or log_std).
    """

    action_size: int
    hidden: Sequence[int]
    activation: str = "swish"
    std_mode: str = "state"
    weight_init: str = Config.weight_init  # Config's default, so that a module built alone is the agent's
    head_scale: float = Config.policy_head_scale  # lecun: the last layer's initial weights x this (orthogonal: gain 0.01)

    @nn.compact
    def __call__(self, obs):
        A = self.action_size
        scale = self.head_scale if self.weight_init == "lecun" else 0.01
        if self.std_mode == "state":
            out = MLP(self.hidden, 2 * A, self.activation, out_scale=scale, weight_init=self.weight_init)(obs)
            return out[..., :A], jax.nn.softplus(out[..., A:]) + MIN_POLICY_STD
        mean = MLP(self.hidden, A, self.activation, out_scale=scale, weight_init=self.weight_init)(obs)
        log_std = self.param("log_std", nn.initializers.zeros, (A,))
        return mean, jnp.exp(log_std) * jnp.ones_like(mean)


class Value(nn.Module):
    """obs [..., O] -> value [...]."""

    hidden: Sequence[int]
    activation: str = "swish"
    weight_init: str = Config.weight_init  # Config's default, so that a module built alone is the agent's

    @nn.compact
    def __call__(self, obs):
        return MLP(self.hidden, 1, self.activation, out_scale=1.0, weight_init=self.weight_init)(obs)[..., 0]


class DynamicsModel(nn.Module):
    """(normalised obs [..., O], action [..., A]) -> Gaussian over the normalised (delta-s, reward).

    Returns (mean [..., O+1], log_std [..., O+1]); the last entry is the reward.
    """

    obs_size: int
    hidden: Sequence[int]

    @nn.compact
    def __call__(self, obs, action):
        x = jnp.concatenate([obs, action], axis=-1)
        for w in self.hidden:  # the same ReLU torso as the Atari latent model's; the heads differ (a Gaussian here)
            x = nn.relu(Dense(w)(x))
        mean = Dense(self.obs_size + 1)(x)
        raw = Dense(self.obs_size + 1)(x)
        log_std = MODEL_LOG_STD_MIN + 0.5 * (MODEL_LOG_STD_MAX - MODEL_LOG_STD_MIN) * (jnp.tanh(raw) + 1.0)
        return mean, log_std


def build(config, obs_size: int, action_size: int) -> dict[str, nn.Module]:
    """The modules an arm of `config` uses, by parameter-group name."""
    modules = {
        "policy": Policy(action_size, tuple(config.policy_hidden), config.activation, config.policy_std, config.weight_init,
                         config.policy_head_scale),
        "value": Value(tuple(config.value_hidden), config.activation, config.weight_init),
    }
    if config.use_model:
        modules["model"] = DynamicsModel(obs_size, tuple(config.model_hidden))
    if config.use_consistency and config.encoder != "l2":
        window = config.horizon * obs_size if config.encoder == "grounded-gru" else 0
        modules["encoder"] = SequenceEncoder(config.encoder_dim, window)
    return modules


def init_params(modules: dict[str, nn.Module], key: jax.Array, obs_size: int, action_size: int,
                init_log_std) -> dict:
    """Parameters of every module; the policy's initial standard deviation is exp(init_log_std)."""
    keys = dict(zip(modules, jax.random.split(key, len(modules))))
    obs = jnp.zeros((1, obs_size), jnp.float32)
    act = jnp.zeros((1, action_size), jnp.float32)
    params = {}
    for name, module in modules.items():
        if name == "model":
            params[name] = module.init(keys[name], obs, act)
        elif name == "encoder":
            params[name] = init_encoder(module, keys[name], obs_size)
        else:
            params[name] = module.init(keys[name], obs)
    params["policy"] = set_initial_std(modules["policy"], params["policy"], init_log_std)
    return params


def set_initial_std(policy: Policy, params: dict, init_log_std) -> dict:
    """The policy's parameters with its initial standard deviation set to exp(init_log_std) (traced)."""
    p = params["params"]
    if policy.std_mode == "global":
        p = dict(p, log_std=jnp.full_like(p["log_std"], init_log_std))
        return {"params": p}
    # state: the std head's bias b with softplus(b) + floor = exp(init_log_std): the std in every state when the
    # head's weights start near 0 (orthogonal init; lecun's x0.1, nearly), the std where the features are 0 with lecun's
    # own head (as Brax).
    A = policy.action_size
    target = jnp.maximum(jnp.exp(init_log_std) - MIN_POLICY_STD, 1e-6)
    bias = target + jnp.log(-jnp.expm1(-target))  # softplus^-1, stable for small and large targets
    mlp = dict(p["MLP_0"])
    last = f"Dense_{len(policy.hidden)}"
    layer = dict(mlp[last])
    layer["bias"] = layer["bias"].at[A:].set(bias)
    mlp[last] = layer
    return {"params": dict(p, MLP_0=mlp)}
