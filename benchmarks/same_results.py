"""Whether an XLA setting changes what cdjax computes: the same updates in one process per setting, every array of the
trainer's state and every metric compared bit for bit.

    python -m benchmarks.same_results --flags xla_gpu_command_buffer_scheduling_mode=LHS \\
        xla_gpu_command_buffer_scheduling_mode=CONCURRENT --cases model-free cd-paper --updates 3 --out DIR

Each setting runs in a child process whose XLA_FLAGS start with `--SETTING` (an option named there is the user's,
so cdjax's own default for it steps aside: cdjax.runtime.apply_xla_defaults). The child builds each case of the
compare suite at the matched Spec (`--tiny`: the CPU smoke sizes), initialises it from key 0, runs `--updates`
jitted updates and saves the state's arrays (PRNG keys as their data) and the last update's metrics. The parent
compares each setting's arrays with the first setting's: per case, how many arrays are bit-identical, and the largest
absolute and relative difference among those that are not. A scheduling option that only reorders independent
kernels must leave every array identical; a difference means it changed an order of arithmetic or broke a
dependency. Name the reference setting twice to see what two processes at one setting differ by: on an H100
(2026-11-27, benchmarks/results/2026-11-27-h100-identity/) two processes at one setting already differed in about
half the arrays after 3 updates (the GPU's atomic sums and the autotuner's choices of kernel differ from run to run),
so compare there with --base xla_gpu_deterministic_ops=true xla_gpu_autotune_level=0: with those, on 2026-11-27, LHS,
LHS and CONCURRENT gave identical arrays (benchmarks/results/2026-11-27-h100-per-program/). Both programs (init and
update) are compiled with cdjax.runtime.compiler_options, so a compile mode (CDJAX_COMPILE_MODE) reaches both; until
2026-11-27 the init was not, and in the `deterministic` mode the physics arrays of its reset then differed between
two processes. Writes results.json and results.md under --out; exit status 1 when any array differs. Bad input
ends in one sentence with exit status 2 before any child starts (the settings asked of XLA first, in one start-up,
as `benchmarks.xla_flags --accepts` asks).
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import re
import subprocess
import sys

import numpy as np

from benchmarks.common import FULL, TINY, Parser, refuse
from benchmarks.throughput import cdjax_cases
from cdjax.options import positive

REPO = pathlib.Path(__file__).resolve().parent.parent


def child_env(setting: str, environ: dict | None = None, base: tuple[str, ...] = ()) -> dict:
    """The environment of a child for `setting` (NAME=VALUE): XLA_FLAGS led by --NAME=VALUE, then each of `base`
    (the settings every child shares), the rest kept."""
    env = dict(os.environ if environ is None else environ)
    env["XLA_FLAGS"] = " ".join([f"--{setting}", *(f"--{b}" for b in base), env.get("XLA_FLAGS", "")]).strip()
    return env


def compare(reference: dict[str, np.ndarray], other: dict[str, np.ndarray]) -> dict:
    """Arrays of the same names, compared: counts of identical ones (NaNs in the same places count as equal) and the
    largest absolute and relative differences of the others; names present on one side only are listed."""
    only = sorted(set(reference) ^ set(other))
    names = sorted(set(reference) & set(other))
    identical, worst_abs, worst_rel, differing = 0, 0.0, 0.0, []
    for name in names:
        a, b = np.asarray(reference[name]), np.asarray(other[name])
        if a.shape == b.shape and a.dtype == b.dtype and np.array_equal(a, b, equal_nan=a.dtype.kind in "fc"):
            identical += 1
            continue
        differing.append(name)
        if a.shape != b.shape:
            worst_abs = worst_rel = float("inf")
            continue
        a64, b64 = a.astype(np.float64), b.astype(np.float64)
        diff = np.abs(a64 - b64)
        diff = np.where(np.isnan(a64) & np.isnan(b64), 0.0, diff)
        worst_abs = max(worst_abs, float(np.nanmax(diff)) if diff.size else 0.0)
        scale = np.maximum(np.abs(a64), np.abs(b64))
        rel = np.where(scale > 0, diff / np.where(scale > 0, scale, 1.0), 0.0)
        worst_rel = max(worst_rel, float(np.nanmax(rel)) if rel.size else 0.0)
    return {"arrays": len(names), "identical": identical, "differing": differing[:20], "n_differing": len(differing),
            "max_abs_diff": worst_abs, "max_rel_diff": worst_rel, "only_one_side": only}


def _arrays(tree, prefix: str) -> dict[str, np.ndarray]:
    """The leaves of `tree` by their checkpoint names (`cdjax.io.checkpoints.named_leaves`) under `prefix`, PRNG keys
    as their key data."""
    import jax

    from cdjax.io.checkpoints import named_leaves

    is_key = lambda x: jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key)  # noqa: E731
    return {f"{prefix}.{name}": np.asarray(jax.random.key_data(x) if is_key(x) else x)
            for name, x in named_leaves(tree)}


def run_child(cases: list[str], updates: int, tiny: bool, path: str) -> None:
    """Run each case's updates in this process and save its arrays to `path` (.npz)."""
    from cdjax import make_agent, runtime  # first: cdjax adds its XLA defaults before JAX starts a backend

    import jax

    spec = TINY if tiny else FULL
    saved = {}
    for case in cases:
        _, overrides, hp_overrides = cdjax_cases(spec)[case]
        trainer = make_agent(spec.config(**overrides))
        hp = spec.hparams(**hp_overrides).as_float32()
        options = runtime.compiler_options()  # both programs as cdjax compiles them (the runner compiles init so too)
        state = jax.jit(trainer.init, compiler_options=options)(jax.random.key(0), hp)
        update = jax.jit(trainer.update, compiler_options=options)
        metrics = {}
        for _ in range(updates):
            state, metrics = update(state, hp)
        jax.block_until_ready(state)
        saved.update(_arrays(state, f"{case}/state"))
        saved.update(_arrays(dict(metrics), f"{case}/metrics"))
    np.savez(path, **saved)


