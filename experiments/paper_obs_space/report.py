"""Figures and RESULTS.md of the observation-space experiments, from the run directories of `train`.

Arms are compared at the same environment-step budget: when a run was stopped early (e.g. by a time
limit), every arm of that task is cut at the largest env-step count that all of its arms reached, and the
table says so. Statistics are cdjax.stats' (through cdjax.plots' curves): IQM over seeds with 95% stratified-bootstrap intervals
(rliable), final = mean of the last 10% of each seed's logged points, AUC = env-step weighted mean of
each seed's curve.
"""

from __future__ import annotations

import csv
import dataclasses
import datetime
import gzip
import json
import math
import pathlib
import shutil
from typing import Sequence

import numpy as np

from cdjax import io, plots, stats
from experiments.paper_obs_space import ABLATION_TASKS, ARMS, TASKS

HERE = pathlib.Path(__file__).resolve().parent
RETURN, DISC = plots.RETURN, plots.DISC_RETURN
# Diagnostics of the model and the consistency term, reported at the end of training (IQM of final values).
DIAGNOSTICS = (
    ("model/openloop_mse_k", "open-loop MSE at k"),
    ("model/openloop_mse_50", "open-loop MSE at 50"),
    ("loss/consistency", "l_cc"),
    ("encoder/spread_real", "encoder spread (real)"),
    ("encoder/spread_imagined", "encoder spread (imagined)"),
    ("consistency/masked_fraction", "masked windows"),
)
# Per-seed, per-update columns kept in the committed data (metrics.jsonl itself is large).
KEEP = ("arm", "hp", "seed", "update", "env_steps", "wall_s", RETURN, DISC, "episode/count", "env/invalid_fraction",
        "opt/skipped_updates") + tuple(name for name, _ in DIAGNOSTICS)
LABELS = {"model-free": "model-free", "mbmf": "Mb-Mf", "cd-k5": "CD k=5", "cd-k20": "CD k=20"}
COLORS = {"model-free": "#7f7f7f", "mbmf": "#1f77b4", "cd-k5": "#ff7f0e", "cd-k20": "#d62728"}


@dataclasses.dataclass
class Task:
    name: str
    run_dir: pathlib.Path
    info: dict  # run.json
    machine: dict  # machine.json written by `train` (device, versions), {} if absent
    curves: dict[str, plots.Curves]  # arm name -> curves (cut at the common budget)
    evals: dict  # plots.load_eval
    budget: float  # env steps every arm reached (the comparison budget)
    planned: float  # env steps per run asked for
    complete: bool  # every arm reached its planned budget


def _cut(c: plots.Curves, budget: float) -> plots.Curves:
    """The curves of an arm up to `budget` env steps (points after it dropped)."""
    keep = np.isfinite(c.env_steps) & (c.env_steps <= budget)
    return dataclasses.replace(c, updates=c.updates[keep], env_steps=c.env_steps[keep], present=c.present[:, keep],
                               metrics={k: v[:, keep] for k, v in c.metrics.items()})


def load_task(run_dir: pathlib.Path, name: str) -> Task | None:
    """A task's run directory (from `train`) or its kept data (data/<task>/ of a RESULTS.md); None if absent."""
    if not (run_dir / "run.json").exists():
        return None
    if not io.jsonl_exists(run_dir / "metrics.jsonl"):  # a run directory, or kept data (metrics.jsonl.gz)
        return None
    info = io.RunDir(run_dir).read()
    machine_path = run_dir / "machine.json"
    machine = json.loads(machine_path.read_text()) if machine_path.exists() else {}
    curves = {arm: c for (arm, _), c in plots.load_metrics(run_dir).items()}
    planned = {a["name"]: a.get("total_env_steps", info.get("total_env_steps")) for a in info["arms"]}
    reached = {}
    for arm, c in curves.items():
        everywhere = c.present.all(axis=0)  # points every seed logged
        reached[arm] = float(np.nanmax(c.env_steps[everywhere])) if everywhere.any() else 0.0
    complete = all(reached.get(arm, 0.0) >= planned[arm] for arm in planned)
    budget = min(reached.values()) if reached else 0.0
    if not complete:  # compare every arm at the env steps all of them reached
        curves = {arm: _cut(c, budget + info.get("env_steps_per_update", 0) / 2) for arm, c in curves.items()}
    return Task(name, run_dir, info, machine, curves, plots.load_eval(run_dir) if complete else {}, budget,
                float(info.get("requested_env_steps", math.nan)), complete)


