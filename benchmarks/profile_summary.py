"""Op-level summary of a jax.profiler trace: where the device time of the traced calls goes.

    python -m benchmarks.profile_summary DIR [--top 25] [--out FILE.md]

DIR is what `jax.profiler.trace(DIR, create_perfetto_trace=True)` wrote (or a directory above several
such, e.g. the `--trace` directory of `benchmarks.run`, one trace per case), or a trace file itself.
The newest run under each trace directory is read from its `perfetto_trace.json.gz` (else
`*.trace.json.gz`).

Which events count as device ops:
- GPU (a `/device:GPU:n` process in the trace): the kernels, memcpys and memsets on its `Stream #...`
  lines (not the derived "XLA Ops" / "XLA Modules" lines, which span the same time again);
- otherwise (CPU): the host events that carry an `hlo_op` (XLA:CPU runs one thunk per HLO op).

Times are self times on a CPU (a `while` op encloses its body's ops; only its own share counts) and the kernels'
durations on a GPU (kernels do not nest; with XLA's CUDA graphs scheduled by data flow, cdjax's default, kernels of
one stream line run side by side and overlap), so the percentages of all ops add up to 100 % of the traced device
time (the sum of those times). Beside it the timeline: the span from the first op's start to the last one's end, the
time some op was running (busy), and the mean number running at once while busy (concurrency: summed time / busy).
On a GPU also the CUDA graphs (XLA's command buffers) with the most kernel time, per launch: kernels, span and busy
time (`graphs`). A loop body's graph is one pass of the loop: the SGD step's span against its busy time says how long
its chain of dependent kernels waits between them.

A GPU kernel's launch shape (blocks x threads per block, and the occupancy the profiler computed) is read from the
`grid:X,Y,Z block:X,Y,Z ... occ_pct:P` text the profiler attaches to each kernel event (its kernel details): a
kernel far slower than its bytes need on few blocks is a fusion XLA gave too little parallelism.

Ops are grouped coarsely into gemm (dot, convolution, cuBLAS/cutlass/Triton gemm), scatter/gather,
sort, copy/transpose (copies, transposes, slices, concatenation, memcpy), memset, fusion (the other
XLA fusions: elementwise and reductions) and other. When the compiled program's HLO text lies beside
the trace (`trace()` below saves it as `<module>.hlo.txt`), an op is grouped by what its HLO
instruction computes (XLA:CPU names a fused dot `ynn_fusion`, for instance); otherwise by its name.
"""

from __future__ import annotations

import argparse
import collections
import contextlib
import gzip
import json
import pathlib
import re
from typing import Any, Iterable

GROUPS = ("gemm", "scatter/gather", "sort", "copy/transpose", "memset", "fusion", "other")
TRACE_NAMES = ("perfetto_trace.json.gz", "*.trace.json.gz")
HLO_SUFFIX = ".hlo.txt"
_NAME_RULES = (  # (group, pattern on the lower-cased kernel / op name), first match wins
    ("memset", r"memset"),
    ("gemm", r"gemm|cublas|cutlass|xmma|wgmma|matmul|\bdot\b|dot[._\-]|_dot|convolution|\bconv|cudnn"),
    ("sort", r"sort"),
    ("scatter/gather", r"scatter|gather"),
    ("copy/transpose", r"memcpy|copy|transpose|dynamic[_\-]update[_\-]slice|dynamic[_\-]slice|concatenate"),
    ("fusion", r"fusion|^wrapped_"),
)
_COPY_OPS = {"copy", "transpose", "dynamic-slice", "dynamic-update-slice", "slice", "concatenate", "pad",
             "reshape", "bitcast", "broadcast", "parameter", "constant", "tuple", "get-tuple-element",
             "copy-start", "copy-done", "reverse"}


# ----------------------------------------------------------------------------------------- writing

