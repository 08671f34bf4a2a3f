"""One sweep as one process per GPU (`--distributed`, NCCL between the GPUs) against the same sweep as one process on
all of the host's GPUs, on one host of several GPUs:

    python -m benchmarks.distributed --out DIR [--gpus N] [--time-limit S] [--tiny]

in one command, in this order (each step's processes side by side, each of them a `cdjax` command as a user types it):
1. `one`: `cdjax sweep ARGS --out DIR/one`, one process seeing every GPU; `many`: the same ARGS as N processes, process
   i seeing GPU i alone (CUDA_VISIBLE_DEVICES) and started with `--distributed --coordinator 127.0.0.1:PORT
   --num-processes N --process-id i`; `cut`: `many` again into DIR/cut, its last process killed (SIGKILL) once the
   first arm has two checkpoints: the others must end with exit status 69 and cdjax's one sentence.
2. `cut` copied to `cut-by-one`; `cut` resumed by N processes (`--resume --distributed`) and `cut-by-one` by one
   process on every GPU (`--resume`).
3. The metrics (metrics.jsonl and eval.jsonl without their wall-clock fields) of `many`, `cut` and `cut-by-one`
   compared with `one`'s: equal, or the largest difference per field where they are not; the files each run
   directory holds outside its checkpoints compared with `one`'s (process 0 the only writer: the others' libraries'
   output in cdjax.process<i>.log and nothing else); the other processes' stdout must be empty.
4. Throughput, the host to itself: `python -m benchmarks.run --suite seeds` as one process on every GPU and as N
   processes with `--distributed`, at the same seed counts (aggregate env steps/s of both layouts).

The sweeps run with `--compile-mode deterministic` by default (no atomic sums, no autotuning: one layout must repeat
the other bit for bit); `--compile-mode default` shows instead how far the layouts differ under the GPU's usual
run-to-run spread. Writes DIR/results.json and DIR/results.md (and each step's logs under DIR/logs); prints the
markdown. `--tiny`: the point mass on CPU devices (N processes with one CPU device each, gloo), as a dry run of the
whole sequence; its numbers mean nothing.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import pathlib
import re
import shlex
import shutil
import signal
import socket
import subprocess
import sys
import time

from benchmarks.common import gpu_count

REPO = pathlib.Path(__file__).resolve().parents[1]
# the ant preset's structure (2,048 envs x T=32, k=20) at a budget a loan holds: 48 updates in chunks of 8
GPU_SWEEP = ["--env", "ant", "--arms", "mbmf", "cd", "--seeds", "8", "--steps", str(48 * 2048 * 32),
             "--chunk-updates", "8", "--eval-episodes", "10", "--no-progress"]
# tests/_shared.TINY_ARGS's point mass: 12 updates in chunks of 2
TINY_SWEEP = ["--env", "point", "--num-envs", "16", "--rollout-len", "12", "--horizon", "4", "--num-epochs", "2",
              "--num-minibatches", "2", "--episode-length", "40", "--policy-hidden", "16", "--value-hidden", "16",
              "--model-hidden", "32", "--encoder-dim", "8", "--eval-horizon", "10", "--eval-envs", "4",
              "--arms", "model-free", "cd", "--seeds", "4", "--steps", str(12 * 192), "--chunk-updates", "2",
              "--eval-episodes", "2", "--bootstrap-reps", "50", "--no-progress"]
GPU_SEEDS = ["--suite", "seeds", "--scaling-cases", "cd-fast", "--seed-counts", "32", "128"]
TINY_SEEDS = ["--tiny", "--suite", "seeds", "--scaling-cases", "model-free", "--seed-counts", "2", "4",
              "--updates", "2"]
WALL = ("wall_s", "phase_wall_s")  # the only fields that differ between two runs of one program
LIBRARY_LOG = re.compile(r"cdjax(\.process\d+)?\.log")


def _port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Host:
    """Starts processes that see all of the host's devices or one of them: GPUs by CUDA_VISIBLE_DEVICES, or
    (--tiny) CPU devices by XLA's host device count."""

    def __init__(self, gpus: int, tiny: bool, logs: pathlib.Path):
        self.n, self.tiny, self.logs = gpus, tiny, logs
        logs.mkdir(parents=True, exist_ok=True)

    def env(self, device: int | None) -> dict:
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        if self.tiny:
            count = self.n if device is None else 1
            env.update(JAX_PLATFORMS="cpu", XLA_FLAGS=f"{env.get('XLA_FLAGS', '')} "
                                                      f"--xla_force_host_platform_device_count={count}".strip())
        elif device is not None:
            env["CUDA_VISIBLE_DEVICES"] = str(device)
        return env

    def start(self, name: str, argv: list[str], device: int | None = None) -> subprocess.Popen:
        out, err = (open(self.logs / f"{name}.{kind}", "w") for kind in ("out", "err"))
        proc = subprocess.Popen([sys.executable, *argv], stdout=out, stderr=err, env=self.env(device), cwd=REPO)
        proc.name = name
        return proc

    def one(self, name: str, argv: list[str]) -> list[subprocess.Popen]:
        return [self.start(name, argv)]

    def many(self, name: str, argv: list[str]) -> list[subprocess.Popen]:
        port = _port()
        return [self.start(f"{name}.p{i}", [*argv, "--distributed", "--coordinator", f"127.0.0.1:{port}",
                                            "--num-processes", str(self.n), "--process-id", str(i)], device=i)
                for i in range(self.n)]

    def said(self, name: str, kind: str = "err") -> str:
        path = self.logs / f"{name}.{kind}"
        return path.read_text(errors="replace") if path.exists() else ""


