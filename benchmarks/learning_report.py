"""The learning benchmark's report: rows.jsonl of one or more runs -> markdown table and curve plot.

Per task and learner (framework + variant): the IQM over seeds of the deterministic evaluation return
at the last evaluation, with a 95% stratified-bootstrap interval (cdjax.stats, rliable's
method), the same for the mean over all evaluations after step 0 (the normalised area under the
curve), the seeds, and training env steps/s. A verdict compares each cdjax learner with Brax PPO on
the final IQM: "cdjax >= brax" when cdjax's IQM is at least Brax's, and whether the intervals overlap.
"""

from __future__ import annotations

import json
import math
import pathlib
from collections import defaultdict

import numpy as np


def split_source(source: str | pathlib.Path) -> tuple[pathlib.Path, str | None, str | None]:
    """"DIR" -> (DIR, None, None); "DIR@FRAMEWORK" (brax or cdjax) -> (DIR, FRAMEWORK, None): only that framework's
    rows of DIR, e.g. the Brax rows of a directory whose cdjax rows a later run replaces; "DIR@cdjax=NAME" -> (DIR,
    "cdjax", NAME): DIR's cdjax rows, each reported as variant NAME, e.g. rows whose `default` ran before a default
    changed, or one setting's seeds spread over runs under two variant names."""
    text = str(source)
    head, sep, tail = text.rpartition("@")
    if sep and not pathlib.Path(text).exists():
        framework, eq, name = tail.partition("=")
        if tail == "brax" or framework == "cdjax" and bool(eq) == bool(name):  # a NAME only for cdjax, never empty
            return pathlib.Path(head), framework, name or None
    return pathlib.Path(text), None, None


def load(dirs: list[pathlib.Path | str]) -> tuple[list[dict], list[dict]]:
    """(rows, metas) of every directory (DIR, DIR@FRAMEWORK or DIR@cdjax=NAME, see `split_source`); a row carries
    its directory's device in `device`."""
    rows, metas = [], []
    for source in dirs:
        d, framework, name = split_source(source)
        if not (d / "rows.jsonl").is_file():
            raise ValueError(f"{source} has no rows.jsonl: give a directory of `python -m benchmarks.learning --out`, "
                             "as DIR, DIR@brax, DIR@cdjax or DIR@cdjax=NAME")
        meta = json.loads((d / "meta.json").read_text()) if (d / "meta.json").exists() else {}
        metas.append({"dir": str(source), **meta})
        for line in (d / "rows.jsonl").read_text().splitlines():
            if line.strip():
                row = json.loads(line)
                if framework is None or row["framework"] == framework:
                    rows.append({**row, "device": meta.get("device", "?"), **({"variant": name} if name else {})})
    return rows, metas


def curves(rows: list[dict]) -> dict[tuple[str, str], dict]:
    """{(task, learner): {"steps": [P], "returns": [S, P] (NaN where missing), "seeds": [S], ...}}."""
    grouped: dict[tuple[str, str], list[dict]] = defaultdict(list)
    for r in rows:
        learner = "brax-ppo" if r["framework"] == "brax" else f"cdjax {r['variant']}"
        grouped[(r["task"], learner)].append(r)
    out = {}
    for key, rs in grouped.items():
        steps = sorted({r["env_steps"] for r in rs})
        seeds = sorted({r["seed"] for r in rs})
        values = np.full((len(seeds), len(steps)), np.nan)
        seen = set()
        for r in rs:
            if (r["seed"], r["env_steps"]) in seen:  # two sources of one seed: one would hide the other
                raise ValueError(f"{key[1]} on {key[0]}: seed {r['seed']} at {r['env_steps']} env steps comes from two "
                                 "rows; report each seed once (DIR@FRAMEWORK selects one framework's rows of DIR)")
            seen.add((r["seed"], r["env_steps"]))
            v = r["eval_return"]
            values[seeds.index(r["seed"]), steps.index(r["env_steps"])] = np.nan if v is None else v
        out[key] = {"steps": np.asarray(steps), "returns": values, "seeds": seeds, "rows": rs}
    return out


def _sps(c: dict) -> float:
    """Training env steps per second (all seeds together for cdjax; per seed, Brax's own figure, for Brax)."""
    rs = c["rows"]
    if rs[0]["framework"] == "brax":
        sps = [r["train_s"] for r in rs if r.get("train_s")]  # Brax's training/sps
        return float(np.median(sps)) if sps else math.nan
    last = max(rs, key=lambda r: r["env_steps"])
    return last["env_steps"] * len(c["seeds"]) / last["train_s"] if last["train_s"] else math.nan


def _devices(rows: list[dict]) -> str:
    """The devices the rows were measured on, each once, in the order they first appear (a learner's seeds may
    come from runs on several devices)."""
    return " + ".join(dict.fromkeys(r.get("device", "?") for r in rows))


def table(rows: list[dict], reps: int = 2000) -> list[dict]:
    from cdjax.stats import iqm_interval

    out = []
    for (task, learner), c in sorted(curves(rows).items()):
        complete = np.isfinite(c["returns"]).all(axis=0)
        if not complete.any():
            continue
        last = int(np.flatnonzero(complete)[-1])
        final = c["returns"][:, last]
        auc = np.nanmean(c["returns"][:, 1: last + 1], axis=1) if last > 0 else final
        f = iqm_interval(final, reps=reps)
        a = iqm_interval(auc, reps=reps)
        out.append({"task": task, "learner": learner, "seeds": len(c["seeds"]), "env_steps": int(c["steps"][last]),
                    "final": f[:3], "auc": a[:3], "sps": _sps(c), "device": _devices(c["rows"]),
                    "per_seed": [round(float(x), 1) for x in final]})
    return out


