"""Policy evaluation on fresh episodes, its JSONL records, and videos.

`evaluate` is pure (jit/vmap it yourself, or use `make_evaluator`): it runs `episodes` environments
side by side, each for exactly one episode, with the trainer's policy, and returns per-episode
undiscounted and discounted returns and lengths. `render_video` is a host-side entry point: it rolls
one episode of a single MJX environment and writes frames from MuJoCo's offscreen renderer; when
rendering is not possible it says why in one sentence and returns None (it never raises).

    evaluator = make_evaluator(trainer, episodes=10, deterministic=True)
    results = evaluator(state.params, state.norms, keys, hps)   # every input with a leading run axis [R]
    append_jsonl(run_dir / "eval.jsonl", eval_records(results, arm="cd-a1", hp_labels=labels,
                                                      seeds=range(num_seeds), deterministic=True))
"""

from __future__ import annotations

import importlib.util
import json
import os
import pathlib
from typing import Any, Callable, Iterable, Sequence

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from cdjax.config import HParams
from cdjax.envs import BatchedEnv, EnvState
from cdjax.train import Trainer


@struct.dataclass
class _EvalCarry:
    env_state: EnvState
    t: jax.Array  # [] int32 agent steps taken
    ret: jax.Array  # [E] undiscounted return, frozen once the episode ended
    disc_ret: jax.Array  # [E] discounted return, frozen once the episode ended
    disc: jax.Array  # [E] gamma^t of the next reward
    length: jax.Array  # [E] int32 agent steps inside the episode
    done: jax.Array  # [E] bool: the episode ended (termination, time-out or non-finite physics)
    terminated: jax.Array  # [E] bool: it ended by a task termination
    invalid: jax.Array  # [E] bool: it ended because the physics went non-finite
    key: jax.Array


