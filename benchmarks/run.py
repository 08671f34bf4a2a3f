"""cdjax benchmarks: one command, all cases of a suite measured in this one process.

    python -m benchmarks.run --suite compare    # ceiling, Brax PPO, cdjax arms at the matched config
    python -m benchmarks.run --suite seeds      # 1/8/32/128 vmapped seeds (sharded over all local devices)
    python -m benchmarks.run --suite envs       # num_envs 512..8192, one seed
    python -m benchmarks.run --suite devices    # a sweep on 1 device vs all devices (multi-GPU hosts)
    python -m benchmarks.run --tiny --suite all # CPU smoke test of every part (CI)
    python -m benchmarks.run --suite seeds --distributed   # one process per host (SLURM: srun); the sweep spans all
    python -m benchmarks.run --merge DIR [DIR ...] --write-results benchmarks/RESULTS.md   # no device needed

Each suite writes results.json / results.md / results.png into --out (default
benchmarks/results/<date>-<device>-<suite>; the JSON is rewritten after every case, so a killed run
keeps what it measured) and prints the markdown last. See benchmarks/README.md.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import os
import pathlib
import shlex
import sys
import time
import traceback
from typing import Callable

if __package__ in (None, ""):  # `python benchmarks/run.py` as well as `python -m benchmarks.run`
    sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))

from benchmarks import report  # noqa: E402
from benchmarks.common import FULL, TINY, Parser, Spec, Timing, cleanup, refuse, unwritable_file  # noqa: E402
from cdjax.options import non_negative, positive, seconds  # noqa: E402

SUITES = ("compare", "seeds", "envs", "devices")
DISTRIBUTED_SUITES = ("seeds", "devices")  # the suites whose sweeps span every process's devices
COMPARE_CASES = ("brax-ppo", "ceiling", "collect", "model-free", "mbmf", "cd-fast", "cd-paper", "cd-w2-unroll",
                 "cd-default")
SCALING_CASES = ("cd-fast", "model-free", "mbmf", "cd-paper")  # the designated CD first: its 32-vs-1 ratio is a target
TRACED_CASES = tuple(c for c in COMPARE_CASES if c not in ("brax-ppo", "ceiling", "collect"))  # compare's, --trace
REPO = pathlib.Path(__file__).resolve().parents[1]


def parse(argv):
    p = Parser(prog="python -m benchmarks.run", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--suite", nargs="+", default=["compare"], choices=[*SUITES, "all"],
                   help="parts to run in this process (GPU: one per command, each fits in ~9 minutes)")
    p.add_argument("--tiny", action="store_true", help="CPU smoke sizes (point env, 16 envs); numbers mean nothing")
    p.add_argument("--cases", nargs="+", choices=COMPARE_CASES, help="compare: only these cases (default: all)")
    p.add_argument("--scaling-cases", nargs="+", choices=SCALING_CASES, default=list(SCALING_CASES[:2]),
                   help="seeds/envs: cdjax cases to scale (default: cd-fast model-free)")
    p.add_argument("--env", help="task (default ant; tiny: point)")
    p.add_argument("--num-envs", type=positive, help="compare: num_envs (default 4096)")
    p.add_argument("--seed-envs", type=positive, help="seeds/devices: num_envs per seed (default 256)")
    p.add_argument("--seed-counts", type=positive, nargs="+", help="seeds: vmapped seed counts (default 1 8 32 128)")
    p.add_argument("--device-seed-counts", type=positive, nargs="+", help="devices: seed counts (default 32 128)")
    p.add_argument("--env-counts", type=positive, nargs="+", help="envs: num_envs values (default 512 ... 8192)")
    p.add_argument("--updates", type=positive, help="timed calls per case (default 5)")
    p.add_argument("--max-case-s", type=seconds, help="stop timing a case after this many timed seconds (min 2 calls)")
    p.add_argument("--brax-steps-per-epoch", type=positive, default=2, help="Brax training steps per timed epoch")
    p.add_argument("--brax-steady-epochs", type=positive, default=3, help="Brax epochs timed after the 2 warm-up epochs")
    p.add_argument("--ceiling-len", type=positive, default=200, help="ceiling: steps per timed scan")
    p.add_argument("--budget-s", type=seconds, default=420.0,
                   help="skip the remaining cases once this process has run this long (default 420 s)")
    p.add_argument("--out", help="output directory (results.json, results.md, results.png)")
    p.add_argument("--write-results", metavar="PATH", help="also render PATH (e.g. benchmarks/RESULTS.md) + PATH.png")
    p.add_argument("--merge", nargs="+", metavar="DIR", help="merge these results (dirs or json) instead of running")
    p.add_argument("--cache", default=os.environ.get("CDJAX_JAX_CACHE"),
                   help="persistent compilation cache dir (default off on GPU so compile times are honest; "
                        "tiny: .jax_cache)")
    p.add_argument("--trace", metavar="DIR",
                   help="compare: write a jax.profiler trace of one update per cdjax case into DIR/<case> (seeds: of "
                        "one update of every seed, DIR/<case>-x<seeds>; envs and devices: not traced) and summarise "
                        "its device ops (benchmarks.profile_summary) into the results")
    p.add_argument("--trace-top", type=positive, default=25, help="--trace: ops listed per case (default 25)")
    p.add_argument("--distributed", action="store_true",
                   help="join the other processes first (cdjax.multihost.initialize: one process per host or GPU, "
                        "each running this command); the seeds and devices suites then sweep over every process's "
                        "devices, and process 0 writes the results (see README)")
    p.add_argument("--coordinator", help="--distributed: coordinator host:port (default: auto-detected)")
    p.add_argument("--num-processes", type=positive, help="--distributed: number of processes (default: auto-detected)")
    p.add_argument("--process-id", type=non_negative, help="--distributed: this process's id (default: auto-detected)")
    p.add_argument("--dry-run", action="store_true", help="print the plan (configs, env steps) and exit")
    args = p.parse_args(argv)
    if args.merge:  # merging reads finished results: what sets up a run would be ignored
        ignored = [f"--{a.dest.replace('_', '-')}" for a in p._actions
                   if a.dest not in ("help", "merge", "out", "write_results") and getattr(args, a.dest) != a.default]
        if ignored:
            p.error(f"{', '.join(ignored)} set{'s' * (len(ignored) == 1)} up a run, which --merge does not make (it "
                    "merges finished results): give them without --merge")
    args.suite = list(SUITES) if "all" in args.suite else list(dict.fromkeys(args.suite))
    if args.distributed and set(args.suite) - set(DISTRIBUTED_SUITES):
        p.error(f"--distributed measures sweeps over every process's devices: give --suite "
                f"{' '.join(DISTRIBUTED_SUITES)} (compare and envs are single-device by design)")
    if args.trace_top != p.get_default("trace_top") and not args.trace:
        p.error("--trace-top goes with --trace DIR (it sets how many ops each trace's table lists)")
    if args.trace and not traced(args):
        p.error(f"--trace traces the compare suite's cdjax cases ({', '.join(TRACED_CASES)}) and the seeds suite's "
                "sweeps, none of which this command runs: give --suite compare with one of those cases, or --suite "
                "seeds, or leave --trace out")
    args = defaults(args)
    check(p.prog, args)
    return args


def traced(args) -> bool:
    """Whether --trace has something to trace: compare's cdjax cases (`run_compare`) or the seeds suite's sweeps
    (`run_seeds`); the envs and devices suites, Brax PPO, the ceiling and the rollout alone are not traced."""
    compare = set(args.cases or COMPARE_CASES) & set(TRACED_CASES)
    return "seeds" in args.suite or ("compare" in args.suite and bool(compare))


def check(prog: str, args) -> None:
    """Refuse, in one sentence with exit status 2, what would otherwise fail only once the cases run (or, for the
    outputs, once they ran): an --out, --write-results or --trace that cannot be written, and a task or sizes that
    some Spec or cdjax Config of the suites cannot take. Builds every one of those (no program); writes nothing."""
    from cdjax import io

    if args.out:
        try:
            io.RunDir(pathlib.Path(args.out)).check_writable()
        except io.RunDirError as err:
            refuse(prog, str(err))
    if args.write_results and (why := unwritable_file(args.write_results)):
        refuse(prog, f"--write-results {args.write_results}: {why}")
    if args.trace:  # a directory made with its parents, as --out is (profile_summary.trace): RunDir's check
        trace = io.RunDir(pathlib.Path(args.trace))
        try:
            trace.check_name("--trace")
        except io.RunDirError as err:
            refuse(prog, str(err))
        try:
            trace.check_writable()
        except io.RunDirError as err:  # (its advice names --out)
            refuse(prog, f"--trace: {str(err).removesuffix('; choose another --out.')}")
    if args.merge:
        return
    from benchmarks.throughput import cdjax_cases

    def build(option: str, value, spec: Callable[[], Spec]) -> Spec:
        try:
            built = spec()
            built.config()
            for _, overrides, _ in cdjax_cases(built).values():
                built.config(**overrides)
        except ValueError as err:  # (ConfigError is one)
            refuse(prog, f"{option} {value}: {err}")
        return built

    base = build("--env", args.env or (TINY if args.tiny else FULL).env, lambda: _base(args))
    main = build("--num-envs", args.num_envs, lambda: base.with_num_envs(args.num_envs)) if args.num_envs else base
    build("--seed-envs", args.seed_envs, lambda: base.with_num_envs(args.seed_envs))
    if "envs" in args.suite or args.dry_run:  # (the dry run builds them whatever the suites)
        for n in args.env_counts:
            build("--env-counts", n, lambda: main.with_num_envs(n))


def _base(args) -> Spec:
    base = TINY if args.tiny else FULL
    return dataclasses.replace(base, env=args.env) if args.env else base


def specs(args) -> tuple[Spec, Spec]:
    base = _base(args)
    main = base.with_num_envs(args.num_envs) if args.num_envs else base
    return main, base.with_num_envs(args.seed_envs)


def defaults(args):
    tiny = args.tiny
    args.seed_envs = args.seed_envs or (16 if tiny else 256)
    args.seed_counts = args.seed_counts or ([1, 2, 4] if tiny else [1, 8, 32, 128])
    args.device_seed_counts = args.device_seed_counts or ([2, 4] if tiny else [32, 128])
    args.env_counts = args.env_counts or ([16, 32] if tiny else [512, 1024, 2048, 4096, 8192])
    args.updates = args.updates or (3 if tiny else 5)
    args.max_case_s = args.max_case_s or (5.0 if tiny else 20.0)
    if tiny:
        args.ceiling_len = min(args.ceiling_len, 20)
    if args.cache is None and tiny:
        args.cache = str(REPO / ".jax_cache")
    return args


class Suite:
    """Runs cases with error capture and a process time budget; rewrites results.json after each."""

    def __init__(self, args, meta: dict, out_dir: str | None):
        self.args, self.t0, self.out_dir = args, time.perf_counter(), out_dir
        self.results = {"metas": [meta], "part_meta": {}, "parts": {}}

    def part(self, name: str) -> list:
        self.results["part_meta"][name] = 0
        return self.results["parts"].setdefault(name, [])

    def run_case(self, label: str, fn) -> dict:
        from benchmarks.scaling import classify_error

        elapsed = time.perf_counter() - self.t0
        over = elapsed > self.args.budget_s
        if self.args.distributed:  # a case's sweep spans every process: all skip it when one's budget is used
            from cdjax import multihost

            over = any(multihost.exchange("1" if over else ""))
        if over:
            row = {"case": label, "status": f"skipped (time budget {self.args.budget_s:.0f} s used)"}
            print(f"[{elapsed:6.0f}s] {label}: skipped, time budget used", flush=True)
            return row
        t0 = time.perf_counter()
        try:
            row = fn()
        except Exception as e:  # noqa: BLE001 - a failed case is a result, the suite goes on
            status = classify_error(e)
            first_line = str(e).splitlines()[0][:300] if str(e) else ""
            row = {"case": label, "status": status, "error": f"{type(e).__name__}: {first_line}"}
            if status != "OOM":
                traceback.print_exc()
        row["case_wall_s"] = round(time.perf_counter() - t0, 2)
        cleanup()
        sps = row.get("env_steps_per_s")
        msg = (f"{sps:,.0f} env steps/s, {row.get('update_s', float('nan')):.4f} s/update, compile "
               f"{row.get('compile_s', float('nan')):.1f} s" if row.get("status") == "ok" else row.get("status"))
        print(f"[{time.perf_counter() - self.t0:6.0f}s] {label}: {msg} (case {row['case_wall_s']:.0f} s)", flush=True)
        return row

    def add(self, part: str, row: dict) -> None:
        self.part(part).append(row)
        self.save()

    def save(self) -> None:
        if self.out_dir:
            import json

            pathlib.Path(self.out_dir).mkdir(parents=True, exist_ok=True)
            (pathlib.Path(self.out_dir) / "results.json").write_text(json.dumps(self.results, indent=1, default=str))


def run_compare(suite: Suite, spec: Spec, timing: Timing, args) -> None:
    from benchmarks import throughput
    from benchmarks.brax_ppo import brax_ppo

    cases = args.cases or COMPARE_CASES
    suite.part("compare")
    # Brax first: the process-wide peak memory is then Brax's own (the other rows use XLA's compiled footprint).
    for case in COMPARE_CASES:
        if case not in cases:
            continue
        if case == "brax-ppo":
            fn = lambda: brax_ppo(spec, args.brax_steps_per_epoch, args.brax_steady_epochs)  # noqa: E731
        elif case == "ceiling":
            fn = lambda: throughput.ceiling(spec, timing, args.ceiling_len)  # noqa: E731
        elif case == "collect":
            fn = lambda: throughput.collect(spec, timing)  # noqa: E731
        else:
            fn = lambda case=case: throughput.cdjax_update(spec, case, timing, args.trace)  # noqa: E731
        row = suite.run_case(case, fn)
        row["case"] = case
        if row.get("trace_dir"):
            attach_profile(row, args.trace_top)
        suite.add("compare", row)


def attach_profile(row: dict, top: int) -> None:
    """Summarise the trace of a case into its row (`profile`, `profile_md`) and print the tables."""
    from benchmarks import profile_summary

    try:
        summary = profile_summary.summarize(row["trace_dir"], top)
    except Exception as e:  # noqa: BLE001 - an unreadable trace costs its table, not the suite
        row["profile_error"] = f"{type(e).__name__}: {e}"
        print(f"{row['case']}: no op-level profile ({row['profile_error']})", flush=True)
        return
    row["profile"] = summary
    row["profile_md"] = profile_summary.markdown(summary)
    print(f"\nop-level profile of one {row['case']} update ({row['trace_dir']}):\n\n{row['profile_md']}", flush=True)


def run_seeds(suite: Suite, spec: Spec, timing: Timing, args) -> None:
    from benchmarks.scaling import seed_scaling

    suite.part("seeds")
    for row in seed_scaling(spec, args.scaling_cases, args.seed_counts, timing, suite.run_case,
                            trace_dir=args.trace):
        row["mesh_devices"] = row.get("mesh_devices") or suite.results["metas"][0]["device_count"]
        if row.get("trace_dir"):
            attach_profile(row, args.trace_top)
        suite.add("seeds", row)


def run_devices(suite: Suite, spec: Spec, timing: Timing, args) -> None:
    import jax

    from benchmarks.scaling import seed_scaling

    suite.part("devices")
    meshes = [1] + ([jax.device_count()] if jax.device_count() > 1 else [])  # (1: each process on its own device)
    if jax.device_count() == 1:
        print("devices: only one device here; measuring the 1-device mesh only", flush=True)
    for n in meshes:
        for row in seed_scaling(spec, ["cd-fast"], args.device_seed_counts, timing, suite.run_case, mesh_devices=n):
            row["mesh_devices"] = n
            suite.add("devices", row)


def run_envs(suite: Suite, spec: Spec, timing: Timing, args) -> None:
    from benchmarks import throughput

    suite.part("envs")
    for n in args.env_counts:
        s = spec.with_num_envs(n)
        for case in ("ceiling", *args.scaling_cases):
            if case == "ceiling":
                fn = lambda s=s: throughput.ceiling(s, timing, args.ceiling_len)  # noqa: E731
            else:
                fn = lambda s=s, case=case: throughput.cdjax_update(s, case, timing)  # noqa: E731
            row = suite.run_case(f"{case} @ {n} envs", fn)
            row.update(case=case, num_envs=n)
            suite.add("envs", row)


def main(argv=None) -> dict:
    argv = list(sys.argv[1:] if argv is None else argv)
    args = parse(argv)
    command = "python -m benchmarks.run " + shlex.join(argv)
    if args.merge:
        try:
            loaded = [report.load(p) for p in args.merge]
        except ValueError as err:
            refuse("python -m benchmarks.run", f"--merge: {err}")
        results = report.merge(loaded)
        if args.out:
            md = report.write_out(results, args.out)
        else:
            md = report.markdown(results)
        if args.write_results:
            report.write_results_md(results, args.write_results, command)
        print(md)
        return results

    spec, seed_spec = specs(args)
    if args.dry_run:
        import json

        print(json.dumps({"suites": args.suite, "compare_spec": spec.describe(), "seed_spec": seed_spec.describe(),
                          "configs": {case: str(spec.config(**ov)) for case, (_, ov, _) in
                                      __import__("benchmarks.throughput", fromlist=["x"]).cdjax_cases(spec).items()},
                          "env_counts": args.env_counts, "seed_counts": args.seed_counts}, indent=1))
        for n in args.env_counts:
            spec.with_num_envs(n).config()
        return {}

    import jax

    if args.distributed:
        from cdjax import multihost

        multihost.initialize(args.coordinator, args.num_processes, args.process_id)
    if args.cache:
        from cdjax import runtime
        from cdjax.protocol import ConfigError

        try:
            runtime.configure(cache_dir=args.cache, cache_source="--cache")
        except ConfigError as err:
            refuse("python -m benchmarks.run", str(err))
    from benchmarks.common import device_info

    info = device_info()
    date = datetime.datetime.now().strftime("%Y-%m-%d")
    meta = {**info, "suite": args.suite, "command": command, "date": date,
            "time": datetime.datetime.now().isoformat(timespec="seconds"), "tiny": args.tiny,
            "compilation_cache": args.cache or os.environ.get("JAX_COMPILATION_CACHE_DIR"),
            "spec": spec.describe(), "seed_spec": seed_spec.describe(),
            "timing": {"updates": args.updates, "max_case_s": args.max_case_s},
            "seed_counts": args.seed_counts, "env_counts": args.env_counts}
    print(f"cdjax benchmarks: {info['device']} x{info['device_count']} ({info['platform']}), jax "
          f"{info['versions'].get('jax')}, suites {args.suite}{' (tiny)' if args.tiny else ''}", flush=True)
    out_dir = args.out
    if out_dir is None and not args.tiny:
        slug = "".join(c if c.isalnum() else "-" for c in info["device"].lower()).strip("-")
        out_dir = str(REPO / "benchmarks" / "results" / f"{date}-{slug}-{'-'.join(args.suite)}")
    writer = jax.process_index() == 0
    if not writer:
        out_dir = None
    suite = Suite(args, meta, out_dir)
    timing = Timing(updates=args.updates, max_seconds=args.max_case_s)
    runners = {"compare": (run_compare, spec), "seeds": (run_seeds, seed_spec), "envs": (run_envs, spec),
               "devices": (run_devices, seed_spec)}
    for name in args.suite:
        fn, s = runners[name]
        fn(suite, s, timing, args)
    results = report.add_ratios(suite.results)
    md = report.write_out(results, out_dir) if out_dir else report.markdown(results)
    if args.write_results and writer:
        report.write_results_md(results, args.write_results, command)
    if out_dir:
        print(f"\nwrote {out_dir}/results.json, results.md, results.png", flush=True)
    if writer:
        print("\n" + md, flush=True)
    return results


if __name__ == "__main__":
    main()
