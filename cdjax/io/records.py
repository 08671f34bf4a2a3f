"""What the run directory's files hold: run.json's fields and their checks (`check_record`), dataclasses and
HParams as JSON, and the rows of metrics.jsonl and phase.jsonl (`metric_rows`, `phase_rows`)."""

from __future__ import annotations

import dataclasses
import math
import os
from typing import Any, Mapping, Sequence

import numpy as np

from cdjax.errors import RunDirError

RUN_VERSION = 2
READABLE_VERSIONS = (1, 2)  # run.json versions that plots and evaluation read; only RUN_VERSION resumes


def json_float(x) -> float | None:
    """A float for JSON: NaN and infinities become None (null)."""
    x = float(x)
    return x if math.isfinite(x) else None


def _plain(value):
    """A numpy scalar as the Python number it holds (JSON writes those); anything else as it is."""
    return value.item() if isinstance(value, np.generic) else value


def dataclass_to_json(obj) -> dict:
    """A (frozen) dataclass of scalars and tuples as JSON fields (tuples become lists, numpy scalars numbers)."""
    return {f.name: ([_plain(x) for x in v] if isinstance(v := getattr(obj, f.name), tuple) else _plain(v))
            for f in dataclasses.fields(obj)}


def dataclass_from_json(cls, fields: Mapping[str, Any], where: str = "run.json"):
    """Inverse of dataclass_to_json: unknown names are an error (RunDirError), missing ones default."""
    known = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(fields) - known)
    if unknown:
        raise RunDirError(f"{where} names {cls.__name__} fields this cdjax does not know: {', '.join(unknown)}.")
    return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in fields.items()})


def hparams_to_json(hp) -> dict:
    return {f.name: float(getattr(hp, f.name)) for f in dataclasses.fields(hp)}


# What each field of run.json holds (checked when it is read, for the fields it has: a version 1 record lacks some).
def _whole(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool) or isinstance(v, float) and v.is_integer()


def _number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _count(v) -> bool:
    return _whole(v) and v >= 0


def _list_of(pred):
    return lambda v: isinstance(v, list) and all(pred(x) for x in v)


def _dict_of(pred):
    return lambda v: isinstance(v, dict) and all(isinstance(k, str) and pred(x) for k, x in v.items())


def _panel(v) -> bool:
    return isinstance(v, list) and len(v) == 3 and isinstance(v[0], str) and isinstance(v[1], str) and isinstance(
        v[2], bool)


def _metric_names(v) -> bool:
    return (isinstance(v, dict) and all(isinstance(v.get(k, ""), str) for k in ("return", "discounted_return"))
            and _list_of(_panel)(v.get("panels", [])) and isinstance(v.get("skipped", ""), (str, type(None))))


_RECORD = {  # field -> (what it must be, in words; test)
    "setting": ("a setting's name", lambda v: isinstance(v, str)),
    "base_config": ("an object of Config fields", lambda v: isinstance(v, dict)),
    "arms": ("a non-empty list of arms", lambda v: isinstance(v, list) and len(v) > 0),
    "grid": ("an object of hyper-parameter value lists", _dict_of(_list_of(_number))),
    "seeds": ("a positive integer", lambda v: _whole(v) and v >= 1),
    "seed": ("a non-negative integer", _count),
    "phase": ("an object or null", lambda v: v is None or isinstance(v, dict)),
    "final_eval": ("true or false", lambda v: isinstance(v, bool)),
    "metrics": ("an object of metric names", _metric_names),
    "command": ("a string", lambda v: isinstance(v, str)),
    **{name: ("a non-negative integer", _count) for name in (
        "total_env_steps", "requested_env_steps", "num_updates", "env_steps_per_update", "chunk_updates",
        "checkpoint_every", "eval_every", "eval_episodes", "bootstrap_reps")},
}
_ARM = {
    "name": ("an arm's name", lambda v: isinstance(v, str) and v != ""),
    "arm": ("a string", lambda v: v is None or isinstance(v, str)),
    "config": ("an object of Config fields", lambda v: isinstance(v, dict)),
    "hparams": ("a list of objects of numbers", _list_of(_dict_of(_number))),
    "hp_labels": ("a list of strings", _list_of(lambda x: isinstance(x, str))),
    "num_updates": ("a non-negative integer", _count),
    "phase_env_steps": ("a non-negative integer", _count),
    "total_env_steps": ("a non-negative integer", _count),
}


