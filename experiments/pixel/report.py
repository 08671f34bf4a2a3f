"""The pixel experiment's table and figures from the directories of its units (experiments/pixel/units.py).

    python -m experiments.pixel.report OUT                       # OUT/report.md, OUT/figures/*.png
    python -m experiments.pixel.report --strips RUN_DIR STRIPS   # PNG strips of seed 0 of each arm of a pixel sweep
    python -m experiments.pixel.report --compact-strips STRIPS SMALL   # what results keep (1 sequence, 20 steps)

OUT holds one directory per sweep, each with its run directory in `pixel/`: either one per task holding every arm
(the earlier passes: OUT/halfcheetah/pixel) or one per unit of `python -m experiments.pixel`, each unit's
directory or its UNIT.tar.gz (experiments.launch collect) unpacked
(OUT/halfcheetah-ltq/pixel, OUT/halfcheetah-ltq-cd0/pixel, ...). The sweeps are grouped by the task they trained
(run.json's env) and their arms put side by side; a hyper-parameter that differs between sweeps of one arm joins
the arm's label (two units of ltq-cd with cc_policy 0 and 1 read as the one sweep of both would), and two sweeps
holding the same arm and label are refused.

Per task, arm and hyper-parameter label (the presets' ltq-cd runs alpha 100 with cc_policy 0 and 1), each seed's
score is its mean over the last WINDOW logged updates up to the last update every arm reached, in every sweep of
the task (the paper: "averaged over the last 50 batches of training"); the table gives the IQM over seeds with
a 95% bootstrap interval (cdjax.stats.iqm_interval) of
  heldout/loglik_k   open-loop log-likelihood of held-out expert frames over the first k predicted steps,
                     nats per frame (64x64x3 Gaussian densities of pixels in [0, 1]; higher is better)
  heldout/loglik_50  the same over all eval_horizon (50) predicted steps
  heldout/imitation  mean squared error of the policy's actions on held-out sequences (lower is better)
  loss/imitation     the same on the training batches
  eval/return        the imitation policy's return acting from pixels (latest evaluation, deterministic)
and, per task, the expert's evaluation return, the dataset size and generation time (cost.json, in the sweep's
directory or beside the expert its run.json names) and the training throughput (frames/s over all runs of each
sweep, its own wall clock; one figure per sweep where a task has several).
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
    """The last update every (arm, hyper-parameter label) reached: each one's last logged update, the least."""
    last: dict[tuple, int] = {}
    for r in rows:
        key = (r["arm"], r.get("hp", "default"))
        last[key] = max(last.get(key, 0), r["update"])
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


def _label_keys(label: str) -> list[str]:
    return [] if label == "default" else [part.split("=")[0] for part in label.split(",")]


def _task_of(unit_dir: pathlib.Path, run: dict) -> str:
    """The task a sweep trained: run.json's env, else the directory's name up to its first '-'."""
    return run.get("base_config", {}).get("env") or pathlib.Path(unit_dir).name.split("-")[0]


def units_of(out: pathlib.Path) -> dict[str, list[pathlib.Path]]:
    """{task: its sweeps' directories (each holding pixel/)}, tasks and directories sorted: every directory of
    `out` with a pixel/metrics.jsonl, grouped by the env its run.json names (else its name up to the first '-')."""
    tasks: dict[str, list[pathlib.Path]] = {}
    for d in sorted(out.iterdir()):
        if not io.jsonl_exists(d / "pixel" / "metrics.jsonl"):
            continue
        run = d / "pixel" / "run.json"
        tasks.setdefault(_task_of(d, json.loads(run.read_text()) if run.exists() else {}), []).append(d)
    return dict(sorted(tasks.items()))


