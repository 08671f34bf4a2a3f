"""What a profiled kernel computes: the fused computations of XLA's optimised HLO whose instruction names start with
a given prefix (the names a GPU profile shows, e.g. `input_multiply_negate_reduce_select_fusion`), with the JAX
operations and source lines their metadata names.

    XLA_FLAGS="--xla_dump_to=DUMP --xla_dump_hlo_as_text --xla_dump_hlo_module_re=jit_update" python -m benchmarks.run ...
    python -m benchmarks.hlo_fusions DUMP PREFIX [PREFIX ...] [--max-lines 80]
    python -m benchmarks.hlo_fusions DUMP --profile TRACE [--top 8]   # the top fusion kernels of a profile

DUMP is an XLA dump directory (its `*after_optimizations.txt` files are read) or one HLO text file (e.g. what
`jax.jit(f).lower(...).compile().as_text()` returns, written to a file). For each instruction whose name starts with
a prefix, or whose kernel name (the instruction's name, with `_` for `.` on a GPU) is a profile's kernel name
(`loop_pad_fusion_2` is the instruction `loop_pad_fusion.2`, not `loop_pad_fusion.1`; `loop_fusion` is `loop_fusion`
alone): the file, the instruction (its shape, operands and kind), the computation it calls, and the distinct
`op_name`s and source lines inside that computation (source_file/source_line, or the stack-frame tables newer XLA
writes), the JAX code the kernel came from.
With `--profile` (a `benchmarks.profile_summary` trace directory of the same program) the names are the profile's
top fusion kernels, each shown with its time and launch shape.

    python -m benchmarks.hlo_fusions DUMP --loops [--top 12]

counts what each loop body (and the entry computation) launches once per pass: its fusions, library calls and
unfused operations, grouped by name without the number (`gemm_fusion_dot.12` and `gemm_fusion_dot.3` are
`gemm_fusion_dot`). On a GPU a small update's time goes with its kernel launches: an SGD step's body holding
475 kernels against another's 137 says where a difference of time comes from before a profile does.
"""

from __future__ import annotations

import argparse
import collections
import pathlib
import re
import sys

if __package__ in (None, ""):  # `python benchmarks/hlo_fusions.py` as well as `python -m benchmarks.hlo_fusions`
    sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))

from benchmarks.common import Parser, refuse  # noqa: E402
from cdjax.options import non_negative, positive  # noqa: E402

_COMPUTATION = re.compile(r"^(?:ENTRY\s+)?%([\w.\-]+)\s.*\{\s*$")
_INSTRUCTION = re.compile(r"^\s*(?:ROOT\s+)?%?([\w.\-]+)\s*=\s*(.*)$")
_CALLS = re.compile(r"calls=%?([\w.\-]+)")
_OP_NAME = re.compile(r'op_name="([^"]*)"')
_SOURCE = re.compile(r'source_file="([^"]*)"\s+source_line=(\d+)')
_FRAME = re.compile(r"stack_frame_id=(\d+)")
_TABLE_ROW = re.compile(r"^(\d+)\s+(.*)$")


def hlo_files(path: pathlib.Path) -> list[pathlib.Path]:
    """The optimised-HLO text files of a dump directory, or the one file given."""
    if path.is_file():
        return [path]
    return sorted(path.rglob("*after_optimizations.txt"))


def computations(text: str) -> dict[str, list[str]]:
    """{computation name: its lines} of one HLO module's text (ENTRY included)."""
    out: dict[str, list[str]] = {}
    name = None
    for line in text.splitlines():
        if name is None:
            m = _COMPUTATION.match(line.strip())
            if m:
                name = m.group(1)
                out[name] = []
            continue
        if line.strip() == "}":
            name = None
            continue
        out[name].append(line)
    return out


