"""Each task's reward as a function of observations: reward(obs, action, next_obs) -> reward, for planners
that score predicted observations with the task's own reward instead of a learned one (the Mb-Mf phase's
`mpc_reward="true"`; Nagabandi et al. score their MPC candidates with the task's reward function).

The simulator computes the reward from its physics state, which the observation does not hold whole, so
the functions here are the task's reward written in what the observation does hold:

- point: exact (cdjax.envs.point: the position is observed).
- halfcheetah, ant, swimmer: the ctrl cost (and ant's healthy reward) are exact; the forward velocity, a
  finite difference of the torso's x position (not observed), is replaced by the trapezoid of the root's
  observed x velocity at the two ends of the step, (v(t) + v(t+1)) / 2. Ant terminates when its torso's
  height leaves [0.2, 1]; here a predicted state out of that range earns no healthy reward, in place of
  the episode's end. How close these are to the simulator's rewards is measured in tests/test_mbmf_options.py.
- humanoid (and the other tasks): none. Humanoid's forward reward is the velocity of the whole body's
  centre of mass, which its observation (joint positions and velocities, body inertias, com-based
  velocities, actuator forces) gives only through the per-body masses and frames of the model: not a
  function of the observation alone that we could check, so its planners use the learned reward.

`action_repeat` agent steps sum that many physics steps' rewards (cdjax.envs.BatchedEnv): the velocity
term is the trapezoid over the whole agent step, the ctrl cost is paid on every physics step.
"""

from __future__ import annotations

from typing import Callable

import jax.numpy as jnp

RewardFn = Callable[..., "jnp.ndarray"]  # (obs [..., O], action [..., A], next_obs [..., O]) -> [...]


def _trapezoid(index: int):
    return lambda obs, next_obs: 0.5 * (obs[..., index] + next_obs[..., index])


def _point(obs, action, next_obs, action_repeat: int = 1):
    if action_repeat != 1:  # the point mass's reward depends on the intermediate positions
        raise ValueError("the point mass's reward from observations needs action_repeat = 1")
    a = jnp.clip(action, -1.0, 1.0)
    return 1.0 - jnp.sum(next_obs[..., :2] ** 2, -1) - 0.01 * jnp.sum(a**2, -1)


def _locomotion(velocity_index: int, ctrl_weight: float, healthy: tuple[float, float, float] | None = None):
    """forward velocity (trapezoid of obs[velocity_index]) - ctrl_weight |a|^2 [+ healthy reward if the height
    obs[0] of the next state lies in its range]."""
    velocity = _trapezoid(velocity_index)

    def reward(obs, action, next_obs, action_repeat: int = 1):
        r = action_repeat * (velocity(obs, next_obs) - ctrl_weight * jnp.sum(action**2, -1))
        if healthy is not None:
            low, high, value = healthy
            z = next_obs[..., 0]
            r = r + action_repeat * value * ((z >= low) & (z <= high))
        return r

    return reward


# obs layouts: halfcheetah qpos[1:] (8) + qvel (9): vx at 8; ant qpos[2:] (13: z first) + qvel (14): vx at 13;
# swimmer (cdjax.envs.swimmer) qpos[2:] (3) + qvel (5): vx at 3.
REWARDS: dict[str, RewardFn] = {
    "point": _point,
    "halfcheetah": _locomotion(8, 0.1),
    "ant": _locomotion(13, 0.5, healthy=(0.2, 1.0, 1.0)),
    "swimmer": _locomotion(3, 1e-4),
}
WHY_NOT = {
    "humanoid": "its forward reward is the velocity of the body's centre of mass, which the observation does not "
                "give without the model's masses and frames",
}


def reward_fn(env: str) -> RewardFn | None:
    """The task's reward as a function of (obs, action, next_obs[, action_repeat]); None where there is none."""
    return REWARDS.get(env)


def why_not(env: str) -> str:
    """Why a task has no reward function of observations (one clause)."""
    return WHY_NOT.get(env, "no reward function of its observations is written for it (cdjax/envs/rewards.py)")
