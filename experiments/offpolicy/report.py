"""RESULTS.md of the off-policy experiment, from the kept data of its units (or their run directories).

    python -m experiments.offpolicy.report                          # from data/ (the kept data)
    python -m experiments.offpolicy.report --runs DIR [DIR ...] --out OUT

Every run directory under --runs (a directory with run.json and metrics) is read; its runs are grouped by task
(run.json's env) and named by what they are (`arm_key`: model-free, model, paper-cd-k3-a1, self-pred-k5-a0.1, ...).
Arms of a task are compared at the same env steps: the task's budget when every arm reached it, else the largest
count all of them reached (and the table says so).

Statistics (cdjax.stats, rliable): per task and arm the IQM over seeds with its 95% stratified-bootstrap interval of
the final training return (the last 10% of each seed's env steps), of the area under the curve and of the final
deterministic evaluation; P(arm > model-free) and P(arm > model) over seeds. Across tasks: the IQM of min-max
normalised final returns, performance profiles and the probability of improvement (averaged over tasks). The
diagnostics (Config.diagnostics) are the final values (IQM over seeds): the model's open-loop error on held-out envs
at the first and the last step of the horizon, the latent's spread, and each consistency term's gradient against the
main loss's on the same parameters (the paper's policy path: consistency / actor loss on the actor; the model path
and self-pred: the term / the critic loss on the encoder).
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import pathlib
from typing import Sequence

import numpy as np

from cdjax import plots, stats
from experiments.offpolicy import TASKS
from experiments.paper_obs_space.report import _cell, _csv, _cut, _reached, _table, aggregate, find_runs, improvement, \
    normalised, profiles_figure

HERE = pathlib.Path(__file__).resolve().parent
RETURN, DISC = plots.RETURN, plots.DISC_RETURN
BASELINES = ("model-free", "model")
# (name, column title, numerator, denominator): numerator / denominator per point, then the final value
RATIOS = (("ratio/policy_path", "cd grad / actor grad (actor)", "grad/consistency/actor", "grad/actor/actor"),
          ("ratio/model_path", "cd grad / critic grad (encoder)", "grad/consistency/encoder", "grad/critic/encoder"),
          ("ratio/self_pred", "self-pred grad / critic grad (encoder)", "grad/self_pred/encoder",
           "grad/critic/encoder"))
DIAGNOSTICS = (("heldout/open_loop_mse_1", "held-out open-loop MSE, step 1"),
               ("heldout/open_loop_mse_k", "held-out open-loop MSE, step k"),
               ("latent/spread", "latent spread"), ("model/obs_mse", "model one-step MSE (replay)"))


def arm_key(arm: dict, hp: dict) -> str:
    """model-free and model as they are (with `-obs` when the actor and critic read the observation alone, the TASK-obs
    unit); a consistency arm with its horizon and weight: paper-cd-k3-a1."""
    kind = arm.get("arm") or arm.get("config", {}).get("arm")
    if kind in BASELINES:
        return kind + ("-obs" if arm.get("config", {}).get("inputs") == "obs" else "")
    return f"{kind}-k{arm.get('config', {}).get('horizon')}-a{hp.get('alpha', math.nan):g}"


def _key_order(keys) -> list[str]:
    return sorted(keys, key=lambda k: (k not in BASELINES, BASELINES.index(k) if k in BASELINES else 0, k))


@dataclasses.dataclass
class Task:
    name: str
    curves: dict  # arm key -> plots.Curves (cut at `budget` when not complete)
    evals: dict  # arm key -> deterministic evaluation {"return": [S], ...} or None
    budget: float
    planned: float
    complete: bool
    commands: list  # run.json's commands of its run directories


def _with_ratios(c: plots.Curves) -> plots.Curves:
    for name, _, num, den in RATIOS:
        if num in c.metrics and den in c.metrics:
            with np.errstate(divide="ignore", invalid="ignore"):
                c.metrics[name] = c.metrics[num] / c.metrics[den]
    k = max((int(n.rsplit("_", 1)[1]) for n in c.metrics if n.startswith("heldout/open_loop_mse_")), default=0)
    if k:
        c.metrics["heldout/open_loop_mse_k"] = c.metrics[f"heldout/open_loop_mse_{k}"]
    return c


def load(roots: Sequence[pathlib.Path]) -> list[Task]:
    """Every task under `roots`, in TASKS order; an arm key found twice keeps its first directory's runs."""
    from cdjax import io

    found: dict[str, dict] = {}
    for path in find_runs(roots):
        info = io.RunDir(path).read()
        labels = {(a["name"], str(label)): arm_key(a, hp) for a in info["arms"]
                  for label, hp in zip(a.get("hp_labels", ["default"]), a.get("hparams", [{}]))}
        task = found.setdefault(info.get("base_config", {}).get("env", "?"),
                                {"curves": {}, "evals": {}, "planned": {}, "commands": []})
        task["commands"].append(info.get("command", ""))
        evals = {(a, h): v for (a, h, det), v in plots.load_eval(path).items() if det}
        for (arm, label), c in plots.load_metrics(path).items():
            key = labels.get((arm, label), f"{arm} {label}")
            if key not in task["curves"]:
                task["curves"][key] = _with_ratios(c)
                task["evals"][key] = evals.get((arm, label))
                task["planned"][key] = float(info.get("total_env_steps", math.nan))
    tasks = []
    for name in [t for t in TASKS if t in found] + sorted(t for t in found if t not in TASKS):
        t = found[name]
        reached = {k: _reached(c) for k, c in t["curves"].items()}
        complete = all(reached[k] >= t["planned"][k] for k in reached)
        budget = min(reached.values())
        curves, evals = t["curves"], t["evals"]
        if not complete:  # compare where every arm got; evaluations were made at each run's own end
            curves = {k: _cut(c, budget) for k, c in curves.items()}
            evals = {k: None for k in evals}
        tasks.append(Task(name, curves, evals, budget, max(t["planned"].values()), complete, t["commands"]))
    return tasks