def frames(text: str) -> dict[str, str]:
    """{stack_frame_id: "file:line (function)"} from a module's FileNames / FunctionNames / FileLocations /
    StackFrames tables (newer XLA's form of source metadata), the innermost frame first with up to two callers."""
    tables: dict[str, dict[str, str]] = collections.defaultdict(dict)
    table = None
    for line in text.splitlines():
        stripped = line.strip()
        if stripped in ("FileNames", "FunctionNames", "FileLocations", "StackFrames"):
            table = stripped
            continue
        if table is None:
            continue
        m = _TABLE_ROW.match(stripped)
        if not m:
            table = None if not stripped else table
            if stripped.startswith("%") or stripped.startswith("ENTRY"):
                break
            continue
        tables[table][m.group(1)] = m.group(2)
    field = lambda row, key: re.search(key + r"=(\d+)", row).group(1)  # noqa: E731

    def location(frame_id: str) -> tuple[str, str | None]:
        row = tables["StackFrames"][frame_id]
        loc = tables["FileLocations"].get(field(row, "file_location_id"), "")
        file_name = tables["FileNames"].get(field(loc, "file_name_id"), '""').strip('"') if loc else "?"
        function = tables["FunctionNames"].get(field(loc, "function_name_id"), '""').strip('"') if loc else "?"
        line_no = field(loc, "line") if loc else "?"
        parent = field(row, "parent_frame_id")
        return f"{file_name}:{line_no} ({function})", (parent if parent != frame_id and parent != "0" else None)

    out = {}
    for frame_id in tables.get("StackFrames", {}):
        chain, current = [], frame_id
        while current is not None and len(chain) < 3 and current in tables["StackFrames"]:
            where, current = location(current)
            if not chain or chain[-1] != where:
                chain.append(where)
        out[frame_id] = " <- ".join(chain)
    return out


def sources(lines: list[str], stack: dict[str, str] | None = None) -> list[tuple[str, str]]:
    """Distinct (op_name, source) of the instructions in lines, in order of appearance."""
    seen: dict[tuple[str, str], None] = {}
    for line in lines:
        op, src, frame = _OP_NAME.search(line), _SOURCE.search(line), _FRAME.search(line)
        where = f"{src.group(1)}:{src.group(2)}" if src else (stack or {}).get(frame.group(1), "") if frame else ""
        if op or where:
            seen.setdefault((op.group(1) if op else "", where), None)
    return list(seen)


def matches(name: str, prefixes: list[str], kernels: list[str]) -> bool:
    """An HLO instruction name against prefixes, or against kernel names as a profile has them (XLA names a fusion's
    kernel after the instruction, `.` written `_` on a GPU): a kernel name is one instruction, `loop_fusion` not
    `loop_fusion.1`."""
    return any(name.startswith(p) for p in prefixes) or name in kernels or name.replace(".", "_") in kernels


def find(path: pathlib.Path, prefixes: list[str], kernels: list[str] = ()) -> list[dict]:
    """Every instruction that `matches` a prefix or a kernel name, with the computation it calls."""
    found = []
    for f in hlo_files(path):
        text = f.read_text()
        comps, stack = computations(text), frames(text)
        for comp, lines in comps.items():
            for line in lines:
                m = _INSTRUCTION.match(line)
                if not m or not matches(m.group(1), prefixes, list(kernels)):
                    continue
                called = _CALLS.search(m.group(2))
                body = comps.get(called.group(1), []) if called else []
                found.append({"file": str(f), "in": comp, "name": m.group(1), "instruction": line.strip(),
                              "calls": called.group(1) if called else None, "body": body,
                              "sources": sources(body + [line], stack)})
    return found


def report(found: list[dict], max_lines: int = 80) -> str:
    if not found:
        return "no instruction with that name"
    out = []
    counts = collections.Counter(f["name"] for f in found)
    for f in found:
        out += [f"== {f['name']} ({f['file']}, in {f['in']}; {counts[f['name']]} such in the dump)",
                f"   {f['instruction'][:600]}"]
        if f["calls"]:
            out.append(f"   calls {f['calls']} ({len(f['body'])} instructions):")
            out += [f"     {line.strip()[:300]}" for line in f["body"][:max_lines]]
            if len(f["body"]) > max_lines:
                out.append(f"     ... {len(f['body']) - max_lines} more")
        out.append("   from:")
        out += [f"     {op}  {src}".rstrip() for op, src in f["sources"]] or ["     (no metadata)"]
    return "\n".join(out)


