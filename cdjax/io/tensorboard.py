"""TensorBoard event files of a sweep, one per run, written synchronously by the caller's thread."""

from __future__ import annotations

import contextlib
import re
import time
from typing import Any, Iterable, Mapping


from cdjax.errors import writing
from cdjax.io.rundir import RunDir

_TAG_UNSAFE = re.compile(r"[^-/\w.]")  # what TensorBoard's tags may not hold (tensorboardX's scalar() cleans the same)


class TensorBoard:
    """One TensorBoard event file per run (step = env steps of the run), written synchronously.

    tensorboardX's SummaryWriter writes from a thread and closes at exit, so a full disk surfaces there as
    tracebacks; here each chunk's events are written and flushed by the caller's thread (WriteError on
    failure). A resumed run starts its files with a purge event at the restored step: TensorBoard then
    hides the events an interrupted process wrote past it.
    """

    def __init__(self, run_dir: RunDir, purge_steps: Mapping[str, int] | None = None):
        self.run_dir = run_dir
        self.purge_steps = dict(purge_steps or {})
        self.writers: dict[tuple, Any] = {}

    def _writer(self, arm: str, hp: str, seed: int):
        from tensorboardX.event_file_writer import EventsWriter
        from tensorboardX.proto.event_pb2 import Event, SessionLog

        key = (arm, hp, seed)
        if key not in self.writers:
            directory = self.run_dir.tb(arm, hp, seed)
            directory.mkdir(parents=True, exist_ok=True)
            writer = EventsWriter(str(directory / "events"), filename_suffix=f".{time.time_ns()}")  # a resumed run adds a file
            purge = self.purge_steps.get(arm)
            if purge:
                writer.write_event(Event(step=purge, wall_time=time.time(),
                                         session_log=SessionLog(status=SessionLog.START)))
            self.writers[key] = writer
        return self.writers[key]

    def write(self, rows: Iterable[dict]) -> None:
        from tensorboardX.proto.event_pb2 import Event
        from tensorboardX.proto.summary_pb2 import Summary

        skip = {"arm", "hp", "seed", "update", "env_steps"}
        with writing(self.run_dir.path / "tb"):
            touched = set()
            for row in rows:
                writer = self._writer(row["arm"], row["hp"], row["seed"])
                touched.add(id(writer))
                # One event per row holding all its scalars (TensorBoard reads each value as its own series): an
                # event per scalar multiplies the host's work per row, which a chunk's logging makes the devices
                # wait for.
                values = [Summary.Value(tag=_TAG_UNSAFE.sub("_", name), simple_value=float(value))
                          for name, value in row.items() if name not in skip and value is not None]
                writer.write_event(Event(wall_time=time.time(), step=int(row["env_steps"]),
                                         summary=Summary(value=values)))
            for writer in self.writers.values():
                if id(writer) in touched:
                    writer.flush()

    def close(self) -> None:
        writers, self.writers = list(self.writers.values()), {}
        for writer in writers:
            with contextlib.suppress(OSError):  # a failed flush was reported when it happened
                writer.close()
