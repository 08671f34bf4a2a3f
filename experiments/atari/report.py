"""Table and sample-efficiency figure of the Atari experiments, from the run directories of its units
(experiments/atari/units.py).

    python -m experiments.atari.report RUN_DIR [RUN_DIR ...] --out DIR     # writes DIR/results.md, DIR/curves.png

One run directory per game (`cdjax sweep --setting atari`). Arms are compared at the same budget: a game whose
runs were stopped by a time limit is cut at the largest env-step count that all of its arms reached, and the
table says so. Statistics are cdjax.stats': IQM over seeds with a 95% stratified-bootstrap interval (rliable);
final = mean of each seed's logged training returns in the last 10% of its env steps up to the budget (a window
of steps, not of points, so that unevenly thinned logs give the same figure as whole ones); AUC = env-step weighted
mean of each seed's training-return curve up to the budget (sample efficiency); eval = the mean return of each
seed's latest evaluation (100 episodes, sampled actions since 2026-11-22, greedy before; sticky actions). Throughput: env steps per second
of wall time of each arm over all of its runs (the arms of a game alternate chunks in one process). An ALE game's
figure also marks the published A2C returns at equal agent steps (`experiments.atari.published`: learning-curve
data without sticky actions; black markers).
"""

from __future__ import annotations

import argparse
import json
import pathlib

import numpy as np

from cdjax import io, stats
from experiments.atari import published

RETURN = "episode/return"
COLORS = {"a2c": "#1f77b4", "a2c-model": "#7f7f7f", "a2c-cd": "#d62728"}
BINS = 50  # points of the figure's curves: each seed's returns averaged within env-step bins


def load(run_dir: pathlib.Path) -> dict:
    """{"game", "seeds", "arms": {label: {"steps" [U], "returns" [S, U], "wall" [S, U]}}, "evals": {label: {seed:
    (update, return, episodes, env steps)}}} of a run dir; a label is the arm, with its hyper-parameters when the
    arm ran a grid (e.g. "a2c-cd alpha=1.0,lr=0.002")."""
    run = json.loads((run_dir / "run.json").read_text())
    rows = io.read_jsonl(run_dir / "metrics.jsonl")
    arms = {}
    for arm, hp in [(a["name"], h) for a in run["arms"] for h in a["hp_labels"]]:
        label = _label(run, arm, hp)
        mine = [r for r in rows if r["arm"] == arm and r["hp"] == hp and r["update"] > 0]
        updates = sorted({r["update"] for r in mine})
        index = {u: i for i, u in enumerate(updates)}
        steps = np.zeros(len(updates))
        returns = np.full((run["seeds"], len(updates)), np.nan)
        wall = np.full((run["seeds"], len(updates)), np.nan)
        for r in mine:
            i = index[r["update"]]
            steps[i] = r["env_steps"]
            value = r.get(RETURN)
            returns[r["seed"], i] = np.nan if value is None else value
            wall[r["seed"], i] = r["wall_s"]
        arms[label] = {"arm": arm, "steps": steps, "returns": returns, "wall": wall}
    evals: dict[str, dict[int, tuple]] = {}
    for e in io.read_jsonl(run_dir / "eval.jsonl"):
        seen = evals.setdefault(_label(run, e["arm"], e["hp"]), {})
        if e["seed"] not in seen or e["update"] >= seen[e["seed"]][0]:
            seen[e["seed"]] = (e["update"], e["eval/return"], e["episodes"], e["env_steps"],
                               "greedy" if e.get("deterministic", True) else "sampled")
    return {"game": run["base_config"]["env"], "seeds": run["seeds"], "arms": arms, "evals": evals}


def _label(run: dict, arm: str, hp: str) -> str:
    """The arm's name, and its hyper-parameter label where the arm has more than one combination."""
    labels = next(a["hp_labels"] for a in run["arms"] if a["name"] == arm)
    return arm if len(labels) == 1 else f"{arm} {hp}"


def budget(data: dict) -> float:
    """The largest env-step count every arm reached."""
    return min(a["steps"][-1] for a in data["arms"].values() if a["steps"].size)


def seed_scores(data: dict, label: str) -> dict[str, np.ndarray]:
    """Per seed [S] of one arm (label) of a run: "final" and "auc" training returns up to the game's budget (the
    largest env-step count all of its arms reached) and "eval", the mean return of the seed's latest evaluation (NaN
    where a seed has none)."""
    a, cut = data["arms"][label], budget(data)
    keep = a["steps"] <= cut
    steps, returns = a["steps"][keep], a["returns"][:, keep]
    present = np.ones(returns.shape, bool)  # every update logged a point (NaN before a first episode end)
    ev = data["evals"].get(label, {})
    evals = np.array([np.nan if ev.get(s, (0, None))[1] is None else ev[s][1] for s in range(returns.shape[0])])
    return {"final": stats.final_values(returns, present, steps=steps), "auc": stats.area_under_curve(returns, present, steps),
            "eval": evals}


