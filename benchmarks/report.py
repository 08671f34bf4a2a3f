"""Ratios, targets, markdown tables, the plot and RESULTS.md, from results dicts (no JAX needed).

A results dict (what results.json holds):

    {"metas": [ {suite, command, date, device, device_count, versions, spec, ...}, ... ],
     "part_meta": {part name: index into metas},
     "parts": {"compare": [row, ...], "seeds": [...], "envs": [...], "devices": [...]}}

Rows are flat dicts; every measured row has `env_steps_per_s`, `update_s` (seconds per update: the
time of spec.env_steps_per_update env steps, per run) and `status` ("ok" or why not). `add_ratios`
adds the derived columns; `merge` joins the results of several suite runs (one per process).
"""

from __future__ import annotations

import json
import math
import pathlib

from benchmarks.throughput import DESIGNATED_CD, PAPER_CD

PARTS = ("compare", "seeds", "envs", "devices")
COLORS = {"ceiling": "tab:gray", "brax-ppo": "tab:red", "collect": "tab:brown", "model-free": "tab:green",
          "mbmf": "tab:olive", DESIGNATED_CD: "tab:blue", PAPER_CD: "tab:orange", "cd-w2-unroll": "tab:cyan",
          "cd-default": "tab:purple"}
TARGETS = {  # name: (description, comparison, threshold)
    "cd_vs_brax": (f"CD ({DESIGNATED_CD}) env steps/s / Brax PPO", ">=", 1.0),
    "mf_vs_brax": ("model-free env steps/s / Brax PPO", ">=", 1.5),
    "cd_wall_vs_mf": (f"CD ({DESIGNATED_CD}) wall-clock per update / model-free", "<=", 1.5),
    "seeds32_vs_1": (f"CD ({DESIGNATED_CD}): aggregate env steps/s of 32 vmapped seeds / 1 seed", ">=", 8.0),
    "cd_compile_s": (f"CD ({DESIGNATED_CD}) update: lower + compile seconds", "<", 60.0),
    "paper_wall_vs_mbmf": (f"CD, the paper's schedule ({PAPER_CD}), wall-clock per update / Mb-Mf", "<=", 1.5),
    "paper_seeds10_vs_mbmf": (f"CD ({PAPER_CD}) / Mb-Mf wall-clock per update, 10 vmapped seeds", "<=", 1.25),
}


def ok(row: dict | None) -> bool:
    return bool(row) and row.get("status") == "ok" and _finite(row.get("env_steps_per_s"))


def _finite(x) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


def _div(a, b):
    return a / b if _finite(a) and _finite(b) and b != 0 else None


def find(rows: list[dict], **match) -> dict | None:
    for r in rows:
        if all(r.get(k) == v for k, v in match.items()):
            return r
    return None


# ---------------------------------------------------------------------------------------------- ratios