def _wait(procs: list[subprocess.Popen], deadline: float) -> dict[str, int | None]:
    """Each process's exit status once all have ended, None for one killed at the deadline."""
    for p in procs:
        try:
            p.wait(timeout=max(1.0, deadline - time.time()))
        except subprocess.TimeoutExpired:
            p.send_signal(signal.SIGTERM)
            try:
                p.wait(timeout=20)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
            p.returncode = None
    return {p.name: p.returncode for p in procs}


def _checkpoints(run: pathlib.Path, arm: str) -> list[int]:
    folder = run / "checkpoints" / arm
    return sorted(int(p.name) for p in folder.iterdir() if p.name.isdigit()) if folder.is_dir() else []


def _rows(run: pathlib.Path, name: str) -> list[dict]:
    path = run / name
    rows = [json.loads(line) for line in path.read_text().splitlines() if line.strip()] if path.exists() else []
    rows = [{k: v for k, v in row.items() if k not in WALL} for row in rows]
    return sorted(rows, key=lambda r: (r["arm"], str(r["hp"]), r["seed"], r.get("update", -1),
                                       r.get("deterministic", 0)))


def _differences(a: list[dict], b: list[dict]) -> dict:
    """How two logs of the same sweep differ: 'equal', or the rows' count, the fields that differ and each one's
    largest absolute difference."""
    if a == b:
        return {"equal": True, "rows": len(a)}
    if len(a) != len(b):
        return {"equal": False, "rows": [len(a), len(b)]}
    largest: dict[str, float] = {}
    for x, y in zip(a, b):
        for key in sorted(set(x) | set(y)):
            u, v = x.get(key), y.get(key)
            if u == v:
                continue
            if isinstance(u, (int, float)) and isinstance(v, (int, float)):
                d = abs(u - v) if math.isfinite(u) and math.isfinite(v) else math.inf
            else:
                d = math.inf  # a field missing on one side, or not a number
            largest[key] = max(largest.get(key, 0.0), d)
    return {"equal": False, "rows": len(a), "largest": largest}


def _files(run: pathlib.Path) -> dict[str, int]:
    """The files of a run directory outside its checkpoints, TensorBoard's counted per folder (their names hold the
    time and the host)."""
    found: dict[str, int] = {}
    for p in run.rglob("*"):
        rel = p.relative_to(run)
        if not p.is_file() or rel.parts[0] in ("checkpoints", "checkpoints.restarted"):
            continue
        key = str(rel.parent / "events.out.tfevents.*") if p.name.startswith("events.out.tfevents.") else str(rel)
        found[key] = found.get(key, 0) + 1
    return found


def _last_line(text: str) -> str:
    lines = [line for line in text.splitlines() if line.strip()]
    return lines[-1] if lines else ""


def _seeds_rows(path: pathlib.Path) -> list[dict]:
    if not (path / "results.json").exists():
        return []
    return json.loads((path / "results.json").read_text())["parts"].get("seeds", [])


