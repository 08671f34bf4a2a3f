"""The pixel experiment's table and figures from the directories of experiments/pixel/device.sh.

    python -m experiments.pixel.report OUT                       # OUT/report.md, OUT/report.csv, OUT/figures/*.png
    python -m experiments.pixel.report --strips RUN_DIR STRIPS   # PNG strips of seed 0 of each arm of a pixel sweep

Per task (OUT/TASK/pixel), arm and hyper-parameter label (the presets' ltq-cd runs alpha 100 with cc_policy 0 and 1), each seed's score is its mean over the last WINDOW logged updates up to
the last update every arm reached (the paper: "averaged over the last 50 batches of training"); the table
gives the IQM over seeds with a 95% bootstrap interval (cdjax.stats.iqm_interval) of
  heldout/loglik_k   open-loop log-likelihood of held-out expert frames over the first k predicted steps,
                     nats per frame (64x64x3 Gaussian densities of pixels in [0, 1]; higher is better)
  heldout/loglik_50  the same over all eval_horizon (50) predicted steps
  heldout/imitation  mean squared error of the policy's actions on held-out sequences (lower is better)
  loss/imitation     the same on the training batches
  eval/return        the imitation policy's return acting from pixels (latest evaluation, deterministic)
and, per task, the expert's evaluation return, the dataset size and generation time (cost.json) and the
training throughput (frames/s over all runs of both arms).
"""

from __future__ import annotations

import argparse
import json
import math
import pathlib

import numpy as np

from cdjax import io
from cdjax.stats import iqm_interval

WINDOW = 50
SCORES = (("heldout/loglik_k", "held-out log-lik at k (nats/frame)"),
          ("heldout/loglik_50", "held-out log-lik at 50 (nats/frame)"),
          ("heldout/imitation", "held-out imitation MSE"),
          ("loss/imitation", "training imitation MSE"))


def seed_scores(rows: list[dict], metric: str, last: int, window: int = WINDOW) -> dict[tuple, float]:
    """{(arm, hp, seed): mean of `metric` over updates in (last - window, last]}."""
    groups: dict[tuple, list[float]] = {}
    for r in rows:
        if last - window < r["update"] <= last and r.get(metric) is not None:
            groups.setdefault((r["arm"], r["hp"], r["seed"]), []).append(float(r[metric]))
    return {k: float(np.mean(v)) for k, v in groups.items()}


def common_last_update(rows: list[dict]) -> int:
    last: dict[str, int] = {}
    for r in rows:
        last[r["arm"]] = max(last.get(r["arm"], 0), r["update"])
    return min(last.values()) if last else 0


def throughput(rows: list[dict], frames_per_update: int) -> float:
    """Training frames per second over all runs of all arms (the sweep's training wall clock)."""
    if not rows:
        return math.nan
    updates: dict[tuple, int] = {}  # each run's last logged update (the logs may be thinned: experiments.thin_logs)
    for r in rows:
        run = (r["arm"], r["hp"], r["seed"])
        updates[run] = max(updates.get(run, 0), r["update"])
    frames = sum(updates.values()) * frames_per_update
    wall = max(r["wall_s"] for r in rows)
    return frames / wall if wall > 0 else math.nan


def _fmt(est: float, low: float, high: float) -> str:
    if not math.isfinite(est):
        return "n/a"
    scale = max(abs(est), 1e-12)
    digits = 1 if scale >= 100 else 3 if scale >= 0.1 else 4
    interval = f" [{low:.{digits}f}, {high:.{digits}f}]" if math.isfinite(low) else ""
    return f"{est:.{digits}f}{interval}"


def task_report(task_dir: pathlib.Path, reps: int = 2000) -> tuple[list[dict], dict]:
    run_dir = task_dir / "pixel"
    rows = io.read_jsonl(run_dir / "metrics.jsonl")
    run = json.loads((run_dir / "run.json").read_text()) if (run_dir / "run.json").exists() else {}
    last = common_last_update(rows)
    table = []
    groups = sorted({(r["arm"], r["hp"]) for r in rows})
    evals = io.read_jsonl(run_dir / "eval.jsonl") if (run_dir / "eval.jsonl").exists() else []
    for arm, hp in groups:
        line = {"task": task_dir.name, "arm": arm if hp == "default" else f"{arm} {hp}", "update": last}
        for metric, _ in SCORES:
            scores = [v for (a, h, _), v in seed_scores(rows, metric, last).items() if (a, h) == (arm, hp)]
            line[metric] = iqm_interval(scores, reps=reps)
        mine = [e for e in evals if e["arm"] == arm and e["hp"] == hp and e["deterministic"]]
        newest = max((e["update"] for e in mine), default=None)
        line["eval/return"] = iqm_interval([e["eval/return"] for e in mine if e["update"] == newest], reps=reps)
        table.append(line)
    info = {"task": task_dir.name, "last_update": last, "seeds": run.get("seeds")}
    config = next((a["config"] for a in run.get("arms", [])), {})
    if config:
        info["frames_per_s"] = throughput(rows, config["batch_size"] * config["seq_len"])
        info["horizon"] = config["horizon"]
    expert = task_dir / "expert.msgpack"
    if expert.exists():
        from cdjax.agents.pixel.expert import load_expert

        info["expert_return"] = load_expert(expert).eval_return
    if (task_dir / "cost.json").exists():
        info["cost"] = json.loads((task_dir / "cost.json").read_text())
    return table, info


