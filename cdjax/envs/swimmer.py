"""Swimmer on MuJoCo-MJX: a 3-link planar swimmer in a viscous fluid.

A chain of three equal capsule links (length 1, radius 0.1) moves in the
horizontal plane. The front link ("torso") is attached to the world through
two slide joints (x, y) and a hinge (yaw); the two joints between the links
are hinges driven by motors with gear 150, so an action ``a`` in ``[-1, 1]^2``
produces joint torques ``150 * a``. Nothing but the fluid pushes the swimmer:
undulating the body makes it move.

Fluid model
-----------
Brax's own ``Swimmer`` only accepts ``backend='generalized'``, which made it
look as if MJX could not simulate a swimmer. That is not the case for
mujoco-mjx 3.17.0. Its JAX backend (``mujoco/mjx/_src/passive.py::_fluid``)
implements MuJoCo's *inertia-box* fluid model, the body-level
viscous + quadratic-drag model that is switched on by ``<option density=...
viscosity=...>`` and used by Gymnasium's swimmer XML. Every link is replaced by
the box with the same inertia, and each box gets

* a linear viscous (Stokes) force and torque, proportional to ``viscosity``,
* a quadratic drag ``-0.5 * density * A_i * |v_i| * v_i`` on each local axis
  ``i``, where ``A_i`` is the box's cross-section normal to that axis.

For these links the equivalent box is about 1.14 x 0.17 x 0.17, so the
sideways cross-section is about 6.6 times the end-on one. That anisotropy
(sideways motion resisted much more than motion along the link) is what lets
a travelling body wave propel the swimmer. MJX also supports the RK4
integrator, so this env uses the same physics settings as Gymnasium
(timestep 0.01, RK4, density 4000, viscosity 0.1). We checked MJX's fluid
forces against C MuJoCo: ``qfrc_passive`` agrees to float32 precision, and
``tests/test_swimmer.py`` compares whole trajectories. RK4 costs about four
times as much per substep as Euler. We keep it because, with the fluid turned
off, semi-implicit Euler at this timestep let the centre of mass of a flailing
swimmer drift by metres (RK4: about 3 cm), and momentum should be conserved.

What mujoco-mjx 3.17.0 (JAX backend) does *not* support, and this model
therefore avoids:

* the *ellipsoid* fluid model (``<geom fluidshape="ellipsoid">``,
  ``geom_fluid``, ``body_fluid_ellipsoid``). MJX accepts such a model without
  an error but quietly uses the inertia-box forces instead, so an
  "ellipsoid" swimmer would run with different physics from C MuJoCo;
* fluid forces with the ``implicitfast`` integrator (``put_model`` raises);
* ``Data.qfrc_fluid`` is never recomputed; MJX adds the fluid forces straight
  into ``qfrc_passive``.

(Gymnasium's XML also has ``<option collision="predefined">``, which MuJoCo
4.0.0's parser rejects. It is not needed here because all geoms have contype
= conaffinity = 0, so there are no contacts.)

Differences from Gymnasium's ``Swimmer-v5`` and why
---------------------------------------------------
* Geometry/root frame: Gymnasium puts the root joints 0.5 behind the rear
  end of the front capsule (a point that is rigidly attached to the front
  link but lies outside it). Here the root is at the *centre of the front
  link*, so ``qpos[:2]`` and the forward reward track a point on the body. Masses
  (35.6 per link), lengths, joint ranges (+/-100 deg on the actuated hinges),
  armature 0.1, gear 150 and fluid parameters are the same. The front-link
  centre and Gymnasium's root point differ only by a bounded rotation term,
  so their average speed over many strokes is the same; per-step rewards
  differ a little.
* No floor, lights, textures or camera: the floor never touched the swimmer
  (no contacts) and rendering assets are not needed for training.
* ``done`` is always 0 (there is no termination). Episode time-outs are
  applied by a wrapper elsewhere, as in Brax.
* ``reward_ctrl`` is stored as a negative number (``-ctrl_cost``), following
  Brax's convention.

Interface
---------
* action: 2 numbers in ``[-1, 1]`` (torques on the two inter-link hinges,
  scaled by gear 150).
* observation (8 numbers, float32): ``[yaw of front link, rot2, rot3,
  vx, vy, yaw rate, rot2 rate, rot3 rate]``, i.e. ``qpos[2:]`` followed by
  ``qvel``. The root x, y position is left out, as in Gymnasium.
* reward: ``forward_reward_weight * x_velocity - ctrl_cost_weight *
  sum(action**2)``, where ``x_velocity = (x_after - x_before) / dt`` and
  ``x`` is the front-link centre.
* reset: ``qpos`` and ``qvel`` get ``U(-reset_noise_scale,
  reset_noise_scale)`` noise (0.1 by default).
* control step: ``dt = 0.01 * n_frames`` (0.04 s by default).
* ``state.metrics``: ``x_position``, ``x_velocity``, ``reward_fwd``,
  ``reward_ctrl``. ``state.info`` is empty.
"""

from __future__ import annotations

