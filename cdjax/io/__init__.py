"""The run directory: every file a sweep reads or writes, and every failure to write as one sentence.

    run.json                       the sweep (version 2): setting, the whole SweepSpec, the arms with their
                                   configs, hparams and hp labels, budgets, metric names, the command
    metrics.jsonl                  one object per (arm, hp, seed, update); NaN written as null
    phase.jsonl                    the pre-update phase's diagnostics per (arm, hp, seed)
    eval.jsonl                     evaluations (cdjax.evaluate.eval_records)
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

import contextlib
import dataclasses
import errno
import json
import lzma
import math
import os
import pathlib
import re
import threading
import time
import zlib
from typing import Any, Iterable, Mapping, Sequence

import jax
import numpy as np

RUN_VERSION = 2
READABLE_VERSIONS = (1, 2)  # run.json versions that plots and evaluation read; only RUN_VERSION resumes


class RunDirError(ValueError):
    """A run directory that cannot be used as asked; the message is one sentence meant for the user."""


class WriteError(RunDirError):
    """Writing into the run directory failed (disk full, no permission); one sentence."""

    def __init__(self, *args):
        super().__init__(*args)
        WRITE_FAILED.set()


# Set once any write failed in this process. After a failed checkpoint write, tensorstore's own threads go on
# completing orbax's abandoned writes and print "Event loop is closed" tracebacks; the `cdjax` command drops
# what threads created outside Python write to stderr from then on (cdjax.cli).
WRITE_FAILED = threading.Event()


def reason(err: BaseException) -> str:
    """What an OS-level failure was, in words: "No space left on device" also from orbax's wrapped errors."""
    if isinstance(err, OSError) and err.strerror:
        return err.strerror
    code = re.search(r"os_error_code='?(\d+)", str(err))
    if code:
        return os.strerror(int(code.group(1)))
    text = str(err).splitlines()[0] if str(err) else type(err).__name__
    return text[:200]


@contextlib.contextmanager
def writing(path: str | os.PathLike):
    """Turn an OSError raised inside into a WriteError naming `path`."""
    try:
        yield
    except OSError as err:
        raise WriteError(f"cannot write {path}: {reason(err)}") from None


# ---------------------------------------------------------------------------------------------------
# Paths and run.json


