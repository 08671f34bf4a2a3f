"""The run directory: every file a sweep reads or writes, and every failure to write as one sentence.

    run.json                       the sweep (version 2): setting, the whole SweepSpec, the arms with their
                                   configs, hparams and hp labels, budgets, metric names, the command
    metrics.jsonl                  one object per (arm, hp, seed, update); NaN written as null
    phase.jsonl                    the pre-update phase's diagnostics per (arm, hp, seed)
    eval.jsonl                     evaluations (cdjax.evaluate.eval_records)
    timings.jsonl                  where each process's time went: tracing, compiling, init, restore, evaluations,
                                   writes (cdjax.io.timings)
    cdjax.log                      what the libraries (orbax, absl, asyncio, warnings) said during the sweep
    cdjax.process<i>.log           the same, of process i > 0 of a sweep of several processes (cdjax.multihost)
    .lock                          flock-ed by the process that trains in the directory (process 0 of several)
    tb/<arm>/<hp>/seed<s>/         TensorBoard event files
    checkpoints/<arm>/<updates>/   orbax checkpoints of the arm's state (cdjax.io.checkpoints); <updates>.unreadable
                                   and <updates>.restarted: checkpoints set aside (kept, no longer read)
    plots/, summary.md, summary.csv, videos/   cdjax.plots and `cdjax eval --video`

Writes that fail (a full disk, a read-only place) raise `WriteError`, a `RunDirError` whose message says
which file and why in one sentence. Readers never misread: run.json is refused in one sentence when it is not
UTF-8 JSON or a field has the wrong type (`check_record`); JSONL readers skip a torn line (a process killed while
writing), bytes that are not UTF-8 and rows whose fields have the wrong types for their file (`ROW_CHECKS`), and
count them, so that callers can say so; `truncate_jsonl` (a resume) drops the same lines.
"""

from __future__ import annotations

import jax
import numpy as np

from cdjax.errors import (  # the errors' old home: `from cdjax.io import RunDirError` works
    WRITE_FAILED, CheckpointMismatch, CheckpointWarning, RunDirError, WriteError, reason, writing)
from cdjax.io.checkpoints import Checkpoints, snapshot
from cdjax.io.jsonl import (PACKED, ROW_CHECKS, Rows, append_jsonl, eval_row_ok, jsonl_exists, jsonl_source,
                            metric_row_ok, read_jsonl, truncate_jsonl, write_packed)
from cdjax.io.records import (READABLE_VERSIONS, RUN_VERSION, check_record, dataclass_from_json, dataclass_to_json,
                              hparams_to_json, json_float, metric_rows, phase_rows)
from cdjax.io.rundir import RunDir, left_before_a_run
from cdjax.io.tensorboard import TensorBoard
from cdjax.io.timings import Timings, read_timings


def host(tree):
    """Device arrays -> numpy (blocks until they are computed)."""
    return jax.tree.map(np.asarray, jax.device_get(tree))


__all__ = ["RunDir", "RunDirError", "WriteError", "CheckpointMismatch", "CheckpointWarning", "Checkpoints", "TensorBoard", "Rows",
           "read_jsonl", "append_jsonl", "truncate_jsonl", "check_record", "metric_row_ok", "eval_row_ok",
           "metric_rows", "phase_rows", "json_float", "snapshot",
           "dataclass_to_json", "dataclass_from_json", "hparams_to_json", "host", "reason", "writing", "WRITE_FAILED",
           "PACKED", "ROW_CHECKS", "jsonl_exists", "jsonl_source", "write_packed", "READABLE_VERSIONS", "RUN_VERSION",
           "left_before_a_run", "Timings", "read_timings"]