@contextlib.contextmanager
def trace(trace_dir: str | pathlib.Path, *compiled):
    """`with trace(DIR, compiled): compiled(...)`: a jax.profiler trace with its perfetto JSON, and the
    HLO text of each given compiled program saved beside it (`<module>.hlo.txt`, for op grouping)."""
    import jax

    trace_dir = pathlib.Path(trace_dir)
    trace_dir.mkdir(parents=True, exist_ok=True)
    for c in compiled:
        text = c.as_text()
        module = re.match(r"HloModule\s+([^\s,]+)", text)
        (trace_dir / f"{module.group(1) if module else 'module'}{HLO_SUFFIX}").write_text(text)
    with jax.profiler.trace(str(trace_dir), create_perfetto_trace=True):
        yield


# ----------------------------------------------------------------------------------------- reading

def find_traces(path: str | pathlib.Path) -> list[pathlib.Path]:
    """The trace file of the newest run of every trace directory under `path` (or `path` itself)."""
    path = pathlib.Path(path)
    if path.is_file():
        return [path]
    runs: dict[pathlib.Path, list[pathlib.Path]] = collections.defaultdict(list)
    for pattern in TRACE_NAMES:
        for f in path.rglob(pattern):
            runs[f.parent].append(f)
    by_root: dict[pathlib.Path, pathlib.Path] = {}
    for run in sorted(runs, key=lambda d: (d.stat().st_mtime, d.name)):  # newest last: it wins
        files = runs[run]
        by_root[trace_root(files[0])] = next((f for f in files if f.name == TRACE_NAMES[0]), files[0])
    return [by_root[r] for r in sorted(by_root)]


def trace_root(trace_file: pathlib.Path) -> pathlib.Path:
    """The directory given to jax.profiler.trace (it holds plugins/profile/<run>/<file>)."""
    run = trace_file.parent
    return run.parents[2] if run.parent.name == "profile" and run.parents[1].name == "plugins" else run


def load_events(trace_file: pathlib.Path) -> list[dict]:
    opener = gzip.open if trace_file.name.endswith(".gz") else open
    with opener(trace_file, "rt") as f:
        data = json.load(f)
    return data["traceEvents"] if isinstance(data, dict) else data


def device_events(events: list[dict]) -> tuple[str, list[dict]]:
    """(source, the complete events that are device ops) - see the module docstring."""
    process = {e["pid"]: e["args"].get("name", "") for e in events
               if e.get("ph") == "M" and e.get("name") == "process_name"}
    thread = {(e["pid"], e.get("tid")): e["args"].get("name", "") for e in events
              if e.get("ph") == "M" and e.get("name") == "thread_name"}
    complete = [e for e in events if e.get("ph") == "X" and "dur" in e]
    devices = {pid for pid, name in process.items() if re.match(r"/device:(GPU|TPU)", name)}
    if devices:
        on_device = [e for e in complete if e["pid"] in devices]
        streams = [e for e in on_device if thread.get((e["pid"], e.get("tid")), "").startswith("Stream")]
        if streams:
            return "GPU kernels", streams
        ops = [e for e in on_device if thread.get((e["pid"], e.get("tid")), "") == "XLA Ops"]
        return "device XLA ops", ops or on_device
    ops = [e for e in complete if "hlo_op" in e.get("args", {}) and not e["name"].startswith("end: ")]
    return "XLA ops (CPU)", ops


def self_times(events: list[dict]) -> list[float]:
    """Duration of each event minus the time of the events nested in it on the same thread (us)."""
    out = [float(e["dur"]) for e in events]
    lines: dict[Any, list[int]] = collections.defaultdict(list)
    for i, e in enumerate(events):
        lines[(e.get("pid"), e.get("tid"))].append(i)
    for idx in lines.values():
        idx.sort(key=lambda i: (events[i]["ts"], -events[i]["dur"]))
        stack: list[int] = []  # enclosing events, innermost last
        for i in idx:
            start, end = events[i]["ts"], events[i]["ts"] + events[i]["dur"]
            while stack and events[stack[-1]]["ts"] + events[stack[-1]]["dur"] <= start:
                stack.pop()
            if stack:
                parent = stack[-1]
                overlap = min(end, events[parent]["ts"] + events[parent]["dur"]) - start
                out[parent] -= max(overlap, 0.0)
            stack.append(i)
    return [max(t, 0.0) for t in out]


