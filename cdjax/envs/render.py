"""Videos of one episode, from MuJoCo's offscreen renderer (the env layer is the one place importing mujoco).

`render_episode` rolls one episode of the single environment inside a `BatchedEnv` (jitted, on the
default device), replays its physics states on the env's MjModel and writes the frames. When rendering
is not possible it prints one sentence saying why and returns None; it never raises for those reasons.
"""

from __future__ import annotations

import importlib.util
import os
import pathlib
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from cdjax.envs import BatchedEnv


def render_episode(env: BatchedEnv, act: Callable, key: jax.Array, path: pathlib.Path, *, steps: int,
                   deterministic: bool = True, width: int = 320, height: int = 240) -> pathlib.Path | None:
    """Roll one episode (at most `steps` agent steps) with act(obs [1, O], key or None) -> [1, A]; write it.

    Frames come from MuJoCo's offscreen renderer on the env's MjModel (the "track" camera when the model
    has one). Writes mp4 when imageio has an ffmpeg backend (imageio-ffmpeg or PyAV), else a gif next to
    `path` (same name, .gif). Returns the written path, or None after printing one sentence saying what is
    missing (no MjModel, e.g. the point env; no OpenGL context: start Python with MUJOCO_GL=egl, or
    MUJOCO_GL=osmesa with Debian's libosmesa6).
    """
    import mujoco

    single = getattr(env, "env", None)
    mj_model = getattr(getattr(single, "sys", None), "mj_model", None)
    if mj_model is None:
        return _unavailable("this env has no MuJoCo model to render")
    try:
        renderer = mujoco.Renderer(mj_model, height=height, width=width)
    except Exception as err:  # noqa: BLE001 - every GL failure means the same thing to the user
        backend = os.environ.get("MUJOCO_GL", "")
        return _unavailable(
            f"no OpenGL context for MuJoCo's renderer (MUJOCO_GL={backend!r}: {type(err).__name__}); start Python "
            "with MUJOCO_GL=egl (GPU, or Mesa's EGL on CPU) or MUJOCO_GL=osmesa (apt-get install libosmesa6)")
    try:
        qpos, qvel, n = _rollout_states(env, act, key, steps, deterministic)
        data = mujoco.MjData(mj_model)
        camera = _camera(mujoco, mj_model)
        frames = []
        for t in range(n):
            data.qpos[:] = qpos[t]
            data.qvel[:] = qvel[t]
            mujoco.mj_forward(mj_model, data)
            renderer.update_scene(data, camera=camera)
            frames.append(renderer.render().copy())
    finally:
        renderer.close()
    fps = 1.0 / (float(getattr(single, "dt", 0.05)) * env.action_repeat)
    return _write_frames(path, frames, fps)


def _unavailable(reason: str) -> None:
    print(f"No video: {reason}.")
    return None


def _rollout_states(env: BatchedEnv, act: Callable, key, steps: int, deterministic: bool):
    """(qpos [n, nq], qvel [n, nv], n): the reset state and the state after each agent step, up to the
    first step that ends the episode (inclusive) or `steps` steps."""
    single = env.env
    steps = max(1, min(int(steps), env.episode_length))

    def physics(state):
        ps = state.pipeline_state  # mjx Data (qpos, qvel), or an older Brax pipeline state (q, qd)
        return (ps.qpos, ps.qvel) if hasattr(ps, "qpos") else (ps.q, ps.qd)

    @jax.jit
    def rollout(key):
        key_reset, key_act = jax.random.split(key)
        state = single.reset(key_reset)

        def step(carry, key_step):
            state, done = carry
            action = act(state.obs[None].astype(jnp.float32), None if deterministic else key_step)[0]
            for _ in range(env.action_repeat):
                state = single.step(state, action)
            q, qd = physics(state)
            finite = jnp.isfinite(q).all() & jnp.isfinite(qd).all()
            ended = (state.done > 0.5) | ~finite
            return (state, done | ended), (q, qd, done)

        (_, _), (q, qd, was_done) = jax.lax.scan(step, (state, jnp.zeros((), bool)), jax.random.split(key_act, steps))
        q0, qd0 = physics(state)
        return (jnp.concatenate([q0[None], q]), jnp.concatenate([qd0[None], qd]),
                jnp.concatenate([jnp.zeros((1,), bool), was_done]))

    q, qd, was_done = jax.device_get(rollout(key))
    n = int((~was_done).sum())  # frames before any step taken after the episode ended
    return np.asarray(q, np.float64), np.asarray(qd, np.float64), n


def _camera(mujoco, model):
    """The model's "track" camera if it has one, else MuJoCo's default free camera (whole model in view)."""
    cam_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, "track")
    if cam_id >= 0:
        return cam_id
    camera = mujoco.MjvCamera()
    mujoco.mjv_defaultFreeCamera(model, camera)
    return camera


def _write_frames(path: pathlib.Path, frames: list[np.ndarray], fps: float) -> pathlib.Path | None:
    import imageio

    path.parent.mkdir(parents=True, exist_ok=True)
    if not frames:
        return _unavailable("the episode produced no frames")
    if path.suffix.lower() != ".gif":
        if importlib.util.find_spec("imageio_ffmpeg") is not None:
            imageio.v2.mimwrite(path, frames, fps=fps, format="FFMPEG", macro_block_size=1)
            return path
        if importlib.util.find_spec("av") is not None:
            import imageio.v3 as iio

            iio.imwrite(path, np.stack(frames), plugin="pyav", fps=int(round(fps)), codec="libx264")
            return path
        print(f"No mp4 encoder (install imageio-ffmpeg); writing a gif instead of {path.name}.")
        path = path.with_suffix(".gif")
    import imageio.v3 as iio

    iio.imwrite(path, np.stack(frames), duration=1000.0 / fps, loop=0)
    return path
