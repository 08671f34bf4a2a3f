"""Copies of run directories small enough to bring back from a GPU machine and to commit.

    python -m experiments.thin_logs SRC_DIR DEST_DIR [--points 250] [--tail 60]

Every run directory under SRC_DIR (a directory holding run.json) is copied to the same relative path under
DEST_DIR with its run.json, eval.jsonl, summary.md, log.txt, phase.jsonl and machine.json where they exist, and
its metrics.jsonl thinned and compressed (metrics.jsonl.xz, `cdjax.io.write_packed`, which `cdjax.io.read_jsonl`
reads in place of a missing metrics.jsonl):
per run (arm, hyper-parameter label, seed), every update of the last `tail` logged updates (the window the
reports average over) and, before them, evenly spaced updates so that a run keeps about `points` rows; each
run's first two and last rows are always kept. Checkpoints, TensorBoard files and videos are left behind.
The reports read the copies as they read the originals; throughputs computed from the first and last rows
are unchanged.
"""

from __future__ import annotations

import argparse
import collections
import json
import pathlib
import shutil

from cdjax import io

KEPT = ("run.json", "eval.jsonl", "summary.md", "log.txt", "phase.jsonl", "machine.json")


def thin_rows(rows: list[dict], points: int, tail: int) -> list[dict]:
    """The rows kept of one metrics.jsonl (original order)."""
    by_run: dict[tuple, list[int]] = collections.defaultdict(list)
    for i, r in enumerate(rows):
        by_run[(r.get("arm"), r.get("hp"), r.get("seed"))].append(i)
    keep = set()
    for idx in by_run.values():
        head, last = idx[:-tail] if tail else idx, idx[-tail:] if tail else []
        step = max(1, -(-len(head) // max(points - len(last), 1)))
        keep.update(head[::step])
        keep.update(last)
        keep.update((idx[0], idx[-1]) + tuple(idx[1:2]))  # the second: the first update after a phase's row
    return [rows[i] for i in sorted(keep)]


def thin_dir(src: pathlib.Path, dest: pathlib.Path, points: int = 250, tail: int = 60) -> list[pathlib.Path]:
    """Thinned copies of every run directory under `src`; returns the run directories written."""
    written = []
    for run_json in sorted(src.rglob("run.json")):
        run = run_json.parent
        out = dest / run.relative_to(src)
        out.mkdir(parents=True, exist_ok=True)
        for name in KEPT:
            if (run / name).exists():
                shutil.copy2(run / name, out / name)
        metrics = run / "metrics.jsonl"
        if metrics.exists():
            with metrics.open() as f:
                rows = [json.loads(line) for line in f if line.strip()]
            text = "".join(json.dumps(r) + "\n" for r in thin_rows(rows, points, tail))
            io.write_packed(out / "metrics.jsonl", text.encode())  # the same rows give the same bytes
        written.append(out)
    return written


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("src")
    parser.add_argument("dest")
    parser.add_argument("--points", type=int, default=250, help="rows kept per run, about (default 250)")
    parser.add_argument("--tail", type=int, default=60, help="last updates kept whole per run (default 60)")
    args = parser.parse_args(argv)
    for out in thin_dir(pathlib.Path(args.src), pathlib.Path(args.dest), args.points, args.tail):
        print(out)


if __name__ == "__main__":
    main()
