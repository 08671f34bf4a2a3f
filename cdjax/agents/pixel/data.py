"""Expert trajectories rendered inside jit, and the environment that evaluates the imitation policy from pixels.

`PixelWorld(config, act)` holds the MJX task, its renderer (cdjax.envs.pixels) and the expert's act function.

    world.generate(key, n, length) -> Dataset   # n sequences: frames [n, length+F-1, S, S, 3] uint8, actions
    world.eval_env(num_envs)                    # episodes of the imitation policy acting from pixels

A sequence starts `burn_in` unrendered expert steps after a reset (the cheetah is running by then); its
frames and the expert's actions follow (see cdjax.agents.pixel.model for the time indexing). The frames are
uint8 to keep the dataset small (N sequences x (L+3) frames x S*S*3 bytes: 512 x 53 x 12 KB = 333 MB at 64x64).
"""

from __future__ import annotations

from typing import Any, Callable

import jax
import jax.numpy as jnp
from flax import struct

from cdjax.envs import Step, physics as batched_physics, pixels, shared_env


@struct.dataclass
class Dataset:
    frames: jax.Array  # [N, L+F-1, S, S, 3] uint8
    actions: jax.Array  # [N, L, A] float32, a_t after observation t
    reward: jax.Array  # [] mean expert reward per step over the recorded steps


@struct.dataclass
class EvalState:
    core: Any  # the task's batched state
    obs: dict  # what the imitation agent reads: frames [B, F, S, S, 3] uint8, h, c [B, H], a [B, A] (previous action)
    t: jax.Array  # [B] int32 steps taken


def to_uint8(frame: jax.Array) -> jax.Array:
    return jnp.round(frame * 255.0).astype(jnp.uint8)


class PixelWorld:
    """The task of a pixel Config, its renderer and the expert acting in it. Not a pytree: close over it."""

    def __init__(self, config, expert_act: Callable[[jax.Array, jax.Array | None], jax.Array], action_repeat: int = 1):
        """action_repeat: physics steps per agent step (the expert's, e.g. 4 for Brax's reacher settings)."""
        self.config, self.action_repeat = config, action_repeat
        self.env = shared_env(config.env)
        self._reset_many, self._step_many = batched_physics(self.env)  # traced once per process (envs.physics)
        self.renderer = pixels.make_renderer(self.env.sys.mj_model, pixels.camera_for(config.env), config.image_size)
        self.expert_act = expert_act
        self.action_size = int(self.env.action_size)

    def frame(self, core) -> jax.Array:
        """[B] states -> [B, S, S, 3] uint8 frames."""
        return to_uint8(jax.vmap(self.renderer.render)(core.pipeline_state))

    def reset(self, key: jax.Array, n: int):
        """n fresh episodes: the task's batched state (with .obs, .reward, .done)."""
        return self._reset_many(jax.random.split(key, n))

    def step(self, core, action: jax.Array):
        """One agent step: the action held for `action_repeat` physics steps; .reward is their sum."""
        def physics(carry, _):
            core, reward = carry
            core = self._step_many(core, action)
            return (core, reward + core.reward.astype(jnp.float32)), None

        if self.action_repeat == 1:
            return self._step_many(core, action)
        zeros = jnp.zeros(action.shape[:1], jnp.float32)
        (core, reward), _ = jax.lax.scan(physics, (core, zeros), None, length=self.action_repeat)  # one compiled step
        return core.replace(reward=reward)

    def generate(self, key: jax.Array, n: int, length: int) -> Dataset:
        """n expert sequences of `length` observations (length + F - 1 frames) after `burn_in` steps.

        One scan over burn_in + length + F - 1 expert steps (one compiled physics step: MJX compiles slowly);
        frames are rendered only after the burn-in (a cond on the step index, which is the same for every
        env) and written into a buffer carried by the scan."""
        c = self.config
        steps = length + c.frame_stack - 1
        key_reset, key_steps = jax.random.split(key)
        del key
        core = self.reset(key_reset, n)
        S = c.image_size
        buffers = (jnp.zeros((steps, n, S, S, 3), jnp.uint8), jnp.zeros((steps, n, self.action_size), jnp.float32),
                   jnp.zeros((), jnp.float32))

        def body(carry, inp):
            core, (frames, actions, reward) = carry
            i, step_key = inp
            j = jnp.maximum(i - c.burn_in, 0)
            recording = i >= c.burn_in
            frame = jax.lax.cond(recording, self.frame, lambda _: frames[0], core)
            action = self.expert_act(core.obs.astype(jnp.float32), step_key if c.expert_sample else None)
            core = self.step(core, action)
            frames = jax.lax.dynamic_update_index_in_dim(frames, frame, j, 0)
            actions = jax.lax.dynamic_update_index_in_dim(actions, action, j, 0)
            reward = reward + jnp.where(recording, core.reward.astype(jnp.float32).mean(), 0.0)
            return (core, (frames, actions, reward)), None

        total = c.burn_in + steps
        (_, (frames, actions, reward)), _ = jax.lax.scan(
            body, (core, buffers), (jnp.arange(total), jax.random.split(key_steps, total)))
        return Dataset(frames=jnp.swapaxes(frames, 0, 1), actions=jnp.swapaxes(actions[c.frame_stack - 1:], 0, 1),
                       reward=reward / steps)

    def eval_env(self, num_envs: int) -> "PixelEvalEnv":
        return PixelEvalEnv(self, num_envs)


