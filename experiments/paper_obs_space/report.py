"""RESULTS.md of the observation-space experiment, from the kept data of its units (or their run directories).

    python -m experiments.paper_obs_space report                       # from data/ (the kept data)
    python -m experiments.paper_obs_space report --runs DIR data --keep  # add the units unpacked in DIR to data/

Every run directory found under --runs (a directory with run.json; a unit's parts are run directories) is read;
its arms are named by what they are (`arm_key`: model-free, mbmf, cd-k5, cd-k20-paper, cd-k20,
cd-k20-paper-schedule) and grouped by task (run.json's env). Arms of a task are compared at the same env steps:
the task's budget when every arm reached it, else the largest count all of them reached (and RESULTS.md says so).

Statistics: per task and arm the IQM over seeds with a 95% stratified-bootstrap interval (rliable, cdjax.stats)
of the final return (the last 10% of each seed's logged points) and of the area under the curve (each seed's curve
averaged over env steps), undiscounted and discounted, and of the deterministic evaluation; across tasks
rliable's probability of improvement (per task P(X > Y) over seeds, averaged over tasks) and performance profiles
and IQM of min-max normalised final returns (per task over every seed of every arm). The diagnostics are the
means over the last 10% of each seed's points (IQM over seeds): the model's own open-loop error and its error on
the common yardstick (yardstick/), l_cc, the encoder's spread, the masked windows, and the consistency gradient's
size against PPO's on the policy and against the NLL's on the model.
"""

from __future__ import annotations

import csv
import dataclasses
import json
import math
import pathlib
import shutil
from typing import Iterable, Sequence

import numpy as np

from cdjax import io, plots, stats
from experiments.paper_obs_space import ARMS, SCHEDULE_TASKS, TASK_BUDGETS, TASKS

HERE = pathlib.Path(__file__).resolve().parent
RETURN, DISC = plots.RETURN, plots.DISC_RETURN
MAIN_ARMS = ("model-free", "mbmf", "cd-k5", "cd-k20-paper", "cd-k20")
LABELS = {"model-free": "model-free", "mbmf": "Mb-Mf", "cd-k5": "CD k=5", "cd-k20-paper": "CD k=20 (paper's weights)",
          "cd-k20": "CD k=20 (cdjax's weights)", "cd-k20-paper-schedule": "CD k=20 (paper's schedule)",
          "mbmf-value0": "Mb-Mf, value not fitted", "mbmf-model-only": "Mb-Mf, model only (untrained policy)"}
COLORS = {"model-free": "#7f7f7f", "mbmf": "#1f77b4", "cd-k5": "#ff7f0e", "cd-k20-paper": "#d62728",
          "cd-k20": "#9467bd", "cd-k20-paper-schedule": "#2ca02c", "mbmf-value0": "#17becf",
          "mbmf-model-only": "#bcbd22"}
HANDOVER_ABLATION = ("mbmf-value0", "mbmf-model-only")  # unit halfcheetah-5: parts of Mb-Mf's hand-over left out
START_ARMS = ("model-free", "mbmf") + HANDOVER_ABLATION  # their section's rows
# (metric, column title, how the final value is formed): diagnostics at the end of training
DIAGNOSTICS = (
    ("model/openloop_mse_k", "open-loop MSE at k (own states)"),
    ("model/openloop_mse_50", "open-loop MSE at 50 (own states)"),
    ("model/yardstick_mse_k", "open-loop MSE at k (yardstick)"),
    ("model/yardstick_mse_50", "open-loop MSE at 50 (yardstick)"),
    ("loss/consistency", "l_cc"),
    ("encoder/spread_real", "encoder spread"),
    ("consistency/masked_fraction", "masked windows"),
    ("consistency/final_beyond_clip", "final imagined features beyond the clip"),
    ("ratio/policy", "l_cc grad / PPO grad (policy)"),
    ("ratio/model", "l_cc grad / NLL grad (model)"),
)
RATIOS = {"ratio/policy": ("grad/consistency/policy", "grad/ppo/policy"),
          "ratio/model": ("grad/consistency/model", "grad/model_nll/model")}
# the columns of metrics.jsonl kept in data/ (metrics.jsonl.xz; older units' metrics.jsonl.gz)
KEEP = ("arm", "hp", "seed", "update", "env_steps", "wall_s", RETURN, DISC, "episode/count", "env/reward_mean",
        "env/invalid_fraction", "opt/skipped_updates", "policy/std") + tuple(
    n for n, _ in DIAGNOSTICS if not n.startswith("ratio/")) + tuple(x for pair in RATIOS.values() for x in pair)
# (X, Y) pairs whose probability of improvement P(X > Y) is reported across tasks
PAIRS = (("cd-k20-paper", "mbmf"), ("cd-k20", "mbmf"), ("cd-k5", "mbmf"), ("cd-k20-paper", "cd-k5"),
         ("mbmf", "model-free"), ("cd-k20-paper", "model-free"))
PHASE_COLUMNS = (  # phase.jsonl (its keys carry "phase/"), (title)
    ("random/reward_mean", "random actions"), ("mpc/reward_mean_last", "MPC"),
    ("dagger/reward_mean_last", "distilled policy"), ("labels/self_error", "one label vs the others' mean"),
    ("labels/mean_abs", "|mean label|"), ("distill/abs_error_mean", "policy vs mean label"),
    ("distill/abs_error_zero", "zero action vs labels"), ("model/heldout_mse_last", "model held-out MSE"))
START_COLUMNS = (  # the phase's handover checks: the policy PPO gets against an untrained one, same reset states
    ("handover/sampled_reward_mean", "distilled, sampled"), ("fresh/sampled_reward_mean", "untrained, sampled"),
    ("handover/mean_action_reward_mean", "distilled, mean action"),
    ("fresh/mean_action_reward_mean", "untrained, mean action"))


