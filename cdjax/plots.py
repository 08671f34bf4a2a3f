"""Plots and summary tables of a run directory (pandas-free; matplotlib without pyplot).

    curves = load_metrics(run_dir)        # {(arm, hp_label): Curves with arrays [seeds, updates]}
    paths = plot_run(run_dir)             # PNGs + the CSV behind each, summary.md, summary.csv

Aggregation across seeds follows rliable (Agarwal et al., 2021): the interquartile mean (IQM) with a
95% stratified-bootstrap confidence interval (`rliable.library.get_interval_estimates`; when that
module cannot be imported, `stratified_bootstrap` here does the same resampling). With a
single task the stratified bootstrap resamples seeds. With fewer than 4 seeds the 25% trimmed mean
trims nothing and the IQM is the plain mean; with one seed there is no interval (NaN, no band).
Missing values (null in metrics.jsonl, e.g. the return before the first finished episode) are NaN
here and every statistic uses only the seeds that have a finite value at that point.
"""

from __future__ import annotations

import csv
import dataclasses
import json
import math
import pathlib
import warnings
from typing import Callable, Iterable, Sequence

import numpy as np
import scipy.stats
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from rliable import metrics as rly_metrics

try:  # rliable.library imports arch, whose 7.x releases (the ones rliable 1.2 accepts) fail under pandas 3
    from rliable import library as rly

    RLIABLE_ERROR = None
except Exception as _err:  # noqa: BLE001 - any import-time failure of arch/pandas lands here
    rly = None
    RLIABLE_ERROR = f"{type(_err).__name__}: {_err}"

RETURN = "episode/return"
DISC_RETURN = "episode/discounted_return"
# (metric name, panel title, log scale) of the model-diagnostics figure, drawn when present in any curve.
MODEL_PANELS = (
    ("model/openloop_mse_k", "open-loop MSE at k steps", True),
    ("model/openloop_mse_50", "open-loop MSE at 50 steps", True),
    ("loss/consistency", "consistency loss", True),
    ("encoder/spread_real", "encoder spread (real)", False),
    ("encoder/spread_imagined", "encoder spread (imagined)", False),
)
_ROW_KEYS = ("arm", "hp", "seed", "update")  # identify a row; every other numeric field is a metric
FINAL_FRACTION = 0.1  # the final return averages the last 10% of each seed's logged updates


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
    if isinstance(value, bool):
        return float(value)
    try:
        return float(value)
    except (TypeError, ValueError):
        return math.nan


def _read_jsonl(path: pathlib.Path) -> list[dict]:
    """Rows of a JSONL file; a line that does not parse (a run killed mid-write) is skipped."""
    rows = []
    if not path.exists():
        return rows
    with path.open() as f:
        for line in f:
            line = line.strip()
            if not line:
                continue
            try:
                row = json.loads(line)
            except json.JSONDecodeError:
                continue
            if isinstance(row, dict):
                rows.append(row)
    return rows


def read_run_info(run_dir: str | pathlib.Path) -> dict:
    path = pathlib.Path(run_dir) / "run.json"
    return json.loads(path.read_text()) if path.exists() else {}


