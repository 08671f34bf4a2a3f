"""Plots and summary tables of a run directory (pandas-free; matplotlib without pyplot).

    curves = load_metrics(run_dir)        # {(arm, hp_label): Curves with arrays [seeds, updates]}
    paths = plot_run(run_dir)             # PNGs + the CSV behind each, summary.md, summary.csv
    paths = plot_runs([run_a, run_b], out)  # the same of several runs' seeds pooled (runs of other --seed)

The statistics (IQM across seeds with 95% stratified-bootstrap intervals, final value, area under the
curve) are cdjax.stats'. Which metric is the return, the discounted return and the diagnostics panels is
read from run.json (the setting's names), with the observation-space setting's names for logs without one.
Missing values (null in metrics.jsonl, e.g. the return before the first finished episode) are NaN here.
"""

from __future__ import annotations

import csv
import dataclasses
import math
import pathlib
from typing import Callable, Iterable, Sequence

import numpy as np
from matplotlib.figure import Figure
from matplotlib.lines import Line2D

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


_STATS = (("final", per_seed_final), ("auc", per_seed_auc))


def summary_rows(curves: dict[tuple[str, str], Curves], evals: dict | None = None, reps: int = 2000,
                 seed: int = 0, names: Names = Names()) -> list[dict]:
    """One row per (arm, hp), sorted by final return IQM (best first, NaN last).

    Columns: arm, hp, arm_type, seeds (those with a finite final return, the figure the rows are ranked by),
    logged_seeds, left_out_seed_ids (logged seeds without one), updates, env_steps, then for each of final/auc x
    return/discounted_return: <stat>_<target>_iqm, _ci_low, _ci_high, _seeds (the seeds finite in it); and with
    evals, for each evaluation mode (det, stoch) found: eval_<mode>_return_* and eval_<mode>_discounted_return_*
    (the same four: _seeds counts the seeds whose latest evaluation is finite in it) and eval_<mode>_seeds (those of
    the evaluation return).
    """
    evals = evals or {}
    modes = sorted({det for (_, _, det) in evals}, reverse=True)  # deterministic first
    rows = []
    for (arm, hp), c in curves.items():
        ranked = np.isfinite(per_seed_final(c, names.ret))  # as every statistic, the seeds column counts finite ones
        row = {"arm": arm, "hp": hp, "arm_type": c.arm_type or "", "seeds": int(ranked.sum()),
               "logged_seeds": int(len(c.seeds)), "left_out_seed_ids": " ".join(str(s) for s in c.seeds[~ranked]),
               "updates": int(c.present.any(axis=0).sum()),
               "env_steps": float(np.nanmax(c.env_steps)) if np.isfinite(c.env_steps).any() else math.nan}
        for stat, fn in _STATS:
            for target, name in (("return", names.ret), ("discounted_return", names.discounted_ret)):
                iqm, lo, hi, n = stats.iqm_interval(fn(c, name), reps, seed)
                row.update({f"{stat}_{target}_iqm": iqm, f"{stat}_{target}_ci_low": lo,
                            f"{stat}_{target}_ci_high": hi, f"{stat}_{target}_seeds": n})
        skipped = per_seed_skipped(c, names.skipped)
        row["nonfinite_seeds"] = int((skipped > 0).sum())
        row["skipped_steps"] = int(np.nansum(skipped))
        row["nonfinite_seed_ids"] = " ".join(str(s) for s in c.seeds[skipped > 0])
        for det in modes:
            mode = "det" if det else "stoch"
            ev = evals.get((arm, hp, det))
            for target in ("return", "discounted_return"):
                iqm, lo, hi, n = stats.iqm_interval(ev[target] if ev else [], reps, seed)
                row.update({f"eval_{mode}_{target}_iqm": iqm, f"eval_{mode}_{target}_ci_low": lo,
                            f"eval_{mode}_{target}_ci_high": hi, f"eval_{mode}_{target}_seeds": n})
            row[f"eval_{mode}_seeds"] = int(np.isfinite(ev["return"]).sum()) if ev else 0
        rows.append(row)
    rows.sort(key=lambda r: (not np.isfinite(r["final_return_iqm"]), -np.nan_to_num(r["final_return_iqm"])))
    return rows