def load_tasks(runs: Sequence[pathlib.Path], tasks: Sequence[str] = TASKS) -> list[Task]:
    """Per task, the first of `runs` that holds it (runs/<task> or data/<task>)."""
    out = []
    for name in tasks:
        for root in runs:
            task = load_task(pathlib.Path(root) / name, name)
            if task is not None:
                out.append(task)
                break
    return out


# ---------------------------------------------------------------------------------------------------
# Tables


def _cell(iqm: float, lo: float, hi: float, digits: int = 4) -> str:
    if not np.isfinite(iqm):
        return "n/a"
    fmt = lambda x: f"{x:.{digits}g}"  # noqa: E731
    return fmt(iqm) if not np.isfinite(lo) else f"{fmt(iqm)} [{fmt(lo)}, {fmt(hi)}]"


def arm_rows(task: Task, reps: int = 2000) -> list[dict]:
    """One row per arm: returns (final, AUC; IQM + CI), evaluation, diagnostics, budgets."""
    rows = []
    arms_info = {a["name"]: a for a in task.info["arms"]}
    for arm in [a for a in ARMS if a in task.curves] + [a for a in task.curves if a not in ARMS]:
        c = task.curves[arm]
        row = {"task": task.name, "arm": arm, "seeds": len(c.seeds),
               "env_steps": float(np.nanmax(c.env_steps)) if c.env_steps.size else math.nan,
               "phase_env_steps": arms_info.get(arm, {}).get("phase_env_steps", 0),
               "ppo_updates": int(c.updates.max()) if c.updates.size else 0}
        for stat, fn in (("final", plots.per_seed_final), ("auc", plots.per_seed_auc)):
            for target, name in (("return", RETURN), ("disc_return", DISC)):
                values = fn(c, name)
                row[f"{stat}_{target}"] = stats.iqm_interval(values, reps)[:3]
                row[f"{stat}_{target}_seeds"] = [None if not np.isfinite(v) else round(float(v), 4) for v in values]
        count = c.metrics.get("episode/count")
        row["episodes"] = float(np.nanmean(np.nansum(np.where(c.present, count, 0.0), axis=1))) \
            if count is not None else math.nan
        ev = next((v for (a, _, det), v in task.evals.items() if a == arm and det), None)
        row["eval_return"] = stats.iqm_interval(ev["return"], reps)[:3] if ev else (math.nan,) * 3
        for name, _ in DIAGNOSTICS:
            row[name] = stats.iqm_interval(plots.per_seed_final(c, name), reps)[:3] if name in c.metrics \
                else (math.nan,) * 3
        rows.append(row)
    return rows


def returns_table(rows: list[dict]) -> str:
    head = ("| task | arm | seeds | env steps | of which Mb-Mf phase | PPO updates | episodes ended / seed | "
            "final return | AUC return | final disc. return | AUC disc. return | eval return (mean action) |")
    lines = [head, "|" + "|".join(["---"] * (head.count("|") - 1)) + "|"]
    for r in rows:
        lines.append(f"| {r['task']} | {LABELS.get(r['arm'], r['arm'])} | {r['seeds']} | {r['env_steps']:,.0f} | "
                     f"{r['phase_env_steps']:,} | {r['ppo_updates']} | {r['episodes']:,.0f} | {_cell(*r['final_return'])} | "
                     f"{_cell(*r['auc_return'])} | {_cell(*r['final_disc_return'])} | {_cell(*r['auc_disc_return'])} | "
                     f"{_cell(*r['eval_return'])} |")
    return "\n".join(lines)


