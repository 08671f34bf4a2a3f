"""A run directory's logs as curves: metrics.jsonl and eval.jsonl read into per-seed arrays (`load_metrics`,
`load_eval`), their per-seed statistics, and the seeds of several runs pooled."""

from __future__ import annotations

import dataclasses
import math
import pathlib
from typing import Callable

import numpy as np

from cdjax import io, stats


RETURN = "episode/return"  # the return metric of logs whose run.json names none
DISC_RETURN = "episode/discounted_return"
# (metric name, panel title, log scale) of the diagnostics figure of logs whose run.json names none.
MODEL_PANELS = (
    ("model/openloop_mse_k", "open-loop MSE at k steps", True),
    ("model/openloop_mse_50", "open-loop MSE at eval_horizon (50 unless set)", True),
    ("loss/consistency", "consistency loss", True),
    ("encoder/spread_real", "encoder spread (real)", False),
    ("encoder/spread_imagined", "encoder spread (imagined)", False),
)
ROW_KEYS = ("arm", "hp", "seed", "update")  # identify a row; every other numeric field is a metric
SKIPPED = ("train/skipped_steps", "train/skipped_step")  # the skipped-step counts of logs whose run.json names none


@dataclasses.dataclass(frozen=True)
class Names:
    """Which logged metrics the figures and tables read."""

    ret: str = RETURN
    discounted_ret: str = DISC_RETURN
    panels: tuple[tuple[str, str, bool], ...] = MODEL_PANELS
    skipped: str | None = None  # optimiser steps skipped for a non-finite loss or gradient, per update

    @classmethod
    def of(cls, info: dict) -> "Names":
        """From run.json's "metrics" (written by the runner from the setting), else the defaults."""
        m = info.get("metrics") or {}
        return cls(m.get("return", RETURN), m.get("discounted_return", DISC_RETURN),
                   tuple(tuple(p) for p in m.get("panels", MODEL_PANELS)), m.get("skipped"))


@dataclasses.dataclass
class Curves:
    """Every logged metric of one (arm, hp label) across seeds and updates, NaN where missing."""

    arm: str  # arm name in the run (e.g. "cd-a1")
    hp: str  # hyper-parameter label (e.g. "alpha=1.0")
    arm_type: str | None  # "cd", "mbmf" or "model-free" when run.json says so
    seeds: np.ndarray  # [S] int seed ids
    updates: np.ndarray  # [U] int update indices (union over seeds, sorted)
    env_steps: np.ndarray  # [U] float environment steps at each update (NaN if never logged)
    present: np.ndarray  # [S, U] bool: seed s logged update u
    metrics: dict[str, np.ndarray]  # name -> [S, U] float (includes "wall_s" when logged)

    @property
    def label(self) -> str:
        return self.arm if not self.hp else f"{self.arm} {self.hp}"


# ---------------------------------------------------------------------------------------------------
# loading


def _float(value) -> float:
    if value is None:
        return math.nan
    try:
        return float(value)
    except (TypeError, ValueError):
        return math.nan


def _say_skipped(path: pathlib.Path, rows: io.Rows, say: Callable[[str], None] | None) -> None:
    if rows.skipped and say is not None:
        say(f"{path}: left out {rows.skipped} line(s) that do not parse as rows (a torn line left by a process "
            "killed while writing, bytes that are not UTF-8, or fields of the wrong types).")


def load_metrics(run_dir: str | pathlib.Path, say: Callable[[str], None] | None = None
                 ) -> dict[tuple[str, str], Curves]:
    """metrics.jsonl as {(arm, hp label): Curves}, ordered as run.json lists arms and hp labels.

    A repeated (arm, hp, seed, update) row (a resumed chunk) keeps the last one written. Lines that do not
    parse (a process killed while writing) are left out, and `say` is told how many.
    """
    run_dir = pathlib.Path(run_dir)
    info = io.RunDir(run_dir).read_if_present()
    names = Names.of(info)
    order: list[tuple[str, str]] = []
    arm_types: dict[str, str] = {}
    for arm in info.get("arms", []):
        arm_types[arm["name"]] = arm.get("arm") or arm.get("config", {}).get("arm")
        order += [(arm["name"], str(label)) for label in arm.get("hp_labels", [""])]

    rows = io.read_jsonl(run_dir / "metrics.jsonl")
    _say_skipped(run_dir / "metrics.jsonl", rows, say)
    groups: dict[tuple[str, str], dict[tuple[int, int], dict]] = {}
    for row in rows:  # every row has arm, seed and update of their types (io.metric_row_ok)
        key = (row["arm"], row.get("hp", ""))
        groups.setdefault(key, {})[(int(row["seed"]), int(row["update"]))] = row
    keys = [k for k in order if k in groups] + [k for k in groups if k not in order]
    return {key: _curves(key, groups[key], arm_types.get(key[0]), names) for key in keys}