def merge_units(unit_dirs) -> tuple[list[dict], list[dict], list[dict]]:
    """(metrics rows, evaluation rows, units) of one task's sweeps, their arms side by side.

    A hyper-parameter whose value differs between the sweeps' sets of one arm (run.json's hparams) is added to the
    rows' labels where a sweep left it out for having one value: ltq-cd "alpha=100.0" from a unit run with
    --cc-policy 0 becomes "alpha=100.0,cc_policy=0.0", the label the sweep of both values gives it. `units`: per
    sweep, its directory's name, its run.json and its last update per label. ValueError when two sweeps hold the
    same arm and label."""
    loaded = []
    for d in unit_dirs:
        run_dir = pathlib.Path(d) / "pixel"
        run = json.loads((run_dir / "run.json").read_text()) if (run_dir / "run.json").exists() else {}
        evals = io.read_jsonl(run_dir / "eval.jsonl") if io.jsonl_exists(run_dir / "eval.jsonl") else []
        loaded.append((pathlib.Path(d), run, list(io.read_jsonl(run_dir / "metrics.jsonl")), list(evals)))
    values: dict[str, dict[str, set]] = {}  # arm -> hyper-parameter -> the values its sets take, over all sweeps
    for _, run, _, _ in loaded:
        for arm in run.get("arms", []):
            for hp in arm.get("hparams", []):
                for k, v in hp.items():
                    values.setdefault(arm["name"], {}).setdefault(k, set()).add(float(v))
    rows, evals, units, owner = [], [], [], {}
    for d, run, unit_rows, unit_evals in loaded:
        relabel = {}
        for arm in run.get("arms", []):
            varying = [k for k, vs in values.get(arm["name"], {}).items() if len(vs) > 1]
            for label, hp in zip(arm.get("hp_labels", []), arm.get("hparams", [])):
                shown = _label_keys(label)
                extra = [f"{k}={float(hp[k])!r}" for k in varying if k not in shown]
                relabel[(arm["name"], label)] = ",".join(([] if label == "default" else [label]) + extra) or "default"
        relabelled = [{**r, "hp": relabel.get((r["arm"], r.get("hp", "default")), r.get("hp", "default"))}
                      for r in unit_rows]
        last: dict[str, int] = {}
        for r in relabelled:
            name = r["arm"] if r["hp"] == "default" else f"{r['arm']} {r['hp']}"
            last[name] = max(last.get(name, 0), r["update"])
            if owner.setdefault((r["arm"], r["hp"]), d.name) != d.name:
                raise ValueError(f"{owner[(r['arm'], r['hp'])]} and {d.name} both hold arm {name!r} of the same "
                                 "task; report them from separate directories.")
        rows += relabelled
        evals += [{**e, "hp": relabel.get((e["arm"], e.get("hp", "default")), e.get("hp", "default"))}
                  for e in unit_evals]
        units.append({"name": d.name, "run": run, "last": last, "rows": relabelled})
    return rows, evals, units


def _task_files(unit_dirs, units: list[dict], name: str) -> pathlib.Path | None:
    """`name` (expert.msgpack, cost.json) in a sweep's directory, else beside the expert its run.json names
    (relative to the working directory, else to the repository: the units train from the kept experts)."""
    places = [pathlib.Path(d) for d in unit_dirs]
    for unit in units:
        expert = unit["run"].get("base_config", {}).get("expert")
        if expert:
            parent = pathlib.Path(expert).parent
            places += [parent, pathlib.Path(__file__).resolve().parents[2] / parent]
    return next((p / name for p in places if (p / name).exists()), None)


def task_report(unit_dirs, reps: int = 2000, merged=None) -> tuple[list[dict], dict]:
    """The table's rows and the task's information from one directory holding every arm (OUT/TASK) or the
    directories of one task's units (OUT/TASK-ARM); `merged`: merge_units(unit_dirs) when already read."""
    unit_dirs = [unit_dirs] if isinstance(unit_dirs, (str, pathlib.Path)) else list(unit_dirs)
    rows, evals, units = merged or merge_units(unit_dirs)
    run = units[0]["run"] if units else {}
    config = next((a["config"] for u in units for a in u["run"].get("arms", [])), {})
    task = _task_of(unit_dirs[0], run)
    last = common_last_update(rows)
    table = []
    groups = sorted({(r["arm"], r["hp"]) for r in rows})
    for arm, hp in groups:
        line = {"task": task, "arm": arm if hp == "default" else f"{arm} {hp}", "update": last}
        for metric, _ in SCORES:
            scores = [v for (a, h, _), v in seed_scores(rows, metric, last).items() if (a, h) == (arm, hp)]
            line[metric] = iqm_interval(scores, reps=reps)
        mine = [e for e in evals if e["arm"] == arm and e["hp"] == hp and e["deterministic"]]
        newest = max((e["update"] for e in mine), default=None)
        line["eval/return"] = iqm_interval([e["eval/return"] for e in mine if e["update"] == newest], reps=reps)
        table.append(line)
    info = {"task": task, "last_update": last, "seeds": run.get("seeds"),
            "units": [{"name": u["name"], "last": u["last"]} for u in units]}
    if config:
        frames = config["batch_size"] * config["seq_len"]
        info["frames_per_s"] = {u["name"]: throughput(u["rows"], frames) for u in units}
        info["horizon"] = config["horizon"]
    expert = _task_files(unit_dirs, units, "expert.msgpack")
    if expert is not None:
        from cdjax.agents.experts import load_expert

        info["expert_return"] = load_expert(expert).eval_return
    cost = _task_files(unit_dirs, units, "cost.json")
    if cost is not None:
        info["cost"] = json.loads(cost.read_text())
    return table, info