# HLO opcodes that launch nothing of their own (their work is other instructions', or none)
_NO_KERNEL = {"parameter", "constant", "get-tuple-element", "tuple", "bitcast", "while", "conditional", "call",
              "after-all", "add-dependency", "opt-barrier", "partition-id", "replica-id", "domain"}
_OPCODE = re.compile(r"^(?:\([^=]*?\)|\S+)\s+([a-z][\w\-]*)\(")
_BODY = re.compile(r"\bbody=%?([\w.\-]+)")
_TRIPS = re.compile(r'known_trip_count"?\s*:\s*\{\s*"n"\s*:\s*"(\d+)"')


def _group(name: str) -> str:
    """An instruction's name without its numbers: `gemm_fusion_dot.12` -> `gemm_fusion_dot`."""
    return re.sub(r"(?:[._]\d+)+$", "", name)


def loop_kernels(path: pathlib.Path) -> list[dict]:
    """Per optimised module, for the entry computation and each while loop's body: the instructions that launch work
    on a device (everything but `_NO_KERNEL`, fused computations' insides not counted) by group, most first."""
    out = []
    for f in hlo_files(path):
        text = f.read_text()
        comps = computations(text)
        entry = next((m.group(1) for line in text.splitlines()
                      if (m := _COMPUTATION.match(line.strip())) and line.lstrip().startswith("ENTRY")), None)
        bodies, parent, trips = [], {}, {}
        for name, lines in comps.items():
            for line in lines:
                if m := _BODY.search(line):
                    bodies.append(m.group(1))
                    parent[m.group(1)] = name
                    trips[m.group(1)] = int(t.group(1)) if (t := _TRIPS.search(line)) else None

        def passes(comp):  # a body's known trip count times its enclosing loops' (unknown counts: once)
            return 1 if comp not in parent else (trips[comp] or 1) * passes(parent[comp])

        for comp in ([entry] if entry else []) + bodies:
            groups: collections.Counter = collections.Counter()
            for line in comps.get(comp, []):
                m = _INSTRUCTION.match(line)
                op = _OPCODE.match(m.group(2)) if m else None
                if op and op.group(1) not in _NO_KERNEL:
                    groups[_group(m.group(1)) if op.group(1) == "fusion" else op.group(1)] += 1
            out.append({"file": str(f), "computation": comp, "entry": comp == entry, "kernels": sum(groups.values()),
                        "trips": trips.get(comp), "passes": passes(comp), "groups": groups.most_common()})
    return sorted(out, key=lambda c: -c["kernels"])


def loops_report(loops: list[dict], top: int) -> str:
    if not loops:
        return "no optimised HLO module"
    out = []
    for c in loops:
        where = "entry" if c["entry"] else "loop body"
        times = "" if c["entry"] else (f", {c['passes']:,} passes" if c["trips"] else ", trip count unknown")
        out.append(f"{c['computation']} ({where}, {pathlib.Path(c['file']).name}): {c['kernels']} kernels per pass"
                   + times)
        out += [f"  {n:5d}  {group}" for group, n in c["groups"][:top]]
        if len(c["groups"]) > top:
            out.append(f"  {sum(n for _, n in c['groups'][top:]):5d}  ({len(c['groups']) - top} other groups)")
    for name in dict.fromkeys(pathlib.Path(c["file"]).name for c in loops):
        total = sum(c["kernels"] * c["passes"] for c in loops if pathlib.Path(c["file"]).name == name)
        out.append(f"{name}: {total:,} kernels per run (the entry once, each loop body times its known trip count "
                   "and its enclosing loops'; a body of unknown count once)")
    return "\n".join(out)