def arm_key(arm: dict, hp: dict, phase: dict | None = None) -> str:
    """The experiment's name of an (arm, hyper-parameters) of a run.json: model-free, mbmf, cd-k5, cd-k20-paper (both
    paths of l_cc at alpha), cd-k20 (cdjax's weights), cd-k20-paper-schedule (l_cc in every epoch), else arm/label;
    an mbmf arm whose phase (run.json's "phase") hands PPO the untrained policy is mbmf-model-only, one whose phase
    leaves the value unfitted mbmf-value0."""
    kind = arm.get("arm") or arm.get("config", {}).get("arm")
    if kind == "mbmf" and phase:
        if not phase.get("hand_policy", True):
            return "mbmf-model-only"
        if phase.get("value_epochs", 1) == 0:
            return "mbmf-value0"
    if kind in ("model-free", "mbmf"):
        return kind
    config = arm.get("config", {})
    k = config.get("horizon")
    paper_weights = hp.get("cc_policy") == 1.0 and hp.get("cc_model", 1.0) == 1.0
    every_epoch = config.get("cc_epochs") == 0 and config.get("num_epochs", 1) > 1
    if kind == "cd" and k == 5:
        return "cd-k5"
    if kind == "cd" and k == 20:
        if every_epoch:
            return "cd-k20-paper-schedule" + ("" if not paper_weights else "-paper-weights")
        return "cd-k20-paper" if paper_weights else "cd-k20"
    return f"{arm.get('name')}"


@dataclasses.dataclass
class Run:
    """One run directory (a unit's part): its record, curves and evaluations by arm key."""

    path: pathlib.Path
    info: dict  # run.json
    machine: dict  # machine.json ({} if absent)
    unit: dict  # the unit's unit.json ({} if absent)
    curves: dict  # arm key -> plots.Curves
    evals: dict  # arm key -> {"return": [S], ...} (deterministic evaluation)
    phase: dict  # arm key -> {metric: [S] values}
    planned: dict  # arm key -> env steps per run asked for (the phase's included)
    phase_steps: dict  # arm key -> env steps of its Mb-Mf phase per run

    @property
    def task(self) -> str:
        return self.info.get("base_config", {}).get("env", "?")


@dataclasses.dataclass
class TaskData:
    name: str
    runs: list[Run]
    curves: dict  # arm key -> Curves, cut at `budget`
    evals: dict
    phase: dict
    budget: float  # env steps the arms are compared at
    stated: float  # the env steps per run its runs asked for (the largest)
    complete: bool  # every arm reached its planned env steps
    pooled: dict = dataclasses.field(default_factory=dict)  # arm key -> base seeds of the runs pooled into it (>1)
    dropped: list = dataclasses.field(default_factory=list)  # "arm key in DIR" for each arm found again and left out


def find_runs(roots: Iterable[pathlib.Path]) -> list[pathlib.Path]:
    """Run directories (with run.json and metrics) under `roots`; a directory reached twice counts once."""
    seen, out = set(), []
    for root in roots:
        root = pathlib.Path(root)
        if not root.exists():
            continue
        for run_json in sorted(root.rglob("run.json")):
            d = run_json.parent
            if d.resolve() not in seen and io.jsonl_exists(d / "metrics.jsonl"):
                seen.add(d.resolve())
                out.append(d)
    return out


def _phase_rows(path: pathlib.Path, keys: dict) -> dict:
    out: dict = {}
    for row in io.read_jsonl(path / "phase.jsonl"):
        key = keys.get((row.get("arm"), str(row.get("hp", ""))))
        if key is None:
            continue
        for name, _ in PHASE_COLUMNS + START_COLUMNS:
            value = row.get(f"phase/{name}")
            out.setdefault(key, {}).setdefault(name, []).append(math.nan if value is None else float(value))
    return {k: {n: np.array(v) for n, v in d.items()} for k, d in out.items()}


def load_run(path: pathlib.Path) -> Run:
    info = io.RunDir(path).read()
    read = lambda name: json.loads((path / name).read_text()) if (path / name).exists() else {}  # noqa: E731
    keys, planned, phase_steps = {}, {}, {}
    for arm in info["arms"]:
        for label, hp in zip(arm.get("hp_labels", ["default"]), arm.get("hparams", [{}])):
            key = arm_key(arm, hp, info.get("phase"))
            keys[(arm["name"], str(label))] = key
            planned[key] = arm.get("total_env_steps", info.get("total_env_steps"))
            phase_steps[key] = arm.get("phase_env_steps", 0)
    curves = {}
    for (arm, label), c in plots.load_metrics(path).items():
        key = keys.get((arm, label), f"{arm} {label}")
        for name, (num, den) in RATIOS.items():
            if num in c.metrics and den in c.metrics:
                with np.errstate(divide="ignore", invalid="ignore"):
                    c.metrics[name] = c.metrics[num] / c.metrics[den]
        curves[key] = c
    evals = {keys.get((a, h), a): v for (a, h, det), v in plots.load_eval(path).items() if det}
    return Run(path, info, read("machine.json"), read("../unit.json") or read("unit.json"), curves, evals,
               _phase_rows(path, keys), planned, phase_steps)


def _cut(c: plots.Curves, budget: float) -> plots.Curves:
    keep = np.isfinite(c.env_steps) & (c.env_steps <= budget)
    return dataclasses.replace(c, updates=c.updates[keep], env_steps=c.env_steps[keep], present=c.present[:, keep],
                               metrics={k: v[:, keep] for k, v in c.metrics.items()})


def _reached(c: plots.Curves) -> float:
    everywhere = c.present.all(axis=0)
    return float(np.nanmax(c.env_steps[everywhere])) if everywhere.any() else 0.0