@dataclasses.dataclass(frozen=True)
class RunDir:
    path: pathlib.Path

    @property
    def run_json(self) -> pathlib.Path:
        return self.path / "run.json"

    @property
    def metrics(self) -> pathlib.Path:
        return self.path / "metrics.jsonl"

    @property
    def eval(self) -> pathlib.Path:
        return self.path / "eval.jsonl"

    @property
    def phase(self) -> pathlib.Path:
        """Diagnostics of the pre-update phase (the update-0 rows of metrics.jsonl, kept apart for reading)."""
        return self.path / "phase.jsonl"

    @property
    def log(self) -> pathlib.Path:
        return self.path / "cdjax.log"

    def process_log(self, index: int) -> pathlib.Path:
        """The library log of process `index` of a sweep of several processes (cdjax.log for process 0)."""
        return self.log if index == 0 else self.path / f"cdjax.process{index}.log"

    def tb(self, arm: str, hp: str, seed: int) -> pathlib.Path:
        return self.path / "tb" / arm / hp / f"seed{seed}"

    def checkpoints(self, arm: str) -> pathlib.Path:
        return self.path / "checkpoints" / arm

    def arms_held(self, metric_rows: Iterable[Mapping] | None = None) -> dict[str, list[str]]:
        """{arm: where the directory holds something of it}: rows of metrics.jsonl (`metric_rows`, when the caller has
        read them), of eval.jsonl and phase.jsonl, and a directory under checkpoints/."""
        held: dict[str, list[str]] = {}
        for name, rows in (("metrics.jsonl", read_jsonl(self.metrics) if metric_rows is None else metric_rows),
                           ("eval.jsonl", read_jsonl(self.eval)), ("phase.jsonl", read_jsonl(self.phase))):
            for arm in dict.fromkeys(row["arm"] for row in rows):
                held.setdefault(arm, []).append(name)
        top = self.path / "checkpoints"
        for path in sorted(top.iterdir()) if top.is_dir() else ():
            if path.is_dir():
                held.setdefault(path.name, []).append(f"checkpoints/{path.name}")
        return held

    def unnamed_arms(self, names: Iterable[str] | None = None, metric_rows: Iterable[Mapping] | None = None) -> str:
        """A note naming the arms whose logs or checkpoints the directory holds but `names` (default: run.json's arms)
        does not, e.g. an arm removed from run.json by hand, with where each was found; "" when there are none."""
        names = set(names if names is not None else (arm["name"] for arm in self.read().get("arms", ())))
        stale = {arm: where for arm, where in self.arms_held(metric_rows).items() if arm not in names}
        if not stale:
            return ""
        held = ", ".join(f"{arm} ({', '.join(where)})" for arm, where in sorted(stale.items()))
        return (f"Note: {self.path} holds logs or checkpoints of arms that run.json does not name, left as found (an "
                f"arm removed from run.json by hand?): {held}; the summary and plots rank their logged runs beside "
                "this run's arms unless those are moved out.")

    def exists(self) -> bool:
        try:
            return self.run_json.is_file()
        except OSError:  # a name the file system cannot hold (too long): no run there
            return False

    def read(self) -> dict:
        """run.json (RunDirError, one sentence, when there is none, it is not UTF-8 JSON, its version is not
        readable or a field it holds has the wrong type: a run.json edited by hand is refused, not misread)."""
        try:
            data = self.run_json.read_bytes()
        except OSError as err:
            if isinstance(err, FileNotFoundError) or err.errno in (errno.ENOTDIR, errno.EISDIR):
                where = ("does not exist" if not self.path.exists() else
                         "is a file, not a run directory" if not self.path.is_dir() else "has no run.json")
                raise RunDirError(f"{self.path} holds no run ({where}); a run directory is the --out of a sweep, "
                                  f"started with `cdjax sweep --out DIR`.") from None
            raise RunDirError(f"cannot read {self.run_json}: {reason(err)}.") from None
        try:
            text = data.decode("utf-8")
        except UnicodeDecodeError as err:
            raise RunDirError(f"{self.run_json} is not UTF-8 text (byte {data[err.start]:#04x} at offset "
                              f"{err.start}); put back the run.json the sweep wrote.") from None
        try:
            run = json.loads(text)
        except json.JSONDecodeError as err:
            raise RunDirError(f"{self.run_json} is not valid JSON ({err.msg} at line {err.lineno}).") from None
        except RecursionError:
            raise RunDirError(f"{self.run_json} is not valid JSON (nested too deeply).") from None
        if not isinstance(run, dict) or run.get("version") not in READABLE_VERSIONS or isinstance(
                run.get("version"), bool):
            version = run.get("version") if isinstance(run, dict) else None
            raise RunDirError(f"{self.run_json} has version {_short(version)}; this cdjax reads versions "
                              f"{', '.join(map(str, READABLE_VERSIONS))}.")
        check_record(run, self.run_json)
        return run

    def read_if_present(self) -> dict:
        """run.json, or {} when the directory has none (plots of hand-made logs)."""
        return self.read() if self.exists() else {}

    def check_name(self, option: str = "--out") -> None:
        """RunDirError (one sentence) for a path this file system or cdjax's logs cannot hold: a name that is not
        UTF-8 text (bytes the command line could not decode), or a component or whole path longer than the file
        system allows. Touches nothing."""
        text = str(self.path)
        try:
            text.encode("utf-8")
        except UnicodeEncodeError:
            raise RunDirError(f"{option} {ascii(text)} is not UTF-8 text; choose a name of UTF-8 characters.") from None
        existing = next((p for p in self.path.absolute().parents if _exists(p)), pathlib.Path("/"))
        try:
            name_max = os.pathconf(existing, "PC_NAME_MAX")
            path_max = os.pathconf(existing, "PC_PATH_MAX")
        except (OSError, ValueError):
            name_max, path_max = 255, 4096
        for part in self.path.parts:
            if len(os.fsencode(part)) > name_max:
                raise RunDirError(f"{option}: the name {part[:40]!r}... is {len(os.fsencode(part))} bytes, longer than "
                                  f"the {name_max} this file system allows; choose a shorter one.")
        if len(os.fsencode(str(self.path.absolute()))) >= path_max:
            raise RunDirError(f"{option}: the path is {len(os.fsencode(str(self.path.absolute())))} bytes, longer than "
                              f"the {path_max} this file system allows; choose a shorter one.")

    def check_writable(self) -> None:
        """RunDirError (one sentence) when the directory could not be made or written; writes nothing."""
        self.check_name()
        if self.path.exists() and not self.path.is_dir():
            raise RunDirError(f"{self.path} is a file, not a directory; choose another --out.")
        existing = next(p for p in (self.path, *self.path.absolute().parents) if p.exists())
        if not existing.is_dir():
            raise RunDirError(f"cannot write into {self.path}: {os.strerror(errno.ENOTDIR)}; choose another --out.")
        if not os.access(existing, os.W_OK | os.X_OK):
            raise RunDirError(f"cannot write into {self.path}: {os.strerror(errno.EACCES)} ({existing}); choose another --out.")

    def create(self) -> None:
        """Make the directory (and its parents): RunDirError, one sentence, when that cannot be done."""
        self.check_writable()
        try:
            self.path.mkdir(parents=True, exist_ok=True)
            probe = self.path / ".cdjax-write-test"
            probe.write_bytes(b"")
            probe.unlink()
        except OSError as err:
            raise RunDirError(f"cannot write into {self.path}: {reason(err)}; choose another --out.") from None

    @contextlib.contextmanager
    def lock(self, advice: str = "wait for it to end or choose another --out"):
        """Hold the directory for one sweep, or one evaluation (an advisory lock, released when the process ends,
        also by kill -9): RunDirError, ending with `advice`, when another process holds it."""
        import fcntl

        with writing(self.path / ".lock"):  # only opening the lock file is this file's write: an error inside
            f = open(self.path / ".lock", "a")  # the sweep is reported by what raised it
        with f:
            try:
                fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                raise RunDirError(f"{self.path} is in use by another cdjax process; {advice}.") from None
            try:
                yield
            finally:
                fcntl.flock(f, fcntl.LOCK_UN)

    def write(self, run: dict) -> None:
        """Write run.json atomically (a half-written run.json would make the directory unreadable)."""
        tmp = self.run_json.with_suffix(".json.tmp")
        with writing(self.run_json):
            tmp.write_text(json.dumps(run, indent=2) + "\n")
            tmp.replace(self.run_json)