def profile_kernels(trace: pathlib.Path, top: int) -> list[dict]:
    """The profile's `top` costliest kernels that are XLA fusions (not library GEMMs, memcpys or memsets), with
    their time and launch shape, from `benchmarks.profile_summary`."""
    from benchmarks import profile_summary

    ops = profile_summary.summarize(trace, top=10 * top)["ops"]
    kernels = [o for o in ops if re.search(r"fusion", o["kernel"]) and not o["kernel"].startswith(("gemm_", "void "))]
    return kernels[:top]


def main(argv=None) -> str:
    """Bad input (a DUMP that does not exist or holds no optimised HLO, a --profile without a trace, counts out of
    range, --loops with what it does not use, nothing to look for) ends in one sentence with exit status 2 before
    anything is read or printed."""
    p = Parser(prog="python -m benchmarks.hlo_fusions", description=__doc__,
               formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("dump", type=pathlib.Path, help="XLA dump directory or one optimised-HLO text file")
    p.add_argument("prefixes", nargs="*", help="instruction-name prefixes (as a GPU profile begins the kernels' names)")
    p.add_argument("--profile", type=pathlib.Path, help="a trace of the same program: its top fusion kernels' names")
    p.add_argument("--top", type=positive, default=8, help="with --profile: how many kernels (default 8); with "
                   "--loops: groups per computation")
    p.add_argument("--loops", action="store_true", help="the kernels each loop body and the entry launch per pass")
    p.add_argument("--max-lines", type=non_negative, default=80, help="lines of each fused computation to print")
    args = p.parse_intermixed_args(argv)  # (PREFIXes after an option too)
    check(p, args)
    if args.loops:
        text = loops_report(loop_kernels(args.dump), args.top)
        print(text)
        return text
    kernels, head = [], []
    if args.profile:
        for k in profile_kernels(args.profile, args.top):
            kernels.append(k["kernel"])
            head.append(f"{k['kernel']}: {k['total_ms']:.3f} ms in {k['count']:,} calls ({k['pct']:.1f}%), launch "
                        f"{k['launch'] or 'not in the trace'}")
        if not kernels and not args.prefixes:
            refuse(p.prog, f"the top ops of --profile {args.profile} hold no XLA fusion kernel to look up; name "
                           "instruction-name PREFIXes")
    text = "\n".join(head + ([""] if head else []) + [report(find(args.dump, args.prefixes, kernels), args.max_lines)])
    print(text)
    return text


def check(p: Parser, args) -> None:
    """Refuse (one sentence, exit status 2) what would otherwise print an empty answer or fail part way."""
    if not args.dump.exists():
        refuse(p.prog, f"DUMP {args.dump} does not exist")
    if not hlo_files(args.dump):
        refuse(p.prog, f"DUMP {args.dump} holds no *after_optimizations.txt file (dump with XLA_FLAGS=--xla_dump_to="
                       "DIR --xla_dump_hlo_as_text, or name one HLO text file)")
    if args.loops:
        ignored = [name for name, given in (("PREFIX", args.prefixes), ("--profile", args.profile),
                                            ("--max-lines", args.max_lines != p.get_default("max_lines"))) if given]
        if ignored:
            refuse(p.prog, f"--loops counts each loop body's launches and shows no fused computation, which "
                           f"{' and '.join(ignored)} {'are' if len(ignored) > 1 else 'is'} for: give "
                           f"{'them' if len(ignored) > 1 else 'it'} without --loops")
        return
    if not args.prefixes and not args.profile:
        refuse(p.prog, f"name instruction-name PREFIXes, --profile TRACE or --loops; see `{p.prog} --help`")
    if args.profile:
        from benchmarks import profile_summary

        if not args.profile.exists():
            refuse(p.prog, f"--profile {args.profile} does not exist")
        if not profile_summary.find_traces(args.profile):
            refuse(p.prog, f"--profile {args.profile} holds no profiler trace "
                           f"({' or '.join(profile_summary.TRACE_NAMES)}; benchmarks.run --trace DIR writes one)")


if __name__ == "__main__":
    main()
