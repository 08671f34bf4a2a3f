"""Where XLA:GPU's compile time goes, from its own timers in a log.

    TF_CPP_MIN_LOG_LEVEL=0 TF_CPP_VMODULE=gpu_compiler=1,nvptx_compiler=1,compile_module_to_llvm_ir=1 \\
      python -m benchmarks.compile_time --out DIR --cache-dir EMPTY -- --env ant --arms model-free mbmf cd-k5 cd \\
      > vlog.log 2>&1
    python -m benchmarks.xla_timers vlog.log [--top N] [--json OUT]

(`bash benchmarks/compile_units.sh timers` runs both on a GPU machine.) XLA logs one line per timed step and
module, e.g. `GpuCompiler::RunHloPasses for jit_chunk time: 39.6 s (39612345 us) ...`. This sums the seconds of each
timer over every module of one kind: a module's name without its numeric suffixes (`gemm_fusion_dot.123` and
`gemm_fusion_dot.7` are the kind `gemm_fusion_dot`, the autotuner's Triton GEMM candidates; `jit_chunk` the sweeps'
chunk programs). The sums add up the seconds of every thread, so on a host that compiles in many threads they can
exceed the wall-clock time, and some timers hold others (the autotuning, and with it the candidates' IR emission,
runs inside `RunHloPasses`): read the rows side by side, not as a total. The log may be gzipped.
"""

from __future__ import annotations

import argparse
import collections
import gzip
import json
import pathlib
import re
import sys

if __package__ in (None, ""):  # `python benchmarks/xla_timers.py` as well as `python -m benchmarks.xla_timers`
    sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))

from benchmarks.common import Parser, refuse, unwritable_file  # noqa: E402
from cdjax import io  # noqa: E402
from cdjax.options import positive  # noqa: E402

_TIMER = re.compile(r"\] (?P<timer>\S.*?) for (?P<module>\S+) time: .*?\((?P<us>\d+) us\)")
_SUFFIX = re.compile(r"(?:[._]\d+)+$")


def module_kind(module: str) -> str:
    """A module's name without its numeric suffixes: the kind of program or kernel it is."""
    return _SUFFIX.sub("", module) or module


def parse(lines) -> list[dict]:
    """Each timer and module kind with its count and seconds summed, the largest first."""
    seconds, count = collections.Counter(), collections.Counter()
    for line in lines:
        m = _TIMER.search(line)
        if m:
            key = (m["timer"], module_kind(m["module"]))
            seconds[key] += int(m["us"]) / 1e6
            count[key] += 1
    return [{"timer": t, "kind": k, "count": count[t, k], "s": round(s, 3)}
            for (t, k), s in sorted(seconds.items(), key=lambda kv: -kv[1])]


def read_lines(path: pathlib.Path):
    opener = gzip.open if path.suffix == ".gz" else open
    with opener(path, "rt", errors="replace") as f:
        yield from f


def table(rows: list[dict], top: int | None = None) -> str:
    lines = ["| XLA timer | module kind | timed | s, summed over threads |", "| --- | --- | ---: | ---: |"]
    for r in rows[:top]:
        lines.append(f"| {r['timer']} | `{r['kind']}` | {r['count']:,d} | {r['s']:.1f} |")
    if top is not None and len(rows) > top:
        rest = rows[top:]
        lines.append(f"| {len(rest)} more | | {sum(r['count'] for r in rest):,d} | {sum(r['s'] for r in rest):.1f} |")
    return "\n".join(lines)


def main(argv=None) -> list[dict]:
    """Bad input (a log that is not a readable file, a --top below 1, a --json that cannot be written, a log without
    timer lines) ends in one sentence with exit status 2 before anything is printed or written."""
    p = Parser(prog="python -m benchmarks.xla_timers", description=__doc__,
               formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("log", type=pathlib.Path, help="a log with XLA:GPU's timer lines (plain or .gz)")
    p.add_argument("--top", type=positive, default=None, help="print only the N largest rows (the rest summed in one)")
    p.add_argument("--json", type=pathlib.Path, help="also write every row here")
    args = p.parse_args(argv)
    if not args.log.is_file():
        refuse(p.prog, f"LOG {args.log} is a directory; name the log file" if args.log.is_dir() else
               f"no such log: {args.log}")
    if args.json and (why := unwritable_file(args.json)):
        refuse(p.prog, f"--json {args.json}: {why}")
    try:
        rows = parse(read_lines(args.log))
    except (OSError, EOFError) as err:  # unreadable, or a .gz that is not gzip or is cut short
        refuse(p.prog, f"cannot read {args.log}: {io.reason(err)}")
    if not rows:
        refuse(p.prog, f"{args.log} holds no XLA timer lines (run with TF_CPP_MIN_LOG_LEVEL=0 and "
                       "TF_CPP_VMODULE=gpu_compiler=1,nvptx_compiler=1,compile_module_to_llvm_ir=1)")
    print(table(rows, args.top))
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    return rows


if __name__ == "__main__":
    main()
