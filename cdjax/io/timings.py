"""Where a sweep's time goes: one row per timed step, kept by `run_sweep` and appended to timings.jsonl in the run
directory.

A row (JSON object):

    arm     the arm's name, or "all" for a step of the whole sweep
    what    what the step worked on: a program ("init", "reset", "phase", "chunk", "evaluator"), or a host step
            ("plan", "build", "memory", "programs", "setup", "evaluation": one evaluation of every arm, whole), the
            process's start-up before run_sweep where the `cdjax` command started it ("interpreter": from the process's
            start to cdjax's import, "imports": from there to run_sweep), or a file ("metrics.jsonl", "checkpoint")
    step    "trace", "lower", "compile", "compile in order" (the same program again in XLA's program order, where the
            first would not fit), "host", "init", "restore", "evaluate", "wait" (an evaluation waiting for its
            evaluator, compiled in the background while training ran), "write"
    s       seconds the step took (wall clock of the thread that ran it)
    start   when it began, in seconds since the sweep's process called run_sweep
    at      when it began, as a Unix time (time.time()): to place the rows in a whole process's time (its imports
            before run_sweep, its plots after)
    process the index of the process that timed it (cdjax.multihost); only process 0 writes the file

Programs are traced and lowered in the calling thread and compiled in compile threads, so compile rows overlap
one another in time (the evaluators' rows come from a background thread while training runs:
cdjax.runner.evaluations); a program taken from this process's cache (a second run_sweep of the same spec) has no row.
A resume appends its own rows after the earlier processes' (each process's `start` counts from its own call, and
its rows open with its "plan" row; the start-up rows that follow it have a negative `start`). Timing costs a clock
read and a dict per step: a few per chunk of training, none inside a compiled program.
"""

from __future__ import annotations

import contextlib
import json
import os
import pathlib
import sys
import threading
import time

from cdjax.errors import writing
from cdjax.io.jsonl import Rows, read_jsonl

STEPS = ("trace", "lower", "compile", "compile in order", "host", "init", "restore", "evaluate", "wait", "write")
_STARTUP_SAID: list = []  # not empty once a sweep of this process recorded its start-up
FIELDS = ("arm", "what", "step", "s", "start", "at", "process")


class Timings:
    """The rows of one process's sweep, in the order the steps ended (thread safe: compile threads add to it)."""

    def __init__(self, process: int = 0):
        self.process = process
        self.origin = time.perf_counter()  # `start` 0
        self.wall_origin = time.time()  # the Unix time of `origin`
        self.rows: list[dict] = []
        self._written = 0
        self._lock = threading.Lock()

    def add(self, arm: str, what: str, step: str, t0: float, end: float | None = None) -> dict:
        """The row of a step that began at time.perf_counter() `t0` and ended at `end` (default: now)."""
        if step not in STEPS:
            raise ValueError(f"timing step {step!r}: choose one of {STEPS}")
        end = time.perf_counter() if end is None else end
        row = {"arm": arm, "what": what, "step": step, "s": end - t0, "start": t0 - self.origin,
               "at": self.wall_origin + (t0 - self.origin), "process": self.process}
        with self._lock:
            self.rows.append(row)
        return row

    def add_startup(self) -> None:
        """Rows of this process's start-up before run_sweep where the `cdjax` command started the process:
        "interpreter" (from the process's start to cdjax's import) and "imports" (from there to now: the command's
        imports and arguments). Once per process: a second sweep in the same process had no start-up of its own."""
        if _STARTUP_SAID or not _started_by_command():
            return
        _STARTUP_SAID.append(True)
        package = sys.modules.get("cdjax")
        marks = [("interpreter", process_started()), ("imports", getattr(package, "_imported_at", None))]
        now = time.time()
        for (what, at), (_, end) in zip(marks, marks[1:] + [("", now)]):
            if at is not None and end is not None:
                self.add("all", what, "host", self.origin + (at - self.wall_origin),
                         self.origin + (end - self.wall_origin))

    @contextlib.contextmanager
    def time(self, arm: str, what: str, step: str):
        """Time the block as one row (also when it raises)."""
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.add(arm, what, step, t0)

    def select(self, step: str | None = None, arm: str | None = None, what: str | None = None) -> list[dict]:
        """The rows of a step (and arm, and what), in order."""
        return [r for r in list(self.rows) if (step is None or r["step"] == step) and (arm is None or r["arm"] == arm)
                and (what is None or r["what"] == what)]

    def total(self, step: str | None = None, arm: str | None = None, what: str | None = None) -> float:
        """Seconds summed over the rows `select` gives (overlapping compile rows count each)."""
        return sum(r["s"] for r in self.select(step, arm, what))

    def flush(self, path: str | os.PathLike) -> None:
        """Append the rows not yet written to `path` (timings.jsonl); WriteError on failure."""
        with self._lock:
            rows, self._written = self.rows[self._written:], len(self.rows)
        if not rows:
            return
        with writing(path), open(path, "a", encoding="utf-8") as f:
            f.write("".join(json.dumps(r) + "\n" for r in rows))


def timing_row_ok(row: dict) -> bool:
    """A row of timings.jsonl: the fields of FIELDS with their types."""
    def number(v) -> bool:
        return isinstance(v, (int, float)) and not isinstance(v, bool)

    return (all(isinstance(row.get(k), str) for k in ("arm", "what", "step"))
            and all(number(row.get(k)) for k in ("s", "start", "at")) and isinstance(row.get("process"), int))


def read_timings(run_dir: str | os.PathLike) -> Rows:
    """The rows of `run_dir`/timings.jsonl (empty when there is none; a torn or mistyped line is skipped and
    counted in `.skipped`)."""
    return read_jsonl(os.path.join(run_dir, "timings.jsonl"), check=timing_row_ok)


def _started_by_command() -> bool:
    """Whether the `cdjax` command started this process (its console script, or `python -m cdjax`)."""
    path = pathlib.Path(sys.argv[0]) if sys.argv and sys.argv[0] else None
    return path is not None and (path.name == "cdjax" or (path.name == "__main__.py" and path.parent.name == "cdjax"))


def process_started() -> float | None:
    """The Unix time this process started, to a clock tick (Linux's /proc); None where it cannot be read."""
    try:
        with open("/proc/self/stat") as f:
            ticks = int(f.read().rsplit(")", 1)[1].split()[19])  # field 22, starttime, after the command's name
        with open("/proc/stat") as f:
            boot = next(int(line.split()[1]) for line in f if line.startswith("btime "))
        return boot + ticks / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError, StopIteration):
        return None