def diagnostics_table(rows: list[dict]) -> str:
    head = "| task | arm | " + " | ".join(label for _, label in DIAGNOSTICS) + " |"
    lines = [head, "|" + "|".join(["---"] * (head.count("|") - 1)) + "|"]
    for r in rows:
        if r["arm"] == "model-free":
            continue
        cells = " | ".join(_cell(*r[name], digits=3) for name, _ in DIAGNOSTICS)
        lines.append(f"| {r['task']} | {LABELS.get(r['arm'], r['arm'])} | {cells} |")
    return "\n".join(lines)


def verdict(rows: list[dict], a: str, b: str, key: str = "final_return") -> str:
    """'a > b', 'a < b' (95% intervals disjoint) or 'no clear difference' (they overlap), per task."""
    by = {r["arm"]: r for r in rows}
    if a not in by or b not in by:
        return "n/a"
    (ia, la, ha), (ib, lb, hb) = by[a][key], by[b][key]
    if not (np.isfinite(ia) and np.isfinite(ib)):
        return "n/a"
    if np.isfinite(la) and np.isfinite(hb) and la > hb:
        return f"{LABELS[a]} > {LABELS[b]} (IQM {ia:.4g} vs {ib:.4g}, intervals disjoint)"
    if np.isfinite(lb) and np.isfinite(ha) and lb > ha:
        return f"{LABELS[a]} < {LABELS[b]} (IQM {ia:.4g} vs {ib:.4g}, intervals disjoint)"
    return f"no clear difference (IQM {ia:.4g} vs {ib:.4g}, intervals overlap)"


# ---------------------------------------------------------------------------------------------------
# Figures


def _series(c: plots.Curves, name: str, reps: int, max_points: int = 120):
    values = c.metrics.get(name)
    if values is None or not np.isfinite(values).any():
        return None
    idx = np.unique(np.linspace(0, len(c.updates) - 1, min(max_points, len(c.updates))).round().astype(int))
    point, low, high, n = stats.interval_curve(values[:, idx], "iqm", reps)
    return c.env_steps[idx], point, low, high, n