def evaluate(trainer: Trainer, params: dict, norms: Any, key: jax.Array, *, episodes: int, hp: HParams,
             deterministic: bool, max_steps: int | None = None) -> dict[str, jax.Array]:
    """One episode in each of `episodes` fresh environments, acting with `trainer.act`.

    deterministic=True acts with tanh(mean) (`trainer.act(..., None)`); otherwise with a sampled action.
    The loop stops when every environment has ended its first episode (termination, time-out at
    `config.episode_length`, or non-finite physics) or after `max_steps` agent steps (episodes still
    running then are cut: `finished` is False). Rewards after an episode's end are ignored.

    Returns arrays [E]: "return", "discounted_return" (discount hp.gamma, the first reward undiscounted),
    "length" (int32), "terminated", "finished", "valid" (bool), "initial_obs" [E, O]; and scalars
    "return_mean", "discounted_return_mean", "length_mean".
    """
    config = trainer.config
    agent_steps = -(-config.episode_length // config.action_repeat)  # the time-out counts physics steps
    horizon = agent_steps if max_steps is None else min(int(max_steps), agent_steps)
    env = BatchedEnv(trainer.env.env, episodes, config.episode_length, config.action_repeat, config.reset_mode)
    gamma = jnp.asarray(hp.gamma, jnp.float32)
    key_reset, key_act = jax.random.split(key)
    del key
    env_state = env.reset(key_reset)
    zeros = jnp.zeros((episodes,), jnp.float32)
    false = jnp.zeros((episodes,), bool)
    carry = _EvalCarry(env_state=env_state, t=jnp.zeros((), jnp.int32), ret=zeros, disc_ret=zeros,
                       disc=jnp.ones((episodes,), jnp.float32), length=jnp.zeros((episodes,), jnp.int32),
                       done=false, terminated=false, invalid=false, key=key_act)

    def running(c: _EvalCarry) -> jax.Array:
        return (c.t < horizon) & ~c.done.all()

    def step(c: _EvalCarry) -> _EvalCarry:
        key, key_step = jax.random.split(c.key)
        action = trainer.act(params, norms, c.env_state.obs, None if deterministic else key_step)
        env_state, out = env.step(c.env_state, action)
        live = ~c.done
        reward = jnp.where(live, out.reward, 0.0)
        ended = out.terminated | out.truncated | ~out.valid
        return _EvalCarry(
            env_state=env_state,
            t=c.t + 1,
            ret=c.ret + reward,
            disc_ret=c.disc_ret + c.disc * reward,
            disc=jnp.where(live, c.disc * gamma, c.disc),
            length=c.length + live.astype(jnp.int32),
            done=c.done | ended,
            terminated=c.terminated | (live & out.terminated),
            invalid=c.invalid | (live & ~out.valid),
            key=key,
        )

    final = jax.lax.while_loop(running, step, carry)
    return {
        "return": final.ret,
        "discounted_return": final.disc_ret,
        "length": final.length,
        "terminated": final.terminated,
        "finished": final.done,
        "valid": ~final.invalid,
        "initial_obs": env_state.obs,
        "return_mean": final.ret.mean(),
        "discounted_return_mean": final.disc_ret.mean(),
        "length_mean": final.length.astype(jnp.float32).mean(),
    }


def make_evaluator(trainer: Trainer, episodes: int, deterministic: bool,
                   max_steps: int | None = None) -> Callable[..., dict[str, jax.Array]]:
    """jit(vmap(evaluate)) over runs: fn(params [R], norms [R], keys [R], hps [R]) -> results [R, ...].

    Feed it a sweep's TrainState directly (`state.params`, `state.norms`) and the stacked HParams of the
    same runs (their gamma discounts the returns).
    """

    def one(params, norms, key, hp):
        return evaluate(trainer, params, norms, key, episodes=episodes, hp=hp, deterministic=deterministic,
                        max_steps=max_steps)

    return jax.jit(jax.vmap(one))


# ---------------------------------------------------------------------------------------------------
# eval.jsonl


def eval_records(results: dict, *, arm: str, hp_labels: Sequence[str], seeds: Sequence[int],
                 deterministic: bool, **extra) -> list[dict]:
    """One JSON-ready record per run of a `make_evaluator` result (leaves [R, E], runs hp-major).

    Run r = i * len(seeds) + s belongs to hp_labels[i] and seeds[s]; runs past len(hp_labels) *
    len(seeds) (device padding) are dropped. `extra` (e.g. update=..., env_steps=...) is copied into
    every record. Keys: arm, hp, seed, deterministic, episodes, eval/return, eval/discounted_return,
    eval/length (means over episodes), eval/terminated_fraction, and the per-episode lists
    returns, discounted_returns, lengths.
    """
    host = {name: np.asarray(value) for name, value in results.items()}
    seeds = list(seeds)
    records = []
    for i, label in enumerate(hp_labels):
        for s, seed in enumerate(seeds):
            r = i * len(seeds) + s
            ret, disc, length = host["return"][r], host["discounted_return"][r], host["length"][r]
            records.append({
                "arm": arm, "hp": label, "seed": int(seed), **extra,
                "deterministic": bool(deterministic), "episodes": int(ret.shape[0]),
                "eval/return": _json_float(ret.mean()),
                "eval/discounted_return": _json_float(disc.mean()),
                "eval/length": float(length.mean()),
                "eval/terminated_fraction": float(host["terminated"][r].mean()),
                "returns": [_json_float(x) for x in ret],
                "discounted_returns": [_json_float(x) for x in disc],
                "lengths": [int(x) for x in length],
            })
    return records


def append_jsonl(path: str | os.PathLike, records: Iterable[dict]) -> pathlib.Path:
    """Append records, one JSON object per line (NaN written as null)."""
    path = pathlib.Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("a") as f:
        for record in records:
            f.write(json.dumps(record, allow_nan=False) + "\n")
    return path


def _json_float(x) -> float | None:
    x = float(x)
    return x if np.isfinite(x) else None


# ---------------------------------------------------------------------------------------------------
# videos


def render_video(trainer: Trainer, params: dict, norms: Any, key: jax.Array, path: str | os.PathLike, *,
                 steps: int, deterministic: bool = True, width: int = 320, height: int = 240
                 ) -> pathlib.Path | None:
    """Roll one episode (at most `steps` agent steps) of one environment and write it as a video.

    Frames come from MuJoCo's offscreen renderer on the env's MjModel (the "track" camera when the
    model has one). Writes mp4 when imageio has an ffmpeg backend (imageio-ffmpeg or PyAV), else a gif
    next to `path` (same name, .gif). Returns the written path, or None after printing one sentence
    saying what is missing (no MjModel, e.g. the point env; no OpenGL context: start Python with
    MUJOCO_GL=egl, or MUJOCO_GL=osmesa with Debian's libosmesa6). Never raises for those reasons.
    """
    try:
        import mujoco
    except ImportError as err:  # pragma: no cover - mujoco is a dependency
        return _unavailable(f"rendering needs the mujoco package ({err})")
    single = trainer.env.env
    mj_model = getattr(getattr(single, "sys", None), "mj_model", None)
    if mj_model is None:
        return _unavailable(f"env {trainer.config.env!r} has no MuJoCo model to render")
    try:
        renderer = mujoco.Renderer(mj_model, height=height, width=width)
    except Exception as err:  # noqa: BLE001 - every GL failure means the same thing to the user
        backend = os.environ.get("MUJOCO_GL", "")
        return _unavailable(
            f"no OpenGL context for MuJoCo's renderer (MUJOCO_GL={backend!r}: {type(err).__name__}); start Python "
            "with MUJOCO_GL=egl (GPU, or Mesa's EGL on CPU) or MUJOCO_GL=osmesa (apt-get install libosmesa6)")
    try:
        qpos, qvel, n = _rollout_states(trainer, params, norms, key, steps, deterministic)
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
    fps = 1.0 / (float(getattr(single, "dt", 0.05)) * trainer.config.action_repeat)
    return _write_frames(pathlib.Path(path), frames, fps)


def _unavailable(reason: str) -> None:
    print(f"No video: {reason}.")
    return None


def _rollout_states(trainer: Trainer, params, norms, key, steps: int, deterministic: bool):
    """(qpos [n, nq], qvel [n, nv], n): the reset state and the state after each agent step, up to the
    first step that ends the episode (inclusive) or `steps` steps."""
    config = trainer.config
    single = trainer.env.env
    steps = max(1, min(int(steps), config.episode_length))

    def physics(state):
        ps = state.pipeline_state  # mjx Data (qpos, qvel), or an older Brax pipeline state (q, qd)
        return (ps.qpos, ps.qvel) if hasattr(ps, "qpos") else (ps.q, ps.qd)

    @jax.jit
    def rollout(params, norms, key):
        key_reset, key_act = jax.random.split(key)
        state = single.reset(key_reset)

        def step(carry, key_step):
            state, done = carry
            action = trainer.act(params, norms, state.obs[None].astype(jnp.float32),
                                 None if deterministic else key_step)[0]
            for _ in range(config.action_repeat):
                state = single.step(state, action)
            q, qd = physics(state)
            finite = jnp.isfinite(q).all() & jnp.isfinite(qd).all()
            ended = (state.done > 0.5) | ~finite
            return (state, done | ended), (q, qd, done)

        (_, _), (q, qd, was_done) = jax.lax.scan(step, (state, jnp.zeros((), bool)),
                                                 jax.random.split(key_act, steps))
        q0, qd0 = physics(state)
        return (jnp.concatenate([q0[None], q]), jnp.concatenate([qd0[None], qd]),
                jnp.concatenate([jnp.zeros((1,), bool), was_done]))

    q, qd, was_done = jax.device_get(rollout(params, norms, key))
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
