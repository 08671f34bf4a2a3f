"""Frames rendered inside jit: one `mujoco.mjx.ray` per pixel, Lambertian shading with the geoms' colours.

    camera = pixels.camera_for("halfcheetah")         # the model's tracking camera; reacher/pusher: fixed views
    renderer = pixels.make_renderer(env.sys.mj_model, camera, size=64)
    frame = renderer.render(pipeline_state)                   # [64, 64, 3] float32 in [0, 1]; jit and vmap freely

mjx 3.17's `ray` intersects planes, spheres, capsules, ellipsoids, boxes and meshes (not cylinders); the
Brax MJX scenes of halfcheetah, reacher and pusher use only planes, spheres and capsules. The camera's
rays follow MuJoCo's pinhole (vertical field of view `fovy`, square pixels, pixel centres), so the body
silhouette matches MuJoCo's own renderer at the same camera (tests/test_pixels.py). Shading is a
headlight: colour x (AMBIENT + (1 - AMBIENT) x |cos| between the ray and the surface normal). Planes get a
checker pattern of CHECKER metres, so that a tracking camera shows the motion over the floor (the
halfcheetah floor is textured in MuJoCo too); rays that hit nothing are BACKGROUND.

Visibility as MuJoCo's default: geoms of groups 0-2 whose colour is not fully transparent. The frame's
body mask (pixels whose geom belongs to a body other than the world) is what the silhouette test compares.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np

AMBIENT = 0.35  # share of a geom's colour seen without light
CHECKER = 0.5  # side of a plane's checker squares, metres
BACKGROUND = (0.55, 0.7, 0.85)  # sky colour of rays that hit nothing
VISIBLE_GROUPS = (1, 1, 1, 0, 0, 0)  # MuJoCo's default: geom groups 0, 1 and 2 are drawn
PLANE, SPHERE, CAPSULE, ELLIPSOID, BOX = 0, 2, 3, 4, 6  # mjtGeom values that `normal_local` handles


@dataclasses.dataclass(frozen=True)
class Camera:
    """A camera: the model's camera `name`, or a fixed free camera (MuJoCo's mjvCamera parameters)."""

    name: str = ""  # a camera of the model (e.g. halfcheetah's "track"); empty: the free camera below
    lookat: tuple[float, float, float] = (0.0, 0.0, 0.0)  # point looked at, metres
    distance: float = 1.0  # from the camera to `lookat`, metres
    azimuth: float = 90.0  # degrees, about +z
    elevation: float = -45.0  # degrees; negative looks down


# A camera external to the agent for each pixel task (halfcheetah: its tracking camera, as the authors').
CAMERAS = {
    "halfcheetah": Camera(name="track"),
    "reacher": Camera(lookat=(0.0, 0.0, 0.0), distance=0.6, azimuth=90.0, elevation=-80.0),
    "pusher": Camera(lookat=(0.35, -0.25, -0.25), distance=1.9, azimuth=135.0, elevation=-45.0),
}


def camera_for(env_name: str) -> Camera:
    if env_name not in CAMERAS:
        raise KeyError(f"no pixel camera for env {env_name!r}; one of {sorted(CAMERAS)}")
    return CAMERAS[env_name]


def free_camera_frame(camera: Camera) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(position, forward, up, right) of a free camera, as MuJoCo's mjv_cameraFrame computes them."""
    az, el = np.deg2rad(camera.azimuth), np.deg2rad(camera.elevation)
    forward = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    up = np.array([-np.sin(el) * np.cos(az), -np.sin(el) * np.sin(az), np.cos(el)])
    right = np.cross(forward, up)
    position = np.asarray(camera.lookat, np.float64) - camera.distance * forward
    return position, forward, up, right


def pixel_offsets(size: int, fovy_deg: float) -> np.ndarray:
    """[size, size, 2] (x right, y up) of each pixel centre on the image plane at unit distance; row 0 on top."""
    half = np.tan(np.deg2rad(fovy_deg) / 2)
    centres = (np.arange(size) + 0.5) / size * 2 - 1  # -1..1 left to right
    x = np.broadcast_to(centres[None, :] * half, (size, size))
    y = np.broadcast_to(-centres[:, None] * half, (size, size))
    return np.stack([x, y], -1).astype(np.float32)


def normal_local(geom_type: jax.Array, size: jax.Array, p: jax.Array) -> jax.Array:
    """The outward surface normal (unnormalised) at the point p [3] of a geom, in the geom's frame."""
    capsule_axis = jnp.array([0.0, 0.0, 1.0]) * jnp.clip(p[2], -size[1], size[1])
    safe = jnp.where(size > 0, size, 1.0)
    box_axis = jnp.argmax(jnp.abs(p) / safe)
    box = jnp.where(jnp.arange(3) == box_axis, jnp.sign(p), 0.0)
    return jnp.select(
        [geom_type == PLANE, geom_type == SPHERE, geom_type == CAPSULE, geom_type == ELLIPSOID, geom_type == BOX],
        [jnp.array([0.0, 0.0, 1.0]), p, p - capsule_axis, p / safe**2, box], p)