def figure(tasks: list[Task], arms: Sequence[str], path: pathlib.Path, reps: int = 1000) -> tuple[pathlib.Path, pathlib.Path]:
    """Average return (top) and average discounted return (bottom) vs env steps, one column per task.

    Writes path (.png) and the plotted numbers next to it (.csv). Lines: IQM over seeds; bands: 95% CIs.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, max(1, len(tasks)), figsize=(4.2 * max(1, len(tasks)), 6.4), squeeze=False)
    rows = []
    for j, task in enumerate(tasks):
        for i, (name, ylabel) in enumerate(((RETURN, "average return"), (DISC, "average discounted return"))):
            ax = axes[i, j]
            for arm in arms:
                c = task.curves.get(arm)
                s = _series(c, name, reps) if c is not None else None
                if s is None:
                    continue
                x, point, low, high, n = s
                ax.plot(x, point, color=COLORS.get(arm), label=LABELS.get(arm, arm), lw=1.5)
                ax.fill_between(x, low, high, color=COLORS.get(arm), alpha=0.2, lw=0)
                rows += [{"task": task.name, "metric": name, "arm": arm, "env_steps": float(a), "iqm": float(b),
                          "ci_low": float(lo), "ci_high": float(hi), "n_seeds": int(k)}
                         for a, b, lo, hi, k in zip(x, point, low, high, n)]
            ax.set_xlabel("environment steps")
            ax.set_ylabel(ylabel)
            if i == 0:
                ax.set_title(task.name + ("" if task.complete else f" (cut at {task.budget:,.0f} steps)"))
            ax.grid(alpha=0.3)
    handles, labels = axes[0, 0].get_legend_handles_labels()
    if handles:
        fig.legend(handles, labels, loc="upper center", ncol=len(labels), frameon=False)
    fig.tight_layout(rect=(0, 0, 1, 0.94))
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    data = path.with_suffix(".csv")
    with data.open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=["task", "metric", "arm", "env_steps", "iqm", "ci_low", "ci_high",
                                               "n_seeds"])
        writer.writeheader()
        writer.writerows(rows)
    return path, data


# ---------------------------------------------------------------------------------------------------
# RESULTS.md


def keep_data(task: Task, out: pathlib.Path) -> pathlib.Path:
    """data/<task>/: run.json, machine.json, phase.jsonl, eval.jsonl and selected columns of metrics.jsonl
    (gzipped): enough for `report --runs data` to rebuild the tables and figures without the run directory."""
    target = out / task.name
    if target.resolve() == task.run_dir.resolve():
        return target
    target.mkdir(parents=True, exist_ok=True)
    with gzip.open(target / "metrics.jsonl.gz", "wt") as f:
        for row in io.read_jsonl(task.run_dir / "metrics.jsonl"):
            f.write(json.dumps({k: row[k] for k in KEEP if k in row}) + "\n")
    for name in ("run.json", "machine.json", "phase.jsonl", "eval.jsonl"):
        if (task.run_dir / name).exists():
            shutil.copy(task.run_dir / name, target / name)
    return target


def settings(info: dict) -> str:
    """One line of the settings a run.json records."""
    c = info.get("base_config", {})
    hp = (info.get("arms") or [{}])[-1].get("hparams", [{}])[0]
    phase = info.get("phase") or {}
    text = (f"{info.get('seeds')} seeds x {c.get('num_envs')} envs, rollout {c.get('rollout_len')}, "
            f"{c.get('num_epochs')} epochs x {c.get('num_minibatches')} minibatches, policy {c.get('policy_hidden')}, "
            f"model {c.get('model_hidden')}, encoder {c.get('encoder')}, {c.get('cc_windows') or 'all'} windows "
            f"(unroll {c.get('cc_unroll')}), alpha {hp.get('alpha')}, gamma {hp.get('gamma')}, "
            f"reward scale {hp.get('reward_scale')}")
    if phase:
        text += (f"; Mb-Mf phase: {phase.get('num_envs')} envs, {phase.get('random_steps')} random steps, "
                 f"{phase.get('aggregation_iters')} x {phase.get('mpc_steps_per_iter')} MPC steps (horizon "
                 f"{phase.get('mpc_horizon')}, {phase.get('mpc_candidates')} candidates), {phase.get('distill_iters')} x "
                 f"{phase.get('distill_steps_per_iter')} DAgger steps")
    return text


def write_results(tasks: list[Task], out: pathlib.Path = HERE, reps: int = 2000) -> pathlib.Path:
    """Both figures, the tables, the data behind them and RESULTS.md into `out`."""
    figures = out / "figures"
    returns_png, _ = figure(tasks, ("mbmf", "cd-k20"), figures / "returns.png")
    ablation = [t for t in tasks if t.name in ABLATION_TASKS]
    ablation_png, _ = figure(ablation, ARMS, figures / "k_ablation.png") if ablation else (None, None)
    all_png, _ = figure(tasks, ARMS, figures / "all_arms.png")
    rows = [r for t in tasks for r in arm_rows(t, reps)]
    (out / "data").mkdir(parents=True, exist_ok=True)
    (out / "data" / "summary.json").write_text(json.dumps(rows, indent=1, default=float))
    for t in tasks:
        keep_data(t, out / "data")

    machines = sorted({json.dumps(t.machine.get("device", "unknown")) for t in tasks})
    lines = [
        "# Observation-space experiments: Mb-Mf vs Mb-Mf + consistency (Sodhani et al., 2019, section 5.1)",
        "",
        f"Generated {datetime.date.today().isoformat()} by `python -m experiments.paper_obs_space report`. "
        f"Device(s): {', '.join(json.loads(m) for m in machines)}.",
        "",
        "What ran (every setting is in `cdjax/agents/obs/presets.py`, presets `paper-<task>`; per task below): PPO with a "
        "Gaussian MLP policy; a Gaussian MLP model over the normalised change of state and the reward. Mb-Mf "
        "and CD first run the Mb-Mf phase (random data, model, random-shooting MPC aggregation, DAgger "
        "distillation into the policy, value fit; its env steps are counted in the budget), then PPO; CD adds "
        "alpha x l_cc (trainable GRU encoder) on random k-step windows. Seeds are vmapped; the arms of a task "
        "see the same seeds.",
        "",
        "Statistics: IQM over seeds with a 95% stratified-bootstrap interval (rliable). Final: mean of the last "
        "10% of each seed's logged points; AUC: each seed's curve averaged over env steps; eval: 10 episodes "
        "with the mean action at the end. Returns are those of the training episodes (stochastic policy).",
        "",
        "**Budgets are far below the paper's** (the paper trains for millions of TRPO steps): what one "
        "30-minute GPU session allows for four arms x 10 seeds per task. Read the results as early-training "
        "comparisons.",
        "",
        "Several tasks ran at once, one per GPU of a 2 x H200 host (each process saw one GPU); wall-clock "
        "times are per task.",
        "",
        "## Verdicts (final return, 95% intervals)",
        "",
        "| task | CD k=20 vs Mb-Mf | CD k=20 vs CD k=5 | Mb-Mf vs model-free |",
        "|---|---|---|---|",
    ]
    for t in tasks:
        r = [x for x in rows if x["task"] == t.name]
        lines.append(f"| {t.name} | {verdict(r, 'cd-k20', 'mbmf')} | {verdict(r, 'cd-k20', 'cd-k5')} | "
                     f"{verdict(r, 'mbmf', 'model-free')} |")
    analysis = out / "analysis.md"
    if analysis.exists():
        lines += ["", "## Reading the results", "", analysis.read_text().strip()]
    lines += ["", "## Returns", "", returns_table(rows), "",
              "## Model and consistency diagnostics (end of training)", "",
              "Open-loop MSE: normalised-state error of the model imagining k and 50 steps from real states under "
              "the real actions (8 envs per seed); k is the arm's own horizon (CD k=5: 5; Mb-Mf and CD k=20: 20), "
              "and each arm is measured on the states its own policy visits. Encoder spread: mean distance of the encodings from their "
              "mean (a collapsed encoder has spread ~0). Masked windows: fraction of consistency windows dropped "
              "because an episode ended inside them.", "", diagnostics_table(rows), "",
              "## Figures", "",
              f"- Average return and average discounted return, Mb-Mf vs CD k=20: `{returns_png.relative_to(out)}` "
              "(data: same name, .csv)",
              ]
    if ablation_png is not None:
        lines.append(f"- k ablation (model-free, Mb-Mf, CD k=5, CD k=20) on {', '.join(t.name for t in ablation)}: "
                     f"`{ablation_png.relative_to(out)}`")
    lines.append(f"- All arms on every task: `{all_png.relative_to(out)}`")
    lines += ["", f"![returns]({returns_png.relative_to(out)})", ""]
    if ablation_png is not None:
        lines += [f"![k ablation]({ablation_png.relative_to(out)})", ""]
    lines += ["## Runs and commands", ""]
    for t in tasks:
        m = t.machine
        state = "complete" if t.complete else f"stopped early: compared at {t.budget:,.0f} env steps (all arms cut there)"
        lines += [f"### {t.name}", "",
                  f"- command: `{t.info.get('command', '')}`",
                  f"- settings: {settings(t.info)}",
                  f"- budget asked: {t.planned:,.0f} env steps per run; {state}",
                  f"- device: {m.get('device', 'unknown')}; jax {m.get('jax', '?')}, brax {m.get('brax', '?')}, "
                  f"mujoco-mjx {m.get('mujoco_mjx', '?')}; {m.get('date', '')}; wall-clock {m.get('wall_s', math.nan):.0f} s",
                  f"- data: `data/{t.name}/` (run.json; metrics.jsonl.gz per seed and update; phase.jsonl, the Mb-Mf "
                  "phase's diagnostics per seed; eval.jsonl)", ""]
    missing = [name for name in TASKS if name not in {t.name for t in tasks}]
    if missing:
        lines += ["## Not run yet", "", f"{', '.join(missing)}: no run directory was found for these tasks.", ""]
    path = out / "RESULTS.md"
    path.write_text("\n".join(lines) + "\n")
    return path
