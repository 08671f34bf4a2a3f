"""Experiment units: what each runs, run in the foreground, or started in the background, polled and collected.

An experiment's unit is one plain command on any GPU (a SLURM job's sbatch line calls it as it is):

    python -m experiments.EXPERIMENT list                          # its units, their budgets and wall-clock
    python -m experiments.EXPERIMENT run UNIT --out DIR [--time-limit S]

(EXPERIMENT: paper_obs_space, pixel, atari, offpolicy). Where a command may not outlive a few minutes (a leased machine whose
commands are cut at 10), the same units run detached and are polled:

    python -m experiments.launch start EXPERIMENT UNIT [UNIT ...] --work DIR [--time-limit S] [--gpu I]
    python -m experiments.launch poll DIR [--wait S]     # exit status 0: every unit ended; 3: still running
    python -m experiments.launch collect DIR OUT         # OUT/UNIT.tar.gz (logs thinned) and OUT/UNIT.log per unit

`start` starts one process session (setsid: it outlives the call, not the machine) that runs the units one after
another on GPU I (CUDA_VISIBLE_DEVICES), unit U in DIR/U/ with its output in DIR/U/unit.log and its exit status in
DIR/U/exit_code; with --time-limit each gets what is left of it when the unit before ended (a unit that would get
less than --min-s is skipped), without it its own default. Several GPUs of one machine: one `start` per GPU, each
with its own DIR. `collect` packs each ended unit: its run directories with their metrics thinned
(experiments.thin_logs, with the experiment's THIN options), every other file it wrote but checkpoints and
TensorBoard files.

For pixel and atari the units are lists of `Step`s (a command, its log, its hang guard) run by `run_unit`;
paper_obs_space's units are sweeps of cdjax, run in its own process.
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib
import json
import os
import pathlib
import shlex
import shutil
import signal
import subprocess
import sys
import tarfile
import tempfile
import time
from collections.abc import Callable, Mapping, Sequence

EXPERIMENTS = ("paper_obs_space", "pixel", "atari", "offpolicy")
RUNNING = 3  # poll's exit status while a unit runs
SKIPPED = 75  # a unit's exit status when too little time was left to start it (EX_TEMPFAIL, as --time-limit)
CHECKPOINTS = ("checkpoints",)  # directories collect leaves behind


@dataclasses.dataclass(frozen=True)
class Context:
    """What a unit's steps are built from: its directory, time limits (seconds from its start) and parameters."""

    out: pathlib.Path
    limit: int  # the training's time limit
    end: int  # when everything (evaluation, plots) should have ended
    params: Mapping[str, str]
    started: float = dataclasses.field(default_factory=time.monotonic)

    def elapsed(self) -> float:
        return time.monotonic() - self.started


@dataclasses.dataclass(frozen=True)
class Step:
    """One command of a unit. `timeout` (seconds, or a function of the Context giving them when the step starts) is
    a hang guard: then `signal`, and SIGKILL `kill_after` seconds later (exit status 124, as GNU timeout)."""

    argv: tuple[str, ...]
    log: str | None = None  # a file under the unit's directory for its output; None: the unit's own output
    timeout: int | Callable[[Context], int] | None = None
    signal: int = signal.SIGINT
    kill_after: int = 60
    env: Mapping[str, str] = dataclasses.field(default_factory=dict)
    when: Callable[[Context], bool] | None = None  # run only where this says so (when the step starts)
    failed: str = ""  # said when it fails

    def line(self) -> str:
        env = " ".join(f"{k}={shlex.quote(v)}" for k, v in self.env.items())
        return " ".join(filter(None, [env, shlex.join(self.argv), f"> {self.log}" if self.log else ""]))


