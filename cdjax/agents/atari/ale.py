"""The real Atari games through ale-py's vector environment and its XLA interface (optional extra `atari`, GPL-2.0).

`AleEnv(config, num_envs, episodic_life)` has the interface of `cdjax.agents.atari.minatar.MinAtarEnv`: `reset(key)`,
`step(state, actions) -> (state, AleStep)`, `episode_length`, `obs_shape`, `num_actions`. Its step and reset are
ale-py's XLA custom calls (`AtariVectorEnv.xla()`): they run inside `jit` and `lax.scan`, but the emulators live
in C++ outside JAX, so:

- one run per process: a sweep of ALE games takes `--seeds 1` (a vmap over more runs is refused in one sentence);
- a checkpoint cannot hold the emulators: a resumed run starts fresh games (the env state and the running
  episode returns come from init), so an ALE resume continues training but is not bit-identical.

Preprocessing (ale-py's, the standard one of Mnih et al. 2015 / Machado et al. 2018): frame skip `frame_skip`
(4) with max-pooling of the last two frames, 84x84 grey, a stack of 4 frames, up to 30 no-op starts, FIRE at
reset where the game needs it, sticky actions with probability `sticky_prob` (ALE v5's 0.25 in the presets),
the minimal action set, a time-out after `episode_length` agent steps (a truncation). Rewards are the raw
scores (the learner clips them for learning; the reported returns are raw). Episodic life (training only): a
lost life is a termination for learning, while the game goes on and the reported return is the whole game's;
the game's own end is `game_over`.

ale-py resets a finished game on the step after its end (its NEXT_STEP autoreset): that step's transition,
from the last frame to a new game's first, is marked `valid=False` (masked out of every loss, as a non-finite
transition of the MinAtar tier) and the policy then acts on the new game.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import struct

from cdjax.protocol import ConfigError

GAMES = {"ale-breakout": "breakout", "ale-seaquest": "seaquest", "ale-mspacman": "ms_pacman",
         "ale-frostbite": "frostbite", "ale-pong": "pong", "ale-spaceinvaders": "space_invaders"}
INSTALL = "The ALE games need the optional extra `atari` (ale-py, GPL-2.0): pip install -e \".[atari]\"."
ONE_RUN = "ALE games run one seed per process (their emulators live outside JAX): use --seeds 1 and one value per hyper-parameter."


@struct.dataclass
class AleState:
    handle: jax.Array  # [8] uint8: ale-py's vector env handle (threads the custom calls' order)
    obs: jax.Array  # [B, 84, 84, 4] uint8: what the policy acts on
    lives: jax.Array  # [B] int32 lives left
    pending_reset: jax.Array  # [B] bool: the game ended on the last step; ale-py resets it on this one
    key: jax.Array


@struct.dataclass
class AleStep:
    """cdjax.envs.Step's fields, plus the game's own end (episodic life ends learning episodes at lost lives)."""

    next_obs: jax.Array  # [B, 84, 84, 4] uint8
    reward: jax.Array  # [B] float32 raw score
    terminated: jax.Array  # [B] bool: game over, or (episodic life) a lost life
    truncated: jax.Array  # [B] bool: time-out
    valid: jax.Array  # [B] bool: False for ale-py's reset step
    game_over: jax.Array  # [B] bool: the game itself ended (terminated or timed out)


def _one_run(fn):
    """fn under vmap over one run is fn on the run; over more, refused (the emulators cannot be batched)."""
    wrapped = jax.custom_batching.custom_vmap(fn)

    @wrapped.def_vmap
    def rule(axis_size, in_batched, *args):
        if axis_size != 1:
            raise ConfigError(ONE_RUN)
        args = [jax.tree.map(lambda x: x[0], a) if b else a for a, b in zip(args, in_batched)]
        out = wrapped(*args)
        return jax.tree.map(lambda x: x[None], out), jax.tree.map(lambda _: True, out)

    return wrapped


class AleEnv:
    """`num_envs` games of ale-py's vector environment, stepped by XLA custom calls. Not a pytree."""

    def __init__(self, config, num_envs: int, episodic_life: bool = True):
        try:
            from ale_py.vector_env import AtariVectorEnv
        except ImportError:
            raise ConfigError(INSTALL) from None
        if config.env not in GAMES:
            raise ConfigError(f"Unknown ALE game {config.env!r}; choose one of {', '.join(GAMES)}.")
        self.num_envs, self.episode_length, self.episodic_life = num_envs, config.episode_length, episodic_life
        self.vector = vector_env(AtariVectorEnv, config, num_envs)
        self.handle, xla_reset, xla_step = self.vector.xla()
        self._reset = _one_run(lambda handle, seeds: xla_reset(handle, seeds))
        self._step = _one_run(xla_step)
        self.obs_shape = (84, 84, 4)
        self.num_actions = int(self.vector.single_action_space.n)

    @staticmethod
    def _frames(obs: jax.Array) -> jax.Array:
        return jnp.moveaxis(obs, 1, -1)  # ale-py's [B, 4, 84, 84] -> [B, 84, 84, 4]

    def reset(self, key: jax.Array) -> AleState:
        """New games, seeded from `key` (the same key gives the same games)."""
        key_seeds, key_next = jax.random.split(key)
        seeds = jax.random.randint(key_seeds, (self.num_envs,), 0, 2**31 - 1, jnp.int32)
        handle, (obs, info) = self._reset(self.handle, seeds)
        return AleState(handle=handle, obs=self._frames(obs), lives=info["lives"].astype(jnp.int32),
                        pending_reset=jnp.zeros((self.num_envs,), bool), key=key_next)

    def step(self, state: AleState, action: jax.Array) -> tuple[AleState, AleStep]:
        assert action.shape == (self.num_envs,), action.shape
        handle, (obs, reward, term, trunc, info) = self._step(state.handle, action.astype(jnp.int32))
        obs, lives = self._frames(obs), info["lives"].astype(jnp.int32)
        valid = ~state.pending_reset
        game_end = term & valid
        truncated = trunc & valid & ~game_end
        life_lost = valid & (lives < state.lives) & ~game_end
        terminated = game_end | (life_lost if self.episodic_life else False)
        out = AleStep(next_obs=obs, reward=jnp.where(valid, reward.astype(jnp.float32), 0.0), terminated=terminated,
                      truncated=truncated & ~terminated, valid=valid, game_over=game_end | truncated)
        return AleState(handle=handle, obs=obs, lives=lives, pending_reset=(term | trunc) & valid,
                        key=state.key), out


def vector_env(vector_type, config, num_envs: int):
    """ale-py's vector env (`vector_type`: ale_py.vector_env.AtariVectorEnv) with this module's preprocessing; its
    own Python-side reset(seed=...) and step(actions) step the same games as `AleEnv` does inside XLA."""
    return vector_type(
        GAMES[config.env], num_envs, frameskip=config.frame_skip, maxpool=True, stack_num=4, img_height=84,
        img_width=84, grayscale=True, noop_max=30, use_fire_reset=True, episodic_life=False, reward_clipping=False,
        repeat_action_probability=config.sticky_prob, max_num_frames_per_episode=config.episode_length * config.frame_skip)