@dataclasses.dataclass(frozen=True)
class Renderer:
    render: Callable[[Any], jax.Array]  # mjx Data -> [S, S, 3] float32 frame in [0, 1]
    body_mask: Callable[[Any], jax.Array]  # mjx Data -> [S, S] bool: the pixel sees a geom of a non-world body
    fovy: float  # vertical field of view, degrees


def make_renderer(mj_model, camera: Camera, size: int = 64) -> Renderer:
    """A `Renderer` of frames [size, size, 3] and body masks [size, size] from `camera`.

    mj_model: the scene's MjModel (a Brax env's `sys.mj_model`), closed over, not traced; data: an mjx Data
    (a Brax pipeline state) with geom_xpos, geom_xmat and cam_xpos/cam_xmat from forward kinematics.
    """
    import mujoco
    from mujoco import mjx  # the env layer is the one place importing mujoco

    model = mjx.put_model(mj_model)
    if mj_model.nmat == 0:  # mjx 3.17's ray indexes mat_rgba[geom_matid] even without materials: give it one row
        model = model.replace(mat_rgba=jnp.ones((1, 4), jnp.float32))
    geom_type = np.asarray(model.geom_type)
    unsupported = set(geom_type.tolist()) - {PLANE, SPHERE, CAPSULE, ELLIPSOID, BOX}
    if unsupported:
        raise ValueError(f"geom types {sorted(unsupported)} are not rendered by this renderer (mjx.ray)")
    cam_id = -1
    if camera.name:
        cam_id = mujoco.mj_name2id(mj_model, mujoco.mjtObj.mjOBJ_CAMERA, camera.name)
        if cam_id < 0:
            raise ValueError(f"the model has no camera named {camera.name!r}")
        fovy = float(np.asarray(model.cam_fovy)[cam_id])
    else:
        fovy = float(mj_model.vis.global_.fovy)
    offsets = jnp.asarray(pixel_offsets(size, fovy))
    rgba = np.asarray(model.geom_rgba, np.float32)
    matid = np.asarray(model.geom_matid)
    if len(matid) and (matid >= 0).any():  # a material's colour replaces the geom's, as in MuJoCo
        mat_rgba = np.asarray(model.mat_rgba, np.float32)
        rgba = np.where((matid >= 0)[:, None], mat_rgba[np.maximum(matid, 0)], rgba)
    colour = jnp.asarray(rgba[:, :3])
    geom_types = jnp.asarray(geom_type)
    geom_size = jnp.asarray(np.asarray(model.geom_size, np.float32))
    is_body = jnp.asarray(np.asarray(model.geom_bodyid) != 0)
    free = [jnp.asarray(v, jnp.float32) for v in free_camera_frame(camera)]

    def pose(data):
        if cam_id < 0:
            return free
        xmat = data.cam_xmat[cam_id]  # columns: camera x (right), y (up), z (backwards)
        return data.cam_xpos[cam_id], -xmat[:, 2], xmat[:, 1], xmat[:, 0]

    def cast(data):
        """(distance [S, S], geom id [S, S], ray directions [S, S, 3], camera position [3])."""
        position, forward, up, right = pose(data)
        dirs = forward + offsets[..., :1] * right + offsets[..., 1:] * up
        dirs = dirs / jnp.linalg.norm(dirs, axis=-1, keepdims=True)
        one = lambda v: mjx.ray(model, data, position, v, geomgroup=VISIBLE_GROUPS)
        dist, geom = jax.vmap(jax.vmap(one))(dirs)
        return dist, geom, dirs, position

    def shade(data, dist, geom, direction, position):
        hit = geom >= 0
        g = jnp.maximum(geom, 0)
        point = position + dist * direction
        xmat, xpos = data.geom_xmat[g], data.geom_xpos[g]
        local = xmat.T @ (point - xpos)
        normal = xmat @ normal_local(geom_types[g], geom_size[g], local)
        normal = normal / jnp.maximum(jnp.linalg.norm(normal), 1e-9)
        light = AMBIENT + (1 - AMBIENT) * jnp.abs(normal @ direction)
        checker = jnp.where(geom_types[g] == PLANE,
                            0.75 + 0.25 * (jnp.floor(local[0] / CHECKER) + jnp.floor(local[1] / CHECKER)) % 2, 1.0)
        return jnp.where(hit, colour[g] * light * checker, jnp.asarray(BACKGROUND, jnp.float32))

    def render(data) -> jax.Array:
        dist, geom, dirs, position = cast(data)
        per_pixel = jax.vmap(jax.vmap(shade, in_axes=(None, 0, 0, 0, None)), in_axes=(None, 0, 0, 0, None))
        return jnp.clip(per_pixel(data, dist, geom, dirs, position), 0.0, 1.0).astype(jnp.float32)

    def body_mask(data) -> jax.Array:
        _, geom, _, _ = cast(data)
        return (geom >= 0) & is_body[jnp.maximum(geom, 0)]

    return Renderer(render=render, body_mask=body_mask, fovy=fovy)