def load(roots: Sequence[pathlib.Path], arms: Sequence[str] | None = None) -> list[TaskData]:
    """Every task found under `roots`, in TASKS order (others after); with `arms`, only those arm keys (LABELS).

    An arm found in several runs is pooled when they ran other base seeds (`cdjax sweep --seed`) at the same budget:
    their seeds together are the arm's. A run of the same arm on seeds already found (a unit run again) is left out:
    the first directory found wins, and the report names the one left out."""
    by_task: dict[str, list[Run]] = {}
    for path in find_runs(roots):
        run = load_run(path)
        by_task.setdefault(run.task, []).append(run)
    order = [t for t in TASKS if t in by_task] + sorted(t for t in by_task if t not in TASKS)
    tasks = []
    for name in order:
        runs = [r for r in by_task[name] if arms is None or any(k in arms for k in r.curves)]
        if not runs:
            continue
        curves, evals, phase, planned, bases, dropped = {}, {}, {}, {}, {}, []
        for run in runs:
            base = int(run.info.get("seed", 0))
            for key, c in run.curves.items():
                if arms is not None and key not in arms:
                    continue
                if key not in curves:
                    curves[key], planned[key] = c, run.planned.get(key, math.nan)
                    evals[key] = run.evals.get(key)
                    phase[key] = run.phase.get(key)
                    bases[key] = [base]
                elif base not in bases[key] and run.planned.get(key) == planned[key]:
                    # the same arm on other seeds (another base seed) at the same budget: its seeds join the arm's
                    curves[key], offset = plots.pool_curves(curves[key], c)
                    theirs = run.evals.get(key)  # its seed ids shifted as its curves' were
                    theirs = theirs and dict(theirs, seeds=theirs["seeds"] + offset)
                    evals[key] = plots.pool_seed_arrays(evals[key], theirs)
                    phase[key] = plots.pool_seed_arrays(phase[key], run.phase.get(key))
                    bases[key].append(base)
                else:  # a unit run again on the same seeds, or at another budget: the first directory found wins
                    dropped.append(f"{key} in {run.path}")
        reached = {k: _reached(c) for k, c in curves.items()}
        complete = all(reached[k] >= planned[k] for k in curves)
        budget = min(reached.values()) if reached else 0.0
        if not complete:
            spu = max(r.info.get("env_steps_per_update", 0) for r in runs)
            curves = {k: _cut(c, budget + spu / 2) for k, c in curves.items()}
            evals = {k: None for k in evals}  # evaluations were made at each run's end, not at the common budget
        stated = max(planned.values(), default=math.nan)
        tasks.append(TaskData(name, runs, curves, evals, phase, budget, stated, complete,
                              {k: b for k, b in bases.items() if len(b) > 1}, dropped))
    return tasks


# ---------------------------------------------------------------------------------------------------
# Tables


def _fmt(x: float, digits: int = 4) -> str:
    return "n/a" if x is None or not np.isfinite(x) else f"{x:.{digits}g}"


def _cell(v: tuple, digits: int = 4) -> str:
    iqm, lo, hi = v[:3]
    if not np.isfinite(iqm):
        return "n/a"
    return _fmt(iqm, digits) if not np.isfinite(lo) else f"{_fmt(iqm, digits)} [{_fmt(lo, digits)}, {_fmt(hi, digits)}]"


def _arm_order(keys: Iterable[str]) -> list[str]:
    keys = list(keys)
    return [a for a in ARMS if a in keys] + sorted(k for k in keys if k not in ARMS)


def arm_rows(task: TaskData, reps: int) -> list[dict]:
    rows = []
    for key in _arm_order(task.curves):
        c = task.curves[key]
        row = {"task": task.name, "arm": key, "seeds": len(c.seeds), "seed_ids": [int(x) for x in c.seeds],
               "env_steps": float(np.nanmax(c.env_steps)) if c.env_steps.size else math.nan,
               "ppo_updates": int(c.updates.max()) if c.updates.size else 0}
        for stat, fn in (("final", plots.per_seed_final), ("auc", plots.per_seed_auc)):
            for target, name in (("return", RETURN), ("disc_return", DISC)):
                values = fn(c, name)
                row[f"{stat}_{target}"] = stats.iqm_interval(values, reps)[:3]
                row[f"{stat}_{target}_seeds"] = [None if not np.isfinite(v) else round(float(v), 4) for v in values]
        count = c.metrics.get("episode/count")
        row["episodes"] = float(np.nanmean(np.nansum(np.where(c.present, count, 0.0), axis=1))) \
            if count is not None else math.nan
        ev = task.evals.get(key)
        row["eval_return"] = stats.iqm_interval(ev["return"], reps)[:3] if ev else (math.nan,) * 3
        for name in [n for n, _ in DIAGNOSTICS] + ["policy/std"]:
            row[name] = stats.iqm_interval(plots.per_seed_final(c, name), reps)[:3] if name in c.metrics \
                else (math.nan,) * 3
        start = c.metrics.get("env/reward_mean")  # the first PPO rollout's reward per step (update 1)
        first = start[:, np.flatnonzero(c.updates == 1)[0]] if start is not None and (c.updates == 1).any() else []
        row["start_reward"] = stats.iqm_interval(first, reps)[:3] if len(first) else (math.nan,) * 3
        rows.append(row)
    return rows


def _table(head: Sequence[str], lines: Iterable[Sequence[str]]) -> str:
    out = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    out += ["| " + " | ".join(cells) + " |" for cells in lines]
    return "\n".join(out)


def returns_table(rows: list[dict]) -> str:
    head = ("task", "arm", "seeds", "env steps", "PPO updates", "episodes / seed", "final return", "AUC return",
            "final disc. return", "AUC disc. return", "eval return (mean action)")
    return _table(head, ([r["task"], LABELS.get(r["arm"], r["arm"]), str(r["seeds"]), f"{r['env_steps']:,.0f}",
                          str(r["ppo_updates"]), _fmt(r["episodes"]), _cell(r["final_return"]), _cell(r["auc_return"]),
                          _cell(r["final_disc_return"]), _cell(r["auc_disc_return"]), _cell(r["eval_return"])]
                         for r in rows))


def diagnostics_table(rows: list[dict]) -> str:
    head = ("task", "arm") + tuple(title for _, title in DIAGNOSTICS)
    return _table(head, ([r["task"], LABELS.get(r["arm"], r["arm"])] + [_cell(r[n], 3) for n, _ in DIAGNOSTICS]
                         for r in rows if r["arm"] != "model-free"))


