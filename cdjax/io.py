"""The run directory: resolved config, JSONL metrics, TensorBoard event files, orbax checkpoints.

    runs/NAME/run.json                       the resolved sweep (version 1): base config, arms with their
                                             configs, hparams and hp labels, seeds, steps, chunking, argv
    runs/NAME/metrics.jsonl                  one object per (arm, hp, seed, update); NaN written as null
    runs/NAME/tb/<arm>/<hp>/seed<s>/         TensorBoard event files (tensorboardX)
    runs/NAME/checkpoints/<arm>/<updates>/   orbax CheckpointManager: the whole TrainState of the arm
                                             (leading run axis) + the host-side progress (max_to_keep=2)
    runs/NAME/eval.jsonl, plots/, summary.md, summary.csv, videos/   written by evaluate.py and plots.py

Checkpoints are atomic (orbax writes a temporary directory and renames it when complete); a latest
checkpoint that cannot be read is skipped in favour of the previous one, with a warning.
"""

from __future__ import annotations

import dataclasses
import json
import math
import pathlib
import re
import warnings
from typing import Any, Iterable

import jax
import numpy as np

from cdjax.config import Config, HParams

RUN_VERSION = 1
MAX_TO_KEEP = 2


class RunDirError(ValueError):
    """A run directory that cannot be used as asked; the message is one sentence meant for the user."""


class CheckpointWarning(UserWarning):
    """A checkpoint could not be restored and an older one is used instead."""


# ---------------------------------------------------------------------------------------------------
# Paths and run.json


@dataclasses.dataclass(frozen=True)
class RunDir:
    path: pathlib.Path

    @property
    def run_json(self) -> pathlib.Path:
        return self.path / "run.json"

    @property
    def metrics(self) -> pathlib.Path:
        return self.path / "metrics.jsonl"

    @property
    def eval(self) -> pathlib.Path:
        return self.path / "eval.jsonl"

    @property
    def phase(self) -> pathlib.Path:
        """Diagnostics of the Mb-Mf phase (the update-0 rows of metrics.jsonl, kept apart for reading)."""
        return self.path / "phase.jsonl"

    def tb(self, arm: str, hp: str, seed: int) -> pathlib.Path:
        return self.path / "tb" / arm / hp / f"seed{seed}"

    def checkpoints(self, arm: str) -> pathlib.Path:
        return self.path / "checkpoints" / arm

    def exists(self) -> bool:
        return self.run_json.is_file()

    def read(self) -> dict:
        if not self.exists():
            raise RunDirError(f"{self.path} holds no run (no run.json); "
                              f"start one with `cdjax sweep --out {self.path}`.")
        try:
            run = json.loads(self.run_json.read_text())
        except json.JSONDecodeError as err:
            raise RunDirError(f"{self.run_json} is not valid JSON ({err.msg} at line {err.lineno}).") from None
        if run.get("version") != RUN_VERSION:
            raise RunDirError(f"{self.run_json} has version {run.get('version')!r}; "
                              f"this cdjax reads version {RUN_VERSION}.")
        return run

    def write(self, run: dict) -> None:
        """Write run.json atomically (a half-written run.json would make the directory unreadable)."""
        self.path.mkdir(parents=True, exist_ok=True)
        tmp = self.run_json.with_suffix(".json.tmp")
        tmp.write_text(json.dumps(run, indent=2) + "\n")
        tmp.replace(self.run_json)


def config_to_json(config: Config) -> dict:
    return {f.name: (list(v) if isinstance(v := getattr(config, f.name), tuple) else v)
            for f in dataclasses.fields(config)}


def config_from_json(fields: dict) -> Config:
    """Config from its JSON form (lists back to tuples); unknown names are an error, missing ones default."""
    known = {f.name for f in dataclasses.fields(Config)}
    unknown = sorted(set(fields) - known)
    if unknown:
        raise RunDirError(f"run.json names config fields this cdjax does not know: {', '.join(unknown)}.")
    return Config(**{k: tuple(v) if isinstance(v, list) else v for k, v in fields.items()})


def hparams_to_json(hp: HParams) -> dict:
    return {f.name: float(getattr(hp, f.name)) for f in dataclasses.fields(HParams)}


def hparams_from_json(fields: dict) -> HParams:
    return HParams(**{k: float(v) for k, v in fields.items()})


# ---------------------------------------------------------------------------------------------------
# Metrics


def _json_float(x) -> float | None:
    x = float(x)
    return x if math.isfinite(x) else None