# --------------------------------------------------------------------------------------- HLO text

def parse_hlo(text: str) -> dict[str, dict]:
    """{module: {instruction: {"group", "op_name"}}} for the instructions of an HLO text dump."""
    module = re.match(r"HloModule\s+([^\s,]+)", text)
    comps: dict[str, list[dict]] = {}
    current = None
    instr_re = re.compile(r"^\s*(?:ROOT\s+)?%?([\w.\-]+)\s*=\s*.*?\s([a-z][\w\-]*)\((.*)$")
    for line in text.splitlines():
        head = re.match(r"^(?:ENTRY\s+)?%?([\w.\-]+)\s.*\{\s*$", line)
        if head and not line.startswith(" "):
            current = comps.setdefault(head.group(1), [])
            continue
        if line.startswith("}"):
            current = None
            continue
        m = instr_re.match(line) if current is not None else None
        if m:
            name, opcode, rest = m.groups()
            called = re.findall(r"(?:calls|to_apply|body|condition)=%?([\w.\-]+)", rest)
            called += [c for group in re.findall(r"(?:called_computations|branch_computations)=\{([^}]*)\}", rest)
                       for c in re.findall(r"%?([\w.\-]+)", group)]
            target = re.search(r'custom_call_target="([^"]*)"', rest)
            op_name = re.search(r'op_name="([^"]*)"', rest)
            current.append({"name": name, "opcode": opcode, "called": called,
                            "target": target.group(1) if target else "", "op_name": op_name.group(1) if op_name else ""})

    def contents(comp: str, seen: set) -> tuple[set, set]:
        ops, targets = set(), set()
        if comp in seen:
            return ops, targets
        seen.add(comp)
        for ins in comps.get(comp, []):
            ops.add(ins["opcode"])
            if ins["target"]:
                targets.add(ins["target"].lower())
            if ins["opcode"] in ("fusion", "call"):
                sub_ops, sub_targets = contents(ins["called"][0], seen) if ins["called"] else (set(), set())
                ops |= sub_ops
                targets |= sub_targets
        return ops, targets

    table = {}
    for instrs in comps.values():
        for ins in instrs:
            ops, targets = {ins["opcode"]}, {ins["target"].lower()} - {""}
            if ins["opcode"] in ("fusion", "call") and ins["called"]:
                sub_ops, sub_targets = contents(ins["called"][0], set())
                ops |= sub_ops
                targets |= sub_targets
            table[ins["name"]] = {"group": _hlo_group(ins["opcode"], ops, targets), "op_name": ins["op_name"]}
    return {module.group(1) if module else "": table}


def _hlo_group(opcode: str, ops: set, targets: set) -> str:
    if ops & {"dot", "convolution"} or any(re.search(r"gemm|matmul|cublas|conv", t) for t in targets):
        return "gemm"
    if "sort" in ops or any("sort" in t for t in targets):
        return "sort"
    if ops & {"scatter", "gather"}:
        return "scatter/gather"
    if opcode in ("while", "conditional", "call", "custom-call", "all-reduce", "send", "recv"):
        return "other"
    if ops - {"fusion"} <= _COPY_OPS:
        return "copy/transpose"
    return "fusion" if opcode == "fusion" else "other"


def load_hlo(root: pathlib.Path) -> dict[str, dict]:
    table: dict[str, dict] = {}
    for f in sorted(root.glob(f"*{HLO_SUFFIX}")):
        table.update(parse_hlo(f.read_text()))
    return table


# ----------------------------------------------------------------------------------------- summary