def load_metrics(run_dir: str | pathlib.Path) -> dict[tuple[str, str], Curves]:
    """metrics.jsonl as {(arm, hp label): Curves}, ordered as run.json lists arms and hp labels.

    A repeated (arm, hp, seed, update) row (a resumed chunk) keeps the last one written.
    """
    run_dir = pathlib.Path(run_dir)
    info = read_run_info(run_dir)
    order: list[tuple[str, str]] = []
    arm_types: dict[str, str] = {}
    for arm in info.get("arms", []):
        arm_types[arm["name"]] = arm.get("arm") or arm.get("config", {}).get("arm")
        order += [(arm["name"], str(label)) for label in arm.get("hp_labels", [""])]

    groups: dict[tuple[str, str], dict[tuple[int, int], dict]] = {}
    for row in _read_jsonl(run_dir / "metrics.jsonl"):
        if "arm" not in row or "seed" not in row or "update" not in row:
            continue
        key = (str(row["arm"]), str(row.get("hp", "")))
        groups.setdefault(key, {})[(int(row["seed"]), int(row["update"]))] = row
    keys = [k for k in order if k in groups] + [k for k in groups if k not in order]

    out = {}
    for key in keys:
        rows = groups[key]
        seeds = np.array(sorted({s for s, _ in rows}), dtype=int)
        updates = np.array(sorted({u for _, u in rows}), dtype=int)
        s_index = {s: i for i, s in enumerate(seeds)}
        u_index = {u: i for i, u in enumerate(updates)}
        names = sorted({n for row in rows.values() for n in row if n not in _ROW_KEYS and n != "env_steps"})
        shape = (len(seeds), len(updates))
        metrics = {n: np.full(shape, np.nan) for n in names}
        steps = np.full(shape, np.nan)
        present = np.zeros(shape, bool)
        for (s, u), row in rows.items():
            i, j = s_index[s], u_index[u]
            present[i, j] = True
            steps[i, j] = _float(row.get("env_steps"))
            for n in names:
                if n in row:
                    metrics[n][i, j] = _float(row[n])
        metrics = {n: v for n, v in metrics.items() if not np.all(np.isnan(v)) or n in (RETURN, DISC_RETURN)}
        out[key] = Curves(arm=key[0], hp=key[1], arm_type=arm_types.get(key[0]), seeds=seeds, updates=updates,
                          env_steps=_nan_reduce(np.nanmax, steps, axis=0), present=present, metrics=metrics)
    return out


def load_eval(run_dir: str | pathlib.Path) -> dict[tuple[str, str, bool], dict[str, np.ndarray]]:
    """eval.jsonl as {(arm, hp, deterministic): {"seeds", "return", "discounted_return", "episodes"}}.

    Per seed the record of the latest evaluated update is kept (the last written when equal).
    """
    latest: dict[tuple[str, str, bool], dict[int, dict]] = {}
    for row in _read_jsonl(pathlib.Path(run_dir) / "eval.jsonl"):
        if "arm" not in row or "seed" not in row:
            continue
        key = (str(row["arm"]), str(row.get("hp", "")), bool(row.get("deterministic", True)))
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


def _nan_reduce(fn, x, axis):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return fn(x, axis=axis)


# ---------------------------------------------------------------------------------------------------
# statistics


def iqm_columns(scores: np.ndarray) -> np.ndarray:
    """IQM of every trailing column of scores [runs, tasks, P] -> [P].

    Equal to `rliable.metrics.aggregate_iqm(scores[..., p])` for each p (a 25% trimmed mean over
    runs x tasks), computed for all p at once so that a bootstrap over long curves stays fast.
    """
    return scipy.stats.trim_mean(scores.reshape(-1, scores.shape[-1]), proportiontocut=0.25, axis=0)


def mean_columns(scores: np.ndarray) -> np.ndarray:
    """Mean over runs x tasks of every trailing column: scores [runs, tasks, P] -> [P]."""
    return scores.reshape(-1, scores.shape[-1]).mean(axis=0)


