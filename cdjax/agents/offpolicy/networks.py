"""The off-policy setting's networks (flax.linen): a tanh-squashed Gaussian actor, an ensemble of Q functions with
LayerNorm, and the latent model (encoder, latent transition, reward head, observation decoder)."""

from __future__ import annotations

import flax.linen as nn
import jax
import jax.numpy as jnp

LOG_STD_MIN, LOG_STD_MAX = -5.0, 2.0  # the actor's log standard deviation (pre-squash) is squashed into this range


class MLP(nn.Module):
    hidden: tuple[int, ...]
    out: int
    layer_norm: bool = False

    @nn.compact
    def __call__(self, x):
        for width in self.hidden:
            x = nn.Dense(width)(x)
            if self.layer_norm:
                x = nn.LayerNorm()(x)
            x = nn.relu(x)
        return nn.Dense(self.out)(x)


class Actor(nn.Module):
    """x -> (mean, log_std) of the pre-squash Gaussian over actions."""

    hidden: tuple[int, ...]
    action_size: int

    @nn.compact
    def __call__(self, x):
        out = MLP(self.hidden, 2 * self.action_size)(x)
        mean, raw = jnp.split(out, 2, axis=-1)
        log_std = LOG_STD_MIN + 0.5 * (LOG_STD_MAX - LOG_STD_MIN) * (jnp.tanh(raw) + 1.0)
        return mean, log_std


class Critic(nn.Module):
    """(x, a) -> Q [...]; one member of the ensemble (the ensemble is this module's parameters stacked)."""

    hidden: tuple[int, ...]
    layer_norm: bool = True

    @nn.compact
    def __call__(self, x, a):
        return MLP(self.hidden, 1, self.layer_norm)(jnp.concatenate([x, a], axis=-1))[..., 0]


class Encoder(nn.Module):
    """Normalised observation -> latent, LayerNorm-ed (a bounded scale, which the latent losses cannot shrink away)."""

    hidden: tuple[int, ...]
    latent_dim: int

    @nn.compact
    def __call__(self, obs):
        return nn.LayerNorm()(MLP(self.hidden, self.latent_dim, True)(obs))


class LatentModel(nn.Module):
    """The latent dynamics: transition (z, a) -> z', reward (z, a) -> r, decoder z -> normalised observation."""

    hidden: tuple[int, ...]
    latent_dim: int
    obs_size: int
    layer_norm: bool = True

    def setup(self):
        self.transition_net = MLP(self.hidden, self.latent_dim, self.layer_norm)
        self.reward_net = MLP(self.hidden, 1, self.layer_norm)
        self.decoder = MLP(self.hidden, self.obs_size, self.layer_norm)
        self.norm = nn.LayerNorm()

    def transition(self, z, a):
        """The next latent, LayerNorm-ed like the encoder's."""
        return self.norm(self.transition_net(jnp.concatenate([z, a], axis=-1)))

    def reward(self, z, a):
        return self.reward_net(jnp.concatenate([z, a], axis=-1))[..., 0]

    def decode(self, z):
        return self.decoder(z)

    def __call__(self, z, a):
        z_next = self.transition(z, a)
        return z_next, self.reward(z, a), self.decode(z_next)


def sample_action(mean, log_std, key):
    """A reparameterised tanh-squashed Gaussian sample and its log-density -> (action [..., A], log_prob [...])."""
    std = jnp.exp(log_std)
    u = mean + std * jax.random.normal(key, mean.shape)
    log_prob = (-0.5 * ((u - mean) / std) ** 2 - log_std - 0.5 * jnp.log(2 * jnp.pi)).sum(-1)
    log_prob -= (2 * (jnp.log(2.0) - u - jax.nn.softplus(-2 * u))).sum(-1)  # log |d tanh(u) / du|, stably
    return jnp.tanh(u), log_prob


class Nets:
    """The modules of one Config, with the functions the losses and the acting call. Not a pytree: close over it."""

    def __init__(self, config, obs_size: int, action_size: int):
        from cdjax.consistency import SequenceEncoder  # the paper's GRU encoder (paper-cd)

        self.config, self.obs_size, self.action_size = config, obs_size, action_size
        self.feature_size = {"latent": config.latent_dim, "obs": obs_size,
                             "obs+latent": obs_size + config.latent_dim}[config.inputs]
        self.actor = Actor(config.actor_hidden, action_size)
        self.critic = Critic(config.critic_hidden, config.layer_norm)
        self.encoder = Encoder(config.encoder_hidden, config.latent_dim) if config.use_encoder else None
        self.model = (LatentModel(config.model_hidden, config.latent_dim, obs_size, config.layer_norm)
                      if config.use_model else None)
        window = config.horizon * obs_size if config.cc_encoder == "grounded-gru" else 0
        self.cc_encoder = (SequenceEncoder(config.cc_dim, window)
                           if config.arm == "paper-cd" and config.cc_encoder != "l2" else None)

    def init(self, key: jax.Array) -> dict:
        """Every parameter group: actor, critic (the ensemble stacked on a leading axis), encoder ({} without a
        latent), log_alpha (filled in by the caller), and model and cc_encoder where the arm has them."""
        from cdjax.consistency import init_encoder

        keys = jax.random.split(key, 5)
        x = jnp.zeros((1, self.feature_size), jnp.float32)
        a = jnp.zeros((1, self.action_size), jnp.float32)
        params = {
            "actor": self.actor.init(keys[0], x),
            "critic": jax.vmap(lambda k: self.critic.init(k, x, a))(jax.random.split(keys[1],
                                                                                    self.config.num_critics)),
            "encoder": self.encoder.init(keys[2], jnp.zeros((1, self.obs_size))) if self.encoder else {},
            "log_alpha": jnp.zeros((), jnp.float32),
        }
        if self.model is not None:
            params["model"] = self.model.init(keys[3], jnp.zeros((1, self.config.latent_dim)), a)
        if self.cc_encoder is not None:
            params["cc_encoder"] = init_encoder(self.cc_encoder, keys[4], self.obs_size)
        return params

    def encode(self, encoder_params, obs_normalised):
        """The encoder's latent (None without an encoder)."""
        return self.encoder.apply(encoder_params, obs_normalised) if self.encoder else None

    def inputs(self, obs_normalised, z):
        """What the actor and critic read (Config.inputs), from the normalised observation and its latent z."""
        if self.config.inputs == "latent":
            return z
        if self.config.inputs == "obs":
            return obs_normalised
        return jnp.concatenate([obs_normalised, z], axis=-1)

    def features(self, encoder_params, obs_normalised):
        """What the actor and critic read at these observations (the encoder applied where it is one)."""
        return self.inputs(obs_normalised, self.encode(encoder_params, obs_normalised))

    def sample(self, actor_params, x, key):
        return sample_action(*self.actor.apply(actor_params, x), key)

    def q(self, critic_params, x, a):
        """[C, ...]: every critic of the ensemble."""
        return jax.vmap(lambda p: self.critic.apply(p, x, a))(critic_params)
