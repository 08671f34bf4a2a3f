"""Compile time of a sweep, cold and then again in the same process.

    python -m benchmarks.compile_time --out DIR [--cache-dir EMPTY_DIR] -- --env ant --arms model-free mbmf cd-k5 cd

runs `cdjax sweep OPTIONS --out DIR/1` in this process up to the moment its training would start (the sweep stops
there, checkpointed, through its `after_chunk`), then the same sweep into DIR/2, and prints for each the seconds
from the call of `run_sweep` to that moment: planning, building, tracing, compiling, initialising and restoring.
With an empty --cache-dir (JAX's persistent compilation cache) the first is a cold start; the second shows what
this process's own cache of trainers and compiled programs saves. The runner's own line ("setup .. s, compile .. s")
is printed too, each program's lowering (serial, in the calling thread) and compiling (in parallel threads) seconds
and when each ended (seconds after the call: the critical path is the last lowering's end plus its compile),
and the host's steps around them (planning, building the trainers, the memory checks before and after compiling).
Results: DIR/compile_time.json.

    python -m benchmarks.compile_time --lower-only --out DIR -- --env ant --arms model-free mbmf cd-k5 cd --num-envs 16

traces and lowers every program of the sweep without compiling any (so it runs on a CPU in a minute, and the
device does not matter) and prints, per program, its lowering seconds, when it was lowered (seconds after the
sweep was called) and the size of its StableHLO: operations
in all and the most frequent ones, and its matrix products' distinct signatures (with how many of them repeat in
another program of the sweep: each program's GEMMs are autotuned as it compiles). What a program holds is a proxy for its compile time on any backend; compare
variants of a config (e.g. `--cc-epochs 0`) to see what a feature adds. Results: DIR/lowered.json.

`--first-chunk-alone` holds the other arms' chunks back until the first arm's chunk is compiled: with it and without
(each cold) it shows whether the chunks, compiling side by side, each autotune the kernels they share. On one H100
of 16 cores (2026-11-27, benchmarks/results/2026-11-27-h100-compile-sched/) the later chunks then compiled in 26-35 s
instead of 37-50 s, but the sweep reached training 18-20 s later: the runner keeps compiling them side by side.

`CDJAX_COMPILE_WORKERS=N` (read by the runner) sets how many threads compile the programs at once (default: half
the CPU cores); 1 compiles them one after the other, which shows each program's compile time alone.
"""

from __future__ import annotations

import argparse
import collections
import contextlib
import json
import pathlib
import re
import sys
import time

if __package__ in (None, ""):
    sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))

from benchmarks.common import Parser, refuse  # noqa: E402

PROG = "python -m benchmarks.compile_time"