# What a sweep stopped between making its directory and writing run.json leaves (the lock file, a write probe): a
# directory holding only these has no run, and a fresh sweep may start in it. A live sweep that holds the lock is
# still found: the new one takes the lock before it writes anything, and refuses in one sentence.
LEFT_BEFORE_A_RUN = frozenset({".lock", ".cdjax-write-test"})


def _exists(path: pathlib.Path) -> bool:
    try:
        return path.exists()
    except OSError:
        return False


def json_float(x) -> float | None:
    """A float for JSON: NaN and infinities become None (null)."""
    x = float(x)
    return x if math.isfinite(x) else None


def _plain(value):
    """A numpy scalar as the Python number it holds (JSON writes those); anything else as it is."""
    return value.item() if isinstance(value, np.generic) else value


def dataclass_to_json(obj) -> dict:
    """A (frozen) dataclass of scalars and tuples as JSON fields (tuples become lists, numpy scalars numbers)."""
    return {f.name: ([_plain(x) for x in v] if isinstance(v := getattr(obj, f.name), tuple) else _plain(v))
            for f in dataclasses.fields(obj)}


def dataclass_from_json(cls, fields: Mapping[str, Any], where: str = "run.json"):
    """Inverse of dataclass_to_json: unknown names are an error (RunDirError), missing ones default."""
    known = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(fields) - known)
    if unknown:
        raise RunDirError(f"{where} names {cls.__name__} fields this cdjax does not know: {', '.join(unknown)}.")
    return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in fields.items()})