def name_group(name: str) -> str:
    low = name.lower()
    for group, pattern in _NAME_RULES:
        if re.search(pattern, low):
            return group
    return "other"


def shorten(name: str, width: int = 60) -> str:
    """A kernel or op name for a table cell: no `void `, no argument list, at most `width` characters."""
    name = re.sub(r"^void\s+", "", name.strip())
    if name.endswith(")") and "(" in name:
        depth = 0
        for i in range(len(name) - 1, -1, -1):
            depth += {")": 1, "(": -1}.get(name[i], 0)
            if depth == 0:
                name = name[:i] if i > 0 else name
                break
    return name if len(name) <= width else name[: width - 3] + "..."


def _source(op_name: str, width: int = 48) -> str:
    """The tail of a JAX op path (`jit(update)/while/body/dot_general` -> `while/body/dot_general`)."""
    parts = [p for p in op_name.split("/") if p and not re.fullmatch(r"jit\(.*\)|jvp\(.*\)|transpose\(.*\)", p)]
    tail = "/".join(parts[-3:])
    return tail if len(tail) <= width else "..." + tail[-(width - 3):]


_LAUNCH = re.compile(r"grid:(\d+),(\d+),(\d+)\s+block:(\d+),(\d+),(\d+)(?:.*?occ_pct:([\d.]+))?")


def launch(args: dict) -> str:
    """'blocks x threads/block (occupancy %)' of a GPU kernel event from its kernel-details text, '' if none."""
    for value in args.values():
        m = _LAUNCH.search(value) if isinstance(value, str) else None
        if m:
            grid = int(m.group(1)) * int(m.group(2)) * int(m.group(3))
            block = int(m.group(4)) * int(m.group(5)) * int(m.group(6))
            occupancy = f" ({float(m.group(7)):.0f}%)" if m.group(7) else ""
            return f"{grid:,} x {block:,}{occupancy}"
    return ""


def summarize(path: str | pathlib.Path, top: int = 25) -> dict:
    """The op-level summary of the (newest) trace at `path`: a JSON-able dict, see `markdown`."""
    files = find_traces(path)
    if not files:
        raise FileNotFoundError(f"no {' or '.join(TRACE_NAMES)} under {path} (was the trace written with "
                                "create_perfetto_trace=True?)")
    trace_file = max(files, key=lambda f: f.stat().st_mtime)
    source, events = device_events(load_events(trace_file))
    hlo = load_hlo(trace_root(trace_file))
    ops: dict[tuple, dict] = {}
    times = [float(e["dur"]) for e in events] if source == "GPU kernels" else self_times(events)
    for e, t in zip(events, times):
        args = e.get("args", {})
        module, hlo_op, kernel = args.get("hlo_module", ""), args.get("hlo_op", ""), e["name"]
        info = hlo.get(module, {}).get(hlo_op) if hlo_op else None
        key = (module, hlo_op, kernel)
        if key not in ops:
            label = shorten(hlo_op or kernel)
            if hlo_op and kernel != hlo_op and kernel.replace("_", ".") != hlo_op.replace("_", "."):
                label = f"{hlo_op}: {shorten(kernel)}"  # a library kernel (cuBLAS, cutlass) under its HLO op
            group = info["group"] if info else name_group(f"{kernel} {hlo_op}")
            op_name = (info or {}).get("op_name") or args.get("tf_op") or args.get("long_name") or ""
            ops[key] = {"name": shorten(label), "group": group, "source": _source(op_name), "launch": launch(args),
                        "kernel": kernel, "count": 0, "us": 0.0}
        ops[key]["count"] += 1
        ops[key]["us"] += t
    total_us = sum(o["us"] for o in ops.values())
    pct = lambda us: 100.0 * us / total_us if total_us > 0 else 0.0  # noqa: E731
    rows = sorted(ops.values(), key=lambda o: -o["us"])
    groups = collections.defaultdict(lambda: {"count": 0, "us": 0.0})
    for o in rows:
        groups[o["group"]]["count"] += o["count"]
        groups[o["group"]]["us"] += o["us"]
    return {
        "trace": str(trace_file), "source": source, "hlo_grouping": bool(hlo), "events": len(events),
        "distinct_ops": len(rows), "device_ms": total_us / 1e3, **timeline(events, total_us),
        "ops": [{"name": o["name"], "group": o["group"], "source": o["source"], "launch": o["launch"],
                 "kernel": o["kernel"], "count": o["count"], "total_ms": o["us"] / 1e3, "pct": pct(o["us"])}
                for o in rows[:top]],
        "groups": [{"group": g, "count": groups[g]["count"], "total_ms": groups[g]["us"] / 1e3,
                    "pct": pct(groups[g]["us"])} for g in sorted(groups, key=lambda g: -groups[g]["us"])],
        "graphs": graphs(events, total_us) if source == "GPU kernels" else [],
    }


