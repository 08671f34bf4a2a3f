"""A common yardstick for dynamics models: open-loop error on fixed, held-out real trajectories.

The agent's own open-loop metric (`model/openloop_mse_k`, `_50`) measures each model on the states its own
policy visits, normalised by its own running statistics, so two arms are measured on different data and in
different units. A yardstick file holds real trajectories collected once per task by a fixed policy, kept
with the results; every model of every arm and seed is scored on the same windows in the same units:

    data = load("experiments/paper_obs_space/yardstick/ant.npz")
    windows = Windows.of(data, k=20, long=50)
    errors(model_step, windows)   # {"model/yardstick_mse_k": ..., "model/yardstick_mse_50": ...}

Scoring: from the first observation of every window the model imagines `long` steps under the window's real
actions (`rollout.open_loop`); the error at step j is the mean over observation dimensions of
((imagined - real) / scale)^2, `scale` the per-dimension standard deviation of the file's observations, averaged
over windows. Dimensions that do not move on the yardstick (standard deviation at most SCALE_FLOOR: humanoid's
observation holds 19 constant entries) are left out: dividing by their floored scale would let them swamp the
rest. Windows start every `stride` steps and stay inside each trajectory's valid part.

File (.npz, written by `save`): obs [N, T+1, O] float32, action [N, T, A] float32, length [N] int32 (valid
steps of each trajectory), scale [O] float32, optionally reward [N, T] float32 (the simulator's), and
metadata (JSON string `meta`: env, action_repeat, policy, seed, created, ...).
"""

from __future__ import annotations

import dataclasses
import json
import pathlib

import jax
import jax.numpy as jnp
import numpy as np

from cdjax.agents.obs.rollout import open_loop
from cdjax.protocol import ConfigError

SCALE_FLOOR = 1e-3  # per-dimension scales are floored here; dimensions at the floor are left out of the error


@dataclasses.dataclass(frozen=True)
class Yardstick:
    """Held-out real trajectories (numpy arrays) and what collected them."""

    obs: np.ndarray  # [N, T+1, O]
    action: np.ndarray  # [N, T, A]
    length: np.ndarray  # [N] int: valid steps per trajectory
    scale: np.ndarray  # [O]
    meta: dict
    reward: np.ndarray | None = None  # [N, T] the simulator's rewards, where the file keeps them

    @property
    def steps(self) -> int:
        return self.action.shape[1]


def scale_of(obs: np.ndarray, length: np.ndarray) -> np.ndarray:
    """Per-dimension std of the valid observations of obs [N, T+1, O] (floored at SCALE_FLOOR)."""
    valid = np.arange(obs.shape[1])[None, :] <= length[:, None]
    flat = obs[valid]
    return np.maximum(flat.std(0), SCALE_FLOOR).astype(np.float32)


def save(path: str | pathlib.Path, obs, action, length, meta: dict, reward=None) -> pathlib.Path:
    path = pathlib.Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    obs, action, length = np.asarray(obs, np.float32), np.asarray(action, np.float32), np.asarray(length, np.int32)
    extra = {} if reward is None else {"reward": np.asarray(reward, np.float32)}
    np.savez_compressed(path, obs=obs, action=action, length=length, scale=scale_of(obs, length),
                        meta=np.array(json.dumps(meta, sort_keys=True)), **extra)
    return path


def load(path: str | pathlib.Path) -> Yardstick:
    """A yardstick file; ConfigError (one sentence) when it is missing or not one."""
    path = pathlib.Path(path)
    if not path.is_file():
        raise ConfigError(f"The yardstick file {path} does not exist.")
    try:
        with np.load(path) as f:
            y = Yardstick(obs=f["obs"], action=f["action"], length=f["length"], scale=f["scale"],
                          meta=json.loads(str(f["meta"])), reward=f["reward"] if "reward" in f.files else None)
    except (OSError, KeyError, ValueError) as err:
        raise ConfigError(f"{path} is not a yardstick file ({type(err).__name__}: {err}).") from None
    N, T = y.action.shape[:2]
    if y.obs.shape[:2] != (N, T + 1) or y.length.shape != (N,) or y.scale.shape != y.obs.shape[2:]:
        raise ConfigError(f"{path} is not a yardstick file (shapes obs {y.obs.shape}, action {y.action.shape}).")
    return y


@dataclasses.dataclass(frozen=True)
class Windows:
    """The windows a model is scored on (numpy; constants of the program that scores it)."""

    start: np.ndarray  # [W, O] first observation
    action: np.ndarray  # [W, long, A] real actions
    target_k: np.ndarray  # [W, O] real observation after k steps
    target_long: np.ndarray  # [W, O] after `long` steps
    scale: np.ndarray  # [O]
    k: int
    long: int

    @classmethod
    def of(cls, y: Yardstick, k: int, long: int, stride: int = 10) -> "Windows":
        """Windows of `long` steps starting every `stride` steps inside each trajectory's valid part."""
        if not 1 <= k <= long:
            raise ValueError(f"need 1 <= k <= long, got k={k}, long={long}")
        if long > y.steps:
            raise ConfigError(f"The yardstick's trajectories have {y.steps} steps, fewer than the {long} the "
                              "long open-loop horizon needs.")
        rows = [(n, s) for n in range(y.obs.shape[0]) for s in range(0, y.steps - long + 1, stride)
                if s + long <= y.length[n]]
        if not rows:
            raise ConfigError(f"The yardstick holds no window of {long} steps inside one episode.")
        n, s = (np.array(x) for x in zip(*rows))
        steps = s[:, None] + np.arange(long)[None]
        return cls(start=y.obs[n, s], action=y.action[n[:, None], steps], target_k=y.obs[n, s + k],
                   target_long=y.obs[n, s + long], scale=y.scale, k=k, long=long)


def errors(model_step, windows: Windows) -> dict[str, jax.Array]:
    """{"model/yardstick_mse_k", "model/yardstick_mse_50"}: model_step(obs [W, O], action [W, A]) -> next obs
    [W, O] imagines every window open loop; mean squared error in units of the yardstick's scale. (The long
    horizon is named 50, as the agent's own metric, whatever `windows.long` is.)"""
    actions = jnp.swapaxes(jnp.asarray(windows.action), 0, 1)  # [long, W, A]
    _, imagined = open_loop(model_step, jnp.asarray(windows.start), actions)  # [long, W, O]
    keep = np.flatnonzero(windows.scale > SCALE_FLOOR)  # static: the dimensions that move on the yardstick
    scale = jnp.asarray(windows.scale[keep])

    def mse(pred, target):
        return (((pred[:, keep] - jnp.asarray(target)[:, keep]) / scale) ** 2).mean()

    return {"model/yardstick_mse_k": mse(imagined[windows.k - 1], windows.target_k),
            "model/yardstick_mse_50": mse(imagined[windows.long - 1], windows.target_long)}


def check_matches(y: Yardstick, env: str, obs_size: int, action_size: int, path) -> None:
    """ConfigError (one sentence) when a yardstick was collected on another task."""
    if y.meta.get("env") != env or y.obs.shape[-1] != obs_size or y.action.shape[-1] != action_size:
        raise ConfigError(f"The yardstick {path} was collected on {y.meta.get('env')!r} (observations "
                          f"{y.obs.shape[-1]}, actions {y.action.shape[-1]}), not on {env!r} ({obs_size}, {action_size}).")