def metric_rows(arm: str, labels: list[str], num_seeds: int, metrics: dict, first_update: int,
                steps_per_update: int, wall_start: float, wall_end: float, steps_offset: int = 0) -> list[dict]:
    """Rows of metrics.jsonl for one chunk of one arm.

    metrics: {name: [R, n]} on the host, runs hp-major (run r = i * num_seeds + s). `update` counts the
    updates done (1-based), `env_steps` the environment steps of that run so far (`steps_offset`: those
    of the Mb-Mf phase before the first update), `wall_s` the training wall-clock of the sweep (compile
    excluded), interpolated linearly inside the chunk.
    """
    names = sorted(metrics)
    n = next(iter(metrics.values())).shape[1]
    rows = []
    for i, label in enumerate(labels):
        for s in range(num_seeds):
            r = i * num_seeds + s
            for j in range(n):
                update = first_update + j + 1
                row = {"arm": arm, "hp": label, "seed": s, "update": update,
                       "env_steps": steps_offset + update * steps_per_update,
                       "wall_s": round(wall_start + (wall_end - wall_start) * (j + 1) / n, 3)}
                row.update({name: _json_float(metrics[name][r, j]) for name in names})
                rows.append(row)
    return rows


# Phase diagnostics that are also the curve's first point (update 0), under the PPO metrics' names.
PHASE_AS_METRIC = {"dagger/episode_return": "episode/return"}


def phase_rows(arm: str, labels: list[str], num_seeds: int, info: dict, env_steps: int, wall_start: float,
               wall_end: float) -> list[dict]:
    """Rows (update 0) of the Mb-Mf phase of one arm: info {name: [R]} on the host, runs hp-major.

    Every diagnostic is kept under "phase/<name>"; the distilled policy's return in the phase's last
    DAgger round is also the row's "episode/return", the first point of the arm's return curve.
    """
    rows = []
    for i, label in enumerate(labels):
        for s in range(num_seeds):
            r = i * num_seeds + s
            row = {"arm": arm, "hp": label, "seed": s, "update": 0, "env_steps": env_steps,
                   "wall_s": round(wall_end, 3), "phase_wall_s": round(wall_end - wall_start, 3)}
            row.update({f"phase/{name}": _json_float(value[r]) for name, value in sorted(info.items())})
            row.update({new: _json_float(info[old][r]) for old, new in PHASE_AS_METRIC.items() if old in info})
            rows.append(row)
    return rows


class MetricsLog:
    """Append-only JSONL; each chunk is written with one write call and flushed."""

    def __init__(self, path: pathlib.Path):
        self.path = path

    def append(self, rows: Iterable[dict]) -> None:
        text = "".join(json.dumps(row, allow_nan=False) + "\n" for row in rows)
        with self.path.open("a") as f:
            f.write(text)
            f.flush()

    def truncate(self, done: dict[str, int]) -> int:
        """Keep the rows of each arm up to `done[arm]` updates (those the restored checkpoints hold).

        Drops the rows a killed process wrote after its last checkpoint, and a torn last line. Returns
        the number of rows dropped.
        """
        if not self.path.exists():
            return 0
        kept, dropped = [], 0
        for line in self.path.read_text().splitlines(keepends=True):
            try:
                row = json.loads(line)
                keep = line.endswith("\n") and row["update"] <= done.get(row["arm"], 0)
            except (json.JSONDecodeError, KeyError, TypeError):
                keep = False
            if keep:
                kept.append(line)
            else:
                dropped += 1
        if dropped:
            tmp = self.path.with_suffix(".jsonl.tmp")
            tmp.write_text("".join(kept))
            tmp.replace(self.path)
        return dropped


def read_jsonl(path: pathlib.Path) -> list[dict]:
    if not path.exists():
        return []
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


class TensorBoard:
    """One tensorboardX SummaryWriter per run, opened on first use (step = env steps of the run).

    A resumed run opens its writers with `purge_step`: TensorBoard then hides the events that an
    interrupted process wrote past the restored checkpoint.
    """

    def __init__(self, run_dir: RunDir, purge_steps: dict[str, int] | None = None):
        self.run_dir = run_dir
        self.purge_steps = purge_steps or {}
        self.writers: dict[tuple, Any] = {}

    def writer(self, arm: str, hp: str, seed: int):
        key = (arm, hp, seed)
        if key not in self.writers:
            from tensorboardX import SummaryWriter

            purge = self.purge_steps.get(arm)
            self.writers[key] = SummaryWriter(str(self.run_dir.tb(arm, hp, seed)), purge_step=purge or None,
                                              flush_secs=30)
        return self.writers[key]

    def write(self, rows: Iterable[dict]) -> None:
        skip = {"arm", "hp", "seed", "update", "env_steps"}
        for row in rows:
            w = self.writer(row["arm"], row["hp"], row["seed"])
            for name, value in row.items():
                if name not in skip and value is not None:
                    w.add_scalar(name, value, row["env_steps"])

    def flush(self) -> None:
        for w in self.writers.values():
            w.flush()

    def close(self) -> None:
        for w in self.writers.values():
            w.close()
        self.writers.clear()


# ---------------------------------------------------------------------------------------------------
# Checkpoints


def _is_key(x) -> bool:
    return hasattr(x, "dtype") and jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key)


def _leaf_name(path) -> str:
    """`.params['policy']['params']['Dense_0']['kernel']` -> `params.policy.params.Dense_0.kernel`."""
    return re.sub(r"[^\w]+", ".", jax.tree_util.keystr(path)).strip(".")