@dataclasses.dataclass(frozen=True)
class Unit:
    """A unit of an experiment: `steps` builds its commands, `show` names files printed when they end."""

    name: str
    about: str  # what it runs: its budget
    minutes: float  # expected wall-clock on one GPU of the kind it ran on, start to end
    steps: Callable[[Context], list[Step]]
    params: Mapping[str, str] = dataclasses.field(default_factory=dict)  # its parameters' defaults
    show: Callable[[Context], list[str]] = lambda ctx: []

    def context(self, out: pathlib.Path, limit: int, end: int, given: Sequence[str] = ()) -> Context:
        params = dict(self.params)
        for item in given:
            key, sep, value = item.partition("=")
            if not sep or key not in params:
                known = ", ".join(params) or "none"
                raise ValueError(f"unit {self.name} has no parameter {key!r} (its parameters: {known})")
            params[key] = value
        return Context(out=out, limit=limit, end=end, params=params)


def python(*args: str) -> tuple[str, ...]:
    """A `python -m` command line (run with this interpreter)."""
    return ("python", "-m", *args)


def _run_step(step: Step, ctx: Context) -> int:
    argv = [sys.executable, *step.argv[1:]] if step.argv[0] == "python" else list(step.argv)
    timeout = step.timeout(ctx) if callable(step.timeout) else step.timeout
    out = open(ctx.out / step.log, "w") if step.log else None  # noqa: SIM115 (closed below)
    try:
        proc = subprocess.Popen(argv, stdout=out or sys.stdout, stderr=subprocess.STDOUT if out else None,
                                env={**os.environ, **step.env})
        try:
            return proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            proc.send_signal(step.signal)
            try:
                proc.wait(timeout=step.kill_after)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
            return 124
    finally:
        if out:
            out.close()


def run_unit(unit: Unit, ctx: Context) -> int:
    """Every step in turn (a step that fails does not stop the next); the first non-zero exit status, else 0."""
    ctx.out.mkdir(parents=True, exist_ok=True)
    status = 0
    for step in unit.steps(ctx):
        if step.when is not None and not step.when(ctx):
            continue
        print(f"$ {step.line()}", flush=True)
        code = _run_step(step, ctx)
        sys.stdout.flush()
        if code:
            print(step.failed or f"exit status {code}", flush=True)
            status = status or code
    for name in unit.show(ctx):
        path = ctx.out / name
        if path.is_file():
            print(f"== {name}\n{path.read_text()}", flush=True)
    return status


def unit_main(prog: str, units: Mapping[str, Unit], limit: int, end: int, argv=None) -> int:
    """`list` and `run` of an experiment whose units are Steps."""
    p = argparse.ArgumentParser(prog=prog)
    sub = p.add_subparsers(dest="command", required=True)
    sub.add_parser("list", help="the units, what each runs and its expected wall-clock")
    r = sub.add_parser("run", help="one unit, in the foreground")
    r.add_argument("unit", choices=list(units), metavar="UNIT")
    r.add_argument("--out", type=pathlib.Path, help="the unit's directory (default runs/<unit>)")
    r.add_argument("--time-limit", type=int, default=limit, metavar="S",
                   help=f"seconds its training may take, compile included (default {limit})")
    r.add_argument("--end", type=int, metavar="S",
                   help=f"seconds from its start by which its evaluation and plots end (default the time limit + "
                        f"{end - limit})")
    r.add_argument("--param", action="append", default=[], metavar="NAME=VALUE", help="one of the unit's parameters")
    args = p.parse_args(argv)
    if args.command == "list":
        print("| unit | what it runs | expected wall-clock | parameters |\n|---|---|---|---|")
        for u in units.values():
            params = ", ".join(f"{k}={v!r}" for k, v in u.params.items())
            print(f"| {u.name} | {u.about} | {u.minutes:g} min | {params} |")
        return 0
    unit = units[args.unit]
    try:
        ctx = unit.context(args.out or pathlib.Path("runs") / unit.name, args.time_limit,
                           args.end if args.end is not None else args.time_limit + end - limit, args.param)
    except ValueError as err:
        p.error(str(err))
    return run_unit(unit, ctx)


# --- in the background ---------------------------------------------------------------------------------------------


def package(name: str) -> str:
    """The package run as `python -m PACKAGE run UNIT`: experiments.NAME for the experiments here, else NAME."""
    return f"experiments.{name}" if name in EXPERIMENTS else name