def table_rows(data: dict, reps: int) -> list[dict]:
    cut = budget(data)
    out = []
    runs: dict[str, int] = {}
    for a in data["arms"].values():
        runs[a["arm"]] = runs.get(a["arm"], 0) + a["returns"].shape[0]
    for arm, a in data["arms"].items():
        keep = a["steps"] <= cut
        steps = a["steps"][keep]
        scores = seed_scores(data, arm)
        ev = data["evals"].get(arm, {})
        wall = np.nanmax(a["wall"][:, keep])
        out.append({
            "game": data["game"], "arm": arm, "seeds": int(a["returns"].shape[0]), "budget": cut,
            "final": stats.iqm_interval(scores["final"], reps), "auc": stats.iqm_interval(scores["auc"], reps),
            "eval": stats.iqm_interval(scores["eval"], reps),
            "eval_steps": sorted({ev[s][3] for s in ev}), "eval_episodes": sorted({ev[s][2] for s in ev}),
            "eval_modes": sorted({ev[s][4] for s in ev}),
            # the arm's program runs all of its hyper-parameter combinations x seeds together
            "steps_per_s": steps[-1] * runs[a["arm"]] / wall if wall > 0 else np.nan,
        })
    return out


def _cell(x: tuple) -> str:
    point, low, high, n = x
    return "n/a" if n == 0 else (f"{point:.2f} [{low:.2f}, {high:.2f}]" if n > 1 else f"{point:.2f}")


def markdown(rows: list[dict]) -> str:
    lines = ["| game | arm | seeds | env steps (budget) | final return | AUC return | eval return | eval at env steps "
             "| env steps/s (the arm's runs) |", "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        evaluated = (f"{_cell(r['eval'])} ({'/'.join(map(str, r['eval_episodes']))} episodes, "
                     f"{'/'.join(r['eval_modes'])})" if r["eval_episodes"] else "n/a (not evaluated)")
        lines.append(f"| {r['game']} | {r['arm']} | {r['seeds']} | {r['budget']:.3g} | {_cell(r['final'])} | "
                     f"{_cell(r['auc'])} | {evaluated} | "
                     f"{', '.join(f'{s:.3g}' for s in r['eval_steps']) or 'n/a'} | {r['steps_per_s']:,.0f} |")
    lines.append("")
    lines.append("IQM over seeds [95% stratified-bootstrap interval]. final: the logged training returns of the last 10% "
                 "of the env steps up to the budget; AUC: env-step weighted mean of the training-return curve up to the budget; eval: "
                 "latest evaluation of each seed (greedy: the most probable action; sampled: the policy's own; sticky actions as "
                 "in training).")
    return "\n".join(lines) + "\n"


def binned(steps: np.ndarray, returns: np.ndarray, cut: float) -> tuple[np.ndarray, np.ndarray]:
    """Each seed's returns averaged within BINS equal env-step bins up to `cut`: (bin ends [P], values [S, P])."""
    edges = np.linspace(0.0, cut, BINS + 1)
    which = np.clip(np.searchsorted(edges, steps, side="left") - 1, 0, BINS - 1)
    values = np.full((returns.shape[0], BINS), np.nan)
    for b in range(BINS):
        cols = (which == b) & (steps <= cut)
        if cols.any():
            values[:, b] = stats.nan_reduce(np.nanmean, returns[:, cols], axis=1)
    return edges[1:], values


def figure(datas: list[dict], path: pathlib.Path, reps: int) -> pathlib.Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(datas), figsize=(5 * len(datas), 3.6), squeeze=False)
    for ax, data in zip(axes[0], datas):
        cut = budget(data)
        for arm, a in data["arms"].items():
            x, values = binned(a["steps"], a["returns"], cut)
            point, low, high, _ = stats.interval_curve(values, "iqm", reps)
            color = COLORS.get(arm) if arm in COLORS else None
            (line,) = ax.plot(x, point, color=color, label=arm)
            ax.fill_between(x, low, high, color=line.get_color(), alpha=0.2, linewidth=0)
        for source, pts in published.points(data["game"], cut).items():
            ax.plot(*zip(*pts), linestyle="none", marker=published.MARKERS.get(source, "o"), color="black",
                    markerfacecolor="none", label=f"A2C, {source}")
        name = data["game"] if data["game"].startswith("ale-") else f"MinAtar {data['game']}"
        ax.set_title(f"{name} ({data['seeds']} seeds)")
        ax.set_xlabel("env steps per run")
        ax.set_ylabel("training episode return (IQM, 95% CI)")
        ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run_dirs", nargs="+", type=pathlib.Path)
    parser.add_argument("--out", type=pathlib.Path, required=True)
    parser.add_argument("--bootstrap-reps", type=int, default=2000)
    args = parser.parse_args(argv)
    datas = [load(d) for d in args.run_dirs if io.jsonl_exists(d / "metrics.jsonl")]
    if not datas:
        raise SystemExit(f"No run directory with logged updates among {', '.join(map(str, args.run_dirs))}.")
    args.out.mkdir(parents=True, exist_ok=True)
    rows = [row for data in datas for row in table_rows(data, args.bootstrap_reps)]
    text = markdown(rows)
    (args.out / "results.md").write_text(text)
    figure(datas, args.out / "curves.png", args.bootstrap_reps)
    print(text)
    print(f"Wrote {args.out / 'results.md'} and {args.out / 'curves.png'}")


if __name__ == "__main__":
    main()