def _flat_saveable(tree) -> dict:
    """The tree as {leaf path: array} as orbax stores it.

    Typed PRNG keys become their uint32 key data; empty arrays (MJX state has some, e.g. `act` of a
    model without actuator state) are left out, because orbax refuses to save zero-size arrays.
    """
    out = {}
    for path, x in jax.tree_util.tree_flatten_with_path(tree)[0]:
        if x.size == 0:
            continue
        name = _leaf_name(path)
        assert name not in out, f"two leaves named {name}"
        out[name] = jax.random.key_data(x) if _is_key(x) else x
    return out


def _unflatten(flat: dict, like):
    """Inverse of `_flat_saveable`: the tree of `like` (abstract or concrete) with the stored leaves."""
    leaves, treedef = jax.tree_util.tree_flatten_with_path(like)
    out = []
    for path, t in leaves:
        if t.size == 0:
            out.append(jax.device_put(np.zeros(t.shape, t.dtype), getattr(t, "sharding", None)))
            continue
        x = flat[_leaf_name(path)]
        out.append(jax.random.wrap_key_data(x) if _is_key(t) else x)
    return jax.tree_util.tree_unflatten(treedef, out)


class Checkpoints:
    """orbax CheckpointManager of one arm: step = updates done; items `state` (pytree) and `progress` (JSON)."""

    def __init__(self, directory: pathlib.Path):
        import orbax.checkpoint as ocp

        self._ocp = ocp
        directory.mkdir(parents=True, exist_ok=True)
        self.manager = ocp.CheckpointManager(
            directory.resolve(),
            options=ocp.CheckpointManagerOptions(max_to_keep=MAX_TO_KEEP, create=True),
            item_names=("state", "progress"),
        )

    def steps(self) -> list[int]:
        return sorted(self.manager.all_steps())

    def save(self, step: int, state, progress: dict) -> None:
        """Start an (asynchronous, atomic) save; `wait` before the state's buffers are reused."""
        ocp = self._ocp
        self.manager.save(step, args=ocp.args.Composite(state=ocp.args.StandardSave(_flat_saveable(state)),
                                                        progress=ocp.args.JsonSave(progress)), force=True)

    def wait(self) -> None:
        self.manager.wait_until_finished()

    def restore(self, abstract_state, delete_bad: bool = True) -> tuple[Any, dict] | None:
        """(state, progress) of the newest checkpoint that can be read, or None if there is none.

        `abstract_state`: jax.ShapeDtypeStruct tree (with shardings) of the state. A checkpoint that
        fails to restore is reported with a CheckpointWarning (and deleted, with `delete_bad`: a resumed
        run will write that step again), and the previous one is tried.
        """
        ocp = self._ocp
        target = {}
        for path, a in jax.tree_util.tree_flatten_with_path(abstract_state)[0]:
            if a.size:
                stored = jax.eval_shape(jax.random.key_data, a) if _is_key(a) else a
                target[_leaf_name(path)] = jax.ShapeDtypeStruct(stored.shape, stored.dtype, sharding=a.sharding)
        for step in reversed(self.steps()):
            try:
                out = self.manager.restore(step, args=ocp.args.Composite(
                    state=ocp.args.StandardRestore(target), progress=ocp.args.JsonRestore()))
                state = _unflatten(dict(out["state"]), abstract_state)
                progress = dict(out["progress"])
                if progress.get("updates") != step:
                    raise ValueError(f"progress says {progress.get('updates')} updates")
                _check_structure(state, abstract_state)
            except Exception as err:  # noqa: BLE001 - any failure to read means: use the previous one
                warnings.warn(f"Checkpoint {self.manager.directory}/{step} cannot be restored "
                              f"({type(err).__name__}: {str(err).splitlines()[0][:200] if str(err) else ''}); "
                              "falling back to the previous one.", CheckpointWarning, stacklevel=2)
                if delete_bad:
                    self.manager.delete(step)
                continue
            return state, progress
        return None

    def close(self) -> None:
        self.manager.wait_until_finished()
        self.manager.close()


def _check_structure(state, abstract_state) -> None:
    """The restored tree has the expected shapes and dtypes (a wrong-but-readable file must not pass)."""
    for got, want in zip(jax.tree.leaves(state), jax.tree.leaves(abstract_state)):
        if got.shape != want.shape or got.dtype != want.dtype:
            raise ValueError(f"leaf {got.shape} {got.dtype} where {want.shape} {want.dtype} was expected")


def host(tree):
    """Device arrays -> numpy (blocks until they are computed)."""
    return jax.tree.map(np.asarray, jax.device_get(tree))


__all__ = ["RunDir", "RunDirError", "CheckpointWarning", "Checkpoints", "MetricsLog", "TensorBoard",
           "metric_rows", "read_jsonl", "config_to_json", "config_from_json", "hparams_to_json",
           "hparams_from_json", "host"]
