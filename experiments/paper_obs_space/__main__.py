"""python -m experiments.paper_obs_space {list,run,train,keep,report} (see the package docstring)."""

from __future__ import annotations

import argparse
import datetime
import json
import os
import pathlib
import platform
import sys
import time

from cdjax import options
from cdjax.cli import Parser, UsageError
from experiments.paper_obs_space import TASKS, UNITS

HERE = pathlib.Path(__file__).resolve().parent
PROG = "python -m experiments.paper_obs_space"
UNIT_LIMIT_S = 1260  # a unit's sweeps (compile, phases, training) stop by then; its evaluations and packing follow


def machine_record(wall_s: float, exit_code: int) -> dict:
    import importlib.metadata as md

    import jax

    def version(name):
        try:
            return md.version(name)
        except md.PackageNotFoundError:
            return "?"

    devices = jax.devices()
    kinds = sorted({d.device_kind for d in devices})
    return {"device": f"{', '.join(kinds)} x{len(devices)} ({devices[0].platform})", "jax": jax.__version__,
            "brax": version("brax"), "mujoco_mjx": version("mujoco-mjx"), "python": platform.python_version(),
            "date": datetime.date.today().isoformat(), "wall_s": round(wall_s, 1), "exit_code": exit_code}


def yardstick_option(task: str, passthrough: list[str]) -> list[str]:
    """--yardstick <the task's file>, unless the command line sets one or another env (a small try on the point
    mass, say): given relative to the working directory, as run.json records it."""
    if any(a in ("--yardstick", "--env") or a.startswith(("--yardstick=", "--env=")) for a in passthrough):
        return []
    path = HERE / "yardstick" / f"{task}.npz"
    return ["--yardstick", os.path.relpath(path)] if path.exists() else []


def sweep_argv(task: str, out: pathlib.Path, args: list[str]) -> list[str]:
    """The command line of `sweep`: `cdjax` plus these."""
    return ["sweep", "--preset", f"paper-{task}", "--out", str(out), *yardstick_option(task, args), *args]


def sweep(task: str, out: pathlib.Path, args: list[str]) -> int:
    """`cdjax sweep --preset paper-<task>` with `args`, into `out`, plus out/machine.json; the exit status."""
    from cdjax.cli import main as cdjax_main

    argv = sweep_argv(task, out, args)
    t0 = time.perf_counter()
    code = 0
    try:
        cdjax_main(argv)
    except SystemExit as stop:  # 75: stopped by --time-limit, 130: interrupted; the run keeps its logs
        code = int(stop.code or 0)
    if (out / "run.json").exists():
        (out / "machine.json").write_text(json.dumps(machine_record(time.perf_counter() - t0, code), indent=1))
    return code


def cmd_train(args, passthrough: list[str]) -> int:
    return sweep(args.task, pathlib.Path(args.out or f"runs/paper/{args.task}"), passthrough)


def cmd_run(args, passthrough: list[str]) -> int:
    unit = UNITS[args.unit]
    out = pathlib.Path(args.out or f"runs/units/{unit.name}")
    out.mkdir(parents=True, exist_ok=True)
    start = time.monotonic()
    limit = args.time_limit
    record = {"unit": unit.name, "task": unit.task, "limit_s": limit, "started": datetime.datetime.now().isoformat(
        timespec="seconds"), "estimate_s": round(unit.estimate()["total"]), "parts": []}
    estimates = unit.estimate()["parts"]
    code = 0
    for i, part in enumerate(unit.parts):
        later = sum(estimates[p.name]["total"] for p in unit.parts[i + 1:])
        left = limit - (time.monotonic() - start) - later
        if left < 120:
            record["parts"].append({"name": part.name, "skipped": f"{left:.0f} s left"})
            code = code or 75
            continue
        # the report recomputes every statistic: the sweep's own plots need few bootstrap replications; nothing
        # outlives the lease, so checkpoints only serve a resume inside it
        options = ["--arms", *part.arms, "--seeds", str(part.seeds), "--steps", str(unit.budget.steps),
                   "--no-progress", "--bootstrap-reps", "200", "--checkpoint-every", "5",
                   "--time-limit", str(int(left)), *part.options, *passthrough]
        t0 = time.monotonic()
        status = sweep(unit.task, out / part.name, options)
        record["parts"].append({"name": part.name, "command": "cdjax " + " ".join(sweep_argv(unit.task, out / part.name,
                                                                                          options)),
                                "exit_code": status, "wall_s": round(time.monotonic() - t0, 1)})
        code = code or status
        (out / "unit.json").write_text(json.dumps(record, indent=1))
    record["wall_s"] = round(time.monotonic() - start, 1)
    (out / "unit.json").write_text(json.dumps(record, indent=1))
    return code


def cmd_list(args) -> int:
    print("| unit | task | parts (arms x seeds) | runs | env steps per run | estimated wall-clock |")
    print("|---|---|---|---|---|---|")
    for unit in UNITS.values():
        est = unit.estimate()
        parts = "; ".join(f"{p.name}: {' '.join(p.arms)}{' x2 weights' if p.runs_per_arm > 1 else ''} x {p.seeds}"
                          for p in unit.parts)
        runs = sum(p.runs for p in unit.parts)
        flag = " (provisional)" if unit.budget.provisional else ""
        print(f"| {unit.name} | {unit.task} | {parts} | {runs} | {unit.budget.steps / 1e6:g}M{flag} | "
              f"{est['total'] / 60:.1f} min |")
    return 0


