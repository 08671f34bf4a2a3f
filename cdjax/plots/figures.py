"""The figures of a run or of several runs pooled (`plot_run`, `plot_runs`): the return and the diagnostics panels
as PNGs, each beside the CSV it is drawn from, and the summary."""

from __future__ import annotations

import math
import pathlib
from typing import Callable, Iterable, Sequence

import numpy as np
from matplotlib.figure import Figure
from matplotlib.lines import Line2D

from cdjax import io, stats
from cdjax.plots.curves import Curves, Names, load_eval, load_metrics, pool_curves, pool_seed_arrays
from cdjax.plots.summary import _write_csv, summary_markdown, summary_rows

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