def markdown(tables: list[list[dict]], infos: list[dict]) -> str:
    head = "| task | arm | update | " + " | ".join(t for _, t in SCORES) + " | eval return (from pixels) |"
    lines = ["IQM over seeds [95% bootstrap interval]; each seed averaged over its last "
             f"{WINDOW} updates up to the update both arms reached.", "", head,
             "|" + "---|" * (len(SCORES) + 4)]
    for table in tables:
        for r in table:
            cells = [_fmt(*r[m][:3]) for m, _ in SCORES] + [_fmt(*r["eval/return"][:3])]
            n = r[SCORES[0][0]][3]
            lines.append(f"| {r['task']} | {r['arm']} (n={n}) | {r['update']} | " + " | ".join(cells) + " |")
    lines += ["", "| task | k | expert return | dataset (all runs) | generated once (compile+run) | "
                  "rendered on the fly per update / update | training frames/s |", "|---|---|---|---|---|---|---|"]
    for info in infos:
        cost = info.get("cost", {})
        data = f"{cost['data_bytes_all_runs'] / 2**20:.0f} MiB" if cost else "n/a"
        once = f"{cost['once_compile_and_run_s']:.1f} s" if cost else "n/a"
        fly = f"{cost['fly_per_update_s'] * 1e3:.1f} ms / {cost['update_s'] * 1e3:.1f} ms" if cost else "n/a"
        lines.append(f"| {info['task']} | {info.get('horizon', '?')} | {info.get('expert_return', math.nan):.1f} | "
                     f"{data} | {once} | {fly} | {info.get('frames_per_s', math.nan):,.0f} |")
    return "\n".join(lines) + "\n"


def figures(out: pathlib.Path, tables: list[list[dict]]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    (out / "figures").mkdir(parents=True, exist_ok=True)
    for metric, title in SCORES[:3]:
        fig, ax = plt.subplots(figsize=(6, 3.2))
        labels, x = [], 0
        for table in tables:
            for r in table:
                est, low, high, _ = r[metric]
                color = "tab:orange" if r["arm"].startswith("ltq-cd") else "tab:blue"
                ax.bar(x, est, color=color)
                if math.isfinite(low):
                    ax.errorbar(x, est, yerr=[[est - low], [high - est]], color="k", capsize=3)
                labels.append(f"{r['task']}\n{r['arm']}")
                x += 1
        ax.set_xticks(range(len(labels)), labels, fontsize=7)
        ax.set_title(title)
        fig.tight_layout()
        fig.savefig(out / "figures" / (metric.replace("/", "_") + ".png"), dpi=120)
        plt.close(fig)


def write_strips(run_dir: str, dest: str, sequences: int = 3) -> list[pathlib.Path]:
    import jax

    from cdjax.agents.pixel.strips import write_strips as strips_of
    from cdjax.runner import restore_arms

    _, arms = restore_arms(run_dir)
    paths = []
    for arm in arms:
        labels = arm.plan.labels
        num_seeds = arm.num_runs // len(labels)  # runs are hp-major: run i * num_seeds + s
        for i, label in enumerate(labels):
            one = jax.tree.map(lambda x, r=i * num_seeds: x[r], arm.state)  # seed 0 of this hyper-parameter set
            name = arm.name if len(labels) == 1 else f"{arm.name}-{label.replace('=', '').replace(',', '-')}"
            paths.append(strips_of(arm.trainer.inner, one.params, one.heldout, jax.random.key(0),
                                   pathlib.Path(dest) / f"{name}.png", sequences=sequences))
    return paths


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("out", nargs="?")
    parser.add_argument("--strips", nargs=2, metavar=("RUN_DIR", "DEST"))
    parser.add_argument("--bootstrap-reps", type=int, default=2000)
    args = parser.parse_args(argv)
    if args.strips:
        for path in write_strips(*args.strips):
            print(f"wrote {path}")
        return
    out = pathlib.Path(args.out)
    tasks = [d for d in sorted(out.iterdir()) if io.jsonl_exists(d / "pixel" / "metrics.jsonl")]
    results = [task_report(d, args.bootstrap_reps) for d in tasks]
    tables, infos = [r[0] for r in results], [r[1] for r in results]
    text = markdown(tables, infos)
    (out / "report.md").write_text(text)
    figures(out, tables)
    print(text)


if __name__ == "__main__":
    main()