def cmd_keep(args) -> int:
    """Copy what the report needs of the run directories under PATHS (a unit unpacked) into data/<unit>/<part>/."""
    from experiments.paper_obs_space import report

    found = report.find_runs(args.paths)
    if not found:
        print(f"No run directory under {', '.join(map(str, args.paths))}.", file=sys.stderr)
        return 2
    for path in found:
        target = report.keep_run(report.load_run(path), pathlib.Path(args.data))
        print(f"{path} -> {target}")
    return 0


def cmd_report(args) -> int:
    from experiments.paper_obs_space import report

    missing = [str(path) for path in args.runs if not path.is_dir()]
    if missing:  # (else the report would say that no unit has run yet)
        print(f"{PROG} report: --runs {', '.join(missing)}: no such directory (give directories that hold run "
              "directories, e.g. experiments/paper_obs_space/data)", file=sys.stderr)
        return 2
    if args.paired is not None and not (args.paired / "summary.json").is_file():
        print(f"python -m experiments.paper_obs_space report: {args.paired} has no summary.json (give the data "
              "directory of another report, e.g. experiments/paper_obs_space/data)", file=sys.stderr)
        return 2
    unknown = sorted(set(args.arms or ()) - set(report.LABELS))
    if unknown:
        print(f"python -m experiments.paper_obs_space report: no arm {', '.join(unknown)} (the arms: "
              f"{', '.join(report.LABELS)})", file=sys.stderr)
        return 2
    tasks = report.load(args.runs, arms=args.arms)
    path = report.write_results(tasks, pathlib.Path(args.out), reps=args.reps, keep=args.keep, paired=args.paired,
                                sources=args.runs)
    print(f"Wrote {path}")
    return 0


def main(argv=None) -> int:
    """The command; its exit status (2 and one sentence on stderr for arguments it cannot take)."""
    try:
        args, rest = parse(argv)
    except UsageError as err:
        print(f"{PROG}: {err}", file=sys.stderr)
        return 2
    if args.command in ("run", "train"):
        return {"run": cmd_run, "train": cmd_train}[args.command](args, rest)
    return {"list": cmd_list, "keep": cmd_keep, "report": cmd_report}[args.command](args)


def parse(argv) -> tuple[argparse.Namespace, list[str]]:
    """(arguments, the options `run` and `train` pass on to cdjax sweep); UsageError (one sentence) for what cannot
    run."""
    p = Parser(prog=PROG, description=__doc__)
    sub = p.add_subparsers(dest="command", required=True)
    u = sub.add_parser("list", help="the units of the experiment, their budgets and estimated wall-clock")
    n = sub.add_parser("run", help="one unit; other options go to cdjax sweep")
    n.add_argument("unit", choices=list(UNITS), metavar="UNIT")
    n.add_argument("--out", help="the unit's directory (default runs/units/<unit>)")
    n.add_argument("--time-limit", type=options.seconds, default=UNIT_LIMIT_S, metavar="SECONDS",
                   help=f"seconds the unit's sweeps may take in all (default {UNIT_LIMIT_S})")
    t = sub.add_parser("train", help="one task's preset as it stands, in one sweep; other options go to cdjax sweep")
    t.add_argument("--task", choices=TASKS, required=True, help="the preset's arms in one sweep")
    t.add_argument("--out", help="the run directory (default runs/paper/<task>)")
    k = sub.add_parser("keep", help="add a unit's run directories (its directory, or its UNIT.tar.gz unpacked) "
                                    "to data/")
    k.add_argument("paths", nargs="+", type=pathlib.Path)
    k.add_argument("--data", default=str(HERE / "data"))
    r = sub.add_parser("report", help="RESULTS.md, figures and tables from the kept data (or run directories)")
    r.add_argument("--runs", nargs="+", type=pathlib.Path, default=[HERE / "data"],
                   help="directories searched for run directories (run.json); default the kept data")
    r.add_argument("--out", default=str(HERE))
    r.add_argument("--reps", type=options.positive, default=2000, help="bootstrap replications (default 2000)")
    r.add_argument("--keep", action="store_true", help="also copy the runs' data (thinned) into OUT/data/")
    r.add_argument("--paired", type=pathlib.Path, metavar="DATA",
                   help="another report's data directory (its summary.json): set this data's final returns beside "
                        "its, seed by seed (e.g. the same units at another setting)")
    r.add_argument("--arms", nargs="+", metavar="ARM",
                   help="only these arms (the report's arm keys, e.g. mbmf cd-k20); default every arm found")
    args, rest = p.parse_known_args(argv)
    if args.command not in ("run", "train") and rest:
        {"list": u, "keep": k, "report": r}[args.command].error(f"unknown option(s): {' '.join(rest)}")
    return args, rest


if __name__ == "__main__":
    raise SystemExit(main())