def main(argv=None) -> list[dict]:
    argv = list(sys.argv[1:] if argv is None else argv)
    sweep_args = argv[argv.index("--") + 1:] if "--" in argv else []
    own = argv[:argv.index("--")] if "--" in argv else argv
    p = Parser(prog=PROG, description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", required=True, help="directory of the two run directories and compile_time.json")
    p.add_argument("--cache-dir", help="JAX's persistent compilation cache (an empty directory: a cold start)")
    p.add_argument("--lower-only", action="store_true",
                   help="lower every program without compiling it and print what each holds (any device)")
    p.add_argument("--first-chunk-alone", action="store_true",
                   help="the other arms' chunk programs start compiling only once the first arm's chunk is compiled "
                        "(an experiment: whether the chunks, compiling side by side, autotune the kernels they share "
                        "each anew; XLA keeps the autotuner's results for the rest of the process)")
    args = p.parse_args(own)
    from cdjax import io
    from cdjax.cli import UsageError
    from cdjax.protocol import ConfigError

    out = pathlib.Path(args.out)
    try:  # the --out and the sweep's options checked before anything is built; the sweep's own refusals likewise
        io.RunDir(out).check_writable()
        _spec(sweep_args, out / ("lowered-run" if args.lower_only else "1"))
        if args.lower_only:
            return lower_only(sweep_args, out)
        if args.first_chunk_alone:
            with first_chunk_alone():
                return measure(args, sweep_args)
        return measure(args, sweep_args)
    except (UsageError, ConfigError, io.RunDirError) as err:
        refuse(PROG, str(err).replace("`cdjax --help`", "`cdjax sweep --help`"))


def measure(args, sweep_args: list[str]) -> list[dict]:
    """The sweep run twice in this process up to its training; the rows of compile_time.json."""
    from cdjax import runtime
    from cdjax.runner import Interrupted, arms, run_sweep

    if args.cache_dir:
        runtime.configure(cache_dir=args.cache_dir, cache_source="--cache-dir")
    rows = []
    for i in (1, 2):
        spec, sweep_argv = _spec(sweep_args, pathlib.Path(args.out) / str(i))
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
        # "end": when the step ended, in seconds after run_sweep was called (the critical path: the last program's
        # lowering ends, then its compile)
        programs = [dict(r, s=round(r["s"], 2), end=round(r["end"] - t0, 2)) for r in arms.COMPILE_TIMES
                    if r["step"] != "host"]
        host = {r["what"]: round(r["s"], 2) for r in arms.COMPILE_TIMES if r["step"] == "host"}
        # the compile time depends on the host's cores (XLA:GPU compiles each program on many threads): say them
        cores, workers = arms.usable_cores(), arms.compile_workers()
        rows.append({"sweep": i, "seconds_to_training": round(started["s"], 2),
                     "command": "cdjax " + " ".join(sweep_argv), "cores": cores, "compile_workers": workers,
                     "first_chunk_alone": bool(args.first_chunk_alone),
                     "host": host, "programs": programs})
        print(f"sweep {i}: training would start {started['s']:.1f} s after run_sweep was called ({cores} CPU cores, "
              f"{workers} compiling threads); on the host before and after compiling: "
              + ", ".join(f"{k} {v:.1f} s" for k, v in host.items()), flush=True)
        for r in sorted(programs, key=lambda r: r["end"]):
            print(f"  {r['arm']:>12} {r['what']:<6} {r['step']:<8} {r['s']:7.2f} s, ended at {r['end']:6.1f} s",
                  flush=True)
    pathlib.Path(args.out).mkdir(parents=True, exist_ok=True)
    (pathlib.Path(args.out) / "compile_time.json").write_text(json.dumps(rows, indent=1))
    return rows


@contextlib.contextmanager
def first_chunk_alone():
    """The runner's compiling (cdjax.runner.arms._compiled) with every chunk after the first arm's compiling only
    once that one is compiled (its job waits in its compiling thread); the inits and resets as always."""
    from cdjax.runner import arms

    original, first = arms._compiled, []

    def compiled(arm, what, lower, *args, pool=None, owner=None):
        if pool is None or what != "chunk":
            return original(arm, what, lower, *args, pool=pool, owner=owner)
        if not first:
            first.append(original(arm, what, lower, *args, pool=pool, owner=owner))
            return first[0]
        gate = first[0]

        class AfterFirst:
            def submit(self, fn):
                return pool.submit(lambda: (gate.result() if hasattr(gate, "result") else None, fn())[1])

        return original(arm, what, lower, *args, pool=AfterFirst(), owner=owner)

    arms._compiled = compiled
    try:
        yield
    finally:
        arms._compiled = original


def _spec(sweep_args: list[str], out: pathlib.Path):
    """The SweepSpec of `cdjax sweep SWEEP_ARGS --out OUT` (no progress bar, no final evaluation), and that argv."""
    from cdjax.cli import build_parser, setting_of, sweep_spec

    sweep_argv = ["sweep", *sweep_args, "--out", str(out), "--no-progress", "--no-final-eval"]
    setting = setting_of(sweep_argv)
    return sweep_spec(build_parser(setting).parse_args(sweep_argv), setting, "cdjax " + " ".join(sweep_argv)), sweep_argv


class _Lowered(Exception):
    """Raised in place of compiling: the sweep stops once its programs are lowered."""


_OP = re.compile(r"= \"?((?:stablehlo|chlo|mhlo|sdy|func|call)\.[a-z_]+)")  # an operation's name, not an attribute


# a matrix product's operand and result types: `stablehlo.dot_general %a, %b, ... : (tensor<..>, tensor<..>) -> tensor<..>`
_DOT = re.compile(r"stablehlo\.dot_general[^\n]*?:\s*\((tensor<[^>]*>), (tensor<[^>]*>)\) -> (tensor<[^>]*>)")


def dot_signatures(text: str) -> set[str]:
    """The distinct operand and result types of a StableHLO text's matrix products (what XLA:GPU autotunes a GEMM
    for, before fusion adds its epilogues)."""
    return {" x ".join(m.groups()) for m in _DOT.finditer(text)}


def program_size(text: str) -> dict:
    """What a lowered program's StableHLO text holds: its characters, operations in all, the six most frequent, and
    its matrix products' distinct signatures (`dot_signatures`)."""
    ops = collections.Counter(_OP.findall(text))
    return {"chars": len(text), "ops": sum(ops.values()), "top": dict(ops.most_common(6)),
            "dot_signatures": sorted(dot_signatures(text))}


def lower_only(sweep_args: list[str], out: pathlib.Path) -> list[dict]:
    """Run the sweep up to compiling: every program is traced and lowered (the runner's own path), none compiled."""
    import jax

    from cdjax.runner import arms, run_sweep

    sizes = []
    compile_ = jax.stages.Lowered.compile

    def record(lowered, *args, **kwargs):
        sizes.append(program_size(lowered.as_text()))
        raise _Lowered

    spec, sweep_argv = _spec(sweep_args, out / "lowered-run")
    arms.COMPILE_TIMES.clear()
    jax.stages.Lowered.compile = record
    t0 = time.perf_counter()
    try:
        run_sweep(spec)
    except _Lowered:
        pass
    finally:
        jax.stages.Lowered.compile = compile_
    lowered = [r for r in arms.COMPILE_TIMES if r["step"] == "lower"]
    rows = [{"arm": r["arm"], "what": r["what"], "lower_s": round(r["s"], 2), "lowered_at": round(r["end"] - t0, 2),
             **size} for r, size in zip(lowered, sizes)]
    for r in rows:
        top = ", ".join(f"{k.split('.')[-1]} {v}" for k, v in r["top"].items())
        print(f"{r['arm']:>12} {r['what']:<6} lowered in {r['lower_s']:5.1f} s (at {r['lowered_at']:5.1f} s): "
              f"{r['ops']:7,d} ops ({top})", flush=True)
    dots = [set(r["dot_signatures"]) for r in rows]
    shared = {"summed": sum(len(d) for d in dots), "distinct": len(set().union(*dots))}
    print(f"matrix product signatures: {shared['summed']} distinct per program, summed over the programs; "
          f"{shared['distinct']} distinct across them (the rest repeat in another program)", flush=True)
    out.mkdir(parents=True, exist_ok=True)
    (out / "lowered.json").write_text(json.dumps({"command": "cdjax " + " ".join(sweep_argv), "programs": rows,
                                                  "dot_signatures": shared}, indent=1))
    return rows


if __name__ == "__main__":
    main()