def _fmt(x: float) -> str:
    return "n/a" if not np.isfinite(x) else f"{x:.4g}"


def _other_count(row: dict, prefix: str) -> int | None:
    """The seeds behind the row's figure `prefix` where they are not as many as the seeds column's (a seed not
    evaluated, a non-finite evaluation, a figure finite for other seeds than the final return); None where they are,
    or where there is no figure."""
    n = row.get(f"{prefix}_seeds", row["seeds"])
    return n if n and n != row["seeds"] else None


def _label(row: dict) -> str:
    """A summary row's arm and hyper-parameter label, as its notes name it ("cd alpha=1.0", or "cd" alone)."""
    return " ".join(part for part in (row["arm"], row["hp"]) if part)


def _cell(row: dict, prefix: str) -> str:
    iqm, lo, hi = row[f"{prefix}_iqm"], row[f"{prefix}_ci_low"], row[f"{prefix}_ci_high"]
    if not np.isfinite(iqm):
        return "n/a"
    text = _fmt(iqm) if not np.isfinite(lo) else f"{_fmt(iqm)} [{_fmt(lo)}, {_fmt(hi)}]"
    n = _other_count(row, prefix)
    return text if n is None else f"{text} (**n = {n}**)"


def _seeds_cell(row: dict) -> str:
    """The seeds behind the row's figures, "4 of 5" where logged seeds were left out."""
    n, logged = row["seeds"], row["logged_seeds"]
    return str(n) if n == logged else f"**{n} of {logged}**"