def hparams_to_json(hp) -> dict:
    return {f.name: float(getattr(hp, f.name)) for f in dataclasses.fields(hp)}


# What each field of run.json holds (checked when it is read, for the fields it has: a version 1 record lacks some).
def _whole(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool) or isinstance(v, float) and v.is_integer()


def _number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _count(v) -> bool:
    return _whole(v) and v >= 0


def _list_of(pred):
    return lambda v: isinstance(v, list) and all(pred(x) for x in v)


def _dict_of(pred):
    return lambda v: isinstance(v, dict) and all(isinstance(k, str) and pred(x) for k, x in v.items())


def _panel(v) -> bool:
    return isinstance(v, list) and len(v) == 3 and isinstance(v[0], str) and isinstance(v[1], str) and isinstance(
        v[2], bool)


def _metric_names(v) -> bool:
    return (isinstance(v, dict) and all(isinstance(v.get(k, ""), str) for k in ("return", "discounted_return"))
            and _list_of(_panel)(v.get("panels", [])) and isinstance(v.get("skipped", ""), (str, type(None))))


_RECORD = {  # field -> (what it must be, in words; test)
    "setting": ("a setting's name", lambda v: isinstance(v, str)),
    "base_config": ("an object of Config fields", lambda v: isinstance(v, dict)),
    "arms": ("a non-empty list of arms", lambda v: isinstance(v, list) and len(v) > 0),
    "grid": ("an object of hyper-parameter value lists", _dict_of(_list_of(_number))),
    "seeds": ("a positive integer", lambda v: _whole(v) and v >= 1),
    "seed": ("a non-negative integer", _count),
    "phase": ("an object or null", lambda v: v is None or isinstance(v, dict)),
    "final_eval": ("true or false", lambda v: isinstance(v, bool)),
    "metrics": ("an object of metric names", _metric_names),
    "command": ("a string", lambda v: isinstance(v, str)),
    **{name: ("a non-negative integer", _count) for name in (
        "total_env_steps", "requested_env_steps", "num_updates", "env_steps_per_update", "chunk_updates",
        "checkpoint_every", "eval_every", "eval_episodes", "bootstrap_reps")},
}
_ARM = {
    "name": ("an arm's name", lambda v: isinstance(v, str) and v != ""),
    "arm": ("a string", lambda v: v is None or isinstance(v, str)),
    "config": ("an object of Config fields", lambda v: isinstance(v, dict)),
    "hparams": ("a list of objects of numbers", _list_of(_dict_of(_number))),
    "hp_labels": ("a list of strings", _list_of(lambda x: isinstance(x, str))),
    "num_updates": ("a non-negative integer", _count),
    "phase_env_steps": ("a non-negative integer", _count),
    "total_env_steps": ("a non-negative integer", _count),
}


def _short(value, limit: int = 60) -> str:
    text = repr(value)
    return text if len(text) <= limit else text[:limit] + "..."


def check_record(run: dict, where: str | os.PathLike = "run.json") -> None:
    """RunDirError (one sentence naming the field) for a run.json field of the wrong type."""
    def refuse(name: str, what: str, value, got: str = "") -> None:
        raise RunDirError(f"{where}: {name} must be {what}, got {got or _short(value)}; put back the run.json the "
                          "sweep wrote.")

    for name, (what, ok) in _RECORD.items():
        if name in run and not ok(run[name]):
            refuse(name, what, run[name])
    for i, arm in enumerate(run.get("arms", [])):
        if not isinstance(arm, dict):
            refuse(f"arms[{i}]", "an object", arm)
        if "name" not in arm:  # every reader of the logs (plot, eval, a resume) finds an arm's rows by its name
            refuse(f"arms[{i}].name", _ARM["name"][0], None, got="no name")
        for name, (what, ok) in _ARM.items():
            if name in arm and not ok(arm[name]):
                refuse(f"arms[{i}].{name}", what, arm[name])
        if "hparams" in arm and "hp_labels" in arm and len(arm["hparams"]) != len(arm["hp_labels"]):
            refuse(f"arms[{i}].hp_labels", f"one label per hparams entry ({len(arm['hparams'])})", arm["hp_labels"])
    names = [a.get("name") for a in run.get("arms", [])]
    if len(set(names)) != len(names):
        refuse("arms", "a list of arms with distinct names", names)