import warnings

import jax
from brax.envs.base import PipelineEnv, State
from brax.io import mjcf
from jax import numpy as jp

SWIMMER_XML = """
<mujoco model="swimmer3">
  <compiler angle="degree" inertiafromgeom="true"/>
  <!-- Inertia-box fluid model (supported by MJX's JAX backend) + RK4, as in
       Gymnasium's swimmer. -->
  <option timestep="0.01" integrator="RK4" density="4000" viscosity="0.1"/>
  <default>
    <geom type="capsule" size="0.1" density="1000" contype="0" conaffinity="0"
          rgba="0.8 0.6 0.4 1"/>
    <joint armature="0.1"/>
    <motor gear="150" ctrllimited="true" ctrlrange="-1 1"/>
  </default>
  <worldbody>
    <body name="torso" pos="0 0 0">
      <!-- Root frame at the centre of the front link. -->
      <joint name="slider1" type="slide" axis="1 0 0"/>
      <joint name="slider2" type="slide" axis="0 1 0"/>
      <joint name="rot" type="hinge" axis="0 0 1"/>
      <geom name="torso" fromto="0.5 0 0 -0.5 0 0"/>
      <body name="mid" pos="-0.5 0 0">
        <joint name="rot2" type="hinge" axis="0 0 1" limited="true"
               range="-100 100"/>
        <geom name="mid" fromto="0 0 0 -1 0 0"/>
        <body name="back" pos="-1 0 0">
          <joint name="rot3" type="hinge" axis="0 0 1" limited="true"
                 range="-100 100"/>
          <geom name="back" fromto="0 0 0 -1 0 0"/>
        </body>
      </body>
    </body>
  </worldbody>
  <actuator>
    <motor name="rot2" joint="rot2"/>
    <motor name="rot3" joint="rot3"/>
  </actuator>
</mujoco>
"""


class Swimmer(PipelineEnv):
  """3-link swimmer with the MJX backend; see the module docstring."""

  def __init__(
      self,
      forward_reward_weight: float = 1.0,
      ctrl_cost_weight: float = 1e-4,
      reset_noise_scale: float = 0.1,
      n_frames: int = 4,
      **kwargs,
  ):
    backend = kwargs.pop('backend', 'mjx')
    if backend != 'mjx':
      raise ValueError(f'Swimmer only supports backend="mjx", got {backend!r}.')
    with warnings.catch_warnings():
      # brax.io.mjcf warns that Brax's own pipelines are unmaintained; we only
      # use its MJCF loader and the MJX pipeline.
      warnings.filterwarnings('ignore', message='Brax System, piplines')
      sys = mjcf.loads(SWIMMER_XML)
    super().__init__(sys=sys, backend='mjx', n_frames=n_frames, **kwargs)

    self._forward_reward_weight = forward_reward_weight
    self._ctrl_cost_weight = ctrl_cost_weight
    self._reset_noise_scale = reset_noise_scale

  def reset(self, rng: jax.Array) -> State:
    rng_q, rng_qd = jax.random.split(rng)
    low, high = -self._reset_noise_scale, self._reset_noise_scale
    qpos = self.sys.qpos0 + jax.random.uniform(
        rng_q, (self.sys.nq,), jp.float32, low, high
    )
    qvel = jax.random.uniform(rng_qd, (self.sys.nv,), jp.float32, low, high)
    pipeline_state = self.pipeline_init(qpos.astype(jp.float32), qvel)
    obs = self._get_obs(pipeline_state)
    zero = jp.zeros((), jp.float32)
    metrics = {
        'x_position': pipeline_state.qpos[0],
        'x_velocity': zero,
        'reward_fwd': zero,
        'reward_ctrl': zero,
    }
    return State(pipeline_state, obs, zero, zero, metrics)

  def step(self, state: State, action: jax.Array) -> State:
    action = jp.asarray(action, jp.float32)
    pipeline_state0 = state.pipeline_state
    pipeline_state = self.pipeline_step(pipeline_state0, action)

    x_before = pipeline_state0.qpos[0]
    x_after = pipeline_state.qpos[0]
    x_velocity = (x_after - x_before) / self.dt
    forward_reward = self._forward_reward_weight * x_velocity
    ctrl_cost = self._ctrl_cost_weight * jp.sum(jp.square(action))
    reward = (forward_reward - ctrl_cost).astype(jp.float32)

    metrics = dict(state.metrics)
    metrics.update(
        x_position=x_after,
        x_velocity=x_velocity,
        reward_fwd=forward_reward,
        reward_ctrl=-ctrl_cost,
    )
    return state.replace(
        pipeline_state=pipeline_state,
        obs=self._get_obs(pipeline_state),
        reward=reward,
        done=jp.zeros_like(state.done),
        metrics=metrics,
    )

  def _get_obs(self, pipeline_state) -> jax.Array:
    # Joint angles without the root x, y position, then all joint velocities.
    return jp.concatenate(
        [pipeline_state.qpos[2:], pipeline_state.qvel]
    ).astype(jp.float32)