GRAPH_OP = re.compile(r"command_buffer_\d+$")  # the HLO op XLA:GPU names a CUDA graph's kernels by
GRAPHS_SHOWN = 8


def graphs(events: list[dict], summed_us: float, shown: int = GRAPHS_SHOWN) -> list[dict]:
    """The CUDA graphs (XLA command buffers) holding the most kernel time, each with its launches' shape.

    A graph's kernels carry its name (`command_buffer_N`) as their HLO op. Its launches are counted as the fewest
    times any one of its kernels ran (each kernel of a graph runs once per launch; a name repeated in the graph, as
    an unrolled chain's GEMMs are, runs more often). When every launch ran the same number of kernels, its events
    in start order are split into the launches, and a launch's span (first kernel's start to last one's end) and
    busy time (some kernel of it running) are averaged: the span of a loop body's graph is one pass of the loop on
    the device, and span over busy says how much of it the GPU waited between dependent kernels."""
    by_graph: dict[str, list[dict]] = collections.defaultdict(list)
    for e in events:
        op = e.get("args", {}).get("hlo_op", "")
        if GRAPH_OP.match(op):
            by_graph[op].append(e)
    rows = []
    for name, evs in by_graph.items():
        counts = collections.Counter(e["name"] for e in evs)
        launches = min(counts.values())
        summed = sum(float(e["dur"]) for e in evs)
        row = {"graph": name, "module": evs[0].get("args", {}).get("hlo_module", ""), "kernels": len(evs),
               "launches": launches, "kernels_per_launch": len(evs) / launches, "total_ms": summed / 1e3,
               "pct": 100.0 * summed / summed_us if summed_us > 0 else 0.0, "span_us": None, "busy_us": None}
        if len(evs) % launches == 0:
            ordered, n = sorted(evs, key=lambda e: float(e["ts"])), len(evs) // launches
            parts = [ordered[i:i + n] for i in range(0, len(ordered), n)]
            row["span_us"] = sum(max(float(e["ts"]) + float(e["dur"]) for e in part) - float(part[0]["ts"])
                                 for part in parts) / launches
            row["busy_us"] = sum(timeline(part, 0.0)["busy_ms"] * 1e3 for part in parts) / launches
        rows.append(row)
    return sorted(rows, key=lambda r: -r["total_ms"])[:shown]


def timeline(events: list[dict], summed_us: float) -> dict:
    """span_ms (first start to last end), busy_ms (the union of the events' intervals: some op running) and
    concurrency (summed_us / busy: how many ran at once on average while any ran)."""
    intervals = sorted((float(e["ts"]), float(e["ts"]) + float(e["dur"])) for e in events)
    busy, end = 0.0, float("-inf")
    for start, stop in intervals:
        if stop > end:
            busy += stop - max(start, end)
            end = stop
    span = intervals[-1][1] - intervals[0][0] if intervals else 0.0
    return {"span_ms": span / 1e3, "busy_ms": busy / 1e3, "concurrency": summed_us / busy if busy > 0 else 0.0}


