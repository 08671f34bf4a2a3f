"""Statistics across seeds: interquartile mean (IQM), 95% stratified-bootstrap intervals, per-seed final
value and area under the curve.

Aggregation follows rliable (Agarwal et al., 2021): the IQM with a 95% stratified-bootstrap confidence
interval (`rliable.library.get_interval_estimates`; when that module cannot be imported, `stratified_bootstrap`
here does the same resampling). rliable is the optional extra `rliable` (`pip install -e ".[rliable]"`): it caps
pandas below 3, which cdjax itself does not need. With a single task the stratified bootstrap
resamples seeds. With fewer than 4 seeds the 25% trimmed mean trims nothing and the IQM is the plain
mean; with one seed there is no interval (NaN). Missing values are NaN, and every statistic uses only
the seeds that have a finite value at that point.
"""

from __future__ import annotations

import math
import warnings
from typing import Callable, Sequence

import numpy as np

try:  # the extra `rliable`; without it (or under pandas 3, where the arch 7.x that rliable 1.2 accepts fails to
    # import) cdjax still plots, evaluates and draws strips with the local bootstrap below
    from rliable import library as rly

    RLIABLE_ERROR = None
except ModuleNotFoundError as _err:
    rly = None
    RLIABLE_ERROR = f"{_err.name} is not installed (it is the extra `rliable`: pip install -e \".[rliable]\")"
except Exception as _err:  # noqa: BLE001 - any import-time failure of rliable/arch/pandas lands here
    rly = None
    RLIABLE_ERROR = f"{type(_err).__name__}: {_err}"

FINAL_FRACTION = 0.1  # the final value averages the last 10% of each seed's logged points