SETTING = re.compile(r"[A-Za-z][A-Za-z0-9_]*=\S+")  # NAME=VALUE, one word of XLA_FLAGS once `--` leads it


def check(prog: str, args) -> None:
    """Refuse, in one sentence with exit status 2, what would otherwise fail in a child process, or in the
    comparison once every child ran, or compare nothing: a setting that is not NAME=VALUE or that this XLA does not
    take (it aborts at start-up), fewer than two --flags, an --out that cannot be written. Writes nothing."""
    from benchmarks import xla_flags
    from cdjax import io

    for option, settings in (("--flags", args.flags), ("--base", args.base)):
        for setting in settings:
            if not SETTING.fullmatch(setting):
                refuse(prog, f"{option} {setting!r} is not NAME=VALUE (an XLA option without its leading --, e.g. "
                             "xla_gpu_autotune_level=0)")
    if len(args.flags) < 2:
        refuse(prog, f"--flags {args.flags[0]} alone compares nothing: give two or more settings (the first is the "
                     "reference; name it twice to see what two processes at one setting differ by)")
    try:
        io.RunDir(pathlib.Path(args.out)).check_writable()
    except io.RunDirError as err:
        refuse(prog, str(err))
    settings = list(dict.fromkeys([*args.flags, *args.base]))
    if not xla_flags.accepts(" --".join(settings)):  # one XLA start for all (XLA_FLAGS is words); one each if refused
        refused = [s for s in settings if not xla_flags.accepts(s)] or [" ".join(settings)]
        refuse(prog, f"XLA refuses {', '.join(refused)} at start-up (benchmarks.xla_flags lists the names it holds)")


def main(argv=None) -> int:
    p = Parser(prog="python -m benchmarks.same_results", description=__doc__,
               formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--flags", nargs="+", required=True, metavar="NAME=VALUE",
                   help="XLA settings, one child process each; the first is the reference")
    p.add_argument("--base", nargs="+", default=[], metavar="NAME=VALUE",
                   help="XLA settings every child shares, after its own (e.g. xla_gpu_deterministic_ops=true "
                        "xla_gpu_autotune_level=0: the GPU's atomics and the autotuner's timing-dependent choices "
                        "out of the way, so that a scheduling option's own effect shows)")
    p.add_argument("--cases", nargs="+", default=["model-free", "cd-paper"], choices=list(cdjax_cases(FULL)))
    p.add_argument("--updates", type=positive, default=3, help="updates per case (default 3)")
    p.add_argument("--tiny", action="store_true", help="the CPU smoke sizes (point env, 16 envs)")
    p.add_argument("--out", required=True, help="directory for the arrays and results.json, results.md")
    p.add_argument("--child", help=argparse.SUPPRESS)  # internal: save this process's arrays to CHILD (.npz)
    args = p.parse_args(argv)
    args.cases = list(dict.fromkeys(args.cases))
    if args.child:
        run_child(args.cases, args.updates, args.tiny, args.child)
        return 0
    check(p.prog, args)
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    files = []
    for i, setting in enumerate(args.flags):
        path = str(out / f"arrays-{i}.npz")
        cmd = [sys.executable, "-m", "benchmarks.same_results", "--flags", setting, "--cases", *args.cases,
               "--updates", str(args.updates), "--out", str(out), "--child", path] + (["--tiny"] if args.tiny else [])
        subprocess.run(cmd, env=child_env(setting, base=tuple(args.base)), cwd=REPO, check=True)
        files.append(path)
    reference = dict(np.load(files[0]))
    rows = []
    for i, (setting, path) in enumerate(zip(args.flags[1:], files[1:]), 1):
        other = dict(np.load(path))
        for case in args.cases:
            pick = lambda arrays: {k: v for k, v in arrays.items() if k.startswith(case + "/")}  # noqa: E731
            rows.append({"case": case, "reference": args.flags[0], "setting": f"{setting} (process {i})",
                         **compare(pick(reference), pick(other))})
    lines = [f"`python -m benchmarks.same_results {' '.join(argv if argv is not None else sys.argv[1:])}`", "",
             "| case | reference | setting | arrays | identical | max abs diff | max rel diff |",
             "| --- | --- | --- | ---: | ---: | ---: | ---: |"]
    lines += [f"| {r['case']} | {r['reference']} | {r['setting']} | {r['arrays']} | {r['identical']} | "
              f"{r['max_abs_diff']:.3g} | {r['max_rel_diff']:.3g} |" for r in rows]
    (out / "results.json").write_text(json.dumps(rows, indent=1))
    (out / "results.md").write_text("\n".join(lines) + "\n")
    for path in files:
        os.remove(path)
    print("\n".join(lines))
    same = all(r["n_differing"] == 0 and not r["only_one_side"] for r in rows)
    print("every array identical" if same else "some arrays differ: " +
          "; ".join(f"{r['case']}: {', '.join(r['differing'][:5])}" for r in rows if r["n_differing"]))
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())
