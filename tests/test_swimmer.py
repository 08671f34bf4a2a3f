"""Tests for the MJX swimmer (cdjax/envs/swimmer.py).

MJX compiles slowly on a CPU, so all tests share two jitted functions (module-scoped fixtures): reset, and one
rollout program, vmapped over a batch of B rollouts of one length, so it is compiled once. A single rollout
runs as row 0 of a batch whose other rows repeat it; the batch's rows are checked to be independent of each other
and of their position, and row 0 against C MuJoCo.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from cdjax.envs.swimmer import Swimmer

T = 200  # steps per rollout (8 s at dt = 0.04); one length, so one compile
WARMUP = 50  # steps left out before averaging the velocity (first stroke, start-up turn)
FREQ_HZ, PHASE = 0.4, np.pi / 4  # travelling-wave gait: a_i(t) = sin(2 pi f t - phase * i)


def wave(phase: float, dt: float, steps: int = T) -> np.ndarray:
    t = np.arange(steps)[:, None] * dt
    i = np.arange(2)[None, :]
    return np.sin(2 * np.pi * FREQ_HZ * t - phase * i).astype(np.float32)


@pytest.fixture(scope="module")
def env():
    return Swimmer()


B = 4  # rollouts per call of the one rollout program


@pytest.fixture(scope="module")
def fns(env):
    def rollout(state, actions):
        def body(s, a):
            s = env.step(s, a)
            out = dict(obs=s.obs, reward=s.reward, done=s.done, qpos=s.pipeline_state.qpos,
                       state=s, **s.metrics)
            return s, out

        return jax.lax.scan(body, state, actions)

    return dict(reset=jax.jit(env.reset), batched=jax.jit(jax.vmap(rollout)))


def stack(states):
    """A batch of states, stacked on the host (no program compiled per leaf)."""
    return jax.tree.map(lambda *leaves: np.stack([np.asarray(x) for x in leaves]), *states)


def row(tree, i):
    return jax.tree.map(lambda leaf: np.asarray(leaf)[i], tree)


def run(fns, state, actions):
    """One rollout from `state` under `actions` [T, 2]: row 0 of the batched program, the other rows repeating it."""
    return row(fns["batched"](stack([state] * B), np.stack([np.asarray(actions)] * B)), 0)


@pytest.fixture(scope="module")
def start(fns):
    return fns["reset"](jax.random.PRNGKey(0))


def test_reset_shapes_and_randomness(env, fns, start):
    assert env.action_size == 2
    assert env.dt == pytest.approx(0.04)
    assert start.obs.shape == (8,) and start.obs.dtype == jnp.float32
    assert np.isfinite(np.asarray(start.obs)).all()
    assert float(start.reward) == 0.0 and float(start.done) == 0.0
    assert set(start.metrics) == {"x_position", "x_velocity", "reward_fwd", "reward_ctrl"}
    assert start.info == {}
    # Noise is at most 0.1 on every qpos / qvel entry and the observation is qpos[2:] ++ qvel.
    q, qd = np.asarray(start.pipeline_state.qpos), np.asarray(start.pipeline_state.qvel)
    assert q.shape == (5,) and qd.shape == (5,)
    assert np.abs(q).max() <= 0.1 and np.abs(qd).max() <= 0.1
    np.testing.assert_array_equal(np.asarray(start.obs), np.concatenate([q[2:], qd]))
    other = fns["reset"](jax.random.PRNGKey(1))
    assert np.abs(np.asarray(other.obs) - np.asarray(start.obs)).max() > 1e-3
    again = fns["reset"](jax.random.PRNGKey(0))
    np.testing.assert_array_equal(np.asarray(again.obs), np.asarray(start.obs))


def test_step_deterministic_markov_and_finite(env, fns, start):
    actions = jax.random.uniform(jax.random.PRNGKey(2), (T, 2), minval=-1.0, maxval=1.0)
    final, traj = run(fns, start, actions)
    _, traj2 = run(fns, start, actions)
    for k in ("obs", "reward", "qpos", "x_velocity"):
        np.testing.assert_array_equal(np.asarray(traj[k]), np.asarray(traj2[k]), err_msg=k)
    for k, v in traj.items():
        if k != "state":
            assert np.isfinite(np.asarray(v)).all(), k
    assert np.all(np.asarray(traj["done"]) == 0.0)
    assert traj["obs"].shape == (T, 8) and traj["obs"].dtype == jnp.float32
    assert traj["reward"].dtype == jnp.float32
    # The state is Markov: restarting from the State stored after step K with the remaining actions
    # reproduces the rest of the run (the tail is padded to keep one scan length / one compile).
    K = 50
    state_k = row(traj["state"], K - 1)
    tail = jnp.concatenate([actions[K:], jnp.zeros((K, 2))])
    _, rest = run(fns, state_k, tail)
    for k in ("obs", "reward", "qpos"):
        np.testing.assert_array_equal(np.asarray(rest[k][: T - K]), np.asarray(traj[k][K:]),
                                      err_msg=k)
    x = np.asarray(traj["x_position"])
    x0 = float(start.metrics["x_position"])
    vx = np.diff(np.concatenate([[x0], x])) / env.dt
    np.testing.assert_allclose(np.asarray(traj["x_velocity"]), vx, rtol=1e-4, atol=1e-4)
    ctrl = -1e-4 * np.sum(np.asarray(actions) ** 2, axis=-1)
    np.testing.assert_allclose(np.asarray(traj["reward_ctrl"]), ctrl, rtol=1e-5, atol=1e-8)
    np.testing.assert_allclose(np.asarray(traj["reward"]),
                               np.asarray(traj["reward_fwd"]) + ctrl, rtol=1e-5, atol=1e-6)
    # Random torques of +-150 N m really move the joints.
    assert np.abs(np.asarray(traj["obs"])[:, 1:3]).max() > 0.3
    assert np.isfinite(np.asarray(final.pipeline_state.qpos)).all()


def test_travelling_wave_swims_forward(env, fns, start):
    gaits = np.stack([wave(PHASE, env.dt), wave(-PHASE, env.dt), np.zeros((T, 2), np.float32), wave(PHASE, env.dt)])
    _, trajs = fns["batched"](stack([start] * B), gaits)
    v_fwd, v_mirror, v_zero, _ = np.mean(np.asarray(trajs["x_velocity"])[:, WARMUP:], axis=1)
    traj = row(trajs, 0)
    print(f"mean x-velocity: wave {v_fwd:.3f}, mirrored wave {v_mirror:.3f}, zero {v_zero:.3f}")
    # A head-to-tail wave swims head first (+x), the mirrored (tail-to-head) wave swims backwards,
    # doing nothing only coasts on the initial velocity (|v| <= 0.1, slowly damped by quadratic drag).
    assert v_fwd > 0.08
    assert v_fwd > v_zero + 0.05
    assert v_mirror < 0.0
    assert v_fwd > v_mirror + 0.1
    # It swims rather than drifts: net displacement over the window is well beyond noise.
    x = np.asarray(traj["x_position"])
    assert x[-1] - x[WARMUP] > 0.5


def test_matches_c_mujoco(env, fns, start):
    """The MJX physics (fluid forces + RK4) follows C MuJoCo on the same model."""
    actions = wave(PHASE, env.dt)
    _, traj = run(fns, start, actions)
    m = env.sys.mj_model
    d = mujoco.MjData(m)
    d.qpos[:] = np.asarray(start.pipeline_state.qpos, np.float64)
    d.qvel[:] = np.asarray(start.pipeline_state.qvel, np.float64)
    qs = []
    for a in actions[:50]:
        d.ctrl[:] = a
        for _ in range(4):
            mujoco.mj_step(m, d)
        qs.append(d.qpos.copy())
    np.testing.assert_allclose(np.asarray(traj["qpos"])[:50], np.array(qs), atol=2e-3)


def test_no_fluid_no_swimming_c_mujoco(env):
    """Without the fluid, the same gait cannot move the centre of mass (no external force).

    Only up to integration error: RK4 leaves ~3 cm over the 8 s of violent, undamped flailing.
    """
    actions = wave(PHASE, env.dt)
    com_shift = {}
    for fluid in (True, False):
        m = env.sys.mj_model.__copy__()
        if not fluid:
            m.opt.density, m.opt.viscosity = 0.0, 0.0
        d = mujoco.MjData(m)
        mujoco.mj_forward(m, d)
        com0 = d.subtree_com[1, :2].copy()
        for a in actions:
            d.ctrl[:] = a
            for _ in range(4):
                mujoco.mj_step(m, d)
        com_shift[fluid] = np.linalg.norm(d.subtree_com[1, :2] - com0)
    assert com_shift[False] < 0.1
    assert com_shift[True] > 0.5
    assert com_shift[True] > 10 * com_shift[False]


def test_batched_rollouts_are_independent_of_each_other_and_of_their_row(fns, start):
    """Four different starts and action sequences give four different rollouts, and the same four in another order
    give the same rollouts in that order (no row reads another), so row 0 of `run`, which C MuJoCo checks, stands
    for every row."""
    states = stack([start] + [fns["reset"](jax.random.PRNGKey(k)) for k in range(1, B)])
    actions = jax.random.uniform(jax.random.PRNGKey(3), (B, T, 2), minval=-1.0, maxval=1.0)
    _, traj = fns["batched"](states, actions)
    assert traj["obs"].shape == (B, T, 8) and traj["reward"].shape == (B, T)
    assert np.isfinite(np.asarray(traj["obs"])).all()
    order = np.array([2, 0, 3, 1])
    _, shuffled = fns["batched"](jax.tree.map(lambda leaf: leaf[order], states), np.asarray(actions)[order])
    for k in ("obs", "reward", "qpos"):
        np.testing.assert_allclose(np.asarray(shuffled[k]), np.asarray(traj[k])[order], rtol=1e-5, atol=1e-5,
                                   err_msg=k)
    # Different starts and actions give different trajectories.
    assert np.abs(np.asarray(traj["qpos"][1] - traj["qpos"][0])).max() > 1e-2