def _curves(key: tuple[str, str], rows: dict[tuple[int, int], dict], arm_type: str | None, names: Names) -> Curves:
    seeds = np.array(sorted({s for s, _ in rows}), dtype=int)
    updates = np.array(sorted({u for _, u in rows}), dtype=int)
    s_index = {s: i for i, s in enumerate(seeds)}
    u_index = {u: i for i, u in enumerate(updates)}
    metric_names = sorted({n for row in rows.values() for n in row if n not in ROW_KEYS and n != "env_steps"})
    shape = (len(seeds), len(updates))
    metrics = {n: np.full(shape, np.nan) for n in metric_names}
    steps = np.full(shape, np.nan)
    present = np.zeros(shape, bool)
    for (s, u), row in rows.items():
        i, j = s_index[s], u_index[u]
        present[i, j] = True
        steps[i, j] = _float(row.get("env_steps"))
        for n in metric_names:
            if n in row:
                metrics[n][i, j] = _float(row[n])
    keep = (names.ret, names.discounted_ret)
    metrics = {n: v for n, v in metrics.items() if not np.all(np.isnan(v)) or n in keep}
    return Curves(arm=key[0], hp=key[1], arm_type=arm_type, seeds=seeds, updates=updates,
                  env_steps=stats.nan_reduce(np.nanmax, steps, axis=0), present=present, metrics=metrics)


def load_eval(run_dir: str | pathlib.Path, say: Callable[[str], None] | None = None
              ) -> dict[tuple[str, str, bool], dict[str, np.ndarray]]:
    """eval.jsonl as {(arm, hp, deterministic): {"seeds", "return", "discounted_return", "episodes"}}.

    Per seed the record of the latest evaluated update is kept (the last written when equal). Lines that cannot
    be read are left out, and `say` is told how many.
    """
    latest: dict[tuple[str, str, bool], dict[int, dict]] = {}
    rows = io.read_jsonl(pathlib.Path(run_dir) / "eval.jsonl")
    _say_skipped(pathlib.Path(run_dir) / "eval.jsonl", rows, say)
    for row in rows:  # arm and seed of their types (io.eval_row_ok)
        key = (row["arm"], row.get("hp", ""), row.get("deterministic", True))
        seed = int(row["seed"])
        old = latest.setdefault(key, {}).get(seed)
        if old is None or _float(row.get("update", -1)) >= _float(old.get("update", -1)):
            latest[key][seed] = row
    out = {}
    for key, by_seed in latest.items():
        seeds = sorted(by_seed)
        out[key] = {
            "seeds": np.array(seeds, dtype=int),
            "return": np.array([_float(by_seed[s].get("eval/return")) for s in seeds]),
            "discounted_return": np.array([_float(by_seed[s].get("eval/discounted_return")) for s in seeds]),
            "episodes": np.array([_float(by_seed[s].get("episodes")) for s in seeds]),
        }
    return out


def per_seed_final(curves: Curves, name: str, fraction: float = stats.FINAL_FRACTION) -> np.ndarray:
    """[S]: per seed, the nan-mean of the metric over the last `fraction` of its logged updates."""
    values = curves.metrics.get(name)
    if values is None:
        return np.full(len(curves.seeds), np.nan)
    return stats.final_values(values, curves.present, fraction)


def per_seed_auc(curves: Curves, name: str) -> np.ndarray:
    """[S]: normalised area under the curve over environment steps, per seed (cdjax.stats.area_under_curve).

    An Mb-Mf phase's point (update 0 at the phase's env steps) weighs the phase's steps. Without env
    steps in the log, every logged update weighs the same.
    """
    values = curves.metrics.get(name)
    if values is None:
        return np.full(len(curves.seeds), np.nan)
    steps = curves.env_steps if np.isfinite(curves.env_steps).all() else curves.updates.astype(float)
    return stats.area_under_curve(values, curves.present, steps)


def per_seed_skipped(curves: Curves, name: str | None = None) -> np.ndarray:
    """[S]: optimiser steps each seed skipped for a non-finite loss or gradient (0 where the log has no count)."""
    name = name if name in curves.metrics else next((n for n in SKIPPED if n in curves.metrics), None)
    if name is None:
        return np.zeros(len(curves.seeds))
    return np.nansum(curves.metrics[name], axis=1)


# ---------------------------------------------------------------------------------------------------
# summary


def pool_curves(a: Curves, b: Curves) -> tuple[Curves, int]:
    """b's seeds after a's, on the union of their logged updates (NaN and not present where a side did not log),
    b's seed ids shifted past a's; and that shift (for b's evaluations)."""
    updates = np.union1d(a.updates, b.updates)
    offset = int(a.seeds.max()) + 1 - int(b.seeds.min()) if len(a.seeds) and len(b.seeds) else 0

    def spread(c: Curves, x: np.ndarray, fill) -> np.ndarray:
        wide = np.full((x.shape[0], len(updates)), fill, dtype=x.dtype)
        wide[:, np.searchsorted(updates, c.updates)] = x
        return wide

    env_steps = np.full(len(updates), np.nan)
    for c in (b, a):  # a's where both logged
        env_steps[np.searchsorted(updates, c.updates)] = c.env_steps
    of = lambda c, n: c.metrics.get(n, np.full(c.present.shape, np.nan)).astype(float)  # noqa: E731
    metrics = {n: np.concatenate([spread(a, of(a, n), np.nan), spread(b, of(b, n), np.nan)])
               for n in list(a.metrics) + [n for n in b.metrics if n not in a.metrics]}
    present = np.concatenate([spread(a, a.present, False), spread(b, b.present, False)])
    return dataclasses.replace(a, seeds=np.concatenate([a.seeds, b.seeds + offset]), updates=updates,
                               env_steps=env_steps, present=present, metrics=metrics), offset


def pool_seed_arrays(a: dict | None, b: dict | None) -> dict | None:
    """Two records of per-seed arrays by name (load_eval's, b's seed ids already shifted; a report's per-seed
    diagnostics) as one, b's seeds after a's, name by name; None unless both exist."""
    if a is None or b is None:
        return None
    return {n: np.concatenate([a[n], b[n]]) for n in a if n in b}
