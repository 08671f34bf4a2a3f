"""Where a whole `cdjax sweep` process spends its time, from the command to its end: several processes run one after
the other, each figure the median (min, max) over them.

    python -m benchmarks.startup --env ant --runs 3 --out DIR              # a 4-arm ant sweep at the preset's settings
    python -m benchmarks.startup --tiny --runs 1 --out DIR                 # the point mass on CPU, in seconds
    python -m benchmarks.startup --env humanoid --runs 3 --out DIR -- --steps 20000000 --seeds 1

Each process is `cdjax sweep --env ENV --out DIR/run-N [what follows --]` (the command's own main, of this checkout
or of --code, e.g. an export of an older commit for a before/after table), with its own empty persistent
compilation cache (--cache cold: what a first run sees) or one cache shared by all, filled by an unrecorded first
process (--cache warm). Its figures come from the sweep's timings.jsonl (cdjax.io.timings: start-up, each program's
trace, lowering and compile, init, writes, evaluations, plots) and the wall clock measured here around the process.

The "phase" rows cut the process's wall clock into consecutive stretches (they sum to the whole): start-up to
run_sweep (interpreter, then imports and arguments), planning (the environments built, the states' shapes),
compiling the training programs, init, training, the final evaluation, plots, and the process's exit. The other
rows are details that overlap those (compiles run in threads, the evaluator's beside training): each program's
trace, lowering and compile summed over arms, the evaluations, writes, and the time from the command to the first
compiled program in flight (the first init). DIR gets table.md and rows.jsonl (one row per process and figure).
"""

from __future__ import annotations

import json
import os
import pathlib
import statistics
import subprocess
import sys
import time

from benchmarks.common import Parser, refuse

TINY = ["--arms", "model-free", "cd", "--seeds", "1", "--steps", "2048", "--num-envs", "16", "--rollout-len", "16",
        "--horizon", "4", "--num-epochs", "1", "--num-minibatches", "2", "--episode-length", "40", "--policy-hidden",
        "16", "--value-hidden", "16", "--model-hidden", "16", "--encoder-dim", "8", "--eval-horizon", "8",
        "--eval-envs", "2", "--eval-episodes", "2", "--chunk-updates", "2", "--no-progress"]
# rows of timings.jsonl that are the start-up before run_sweep, in order (written where the `cdjax` command ran it)
STARTUP = ("interpreter", "imports")
PROGRAMS = ("reset", "init", "phase", "chunk", "evaluator")


def phases(rows: list[dict], launched: float, ended: float) -> dict[str, float]:
    """The process's wall clock [launched, ended] (Unix times) cut at the boundaries its timings rows give, in order;
    the stretches sum to ended - launched. A boundary that a process lacks (no evaluation) gives a zero stretch."""
    def end(r):
        return r["at"] + r["s"]

    def first(pred, default):
        found = [r for r in rows if pred(r)]
        return min(r["at"] for r in found) if found else default

    def last_end(pred, default):
        found = [r for r in rows if pred(r)]
        return max(end(r) for r in found) if found else default

    plan = first(lambda r: r["what"] == "plan", launched)
    marks = {r["what"]: end(r) for r in rows if r["arm"] == "all" and r["what"] in STARTUP}
    imported = marks.get("interpreter", plan)
    compiling = first(lambda r: r["what"] in PROGRAMS[:4] and r["step"] in ("trace", "lower"), plan)
    compiled = last_end(lambda r: r["what"] == "programs", compiling)
    trained = last_end(lambda r: r["what"] == "setup", compiled)
    evaluations = [r for r in rows if (r["arm"], r["what"], r["step"]) == ("all", "evaluation", "host")]
    written = last_end(lambda r: r["what"] in ("checkpoint", "metrics.jsonl", "tensorboard"), trained)
    if evaluations:
        evaluating, evaluated = evaluations[-1]["at"], end(evaluations[-1])
    else:  # a cdjax without that row: from the first evaluator or evaluation row after training to eval.jsonl's write
        evaluating = first(lambda r: r["what"] in ("evaluator", "evaluation") and r["at"] >= written, written)
        evaluated = last_end(lambda r: r["what"] == "eval.jsonl", evaluating)
    plotted = last_end(lambda r: r["what"] == "plots", evaluated)
    cuts = [("start-up: interpreter", launched), ("start-up: imports and arguments", imported),
            ("planning (envs built, shapes)", plan), ("compiling the training programs", compiling),
            ("init", compiled), ("training", trained), ("final evaluation", evaluating),
            ("plots and summary", evaluated), ("exit", plotted)]
    out, previous = {}, launched
    for (name, at), (_, following) in zip(cuts, cuts[1:] + [("", ended)]):
        at, following = max(at, previous), max(following, max(at, previous))
        following = min(following, ended)
        out[name] = max(following - at, 0.0)
        previous = max(following, at)
    return out