def summary_markdown(rows: list[dict], title: str = "", notes: Sequence[str] = ()) -> str:
    """The summary table of `rows` (summary_rows') with its notes; `notes`: more paragraphs under it (the sweep's
    note on the measure the arms are ranked by, `cdjax.runner.plan.return_note`)."""
    columns = [("final return", "final_return"), ("AUC return", "auc_return"),
               ("final disc. return", "final_discounted_return"), ("AUC disc. return", "auc_discounted_return")]
    for mode, words in (("det", "deterministic"), ("stoch", "stochastic")):
        if rows and f"eval_{mode}_return_iqm" in rows[0]:
            columns += [(f"eval return ({words})", f"eval_{mode}_return"),
                        (f"eval disc. return ({words})", f"eval_{mode}_discounted_return")]
    flagged = [row for row in rows if row.get("nonfinite_seeds")]
    short = [row for row in rows if row["seeds"] < row["logged_seeds"]]
    counted = [(row, name, n) for row in rows for name, prefix in columns
               if (n := _other_count(row, prefix)) is not None]
    head = ["rank", "arm", "hp", "seeds", "env steps"] + [name for name, _ in columns] + (
        ["non-finite"] if flagged else [])
    lines = [f"# {title}" if title else "# Summary", "",
             "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for i, row in enumerate(rows, 1):
        steps = f"{row['env_steps']:.3g}" if np.isfinite(row["env_steps"]) else "n/a"
        arm = row["arm"] + (f" ({row['arm_type']})" if row["arm_type"] and row["arm_type"] != row["arm"] else "")
        cells = [str(i), arm, row["hp"] or "-", _seeds_cell(row), steps] + [_cell(row, p) for _, p in columns]
        if flagged:
            cells.append(f"**{row['nonfinite_seeds']} of {row['logged_seeds']} seeds**"
                         if row.get("nonfinite_seeds") else "-")
        lines.append("| " + " | ".join(cells) + " |")
    lines += [
        "",
        "IQM across seeds with a 95% stratified-bootstrap confidence interval "
        f"({'rliable' if stats.rly is not None else 'rliable method, computed locally: rliable.library does not import'}). "
        "With fewer than 4 seeds "
        "the IQM equals the mean; with 1 seed no interval is given. Final: mean of the last "
        f"{stats.FINAL_FRACTION:.0%} of each seed's logged updates. AUC: mean of each seed's whole return curve, "
        "each point weighted by the env steps since the previous one (an Mb-Mf phase's point by the phase's "
        "steps; points before the first finished episode are skipped). Eval: mean return over the evaluation "
        "episodes of each seed's latest evaluation.",
    ]
    if short:
        runs = "; ".join(f"{_label(row)} seeds {row['left_out_seed_ids']}" for row in short)
        lines += ["", "**Seeds left out**: the seeds column counts the seeds with a finite final return (the figure "
                      "the rows are ranked by), and every figure uses only the seeds finite in it; these logged "
                      f"seeds have no finite return over the last {stats.FINAL_FRACTION:.0%} of their logged "
                      f"updates: {runs}."]
    if counted:
        figures = "; ".join(f"{_label(row)} {name}: n = {n} (seeds column {row['seeds']})" for row, name, n in counted)
        lines += ["", "**Seed counts**: a figure marked n = N is over N seeds, not the seeds column's: an evaluation "
                      "column counts the seeds whose latest evaluation is finite in it (a seed not evaluated, or "
                      f"evaluated to a non-finite return, is not in it), every other column the seeds finite in it: "
                      f"{figures}."]
    if flagged:
        runs = "; ".join(f"{_label(row)} seeds {row['nonfinite_seed_ids']}: {row['skipped_steps']} steps"
                         for row in flagged)
        lines += ["", f"**Non-finite training**: these runs skipped optimiser steps whose loss or gradient was not "
                      f"finite (the parameters stayed as they were; their numbers are suspect): {runs}."]
    for note in notes:
        lines += ["", note]
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
        point, low, high, n = stats.interval_curve(values[:, idx], stat, reps, seed)
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


def plot_run(run_dir: str | pathlib.Path, *, reps: int = 2000, max_points: int = 300, seed: int = 0,
             say: Callable[[str], None] | None = None, notes: Sequence[str] = ()) -> dict[str, pathlib.Path]:
    """Write RUN/plots/{return,discounted_return,model}.{png,csv}, RUN/summary.{md,csv}.

    Returns {"return", "return_csv", "discounted_return", "discounted_return_csv", "model", "model_csv",
    "summary_md", "summary_csv"} -> written path (the diagnostics figure "model" only when some arm logs
    one of its metrics). Curves are thinned to at most `max_points` updates; the CSVs hold exactly the
    plotted numbers. `say` hears about torn log lines; a failed write raises io.WriteError. `notes` go under the
    summary table (summary_markdown).
    """
    run_dir = pathlib.Path(run_dir)
    info = io.RunDir(run_dir).read_if_present()
    curves = _loaded(run_dir, say, run_dir)
    env = info.get("base_config", {}).get("env") if isinstance(info.get("base_config"), dict) else None
    title = f"Summary of {run_dir.name}" + (f" ({env})" if env else "")
    return _write(run_dir, curves, load_eval(run_dir, say), Names.of(info), title, reps, max_points, seed, notes)


def _loaded(run_dir: pathlib.Path, say: Callable[[str], None] | None, out: pathlib.Path) -> dict:
    """load_metrics(run_dir), or RunDirError when it holds no row (rather than overwrite a summary with an empty
    table)."""
    curves = load_metrics(run_dir, say)
    if not curves:
        where = run_dir / "metrics.jsonl"
        state = "holds no readable row" if io.jsonl_exists(where) else "is missing"
        raise io.RunDirError(f"{where} {state}, so there is nothing to plot; {out}/summary.md and plots/ were "
                             "left as they were.")
    return curves


def plot_runs(run_dirs: Sequence[str | pathlib.Path], out: str | pathlib.Path, *, reps: int = 2000,
              max_points: int = 300, seed: int = 0, say: Callable[[str], None] | None = None,
              notes: Sequence[str] = ()) -> dict[str, pathlib.Path]:
    """plot_run's figures and summary, into OUT/, of several runs of one environment with their seeds pooled.

    Each (arm, hp label) holds the seeds of every run that has it (`pool_curves`): runs of the same sweep
    started with other base seeds (`cdjax sweep --seed`), e.g. because one machine could not hold all the seeds.
    RunDirError (one sentence) when the runs are of other environments or settings, when two of them share a base
    seed (their seeds would be the same keys counted twice), when one arm asked for other env steps per run in
    another run (its seeds would end at other budgets), or when an (arm, hp label) ran with another configuration or
    other hyper-parameters in another run (`_same_settings`).
    """
    run_dirs = [pathlib.Path(d) for d in run_dirs]
    out = pathlib.Path(out)
    if not run_dirs:
        raise io.RunDirError(f"plot_runs was given no run directory, so there is nothing to plot into {out}.")
    infos = [io.RunDir(d).read() for d in run_dirs]
    first, where = infos[0], run_dirs[0]
    for info, d in zip(infos[1:], run_dirs[1:]):
        for what, get in (("environment", lambda i: i.get("base_config", {}).get("env")),
                          ("setting", lambda i: i.get("setting"))):
            if get(info) != get(first):
                raise io.RunDirError(f"{d} is a run of {what} {get(info)!r} and {where} of {get(first)!r}; pool runs "
                                     f"of one {what}.")
    bases = {}
    for info, d in zip(infos, run_dirs):
        base = int(info.get("seed", 0))
        if base in bases:
            raise io.RunDirError(f"{d} and {bases[base]} both ran base seed {base}, so their seeds are the same keys; "
                                 "pool runs started with other --seed values.")
        bases[base] = d
    budgets: dict[str, tuple] = {}
    for info, d in zip(infos, run_dirs):
        for arm in info.get("arms", []):
            steps = arm.get("total_env_steps", info.get("total_env_steps"))
            if budgets.setdefault(arm["name"], (steps, d))[0] != steps:
                raise io.RunDirError(f"arm {arm['name']} ran {steps:,} env steps per run in {d} and "
                                     f"{budgets[arm['name']][0]:,} in {budgets[arm['name']][1]}; pool runs of one "
                                     "budget.")
    _same_settings(infos, run_dirs)
    curves, evals = {}, {}
    for d in run_dirs:
        offsets = {}
        for key, c in _loaded(d, say, out).items():
            if key in curves:
                curves[key], offsets[key] = pool_curves(curves[key], c)
            else:
                curves[key], offsets[key] = c, 0
        for (arm, hp, det), e in load_eval(d, say).items():
            offset = offsets.get((arm, hp), 0)
            e = dict(e, seeds=e["seeds"] + offset)
            evals[(arm, hp, det)] = pool_seed_arrays(evals[(arm, hp, det)], e) if (arm, hp, det) in evals else e
    env = first.get("base_config", {}).get("env")
    title = (f"Summary of {', '.join(d.name for d in run_dirs)} pooled (base seeds {', '.join(map(str, bases))})"
             + (f" ({env})" if env else ""))
    return _write(out, curves, evals, Names.of(first), title, reps, max_points, seed, notes)


def _same_settings(infos: list[dict], run_dirs: list[pathlib.Path]) -> None:
    """RunDirError (one sentence) unless each (arm, hp label) ran with the same configuration and hyper-parameters in
    every run that has it (run.json's `config` and `hparams`): a curve pools seeds of one setting only, and the label
    names the grid's values, not every field. A yardstick is compared by its file's name (another machine's path)."""
    seen: dict[tuple, tuple] = {}
    for info, d in zip(infos, run_dirs):
        for arm in info.get("arms", []):
            config = dict(arm.get("config", {}))
            if config.get("yardstick"):
                config["yardstick"] = pathlib.PurePath(config["yardstick"]).name
            labels = arm.get("hp_labels", [""])
            for label, hp in zip(labels, arm.get("hparams", [{}] * len(labels))):
                key = (arm["name"], str(label))
                earlier, where = seen.setdefault(key, ((config, hp), d))
                for before, now, kind in ((earlier[0], config, "configuration"), (earlier[1], hp, "hyper-parameters")):
                    for name in [*before, *(n for n in now if n not in before)]:
                        if before.get(name) != now.get(name):
                            raise io.RunDirError(
                                f"arm {arm['name']}{f' ({label})' if label else ''} ran with {name}="
                                f"{now.get(name)!r} in {d} and {before.get(name)!r} in {where}; pool runs of one "
                                f"{kind}.")


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


def _write(out: pathlib.Path, curves: dict, evals: dict, names: Names, title: str, reps: int, max_points: int,
           seed: int, notes: Sequence[str] = ()) -> dict[str, pathlib.Path]:
    """The figures, their CSVs and the summary of `curves` into OUT/plots/ and OUT/summary.{md,csv}."""
    colors = {c.label: f"C{i % 10}" for i, c in enumerate(curves.values())}  # one colour per curve everywhere
    plots = out / "plots"
    written: dict[str, pathlib.Path] = {}
    with io.writing(plots):
        plots.mkdir(parents=True, exist_ok=True)
        for key, name, what in (("return", names.ret, "return"),
                                ("discounted_return", names.discounted_ret, "discounted return")):
            written.update(_return_figure(plots, key, name, what, curves, colors, max_points, reps, seed))
        written.update(_panels_figure(plots, names.panels, curves, colors, max_points, reps, seed))
    rows = summary_rows(curves, evals, reps, seed, names)
    written["summary_md"] = out / "summary.md"
    with io.writing(written["summary_md"]):
        written["summary_md"].write_text(summary_markdown(rows, title, notes))
        written["summary_csv"] = _write_csv(out / "summary.csv", rows)
    return written


def _return_figure(plots: pathlib.Path, key: str, name: str, title: str, curves: dict, colors: dict,
                   max_points: int, reps: int, seed: int) -> dict[str, pathlib.Path]:
    series, rows = _curve_rows(curves.values(), name, "iqm", max_points, reps, seed)
    fig = Figure(figsize=(7, 4.5))
    ax = fig.add_subplot()
    _draw(ax, series, colors)
    ax.set_ylabel(f"{title} (IQM over seeds)")
    ax.set_title(f"Episode {title}: IQM across seeds, 95% stratified bootstrap CI", fontsize=10)
    if series:
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(plots / f"{key}.png", dpi=120)
    csv_path = _write_csv(plots / f"{key}.csv", rows, ["metric", "curve", "arm", "hp", "update", "env_steps", "iqm",
                                                      "ci_low", "ci_high", "n_seeds"])
    return {key: plots / f"{key}.png", f"{key}_csv": csv_path}


def _panels_figure(plots: pathlib.Path, panels: Sequence[tuple[str, str, bool]], curves: dict, colors: dict,
                   max_points: int, reps: int, seed: int) -> dict[str, pathlib.Path]:
    """The diagnostics figure (one panel per metric some arm logs, mean over seeds), if any."""
    panels = [(n, t, log) for n, t, log in panels
              if any(n in c.metrics and np.isfinite(c.metrics[n]).any() for c in curves.values())]
    if not panels:
        return {}
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
    fig.savefig(plots / "model.png", dpi=110)
    csv_path = _write_csv(plots / "model.csv", all_rows, ["metric", "curve", "arm", "hp", "update", "env_steps",
                                                         "mean", "ci_low", "ci_high", "n_seeds"])
    return {"model": plots / "model.png", "model_csv": csv_path}