class PixelEvalEnv:
    """Episodes of a recurrent agent acting from frames, in cdjax.envs.BatchedEnv's interface.

    The agent's memory travels in the observation: `obs` holds the last F frames and the agent's LSTM state
    and previous action; the agent returns [action, h', c'] (`act` of the pixel setting) and `step` keeps
    h', c' and the action for the next step. Episodes end at the time-out `episode_length` (agent steps);
    the first observation repeats the reset frame F times.
    """

    action_repeat = 1

    def __init__(self, world, num_envs: int):
        """world: a PixelWorld, or anything with its config, action_size, reset, step and frame."""
        self.world, self.num_envs = world, num_envs
        self.episode_length = world.config.eval_episode_length
        self.hidden, self.A = world.config.hidden, world.action_size

    def reset(self, key: jax.Array) -> EvalState:
        core = self.world.reset(key, self.num_envs)
        frame = self.world.frame(core)
        zeros = jnp.zeros((self.num_envs, self.hidden), jnp.float32)
        obs = {"frames": jnp.repeat(frame[:, None], self.world.config.frame_stack, axis=1), "h": zeros, "c": zeros,
               "a": jnp.zeros((self.num_envs, self.A), jnp.float32)}
        return EvalState(core=core, obs=obs, t=jnp.zeros((self.num_envs,), jnp.int32))

    def step(self, state: EvalState, agent_out: jax.Array) -> tuple[EvalState, Step]:
        A, H = self.A, self.hidden
        assert agent_out.shape == (self.num_envs, A + 2 * H), agent_out.shape
        action = agent_out[:, :A]
        core = self.world.step(state.core, action)
        frames = jnp.concatenate([state.obs["frames"][:, 1:], self.world.frame(core)[:, None]], axis=1)
        obs = {"frames": frames, "h": agent_out[:, A:A + H], "c": agent_out[:, A + H:], "a": action}
        reward = core.reward.astype(jnp.float32)
        valid = jnp.isfinite(reward) & jnp.isfinite(core.obs).all(-1)
        t = state.t + 1
        terminated = (core.done > 0.5) & valid
        truncated = (t >= self.episode_length) & ~terminated & valid
        step = Step(next_obs=obs, reward=jnp.where(valid, reward, 0.0), terminated=terminated, truncated=truncated,
                    valid=valid)
        return EvalState(core=core, obs=obs, t=t), step