def markdown(tables: list[list[dict]], infos: list[dict]) -> str:
    head = "| task | arm | update | " + " | ".join(t for _, t in SCORES) + " | eval return (from pixels) |"
    lines = ["IQM over seeds [95% bootstrap interval]; each seed averaged over its last "
             f"{WINDOW} updates up to the update every arm of its task reached."]
    for info in infos:
        if len(info.get("units", [])) > 1:
            reached = ", ".join(f"{u['name']} {min(u['last'].values(), default=0)}" for u in info["units"])
            lines.append(f"- {info['task']}: {len(info['units'])} separate sweeps, compared at update "
                         f"{info['last_update']}, the last all of them reached (last updates: {reached}).")
    lines += ["", head, "|" + "---|" * (len(SCORES) + 4)]
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
        rates = info.get("frames_per_s", {})
        speed = (f"{next(iter(rates.values())):,.0f}" if len(rates) == 1 else
                 "; ".join(f"{name} {v:,.0f}" for name, v in rates.items()) if rates else "n/a")
        lines.append(f"| {info['task']} | {info.get('horizon', '?')} | {info.get('expert_return', math.nan):.1f} | "
                     f"{data} | {once} | {fly} | {speed} |")
    return "\n".join(lines) + "\n"


def short_label(arm: str) -> str:
    """'ltq-cd alpha=100.0,cc_policy=0.0' -> 'ltq-cd\nalpha 100, cc_policy 0' (for the figures' axes)."""
    name, _, hp = arm.partition(" ")
    parts = [f"{k} {float(v):g}" for k, v in (item.split("=") for item in hp.split(",") if "=" in item)]
    return name + ("\n" + ", ".join(parts) if parts else "")