def _phase_of(task: TaskData) -> dict | None:
    """The phase's per-seed values of the Mb-Mf arm (every phase of a task is the same program and seeds; another
    arm's when Mb-Mf has not run)."""
    return task.phase.get("mbmf") or next((v for v in task.phase.values() if v), None)


def phase_table(tasks: list[TaskData], reps: int) -> str:
    """Per task: the phase's rewards per step (random, MPC, distilled policy) and its label checks."""
    head = ("task",) + tuple(title for _, title in PHASE_COLUMNS)
    lines = []
    for t in tasks:
        ph = _phase_of(t)
        lines.append([t.name] + [_cell(stats.iqm_interval(ph[n], reps)[:3], 3) if ph and n in ph else "n/a"
                                 for n, _ in PHASE_COLUMNS])
    return _table(head, lines)


def start_table(tasks: list[TaskData], rows: list[dict], reps: int) -> str:
    """Per task: the handover checks (reward per step of the policy PPO gets and of an untrained one, from the same
    reset states) and the first PPO rollout's reward per step of model-free and Mb-Mf."""
    by = {(r["task"], r["arm"]): r for r in rows}
    head = ("task",) + tuple(title for _, title in START_COLUMNS) + ("first PPO rollout: model-free", "Mb-Mf")
    lines = []
    for t in tasks:
        ph = _phase_of(t)
        cells = [t.name] + [_cell(stats.iqm_interval(ph[n], reps)[:3], 3) if ph and n in ph else "n/a"
                            for n, _ in START_COLUMNS]
        cells += [_cell(by[(t.name, a)]["start_reward"], 3) if (t.name, a) in by else "n/a" for a in ("model-free", "mbmf")]
        lines.append(cells)
    return _table(head, lines)


def verdict(rows: list[dict], a: str, b: str, key: str = "final_return") -> str:
    """'A > B' / 'A < B' (95% intervals disjoint) or 'no clear difference' (they overlap)."""
    by = {r["arm"]: r for r in rows}
    if a not in by or b not in by:
        return "n/a"
    (ia, la, ha), (ib, lb, hb) = by[a][key], by[b][key]
    if not (np.isfinite(ia) and np.isfinite(ib)):
        return "n/a"
    if np.isfinite(la) and np.isfinite(hb) and la > hb:
        return f"{LABELS[a]} > {LABELS[b]} ({ia:.4g} vs {ib:.4g}, disjoint)"
    if np.isfinite(lb) and np.isfinite(ha) and lb > ha:
        return f"{LABELS[a]} < {LABELS[b]} ({ia:.4g} vs {ib:.4g}, disjoint)"
    return f"no clear difference ({ia:.4g} vs {ib:.4g}, overlap)"


# ---------------------------------------------------------------------------------------------------
# Across tasks (rliable)


def final_scores(tasks: list[TaskData], arms: Sequence[str] = MAIN_ARMS) -> dict[str, dict[str, np.ndarray]]:
    """{task: {arm: final return per seed [S]}} (finite values only)."""
    out = {}
    for t in tasks:
        per = {}
        for a in arms:
            if a in t.curves:
                v = plots.per_seed_final(t.curves[a], RETURN)
                per[a] = v[np.isfinite(v)]
        out[t.name] = per
    return out


def normalised(scores: dict[str, dict[str, np.ndarray]]) -> dict[str, dict[str, np.ndarray]]:
    """Per task, (x - min) / (max - min) over every seed of every arm of that task."""
    out = {}
    for task, per in scores.items():
        values = np.concatenate([v for v in per.values() if v.size]) if per else np.array([])
        if values.size == 0:
            continue
        lo, hi = values.min(), values.max()
        out[task] = {a: (v - lo) / (hi - lo) if hi > lo else np.zeros_like(v) for a, v in per.items()}
    return out


def _matrix(per_task: dict[str, np.ndarray], tasks: Sequence[str]) -> np.ndarray:
    """[runs, tasks]: the first n seeds of each task, n the fewest any task has."""
    n = min(per_task[t].size for t in tasks)
    return np.stack([per_task[t][:n] for t in tasks], axis=1)


def _rliable():
    if stats.rly is None:
        raise RuntimeError(f"rliable does not import ({stats.RLIABLE_ERROR}); the across-task statistics need it")
    from rliable import metrics

    return stats.rly, metrics


def improvement(scores: dict[str, dict[str, np.ndarray]], pairs=PAIRS, reps: int = 2000, seed: int = 0) -> list[dict]:
    """rliable's probability of improvement P(X > Y) with its 95% interval, over the tasks that have both arms."""
    _rliable()  # refuses in one sentence where rliable does not import
    out = []
    for x, y in pairs:
        tasks = [t for t, per in scores.items() if per.get(x) is not None and per.get(y) is not None
                 and per[x].size > 1 and per[y].size > 1]
        if not tasks:
            continue
        X = _matrix({t: scores[t][x] for t in tasks}, tasks)
        Y = _matrix({t: scores[t][y] for t in tasks}, tasks)
        p, low, high = stats.probability_of_improvement(X, Y, reps=reps, seed=seed)
        out.append({"x": x, "y": y, "tasks": tasks, "p": p, "low": low, "high": high})
    return out


def per_task_improvement(scores: dict[str, dict[str, np.ndarray]], reps: int, pairs=PAIRS) -> str:
    """A table: per task (rows), P(X > Y) of the final return over that task's seeds for every pair (columns) that
    some task has, with its 95% interval; n/a where the task lacks an arm of the pair."""
    per = {task: {(p["x"], p["y"]): p for p in improvement({task: arms}, pairs, reps)} for task, arms in scores.items()}
    shown = [pair for pair in pairs if any(pair in cells for cells in per.values())]
    return _table(("task",) + tuple(f"P({LABELS[x]} > {LABELS[y]})" for x, y in shown),
                  ([task] + [_cell((c["p"], c["low"], c["high"]), 3) if (c := cells.get(pair)) else "n/a"
                             for pair in shown] for task, cells in per.items()))