def add_ratios(results: dict) -> dict:
    """Add derived columns in place (and return results):

    compare: vs_ceiling = steps/s / ceiling steps/s; vs_brax = steps/s / Brax PPO steps/s;
             wall_vs_model_free = update_s / model-free update_s (same env steps per update).
    seeds:   speedup_vs_1 = aggregate steps/s / same case's 1-seed steps/s (same mesh);
             s_per_seed_update = update_s / seeds.
    devices: speedup_vs_1_device = steps/s / same case and seeds on a 1-device mesh.
    envs:    vs_ceiling and wall_vs_model_free at the same num_envs.
    """
    parts = results.get("parts", {})
    rows = parts.get("compare", [])
    ceil, brax, mf = find(rows, case="ceiling"), find(rows, case="brax-ppo"), find(rows, case="model-free")
    mbmf = find(rows, case="mbmf")
    for r in rows:
        if not ok(r):
            continue
        r["vs_ceiling"] = _div(r["env_steps_per_s"], ceil["env_steps_per_s"]) if ok(ceil) else None
        r["vs_brax"] = _div(r["env_steps_per_s"], brax["env_steps_per_s"]) if ok(brax) else None
        r["wall_vs_model_free"] = _div(r["update_s"], mf["update_s"]) if ok(mf) and r["case"] != "ceiling" else None
        r["wall_vs_mbmf"] = _div(r["update_s"], mbmf["update_s"]) if ok(mbmf) and r.get("arm") == "cd" else None
    for part in ("seeds", "devices"):
        for r in parts.get(part, []):
            if not ok(r):
                continue
            r["s_per_seed_update"] = r["update_s"] / r["seeds"]
            one = find(parts[part], case=r["case"], seeds=1, mesh_devices=r.get("mesh_devices"))
            r["speedup_vs_1"] = _div(r["env_steps_per_s"], one["env_steps_per_s"]) if ok(one) else None
            if part == "devices":
                single = find(parts[part], case=r["case"], seeds=r["seeds"], mesh_devices=1)
                r["speedup_vs_1_device"] = _div(r["env_steps_per_s"], single["env_steps_per_s"]) if ok(single) else None
    env_rows = parts.get("envs", [])
    for r in env_rows:
        if not ok(r):
            continue
        c = find(env_rows, case="ceiling", num_envs=r["num_envs"])
        m = find(env_rows, case="model-free", num_envs=r["num_envs"])
        r["vs_ceiling"] = _div(r["env_steps_per_s"], c["env_steps_per_s"]) if ok(c) else None
        r["wall_vs_model_free"] = _div(r["update_s"], m["update_s"]) if ok(m) and r["case"] != "ceiling" else None
    return results


def targets(results: dict) -> list[dict]:
    """The issue's targets, evaluated on the designated CD row (the default-settings CD row beside it)."""
    parts = results.get("parts", {})
    cmp_rows, seed_rows = parts.get("compare", []), parts.get("seeds", [])
    cd, cd_def = find(cmp_rows, case=DESIGNATED_CD), find(cmp_rows, case="cd-default")
    mf, paper = find(cmp_rows, case="model-free"), find(cmp_rows, case=PAPER_CD)

    def seeds_ratio(case):
        r = find(seed_rows, case=case, seeds=32)
        return r.get("speedup_vs_1") if ok(r) else None

    def seeds_vs_mbmf(case, seeds=10):
        r, m = find(seed_rows, case=case, seeds=seeds), find(seed_rows, case="mbmf", seeds=seeds)
        return _div(r["update_s"], m["update_s"]) if ok(r) and ok(m) else None

    values = {
        "cd_vs_brax": ((cd or {}).get("vs_brax"), (cd_def or {}).get("vs_brax")),
        "mf_vs_brax": ((mf or {}).get("vs_brax"), None),
        "cd_wall_vs_mf": ((cd or {}).get("wall_vs_model_free"), (cd_def or {}).get("wall_vs_model_free")),
        "seeds32_vs_1": (seeds_ratio(DESIGNATED_CD), seeds_ratio("model-free")),
        "cd_compile_s": ((cd or {}).get("compile_s") if ok(cd) else None,
                         (cd_def or {}).get("compile_s") if ok(cd_def) else None),
        "paper_wall_vs_mbmf": ((paper or {}).get("wall_vs_mbmf"), (cd or {}).get("wall_vs_mbmf")),
        "paper_seeds10_vs_mbmf": (seeds_vs_mbmf(PAPER_CD), seeds_vs_mbmf(DESIGNATED_CD)),
    }
    out = []
    for name, (what, op, threshold) in TARGETS.items():
        value, other = values[name]
        met = None
        if _finite(value):
            met = {">=": value >= threshold, "<=": value <= threshold, "<": value < threshold}[op]
        other_label = {"seeds32_vs_1": "model-free", "paper_wall_vs_mbmf": DESIGNATED_CD,
                       "paper_seeds10_vs_mbmf": DESIGNATED_CD}.get(name, "cd-default")
        out.append({"target": name, "what": what, "required": f"{op} {threshold:g}", "value": value,
                    "met": met, "other": other if name != "mf_vs_brax" else None, "other_label": other_label})
    return out


# ---------------------------------------------------------------------------------------------- markdown

def _n(x, digits=0):
    if not _finite(x):
        return "–"
    return f"{x:,.{digits}f}"