def _cell(text: str) -> str:
    return str(text).replace("|", "\\|")


def markdown(summary: dict) -> str:
    """Markdown tables: the top ops, the groups (all ops), and on a GPU the CUDA graphs with the most kernel time."""
    shown = sum(o["pct"] for o in summary["ops"])
    lines = [f"{summary['source']}: {summary['device_ms']:.3f} ms of device time in {summary['events']:,} events, "
             f"{summary['distinct_ops']} distinct ops; the top {len(summary['ops'])} hold {shown:.1f} % "
             f"(grouped by {'HLO' if summary['hlo_grouping'] else 'name'}). Timeline: {summary['span_ms']:.3f} ms "
             f"from the first op to the last, ops running {summary['busy_ms']:.3f} ms of it, "
             f"{summary['concurrency']:.2f} at once on average while any ran.", "",
             "| # | op | group | JAX op | launch (blocks x threads) | count | total ms | % |",
             "| ---: | --- | --- | --- | --- | ---: | ---: | ---: |"]
    for i, o in enumerate(summary["ops"], 1):
        lines.append(f"| {i} | `{_cell(o['name'])}` | {o['group']} | {_cell(o['source'])} | {o.get('launch') or '–'} | "
                     f"{o['count']:,} | {o['total_ms']:.3f} | {o['pct']:.1f} |")
    lines += ["", "| group | count | total ms | % |", "| --- | ---: | ---: | ---: |"]
    for g in summary["groups"]:
        lines.append(f"| {g['group']} | {g['count']:,} | {g['total_ms']:.3f} | {g['pct']:.1f} |")
    if summary.get("graphs"):
        lines += ["", "CUDA graphs (XLA command buffers) with the most kernel time; a launch's span is its first kernel's "
                  "start to its last one's end, busy the time some kernel of it ran:", "",
                  "| graph | launches | kernels / launch | total ms | % | span / launch µs | busy / launch µs | "
                  "kernel µs / launch |", "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
        for g in summary["graphs"]:
            us = lambda v: "–" if v is None else f"{v:,.1f}"  # noqa: E731
            lines.append(f"| `{g['graph']}` | {g['launches']:,} | {g['kernels_per_launch']:,.1f} | {g['total_ms']:.3f} | "
                         f"{g['pct']:.1f} | {us(g['span_us'])} | {us(g['busy_us'])} | "
                         f"{g['total_ms'] * 1e3 / g['launches']:,.1f} |")
    return "\n".join(lines) + "\n"


def summarize_all(path: str | pathlib.Path, top: int = 25) -> Iterable[tuple[pathlib.Path, dict]]:
    """(trace directory, summary) for every trace directory under `path`."""
    for f in find_traces(path):
        yield trace_root(f), summarize(f, top)


def main(argv=None) -> str:
    from benchmarks.common import Parser, refuse, unwritable_file  # (imports cdjax: only the command needs it)
    from cdjax.options import positive

    p = Parser(prog="python -m benchmarks.profile_summary", description=__doc__,
               formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("path", help="trace directory (or a directory of several, or a trace file)")
    p.add_argument("--top", type=positive, default=25, help="ops listed (default 25)")
    p.add_argument("--out", help="also write the markdown to this file")
    args = p.parse_args(argv)
    if not pathlib.Path(args.path).exists():
        refuse(p.prog, f"{args.path} does not exist")
    if args.out and (why := unwritable_file(args.out)):
        refuse(p.prog, f"--out {args.out}: {why}")
    sections = [(root, s) for root, s in summarize_all(args.path, args.top)]
    if not sections:
        refuse(p.prog, f"no {' or '.join(TRACE_NAMES)} under {args.path}")
    md = "\n".join((f"### {root}\n\n" if len(sections) > 1 else "") + markdown(s) for root, s in sections)
    if args.out:
        pathlib.Path(args.out).write_text(md)
    print(md)
    return md


if __name__ == "__main__":
    main()