def _short(value, limit: int = 60) -> str:
    text = repr(value)
    return text if len(text) <= limit else text[:limit] + "..."


def check_record(run: dict, where: str | os.PathLike = "run.json") -> None:
    """RunDirError (one sentence naming the field) for a run.json field of the wrong type."""
    def refuse(name: str, what: str, value, got: str = "") -> None:
        raise RunDirError(f"{where}: {name} must be {what}, got {got or _short(value)}; put back the run.json the "
                          "sweep wrote.")

    for name, (what, ok) in _RECORD.items():
        if name in run and not ok(run[name]):
            refuse(name, what, run[name])
    for i, arm in enumerate(run.get("arms", [])):
        if not isinstance(arm, dict):
            refuse(f"arms[{i}]", "an object", arm)
        if "name" not in arm:  # every reader of the logs (plot, eval, a resume) finds an arm's rows by its name
            refuse(f"arms[{i}].name", _ARM["name"][0], None, got="no name")
        for name, (what, ok) in _ARM.items():
            if name in arm and not ok(arm[name]):
                refuse(f"arms[{i}].{name}", what, arm[name])
        if "hparams" in arm and "hp_labels" in arm and len(arm["hparams"]) != len(arm["hp_labels"]):
            refuse(f"arms[{i}].hp_labels", f"one label per hparams entry ({len(arm['hparams'])})", arm["hp_labels"])
    names = [a.get("name") for a in run.get("arms", [])]
    if len(set(names)) != len(names):
        refuse("arms", "a list of arms with distinct names", names)


# ---------------------------------------------------------------------------------------------------
# JSONL logs


def metric_rows(arm: str, labels: Sequence[str], num_seeds: int, metrics: Mapping, first_update: int,
                steps_per_update: int, wall_start: float, wall_end: float, steps_offset: int = 0) -> list[dict]:
    """Rows of metrics.jsonl for one chunk of one arm.

    metrics: {name: [R, n]} on the host, runs hp-major (run r = i * num_seeds + s). `update` counts the
    updates done (1-based), `env_steps` the environment steps of that run so far (`steps_offset`: those
    of a phase before the first update), `wall_s` the training wall-clock of the sweep (compile
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
                row.update({name: json_float(metrics[name][r, j]) for name in names})
                rows.append(row)
    return rows


def phase_rows(arm: str, labels: Sequence[str], num_seeds: int, info: Mapping, env_steps: int, wall_start: float,
               wall_end: float, as_metrics: Mapping[str, str]) -> list[dict]:
    """Rows (update 0) of a phase of one arm: info {name: [R]} on the host, runs hp-major.

    Every diagnostic is kept under "phase/<name>"; those named in `as_metrics` are also the row's metric
    of the given name (e.g. the distilled policy's return is the first point of the return curve).
    """
    rows = []
    for i, label in enumerate(labels):
        for s in range(num_seeds):
            r = i * num_seeds + s
            row = {"arm": arm, "hp": label, "seed": s, "update": 0, "env_steps": env_steps,
                   "wall_s": round(wall_end, 3), "phase_wall_s": round(wall_end - wall_start, 3)}
            row.update({f"phase/{name}": json_float(value[r]) for name, value in sorted(info.items())})
            row.update({new: json_float(info[old][r]) for old, new in as_metrics.items() if old in info})
            rows.append(row)
    return rows
