"""A stand-in for the rendered task (PixelWorld's interface, no physics): fast to compile, for tests and for
measuring the update's speed without MJX.

`generate` gives frames of noise dimmed by a random brightness per frame and expert actions that are a fixed
function of the newest frame's brightness (imitation is learnable); the evaluation episodes play a scene whose
brightness follows the action (reward: closeness of the action to 0.5).

    learner = PixelLearner(config, world=SyntheticWorld(config))
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import struct

from cdjax.agents.pixel.data import Dataset, PixelEvalEnv


@struct.dataclass
class Core:
    obs: jax.Array  # [B, 1] brightness of the scene
    reward: jax.Array  # [B]
    done: jax.Array  # [B]


class SyntheticWorld:
    """PixelWorld's interface (generate, reset, step, frame, eval_env) on synthetic frames."""

    def __init__(self, config, action_size: int = 2):
        """action_size: the expert's actions (at least 2; the render tasks have 2 to 7)."""
        self.config, self.action_size = config, action_size

    def reset(self, key, n):
        obs = jax.random.uniform(key, (n, 1))
        return Core(obs, jnp.zeros((n,), jnp.float32), jnp.zeros((n,), jnp.float32))

    def step(self, core, action):
        obs = jnp.clip(0.8 * core.obs + 0.2 * (action[:, :1] + 1) / 2, 0.0, 1.0)
        return Core(obs, -jnp.abs(action[:, 0] - 0.5), jnp.zeros_like(core.done))

    def frame(self, core):
        S = self.config.image_size
        return jnp.broadcast_to(jnp.round(255 * core.obs)[:, :, None, None],
                                (core.obs.shape[0], S, S, 3)).astype(jnp.uint8)

    def eval_env(self, num_envs):
        return PixelEvalEnv(self, num_envs)

    def generate(self, key, n, length):
        """n sequences: frames of noise dimmed by a random brightness per frame; the expert's action is a function
        of the newest frame's brightness."""
        S, F = self.config.image_size, self.config.frame_stack
        key_noise, key_brightness = jax.random.split(key)
        brightness = jax.random.uniform(key_brightness, (n, length + F - 1))
        noise = jax.random.uniform(key_noise, (n, length + F - 1, S, S, 3))
        frames = jnp.round(255 * noise * brightness[..., None, None, None]).astype(jnp.uint8)
        b = brightness[:, F - 1:]
        actions = 0.9 * jnp.stack([2 * b - 1, jnp.cos(6 * b)] + [b * 0] * (self.action_size - 2), -1)
        return Dataset(frames=frames, actions=actions, reward=jnp.zeros((), jnp.float32))
