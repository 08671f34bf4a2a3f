"""MinAtar games (Young & Tian, 2019) as gymnax implements them, batched and auto-resetting, fully in JAX.

`MinAtarEnv(game, num_envs, episode_length, sticky_prob)` has the interface of `cdjax.envs.BatchedEnv`
that the A2C learner and `cdjax.evaluate` use: `reset(key) -> state` (with `.obs`), `step(state, actions)
-> (state, cdjax.envs.Step)`, `episode_length`, plus `obs_shape` and `num_actions`. Everything is a pure
function of arrays, so it runs inside `jit`, `lax.scan` and `vmap` over the seeds of a sweep.

- Observations are the games' boolean channels as float32 [B, 10, 10, C].
- A game's own end (the ball lost, the submarine hit) is a termination; reaching `episode_length` agent
  steps is a time-out, kept apart as a truncation (the learner bootstraps there). gymnax's own time limit
  is set to the same length, and the wrapper counts the steps itself so that every game truncates alike.
- Sticky actions as in MinAtar (its default 0.1): with probability `sticky_prob` an environment repeats its
  previous action instead of the one chosen (gymnax's MinAtar has none). `sticky_prob=0` turns them off.
- A transition whose observation or reward is not finite (no MinAtar game makes one, but a NaN must not
  reach a loss) is marked `valid=False`, its numbers are zeros and that environment is reset.
- `next_obs` is the observation right after the action, before any reset; `state.obs` is what the policy
  sees next (the first observation of a new episode after an end).
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
from flax import struct

from cdjax.envs import Step

# cdjax game name -> gymnax environment id
GAMES = {
    "breakout": "Breakout-MinAtar",
    "seaquest": "Seaquest-MinAtar",
    "asterix": "Asterix-MinAtar",
    "freeway": "Freeway-MinAtar",
    "space_invaders": "SpaceInvaders-MinAtar",
}


@struct.dataclass
class MinAtarState:
    """Batched state of `MinAtarEnv`; leaves have a leading [B] axis except `key`."""

    core: Any  # gymnax's game state, batched [B]
    obs: jax.Array  # [B, 10, 10, C] float32: what the policy acts on (after any reset)
    t: jax.Array  # [B] int32 agent steps into the current episode
    last_action: jax.Array  # [B] int32 the action executed last (what a sticky action repeats)
    key: jax.Array  # PRNG key for the games' randomness, sticky actions and resets


def _select(mask: jax.Array, a, b):
    """Per-env select over pytrees with a leading [B] axis."""

    def pick(x, y):
        return jnp.where(mask.reshape(mask.shape + (1,) * (x.ndim - 1)), x, y)

    return jax.tree.map(pick, a, b)


def _finite(x: jax.Array) -> jax.Array:
    """[B] True where every entry of x [B, ...] is finite."""
    return jnp.isfinite(x.reshape(x.shape[0], -1)).all(axis=-1)


class MinAtarEnv:
    """`num_envs` auto-resetting copies of one MinAtar game. Not a pytree: close over it."""

    def __init__(self, game: str, num_envs: int, episode_length: int, sticky_prob: float = 0.1):
        import gymnax  # imported here: only the MinAtar tier needs it

        if game not in GAMES:
            raise KeyError(f"unknown MinAtar game {game!r}; choose one of {', '.join(GAMES)}")
        self.game, self.num_envs, self.episode_length = game, num_envs, episode_length
        self.sticky_prob = float(sticky_prob)
        self.env, params = gymnax.make(GAMES[game])
        self.params = params.replace(max_steps_in_episode=episode_length)
        self.obs_shape = tuple(int(n) for n in self.env.obs_shape)
        self.num_actions = int(self.env.num_actions)

    def _reset_all(self, key: jax.Array):
        obs, core = jax.vmap(self.env.reset_env, in_axes=(0, None))(jax.random.split(key, self.num_envs),
                                                                     self.params)
        return obs.astype(jnp.float32), core

    def reset(self, key: jax.Array) -> MinAtarState:
        key_reset, key_next = jax.random.split(key)
        obs, core = self._reset_all(key_reset)
        zeros = jnp.zeros((self.num_envs,), jnp.int32)
        return MinAtarState(core=core, obs=obs, t=zeros, last_action=zeros, key=key_next)

    def step(self, state: MinAtarState, action: jax.Array) -> tuple[MinAtarState, Step]:
        """One agent step of every environment; action [B] int."""
        assert action.shape == (self.num_envs,), action.shape
        key, key_step, key_sticky, key_reset = jax.random.split(state.key, 4)
        action = action.astype(jnp.int32)
        sticky = jax.random.uniform(key_sticky, (self.num_envs,)) < self.sticky_prob
        action = jnp.where(sticky, state.last_action, action)
        keys = jax.random.split(key_step, self.num_envs)
        obs, core, reward, terminated, _ = jax.vmap(self.env.step_env, in_axes=(0, 0, 0, None))(
            keys, state.core, action, self.params)
        obs, reward = obs.astype(jnp.float32), reward.astype(jnp.float32)
        valid = _finite(obs) & jnp.isfinite(reward)
        obs, reward = jnp.where(valid[:, None, None, None], obs, 0.0), jnp.where(valid, reward, 0.0)
        terminated = terminated.astype(bool) & valid
        t = state.t + 1
        truncated = (t >= self.episode_length) & ~terminated & valid
        ended = terminated | truncated | ~valid
        reset_obs, reset_core = self._reset_all(key_reset)
        new_state = MinAtarState(
            core=_select(ended, reset_core, core), obs=jnp.where(ended[:, None, None, None], reset_obs, obs),
            t=jnp.where(ended, 0, t), last_action=jnp.where(ended, 0, action), key=key)
        return new_state, Step(next_obs=obs, reward=reward, terminated=terminated, truncated=truncated, valid=valid)