def _gib(row):
    b = row.get("mem_bytes")
    if not _finite(b):
        return "–"
    tag = "p" if str(row.get("mem_source", "")).startswith("process") else "c"
    return f"{b / 2**30:.2f} ({tag})"


def _status(row):
    if ok(row):
        return ""
    error = str(row.get("error", "")).replace("|", "/")[:90]
    return f" **{row.get('status', '?')}**" + (f": {error}" if error else "")


def compare_table(rows: list[dict]) -> str:
    lines = ["| case | what | env steps/s | vs ceiling | vs Brax PPO | wall vs model-free | s / update | compile s "
             "| peak GiB |", "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for r in rows:
        name = f"**{r['case']}** (designated CD)" if r["case"] == DESIGNATED_CD else r["case"]
        if not ok(r):
            lines.append(f"| {name} | {r.get('what', '')}{_status(r)} | | | | | | | |")
            continue
        lines.append(f"| {name} | {r.get('what', '')} | {_n(r['env_steps_per_s'])} | {_n(r.get('vs_ceiling'), 2)} | "
                     f"{_n(r.get('vs_brax'), 2)} | {_n(r.get('wall_vs_model_free'), 2)} | {_n(r['update_s'], 3)} | "
                     f"{_n(r.get('compile_s'), 1)} | {_gib(r)} |")
    return "\n".join(lines)


def time_table(rows: list[dict]) -> str:
    """Where the time of one update goes: physics alone, rollout (collect), SGD and the model/consistency extra."""
    ceil, col = find(rows, case="ceiling"), find(rows, case="collect")
    mf, mbmf = find(rows, case="model-free"), find(rows, case="mbmf")
    lines = ["| case | s / update | physics only (ceiling rate) | rollout + GAE (collect) | SGD (update - collect) | "
             "ms / SGD minibatch | + over model-free | + over Mb-Mf |",
             "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for r in rows:
        if r.get("kind") not in ("cdjax", "brax") or not ok(r):
            continue
        steps = r["steps_per_update"]
        physics = steps / ceil["env_steps_per_s"] if ok(ceil) else None
        rollout = col["update_s"] if ok(col) and r["kind"] == "cdjax" else None
        sgd = r["update_s"] - rollout if rollout is not None else None
        over_mf = r["update_s"] - mf["update_s"] if ok(mf) and r["kind"] == "cdjax" else None
        over_mbmf = r["update_s"] - mbmf["update_s"] if ok(mbmf) and r.get("arm") == "cd" else None
        per_mb = 1e3 * sgd / r["sgd_steps"] if sgd is not None and r.get("sgd_steps") else None
        lines.append(f"| {r['case']} | {_n(r['update_s'], 3)} | {_n(physics, 3)} | {_n(rollout, 3)} | {_n(sgd, 3)} | "
                     f"{_n(per_mb, 2)} | {_n(over_mf, 3)} | {_n(over_mbmf, 3)} |")
    return "\n".join(lines)


def diagnose(results: dict) -> list[str]:
    """One line per missed target saying where the time goes, from the measured rows."""
    parts = results.get("parts", {})
    rows = parts.get("compare", [])
    get = {r["case"]: r for r in rows if ok(r)}
    col, mf, mbmf, cd, ceil = (get.get(c) for c in ("collect", "model-free", "mbmf", DESIGNATED_CD, "ceiling"))
    out = []

    def split(r):
        if not col:  # the rollout/SGD split needs the collect case (and the ceiling for the physics)
            return f"{r['case']}: {r['update_s']:.3f} s/update; no split (add the `collect` and `ceiling` cases)"
        sgd = r["update_s"] - col["update_s"]
        return (f"{r['case']}: {r['update_s']:.3f} s/update = rollout+GAE {col['update_s']:.3f} s "
                f"({col['update_s'] / r['update_s']:.0%}) + SGD {sgd:.3f} s ({sgd / r['update_s']:.0%})")

    for t in targets(results):
        if t["met"] is not False:
            continue
        if t["target"] in ("cd_vs_brax", "cd_wall_vs_mf") and cd:
            line = split(cd)
            if mbmf:
                line += f"; the consistency term adds {cd['update_s'] - mbmf['update_s']:.3f} s over Mb-Mf"
            if mbmf and mf:
                line += f", the model NLL {mbmf['update_s'] - mf['update_s']:.3f} s over model-free"
            out.append(f"- {t['target']} missed. {line}.")
        elif t["target"] == "mf_vs_brax" and mf:
            line = split(mf)
            if ceil and col:
                physics = col["steps_per_update"] / ceil["env_steps_per_s"]
                line += f"; physics alone would take {physics:.3f} s of the rollout"
            out.append(f"- {t['target']} missed. {line}.")
        elif t["target"] == "seeds32_vs_1":
            seed_rows = parts.get("seeds", [])
            one, many = find(seed_rows, case=DESIGNATED_CD, seeds=1), find(seed_rows, case=DESIGNATED_CD, seeds=32)
            if ok(one) and ok(many):
                out.append(f"- {t['target']} missed. 1 seed: {one['update_s']:.3f} s/update; 32 seeds: "
                           f"{many['update_s']:.3f} s/update ({many['update_s'] / one['update_s']:.1f}x the time "
                           "for 32x the work): the vmapped update is no longer latency-bound at 32 seeds.")
        elif t["target"] == "paper_wall_vs_mbmf" and get.get(PAPER_CD) and mbmf:
            paper = get[PAPER_CD]
            extra = paper["update_s"] - mbmf["update_s"]
            per_step = 1e3 * extra / paper["sgd_steps"] if paper.get("sgd_steps") else float("nan")
            out.append(f"- {t['target']} missed. {PAPER_CD}: {paper['update_s']:.3f} s/update, "
                       f"{extra:.3f} s over Mb-Mf ({per_step:.2f} ms per SGD minibatch for the consistency term).")
        elif t["target"] == "cd_compile_s" and cd:
            out.append(f"- {t['target']} missed. lower (tracing) {cd.get('lower_s', float('nan')):.1f} s, XLA compile "
                       f"{cd.get('xla_compile_s', float('nan')):.1f} s.")
    return out


def targets_table(results: dict) -> str:
    lines = ["| target | required | measured | verdict | beside it |", "| --- | --- | ---: | --- | --- |"]
    for t in targets(results):
        verdict = {True: "met", False: "**MISSED**", None: "not measured"}[t["met"]]
        other = f"{t['other_label']}: {_n(t['other'], 2)}" if t.get("other") is not None else ""
        lines.append(f"| {t['what']} | {t['required']} | {_n(t['value'], 2)} | {verdict} | {other} |")
    return "\n".join(lines)


def seeds_table(rows: list[dict], devices_part: bool = False) -> str:
    head = "| case | seeds | envs / seed | mesh devices | aggregate env steps/s | speedup vs 1 seed | "
    head += "speedup vs 1 device | " if devices_part else ""
    head += "s / seed-update | s / update (all seeds) | compile s | peak GiB / device | status |"
    lines = [head, "| " + " | ".join(["---"] * (head.count("|") - 1)) + " |"]
    for r in rows:
        cells = [r["case"], str(r.get("seeds")), str(r.get("num_envs")), str(r.get("mesh_devices") or "all")]
        if ok(r):
            cells += [_n(r["env_steps_per_s"]), _n(r.get("speedup_vs_1"), 2)]
            cells += [_n(r.get("speedup_vs_1_device"), 2)] if devices_part else []
            cells += [_n(r.get("s_per_seed_update"), 4), _n(r["update_s"], 3), _n(r.get("compile_s"), 1),
                      _gib(r), "ok"]
        else:
            cells += [""] * (7 if devices_part else 6) + [_status(r).strip()]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def seeds_summary(rows: list[dict], limit_bytes: int | None) -> str:
    """The largest count that ran per case, and the count the compiled memory predicts would fit."""
    out = []
    for case in dict.fromkeys(r["case"] for r in rows):
        mine = [r for r in rows if r["case"] == case]
        ran = [r["seeds"] for r in mine if ok(r)]
        oom = [r["seeds"] for r in mine if r.get("status") == "OOM"]
        text = f"- {case}: largest count that ran: {max(ran) if ran else 'none'}"
        text += f"; first OOM at {min(oom)}" if oom else "; no OOM among the counts tried"
        est = estimate_max_seeds(mine, limit_bytes)
        if est is not None:
            text += f"; compiled memory grows linearly to the device limit at about {est:,} seeds (estimate)"
        out.append(text)
    return "\n".join(out)


def estimate_max_seeds(rows: list[dict], limit_bytes: int | None) -> int | None:
    """Least-squares line through (seeds, compiled bytes) of the rows that ran, solved for the device limit."""
    pts = [(r["seeds"], r["mem_bytes"]) for r in rows if ok(r) and _finite(r.get("mem_bytes"))]
    if not _finite(limit_bytes) or len(pts) < 2:
        return None
    n = len(pts)
    mx, my = sum(p[0] for p in pts) / n, sum(p[1] for p in pts) / n
    sxx = sum((p[0] - mx) ** 2 for p in pts)
    if sxx == 0:
        return None
    slope = sum((p[0] - mx) * (p[1] - my) for p in pts) / sxx
    if slope <= 0:
        return None
    return int((limit_bytes - (my - slope * mx)) / slope)


def envs_table(rows: list[dict]) -> str:
    cases = list(dict.fromkeys(r["case"] for r in rows))
    sizes = sorted({r["num_envs"] for r in rows})
    head = "| num_envs | " + " | ".join(f"{c} env steps/s" for c in cases)
    head += " | " + " | ".join(f"{c} vs ceiling" for c in cases if c != "ceiling")
    head += f" | {DESIGNATED_CD} wall vs model-free |" if DESIGNATED_CD in cases else " |"
    lines = [head, "| " + " | ".join(["---:"] * (head.count("|") - 1)) + " |"]
    for n in sizes:
        cells = [str(n)]
        for c in cases:
            r = find(rows, case=c, num_envs=n)
            cells.append(_n(r["env_steps_per_s"]) if ok(r) else (r or {}).get("status", "–"))
        for c in cases:
            if c != "ceiling":
                r = find(rows, case=c, num_envs=n)
                cells.append(_n(r.get("vs_ceiling"), 2) if ok(r) else "–")
        if DESIGNATED_CD in cases:
            r = find(rows, case=DESIGNATED_CD, num_envs=n)
            cells.append(_n(r.get("wall_vs_model_free"), 2) if ok(r) else "–")
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def meta_lines(meta: dict) -> str:
    d = meta
    s = (f"device: {d.get('device')} x{d.get('device_count')} ({d.get('platform')}), "
         f"jax {d.get('versions', {}).get('jax')}, brax {d.get('versions', {}).get('brax')}, "
         f"mujoco-mjx {d.get('versions', {}).get('mujoco-mjx', d.get('versions', {}).get('mujoco_mjx'))}; "
         f"{d.get('date')}; compilation cache: {d.get('compilation_cache') or 'off'}")
    if d.get("tiny"):
        s += "; **tiny CPU smoke sizes: the numbers mean nothing**"
    return s


def profiles(rows: list[dict], vmapped: bool = False) -> list[str]:
    """The op-level profile of each traced row (`--trace`), headed by what was traced (`vmapped`: rows of the seeds
    suite, one update of all their seeds)."""
    out = []
    for row in rows:
        if row.get("profile_md"):
            what = f"`{row['case']}` update" + (f" of {row['seeds']} vmapped seeds" if vmapped else "")
            out.append(f"\nOp-level profile of one {what} (`--trace`, "
                       f"`python -m benchmarks.profile_summary {row.get('trace_dir', 'DIR')}`):\n")
            out.append(row["profile_md"].rstrip("\n"))
    return out


def markdown(results: dict) -> str:
    """All tables of the parts present; the targets table (short) comes last."""
    add_ratios(results)
    parts, metas, pm = results.get("parts", {}), results.get("metas", []), results.get("part_meta", {})
    out = []
    for part in PARTS:
        if part not in parts:
            continue
        meta = metas[pm[part]] if part in pm and pm[part] < len(metas) else {}
        spec = meta.get("spec", {})
        out.append(f"### {part}\n\n{meta_lines(meta)}\n\n`{meta.get('command', '')}`\n")
        if part == "compare":
            if spec:
                out.append(f"{spec['env']}, {spec['num_envs']} envs, {spec['rollout_len']} steps/env/update (= "
                           f"{spec['unrolls_per_env']} Brax unrolls of {spec['unroll_length']}), "
                           f"{spec['env_steps_per_update']:,} env steps/update, {spec['num_epochs']} epochs x "
                           f"{spec['num_minibatches']} minibatches of {spec['samples_per_minibatch']:,} samples, "
                           f"policy {tuple(spec['policy_hidden'])}, value {tuple(spec['value_hidden'])}, "
                           f"k = {spec['horizon']}.")
            out.append("Peak GiB: (c) XLA's compiled footprint of the timed call, (p) process peak measured with "
                       "Brax run first in the process.\n")
            out.append(compare_table(parts[part]))
            out.append("\nWhere the time of one update goes (seconds):\n")
            out.append(time_table(parts[part]))
            out.extend(profiles(parts[part]))
        elif part == "seeds":
            seed_spec = meta.get("seed_spec", spec)
            out.append(f"Per seed: {seed_spec.get('num_envs')} envs, {seed_spec.get('rollout_len')} steps/env/update, "
                       f"{seed_spec.get('num_epochs')} x {seed_spec.get('num_minibatches')} minibatches; runs vmapped "
                       f"and sharded over {meta.get('device_count')} device(s).\n")
            out.append(seeds_table(parts[part]))
            out.append("\n" + seeds_summary(parts[part], meta.get("bytes_limit")))
            out.extend(profiles(parts[part], vmapped=True))
        elif part == "devices":
            out.append("The same sweep on a 1-device mesh and on all devices.\n")
            out.append(seeds_table(parts[part], devices_part=True))
        elif part == "envs":
            out.append("One seed; rollout length and SGD schedule as in compare (batch_size scales with num_envs).\n")
            out.append(envs_table(parts[part]))
        out.append("")
    if "compare" in parts or "seeds" in parts:
        out.append("### targets\n")
        out.append(targets_table(results))
        notes = diagnose(results)
        if notes:
            out.append("\nWhere the time goes for the missed targets (see the tables above; `--trace` for op level):\n")
            out.extend(notes)
    return "\n".join(out).rstrip() + "\n"


# ---------------------------------------------------------------------------------------------- plot

def _scaling_axis(ax, rows: list[dict], x: str, xlabel: str, ylabel: str, title: str, linear: bool = False) -> None:
    """Env steps/s against `x` per case on log-log axes; `linear`: a dotted line of perfect scaling from x = 1."""
    for case in dict.fromkeys(r["case"] for r in rows):
        pts = sorted((r[x], r["env_steps_per_s"]) for r in rows if r["case"] == case)
        line, = ax.plot(*zip(*pts), "o-", label=case, color=COLORS.get(case))
        if linear and pts[0][0] == 1:
            ax.plot([p[0] for p in pts], [pts[0][1] * p[0] for p in pts], ":", color=line.get_color(), alpha=0.6)
    if not rows:
        ax.text(0.5, 0.5, f"{'seeds' if x == 'seeds' else 'envs'}: not run", ha="center")
        return
    ax.set_xscale("log", base=2)
    ax.set_yscale("log")
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.legend()


def plot(results: dict, path: str | pathlib.Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    add_ratios(results)
    parts = results.get("parts", {})
    fig, axes = plt.subplots(1, 3, figsize=(17, 4.8))
    ax = axes[0]
    rows = [r for r in parts.get("compare", []) if ok(r)]
    if rows:
        ax.barh([r["case"] for r in rows][::-1], [r["env_steps_per_s"] for r in rows][::-1],
                color=[COLORS.get(r["case"], "tab:blue") for r in rows][::-1])
        ax.set_xscale("log")
        ax.set_xlabel("env steps / s")
        ax.set_title("matched config, one seed")
    else:
        ax.text(0.5, 0.5, "compare: not run", ha="center")
    _scaling_axis(axes[1], [r for r in parts.get("seeds", []) if ok(r)], "seeds", "vmapped seeds",
                  "aggregate env steps / s", "seed scaling (dotted: linear)", linear=True)
    _scaling_axis(axes[2], [r for r in parts.get("envs", []) if ok(r)], "num_envs", "num_envs (one seed)",
                  "env steps / s", "num_envs scaling")
    metas = results.get("metas", [])
    if metas:
        tiny = " (tiny CPU smoke)" if metas[0].get("tiny") else ""
        fig.suptitle(f"cdjax benchmarks on {metas[0].get('device')}{tiny}")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


# ---------------------------------------------------------------------------------------------- files

def merge(results_list: list[dict]) -> dict:
    """Join several results. `compare` comes whole from the last run that has it (its ratios need one
    process). The scaling parts (seeds, envs, devices) take the rows of every run, so that e.g.
    `--suite seeds --scaling-cases cd-fast` and `... model-free` may run as two commands; a row measured
    twice (same case, seeds, num_envs and mesh) keeps the later measurement."""
    out = {"metas": [], "part_meta": {}, "parts": {}}
    for res in results_list:
        offset = len(out["metas"])
        out["metas"].extend(res.get("metas", []))
        for part, rows in res.get("parts", {}).items():
            index = res.get("part_meta", {}).get(part, 0) + offset
            if part == "compare" or part not in out["parts"]:
                out["parts"][part] = list(rows)
                out["part_meta"][part] = index
                continue
            # A skipped row carries no seed count or mesh: those default to 1, so a later measurement replaces it.
            key = lambda r: (r.get("case"), r.get("seeds") or 1, r.get("num_envs"), r.get("mesh_devices") or 1)  # noqa: E731
            new_keys = {key(r) for r in rows}
            out["parts"][part] = [r for r in out["parts"][part] if key(r) not in new_keys] + list(rows)
    return out


def load(path: str | pathlib.Path) -> dict:
    """The results of a run (its --out directory or its results.json); ValueError, one sentence, when there are none."""
    p = pathlib.Path(path)
    if p.is_dir():
        p = p / "results.json"
        if not p.is_file():
            raise ValueError(f"{path} holds no results.json (name a directory of `python -m benchmarks.run --out`)")
    elif not p.is_file():
        raise ValueError(f"{path} does not exist")
    try:
        results = json.loads(p.read_text())
    except (UnicodeDecodeError, json.JSONDecodeError) as err:
        raise ValueError(f"{p} is not a results.json ({getattr(err, 'msg', None) or err.reason})") from None
    if not isinstance(results, dict) or not isinstance(results.get("parts"), dict):
        raise ValueError(f"{p} is not a results.json (it has no \"parts\")")
    return results


def write_out(results: dict, out_dir: str | pathlib.Path) -> str:
    """results.json, results.md and results.png into out_dir; returns the markdown."""
    out = pathlib.Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    md = markdown(results)
    (out / "results.json").write_text(json.dumps(results, indent=1, default=str))
    (out / "results.md").write_text(md)
    plot(results, out / "results.png")
    return md


def write_results_md(results: dict, path: str | pathlib.Path, command: str) -> None:
    """benchmarks/RESULTS.md: device(s), the exact commands, date, the tables, the targets and the plot."""
    path = pathlib.Path(path)
    png = path.with_suffix(".png")
    plot(results, png)
    metas = results.get("metas", [])
    devices = sorted({f"{m.get('device')} x{m.get('device_count')}" for m in metas})
    import datetime

    lines = ["# cdjax benchmark results", "",
             f"Device(s): {', '.join(devices)}. Generated {datetime.date.today().isoformat()}. How to run and what "
             "every number means: `benchmarks/README.md`.", "",
             "Commands (one process per suite, each timed in its own process):", ""]
    for m in metas:
        lines.append(f"- {m.get('date')}, {m.get('device')} x{m.get('device_count')}: `{m.get('command')}`")
    lines += ["", f"This file: `{command}`", "", markdown(results), "", f"![throughput and scaling]({png.name})", ""]
    notes = path.with_name("analysis.md")  # hand-written reading of the numbers, kept across regenerations
    if notes.exists():
        lines += ["## Reading the numbers", "", notes.read_text().strip(), ""]
    path.write_text("\n".join(lines))