def figures(out: pathlib.Path, tables: list[list[dict]], curves: dict | None = None) -> None:
    """out/figures: per score, a panel per task (its own scale) with each arm's IQM and 95% interval; with
    `curves` ({task: {arm: (updates, {metric: [(iqm, low, high)]})}}), the held-out scores against updates."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    (out / "figures").mkdir(parents=True, exist_ok=True)
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for metric, title in SCORES[:3]:
        fig, axes = plt.subplots(1, len(tables), figsize=(3.2 * len(tables), 3.4), squeeze=False)
        for ax, table in zip(axes[0], tables):
            for x, r in enumerate(table):
                est, low, high, _ = r[metric]
                ax.bar(x, est, color=colors[x % len(colors)])
                if math.isfinite(low):
                    ax.errorbar(x, est, yerr=[[est - low], [high - est]], color="k", capsize=3)
            ax.set_xticks(range(len(table)), [short_label(r["arm"]) for r in table], fontsize=6)
            ax.set_title(f"{table[0]['task']} (update {table[0]['update']})" if table else "", fontsize=9)
        fig.suptitle(title, fontsize=10)
        fig.tight_layout()
        fig.savefig(out / "figures" / (metric.replace("/", "_") + ".png"), dpi=120)
        plt.close(fig)
    if not curves:
        return
    metrics = SCORES[0], SCORES[2]
    fig, axes = plt.subplots(len(metrics), len(curves), figsize=(3.6 * len(curves), 5.6), squeeze=False)
    for col, (task, arms) in enumerate(curves.items()):
        for i, (arm, (updates, values)) in enumerate(arms.items()):
            for row, (metric, title) in enumerate(metrics):
                est, low, high = (np.array([v[j] for v in values[metric]]) for j in range(3))
                ax = axes[row][col]
                ax.plot(updates, est, color=colors[i % len(colors)], label=short_label(arm).replace("\n", " "))
                ax.fill_between(updates, low, high, color=colors[i % len(colors)], alpha=0.2, linewidth=0)
                ax.set_title(f"{task}: {title}", fontsize=8)
                if metric == "heldout/imitation":
                    ax.set_yscale("log")
                else:
                    ax.set_ylim(bottom=0)
        axes[-1][col].set_xlabel("update")
    axes[0][0].legend(fontsize=6)
    fig.tight_layout()
    fig.savefig(out / "figures" / "curves.png", dpi=120)
    plt.close(fig)


def curve(rows: list[dict], metrics, every: int = 10, reps: int = 500) -> dict:
    """{arm label: (updates, {metric: [(IQM, low, high) over seeds]})} at every `every`-th logged update (the
    updates every seed logged), for the learning-curve figure."""
    out: dict = {}
    for arm, hp in sorted({(r["arm"], r["hp"]) for r in rows}):
        mine = [r for r in rows if (r["arm"], r["hp"]) == (arm, hp)]
        seeds = {r["seed"] for r in mine}
        by_update: dict[int, list[dict]] = {}
        for r in mine:
            by_update.setdefault(r["update"], []).append(r)
        # updates 1, 1 + every, ... (those a thinned log kept), where every seed logged
        updates = [u for u in sorted(by_update) if len(by_update[u]) == len(seeds) and u % every == 1 % every]
        values = {m: [iqm_interval([r[m] for r in by_update[u]], reps=reps)[:3] for u in updates] for m, _ in metrics}
        out[arm if hp == "default" else f"{arm} {hp}"] = (updates, values)
    return out


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


def compact_strips(src: str, dest: str, steps: int = 20, sequences: int = 1, cell: int = 66) -> list[pathlib.Path]:
    """Copies of the strips in `src` small enough to commit: the first `sequences` held-out sequences (three rows
    each) and `steps` columns (the context, then the first open-loop steps) of cells `cell` pixels square (a
    64x64 frame and its 1-pixel frame), as 256-colour palette PNGs."""
    from PIL import Image

    paths = []
    for path in sorted(pathlib.Path(src).glob("*.png")):
        image = Image.open(path).convert("RGB")
        box = (0, 0, min(image.width, steps * cell), min(image.height, 3 * sequences * cell))
        out = pathlib.Path(dest) / path.name
        out.parent.mkdir(parents=True, exist_ok=True)
        image.crop(box).quantize(256, method=Image.Quantize.MEDIANCUT).save(out, optimize=True)
        paths.append(out)
    return paths


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("out", nargs="?")
    parser.add_argument("--strips", nargs=2, metavar=("RUN_DIR", "DEST"))
    parser.add_argument("--compact-strips", nargs=2, metavar=("SRC", "DEST"),
                        help="copies of SRC's strips small enough to commit (one sequence, 20 steps, 256 colours)")
    parser.add_argument("--bootstrap-reps", type=int, default=2000)
    args = parser.parse_args(argv)
    if args.strips or args.compact_strips:
        for path in write_strips(*args.strips) if args.strips else compact_strips(*args.compact_strips):
            print(f"wrote {path}")
        return
    out = pathlib.Path(args.out)
    tasks = units_of(out)
    merged = {task: merge_units(dirs) for task, dirs in tasks.items()}
    results = [task_report(dirs, args.bootstrap_reps, merged[task]) for task, dirs in tasks.items()]
    tables, infos = [r[0] for r in results], [r[1] for r in results]
    text = markdown(tables, infos)
    (out / "report.md").write_text(text)
    curves = {task: curve(merged[task][0], (SCORES[0], SCORES[2])) for task in tasks}
    figures(out, tables, curves)
    print(text)


if __name__ == "__main__":
    main()