def final_scores(tasks: list[Task]) -> dict[str, dict[str, np.ndarray]]:
    """{task: {arm key: final training return per seed}} (finite values only)."""
    out = {}
    for t in tasks:
        out[t.name] = {}
        for key, c in t.curves.items():
            v = plots.per_seed_final(c, RETURN)
            out[t.name][key] = v[np.isfinite(v)]
    return out


def task_rows(task: Task, reps: int) -> list[dict]:
    scores = final_scores([task])
    rows = []
    for key in _key_order(task.curves):
        c = task.curves[key]
        row = {"task": task.name, "arm": key, "seeds": len(c.seeds),
               "env_steps": float(np.nanmax(c.env_steps)) if c.env_steps.size else math.nan,
               "final": stats.iqm_interval(plots.per_seed_final(c, RETURN), reps)[:3],
               "auc": stats.iqm_interval(plots.per_seed_auc(c, RETURN), reps)[:3]}
        ev = task.evals.get(key)
        row["eval"] = stats.iqm_interval(ev["return"], reps)[:3] if ev else (math.nan,) * 3
        for base in BASELINES:
            imp = improvement(scores, ((key, base),), reps=reps) if key != base else []
            row[f"p_{base}"] = (imp[0]["p"], imp[0]["low"], imp[0]["high"]) if imp else (math.nan,) * 3
        for name, *_ in DIAGNOSTICS + RATIOS:
            row[name] = stats.iqm_interval(plots.per_seed_final(c, name), reps)[:3] if name in c.metrics \
                else (math.nan,) * 3
        rows.append(row)
    return rows


def returns_table(rows: list[dict]) -> str:
    return _table(("task", "arm", "seeds", "env steps", "final return", "AUC", "final eval (deterministic)",
                   "P(> model-free)", "P(> model)"),
                  ([r["task"], r["arm"], str(r["seeds"]), f"{r['env_steps']:,.0f}", _cell(r["final"]), _cell(r["auc"]),
                    _cell(r["eval"]), _cell(r["p_model-free"], 3), _cell(r["p_model"], 3)] for r in rows))


def diagnostics_table(rows: list[dict]) -> str:
    shown = [(n, t) for n, t, *_ in DIAGNOSTICS + RATIOS if any(np.isfinite(r[n][0]) for r in rows)]
    return _table(("task", "arm") + tuple(t for _, t in shown),
                  ([r["task"], r["arm"]] + [_cell(r[n], 3) for n, _ in shown] for r in rows))


def write_results(tasks: list[Task], out: pathlib.Path, reps: int = 2000) -> pathlib.Path:
    rows = [r for t in tasks for r in task_rows(t, reps)]
    scores = final_scores(tasks)
    keys = _key_order({k for per in scores.values() for k in per})
    agg, profiles = aggregate(normalised(scores), keys, reps=reps)
    pairs = tuple((k, b) for k in keys for b in BASELINES if k != b and not (k == "model-free" and b == "model"))
    across = improvement(scores, pairs, reps=reps) if len(scores) > 1 else []
    lines = ["# Does consistency help a sample-efficient learner? (results)", "",
             "Generated by `python -m experiments.offpolicy.report` from the kept data (`data/`); the reading is "
             "`analysis.md`. Units: `python -m experiments.offpolicy list`.", ""]
    for t in tasks:
        state = "every arm at its budget" if t.complete else f"cut at {t.budget:,.0f} env steps, where every arm got"
        lines.append(f"- {t.name}: {t.planned:,.0f} env steps per run planned, {state}.")
    lines += ["", "## Returns per task", "", returns_table(rows), "", "## Diagnostics (final values, IQM over seeds)",
              "", diagnostics_table(rows), ""]
    if agg:
        lines += ["## Across tasks", "", f"Tasks: {', '.join(agg[0]['tasks'])}. Min-max normalised final return per "
                  "task over every seed of every arm.", "",
                  _table(("arm", "IQM normalised final return"), ([a["arm"], _cell((a["iqm"], a["low"], a["high"]), 3)]
                                                                   for a in agg)), ""]
        profiles_figure(profiles, out / "figures" / "profiles.png")
        lines += ["![performance profiles](figures/profiles.png)", ""]
    if across:
        lines += [_table(("X", "Y", "P(X > Y) over tasks"), ([p["x"], p["y"], _cell((p["p"], p["low"], p["high"]), 3)]
                                                             for p in across)), ""]
    lines += ["## Commands", ""] + [f"- `{c}`" for t in tasks for c in t.commands] + [""]
    out.mkdir(parents=True, exist_ok=True)
    _csv(out / "results.csv", [{k: (v[0] if isinstance(v, tuple) else v) for k, v in r.items()} for r in rows])
    path = out / "RESULTS.md"
    path.write_text("\n".join(lines))
    return path


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m experiments.offpolicy.report", description=__doc__.split("\n\n")[0])
    p.add_argument("--runs", nargs="+", type=pathlib.Path, default=[HERE / "data"])
    p.add_argument("--out", type=pathlib.Path, default=HERE)
    p.add_argument("--bootstrap-reps", type=int, default=2000)
    args = p.parse_args(argv)
    tasks = load(args.runs)
    if not tasks:
        p.exit(2, f"{p.prog}: no run directory with logged updates under {', '.join(map(str, args.runs))}.\n")
    print(f"Wrote {write_results(tasks, args.out, args.bootstrap_reps)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