def ablation(rows: list[dict], reps: int = 2000) -> list[dict]:
    """Each cdjax variant at its last complete evaluation, beside cdjax default at the same env steps."""
    from cdjax.stats import iqm_interval

    cs = curves(rows)
    out = []
    for (task, learner), c in sorted(cs.items()):
        base = cs.get((task, "cdjax default"))
        if not learner.startswith("cdjax ") or learner == "cdjax default" or base is None:
            continue
        complete = np.isfinite(c["returns"]).all(axis=0)
        if not complete.any():
            continue
        step = c["steps"][int(np.flatnonzero(complete)[-1])]
        if step not in base["steps"]:
            continue
        j = list(base["steps"]).index(step)
        out.append({"task": task, "learner": learner, "env_steps": int(step), "seeds": len(c["seeds"]),
                    "iqm": iqm_interval(c["returns"][:, list(c["steps"]).index(step)], reps=reps)[:3],
                    "default": iqm_interval(base["returns"][:, j], reps=reps)[:3], "default_seeds": len(base["seeds"])})
    return out


def _ci(x: tuple) -> str:
    point, low, high = x
    return f"{point:.1f} [{low:.1f}, {high:.1f}]" if math.isfinite(low) else f"{point:.1f}"


def verdicts(entries: list[dict]) -> list[str]:
    lines = []
    by_task = defaultdict(dict)
    for e in entries:
        by_task[e["task"]][e["learner"]] = e
    for task, learners in by_task.items():
        brax = learners.get("brax-ppo")
        if brax is None:
            continue
        for name, e in learners.items():
            if name == "brax-ppo" or e["env_steps"] != brax["env_steps"]:
                continue
            ge = e["final"][0] >= brax["final"][0]
            overlap = not (e["final"][1] > brax["final"][2] or e["final"][2] < brax["final"][1])
            speed = e["sps"] / brax["sps"] if brax["sps"] else math.nan
            lines.append(f"- {task}: {name} final IQM {e['final'][0]:.1f} {'>=' if ge else '<'} Brax PPO's "
                         f"{brax['final'][0]:.1f} at {e['env_steps']:,} env steps (intervals "
                         f"{'overlap' if overlap else 'disjoint'}); training env steps/s {speed:.2f}x Brax's "
                         "(cdjax: its seeds vmapped together; Brax: one seed at a time).")
    return lines


def plot(rows: list[dict], path: pathlib.Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from cdjax.stats import interval_curve

    cs = curves(rows)
    tasks = sorted({t for t, _ in cs})
    fig, axes = plt.subplots(1, len(tasks), figsize=(4.5 * len(tasks), 3.4), squeeze=False)
    for ax, task in zip(axes[0], tasks):
        for (t, learner), c in sorted(cs.items()):
            if t != task:
                continue
            point, low, high, _ = interval_curve(c["returns"], "iqm", reps=500)
            x = c["steps"] / 1e6
            style = "--" if learner == "brax-ppo" else "-"
            ax.plot(x, point, style, label=learner)
            ax.fill_between(x, low, high, alpha=0.15)
        ax.set_title(task)
        ax.set_xlabel("env steps (M)")
        ax.set_ylabel("eval return (IQM, 95% CI)")
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def report(dirs: list[pathlib.Path], write: str | None = None, parity_variants: tuple[str, ...] = ("default",)) -> str:
    """The markdown (and with `write` the file and the plot beside it); `parity_variants`: the cdjax variants
    set against Brax PPO in the first table (the others appear in the ablation beside cdjax default)."""
    rows, metas = load(dirs)
    entries = table(rows)
    wanted = {"brax-ppo"} | {f"cdjax {v}" for v in parity_variants}
    parity = [e for e in entries if e["learner"] in wanted]
    lines = ["### cdjax model-free against Brax PPO", "",
             "| task | learner | seeds | env steps | final return IQM [95% CI] | mean over evals IQM [95% CI] | "
             "train env steps/s | device | final per seed |", "|---|---|---:|---:|---|---|---:|---|---|"]
    for e in parity:
        lines.append(f"| {e['task']} | {e['learner']} | {e['seeds']} | {e['env_steps']:,} | {_ci(e['final'])} | "
                     f"{_ci(e['auc'])} | {e['sps']:,.0f} | {e['device']} | {e['per_seed']} |")
    lines += [""] + verdicts(parity)
    abl = ablation(rows)
    if abl:
        lines += ["", "### Ablation: one cdjax option changed (each at its last evaluation)", "",
                  "| task | variant | seeds | env steps | variant IQM [95% CI] | cdjax default IQM [95% CI] (seeds) |",
                  "|---|---|---:|---:|---|---|"]
        for a in abl:
            lines.append(f"| {a['task']} | {a['learner'].removeprefix('cdjax ')} | {a['seeds']} | {a['env_steps']:,} | "
                         f"{_ci(a['iqm'])} | {_ci(a['default'])} ({a['default_seeds']}) |")
    lines += ["", "Commands:"] + [f"- `{m.get('command', '?')}` ({m.get('device', '?')}, {m.get('date', '?')}; "
                                  f"{m['dir']})" for m in metas]
    text = "\n".join(lines)
    if write:
        path = pathlib.Path(write)
        png = path.with_suffix(".png")
        plot(rows, png)
        path.write_text(text + f"\n\n![curves]({png.name})\n")
    return text