def schedule_improvement(tasks: list[TaskData], reps: int) -> str:
    """P(paper's schedule > the presets') of the final returns over seeds, with its 95% interval: over one task's
    seeds, or averaged over several tasks (rliable's stratified bootstrap)."""
    scores = final_scores(tasks, ("cd-k20", "cd-k20-paper-schedule"))
    imp = improvement(scores, (("cd-k20-paper-schedule", "cd-k20"),), reps=reps)
    return _cell((imp[0]["p"], imp[0]["low"], imp[0]["high"]), 3) if imp else "n/a"


def _improvement_cells(task: TaskData, arm: str, against: Sequence[str], reps: int) -> list[str]:
    """P(arm > each of `against`) of the final return over one task's seeds, with its 95% interval; n/a for the arm
    itself or a missing arm."""
    scores = final_scores([task], (arm,) + tuple(against))
    cells = []
    for other in against:
        imp = improvement(scores, ((arm, other),), reps=reps) if other != arm else []
        cells.append(_cell((imp[0]["p"], imp[0]["low"], imp[0]["high"]), 3) if imp else "n/a")
    return cells


def aggregate(norm: dict[str, dict[str, np.ndarray]], arms: Sequence[str] = MAIN_ARMS, reps: int = 2000,
              seed: int = 0) -> tuple[list[dict], dict]:
    """IQM of normalised final returns across tasks (95% interval) per arm, and performance profiles
    {arm: (taus, profile, low, high)}, over the tasks that have every arm listed."""
    rly, metrics = _rliable()
    arms = [a for a in arms if any(a in per for per in norm.values())]
    tasks = [t for t, per in norm.items() if all(a in per and per[a].size > 1 for a in arms)]
    if not tasks or not arms:
        return [], {}
    data = {a: _matrix({t: norm[t][a] for t in tasks}, tasks) for a in arms}
    taus = np.linspace(0.0, 1.0, 51)
    saved = np.random.get_state()
    np.random.seed(seed)
    try:
        point, interval = rly.get_interval_estimates(data, lambda s: np.array([metrics.aggregate_iqm(s)]), reps=reps)
        profiles, cis = rly.create_performance_profile(data, taus, reps=reps)
    finally:
        np.random.set_state(saved)
    rows = [{"arm": a, "tasks": tasks, "iqm": float(point[a][0]), "low": float(interval[a][0][0]),
             "high": float(interval[a][1][0])} for a in arms]
    return rows, {a: (taus, np.asarray(profiles[a]), np.asarray(cis[a][0]), np.asarray(cis[a][1])) for a in arms}


# ---------------------------------------------------------------------------------------------------
# Figures


def _series(c: plots.Curves, name: str, reps: int, max_points: int = 100):
    values = c.metrics.get(name)
    if values is None or not np.isfinite(values).any():
        return None
    idx = np.unique(np.linspace(0, len(c.updates) - 1, min(max_points, len(c.updates))).round().astype(int))
    point, low, high, n = stats.interval_curve(values[:, idx], "iqm", reps)
    return c.env_steps[idx], point, low, high, n