def experiment(name: str):
    """The module that holds an experiment's UNITS (and THIN: experiments.thin_logs' points and tail for it)."""
    module = importlib.import_module(package(name))
    return module if hasattr(module, "UNITS") else importlib.import_module(f"{package(name)}.units")


def _queue(work: pathlib.Path) -> int:
    """The detached process: the units of work/queue.json one after another."""
    q = json.loads((work / "queue.json").read_text())
    limit = q["time_limit"]  # None: each unit its own default
    for name in q["units"]:
        d = work / name
        d.mkdir(parents=True, exist_ok=True)
        left = None if limit is None else int(q["started"] + limit - time.time())
        if left is not None and left < q["min_s"]:
            (d / "unit.log").write_text(f"skipped: {left} s left, it needs {q['min_s']}\n")
            (d / "exit_code").write_text(f"{SKIPPED}\n")
            continue
        argv = [sys.executable, "-m", package(q["experiment"]), "run", name, "--out", str(d),
                *(() if left is None else ("--time-limit", str(left))), *q["args"]]
        (d / "command").write_text(shlex.join(["python", *argv[1:]]) + "\n")
        with open(d / "unit.log", "w") as log:
            code = subprocess.call(argv, stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                   env={**os.environ, "PYTHONUNBUFFERED": "1", **q["env"]})
        (d / "exit_code").write_text(f"{code}\n")
    (work / "done").write_text("")
    return 0


def experiment_units(name: str) -> Mapping:
    return experiment(name).UNITS


def start(experiment: str, units: Sequence[str], work: pathlib.Path, time_limit: int | None = None,
          gpu: int | None = None, min_s: int = 0, args: Sequence[str] = ()) -> bool:
    """Start the queue once (False where work/ already holds one: a poll finds it)."""
    unknown = [u for u in units if u not in experiment_units(experiment)]
    if unknown:
        raise ValueError(f"{experiment} has no unit {', '.join(unknown)} (`python -m experiments.{experiment} list`)")
    if (work / "queue.json").exists():
        return False
    work.mkdir(parents=True, exist_ok=True)
    env = {} if gpu is None else {"CUDA_VISIBLE_DEVICES": str(gpu)}
    (work / "queue.json").write_text(json.dumps({
        "experiment": experiment, "units": list(units), "time_limit": time_limit, "min_s": min_s, "args": list(args),
        "env": env, "started": time.time()}, indent=1))
    subprocess.Popen([sys.executable, "-m", "experiments.launch", "_queue", str(work)], start_new_session=True,
                     stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                     cwd=os.getcwd())
    return True


def state(work: pathlib.Path) -> dict[str, str]:
    """Each unit's state: 'waiting', 'running' or 'exit N'."""
    q = json.loads((work / "queue.json").read_text())
    out = {}
    for name in q["units"]:
        d = work / name
        code = d / "exit_code"
        out[name] = f"exit {code.read_text().strip()}" if code.exists() else "running" if d.exists() else "waiting"
    return out


def poll(work: pathlib.Path, wait_s: float = 0, tail: int = 6) -> int:
    """Wait up to wait_s for the queue to end; print each unit's state and the running unit's last lines."""
    if not (work / "queue.json").exists():
        print(f"{work}: nothing started there", file=sys.stderr)
        return 2
    stop = time.monotonic() + wait_s
    while not (work / "done").exists() and time.monotonic() < stop:
        time.sleep(2)
    started = json.loads((work / "queue.json").read_text())["started"]
    print(f"{time.time() - started:.0f} s since it started")
    for name, s in state(work).items():
        print(f"{name}: {s}")
        if s == "running":
            lines = [x for x in (work / name / "unit.log").read_text(errors="replace").splitlines()
                     if x.strip() and "warn" not in x.lower()]
            print("\n".join("  " + x for x in lines[-tail:]))
    if (work / "done").exists():
        print("DONE")
        return 0
    print(f"RUNNING: poll again (python -m experiments.launch poll {work})")
    return RUNNING