def nan_reduce(fn, x, axis):
    """fn (np.nanmean, np.nanmax, ...) without the warning for an all-NaN slice."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return fn(x, axis=axis)


def iqm_columns(scores: np.ndarray) -> np.ndarray:
    """IQM of every trailing column of scores [runs, tasks, P] -> [P].

    Equal to `rliable.metrics.aggregate_iqm(scores[..., p])` for each p (a 25% trimmed mean over
    runs x tasks), computed for all p at once so that a bootstrap over long curves stays fast.
    """
    # scipy.stats.trim_mean(flat, 0.25, axis=0) without its per-call overhead (~1 ms, once per bootstrap replication)
    flat = scores.reshape(-1, scores.shape[-1])
    cut = int(0.25 * flat.shape[0])
    return np.sort(flat, axis=0)[cut:flat.shape[0] - cut].mean(axis=0)


def mean_columns(scores: np.ndarray) -> np.ndarray:
    """Mean over runs x tasks of every trailing column: scores [runs, tasks, P] -> [P]."""
    return scores.reshape(-1, scores.shape[-1]).mean(axis=0)


def bootstrap(scores: np.ndarray, func: Callable, reps: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """rliable point estimate and 95% stratified-bootstrap interval [2, ...], reproducibly.

    rliable's StratifiedBootstrap draws indices from numpy's global generator, so it is seeded here
    and its previous state put back.
    """
    saved = np.random.get_state()
    np.random.seed(seed)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            if rly is not None:
                point, interval = rly.get_interval_estimates({"x": scores}, func, reps=reps,
                                                             confidence_interval_size=0.95)
                point, interval = point["x"], interval["x"]
            else:
                point, interval = stratified_bootstrap(scores, func, reps)
    finally:
        np.random.set_state(saved)
    return np.asarray(point, float), np.asarray(interval, float)


def probability_of_improvement(x: np.ndarray, y: np.ndarray, reps: int = 2000,
                               seed: int = 0) -> tuple[float, float, float] | None:
    """rliable's probability of improvement P(X > Y) (a run of X against a run of Y, ties counted half, averaged
    over tasks) with its 95% stratified-bootstrap interval, reproducibly (numpy's global generator seeded and put
    back, as `bootstrap`): x [runs, tasks] and y [runs', tasks], or one task's runs as 1-D arrays. None where
    rliable does not import (the extra `rliable`; RLIABLE_ERROR says why).

    As every statistic here, it uses only the runs with a finite value (with several tasks, the runs finite on
    every task); NaN where either side has none left, and a NaN interval where either has one run (no spread to
    resample)."""
    if rly is None:
        return None
    from rliable import metrics

    x, y = (np.asarray(v, float) for v in (x, y))
    x, y = (v[:, None] if v.ndim == 1 else v for v in (x, y))
    x, y = (v[np.isfinite(v).all(axis=1)] for v in (x, y))
    if not len(x) or not len(y):
        return math.nan, math.nan, math.nan
    if min(len(x), len(y)) < 2:
        return float(metrics.probability_of_improvement(x, y)), math.nan, math.nan
    saved = np.random.get_state()
    np.random.seed(seed)
    try:
        point, interval = rly.get_interval_estimates({"p": (x, y)}, metrics.probability_of_improvement, reps=reps)
    finally:
        np.random.set_state(saved)
    low, high = np.asarray(interval["p"])
    return float(np.asarray(point["p"]).squeeze()), float(low.squeeze()), float(high.squeeze())


def stratified_bootstrap(scores: np.ndarray, func: Callable, reps: int, size: float = 0.95):
    """(func(scores), percentile interval [2, ...]) by the same resampling as rliable's StratifiedBootstrap.

    Used only when `rliable.library` cannot be imported (see RLIABLE_ERROR). Each replication draws,
    from numpy's global generator, a run index for every entry of scores [runs, tasks, ...] (runs are
    resampled within each task and each point), applies func, and the interval is the (1 - size) / 2
    and (1 + size) / 2 percentiles of the replications, as arch's "percentile" method.
    """
    n = scores.shape[0]
    strata = np.ogrid[tuple(slice(x) for x in (0, *scores.shape[1:]))][1:]
    stats = np.stack([np.asarray(func(scores[(np.random.choice(n, scores.shape, replace=True), *strata)]))
                      for _ in range(reps)])
    tail = 100 * (1 - size) / 2
    interval = np.stack([np.percentile(stats, tail, axis=0), np.percentile(stats, 100 - tail, axis=0)])
    return np.asarray(func(scores)), interval


def interval_curve(values: np.ndarray, stat: str = "iqm", reps: int = 2000, seed: int = 0):
    """Across-seed statistic of a curve values [S, P] -> (point [P], low [P], high [P], n_seeds [P]).

    stat "iqm" (rliable IQM) or "mean". At each point only seeds with a finite value count; points
    sharing the same set of finite seeds are bootstrapped together. No interval (NaN) with < 2 seeds.
    """
    funcs = {"iqm": iqm_columns, "mean": mean_columns}
    if stat not in funcs:
        raise ValueError(f"interval_curve's stat is 'iqm' or 'mean', got {stat!r}.")
    values = np.asarray(values, float)
    if values.ndim != 2:
        raise ValueError(f"interval_curve takes values [seeds, points], got an array of shape {values.shape}.")
    func = funcs[stat]
    S, P = values.shape
    finite = np.isfinite(values)
    point, low, high = (np.full(P, np.nan) for _ in range(3))
    patterns: dict[bytes, list[int]] = {}
    for p in range(P):
        if finite[:, p].any():
            patterns.setdefault(finite[:, p].tobytes(), []).append(p)
    for cols in patterns.values():
        rows = finite[:, cols[0]]
        sub = values[rows][:, cols][:, None, :]  # [n, 1 task, points]
        if sub.shape[0] == 1:
            point[cols] = sub[0, 0]
            continue
        est, interval = bootstrap(sub, func, reps, seed)
        point[cols], low[cols], high[cols] = est, interval[0], interval[1]
    return point, low, high, finite.sum(axis=0)


def iqm_interval(values: Sequence[float], reps: int = 2000, seed: int = 0) -> tuple[float, float, float, int]:
    """(IQM, CI low, CI high, n) over the finite values (the IQM is rliable's `metrics.aggregate_iqm`: `iqm_columns`)."""
    x = np.asarray(values, float)
    x = x[np.isfinite(x)]
    if x.size == 0:
        return math.nan, math.nan, math.nan, 0
    if x.size == 1:
        return float(x[0]), math.nan, math.nan, 1
    est, interval = bootstrap(x[:, None], lambda s: iqm_columns(s[..., None]), reps, seed)
    return float(est[0]), float(interval[0, 0]), float(interval[1, 0]), int(x.size)


def final_values(values: np.ndarray, present: np.ndarray, fraction: float = FINAL_FRACTION,
                 steps: np.ndarray | None = None) -> np.ndarray:
    """[S]: per seed, the nan-mean of values [S, U] over the last `fraction` of its logged points (present).

    With steps [U] (the env steps of the points), over the points in the last `fraction` of the seed's steps
    instead (those past (1 - fraction) x its last logged step; at least the last point): the same window for a
    log kept at every update, and still the same window after a log is thinned unevenly (every n-th point early,
    every point late), where counting points would shrink it."""
    if not 0.0 < fraction <= 1.0:
        raise ValueError(f"final_values' fraction is a share of the points in (0, 1], got {fraction!r}.")
    out = np.full(values.shape[0], np.nan)
    for s in range(values.shape[0]):
        idx = np.flatnonzero(present[s])
        if idx.size:
            if steps is None:
                last = idx[-max(1, math.ceil(fraction * idx.size)):]
            else:
                at = np.asarray(steps, float)[idx]
                last = idx[(at > (1.0 - fraction) * at[-1]) | (np.arange(idx.size) == idx.size - 1)]
            out[s] = nan_reduce(np.nanmean, values[s, last], axis=None)
    return out


def area_under_curve(values: np.ndarray, present: np.ndarray, steps: np.ndarray) -> np.ndarray:
    """[S]: normalised area under each seed's curve values [S, U] over steps [U].

    Each logged point stands for the steps since the previous point (the first for those since 0): the
    area is the mean of the values weighted by those steps, so arms compare over the same budget even
    when one logs its first point late. Points with a NaN value are skipped, and so are points whose steps do
    not exceed the previous point's (they stand for no steps).
    """
    steps = np.asarray(steps, float)
    out = np.full(values.shape[0], np.nan)
    for s in range(values.shape[0]):
        idx = np.flatnonzero(present[s])
        if idx.size == 0:
            continue
        weights = np.diff(np.r_[0.0, steps[idx]])
        v = values[s, idx]
        ok = np.isfinite(v) & (weights > 0)
        if ok.any():
            out[s] = float(np.sum(v[ok] * weights[ok]) / np.sum(weights[ok]))
    return out
