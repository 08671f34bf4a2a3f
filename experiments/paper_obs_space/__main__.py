"""python -m experiments.paper_obs_space {train,figure,report} (see the package docstring)."""

from __future__ import annotations

import argparse
import datetime
import json
import pathlib
import platform
import sys
import time

from experiments.paper_obs_space import ABLATION_TASKS, ARMS, TASKS

HERE = pathlib.Path(__file__).resolve().parent


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


def cmd_train(args, passthrough: list[str]) -> int:
    from cdjax.cli import main as cdjax_main

    out = pathlib.Path(args.out or f"runs/paper/{args.task}")
    argv = ["sweep", "--preset", f"paper-{args.task}", "--out", str(out), *passthrough]
    t0 = time.perf_counter()
    code = 0
    try:
        cdjax_main(argv)
    except SystemExit as stop:  # 130: interrupted (e.g. `timeout -s INT`), the run keeps its logs
        code = int(stop.code or 0)
    if (out / "run.json").exists():
        (out / "machine.json").write_text(json.dumps(machine_record(time.perf_counter() - t0, code), indent=1))
    return code


def cmd_figure(args) -> int:
    from experiments.paper_obs_space import report

    tasks = report.load_tasks(args.runs, ABLATION_TASKS if args.which == "k-ablation" else TASKS)
    if not tasks:
        print(f"No task run found under {', '.join(map(str, args.runs))}.", file=sys.stderr)
        return 2
    arms = ARMS if args.which == "k-ablation" else ("mbmf", "cd-k20")
    name = "k_ablation.png" if args.which == "k-ablation" else "returns.png"
    png, data = report.figure(tasks, arms, pathlib.Path(args.out) / name)
    print(f"Wrote {png} and {data}")
    return 0


def cmd_report(args) -> int:
    from experiments.paper_obs_space import report

    tasks = report.load_tasks(args.runs)
    if not tasks:
        print(f"No task run found under {', '.join(map(str, args.runs))}.", file=sys.stderr)
        return 2
    path = report.write_results(tasks, pathlib.Path(args.out), reps=args.reps)
    print(f"Wrote {path}")
    return 0


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m experiments.paper_obs_space", description=__doc__)
    sub = p.add_subparsers(dest="command", required=True)
    t = sub.add_parser("train", help="one task, arms model-free/mbmf/cd-k5/cd-k20 (other options go to cdjax sweep)")
    t.add_argument("--task", required=True, choices=TASKS)
    t.add_argument("--out", help="run directory (default runs/paper/<task>)")
    runs_help = "directories holding <task>/ run dirs or kept data; per task the first that has it wins"
    f = sub.add_parser("figure", help="one figure of the paper from the runs")
    f.add_argument("which", choices=("returns", "k-ablation"))
    f.add_argument("--runs", nargs="+", type=pathlib.Path, default=[pathlib.Path("runs/paper")], help=runs_help)
    f.add_argument("--out", default=str(HERE / "figures"))
    r = sub.add_parser("report", help="both figures, tables, kept data and RESULTS.md")
    r.add_argument("--runs", nargs="+", type=pathlib.Path, default=[pathlib.Path("runs/paper"), HERE / "data"],
                   help=runs_help)
    r.add_argument("--out", default=str(HERE))
    r.add_argument("--reps", type=int, default=2000, help="bootstrap replications")
    args, rest = p.parse_known_args(argv)
    if args.command == "train":
        return cmd_train(args, rest)
    if rest:
        p.error(f"unknown option(s): {' '.join(rest)}")
    return cmd_figure(args) if args.command == "figure" else cmd_report(args)


if __name__ == "__main__":
    raise SystemExit(main())
