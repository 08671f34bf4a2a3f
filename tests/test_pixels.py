"""The in-jit renderer (cdjax.envs.pixels) against MuJoCo's own renderer: the body silhouettes of the three
pixel tasks at random poses, from the same cameras, overlap with IoU >= 0.9.

MuJoCo's renderer runs in a fresh process with MUJOCO_GL=osmesa (Debian's libosmesa6; `.ci/run` installs it
when it can): MUJOCO_GL is read when mujoco is imported. Its segmentation image gives each pixel's geom; the
body mask is the pixels whose geom belongs to a body other than the world."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

import jax
import numpy as np
import pytest

from cdjax.envs import make_single_env, pixels

TASKS = ("halfcheetah", "reacher", "pusher")
SIZE = 64
POSES = 2

_MUJOCO_MASKS = textwrap.dedent("""
    import sys, numpy as np, mujoco
    from cdjax.envs import make_single_env, pixels
    out, size, poses = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
    result = {}
    for name in sys.argv[4:]:
        m = make_single_env(name).sys.mj_model
        d = mujoco.MjData(m)
        renderer = mujoco.Renderer(m, size, size)
        renderer.enable_segmentation_rendering()
        cam = pixels.camera_for(name)
        if cam.name:
            view = cam.name
        else:
            view = mujoco.MjvCamera()
            view.type = mujoco.mjtCamera.mjCAMERA_FREE
            view.lookat[:], view.distance, view.azimuth, view.elevation = cam.lookat, cam.distance, cam.azimuth, cam.elevation
        rng = np.random.default_rng(7)
        for i in range(poses):
            d.qpos[:] = m.qpos0 + 0.4 * rng.standard_normal(m.nq)
            mujoco.mj_forward(m, d)
            renderer.update_scene(d, camera=view)
            seg = renderer.render()
            geom = seg[..., 0]
            is_geom = (seg[..., 1] == int(mujoco.mjtObj.mjOBJ_GEOM)) & (geom >= 0)
            result[f"{name}/{i}/mask"] = is_geom & (m.geom_bodyid[np.maximum(geom, 0)] != 0)
            result[f"{name}/{i}/qpos"] = d.qpos.copy()
    np.savez(out, **result)
    print("RESULT ok")
""")


@pytest.fixture(scope="module")
def mujoco_masks(tmp_path_factory):
    out = tmp_path_factory.mktemp("masks") / "masks.npz"
    env = {**os.environ, "MUJOCO_GL": "osmesa", "PYTHONPATH": os.pathsep.join(sys.path)}
    proc = subprocess.run([sys.executable, "-c", _MUJOCO_MASKS, str(out), str(SIZE), str(POSES), *TASKS], env=env,
                          capture_output=True, text=True, timeout=300)
    if "RESULT ok" not in proc.stdout:
        if "OSMesa" in proc.stderr or "osmesa" in proc.stderr.lower() or "GL" in proc.stderr:
            pytest.skip("MuJoCo's renderer has no OSMesa context here (install Debian's libosmesa6): "
                        + proc.stderr.strip().splitlines()[-1][:200])
        raise AssertionError(proc.stderr[-3000:])
    return dict(np.load(out))


def _data(mj_model, qpos):
    import mujoco
    from mujoco import mjx

    d = mujoco.MjData(mj_model)
    d.qpos[:] = qpos
    mujoco.mj_forward(mj_model, d)
    return mjx.put_data(mj_model, d)


@pytest.mark.parametrize("task", TASKS)
def test_body_silhouette_matches_mujoco(task, mujoco_masks):
    mj_model = make_single_env(task).sys.mj_model
    renderer = pixels.make_renderer(mj_model, pixels.camera_for(task), SIZE)
    datas = [_data(mj_model, mujoco_masks[f"{task}/{i}/qpos"]) for i in range(POSES)]
    batch = jax.tree.map(lambda *x: np.stack(x), *datas)
    masks = np.asarray(jax.jit(jax.vmap(renderer.body_mask))(batch))
    render = jax.jit(jax.vmap(renderer.render))
    frames = np.asarray(render(batch))
    assert frames.shape == (POSES, SIZE, SIZE, 3) and frames.dtype == np.float32
    assert 0.0 <= frames.min() and frames.max() <= 1.0
    for i in range(POSES):
        theirs = mujoco_masks[f"{task}/{i}/mask"]
        assert theirs.sum() >= 20, f"{task}: the body is hardly in view ({theirs.sum()} pixels)"
        iou = (masks[i] & theirs).sum() / (masks[i] | theirs).sum()
        assert iou >= 0.9, (task, i, iou)
        # a frame does not depend on the other envs of the batch (same program, the pose twice)
        twice = np.asarray(render(jax.tree.map(lambda *x: np.stack(x), datas[i], datas[i])))
        np.testing.assert_allclose(twice[0], frames[i], atol=1e-6)
        np.testing.assert_allclose(twice[1], frames[i], atol=1e-6)


def test_expert_data_is_rendered_from_the_task_in_jit():
    """PixelWorld.generate on MJX reacher at 16x16 (the untrained expert acting by its mean, no burn-in): the
    first frame of each sequence is the rendering of its reset state, the arm moves, and the actions are
    the expert's (in [-1, 1], different between sequences)."""
    from cdjax.agents.pixel import PRESETS, PixelConfig
    from cdjax.agents.pixel.data import PixelWorld
    from cdjax.agents.experts import actor, untrained_expert

    config = PixelConfig(**PRESETS["pixel-tiny"].config).replace(burn_in=0, expert_sample=False)
    world = PixelWorld(config, actor(untrained_expert("reacher", jax.random.key(1))))
    key = jax.random.key(5)
    n, length, F = 2, 4, config.frame_stack

    @jax.jit
    def probe(key):
        data = world.generate(key, n, length)
        first = world.frame(world.reset(jax.random.split(key)[0], n))  # generate's reset key
        return data, first

    data, first = probe(key)
    frames, actions = np.asarray(data.frames), np.asarray(data.actions)
    assert frames.shape == (n, length + F - 1, 16, 16, 3) and frames.dtype == np.uint8
    assert actions.shape == (n, length, world.action_size) and np.abs(actions).max() <= 1.0
    np.testing.assert_array_equal(frames[:, 0], np.asarray(first))
    assert (frames[:, -1] != frames[:, 0]).any()  # the arm moved
    assert not np.allclose(actions[0], actions[1])  # two episodes, two observations
    assert np.isfinite(float(data.reward))
