"""RESULTS tables and the figure of the path-weight grid, from `cdjax sweep` run directories (or the kept data).

    python -m experiments.consistency_weights.report --runs DIR_ANT DIR_HALFCHEETAH   # keeps their data here
    python -m experiments.consistency_weights.report                                 # from data/ (kept)
    python -m experiments.consistency_weights.report --data data-gru-recon --out tables-gru-recon.md \
        --figure grid-gru-recon.png                                                  # the first encoder's grid
    python -m experiments.consistency_weights.report --default-sweep DIR             # + the issue's default sweep

Each task's run has one cd arm whose hyper-parameter grid crosses cc_model (the consistency gradient's
weight on the model and the encoder) with cc_policy (its weight on the policy, through the actions), alpha
= 1, seeds vmapped. The cell cc_model = cc_policy = 0 is Mb-Mf: the policy, value and model get exactly
Mb-Mf's gradients (tests/test_learner.py); only the unused encoder trains. Cells with cc_policy = 0 differ
from it only in the model, which PPO never reads, so their returns differ from Mb-Mf's only by the GPU's
floating-point non-determinism: they show how far apart identical learners land.

Statistics are cdjax.stats': IQM over seeds with a 95% stratified-bootstrap interval; "final" is the mean
of each seed's last 10% of logged updates, "eval" the final deterministic evaluation (mean over its
episodes), diagnostics are final values.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import shutil

import numpy as np

from cdjax import io, plots, stats
from experiments.consistency_weights import TASKS

HERE = pathlib.Path(__file__).resolve().parent
DIAGNOSTICS = (
    ("model/openloop_mse_k", "open-loop MSE at k"),
    ("model/openloop_mse_50", "open-loop MSE at 50"),
    ("model/onestep_mse", "one-step MSE"),
    ("loss/consistency", "l_cc"),
)
RATIOS = (("grad/consistency/policy", "grad/ppo/policy", "policy: l_cc / PPO"),
          ("grad/consistency/model", "grad/model_nll/model", "model: l_cc / NLL"))
SPREAD = "encoder/spread_real"


def keep(run_dir: pathlib.Path, task: str, data: pathlib.Path) -> pathlib.Path:
    """Copy run.json, eval.jsonl and metrics.jsonl (compressed: `cdjax.io.write_packed`) of a run directory into
    <data>/<task>/."""
    out = data / task
    out.mkdir(parents=True, exist_ok=True)
    for name in ("run.json", "eval.jsonl"):
        shutil.copy(run_dir / name, out / name)
    io.write_packed(out / "metrics.jsonl", (run_dir / "metrics.jsonl").read_bytes())
    return out


def _weights(label: str) -> tuple[float, float]:
    fields = dict(part.split("=") for part in label.split(","))
    return float(fields.get("cc_model", 1.0)), float(fields.get("cc_policy", 1.0))


def _ci(x: tuple, digits: int = 4) -> str:
    point, low, high = x[:3]
    fmt = lambda v: f"{v:.{digits}g}"  # noqa: E731
    return f"{fmt(point)} [{fmt(low)}, {fmt(high)}]" if np.isfinite(low) else fmt(point)


def cells(run_dir: pathlib.Path, reps: int = 2000) -> list[dict]:
    """One row per grid cell: returns, diagnostics, encoder spread and gradient balance, IQM over seeds."""
    curves = plots.load_metrics(run_dir)
    evals = plots.load_eval(run_dir)
    rows = []
    for (arm, label), c in curves.items():
        ev = evals.get((arm, label, True), {}).get("return", np.array([]))
        row = {"label": label, "weights": _weights(label), "seeds": len(c.seeds),
               "env_steps": float(np.nanmax(c.env_steps)),
               "eval": stats.iqm_interval(ev, reps=reps),
               "final": stats.iqm_interval(plots.per_seed_final(c, plots.RETURN), reps=reps),
               "auc": stats.iqm_interval(plots.per_seed_auc(c, plots.RETURN), reps=reps)}
        for name, _ in DIAGNOSTICS:
            row[name] = stats.iqm_interval(plots.per_seed_final(c, name), reps=reps)
        spread = c.metrics.get(SPREAD)
        if spread is not None:
            first = spread[:, np.argmax(c.updates >= 1)]
            row["spread_first"] = stats.iqm_interval(first, reps=reps)
            row["spread_end"] = stats.iqm_interval(plots.per_seed_final(c, SPREAD), reps=reps)
            row["spread_min"] = float(np.nanmin(spread))
        for num, den, name in RATIOS:
            if num in c.metrics and den in c.metrics:
                ratio = np.nanmean(c.metrics[num] / c.metrics[den], axis=1)
                row[name] = stats.iqm_interval(ratio, reps=reps)
        rows.append(row)
    return sorted(rows, key=lambda r: r["weights"])


def tables(task: str, rows: list[dict]) -> str:
    head = ("| cc_model | cc_policy | seeds | eval return | training return, final | training return, AUC | "
            + " | ".join(label for _, label in DIAGNOSTICS) + " |")
    lines = [f"### {task}", "", head, "|" + "---|" * (6 + len(DIAGNOSTICS))]
    for r in rows:
        m, p = r["weights"]
        lines.append(f"| {m:g} | {p:g} | {r['seeds']} | {_ci(r['eval'])} | {_ci(r['final'])} | {_ci(r['auc'])} | "
                     + " | ".join(_ci(r[name], 3) for name, _ in DIAGNOSTICS) + " |")
    lines += ["", "| cc_model | cc_policy | encoder spread, update 1 | encoder spread, end | lowest in any run | "
              + " | ".join(name for _, _, name in RATIOS) + " (gradient norms) |", "|" + "---|" * (5 + len(RATIOS))]
    for r in rows:
        m, p = r["weights"]
        ratios = " | ".join(_ci(r[name], 3) if name in r else "–" for _, _, name in RATIOS)
        lines.append(f"| {m:g} | {p:g} | {_ci(r['spread_first'], 3)} | {_ci(r['spread_end'], 3)} | "
                     f"{r['spread_min']:.2g} | {ratios} |")
    return "\n".join(lines)


def default_sweep(run_dir: pathlib.Path, reps: int = 2000) -> str:
    """The issue's check at the defaults (arms mbmf and cd on ant): each arm's evaluation, and for cd the encoder
    spread at update 1 and at the end of every run (their ratio must stay >= 0.1) and the gradient balance."""
    curves, evals = plots.load_metrics(run_dir), plots.load_eval(run_dir)
    lines = ["| arm | seeds | eval return, IQM [95% CI] | per seed | encoder spread: end / update 1, per seed | "
             "lowest spread | policy: l_cc / PPO | model: l_cc / NLL |", "|" + "---|" * 8]
    for (arm, label), c in sorted(curves.items()):
        ev = evals.get((arm, label, True), {}).get("return", np.array([]))
        cols = [arm, str(len(c.seeds)), _ci(stats.iqm_interval(ev, reps=reps)), ", ".join(f"{v:.0f}" for v in ev)]
        spread = c.metrics.get(SPREAD)
        if spread is None:
            cols += ["–", "–", "–", "–"]
        else:
            first = spread[:, np.argmax(c.updates >= 1)]
            ratio = plots.per_seed_final(c, SPREAD) / first
            cols += [", ".join(f"{v:.2f}" for v in ratio), f"{np.nanmin(spread):.2g}"]
            for num, den, _ in RATIOS:
                cols.append(_ci(stats.iqm_interval(np.nanmean(c.metrics[num] / c.metrics[den], axis=1), reps=reps), 3))
        lines.append("| " + " | ".join(cols) + " |")
    return "\n".join(lines)


def figure(results: dict[str, list[dict]], path: pathlib.Path) -> pathlib.Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = (("eval", "eval return (IQM, 95% CI)"), ("model/openloop_mse_50", "open-loop MSE at 50 steps"),
              ("spread_end", "encoder spread at the end"))
    fig, axes = plt.subplots(len(results), len(panels), figsize=(4.6 * len(panels), 0.45 * 9 + 1.2 * len(results)),
                             squeeze=False)
    for row_axes, (task, rows) in zip(axes, results.items()):
        labels = [f"{r['weights'][0]:g} / {r['weights'][1]:g}" for r in rows]
        y = np.arange(len(rows))
        for ax, (key, title) in zip(row_axes, panels):
            point = np.array([r[key][0] for r in rows])
            low = np.array([r[key][1] for r in rows])
            high = np.array([r[key][2] for r in rows])
            colors = ["#1f77b4" if r["weights"] == (0.0, 0.0) else "#d62728" for r in rows]
            ax.errorbar(point, y, xerr=[np.nan_to_num(point - low), np.nan_to_num(high - point)], fmt="none",
                        ecolor="#999999")
            ax.scatter(point, y, c=colors, zorder=3)
            ax.set_yticks(y, labels)
            ax.set_title(f"{task}: {title}", fontsize=9)
            if key != "eval":
                ax.set_xscale("log")
        row_axes[0].set_ylabel("cc_model / cc_policy (blue: Mb-Mf)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m experiments.consistency_weights.report", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--runs", nargs="*", type=pathlib.Path, help="run directories, one per task in TASKS order")
    p.add_argument("--data", type=pathlib.Path, default=HERE / "data", help="where the kept data is (or goes)")
    p.add_argument("--out", type=pathlib.Path, default=HERE / "tables.md", help="where the tables go")
    p.add_argument("--figure", type=pathlib.Path, default=HERE / "grid.png", help="where the figure goes")
    p.add_argument("--default-sweep", type=pathlib.Path,
                   help="run directory of `cdjax sweep --env ant --arms mbmf cd` at the defaults (kept as "
                        "<data>/ant-defaults); without it, the kept one is reported when there is one")
    args = p.parse_args(argv)
    data = args.data if args.data.is_absolute() else HERE / args.data
    out = args.out if args.out.is_absolute() or args.out.parent != pathlib.Path(".") else HERE / args.out
    fig = args.figure if args.figure.is_absolute() or args.figure.parent != pathlib.Path(".") else HERE / args.figure
    results, parts = {}, []
    for i, task in enumerate(TASKS):
        kept = keep(args.runs[i], task, data) if args.runs else data / task
        info = json.loads((kept / "run.json").read_text())
        results[task] = cells(kept)  # its metrics.jsonl.xz (or .gz) is read in place of metrics.jsonl (io.read_jsonl)
        parts.append(tables(task, results[task]) + f"\n\nCommand: `{info.get('command', '?')}`\n")
    sweep = keep(args.default_sweep, "ant-defaults", data) if args.default_sweep else data / "ant-defaults"
    if sweep.exists():
        info = json.loads((sweep / "run.json").read_text())
        parts.append("### ant, the defaults: Mb-Mf against CD\n\n" + default_sweep(sweep)
                     + f"\n\nCommand: `{info.get('command', '?')}`\n")
    out.write_text("\n".join(parts))
    figure(results, fig)
    print(out.read_text())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