def details(rows: list[dict], launched: float) -> dict[str, float]:
    """Figures that overlap the phases: each program's trace, lowering and compile (summed over arms), the
    evaluations, writes, and the time from the command to the first compiled program in flight."""
    def total(**match):
        return sum(r["s"] for r in rows if all(r[k] == v for k, v in match.items()))

    out = {}
    for what in PROGRAMS:
        for step in ("trace", "lower", "compile"):
            if any(r["what"] == what and r["step"] == step for r in rows):
                out[f"{what} {step} (sum over arms)"] = total(what=what, step=step)
    first = [r["at"] for r in rows if r["step"] == "init"]
    if first:
        out["command to the first program in flight"] = min(first) - launched
    evaluations = [r for r in rows if (r["arm"], r["what"], r["step"]) == ("all", "evaluation", "host")]
    for i, whole in enumerate(evaluations):
        inside = [r for r in rows if r["what"] in ("evaluation", "evaluator") and r["step"] in ("evaluate", "wait")
                  and whole["at"] - 1e-6 <= r["at"] <= whole["at"] + whole["s"] + 1e-6]
        out[f"evaluation {i + 1}: episodes (sum over arms)"] = sum(r["s"] for r in inside if r["step"] == "evaluate")
        out[f"evaluation {i + 1}: waiting for the evaluator"] = sum(r["s"] for r in inside if r["step"] == "wait")
    out["checkpoint writes"] = total(what="checkpoint", step="write")
    out["log writes (metrics, tensorboard, eval)"] = sum(total(what=w, step="write")
                                                         for w in ("metrics.jsonl", "tensorboard", "eval.jsonl"))
    return out


def run_one(command: list[str], run_dir: pathlib.Path, env: dict, code: str,
            timeout: float) -> tuple[list[dict], float, float]:
    """One whole process, in the directory `code` (Python puts it first on the path): (its timings rows, launch and
    end as Unix times)."""
    with open(run_dir.parent / f"{run_dir.name}.log", "w") as log:
        launched = time.time()
        try:
            done = subprocess.run(command + ["--out", str(run_dir)], env=env, cwd=code, stdout=log,
                                  stderr=subprocess.STDOUT, timeout=timeout)
        except subprocess.TimeoutExpired:
            refuse("python -m benchmarks.startup", f"{run_dir.name} was still running at --time-limit (see {log.name})")
        ended = time.time()
    if done.returncode:
        refuse("python -m benchmarks.startup", f"{run_dir.name} ended with status {done.returncode} (see {log.name})")
    rows = [json.loads(line) for line in (run_dir / "timings.jsonl").read_text().splitlines() if line.strip()]
    return rows, launched, ended