def _bootstrap(scores: np.ndarray, func: Callable, reps: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
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
    func = {"iqm": iqm_columns, "mean": mean_columns}[stat]
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
        est, interval = _bootstrap(sub, func, reps, seed)
        point[cols], low[cols], high[cols] = est, interval[0], interval[1]
    return point, low, high, finite.sum(axis=0)


def iqm_interval(values: Sequence[float], reps: int = 2000, seed: int = 0) -> tuple[float, float, float, int]:
    """(IQM, CI low, CI high, n) over the finite values, with `rliable.metrics.aggregate_iqm`."""
    x = np.asarray(values, float)
    x = x[np.isfinite(x)]
    if x.size == 0:
        return math.nan, math.nan, math.nan, 0
    if x.size == 1:
        return float(x[0]), math.nan, math.nan, 1
    est, interval = _bootstrap(x[:, None], lambda s: np.array([rly_metrics.aggregate_iqm(s)]), reps, seed)
    return float(est[0]), float(interval[0, 0]), float(interval[1, 0]), int(x.size)


def per_seed_final(curves: Curves, name: str, fraction: float = FINAL_FRACTION) -> np.ndarray:
    """[S]: per seed, the nan-mean of the metric over the last `fraction` of its logged updates."""
    values = curves.metrics.get(name)
    out = np.full(len(curves.seeds), np.nan)
    if values is None:
        return out
    for s in range(len(curves.seeds)):
        idx = np.flatnonzero(curves.present[s])
        if idx.size:
            last = idx[-max(1, math.ceil(fraction * idx.size)):]
            out[s] = _nan_reduce(np.nanmean, values[s, last], axis=None)
    return out


def per_seed_auc(curves: Curves, name: str) -> np.ndarray:
    """[S]: normalised area under the curve over environment steps, per seed.

    Each logged point stands for the env steps since the previous point (the first for those since 0):
    the AUC is the mean of the metric weighted by those steps, so arms compare over the same budget even
    when one logs its first point late (an Mb-Mf phase, logged as update 0 at the phase's env steps).
    Points with a NaN value (before the first finished episode) are skipped. Without env steps in the
    log, every logged update weighs the same.
    """
    values = curves.metrics.get(name)
    out = np.full(len(curves.seeds), np.nan)
    if values is None:
        return out
    steps = curves.env_steps if np.isfinite(curves.env_steps).all() else curves.updates.astype(float)
    for s in range(len(curves.seeds)):
        idx = np.flatnonzero(curves.present[s])
        if idx.size == 0:
            continue
        x = steps[idx]
        weights = np.diff(np.r_[0.0, x])
        v = values[s, idx]
        ok = np.isfinite(v) & (weights > 0)
        if ok.any():
            out[s] = float(np.sum(v[ok] * weights[ok]) / np.sum(weights[ok]))
    return out


# ---------------------------------------------------------------------------------------------------
# summary


_STATS = (("final", per_seed_final), ("auc", per_seed_auc))
_TARGETS = (("return", RETURN), ("discounted_return", DISC_RETURN))


def summary_rows(curves: dict[tuple[str, str], Curves], evals: dict | None = None, reps: int = 2000,
                 seed: int = 0) -> list[dict]:
    """One row per (arm, hp), sorted by final return IQM (best first, NaN last).

    Columns: arm, hp, arm_type, seeds, updates, env_steps, then for each of final/auc x
    return/discounted_return: <stat>_<target>_iqm, _ci_low, _ci_high; and with evals, for each
    evaluation mode (det, stoch) found: eval_<mode>_return_*, eval_<mode>_discounted_return_*, _seeds.
    """
    evals = evals or {}
    modes = sorted({det for (_, _, det) in evals}, reverse=True)  # deterministic first
    rows = []
    for (arm, hp), c in curves.items():
        row = {"arm": arm, "hp": hp, "arm_type": c.arm_type or "", "seeds": int(len(c.seeds)),
               "updates": int(c.present.any(axis=0).sum()),
               "env_steps": float(np.nanmax(c.env_steps)) if np.isfinite(c.env_steps).any() else math.nan}
        for stat, fn in _STATS:
            for target, name in _TARGETS:
                iqm, lo, hi, _ = iqm_interval(fn(c, name), reps, seed)
                row.update({f"{stat}_{target}_iqm": iqm, f"{stat}_{target}_ci_low": lo,
                            f"{stat}_{target}_ci_high": hi})
        for det in modes:
            mode = "det" if det else "stoch"
            ev = evals.get((arm, hp, det))
            for target in ("return", "discounted_return"):
                iqm, lo, hi, n = iqm_interval(ev[target] if ev else [], reps, seed)
                row.update({f"eval_{mode}_{target}_iqm": iqm, f"eval_{mode}_{target}_ci_low": lo,
                            f"eval_{mode}_{target}_ci_high": hi})
            row[f"eval_{mode}_seeds"] = int(np.isfinite(ev["return"]).sum()) if ev else 0
        rows.append(row)
    rows.sort(key=lambda r: (not np.isfinite(r["final_return_iqm"]), -np.nan_to_num(r["final_return_iqm"])))
    return rows


def _fmt(x: float) -> str:
    return "n/a" if not np.isfinite(x) else f"{x:.4g}"


def _cell(row: dict, prefix: str) -> str:
    iqm, lo, hi = row[f"{prefix}_iqm"], row[f"{prefix}_ci_low"], row[f"{prefix}_ci_high"]
    if not np.isfinite(iqm):
        return "n/a"
    return _fmt(iqm) if not np.isfinite(lo) else f"{_fmt(iqm)} [{_fmt(lo)}, {_fmt(hi)}]"


def summary_markdown(rows: list[dict], title: str = "") -> str:
    columns = [("final return", "final_return"), ("AUC return", "auc_return"),
               ("final disc. return", "final_discounted_return"), ("AUC disc. return", "auc_discounted_return")]
    for mode, words in (("det", "deterministic"), ("stoch", "stochastic")):
        if rows and f"eval_{mode}_return_iqm" in rows[0]:
            columns += [(f"eval return ({words})", f"eval_{mode}_return"),
                        (f"eval disc. return ({words})", f"eval_{mode}_discounted_return")]
    head = ["rank", "arm", "hp", "seeds", "env steps"] + [name for name, _ in columns]
    lines = [f"# {title}" if title else "# Summary", "",
             "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for i, row in enumerate(rows, 1):
        steps = f"{row['env_steps']:.3g}" if np.isfinite(row["env_steps"]) else "n/a"
        arm = row["arm"] + (f" ({row['arm_type']})" if row["arm_type"] and row["arm_type"] != row["arm"] else "")
        cells = [str(i), arm, row["hp"] or "-", str(row["seeds"]), steps] + [_cell(row, p) for _, p in columns]
        lines.append("| " + " | ".join(cells) + " |")
    lines += [
        "",
        "IQM across seeds with a 95% stratified-bootstrap confidence interval "
        f"({'rliable' if rly is not None else 'rliable method, computed locally: rliable.library does not import'}). "
        "With fewer than 4 seeds "
        "the IQM equals the mean; with 1 seed no interval is given. Final: mean of the last "
        f"{FINAL_FRACTION:.0%} of each seed's logged updates. AUC: mean of each seed's whole return curve, "
        "each point weighted by the env steps since the previous one (an Mb-Mf phase's point by the phase's "
        "steps; points before the first finished episode are skipped). Eval: mean return over the evaluation "
        "episodes of each seed's latest evaluation.",
    ]
    return "\n".join(lines) + "\n"


def _write_csv(path: pathlib.Path, rows: list[dict], columns: Sequence[str] | None = None) -> pathlib.Path:
    columns = list(columns or (rows[0].keys() if rows else []))
    with path.open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=columns)
        writer.writeheader()
        for row in rows:
            writer.writerow({k: ("" if isinstance(v, float) and not np.isfinite(v) else v) for k, v in row.items()})
    return path


# ---------------------------------------------------------------------------------------------------
# figures


def _thin(n: int, max_points: int) -> np.ndarray:
    """Indices of at most max_points evenly spaced points of n, first and last included."""
    if n <= max_points:
        return np.arange(n)
    return np.unique(np.linspace(0, n - 1, max_points).round().astype(int))


def _curve_rows(curves: Iterable[Curves], name: str, stat: str, max_points: int, reps: int, seed: int):
    """(plotted series [(label, x, point, low, high)], CSV rows) of one metric for every curve having it."""
    series, rows = [], []
    for c in curves:
        values = c.metrics.get(name)
        if values is None or not np.isfinite(values).any():
            continue
        idx = _thin(len(c.updates), max_points)
        point, low, high, n = interval_curve(values[:, idx], stat, reps, seed)
        x = c.env_steps[idx]
        x = np.where(np.isfinite(x), x, c.updates[idx].astype(float))
        series.append((c.label, x, point, low, high))
        for j, i in enumerate(idx):
            rows.append({"metric": name, "curve": c.label, "arm": c.arm, "hp": c.hp, "update": int(c.updates[i]),
                         "env_steps": float(x[j]), stat: float(point[j]), "ci_low": float(low[j]),
                         "ci_high": float(high[j]), "n_seeds": int(n[j])})
    return series, rows


def _draw(ax, series, colors: dict[str, str], log: bool = False):
    for label, x, point, low, high in series:
        ax.plot(x, point, label=label, lw=1.5, color=colors[label])
        ax.fill_between(x, low, high, color=colors[label], alpha=0.2, lw=0)
    if log and all(np.nanmin(np.r_[s[2], s[3]]) > 0 for s in series if np.isfinite(s[2]).any()):
        ax.set_yscale("log")
    ax.set_xlabel("environment steps")
    ax.grid(alpha=0.3)


def plot_run(run_dir: str | pathlib.Path, *, reps: int = 2000, max_points: int = 300, seed: int = 0
             ) -> dict[str, pathlib.Path]:
    """Write RUN/plots/{return,discounted_return,model}.{png,csv}, RUN/summary.{md,csv}.

    Returns {"return", "return_csv", "discounted_return", "discounted_return_csv", "model", "model_csv",
    "summary_md", "summary_csv"} -> written path (model figures only when some arm logs model metrics).
    Curves are thinned to at most `max_points` updates; the CSVs hold exactly the plotted numbers.
    """
    run_dir = pathlib.Path(run_dir)
    plots = run_dir / "plots"
    plots.mkdir(parents=True, exist_ok=True)
    curves = load_metrics(run_dir)
    colors = {c.label: f"C{i % 10}" for i, c in enumerate(curves.values())}  # one colour per curve everywhere
    written: dict[str, pathlib.Path] = {}

    for key, name, title in (("return", RETURN, "return"), ("discounted_return", DISC_RETURN, "discounted return")):
        series, rows = _curve_rows(curves.values(), name, "iqm", max_points, reps, seed)
        fig = Figure(figsize=(7, 4.5))
        ax = fig.add_subplot()
        _draw(ax, series, colors)
        ax.set_ylabel(f"{title} (IQM over seeds)")
        ax.set_title(f"Episode {title}: IQM across seeds, 95% stratified bootstrap CI", fontsize=10)
        if series:
            ax.legend(fontsize=8)
        fig.tight_layout()
        written[key] = plots / f"{key}.png"
        fig.savefig(written[key], dpi=120)
        written[f"{key}_csv"] = _write_csv(plots / f"{key}.csv", rows, ["metric", "curve", "arm", "hp", "update",
                                           "env_steps", "iqm", "ci_low", "ci_high", "n_seeds"])

    panels = [(n, t, log) for n, t, log in MODEL_PANELS
              if any(n in c.metrics and np.isfinite(c.metrics[n]).any() for c in curves.values())]
    if panels:
        ncols = min(3, len(panels))
        nrows = math.ceil(len(panels) / ncols)
        fig = Figure(figsize=(5 * ncols, 3.6 * nrows))
        all_rows = []
        for i, (name, title, log) in enumerate(panels):
            ax = fig.add_subplot(nrows, ncols, i + 1)
            series, rows = _curve_rows(curves.values(), name, "mean", max_points, reps, seed)
            _draw(ax, series, colors, log)
            ax.set_title(f"{title}\n(mean over seeds, 95% bootstrap CI)", fontsize=9)
            all_rows += rows
        shown = {r["curve"] for r in all_rows}
        handles = [Line2D([], [], color=colors[label], lw=1.5) for label in colors if label in shown]
        fig.legend(handles, [label for label in colors if label in shown], loc="lower center",
                   ncol=min(4, len(handles)), fontsize=8, frameon=False)
        fig.tight_layout(rect=(0, 0.06 + 0.02 * math.ceil(len(handles) / 4), 1, 1))
        written["model"] = plots / "model.png"
        fig.savefig(written["model"], dpi=110)
        written["model_csv"] = _write_csv(plots / "model.csv", all_rows, ["metric", "curve", "arm", "hp", "update",
                                          "env_steps", "mean", "ci_low", "ci_high", "n_seeds"])

    rows = summary_rows(curves, load_eval(run_dir), reps, seed)
    info = read_run_info(run_dir)
    title = f"Summary of {run_dir.name}" + (f" ({info['base_config'].get('env')})"
                                            if isinstance(info.get("base_config"), dict) else "")
    written["summary_md"] = run_dir / "summary.md"
    written["summary_md"].write_text(summary_markdown(rows, title))
    written["summary_csv"] = _write_csv(run_dir / "summary.csv", rows)
    return written