# ---------------------------------------------------------------------------------------------------
# JSONL logs


class Rows(list):
    """Rows of a JSONL file; `skipped` counts the lines left out: a torn line (a process killed while writing),
    bytes that are not UTF-8, or a row whose fields have the wrong types for its file."""

    skipped: int = 0


def metric_row_ok(row: dict) -> bool:
    """A row of metrics.jsonl or phase.jsonl: arm, (hp,) seed, update and numbers (or null) for the rest."""
    return (isinstance(row.get("arm"), str) and isinstance(row.get("hp", ""), str) and _count(row.get("seed"))
            and _count(row.get("update"))
            and all(v is None or _number(v) for k, v in row.items() if k not in ("arm", "hp")))


def eval_row_ok(row: dict) -> bool:
    """A row of eval.jsonl (cdjax.evaluate.eval_records): the fields a reader uses have their types."""
    numbers = _list_of(lambda x: x is None or _number(x))
    checks = {"hp": lambda v: isinstance(v, str), "update": _count, "env_steps": _count, "episodes": _count,
              "deterministic": lambda v: isinstance(v, bool), "returns": numbers, "discounted_returns": numbers,
              "lengths": _list_of(_count)}
    return (isinstance(row.get("arm"), str) and _count(row.get("seed"))
            and all(ok(row[k]) for k, ok in checks.items() if k in row)
            and all(v is None or _number(v) for k, v in row.items() if k.startswith("eval/")))


ROW_CHECKS = {"metrics.jsonl": metric_row_ok, "phase.jsonl": metric_row_ok, "eval.jsonl": eval_row_ok}


# Compressed copies of a JSONL file, read in its place when it is missing: the form experiments keep their logs in
# (`metrics.jsonl.xz`, `write_packed`) first, then the older one (`metrics.jsonl.gz`).
PACKED = (".xz", ".gz")


def jsonl_source(path: str | os.PathLike) -> pathlib.Path | None:
    """The file `read_jsonl(path)` reads: `path` itself, else its compressed copy beside it (`path` + a suffix of
    `PACKED`, in that order), else None."""
    path = pathlib.Path(path)
    for candidate in (path, *(path.with_name(path.name + suffix) for suffix in PACKED)):
        if candidate.exists():
            return candidate
    return None


def jsonl_exists(path: str | os.PathLike) -> bool:
    """Whether `read_jsonl(path)` has a file to read: the JSONL file or its compressed copy (`jsonl_source`)."""
    return jsonl_source(path) is not None


def write_packed(path: str | os.PathLike, data: bytes) -> pathlib.Path:
    """Write `data` (the bytes of the JSONL file `path`) as `path` + ".xz", what `xz -9e` makes of them (the format
    has no timestamp: the same rows give the same bytes, so a rebuilt copy does not show as a change in git), and
    remove the other compressed copies of `path` beside it, so that one file holds its rows. WriteError on failure."""
    path = pathlib.Path(path)
    target = path.with_name(path.name + PACKED[0])
    with writing(target):
        target.parent.mkdir(parents=True, exist_ok=True)
        target.write_bytes(lzma.compress(data, format=lzma.FORMAT_XZ, check=lzma.CHECK_CRC64,
                                         preset=9 | lzma.PRESET_EXTREME))
        for suffix in PACKED[1:]:
            path.with_name(path.name + suffix).unlink(missing_ok=True)
    return target


