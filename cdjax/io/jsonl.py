"""JSONL files of the run directory: read (torn lines, bad bytes and mistyped rows skipped and counted), appended,
truncated to a resume's checkpoints.

One rule for compressed logs, for every reader and the resume alike: a log's rows are those of its compressed copy
(`metrics.jsonl.xz`, or an older `.gz`: the form experiments keep their logs in) followed by those of the plain file
beside it, if either exists. A resume folds the compressed copy into the plain file it goes on appending to. A
compressed copy that does not decompress to its end is damaged: `Rows.damaged` says where, and the plot and the
resume refuse it in one sentence rather than use part of the log."""

from __future__ import annotations

import json
import lzma
import os
import pathlib
import zlib
from typing import Iterable, Mapping

from cdjax.errors import RunDirError, reason, writing
from cdjax.io.records import _count, _list_of, _number


class Rows(list):
    """Rows of a JSONL file; `skipped` counts the lines left out: a torn line (a process killed while writing),
    bytes that are not UTF-8, or a row whose fields have the wrong types for its file. `damaged`: "" or, for a
    compressed copy that does not decompress to its end, a sentence naming it, the rows read and the last update."""

    skipped: int = 0
    damaged: str = ""


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


def _packed(path: pathlib.Path) -> pathlib.Path | None:
    """The compressed copy beside `path` (`path` + a suffix of `PACKED`, in that order), or None."""
    return next((c for c in (path.with_name(path.name + suffix) for suffix in PACKED) if c.exists()), None)


def _damage(packed: pathlib.Path, rows: list) -> str:
    """The sentence for a compressed copy cut or damaged after `rows` (the rows read from it)."""
    last = next((r for r in reversed(rows) if "update" in r), None)
    where = (f"the last row read is {last.get('arm', '?')} update {last['update']}" if last is not None
             else "no row could be read")
    return (f"{packed} is damaged: it decompresses only in part ({len(rows)} rows read; {where}), so the rows "
            "after that are missing")


def _lines(data: bytes, check, rows: Rows) -> list[dict]:
    out = []
    for line in data.split(b"\n"):
        if not line.strip():
            continue
        row = _row(line, check)
        if row is None:
            rows.skipped += 1
        else:
            out.append(row)
    return out


def read_jsonl(path: str | os.PathLike, check=...) -> Rows:
    """The objects of a JSONL file ([] when it does not exist); lines that cannot be read are skipped and counted.

    `check(row) -> bool` says which rows have the right types (default: by the file's name, `ROW_CHECKS`; None:
    any object). The rows of a compressed copy beside it (`metrics.jsonl.xz` or `.gz`, as the committed experiment
    data are stored) come first, then the file's own (the module's one rule); a copy that does not decompress to its
    end gives its readable rows, counts one torn line and sets `damaged`.
    """
    rows = Rows()
    path = pathlib.Path(path)
    if check is ...:
        check = ROW_CHECKS.get(path.name)
    try:
        packed = _packed(path)
        if packed is not None:
            data, whole = _unpack(packed)
            rows.extend(_lines(data, check, rows))
            if not whole:
                rows.skipped += 1
                rows.damaged = _damage(packed, rows)
        if path.exists():
            rows.extend(_lines(path.read_bytes(), check, rows))
    except OSError as err:
        raise RunDirError(f"cannot read {path}: {reason(err)}.") from None
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
    packed = _packed(path)
    try:
        data = path.read_bytes() if path.exists() or packed is None else b""
    except FileNotFoundError:
        return 0, 0
    except OSError as err:
        raise RunDirError(f"cannot read {path}: {reason(err)}.") from None
    if packed is not None:  # folded into the plain file, which the resume goes on appending to
        try:
            unpacked, whole = _unpack(packed)
        except OSError as err:
            raise RunDirError(f"cannot read {packed}: {reason(err)}.") from None
        if not whole:
            raise RunDirError(_damage(packed, _lines(unpacked, ROW_CHECKS.get(path.name), Rows()))
                              + f"; a resume would log over the gap: restore it, or keep its readable part as {path} "
                              f"(`xz -dc {packed} > {path}`, then remove {packed.name}) to go on without those rows.")
        data = unpacked + (b"" if not unpacked or unpacked.endswith(b"\n") else b"\n") + data
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
    if dropped or packed is not None:
        tmp = path.with_suffix(".jsonl.tmp")
        with writing(path):
            tmp.write_bytes(b"".join(kept))
            tmp.replace(path)
            if packed is not None:
                packed.unlink()
    return dropped, torn
