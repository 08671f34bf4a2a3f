"""The run directory's paths, its creation and lock, and run.json's reading and writing (`RunDir`)."""

from __future__ import annotations

import contextlib
import dataclasses
import errno
import json
import os
import pathlib
import tempfile
from typing import Iterable, Mapping


from cdjax.errors import RunDirError, reason, writing
from cdjax.io.jsonl import read_jsonl
from cdjax.io.records import READABLE_VERSIONS, _short, check_record

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
    def timings(self) -> pathlib.Path:
        return self.path / "timings.jsonl"

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

    def check_logs(self, then: str) -> None:
        """RunDirError (one sentence, ending with `then`: what was not done) when a compressed log of the run
        (metrics, eval or phase: `metrics.jsonl.xz`, ...) is damaged, so that no command uses part of it as the
        whole (cdjax.io.jsonl's one rule)."""
        for path in (self.metrics, self.eval, self.phase):
            damaged = read_jsonl(path).damaged
            if damaged:
                raise RunDirError(f"{damaged}; {then}")

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
        link = next((p for p in (self.path, *self.path.parents) if p.is_symlink() and not p.exists()), None)
        if link is not None:
            raise RunDirError(f"{option} {self.path}: {link} is a symbolic link to {os.readlink(link)}, which does not "
                              "exist; create its target or name another path.")

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
        self.check_run_writable()

    # What a run writes beside its logs: the folders probed by check_run_writable, and (below) its files.
    WRITTEN_DIRS = ("checkpoints", "tb", "plots", "videos")
    WRITTEN_FILES = ("run.json", "metrics.jsonl", "eval.jsonl", "phase.jsonl", "timings.jsonl", "summary.md",
                     "summary.csv", ".lock")

    def check_run_writable(self, dirs: Iterable[str] = WRITTEN_DIRS, files: Iterable[str] = WRITTEN_FILES) -> None:
        """RunDirError (one sentence naming the path) when something the run will write into already exists and
        cannot be written: its folders (checkpoints/ and each arm's, tb/, plots/, videos/: a file is made and removed
        in each, which a read-only mount or an immutable folder refuses even to root) and its files (opened for
        appending, nothing written), so that a fresh start or a resume is refused before any training rather than
        at its first checkpoint. `dirs` and `files`: what the command writes (default: what a sweep does). Changes
        no file."""
        folders = [self.path] if self.path.is_dir() else []
        for name in dirs:
            top = self.path / name
            if top.is_dir():
                below = top.iterdir() if name == "checkpoints" else top.rglob("*")  # a checkpoint is written once
                folders += [top, *sorted(p for p in below if p.is_dir())]
        for folder in folders:
            try:
                _probe(folder)
            except OSError as err:
                raise RunDirError(f"cannot write into {folder}: {reason(err)}; the command writes there, so nothing "
                                  "was started: make it writable, then run the command again.") from None
        paths = [self.path / name for name in files]
        paths += [p for p in (self.path / "plots").glob("*") if p.is_file()] if "plots" in dirs else []
        for path in paths:
            if not path.is_file():
                continue
            try:
                os.close(os.open(path, os.O_WRONLY | os.O_APPEND))
            except FileNotFoundError:
                continue  # removed since it was listed (by another process of the sweep): nothing to write into
            except OSError as err:
                raise RunDirError(f"cannot write {path}: {reason(err)}; the command writes it, so nothing was started: "
                                  "make it writable, then run the command again.") from None

    def create(self) -> None:
        """Make the directory (and its parents): RunDirError, one sentence, when that cannot be done."""
        self.check_writable()
        try:
            self.path.mkdir(parents=True, exist_ok=True)
            _probe(self.path)
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


PROBE = ".cdjax-write-test."


def _probe(folder: pathlib.Path) -> None:
    """Make and remove a file in `folder` (OSError when it cannot be written). Its name is this call's own, so that
    the processes of one sweep probing the same folder at once do not remove each other's."""
    fd, name = tempfile.mkstemp(prefix=PROBE, dir=folder)
    os.close(fd)
    os.unlink(name)


def left_before_a_run(name: str) -> bool:
    """Whether a file of this name is what a sweep stopped between making its directory and writing run.json leaves
    (the lock file, a write probe): a directory holding only these has no run, and a fresh sweep may start in it. A
    live sweep that holds the lock is still found: the new one takes the lock before it writes anything, and refuses
    in one sentence."""
    return name == ".lock" or name.startswith(PROBE)


def _exists(path: pathlib.Path) -> bool:
    try:
        return path.exists()
    except OSError:
        return False