def _kill_when_checkpointed(procs, run: pathlib.Path, arm: str, deadline: float) -> dict:
    """SIGKILL the last process once the first arm has two checkpoints; what was seen when."""
    start = time.time()
    while time.time() < deadline and all(p.poll() is None for p in procs):
        if len(_checkpoints(run, arm)) >= 2:
            procs[-1].kill()
            return {"killed": procs[-1].name, "after_s": round(time.time() - start, 1),
                    "checkpoints": _checkpoints(run, arm)}
        time.sleep(0.2)
    return {"killed": None, "ended": {p.name: p.poll() for p in procs}}


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(prog="python -m benchmarks.distributed", description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", required=True, type=pathlib.Path, help="output directory (must not exist)")
    p.add_argument("--gpus", type=int, default=None, help="processes and devices (default: the GPUs nvidia-smi "
                   "lists; --tiny: 2)")
    p.add_argument("--compile-mode", default="deterministic", choices=("deterministic", "default"),
                   help="the sweeps' --compile-mode (default deterministic: the layouts must agree bit for bit)")
    p.add_argument("--time-limit", type=float, default=1200, help="seconds for the whole command; the throughput "
                   "step is skipped when less than --throughput-s is left (default 1200)")
    p.add_argument("--throughput-s", type=float, default=400, help="seconds for both layouts' seeds suite (default "
                   "400; 0: not measured)")
    p.add_argument("--tiny", action="store_true", help="the point mass on CPU devices: a dry run of the sequence")
    args = p.parse_args(argv)
    begin = time.time()
    deadline = begin + args.time_limit
    if args.out.exists():
        p.error(f"--out {args.out} exists; give a new directory")
    n = args.gpus or (2 if args.tiny else gpu_count())
    if n < 2:
        p.error(f"needs at least 2 devices, found {n} (nvidia-smi -L); give --gpus N, or --tiny on a CPU")
    host = Host(n, args.tiny, args.out / "logs")
    sweep = [*(TINY_SWEEP if args.tiny else GPU_SWEEP), "--compile-mode", args.compile_mode]
    arm = sweep[sweep.index("--arms") + 1]
    cdjax = ["-m", "cdjax.cli", "sweep"]
    runs = {name: args.out / name for name in ("one", "many", "cut", "cut-by-one")}
    steps: list[dict] = []

    def step(name, procs, limit, **more):
        t = time.time()
        ended = _wait(procs, min(deadline, t + limit))
        steps.append({"step": name, "wall_s": round(time.time() - t, 1), "status": ended, **more})
        print(f"{name}: {ended} in {time.time() - t:.0f} s", flush=True)
        return ended

    # 1. the two layouts, and the one whose last process is killed, side by side
    t0 = time.time()
    first = [*host.one("one", [*cdjax, *sweep, "--out", str(runs["one"])]),
             *host.many("many", [*cdjax, *sweep, "--out", str(runs["many"])])]
    cut = host.many("cut", [*cdjax, *sweep, "--out", str(runs["cut"])])
    kill = _kill_when_checkpointed(cut, runs["cut"], arm, deadline)
    step("cut", cut, 300, kill=kill)
    step("one + many", first, 900, started_s=round(t0 - begin, 1))

    # 2. the cut run resumed by N processes and, from a copy, by one
    if runs["cut"].exists():
        shutil.copytree(runs["cut"], runs["cut-by-one"])
        # --compile-mode is not recorded in run.json (each command chooses how XLA compiles): given again
        again = ["--resume", "--no-progress", "--compile-mode", args.compile_mode]
        resumed = [*host.many("resume-many", [*cdjax, "--out", str(runs["cut"]), *again]),
                   *host.one("resume-one", [*cdjax, "--out", str(runs["cut-by-one"]), *again])]
        step("resume", resumed, 900)

    # 3. what the layouts wrote
    compared = {}
    for name, commands in (("many", 1), ("cut", 2), ("cut-by-one", 2)):
        compared[name] = {log: _differences(_rows(runs["one"], log), _rows(runs[name], log))
                          for log in ("metrics.jsonl", "eval.jsonl")}
        # what `one` wrote, with one TensorBoard file per run for each command that trained in the directory (a
        # resumed run adds one); the libraries' logs (cdjax.log, cdjax.process<i>.log) say what each process met
        expected = {k: v * commands if k.endswith("events.out.tfevents.*") else v for k, v in _files(runs["one"]).items()
                    if not LIBRARY_LOG.fullmatch(k)}
        found = {k: v for k, v in _files(runs[name]).items() if not LIBRARY_LOG.fullmatch(k)}
        compared[name]["files"] = {"unexpected": {k: v for k, v in found.items() if expected.get(k) != v},
                                   "missing": sorted(k for k in expected if k not in found)}
    others_stdout = {f"{name}.p{i}": host.said(f"{name}.p{i}", "out") for name in ("many", "resume-many")
                     for i in range(1, n)}
    cut_said = {f"cut.p{i}": _last_line(host.said(f"cut.p{i}")) for i in range(n - 1)}

    # 4. throughput, each layout alone on the host
    throughput = {}
    left = deadline - time.time()
    bench = ["-m", "benchmarks.run", *(TINY_SEEDS if args.tiny else GPU_SEEDS)]
    if args.throughput_s <= 0:
        steps.append({"step": "throughput", "skipped": "--throughput-s 0"})
    elif left >= args.throughput_s:
        budget = str(int(args.throughput_s / 2 - 30))  # benchmarks.run starts no case after it
        for name, start in (("seeds-one", host.one), ("seeds-many", host.many)):
            step(name, start(name, [*bench, "--budget-s", budget, "--out", str(args.out / name)]),
                 args.throughput_s / 2 + 60)
            throughput[name] = _seeds_rows(args.out / name)
    else:
        steps.append({"step": "throughput", "skipped": f"{left:.0f} s left of --time-limit"})

    results = {"command": "python -m benchmarks.distributed " + shlex.join(argv if argv is not None else sys.argv[1:]),
               "processes": n, "tiny": args.tiny, "compile_mode": args.compile_mode,
               "sweep": shlex.join(sweep), "date": time.strftime("%Y-%m-%d"), "steps": steps,
               "compared_with_one": compared, "others_stdout": others_stdout, "cut_last_lines": cut_said,
               "throughput": throughput, "wall_s": round(time.time() - begin, 1)}
    (args.out / "results.json").write_text(json.dumps(results, indent=1))
    md = markdown(results)
    (args.out / "results.md").write_text(md)
    print(md, flush=True)
    return results


def markdown(r: dict) -> str:
    n = r["processes"]
    lines = [f"# One sweep, one process per device ({n} processes, --distributed) against one process on {n} devices",
             "", f"`{r['command']}` ({r['date']}, {r['wall_s']:.0f} s); sweeps: `cdjax sweep {r['sweep']}`", "",
             "| step | wall s | exit status |", "| --- | ---: | --- |"]
    for s in r["steps"]:
        status = s.get("skipped") or ", ".join(f"{k} {v}" for k, v in s["status"].items())
        lines.append(f"| {s['step']} | {s.get('wall_s', '')} | {status} |")
    kill = next((s.get("kill") for s in r["steps"] if s["step"] == "cut"), None)
    lines += ["", f"Kill: {kill}", "", "Last line of each process that was not killed:", ""]
    lines += [f"- {name}: `{line}`" for name, line in r["cut_last_lines"].items()]
    lines += ["", "Each run directory against `one`'s:", "",
              "| run | metrics.jsonl | eval.jsonl | files outside checkpoints |", "| --- | --- | --- | --- |"]
    for name, c in r["compared_with_one"].items():
        def cell(d):
            return f"equal ({d['rows']} rows)" if d["equal"] else f"differ: {d.get('largest', d['rows'])}"
        files = c["files"]
        same = not files["unexpected"] and not files["missing"]
        lines.append(f"| {name} | {cell(c['metrics.jsonl'])} | {cell(c['eval.jsonl'])} | "
                     f"{'as expected' if same else files} |")
    quiet = all(not text for text in r["others_stdout"].values())
    lines += ["", f"The other processes' stdout: {'empty' if quiet else r['others_stdout']}"]
    if r["throughput"]:
        lines += ["", "| case | seeds | one process, env steps/s | " f"{n} processes, env steps/s | ratio |",
                  "| --- | ---: | ---: | ---: | ---: |"]
        one = {(x["case"], x["seeds"]): x for x in r["throughput"].get("seeds-one", [])}
        for x in r["throughput"].get("seeds-many", []):
            y = one.get((x["case"], x["seeds"]), {})
            a, b = y.get("env_steps_per_s"), x.get("env_steps_per_s")
            ratio = f"{b / a:.2f}" if a and b else ""
            lines.append(f"| {x['case']} | {x['seeds']} | {f'{a:,.0f}' if a else y.get('status', '')} | "
                         f"{f'{b:,.0f}' if b else x.get('status')} | {ratio} |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
