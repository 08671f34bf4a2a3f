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
- Playground's DM Control tasks (cdjax.envs.playground), exact where the reward reads only what the observation
  holds after the step: dmc-pendulum-swingup (the pole's vertical cosine), dmc-cartpole-balance/-swingup and their
  -sparse variants (cart position, pole cosine, angular velocity, action), dmc-reacher-easy/-hard (the observed
  finger-to-target vector; the radii from the model) and dmc-point-mass (the mass's x, y one physics step back
  from its observed position and velocity: target and mass share a height; the target's size from the model),
  with Playground's own `tolerance`; tests/test_playground.py checks them against Playground's step. They need
  action_repeat = 1 (the reward of intermediate physics steps is not observed). The others have none: their rewards read
  bodies' positions, heights, velocities or the centre of mass that their observations do not hold whole (cheetah,
  walker, hopper, humanoid: subtree or torso velocities and heights; acrobot, finger, fish, ball-in-cup, swimmer:
  positions of bodies relative to a target, through the model's geometry).
- humanoid (and the other tasks): none. Humanoid's forward reward is the velocity of the whole body's
  centre of mass, which its observation (joint positions and velocities, body inertias, com-based
  velocities, actuator forces) gives only through the per-body masses and frames of the model: not a
  function of the observation alone that we could check, so its planners use the learned reward.

`action_repeat` agent steps sum that many physics steps' rewards (cdjax.envs.BatchedEnv): the velocity
term is the trapezoid over the whole agent step, the ctrl cost is paid on every physics step.
"""

from __future__ import annotations

import functools
import math
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


@functools.cache
def _playground_model(name: str):
    """The MuJoCo model of a Playground task (for its geoms' sizes); needs the playground extra."""
    from cdjax.envs.playground import NAMES, _import_suite

    return _import_suite().load(NAMES[name], config_overrides={"impl": "jax"}).mj_model


def _tolerance(*args, **kwargs):
    from mujoco_playground._src import reward  # Playground's tolerance, that its tasks' rewards are written with

    return reward.tolerance(*args, **kwargs)


def _repeat_one(name: str, action_repeat: int) -> None:
    if action_repeat != 1:
        raise ValueError(f"{name}'s reward from observations needs action_repeat = 1")


def _small_control(action):
    """DM Control's (4 + quadratic tolerance of the action, within margin 1) / 5, averaged over actuators."""
    return (4 + _tolerance(action, margin=1, value_at_margin=0, sigmoid="quadratic").mean(-1)) / 5


def _pendulum_swingup(obs, action, next_obs, action_repeat: int = 1):
    _repeat_one("dmc-pendulum-swingup", action_repeat)
    return _tolerance(next_obs[..., 1], (math.cos(math.radians(8.0)), 1.0))  # obs: [xz, zz, angular vel]


def _cartpole(sparse: bool):
    """obs: [cart x, pole cosine, pole sine, cart velocity, pole angular velocity] (one pole)."""

    def reward(obs, action, next_obs, action_repeat: int = 1):
        _repeat_one("dmc-cartpole", action_repeat)
        x, cosine, angular = next_obs[..., 0], next_obs[..., 1], next_obs[..., 4]
        if sparse:
            return _tolerance(x, (-0.25, 0.25)) * _tolerance(cosine, (0.995, 1.0))
        upright = (cosine + 1) / 2
        centered = (1 + _tolerance(x, margin=2)) / 2
        small_velocity = (1 + _tolerance(angular, margin=5)) / 2
        return upright * centered * _small_control(action) * small_velocity

    return reward


def _reacher(name: str):
    """obs: [2 joint angles, finger-to-target x y, 2 joint velocities]; within the target and finger radii."""

    def reward(obs, action, next_obs, action_repeat: int = 1):
        _repeat_one(name, action_repeat)
        model = _playground_model(name)
        radii = float(model.geom("target").size[0] + model.geom("finger").size[0])
        return _tolerance(jnp.linalg.norm(next_obs[..., 2:4], axis=-1), (0.0, radii))

    return reward


def _point_mass(obs, action, next_obs, action_repeat: int = 1):
    """obs: [x, y, vx, vy]; the target at the origin, at the mass's height. Playground measures the distance with
    the geoms' positions of the physics step's start (MuJoCo computes positions, then integrates), so the position
    is taken one (semi-implicit Euler) physics step back: x - timestep * v, with the step's new velocity."""
    _repeat_one("dmc-point-mass", action_repeat)
    model = _playground_model("dmc-point-mass")
    size, timestep = float(model.geom("target").size[0]), float(model.opt.timestep)
    position = next_obs[..., :2] - timestep * next_obs[..., 2:4]
    near = _tolerance(jnp.linalg.norm(position, axis=-1), bounds=(0.0, size), margin=size)
    return near * _small_control(action)


REWARDS.update({
    "dmc-pendulum-swingup": _pendulum_swingup,
    "dmc-cartpole-balance": _cartpole(sparse=False),
    "dmc-cartpole-swingup": _cartpole(sparse=False),
    "dmc-cartpole-balance-sparse": _cartpole(sparse=True),
    "dmc-cartpole-swingup-sparse": _cartpole(sparse=True),
    "dmc-reacher-easy": _reacher("dmc-reacher-easy"),
    "dmc-reacher-hard": _reacher("dmc-reacher-hard"),
    "dmc-point-mass": _point_mass,
})
WHY_NOT = {
    "humanoid": "its forward reward is the velocity of the body's centre of mass, which the observation does not "
                "give without the model's masses and frames",
}


def needs_action_repeat_one(env: str) -> bool:
    """Whether the task's reward from observations holds only for one physics step per agent step."""
    return env == "point" or env.startswith("dmc-")


def reward_fn(env: str) -> RewardFn | None:
    """The task's reward as a function of (obs, action, next_obs[, action_repeat]); None where there is none."""
    return REWARDS.get(env)


def why_not(env: str) -> str:
    """Why a task has no reward function of observations (one clause)."""
    if env.startswith("dmc-") and env not in WHY_NOT:
        return ("its reward reads the positions, heights or velocities of bodies that its observation does not hold "
                "whole (cdjax/envs/rewards.py)")
    return WHY_NOT.get(env, "no reward function of its observations is written for it (cdjax/envs/rewards.py)")