def returns_figure(tasks: list[TaskData], path: pathlib.Path, arms: Sequence[str] = MAIN_ARMS, reps: int = 500):
    """Average return (top) and average discounted return (bottom) vs env steps, a column per task; IQM over seeds
    with 95% bands. Writes path (.png) and the numbers plotted (.csv)."""
    from matplotlib.figure import Figure

    n = max(1, len(tasks))
    fig = Figure(figsize=(4.2 * n, 6.4))
    axes = fig.subplots(2, n, squeeze=False)
    rows = []
    for j, task in enumerate(tasks):
        for i, (name, ylabel) in enumerate(((RETURN, "average return"), (DISC, "average discounted return"))):
            ax = axes[i, j]
            for arm in arms:
                c = task.curves.get(arm)
                s = _series(c, name, reps) if c is not None else None
                if s is None:
                    continue
                x, point, low, high, k = s
                ax.plot(x, point, color=COLORS.get(arm), label=LABELS.get(arm, arm), lw=1.4)
                ax.fill_between(x, low, high, color=COLORS.get(arm), alpha=0.18, lw=0)
                rows += [{"task": task.name, "metric": name, "arm": arm, "env_steps": float(a), "iqm": float(b),
                          "ci_low": float(lo), "ci_high": float(hi), "n_seeds": int(m)}
                         for a, b, lo, hi, m in zip(x, point, low, high, k)]
            ax.set_xlabel("environment steps")
            ax.set_ylabel(ylabel)
            if i == 0:
                ax.set_title(task.name + ("" if task.complete else f" (cut at {task.budget:,.0f})"))
            ax.grid(alpha=0.3)
    found = {}  # every arm drawn in any column (the first task may lack some), in the order of `arms`
    for ax in axes[0]:
        for handle, label in zip(*ax.get_legend_handles_labels()):
            found.setdefault(label, handle)
    labels = [LABELS.get(arm, arm) for arm in arms if LABELS.get(arm, arm) in found]
    handles = [found[label] for label in labels]
    ncol = max(1, min(len(labels), 2 * n))  # two labels per task column: the legend never outgrows the figure
    rows_legend = -(-len(labels) // ncol) if labels else 0
    if handles:
        fig.legend(handles, labels, loc="upper center", ncol=ncol, frameon=False, fontsize=8)
    fig.tight_layout(rect=(0, 0, 1, 1 - 0.035 * rows_legend - 0.01))
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    _csv(path.with_suffix(".csv"), rows)
    return path


def profiles_figure(profiles: dict, path: pathlib.Path):
    from matplotlib.figure import Figure

    fig = Figure(figsize=(5.5, 4))
    ax = fig.subplots()
    rows = []
    for arm, (taus, prof, low, high) in profiles.items():
        ax.plot(taus, prof, color=COLORS.get(arm), label=LABELS.get(arm, arm), lw=1.4)
        ax.fill_between(taus, low, high, color=COLORS.get(arm), alpha=0.18, lw=0)
        rows += [{"arm": arm, "tau": float(t), "fraction": float(p), "ci_low": float(lo), "ci_high": float(hi)}
                 for t, p, lo, hi in zip(taus, prof, low, high)]
    ax.set_xlabel("normalised final return tau (per task: min-max over all seeds and arms)")
    ax.set_ylabel("fraction of runs with score > tau")
    ax.grid(alpha=0.3)
    ax.legend(frameon=False, fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    _csv(path.with_suffix(".csv"), rows)
    return path


def _csv(path: pathlib.Path, rows: list[dict]) -> None:
    with path.open("w", newline="") as f:
        if rows:
            writer = csv.DictWriter(f, fieldnames=list(rows[0]))
            writer.writeheader()
            writer.writerows(rows)


# ---------------------------------------------------------------------------------------------------
# Kept data and RESULTS.md


def keep_run(run: Run, data: pathlib.Path) -> pathlib.Path | None:
    """data/<unit>/<part>/ (or data/<task>/<name>/): run.json, machine.json, phase.jsonl, eval.jsonl, the unit's
    unit.json and KEEP's columns of metrics.jsonl (compressed: `io.write_packed`). None when the run is already
    under data/."""
    if data.resolve() in run.path.resolve().parents:
        return None
    unit = run.unit.get("unit") or run.task
    target = data / unit / run.path.name
    target.mkdir(parents=True, exist_ok=True)
    text = "".join(json.dumps({k: row[k] for k in KEEP if k in row}) + "\n"
                   for row in io.read_jsonl(run.path / "metrics.jsonl"))
    io.write_packed(target / "metrics.jsonl", text.encode())
    for name in ("run.json", "machine.json", "phase.jsonl", "eval.jsonl"):
        if (run.path / name).exists():
            shutil.copy(run.path / name, target / name)
    if run.unit:
        (data / unit / "unit.json").write_text(json.dumps(run.unit, indent=1))
    return target


def units_table(tasks: list[TaskData]) -> str:
    head = ("task", "unit / part", "command", "device", "env steps per run asked", "reached", "wall-clock",
            "training env steps/s")
    lines = []
    for t in tasks:
        for run in t.runs:
            name = f"{run.unit.get('unit', '-')} / {run.path.name}"
            m = run.machine
            # each arm against its own budget (an arm with a Mb-Mf phase plans whole PPO updates after the phase,
            # so the arms of one sweep may ask for slightly different env steps)
            reached = min((_reached(c) for c in run.curves.values()), default=0.0)
            asked = max(run.planned.values(), default=math.nan)
            low = min((v for v in run.planned.values() if v), default=asked)
            asked_text = f"{asked:,.0f}" if low == asked else f"{low:,.0f} to {asked:,.0f} (by arm)"
            cut = any(_reached(c) < (run.planned.get(k) or 0.0) for k, c in run.curves.items())
            wall = max((float(np.nanmax(c.metrics["wall_s"])) for c in run.curves.values() if "wall_s" in c.metrics
                        and np.isfinite(c.metrics["wall_s"]).any()), default=math.nan)
            steps = sum(len(c.seeds) * (_reached(c) - run.phase_steps.get(k, 0)) for k, c in run.curves.items())
            lines.append([t.name, name, f"`{run.info.get('command', '')}`", m.get("device", "unknown"),
                          asked_text, f"{reached:,.0f}" + (" (cut)" if cut else ""),
                          f"{m.get('wall_s', math.nan):.0f} s (training {wall:.0f} s)", _fmt(steps / wall, 3)])
    return _table(head, lines)


def _data_dates(tasks: list[TaskData]) -> str:
    """', units run D1 to D2' from the units' start dates (unit.json), so that the same data gives the same file on any
    day; '' when no unit says when it started."""
    days = sorted({r.unit["started"][:10] for t in tasks for r in t.runs if r.unit.get("started")})
    if not days:
        return ""
    return f", units run {days[0]}" + (f" to {days[-1]}" if days[-1] != days[0] else "")


def _head_scales(tasks: list[TaskData]) -> str:
    """A sentence saying with which policy head the runs started: run.json's `policy_head_scale` (lecun-uniform's
    last policy layer x this; a run.json from before the field ran with x1, Brax's head)."""
    scales = sorted({float(run.info.get("base_config", {}).get("policy_head_scale", 1.0))
                     for t in tasks for run in t.runs})
    if not scales:
        return ""
    said = " and ".join(f"x{s:g}" for s in scales)
    return (f" The policies started with lecun-uniform's policy head {said} (`--policy-head-scale`; x1 is Brax's "
            "head, cdjax's default x0.1 since 2026-11-26, `benchmarks/LEARNING.md`).")


def _sources(sources: Sequence[pathlib.Path] | None, out: pathlib.Path, keep: bool) -> str:
    """Where the header says the runs came from: the report's kept data, or the directories it was given."""
    own = (out / "data").resolve()
    if keep or sources is None or all(pathlib.Path(s).resolve() == own for s in sources):
        return "the kept data (`data/<unit>/<part>/`"
    return "the runs under " + ", ".join(f"`{s}`" for s in sources) + " (not copied here"


def paired_table(rows: list[dict], other: list[dict], other_name: str) -> list[str]:
    """Markdown lines setting each (task, arm) of `rows` (this report's summary) beside the same (task, arm) of
    `other` (another report's data/summary.json, e.g. the same units at another setting), seed by seed: the same seed
    ids side by side (a summary.json from before the ids were recorded pairs by position: the units run seeds 0-9 of
    base seed 0). An arm whose seeds differ is named, not paired; one only this side has is left out."""
    theirs = {(r["task"], r["arm"]): r for r in other}
    head = ("task", "arm", f"final return, {other_name}", "final return, here", "seeds higher here",
            f"per seed, {other_name}", "per seed, here")
    body, skipped = [], []

    def said(x):
        return "n/a" if x is None else f"{x:.0f}"

    for r in rows:
        o = theirs.get((r["task"], r["arm"]))
        if o is None:
            continue
        a, b = o.get("final_return_seeds", []), r.get("final_return_seeds", [])
        ids_a, ids_b = o.get("seed_ids"), r.get("seed_ids")
        if len(a) != len(b) or not a or (ids_a is not None and ids_b is not None and ids_a != ids_b):
            skipped.append(f"{r['task']} {LABELS.get(r['arm'], r['arm'])} (seeds {ids_a or len(a)} there, "
                           f"{ids_b or len(b)} here)")
            continue
        pairs = [(x, y) for x, y in zip(a, b) if x is not None and y is not None]
        body.append([r["task"], LABELS.get(r["arm"], r["arm"]), _cell(o["final_return"]), _cell(r["final_return"]),
                     f"{sum(y > x for x, y in pairs)} of {len(pairs)}", ", ".join(map(said, a)),
                     ", ".join(map(said, b))])
    if not body and not skipped:
        return [f"No task and arm of this data is in {other_name}.", ""]
    lines = [_table(head, body)] if body else []
    if skipped:
        lines.append("Not paired (their seeds differ): " + "; ".join(skipped) + ".")
    return lines + [""]


def write_results(tasks: list[TaskData], out: pathlib.Path = HERE, reps: int = 2000, keep: bool = False,
                  paired: pathlib.Path | None = None, sources: Sequence[pathlib.Path] | None = None) -> pathlib.Path:
    """Figures, tables, summary.json and RESULTS.md into `out` (and, with keep, the runs' data into out/data/);
    with `paired` (a directory holding another report's summary.json), a section setting this data's final returns
    beside that data's, seed by seed (`paired_table`). `sources`: the directories the runs were found in, named in the
    header when they are not out/data (the report's own kept data)."""
    out.mkdir(parents=True, exist_ok=True)
    if keep:
        for t in tasks:
            for run in t.runs:
                keep_run(run, out / "data")
    rows = [r for t in tasks for r in arm_rows(t, reps)]
    figures = out / "figures"
    lines = [
        "# Observation-space experiment, powered: Mb-Mf vs Mb-Mf + consistency (Sodhani et al., 2019, section 5.1)",
        "",
        f"Generated by `python -m experiments.paper_obs_space report` from {_sources(sources, out, keep)}"
        f"{_data_dates(tasks)}). The plan (units, budgets, commands): `PLAN.md`. Settings: the `paper-<task>` "
        f"presets in `cdjax/agents/obs/presets.py`.{_head_scales(tasks)}",
        "",
    ]
    missing = [t for t in TASKS if t not in {x.name for x in tasks}]
    if not tasks:
        lines += ["No unit has run yet: see `PLAN.md` for the units and the commands.", ""]
    analysis = out / "analysis.md"
    if analysis.exists() and tasks:
        lines += ["## Reading the results", "", analysis.read_text().strip(), ""]
    if tasks:
        lines += ["## Budgets", ""]
        for t in tasks:
            state = ("every arm reached it" if t.complete else
                     f"**not every arm reached it**: compared at {t.budget:,.0f} env steps, the most all arms reached")
            arms = ", ".join(LABELS.get(a, a) for a in _arm_order(t.curves))
            plan = TASK_BUDGETS.get(t.name)
            differs = f" (PLAN.md's budget: {plan.steps:,})" if plan is not None and plan.steps != t.stated else ""
            lines.append(f"- {t.name}: {t.stated:,.0f} env steps per run asked{differs} (the Mb-Mf phase's included); "
                         f"{state}. Arms: {arms}.")
            if t.pooled:
                lines.append("  Pooled: " + "; ".join(
                    f"{LABELS.get(a, a)} holds the seeds of runs of base seeds {', '.join(map(str, b))} "
                    f"({len(t.curves[a].seeds)} seeds)" for a, b in t.pooled.items()) + ".")
            if t.dropped:
                lines.append("  Left out (an arm found again on the same seeds or at another budget; the first "
                             "directory found is kept): " + "; ".join(t.dropped) + ".")
        if missing:
            lines.append(f"- not in this data: {', '.join(missing)}.")
        lines += ["", "## Verdicts per task (final return, 95% intervals)", ""]
        pairs = (("cd-k20-paper", "mbmf"), ("cd-k20", "mbmf"), ("cd-k20-paper", "cd-k5"), ("mbmf", "model-free"))
        cells = {t.name: [verdict([r for r in rows if r["task"] == t.name], a, b) for a, b in pairs] for t in tasks}
        if all(c == "n/a" for row in cells.values() for c in row):  # e.g. a check that re-ran some CD arms alone
            lines.append("None: no task here has both arms of " + "; ".join(
                f"{LABELS[a]} vs {LABELS[b]}" for a, b in pairs) + ".")
        else:
            lines.append(_table(("task",) + tuple(f"{LABELS[a]} vs {LABELS[b]}" for a, b in pairs),
                                ([name] + row for name, row in cells.items())))
        scores = final_scores(tasks)
        try:
            imp = improvement(scores, reps=reps)
            agg, profiles = aggregate(normalised(scores), reps=reps)
        except RuntimeError as err:
            imp, agg, profiles = None, [], {}  # said above; no second sentence below
            lines += ["", f"Across tasks: not computed ({err})."]
        lines += ["", "## Across tasks (rliable)", "",
                  "Probability of improvement P(X > Y) of the final return (per task over seeds, averaged over the "
                  "tasks that have both arms), with 95% stratified-bootstrap intervals:", ""]
        if imp:
            lines.append(_table(("X", "Y", "tasks", "P(X > Y)"), ([LABELS[p["x"]], LABELS[p["y"]], ", ".join(
                p["tasks"]), _cell((p["p"], p["low"], p["high"]), 3)] for p in imp)))
            lines += ["", "The same per task (its seeds only):", ""]
            lines.append(per_task_improvement(scores, reps))
        elif imp is not None:
            lines.append("None: no task here has both arms of any compared pair.")
        if agg:
            lines += ["", f"IQM of the normalised final return over {', '.join(agg[0]['tasks'])} (per task min-max over "
                      "every seed of every arm):", ""]
            lines.append(_table(("arm", "IQM [95% CI]"), ([LABELS[a["arm"]], _cell((a["iqm"], a["low"], a["high"]), 3)]
                                                          for a in agg)))
            profile_png = profiles_figure(profiles, figures / "profiles.png")
            lines += ["", f"![performance profiles]({profile_png.relative_to(out)})"]
        returns_png = returns_figure(tasks, figures / "returns.png", reps=min(reps, 500))
        lines += ["", "## Returns", "", returns_table(rows), "",
                  "Final: the mean of the last 10% of each seed's logged points; AUC: each seed's curve averaged over "
                  "env steps; IQM over seeds [95% stratified-bootstrap interval]. Training returns are those of "
                  "whole episodes of the stochastic policy (with staggered resets, each env's first, shortened episode "
                  "is not counted); the evaluation plays 10 fresh episodes with the mean action at the end.", "",
                  f"![returns]({returns_png.relative_to(out)})", "",
                  "## The Mb-Mf phase: does it hand PPO a better start?", "",
                  "Rewards per step inside the phase (random actions, the MPC on the learned model, the distilled "
                  "policy in the DAgger rounds) and the MPC labels' noise (mean absolute difference per action "
                  "dimension, on the distilled policy's states; IQM over seeds):", "",
                  phase_table(tasks, reps), "",
                  "The start PPO gets: reward per step of the distilled policy and of an untrained one (what the "
                  "model-free arm starts from), sampling as PPO's first rollout does and with the mean action, from "
                  "the same reset states (the phase's handover checks), and the first PPO rollout of each arm:", "",
                  start_table(tasks, rows, reps), "",
                  "## Model and consistency diagnostics (end of training)", "",
                  "Open-loop MSE on the arm's own states: its model imagining k and 50 steps from the recent real "
                  "states of 8 of its envs, in its own normalisation; on the yardstick: the same model on the task's "
                  "fixed held-out trajectories (`yardstick/<task>.npz`), in the yardstick's units (the same for every "
                  "arm). Gradient ratios: the norm of alpha x l_cc's gradient over that of PPO's loss on the policy "
                  "and of the model NLL on the model.", "", diagnostics_table(rows), ""]
        sched = [t for t in tasks if t.name in SCHEDULE_TASKS and "cd-k20-paper-schedule" in t.curves]
        if sched:
            lines += ["## The consistency schedule: the presets' against the paper's", "",
                      "CD k=20 at cdjax's weights with l_cc in the first epoch only (the presets) against every "
                      "minibatch of every epoch (the paper), at equal env steps:", ""]
            lines.append(_table(("task", "schedule", "seeds", "final return", "AUC return", "yardstick MSE at 50", "l_cc"),
                                ([t.name, LABELS[a], str(r["seeds"]), _cell(r["final_return"]), _cell(r["auc_return"]),
                                  _cell(r["model/yardstick_mse_50"], 3), _cell(r["loss/consistency"], 3)]
                                 for t in sched for a in ("cd-k20", "cd-k20-paper-schedule")
                                 for r in rows if r["task"] == t.name and r["arm"] == a)))
            lines += ["", "Per task, the paper's schedule against the presets' (final return: verdict from the IQMs' "
                      "intervals; rliable's probability of improvement over seeds):", ""]
            lines.append(_table(("task", "final return", "P(paper's schedule > presets')"),
                                ([t.name, verdict([r for r in rows if r["task"] == t.name], "cd-k20-paper-schedule",
                                                  "cd-k20"), schedule_improvement([t], reps)] for t in sched)))
            if len(sched) > 1:
                lines.append(f"| {', '.join(t.name for t in sched)} (across) | | "
                             f"{schedule_improvement(sched, reps)} |")
            lines.append("")
        start = [t for t in tasks if any(a in t.curves for a in HANDOVER_ABLATION)]
        if start:
            lines += ["## Why the Mb-Mf start learns slower: the hand-over ablated", "",
                      "Mb-Mf hands PPO a distilled policy, a value fitted to the DAgger returns, the model and the "
                      "observation normalisation. The ablations leave out the value fit, or both the value fit and the "
                      "distilled policy (PPO then starts from an untrained policy, as model-free does, with the "
                      "phase's model and normalisation); the phase runs and costs the same:", ""]
            lines.append(_table(("task", "arm", "seeds", "first PPO rollout (reward per step)", "final return",
                                 "AUC return", "eval return (mean action)", "policy std at the end",
                                 "P(arm > Mb-Mf)", "P(arm > model-free)"),
                                ([t.name, LABELS[a], str(r["seeds"]), _cell(r["start_reward"], 3),
                                  _cell(r["final_return"]), _cell(r["auc_return"]), _cell(r["eval_return"]),
                                  _cell(r["policy/std"], 3)] + _improvement_cells(t, a, ("mbmf", "model-free"), reps)
                                 for t in start for a in START_ARMS
                                 for r in rows if r["task"] == t.name and r["arm"] == a)))
            lines.append("")
        if paired is not None:
            other = json.loads((paired / "summary.json").read_text())
            lines += [f"## Seed by seed against `{paired}`", "",
                      "Final return (the mean of each seed's last 10% of logged training episodes), IQM over seeds "
                      "[95% interval], each side as its own report gives it; then each seed's value, in the order of "
                      "the seed ids, the same ids on both sides.", ""]
            lines += paired_table(rows, other, f"`{paired}`")
        lines += ["## Units: commands, devices, wall-clock", "", units_table(tasks), ""]
    (out / "data").mkdir(parents=True, exist_ok=True)
    (out / "data" / "summary.json").write_text(json.dumps(rows, indent=1, default=float))
    path = out / "RESULTS.md"
    path.write_text("\n".join(lines) + "\n")
    return path
