"""Compile time of a sweep, cold and then again in the same process.

    python -m benchmarks.compile_time --out DIR [--cache-dir EMPTY_DIR] -- --env ant --arms model-free mbmf cd-k5 cd

runs `cdjax sweep OPTIONS --out DIR/1` in this process up to the moment its training would start (the sweep stops
there, checkpointed, through its `after_chunk`), then the same sweep into DIR/2, and prints for each the seconds
from the call of `run_sweep` to that moment: planning, building, tracing, compiling, initialising and restoring.
With an empty --cache-dir (JAX's persistent compilation cache) the first is a cold start; the second shows what
this process's own cache of trainers and compiled programs saves. The runner's own line ("setup .. s, compile .. s")
is printed too, and each program's lowering (serial, in the calling thread) and compiling (in parallel threads) seconds.
Results: DIR/compile_time.json.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys
import time

if __package__ in (None, ""):
    sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))


def main(argv=None) -> list[dict]:
    argv = list(sys.argv[1:] if argv is None else argv)
    sweep_args = argv[argv.index("--") + 1:] if "--" in argv else []
    own = argv[:argv.index("--")] if "--" in argv else argv
    p = argparse.ArgumentParser(prog="python -m benchmarks.compile_time", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", required=True, help="directory of the two run directories and compile_time.json")
    p.add_argument("--cache-dir", help="JAX's persistent compilation cache (an empty directory: a cold start)")
    args = p.parse_args(own)

    from cdjax import runtime
    from cdjax.cli import build_parser, setting_of, sweep_spec
    from cdjax.runner import Interrupted, arms, run_sweep

    if args.cache_dir:
        runtime.configure(cache_dir=args.cache_dir)
    rows = []
    for i in (1, 2):
        sweep_argv = ["sweep", *sweep_args, "--out", str(pathlib.Path(args.out) / str(i)), "--no-progress",
                      "--no-final-eval"]
        setting = setting_of(sweep_argv)
        spec = sweep_spec(build_parser(setting).parse_args(sweep_argv), setting, "cdjax " + " ".join(sweep_argv))
        arms.COMPILE_TIMES.clear()
        t0 = time.perf_counter()
        started = {}

        def stop(rounds, updates, started=started, t0=t0):
            started.setdefault("s", time.perf_counter() - t0)
            return True

        try:
            run_sweep(spec, after_chunk=stop)
        except Interrupted:
            pass
        programs = [dict(r, s=round(r["s"], 2)) for r in arms.COMPILE_TIMES]
        rows.append({"sweep": i, "seconds_to_training": round(started["s"], 2),
                     "command": "cdjax " + " ".join(sweep_argv), "programs": programs})
        print(f"sweep {i}: training would start {started['s']:.1f} s after run_sweep was called", flush=True)
        for r in sorted(programs, key=lambda r: -r["s"]):
            print(f"  {r['arm']:>12} {r['what']:<6} {r['step']:<8} {r['s']:7.2f} s", flush=True)
    pathlib.Path(args.out).mkdir(parents=True, exist_ok=True)
    (pathlib.Path(args.out) / "compile_time.json").write_text(json.dumps(rows, indent=1))
    return rows


if __name__ == "__main__":
    main()