def _decompress(data: bytes, engine, error) -> tuple[bytes, bool]:
    """(what decompresses of the streams in `data`, whether all of it did): a damaged or cut file gives its readable
    start. `engine()` makes a decompressor of one stream (zlib's or lzma's); `error` is what it raises."""
    out, whole = [], True
    while data:
        decompressor = engine()
        try:
            out.append(decompressor.decompress(data))
        except error:
            whole = False
            break
        if not decompressor.eof:
            whole = False
            break
        data = decompressor.unused_data  # a second stream (files concatenated)
    return b"".join(out), whole


def _unpack(path: pathlib.Path) -> tuple[bytes, bool]:
    """The decompressed bytes of a compressed copy (suffix ".xz" or ".gz") and whether all of it decompressed."""
    if path.suffix == ".xz":
        return _decompress(path.read_bytes(), lambda: lzma.LZMADecompressor(lzma.FORMAT_XZ), lzma.LZMAError)
    return _decompress(path.read_bytes(), lambda: zlib.decompressobj(16 + zlib.MAX_WBITS), zlib.error)


def _row(line: bytes, check) -> dict | None:
    """The object of one JSONL line, or None: not UTF-8, not JSON, not an object, or the wrong types."""
    try:
        row = json.loads(line.decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError, RecursionError):
        return None
    if not isinstance(row, dict) or (check is not None and not check(row)):
        return None
    return row


def read_jsonl(path: str | os.PathLike, check=...) -> Rows:
    """The objects of a JSONL file ([] when it does not exist); lines that cannot be read are skipped and counted.

    `check(row) -> bool` says which rows have the right types (default: by the file's name, `ROW_CHECKS`; None:
    any object). A kept copy compressed beside the missing file (`metrics.jsonl.xz` or `.gz`, as the committed
    experiment data are stored: `jsonl_source`) is read in its place; what of it cannot be decompressed counts as
    one torn line.
    """
    rows = Rows()
    path = pathlib.Path(path)
    if check is ...:
        check = ROW_CHECKS.get(path.name)
    try:
        source = jsonl_source(path)
        if source is None:
            return rows
        if source == path:
            data = path.read_bytes()
        else:
            data, whole = _unpack(source)
            rows.skipped += not whole
    except OSError as err:
        raise RunDirError(f"cannot read {path}: {reason(err)}.") from None
    for line in data.split(b"\n"):
        if not line.strip():
            continue
        row = _row(line, check)
        if row is None:
            rows.skipped += 1
        else:
            rows.append(row)
    return rows


def append_jsonl(path: str | os.PathLike, rows: Iterable[dict]) -> pathlib.Path:
    """Append rows, one JSON object per line (NaN written as null), in one write; WriteError on failure. A torn
    last line (a process killed while writing) is ended first, so that it stays one skipped line of its own."""
    path = pathlib.Path(path)
    text = "".join(json.dumps(row, allow_nan=False) + "\n" for row in rows)
    with writing(path):
        path.parent.mkdir(parents=True, exist_ok=True)
        with path.open("ab+") as f:
            if f.tell() > 0:
                f.seek(-1, os.SEEK_END)
                if f.read(1) != b"\n":
                    text = "\n" + text
            f.write(text.encode())
            f.flush()
    return path


def truncate_jsonl(path: pathlib.Path, done: Mapping[str, int]) -> tuple[int, int]:
    """Keep the rows of each arm up to `done[arm]` updates (those the restored checkpoints hold; an arm at -1 keeps
    none; the rows of an arm `done` does not name are not this run's to judge and are kept).

    Drops the rows a killed process wrote after its last checkpoint, and what `read_jsonl` would skip (torn
    lines, bytes that are not UTF-8, rows of the wrong types). Returns (rows dropped, of which unreadable).
    """
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        return 0, 0
    except OSError as err:
        raise RunDirError(f"cannot read {path}: {reason(err)}.") from None
    check = ROW_CHECKS.get(path.name)
    kept, dropped, torn = [], 0, 0
    lines = data.split(b"\n")
    for i, line in enumerate(lines):
        if not line.strip():
            continue
        row = _row(line, check) if i < len(lines) - 1 else None  # the last piece has no newline: torn
        if row is None or "update" not in row:
            dropped, torn = dropped + 1, torn + 1
        elif row["arm"] not in done or row["update"] <= done[row["arm"]]:
            kept.append(line + b"\n")
        else:
            dropped += 1
    if dropped:
        tmp = path.with_suffix(".jsonl.tmp")
        with writing(path):
            tmp.write_bytes(b"".join(kept))
            tmp.replace(path)
    return dropped, torn


