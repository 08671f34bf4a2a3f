"""The Atari setting's networks: an actor-critic on a conv torso, and a dynamics model in the torso's latent space.

- `MinAtarTorso`: the network of the MinAtar paper (Young & Tian 2019): one 3x3 convolution of 16 channels
  (stride 1, ReLU) and a dense layer of 128 (ReLU) on the 10x10xC boolean frame.
- `NatureTorso`: the Nature-DQN CNN (Mnih et al. 2015) used by A2C on the real games: 32 8x8/4, 64 4x4/2,
  64 3x3/1 convolutions and a dense layer of 512, on 84x84x4 grey frames (uint8, scaled by 1/255).
- `ActorCritic`: torso -> latent z; logits and value are linear heads of z. Orthogonal initialisation
  (gain sqrt 2 in the torso, 0.01 for the logits, 1 for the value), as OpenAI baselines' A2C.
- `LatentModel`: z, one-hot action -> (z', reward): an MLP predicting the change of z and the reward.
"""

from __future__ import annotations

import math
from typing import Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp

from cdjax.numerics import orthogonal

ORTHO = orthogonal  # flax's, drawn one run at a time under vmap (cdjax.numerics.orthogonal)


class MinAtarTorso(nn.Module):
    channels: int = 16  # convolution channels
    latent: int = 128  # output size

    @nn.compact
    def __call__(self, obs):
        x = nn.relu(nn.Conv(self.channels, (3, 3), padding="VALID", kernel_init=ORTHO(math.sqrt(2)))(obs))
        x = x.reshape(x.shape[:-3] + (-1,))
        return nn.relu(nn.Dense(self.latent, kernel_init=ORTHO(math.sqrt(2)))(x))


class NatureTorso(nn.Module):
    latent: int = 512  # output size

    @nn.compact
    def __call__(self, obs):
        x = obs.astype(jnp.float32) / 255.0
        for channels, kernel, stride in ((32, 8, 4), (64, 4, 2), (64, 3, 1)):
            x = nn.relu(nn.Conv(channels, (kernel, kernel), (stride, stride), padding="VALID",
                                kernel_init=ORTHO(math.sqrt(2)))(x))
        x = x.reshape(x.shape[:-3] + (-1,))
        return nn.relu(nn.Dense(self.latent, kernel_init=ORTHO(math.sqrt(2)))(x))


class ActorCritic(nn.Module):
    """obs [..., H, W, C] -> (logits [..., A], value [...], latent z [..., D]); `heads(z)` -> (logits, value)."""

    num_actions: int
    torso: nn.Module

    def setup(self):
        self.logits = nn.Dense(self.num_actions, kernel_init=ORTHO(0.01))
        self.value = nn.Dense(1, kernel_init=ORTHO(1.0))

    def __call__(self, obs):
        z = self.torso(obs)
        return self.heads(z) + (z,)

    def heads(self, z):
        return self.logits(z), self.value(z)[..., 0]


class LatentModel(nn.Module):
    """(z [..., D], action one-hot [..., A]) -> (z' [..., D], reward [...]): z' = z + MLP(z, a)[:D]."""

    latent: int
    hidden: Sequence[int] = (256, 256)

    @nn.compact
    def __call__(self, z, action):
        x = jnp.concatenate([z, action], axis=-1)
        for width in self.hidden:  # the obs setting's model has the same ReLU torso; the heads differ (a residual here)
            x = nn.relu(nn.Dense(width)(x))
        out = nn.Dense(self.latent + 1)(x)
        return z + out[..., :-1], out[..., -1]


def torso_of(config) -> nn.Module:
    """The conv torso an env of `config` uses: MinAtar's small net, or the Nature CNN for the ALE games."""
    if config.is_ale:
        return NatureTorso(config.latent)
    return MinAtarTorso(config.conv_channels, config.latent)


def entropy(logits: jax.Array) -> jax.Array:
    """Entropy of the categorical distribution of `logits` [..., A]."""
    logp = jax.nn.log_softmax(logits)
    return -(jnp.exp(logp) * logp).sum(-1)