def pack(unit_dir: pathlib.Path, dest: pathlib.Path, thin: Mapping[str, int] | None = None) -> pathlib.Path:
    """dest/<unit>.tar.gz of unit_dir: run directories thinned (experiments.thin_logs), every other file but
    checkpoints and TensorBoard files as it is."""
    from experiments import thin_logs

    thin = {"points": 250, "tail": 60, **(thin or {})}
    name = unit_dir.name
    with tempfile.TemporaryDirectory() as tmp:
        copy = pathlib.Path(tmp) / name
        runs = [p.parent for p in unit_dir.rglob("run.json")]
        thin_logs.thin_dir(unit_dir, copy, thin["points"], thin["tail"])
        for path in unit_dir.rglob("*"):
            rel = path.relative_to(unit_dir)
            if (not path.is_file() or any(r in path.parents for r in runs)
                    or any(part in CHECKPOINTS for part in rel.parts) or path.name.startswith("events.out.tfevents")):
                continue
            (copy / rel).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(path, copy / rel)
        copy.mkdir(parents=True, exist_ok=True)
        dest.mkdir(parents=True, exist_ok=True)
        target = dest / f"{name}.tar.gz"
        with tarfile.open(target, "w:gz") as tar:
            tar.add(copy, arcname=name)
    return target


def collect(work: pathlib.Path, dest: pathlib.Path) -> list[pathlib.Path]:
    """Every ended unit of the queue packed into dest (UNIT.tar.gz, UNIT.log)."""
    q = json.loads((work / "queue.json").read_text())
    thin = getattr(experiment(q["experiment"]), "THIN", None)
    written = []
    for name, s in state(work).items():
        if not s.startswith("exit"):
            continue
        d = work / name
        written.append(pack(d, dest, thin))
        shutil.copy2(d / "unit.log", dest / f"{name}.log")
    return written


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m experiments.launch", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="command", required=True)
    s = sub.add_parser("start", help="start units one after another in the background (once: again, it says so)")
    s.add_argument("experiment", help=f"{', '.join(EXPERIMENTS)} (or a package of units, run as python -m)")
    s.add_argument("units", nargs="+", metavar="UNIT")
    s.add_argument("--work", type=pathlib.Path, required=True, help="the queue's directory")
    s.add_argument("--time-limit", type=int, metavar="S",
                   help="seconds the units' training may take in all, from the start (each unit gets what is left as "
                        "its --time-limit; default: each unit its own default)")
    s.add_argument("--min-s", type=int, default=0, metavar="S", help="skip a unit left fewer seconds than this")
    s.add_argument("--gpu", type=int, help="the GPU (CUDA_VISIBLE_DEVICES) the units run on")
    s.add_argument("--arg", action="append", default=[], metavar="ARG",
                   help="one more argument to every unit's `run` (repeat: --arg=--param --arg=updates=150)")
    pl = sub.add_parser("poll", help="wait for the units; exit status 0 when all ended, 3 while one runs")
    pl.add_argument("work", type=pathlib.Path)
    pl.add_argument("--wait", type=float, default=0, metavar="S", help="seconds to wait for the end (default 0)")
    c = sub.add_parser("collect", help="pack every ended unit into OUT")
    c.add_argument("work", type=pathlib.Path)
    c.add_argument("out", type=pathlib.Path)
    q = sub.add_parser("_queue")  # the detached process
    q.add_argument("work", type=pathlib.Path)
    args = p.parse_args(argv)
    if args.command == "_queue":
        return _queue(args.work)
    if args.command == "start":
        try:
            new = start(args.experiment, args.units, args.work, args.time_limit, args.gpu, args.min_s, args.arg)
        except ValueError as err:
            p.error(str(err))
        print(f"{'STARTED' if new else 'already started'}: {' '.join(args.units)} in {args.work}")
        return 0
    if args.command == "poll":
        return poll(args.work, args.wait)
    for path in collect(args.work, args.out):
        print(path)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
