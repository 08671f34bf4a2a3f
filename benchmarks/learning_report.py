"""The learning benchmarks' report: rows.jsonl of one or more runs (benchmarks.learning: Brax PPO against cdjax's
obs setting; benchmarks.brax_sac: Brax SAC against the off-policy setting) -> markdown table and curve plot.

Per task and learner (cdjax: its variant; Brax: brax-ppo or brax-sac): the IQM over seeds of the deterministic
evaluation return at the last evaluation, with a 95% stratified-bootstrap interval (cdjax.stats, rliable's
method), the same for the mean over all evaluations after step 0 (the normalised area under the
curve), the seeds, and training env steps/s. A verdict compares each cdjax learner with Brax's learner of its
kind (offpolicy-* with Brax SAC, the others with Brax PPO) on the final IQM: whether cdjax's IQM is at least Brax's,
and whether the intervals overlap. Both are read at their last evaluation, which must be at the same env steps
within 1%: Brax SAC's evaluations count its prefill steps, so they fall a little off cdjax's (the line says both).
Rows without an evaluation return (brax_sac's speed case) are not read.
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


def _json(path: pathlib.Path, text: str, where: str = ""):
    try:
        return json.loads(text)
    except json.JSONDecodeError as err:
        raise ValueError(f"{path}{where} is not JSON ({err.msg})") from None


def load(dirs: list[pathlib.Path | str]) -> tuple[list[dict], list[dict]]:
    """(rows, metas) of every directory (DIR, DIR@FRAMEWORK or DIR@cdjax=NAME, see `split_source`); a row carries
    its directory's device in `device` and the directory in `source` (one run's rows). ValueError (one sentence) for
    a directory without rows, a line that is not JSON, or sources that leave no row."""
    rows, metas = [], []
    for source in dirs:
        d, framework, name = split_source(source)
        if not (d / "rows.jsonl").is_file():
            raise ValueError(f"{source} has no rows.jsonl: give a directory of `python -m benchmarks.learning --out`, "
                             "as DIR, DIR@brax, DIR@cdjax or DIR@cdjax=NAME")
        meta = _json(d / "meta.json", (d / "meta.json").read_text()) if (d / "meta.json").exists() else {}
        metas.append({"dir": str(source), **meta})
        lines = [(i, line) for i, line in enumerate((d / "rows.jsonl").read_text().splitlines(), 1) if line.strip()]
        if not lines:
            raise ValueError(f"no rows in {d / 'rows.jsonl'}: its run measured nothing (yet)")
        for i, line in lines:
            row = _json(d / "rows.jsonl", line, f" line {i}")
            if "eval_return" in row and (framework is None or row["framework"] == framework):
                rows.append({**row, "device": meta.get("device", "?"), "shared": bool(meta.get("shared_device")),
                             "started": meta.get("process_started_at"), "source": str(d),
                             **({"variant": name} if name else {})})
    if not rows:
        raise ValueError(f"no rows in {', '.join(map(str, dirs))}: each holds only the other framework's rows")
    return rows, metas


def curves(rows: list[dict]) -> dict[tuple[str, str], dict]:
    """{(task, learner): {"steps": [P], "returns": [S, P] (NaN where missing), "seeds": [S], ...}}."""
    grouped: dict[tuple[str, str], list[dict]] = defaultdict(list)
    for r in rows:
        brax = "brax-sac" if r["variant"] == "brax-sac" else "brax-ppo"  # (PPO rows' variant: brax-ppo)
        learner = brax if r["framework"] == "brax" else f"cdjax {r['variant']}"
        grouped[(r["task"], learner)].append(r)
    out = {}
    for key, rs in grouped.items():
        steps = sorted({r["env_steps"] for r in rs})
        seeds = sorted({r["seed"] for r in rs})
        values = np.full((len(seeds), len(steps)), np.nan)
        present = np.zeros((len(seeds), len(steps)), bool)  # a row there (its value may still be NaN)
        seen = set()
        for r in rs:
            if (r["seed"], r["env_steps"]) in seen:  # two sources of one seed: one would hide the other
                raise ValueError(f"{key[1]} on {key[0]}: seed {r['seed']} at {r['env_steps']} env steps comes from two "
                                 "rows; report each seed once (DIR@FRAMEWORK selects one framework's rows of DIR)")
            seen.add((r["seed"], r["env_steps"]))
            v = r["eval_return"]
            values[seeds.index(r["seed"]), steps.index(r["env_steps"])] = np.nan if v is None else v
            present[seeds.index(r["seed"]), steps.index(r["env_steps"])] = True
        out[key] = {"steps": np.asarray(steps), "returns": values, "present": present, "seeds": seeds, "rows": rs}
    return out


def _sps(c: dict) -> float:
    """Training env steps per second, the median over runs: for cdjax, all of a run's seeds together (its train_s
    is after compilation); for Brax, one seed, from the training time benchmarks.learning measures (rows with
    `eval_s`), leaving out the first interval (Brax compiles in it), else Brax's own training/sps (brax_sac's rows
    say `sps`; benchmarks.learning's before they measured it kept it in `train_s`). NaN when another process shared
    the device with any of the runs (their meta says shared_device): their times are not speeds."""
    rs = c["rows"]
    if any(r.get("shared") for r in rs):
        return math.nan
    brax = rs[0]["framework"] == "brax"
    if brax and not all("eval_s" in r for r in rs):
        sps = [r.get("sps", r.get("train_s")) for r in rs]
        sps = [x for x in sps if x]
        return float(np.median(sps)) if sps else math.nan
    runs = defaultdict(list)  # a learner's seeds may come from several runs (sources), each with its own time
    for r in rs:
        runs[(r.get("source"), r["seed"] if brax else None)].append(r)
    sps = []
    for run in runs.values():
        run = sorted(run, key=lambda r: r["env_steps"])
        first = run[1] if brax and len(run) > 2 else run[0]
        if run[-1]["train_s"] > first["train_s"]:
            steps = run[-1]["env_steps"] - first["env_steps"]
            sps.append(steps * len({r["seed"] for r in run}) / (run[-1]["train_s"] - first["train_s"]))
    return float(np.median(sps)) if sps else math.nan


def _speed(sps: float) -> str:
    return f"{sps:,.0f}" if math.isfinite(sps) else "not read"


def _devices(rows: list[dict]) -> str:
    """The devices the rows were measured on, each once, in the order they first appear (a learner's seeds may
    come from runs on several devices)."""
    return " + ".join(dict.fromkeys(r.get("device", "?") for r in rows))


def final_step(returns: np.ndarray) -> tuple[int, np.ndarray]:
    """(the evaluation the final return is read at, which seeds it is read over) for returns [S, P]. Normally the
    last evaluation, over every seed. A seed whose run stopped early (a time limit cut it) has none there: it is left
    out, so long as at least half the seeds reached the end, rather than cutting every seed back to where the
    shortest stopped (which would set one learner's early return beside another's final one). With fewer than half
    at the end, the last evaluation every seed reached, over all of them. (-1, none) when no evaluation has all."""
    reached = np.isfinite(returns[:, -1])
    if 2 * reached.sum() >= len(reached) and reached.any():
        return returns.shape[1] - 1, reached
    complete = np.isfinite(returns).all(axis=0)
    if not complete.any():
        return -1, np.zeros(len(reached), bool)
    return int(np.flatnonzero(complete)[-1]), np.ones(len(reached), bool)


def table(rows: list[dict], reps: int = 2000) -> list[dict]:
    from cdjax.stats import iqm_interval

    out = []
    for (task, learner), c in sorted(curves(rows).items()):
        last, kept = final_step(c["returns"])
        if last < 0:
            continue
        returns = c["returns"][kept]
        final = returns[:, last]
        auc = np.nanmean(returns[:, 1: last + 1], axis=1) if last > 0 else final
        f = iqm_interval(final, reps=reps)
        a = iqm_interval(auc, reps=reps)
        # (seed, env steps of its last row, whether that row's return is NaN) of each seed left out
        left_out = []
        for i in np.flatnonzero(~kept):
            j = int(np.flatnonzero(c["present"][i])[-1])
            left_out.append((c["seeds"][i], int(c["steps"][j]), not np.isfinite(c["returns"][i, j])))
        out.append({"task": task, "learner": learner, "seeds": int(kept.sum()), "env_steps": int(c["steps"][last]),
                    "final": f[:3], "auc": a[:3], "sps": _sps(c), "device": _devices(c["rows"]),
                    "per_seed": [round(float(x), 1) for x in final], "final_values": final, "left_out": left_out,
                    "curve": c})
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
        last, kept = final_step(c["returns"])
        if last < 0 or c["steps"][last] not in base["steps"]:
            continue
        step = c["steps"][last]
        j = list(base["steps"]).index(step)
        base_kept = np.isfinite(base["returns"][:, j])
        out.append({"task": task, "learner": learner, "env_steps": int(step), "seeds": int(kept.sum()),
                    "iqm": iqm_interval(c["returns"][kept, last], reps=reps)[:3],
                    "default": iqm_interval(base["returns"][base_kept, j], reps=reps)[:3],
                    "default_seeds": int(base_kept.sum())})
    return out


def _ci(x: tuple) -> str:
    point, low, high = x
    return f"{point:.1f} [{low:.1f}, {high:.1f}]" if math.isfinite(low) else f"{point:.1f}"


def verdicts(entries: list[dict], reps: int = 2000) -> list[str]:
    from cdjax.stats import probability_of_improvement

    lines = []
    by_task = defaultdict(dict)
    for e in entries:
        by_task[e["task"]][e["learner"]] = e
    for task, learners in by_task.items():
        for name, e in learners.items():
            kind = "brax-sac" if name.startswith("cdjax offpolicy-") else "brax-ppo"
            brax, them = learners.get(kind), "Brax " + kind[5:].upper()
            if brax is None or name.startswith("brax"):
                continue
            steps = f"{e['env_steps']:,} env steps" + (
                f" (Brax's at {brax['env_steps']:,})" if e["env_steps"] != brax["env_steps"] else "")
            if abs(e["env_steps"] - brax["env_steps"]) > 0.01 * max(e["env_steps"], brax["env_steps"]):
                lines.append(f"- {task}: {name} not compared: its final return is read at {e['env_steps']:,} env "
                             f"steps, {them}'s at {brax['env_steps']:,}.")
                continue
            ge = e["final"][0] >= brax["final"][0]
            overlap = not (e["final"][1] > brax["final"][2] or e["final"][2] < brax["final"][1])
            speed = e["sps"] / brax["sps"] if brax["sps"] else math.nan
            speed = (f"training env steps/s {speed:.2f}x Brax's (cdjax: its seeds vmapped together, the median over "
                     "its runs; Brax: one seed at a time)" if math.isfinite(speed) else
                     "training env steps/s not compared (other processes shared the device, or no time was measured)")
            poi = (probability_of_improvement(e["final_values"], brax["final_values"], reps=reps)
                   if min(len(e["final_values"]), len(brax["final_values"])) > 1 else None)
            poi = f"; P({name} > {them}) = {poi[0]:.2f} [{poi[1]:.2f}, {poi[2]:.2f}]" if poi else ""
            lines.append(f"- {task}: {name} final IQM {e['final'][0]:.1f} {'>=' if ge else '<'} {them}'s "
                         f"{brax['final'][0]:.1f} at {steps} (intervals "
                         f"{'overlap' if overlap else 'disjoint'}{poi}); {speed}.")
            timed = time_to(e, brax, them)
            if timed:
                lines.append(timed)
    return lines


def time_to(e: dict, brax: dict, them: str) -> str | None:
    """The wall-clock, from the command, for cdjax's learner `e` to reach Brax's final return (its IQM over seeds)
    with all its seeds, against Brax's time to its own final evaluation, one process a seed, as one sentence; None
    unless both were timed alone (no other process on the device, each process's launch in its meta) and cdjax's
    seeds ran in one process."""
    rows = e["curve"]["rows"] + brax["curve"]["rows"]
    if any(r.get("shared") or not r.get("started") or r.get("at", 0.0) < r["started"] for r in rows):
        return None  # (a row measured before its process started: an earlier unit's, resumed)
    if len({r["source"] for r in e["curve"]["rows"]}) != 1:
        return None
    from cdjax.stats import iqm_columns

    target = brax["final"][0]
    per_process = defaultdict(list)
    for r in brax["curve"]["rows"]:
        per_process[r["source"]].append(r)
    brax_total = sum(max(r["at"] for r in rs) - rs[0]["started"] for rs in per_process.values())
    n_brax = len({r["seed"] for r in brax["curve"]["rows"]})
    per_seed = brax_total / n_brax
    c = e["curve"]
    n = len(c["seeds"])
    returns = np.where(np.isfinite(c["returns"]), c["returns"], -np.inf)
    reached = np.flatnonzero(iqm_columns(returns[:, None, :]) >= target)
    at = {int(s): max(r["at"] for r in c["rows"] if r["env_steps"] == s) - c["rows"][0]["started"] for s in c["steps"]}
    seeds = lambda k: f"{k} seed{'s' if k != 1 else ''}"  # noqa: E731
    head = (f"- {e['task']}: wall-clock from the command to {them}'s final return (IQM {target:.1f}): Brax "
            f"{per_seed:.0f} s a seed to its final evaluation (the mean over its {seeds(n_brax)}' processes), so "
            f"{seeds(n)} one after another {n * per_seed:.0f} s; {e['learner']}, {seeds(n)} in one process, ")
    if not reached.size:
        return head + f"did not reach it in its {at[int(c['steps'][-1])]:.0f} s."
    t = at[int(c["steps"][reached[0]])]
    return head + (f"{t:.0f} s (its IQM over seeds first reached it at {int(c['steps'][reached[0]]):,} env steps): "
                   f"{t / (n * per_seed):.2f}x Brax's time for {seeds(n)}, {t / per_seed:.2f}x Brax's for one.")


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
            _, kept = final_step(c["returns"])  # the seeds the table reads, so the curve ends where it does
            if not kept.any():
                continue
            point, low, high, _ = interval_curve(c["returns"][kept], "iqm", reps=500)
            x = c["steps"] / 1e6
            style = "--" if learner.startswith("brax") else "-"
            ax.plot(x, point, style, label=learner)
            ax.fill_between(x, low, high, alpha=0.15)
        ax.set_title(task)
        ax.set_xlabel("env steps (M)")
        ax.set_ylabel("eval return (IQM, 95% CI)")
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def report(dirs: list[pathlib.Path], write: str | None = None, parity_variants: tuple[str, ...] = ("default",),
           reps: int = 2000) -> str:
    """The markdown (and with `write` the file and the plot beside it); `parity_variants`: the cdjax variants
    set against Brax PPO in the first table (the others appear in the ablation beside cdjax default); `reps`: the
    bootstrap's resamples for the tables' intervals."""
    rows, metas = load(dirs)
    text = report_text(rows, metas, parity_variants, reps)
    if write:
        path = pathlib.Path(write)
        png = path.with_suffix(".png")
        plot(rows, png)
        path.write_text(text + f"\n\n![curves]({png.name})\n")
    return text


def report_text(rows: list[dict], metas: list[dict], parity_variants: tuple[str, ...] = ("default",),
                reps: int = 2000) -> str:
    """The report's markdown for these rows (and the commands of `metas`); `reps`: the bootstrap's resamples."""
    entries = table(rows, reps)
    wanted = {f"cdjax {v}" for v in parity_variants}
    parity = [e for e in entries if e["learner"] in wanted or e["learner"].startswith(("brax", "cdjax offpolicy-"))]
    lines = ["### cdjax against Brax (PPO: the obs setting's model-free arm; SAC: the off-policy setting)", "",
             "| task | learner | seeds | env steps | final return IQM [95% CI] | mean over evals IQM [95% CI] | "
             "train env steps/s | device | final per seed |", "|---|---|---:|---:|---|---|---:|---|---|"]
    for e in parity:
        lines.append(f"| {e['task']} | {e['learner']} | {e['seeds']} | {e['env_steps']:,} | {_ci(e['final'])} | "
                     f"{_ci(e['auc'])} | {_speed(e['sps'])} | {e['device']} | {e['per_seed']} |")
    lines += [""] + verdicts(parity, reps)
    for e in entries:
        for seed, steps, nan in e["left_out"]:
            why = (f"its evaluation at {steps:,} env steps is not a number" if nan else
                   f"its run stopped at {steps:,} env steps, before the last evaluation")
            lines.append(f"- {e['task']}: {e['learner']} seed {seed} left out of the final return and the mean over "
                         f"evaluations: {why}.")
    abl = ablation(rows, reps)
    if abl:
        lines += ["", "### Ablation: one cdjax option changed (each at its last evaluation)", "",
                  "| task | variant | seeds | env steps | variant IQM [95% CI] | cdjax default IQM [95% CI] (seeds) |",
                  "|---|---|---:|---:|---|---|"]
        for a in abl:
            lines.append(f"| {a['task']} | {a['learner'].removeprefix('cdjax ')} | {a['seeds']} | {a['env_steps']:,} | "
                         f"{_ci(a['iqm'])} | {_ci(a['default'])} ({a['default_seeds']}) |")
    lines += ["", "Commands:"] + [f"- `{m.get('command', '?')}` ({m.get('device', '?')}, {m.get('date', '?')}; "
                                  f"{m['dir']})" for m in metas]
    return "\n".join(lines)