def metric_rows(arm: str, labels: Sequence[str], num_seeds: int, metrics: Mapping, first_update: int,
                steps_per_update: int, wall_start: float, wall_end: float, steps_offset: int = 0) -> list[dict]:
    """Rows of metrics.jsonl for one chunk of one arm.

    metrics: {name: [R, n]} on the host, runs hp-major (run r = i * num_seeds + s). `update` counts the
    updates done (1-based), `env_steps` the environment steps of that run so far (`steps_offset`: those
    of a phase before the first update), `wall_s` the training wall-clock of the sweep (compile
    excluded), interpolated linearly inside the chunk.
    """
    names = sorted(metrics)
    n = next(iter(metrics.values())).shape[1]
    rows = []
    for i, label in enumerate(labels):
        for s in range(num_seeds):
            r = i * num_seeds + s
            for j in range(n):
                update = first_update + j + 1
                row = {"arm": arm, "hp": label, "seed": s, "update": update,
                       "env_steps": steps_offset + update * steps_per_update,
                       "wall_s": round(wall_start + (wall_end - wall_start) * (j + 1) / n, 3)}
                row.update({name: json_float(metrics[name][r, j]) for name in names})
                rows.append(row)
    return rows


def phase_rows(arm: str, labels: Sequence[str], num_seeds: int, info: Mapping, env_steps: int, wall_start: float,
               wall_end: float, as_metrics: Mapping[str, str]) -> list[dict]:
    """Rows (update 0) of a phase of one arm: info {name: [R]} on the host, runs hp-major.

    Every diagnostic is kept under "phase/<name>"; those named in `as_metrics` are also the row's metric
    of the given name (e.g. the distilled policy's return is the first point of the return curve).
    """
    rows = []
    for i, label in enumerate(labels):
        for s in range(num_seeds):
            r = i * num_seeds + s
            row = {"arm": arm, "hp": label, "seed": s, "update": 0, "env_steps": env_steps,
                   "wall_s": round(wall_end, 3), "phase_wall_s": round(wall_end - wall_start, 3)}
            row.update({f"phase/{name}": json_float(value[r]) for name, value in sorted(info.items())})
            row.update({new: json_float(info[old][r]) for old, new in as_metrics.items() if old in info})
            rows.append(row)
    return rows


# ---------------------------------------------------------------------------------------------------
# TensorBoard


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
                # One event per row holding all its scalars (TensorBoard reads each value as its own series): one
                # event per scalar took ~0.45 ms a row, ~0.9 s of host time for a 10-run chunk of 200 updates while
                # the GPU waited for the next chunk.
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


def host(tree):
    """Device arrays -> numpy (blocks until they are computed)."""
    return jax.tree.map(np.asarray, jax.device_get(tree))


from cdjax.io.checkpoints import (  # noqa: E402  (uses the errors above)
    CheckpointMismatch, CheckpointWarning, Checkpoints, snapshot)

__all__ = ["RunDir", "RunDirError", "WriteError", "CheckpointMismatch", "CheckpointWarning", "Checkpoints", "TensorBoard", "Rows",
           "read_jsonl", "append_jsonl", "truncate_jsonl", "check_record", "metric_row_ok", "eval_row_ok",
           "metric_rows", "phase_rows", "json_float", "snapshot",
           "dataclass_to_json", "dataclass_from_json", "hparams_to_json", "host", "reason", "writing"]
