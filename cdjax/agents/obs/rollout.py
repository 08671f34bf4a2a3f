"""The two pathways, both `lax.scan`, both returning (final_carry, time-major stack [T, B, ...]).

closed_loop: the policy acts in the (batched) environment and observes the real next states.
open_loop:   a dynamics model step is applied from a start state to a given action sequence, without
             looking at the environment again (the imagined pathway).
"""

from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp
from flax import struct

from cdjax.envs import BatchedEnv, EnvState, EpisodeStats


@struct.dataclass
class Transition:
    """One closed-loop step of B environments; stacked by the scan into [T, B, ...]."""

    obs: jax.Array  # [B, O] observation acted on
    next_obs: jax.Array  # [B, O] true observation after the action (before any reset)
    action: jax.Array  # [B, A] executed (squashed) action
    raw_action: jax.Array  # [B, A] pre-squash action u = mean + std * noise; action = tanh(u)
    noise: jax.Array  # [B, A] standard-normal noise that produced it
    log_prob: jax.Array  # [B] behaviour log-probability of the pre-squash action
    value: jax.Array  # [B] value estimate of obs (closed_loop fills it after the scan, in one batched pass)
    next_value: jax.Array  # [B] value estimate of next_obs, the bootstrap target (filled likewise)
    reward: jax.Array  # [B]
    terminated: jax.Array  # [B] bool
    truncated: jax.Array  # [B] bool (time-out)
    valid: jax.Array  # [B] bool (False: non-finite physics, masked everywhere)

    @property
    def ended(self) -> jax.Array:
        """The episode ended after this step (the next obs in the batch belongs to a new episode)."""
        return self.terminated | self.truncated | ~self.valid


def env_step(env: BatchedEnv, env_state: EnvState, stats: EpisodeStats, action: jax.Array, gamma):
    """One step of every environment, with the episode statistics recorded: (env_state, stats, Step).

    The step shape both the PPO rollout and the Mb-Mf phase's acting loops are made of. Episodes that
    end by a non-finite state are reset but not counted in the returns.
    """
    env_state, out = env.step(env_state, action)
    ended = out.terminated | out.truncated | ~out.valid
    stats = stats.record(out.reward, ended, out.terminated | out.truncated, gamma)
    return env_state, stats, out


ActFn = Callable[[jax.Array, jax.Array], tuple[jax.Array, ...]]
ValueFn = Callable[[jax.Array], jax.Array]


def closed_loop(env: BatchedEnv, act: ActFn, value: ValueFn, env_state: EnvState, stats: EpisodeStats,
                key: jax.Array, length: int, gamma,
                timeouts_only: bool = False) -> tuple[tuple[EnvState, EpisodeStats], Transition]:
    """Run the policy for `length` steps in all B environments.

    act(obs [B, O], key) -> (action, raw_action, noise [B, A], log_prob [B]).
    value(obs [N, O]) -> [N]: not applied per step but after the scan, in one batched pass (`_values`);
    with `timeouts_only` only on the final observations of time-outs (`timeout_values`: the one thing a
    learner that recomputes GAE with its current value net needs from acting time), value left None.
    Returns ((env_state, stats), Transition with leaves [length, B, ...]).
    """
    assert env_state.obs.shape == (env.num_envs, env.observation_size), env_state.obs.shape

    def step(carry, step_key):
        env_state, stats = carry
        obs = env_state.obs
        action, raw_action, noise, log_prob = act(obs, step_key)
        env_state, stats, out = env_step(env, env_state, stats, action, gamma)
        tr = Transition(obs=obs, next_obs=out.next_obs, action=action, raw_action=raw_action, noise=noise,
                        log_prob=log_prob, value=None, next_value=None, reward=out.reward,
                        terminated=out.terminated, truncated=out.truncated, valid=out.valid)
        return (env_state, stats), tr

    carry, traj = jax.lax.scan(step, (env_state, stats.start_rollout()), jax.random.split(key, length))
    if timeouts_only:
        return carry, traj.replace(next_value=timeout_values(value, traj, env.max_timeouts(length)))
    v_obs, v_next = _values(value, traj, env.restart_obs(env_state))
    return carry, traj.replace(value=v_obs, next_value=v_next)


def timeout_values(value: ValueFn, traj: Transition, max_timeouts: int) -> jax.Array:
    """[T, B]: value(next_obs) where the step timed out (the final observation, bootstrapped), 0 elsewhere.

    An env times out at most `max_timeouts` times in T steps, so only that many rows per env are valued
    (one for T up to the episode length) instead of T: each env's time-out steps are sorted to the front.
    """
    T, B, O = traj.next_obs.shape
    m = min(max_timeouts, T)
    steps = jnp.argsort(~traj.truncated, axis=0, stable=True)[:m]  # [m, B]: time-out steps first, in order
    rows = jnp.take_along_axis(traj.next_obs, steps[..., None], axis=0)
    hit = jnp.take_along_axis(traj.truncated, steps, axis=0)
    v = jnp.where(hit, value(rows.reshape(m * B, O)).reshape(m, B), 0.0)
    return jnp.zeros((T, B), jnp.float32).at[steps, jnp.arange(B)[None]].set(v)


def _values(value: ValueFn, traj: Transition, restart_obs: jax.Array | None) -> tuple[jax.Array, jax.Array]:
    """(value of traj.obs, value of traj.next_obs), both [T, B], from one call of `value` on stacked rows.

    next_obs always needs its own rows: where an episode ended it is the final observation, not the next
    obs. The next obs is otherwise next_obs itself: obs[t+1] = where(ended[t], restart obs, next_obs[t]).
    When every env restarts from a fixed observation (`restart_obs` [B, O], cached resets) the values of
    obs follow from those of next_obs, obs[0] and restart_obs (T*B + 2B rows); otherwise (fresh resets)
    obs and next_obs are valued together (2*T*B rows).
    """
    T, B, O = traj.obs.shape
    if restart_obs is None:
        v = value(jnp.concatenate([traj.obs, traj.next_obs]).reshape(2 * T * B, O)).reshape(2, T, B)
        return v[0], v[1]
    rows = jnp.concatenate([restart_obs[None], traj.obs[:1], traj.next_obs])  # [T + 2, B, O]
    v = value(rows.reshape((T + 2) * B, O)).reshape(T + 2, B)
    v_restart, v_first, v_next = v[0], v[1], v[2:]
    v_obs = jnp.concatenate([v_first[None], jnp.where(traj.ended[:-1], v_restart, v_next[:-1])])
    return v_obs, v_next


def open_loop(model_step: Callable[[jax.Array, jax.Array], jax.Array], s0: jax.Array,
              actions: jax.Array, unroll: int = 1) -> tuple[jax.Array, jax.Array]:
    """Imagine s_1..s_k from s0 [B, O] under actions [k, B, A]; model_step(s, a) -> s'.

    Returns (s_k [B, O], states [k, B, O]).
    """
    assert actions.ndim == 3 and actions.shape[1] == s0.shape[0], (s0.shape, actions.shape)

    def step(s, a):
        s = model_step(s, a)
        return s, s

    return jax.lax.scan(step, s0, actions, unroll=unroll)