def table(results: list[dict], command: str, device: str, cache: str) -> str:
    """The markdown table: median (min, max) of each figure over the processes, phases first."""
    lines = [f"Command (each process): `{command}`; device: {device}; compilation cache: {cache}; "
             f"{len(results)} processes.", "", "| figure | median s | min s | max s |", "|---|---:|---:|---:|"]
    names = list(dict.fromkeys(n for r in results for n in r["phases"]))
    names += ["total (wall clock)"] + list(dict.fromkeys(n for r in results for n in r["details"]))
    for name in names:
        values = [r["wall"] if name == "total (wall clock)" else r["phases"].get(name, r["details"].get(name))
                  for r in results]
        values = [v for v in values if v is not None]
        if values:
            lines.append(f"| {name} | {statistics.median(values):.2f} | {min(values):.2f} | {max(values):.2f} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> list[dict]:
    argv = sys.argv[1:] if argv is None else list(argv)
    extra = argv[argv.index("--") + 1:] if "--" in argv else []
    argv = argv[:argv.index("--")] if "--" in argv else argv
    parser = Parser(prog="python -m benchmarks.startup", description=__doc__.splitlines()[0])
    parser.add_argument("--env", default="ant", help="the sweep's --env (default ant, at its preset)")
    parser.add_argument("--runs", type=int, default=3, help="whole processes timed one after the other")
    parser.add_argument("--out", required=True, help="directory for the runs, table.md and rows.jsonl")
    parser.add_argument("--cache", choices=("cold", "warm"), default="cold",
                        help="cold: each process its own empty compilation cache; warm: one shared, filled first")
    parser.add_argument("--cache-dir", help="one compilation cache for every process, as it is (instead of --cache)")
    parser.add_argument("--time-limit", type=float, default=3600.0,
                        help="seconds for the whole benchmark: no process starts that could not end within it")
    parser.add_argument("--code", type=lambda p: str(pathlib.Path(p).resolve()),
                        default=str(pathlib.Path(__file__).resolve().parents[1]),
                        help="the checkout whose cdjax the processes run (default: this one)")
    parser.add_argument("--tiny", action="store_true", help="the point mass at tiny sizes (a CPU check)")
    args = parser.parse_args(argv)
    if args.runs < 1:
        refuse(parser.prog, "--runs must be at least 1")
    out = pathlib.Path(args.out).absolute()
    if out.exists() and any(out.iterdir()):
        refuse(parser.prog, f"{out} exists and is not empty; choose another --out")
    out.mkdir(parents=True, exist_ok=True)
    sweep = ["sweep", "--env", "point" if args.tiny else args.env] + (TINY if args.tiny else []) + extra
    # the `cdjax` console script's main, as a program (argv[0] "cdjax": its start-up rows are recorded)
    command = [sys.executable, "-c", "import sys; sys.argv[0] = 'cdjax'; from cdjax.cli import main; main()"] + sweep
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([args.code] + [p for p in [os.environ.get("PYTHONPATH")] if p]))
    deadline = time.monotonic() + args.time_limit
    results, longest = [], 0.0
    warmup = args.cache == "warm" and not args.cache_dir
    for i in range(args.runs + warmup):
        if time.monotonic() + longest > deadline:
            print(f"Stopping after {len(results)} processes: another would pass --time-limit.", file=sys.stderr)
            break
        env["CDJAX_JAX_CACHE"] = args.cache_dir or str(out / ("cache" if args.cache == "warm" else f"cache-{i}"))
        t0 = time.monotonic()
        rows, launched, ended = run_one(command, out / f"run-{i}", env, args.code,
                                        max(deadline - time.monotonic(), 1.0))
        longest = max(longest, time.monotonic() - t0)
        if warmup and i == 0:
            continue  # it filled the cache
        results.append({"run": i, "wall": ended - launched, "launched": launched,
                        "phases": phases(rows, launched, ended),
                        "details": details(rows, launched)})
    if not results:
        refuse(parser.prog, "no process ran within --time-limit")
    with open(out / "rows.jsonl", "w") as f:
        for r in results:
            for kind in ("phases", "details"):
                f.writelines(json.dumps({"run": r["run"], "kind": kind, "figure": name, "s": s}) + "\n"
                             for name, s in r[kind].items())
            f.write(json.dumps({"run": r["run"], "kind": "wall", "figure": "total (wall clock)", "s": r["wall"],
                                "launched": r["launched"], "ended": r["launched"] + r["wall"]}) + "\n")
    code = json.loads((out / f"run-{results[0]['run']}" / "run.json").read_text()).get("code", [{}])[-1]
    device = f"{code.get('backend', '?')} (jax {code.get('jax', '?')})"
    cache = f"{args.cache_dir} (as it was)" if args.cache_dir else args.cache
    text = table(results, " ".join(["cdjax"] + sweep + ["--out", "DIR"]), device, cache)
    commit = (code.get("commit") or "not a git checkout")[:10] + (", modified" if code.get("modified") else "")
    text += f"\nCode: {args.code} ({commit}).\n"
    (out / "table.md").write_text(text)
    print(text)
    return results


if __name__ == "__main__":
    main()
