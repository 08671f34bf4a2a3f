"""The ALE tier at the paper's budget: 4 games x 2 arms x 3 seeds x 10M agent steps (40M frames) per run, in pieces
that run side by side on a many-core GPU host and continue across loans of it.

A piece is one arm of one game, `ale40m-GAME-ARM` (experiments/atari/units.py): `cdjax sweep --setting atari --preset
GAME --arms ARM --seeds 3 --steps 10000000`, its 3 runs' 48 emulators one ale-py vector environment, on one GPU and
its own share of the host's cores. A loan (at most 30 minutes held) is far shorter than a piece (30M agent steps,
about an hour of a 16-core share at the 1M tier's rate), so a piece stops at --time-limit, packs its resumable state
(its run directory with each arm's latest checkpoint; `pack`) into parts of at most 16 MiB, which the calls bring back
(`send`: at most 8 files, 64 MiB a call); at the next loan the parts are carried in and the piece resumes from them
(`start`: unpacked, then `cdjax sweep --resume`). What a resume promises: on MinAtar the run is the uncut run bit for
bit; on the ALE the parameters, optimiser state, keys and counters are the cut run's, and the emulators start new
games (they live outside JAX and are not checkpointed: cdjax.agents.atari.ale), the same games wherever it resumes.

On the GPU host (every call: `. experiments/wheels.sh && ensure_wheels && atari_packages ale &&` first):

    python -m experiments.atari.ale40m start PIECE [PIECE ...] --work W [--carried DIR] [--end-in S] [--gpus N] \
        [--param NAME=VALUE ...]
    python -m experiments.atari.ale40m poll --work W [--wait S]
    python -m experiments.atari.ale40m send --work W --out "$OUT" [--again]   # again while it prints MORE

Here (the CPU machine that holds the state between loans; experiments/atari/RESULTS.md, "The ALE tier at 40M
frames", gives the whole sequence):

    python -m experiments.atari.ale40m plan [--store S]                  # each piece's progress, what to run next
    python -m experiments.atari.ale40m stage PIECE [PIECE ...] --store S --into .ale40m-in [--first] [--beside P..]
    python -m experiments.atari.ale40m absorb FILES_AT --store S         # what a call brought back
    python -m experiments.atari.ale40m merge --store S --out experiments/atari/data/ale-10m
    python -m experiments.atari.ale40m sizes --out DIR [--games G ..] [--arms A ..] [--seeds 3]   # a piece's state

`start` is idempotent: a piece already started is left alone and a piece whose parts have not all been carried in
yet waits for the call that brings the rest, so the parts of several pieces can come in over several calls (each
carries 64 MiB with the tracked tree) while the pieces already complete train.
"""

from __future__ import annotations

import argparse
import io as _io
import json
import lzma
import os
import pathlib
import re
import shutil
import sys
import tarfile
import time
from collections.abc import Sequence

GAMES = ("breakout", "seaquest", "mspacman", "frostbite")  # the paper's four ALE games
ARMS = ("a2c", "a2c-cd")
SEEDS = 3
STEPS = 10_000_000  # agent steps per run: 40M frames at frame skip 4, A2C's published budget
STEPS_PER_UPDATE = 16 * 5  # the ALE presets' 16 envs x 5 steps
UPDATES = STEPS // STEPS_PER_UPDATE  # 125,000 per run
PIECES = tuple(f"ale40m-{game}-{arm}" for game in GAMES for arm in ARMS)
# The metrics a piece's state carries: every EVERY-th update's rows (5,000 of a run's 125,000; a row of a2c-cd is
# about 1 kB, so its whole log would be about 380 MB, 75 MB compressed, by the end), the same rows wherever the run
# was cut. The report's final return then averages 500 points of each run's last 10%, its AUC 5,000.
EVERY = 25
# The fields of the rows kept in the repository (`merge`): what experiments.atari.report and aggregate read.
KEPT_FIELDS = ("arm", "hp", "seed", "update", "env_steps", "wall_s", "episode/return", "episode/discounted_return")

# What one call of the device tool brings back from $OUT, and carries in (experiments/atari/RESULTS.md).
FILE_MAX = 16 * 2**20  # bytes of one file back
CALL_FILES = 8  # files back per call
CALL_MAX = 64 * 2**20  # bytes back per call, and bytes carried in per call (the tracked tree included)

HOLD_S = 1800  # a machine is held at most 30 minutes, its start included
SEND_S = 240  # kept at the loan's end for the calls that bring the parts back
EVAL_S = 150  # a piece's evaluation (3 runs x 100 episodes) at most, where its run has reached its steps
PACK_S = 90  # a piece's packing at most
MANIFEST = "MANIFEST.json"  # the staged pieces' updates, in the carried folder
PART = re.compile(r"^(?P<piece>ale40m-[a-z]+-[a-z0-9-]+)\.u(?P<updates>\d+)\.(?P<index>\d+)-of-(?P<count>\d+)$")


def piece_of(name: str) -> tuple[str, str]:
    """(game, arm) of a piece's name."""
    for game in GAMES:
        for arm in ARMS:
            if name == f"ale40m-{game}-{arm}":
                return game, arm
    raise ValueError(f"no piece {name!r} (the pieces: {', '.join(PIECES)})")


# --- sharing one host -----------------------------------------------------------------------------------------------


def shares(cores: Sequence[int], gpus: int, pieces: int) -> list[tuple[int, str]]:
    """(GPU, cores as a taskset-style list) of `pieces` side by side on a host whose usable cores are `cores`: piece i
    on GPU i % gpus and on the i-th of `pieces` equal slices of the cores (the remainder unused), so that no two pieces
    share a core. Refused where a piece would get no core."""
    cores = sorted(cores)
    each = len(cores) // pieces if pieces else 0
    if pieces < 1 or gpus < 1 or each < 1:
        raise ValueError(f"{pieces} pieces cannot share {len(cores)} cores and {gpus} GPUs")
    return [(i % gpus, cpu_list(cores[i * each:(i + 1) * each])) for i in range(pieces)]


def cpu_list(cores: Sequence[int]) -> str:
    """[0, 1, 2, 5] -> "0-2,5" (taskset's and sched_setaffinity's list form)."""
    out, cores = [], sorted(cores)
    i = 0
    while i < len(cores):
        j = i
        while j + 1 < len(cores) and cores[j + 1] == cores[j] + 1:
            j += 1
        out.append(str(cores[i]) if i == j else f"{cores[i]}-{cores[j]}")
        i = j + 1
    return ",".join(out)


def parse_cpus(text: str) -> set[int]:
    """"0-2,5" -> {0, 1, 2, 5}."""
    out = set()
    for item in filter(None, text.split(",")):
        first, _, last = item.partition("-")
        out.update(range(int(first), int(last or first) + 1))
    return out


def pinned(cpus: str, argv: Sequence[str]) -> tuple[str, ...]:
    """argv run on the cores `cpus` (`python -m experiments.atari.ale40m pin CPUS ARGV...`; as `taskset -c`, which the
    image may lack); argv as it is where cpus is empty."""
    return tuple(argv) if not cpus else ("python", "-m", "experiments.atari.ale40m", "pin", cpus, *argv)


def _pin(cpus: str, argv: Sequence[str]) -> None:
    """Replace this process by argv, on the cores `cpus` (its threads, and its children's, inherit them)."""
    os.sched_setaffinity(0, parse_cpus(cpus))
    argv = [sys.executable, *argv[1:]] if argv[0] == "python" else list(argv)
    os.execvp(argv[0], argv)


# --- a piece's run directory ----------------------------------------------------------------------------------------


def latest_checkpoints(run_dir: pathlib.Path) -> dict[str, int]:
    """{arm: the step of its newest complete checkpoint} of a run directory (directories named by their step)."""
    top = run_dir / "checkpoints"
    out = {}
    for arm_dir in sorted(top.iterdir()) if top.is_dir() else ():
        steps = [int(p.name) for p in arm_dir.iterdir() if p.name.isdigit()] if arm_dir.is_dir() else []
        if steps:
            out[arm_dir.name] = max(steps)
    return out


def updates_done(run_dir: pathlib.Path) -> int:
    """The updates every arm of a run directory has checkpointed (0 where one has none)."""
    run = json.loads((run_dir / "run.json").read_text()) if (run_dir / "run.json").exists() else {"arms": []}
    done = latest_checkpoints(run_dir)
    return min((done.get(a["name"], 0) for a in run["arms"]), default=0)


def num_updates(run_dir: pathlib.Path) -> int | None:
    """The updates each run of a run directory is to reach (run.json), None where it has none."""
    if not (run_dir / "run.json").exists():
        return None
    return min(a["num_updates"] for a in json.loads((run_dir / "run.json").read_text())["arms"])


def complete(run_dir: pathlib.Path) -> bool:
    """Every arm checkpointed at its last update."""
    target = num_updates(run_dir)
    return target is not None and updates_done(run_dir) >= target


def evaluated(run_dir: pathlib.Path, episodes: int = 100) -> bool:
    """Every run of the run directory evaluated over `episodes` episodes at its last update."""
    from cdjax import io

    if not complete(run_dir):
        return False
    run = json.loads((run_dir / "run.json").read_text())
    rows = io.read_jsonl(run_dir / "eval.jsonl")
    last = num_updates(run_dir)
    seen = {(r["arm"], r["seed"]) for r in rows if r.get("episodes") == episodes and r["update"] == last}
    return all((a["name"], s) in seen for a in run["arms"] for s in range(run["seeds"]))


# --- packing: the resumable state in parts --------------------------------------------------------------------------


def _kept(run_dir: pathlib.Path) -> list[pathlib.Path]:
    """The files of a run directory a resume needs and a report reads: all but TensorBoard's, the lock and each arm's
    older checkpoints."""
    latest = latest_checkpoints(run_dir)
    out = []
    for path in sorted(run_dir.rglob("*")):
        rel = path.relative_to(run_dir)
        if not path.is_file() or rel.parts[0] == "tb" or path.name == ".lock":
            continue
        if rel.parts[0] == "checkpoints" and (len(rel.parts) < 4 or rel.parts[2] != str(latest.get(rel.parts[1]))):
            continue  # an older checkpoint, or one set aside (<step>.unreadable)
        out.append(path)
    return out


def pack(run_dir: pathlib.Path, dest: pathlib.Path, name: str, part_bytes: int = FILE_MAX,
         logs: Sequence[pathlib.Path] = (), every: int = EVERY) -> list[pathlib.Path]:
    """dest/NAME.uUPDATES.I-of-N: the run directory's resumable state (`_kept`, its metrics.jsonl reduced to the rows of
    every `every`-th update) as one xz-compressed tar cut into N parts of at most `part_bytes`; UPDATES is what every
    arm has checkpointed. `logs` (e.g. the unit's log) are first
    copied into run_dir/logs/ as STEM.uUPDATES.SUFFIX, so that each loan's log travels on with the run. Earlier parts
    of the same piece in dest are removed once the new ones are written."""
    updates = updates_done(run_dir)
    for path in logs:
        if path.is_file():
            (run_dir / "logs").mkdir(exist_ok=True)
            shutil.copyfile(path, run_dir / "logs" / f"{path.stem}.u{updates:06d}{path.suffix}")
    from cdjax import io

    buf = _io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w") as tar:
        for path in _kept(run_dir):
            if path.name not in ("metrics.jsonl", "metrics.jsonl.xz", "metrics.jsonl.gz"):
                tar.add(path, arcname=str(path.relative_to(run_dir)), recursive=False)
        rows = [r for r in io.read_jsonl(run_dir / "metrics.jsonl") if r["update"] % every == 0]
        text = "".join(json.dumps(r) + "\n" for r in rows).encode()
        info = tarfile.TarInfo("metrics.jsonl")
        info.size, info.mtime = len(text), int(time.time())
        tar.addfile(info, _io.BytesIO(text))
    # xz at preset 1: the checkpoints' float32 arrays hardly compress at any preset (RESULTS.md), the logs do at any
    data = lzma.compress(buf.getvalue(), preset=1)
    count = max(1, -(-len(data) // part_bytes))
    dest.mkdir(parents=True, exist_ok=True)
    old = [p for p in dest.iterdir() if (m := PART.match(p.name)) and m["piece"] == name]
    written = []
    for i in range(count):
        path = dest / f"{name}.u{updates:06d}.{i:02d}-of-{count:02d}"
        tmp = path.with_name(path.name + ".tmp")
        tmp.write_bytes(data[i * part_bytes:(i + 1) * part_bytes])
        tmp.replace(path)
        written.append(path)
    for p in old:
        if p not in written:
            p.unlink()
    return written


def part_sets(directory: pathlib.Path) -> dict[str, dict]:
    """{piece: {"updates", "count", "parts": [paths present]}} of the parts in a directory: for each piece its newest
    set (by updates)."""
    sets: dict[str, dict] = {}
    for path in sorted(directory.iterdir()) if directory.is_dir() else ():
        m = PART.match(path.name)
        if not m:
            continue
        updates, count = int(m["updates"]), int(m["count"])
        s = sets.get(m["piece"])
        if s is None or updates > s["updates"]:
            s = sets[m["piece"]] = {"updates": updates, "count": count, "parts": []}
        if updates == s["updates"]:
            s["parts"].append(path)
    return sets


def whole(s: dict) -> bool:
    """A set of parts holds all of its parts."""
    return sorted(PART.match(p.name)["index"] for p in s["parts"]) == [f"{i:02d}" for i in range(s["count"])]


def unpack(parts: Sequence[pathlib.Path], run_dir: pathlib.Path) -> int:
    """A piece's parts (all of one set, any order) unpacked into run_dir (made; refused where it holds a run); returns
    the updates its arms had checkpointed. lzma refuses a set with a part missing or damaged."""
    parts = sorted(parts, key=lambda p: int(PART.match(p.name)["index"]))
    if (run_dir / "run.json").exists():
        raise FileExistsError(f"{run_dir} already holds a run")
    data = lzma.decompress(b"".join(p.read_bytes() for p in parts))
    run_dir.mkdir(parents=True, exist_ok=True)
    with tarfile.open(fileobj=_io.BytesIO(data)) as tar:
        for m in tar.getmembers():
            if m.name.startswith("/") or ".." in pathlib.PurePosixPath(m.name).parts or not m.isfile():
                raise ValueError(f"unexpected member {m.name!r} in {parts[0].name}")
        tar.extractall(run_dir, filter="data")
    return updates_done(run_dir)


def send(outbox: pathlib.Path, out: pathlib.Path, files: int = CALL_FILES, limit: int = CALL_MAX,
         again: bool = False) -> list[pathlib.Path]:
    """Copy what fits one call's return (at most `files` files and `limit` bytes) from outbox to out, in name order (a
    piece's parts together), and move the originals to outbox/sent; returns the files left waiting. `again`: the files
    sent before wait again (a call whose files did not come back)."""
    sent = outbox / "sent"
    if again and sent.is_dir():
        for path in sent.iterdir():
            path.replace(outbox / path.name)
    waiting = sorted(p for p in outbox.iterdir() if p.is_file() and PART.match(p.name)) if outbox.is_dir() else []
    taken, size = 0, 0
    out.mkdir(parents=True, exist_ok=True)
    sent.mkdir(parents=True, exist_ok=True)
    left = []
    for path in waiting:
        n = path.stat().st_size
        if taken < files and size + n <= limit:
            shutil.copyfile(path, out / path.name)
            path.replace(sent / path.name)
            taken, size = taken + 1, size + n
        else:
            left.append(path)
    return left


# --- the loan: start, poll, send ------------------------------------------------------------------------------------


def _end_in(given: int | None) -> int:
    """Seconds from now by which the pieces must have ended, packed: given, else the 30 minutes a machine is held less
    what it has been up (its start before the kernel's clock: a minute more), less SEND_S for the calls that bring the
    parts back."""
    if given is not None:
        return given
    up = float(pathlib.Path("/proc/uptime").read_text().split()[0])
    return int(HOLD_S - up - 60 - SEND_S)


def start(pieces: Sequence[str], work: pathlib.Path, carried: pathlib.Path | None, end_in: int, gpus: int,
          cores: Sequence[int], params: Sequence[str] = (), say=print) -> list[str]:
    """Start each piece not yet started whose state is here (or that starts from nothing), on its GPU and cores
    (`shares` of all the pieces named), its training stopped so that it has evaluated (where its run reached its steps)
    and packed `end_in` seconds from now; `params` (NAME=VALUE) go to every piece's unit (e.g. a dry run's smaller
    `steps` and `sweep` options); returns the pieces started by this call. The carried folder's MANIFEST
    (`stage`) names the updates each piece has done: a piece done in part waits for its parts, never starts afresh."""
    from experiments import launch

    for piece in pieces:
        piece_of(piece)
    # A call's carry replaces the carried folder there: its parts are gathered in work/incoming across the calls.
    incoming = work / "incoming"
    incoming.mkdir(parents=True, exist_ok=True)
    for path in sorted(carried.iterdir()) if carried is not None and carried.is_dir() else ():
        if PART.match(path.name) or path.name == MANIFEST:
            shutil.copyfile(path, incoming / path.name)
    carried_sets = part_sets(incoming)
    manifest = incoming / MANIFEST
    expected = json.loads(manifest.read_text()) if manifest.exists() else {}
    started = []
    for piece, (gpu, cpus) in zip(pieces, shares(cores, gpus, len(pieces))):
        queue = work / piece
        if (queue / "queue.json").exists():
            say(f"{piece}: started earlier ({', '.join(f'{k} {v}' for k, v in launch.state(queue).items())})")
            continue
        unit_dir = queue / piece
        run_dir = unit_dir / piece_of(piece)[0]
        s = carried_sets.get(piece)
        if not (run_dir / "run.json").exists():
            want = expected.get(piece, 0)
            if s is not None and whole(s) and s["updates"] >= want:
                updates = unpack(s["parts"], run_dir)
                say(f"{piece}: unpacked at {updates} updates into {run_dir}")
            elif s is not None or want:
                have = f"{len(s['parts'])} of its {s['count']} parts at {s['updates']} updates" if s else "no parts"
                say(f"{piece}: done to {want} updates, {have} here; it starts once they are all carried in")
                continue
        limit = end_in - EVAL_S - PACK_S
        if limit < 120:
            say(f"{piece}: not started: {end_in} s left, fewer than {EVAL_S + PACK_S + 120} s")
            continue
        launch.start("atari", [piece], queue, time_limit=limit, gpu=gpu,
                     args=["--end", str(end_in), "--param", f"cpus={cpus}", "--param", f"outbox={outbox(work)}",
                           *(x for item in params for x in ("--param", item))])
        say(f"{piece}: STARTED on GPU {gpu}, cores {cpus}, training for at most {limit} s, packed within {end_in} s")
        started.append(piece)
    return started


def outbox(work: pathlib.Path) -> pathlib.Path:
    return work / "outbox"


def poll(work: pathlib.Path, wait_s: float = 0, say=print) -> int:
    """Each piece's state (launch.poll's); 0 when all have ended, launch.RUNNING while one runs."""
    from experiments import launch

    queues = sorted(p.parent for p in work.glob("*/queue.json"))
    if not queues:
        say(f"{work}: nothing started there")
        return 2
    stop = time.monotonic() + wait_s
    while time.monotonic() < stop and not all((q / "done").exists() for q in queues):
        time.sleep(2)
    status = 0
    for q in queues:
        say(f"== {q.name}")
        status = max(status, launch.poll(q))
    return status


# --- here: the store of states between loans, and the report's run directories ------------------------------------


def progress(store: pathlib.Path) -> dict[str, dict]:
    """{piece: {"updates", "of", "parts", "bytes", "evaluated"}} of the states kept in the store."""
    sets = part_sets(store / "state")
    out = {}
    for piece in PIECES:
        s = sets.get(piece)
        record = store / "done" / f"{piece}.json"
        info = json.loads(record.read_text()) if record.exists() else {}
        out[piece] = {"updates": s["updates"] if s else 0, "of": UPDATES, "parts": len(s["parts"]) if s else 0,
                      "bytes": sum(p.stat().st_size for p in s["parts"]) if s else 0,
                      "evaluated": bool(info.get("evaluated"))}
    return out


def absorb(files_at: pathlib.Path, store: pathlib.Path, say=print) -> dict[str, int]:
    """Take what a call brought back (parts of pieces' states) into the store: a piece's parts go to store/incoming
    until its set is whole, then replace its state in store/state, and its run directory is unpacked into
    store/runs/PIECE (logs and evaluations for `merge`). Returns {piece: updates} of the sets completed."""
    incoming, state = store / "incoming", store / "state"
    incoming.mkdir(parents=True, exist_ok=True)
    for path in sorted(files_at.iterdir()):
        if PART.match(path.name):
            shutil.copyfile(path, incoming / path.name)
    done = {}
    for piece, s in part_sets(incoming).items():
        if not whole(s):
            say(f"{piece}: {len(s['parts'])} of {s['count']} parts at {s['updates']} updates so far")
            continue
        runs = store / "runs" / piece
        tmp = runs.with_name(piece + ".tmp")
        shutil.rmtree(tmp, ignore_errors=True)
        updates = unpack(s["parts"], tmp)  # refuses a damaged set before anything is replaced
        shutil.rmtree(runs, ignore_errors=True)
        tmp.replace(runs)
        state.mkdir(parents=True, exist_ok=True)
        for old in state.iterdir():
            if (m := PART.match(old.name)) and m["piece"] == piece:
                old.unlink()
        for p in s["parts"]:
            p.replace(state / p.name)
        for p in incoming.iterdir():  # older sets of the piece that never came whole
            if (m := PART.match(p.name)) and m["piece"] == piece and int(m["updates"]) < s["updates"]:
                p.unlink()
        (store / "done").mkdir(exist_ok=True)
        (store / "done" / f"{piece}.json").write_text(json.dumps({"updates": updates, "evaluated": evaluated(runs)}))
        say(f"{piece}: kept at {updates} of {UPDATES} updates{' (evaluated)' if evaluated(runs) else ''}")
        done[piece] = updates
    return done


def tree_bytes(repo: pathlib.Path, beside: Sequence[pathlib.Path] = ()) -> int:
    """What a call from `repo` sends besides the staged parts, as the device tool counts it (experiments/wheels.sh's
    carry_size): the tracked files, the untracked ones git does not ignore, and the paths `beside` (other carried
    folders), each file 512 bytes of header and its bytes in 512-byte blocks."""
    import subprocess

    def listed(*args):
        out = subprocess.run(["git", "-C", str(repo), "ls-files", "-z", *args], capture_output=True, check=True).stdout
        return [repo / f.decode() for f in out.split(b"\0") if f]

    files = {f for f in listed() + listed("-o", "--exclude-standard") if f.is_file()}
    for path in beside:
        files.update(f for f in ([path] if path.is_file() else path.rglob("*")) if f.is_file())
    return sum(512 + -(-f.stat().st_size // 512) * 512 for f in files)


def stage(pieces: Sequence[str], store: pathlib.Path, into: pathlib.Path, room: int, first: bool = False,
          say=print) -> list[pathlib.Path]:
    """Copy into `into` (emptied first; a folder of the repository that .git/info/exclude ignores, named in the call's
    carry) the parts of the pieces' states that `room` bytes hold, in the order the pieces are named, and MANIFEST
    ({piece: updates} of the pieces in the store); parts staged earlier in this loan (store/staged; forgotten with
    `first`, a new loan) are not staged again. Returns what was copied."""
    sets = part_sets(store / "state")
    shutil.rmtree(into, ignore_errors=True)
    into.mkdir(parents=True)
    (into / MANIFEST).write_text(json.dumps({p: sets[p]["updates"] for p in pieces if p in sets}))
    record = store / "staged"
    sent = set() if first or not record.exists() else set(record.read_text().split())
    copied, used, full = [], 1024, False
    for piece in pieces:
        piece_of(piece)
    todo = [part for piece in pieces for part in (sets.get(piece) or {"parts": []})["parts"] if part.name not in sent]
    for part in todo:
        size = 512 + -(-part.stat().st_size // 512) * 512  # as the device tool counts a file
        if full or used + size > room:
            full = True  # parts go in the pieces' order: a piece's parts are not split around a later piece's
            continue
        shutil.copyfile(part, into / part.name)
        copied.append(into / part.name)
        used += size
    record.write_text("".join(f"{n}\n" for n in sorted(sent | {p.name for p in copied})))
    say(f"staged {len(copied)} parts ({used:,} bytes of {room:,}) in {into}; {len(todo) - len(copied)} parts of these "
        "pieces left for later calls" + ("" if copied or not todo else ": none fits this call's room"))
    return copied


def merge_game(runs: Sequence[pathlib.Path], out: pathlib.Path) -> pathlib.Path:
    """One run directory per game for experiments.atari.report and aggregate (as the 1M tier's): the pieces' run
    directories (one arm each, the same game, seeds and preset) joined: run.json with every arm, metrics.jsonl.xz
    (the rows the pieces carried, with KEPT_FIELDS) and eval.jsonl with every arm's rows, each piece's log.txt as
    log-ARM.txt and its loans' unit logs under logs-ARM/."""
    from cdjax import io

    records = [json.loads((r / "run.json").read_text()) for r in runs]
    first = records[0]
    for rec in records[1:]:
        if rec["base_config"] != first["base_config"] or rec["seeds"] != first["seeds"]:
            raise ValueError(f"{runs[0]} and another piece differ in game, config or seeds")
    merged = dict(first, arms=[a for rec in records for a in rec["arms"]])
    out.mkdir(parents=True, exist_ok=True)
    (out / "run.json").write_text(json.dumps(merged, indent=1))
    metrics = [{k: row[k] for k in KEPT_FIELDS if k in row} for r in runs for row in io.read_jsonl(r / "metrics.jsonl")]
    io.write_packed(out / "metrics.jsonl", "".join(json.dumps(row) + "\n" for row in metrics).encode())
    evals = [row for r in runs for row in io.read_jsonl(r / "eval.jsonl")]
    (out / "eval.jsonl").write_text("".join(json.dumps(row) + "\n" for row in evals))
    for r, rec in zip(runs, records):
        arm = rec["arms"][0]["name"]
        if (r / "log.txt").exists():
            shutil.copyfile(r / "log.txt", out / f"log-{arm}.txt")
        if (r / "logs").is_dir():
            shutil.copytree(r / "logs", out / f"logs-{arm}", dirs_exist_ok=True)
    return out


def merge(store: pathlib.Path, out: pathlib.Path, say=print) -> list[pathlib.Path]:
    """Each game whose two pieces are kept: joined into out/GAME (`merge_game`)."""
    written = []
    for game in GAMES:
        runs = [store / "runs" / f"ale40m-{game}-{arm}" for arm in ARMS]
        if all((r / "run.json").exists() for r in runs):
            written.append(merge_game(runs, out / game))
            say(f"{game}: {', '.join(f'{r.name} at {updates_done(r)} updates' for r in runs)} -> {out / game}")
    return written


def state_size(game: str, arm: str, seeds: int, out: pathlib.Path, steps: int = 2) -> dict:
    """What one piece's checkpoint takes, at the game's preset sizes (needs ale-py; no emulator is started): `seeds`
    runs' parameters and optimiser state after `steps` optimiser steps on random frames (so that no leaf is all zeros,
    which a checkpoint leaves out), written by cdjax.io.Checkpoints into out/checkpoints/ARM; returns the bytes of the
    arrays, of orbax's files, of their tar and of that tar compressed (xz presets 1 and 6, gzip), with the seconds each
    compression took."""
    import gzip

    import jax
    import jax.numpy as jnp

    from cdjax import consistency, io
    from cdjax.agents.atari import AtariConfig, AtariHParams
    from cdjax.agents.atari.learner import A2C, Batch
    from cdjax.agents.atari.presets import PRESETS

    config = AtariConfig(**PRESETS[game].config, arm=arm)
    agent, hp = A2C(config), AtariHParams()
    T, B = config.rollout_len, config.num_envs

    def one_run(key):
        key_params, key = jax.random.split(key)
        params = agent.init_params(key_params)
        opt = agent.optimizer(hp)
        opt_state = opt.init(params)
        for _ in range(steps):
            key_obs, key_act, key_rew, key_win, key = jax.random.split(key, 5)
            frames = jax.random.randint(key_obs, (T + 1, B, *agent.env.obs_shape), 0, 255).astype(jnp.uint8)
            batch = Batch(obs=frames[:-1], action=jax.random.randint(key_act, (T, B), 0, agent.num_actions),
                          reward=jax.random.normal(key_rew, (T, B)), next_obs=frames[1:],
                          terminated=jnp.zeros((T, B), bool), ended=jnp.zeros((T, B), bool),
                          valid=jnp.ones((T, B), bool))
            offsets = consistency.window_offsets(key_win, T, config.horizon, config.num_windows)
            grads, _ = jax.grad(agent.loss, has_aux=True)(params, batch, offsets, hp)
            updates, opt_state = opt.update(grads, opt_state, params)
            params = jax.tree.map(jnp.add, params, updates)
        return {"params": params, "opt_state": opt_state}

    tree = jax.jit(jax.vmap(one_run))(jax.random.split(jax.random.key(0), seeds))
    ckpt = io.Checkpoints(out / "checkpoints" / arm)
    ckpt.save(steps, tree, {"updates": steps})
    ckpt.wait()
    ckpt.close()
    buf = _io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w") as tar:
        tar.add(out / "checkpoints", arcname="checkpoints")
    data = buf.getvalue()
    sizes = {"arrays": sum(x.size * x.dtype.itemsize for x in jax.tree.leaves(tree)),
             "params": sum(x.size for x in jax.tree.leaves(tree["params"])) // seeds,
             "files": sum(p.stat().st_size for p in (out / "checkpoints").rglob("*") if p.is_file()), "tar": len(data)}
    for name, compress in (("xz1", lambda d: lzma.compress(d, preset=1)), ("xz6", lambda d: lzma.compress(d, preset=6)),
                           ("gzip6", lambda d: gzip.compress(d, 6))):
        t = time.perf_counter()
        sizes[name] = (len(compress(data)), round(time.perf_counter() - t, 1))
    return sizes


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m experiments.atari.ale40m", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="command", required=True)
    s = sub.add_parser("start", help="on the GPU host: unpack what was carried in, start the pieces (again: the rest)")
    s.add_argument("pieces", nargs="+", metavar="PIECE")
    s.add_argument("--work", type=pathlib.Path, required=True)
    s.add_argument("--carried", type=pathlib.Path, help="the carried folder that holds the pieces' parts")
    s.add_argument("--end-in", type=int, metavar="S", help="seconds from now by which every piece has packed "
                   f"(default: {HOLD_S} s less the machine's uptime, a minute and {SEND_S} s)")
    s.add_argument("--gpus", type=int, help="GPUs to share (default: nvidia-smi's count)")
    s.add_argument("--param", action="append", default=[], metavar="NAME=VALUE",
                   help="a parameter of every piece's unit (a dry run: steps=400, sweep='--num-envs 2 --latent 32')")
    pl = sub.add_parser("poll", help="on the GPU host: each piece's state; exit status 0 once all have ended")
    pl.add_argument("--work", type=pathlib.Path, required=True)
    pl.add_argument("--wait", type=float, default=0, metavar="S")
    se = sub.add_parser("send", help="on the GPU host: move what one call brings back into --out (MORE: call again)")
    se.add_argument("--work", type=pathlib.Path, required=True)
    se.add_argument("--out", type=pathlib.Path, required=True)
    se.add_argument("--again", action="store_true", help="send again what was sent (its call's files were lost)")
    pk = sub.add_parser("pack", help="a run directory's resumable state into parts (a piece's last step)")
    pk.add_argument("run_dir", type=pathlib.Path)
    pk.add_argument("dest", type=pathlib.Path)
    pk.add_argument("--name", required=True)
    pk.add_argument("--log", type=pathlib.Path, action="append", default=[], help="a log to keep with the run")
    pk.add_argument("--every", type=int, default=EVERY, help=f"metrics of every N-th update kept (default {EVERY})")
    pin = sub.add_parser("pin", help="run a command on the given cores")
    pin.add_argument("cpus")
    pin.add_argument("argv", nargs=argparse.REMAINDER)
    pn = sub.add_parser("plan", help="here: each piece's progress in the store")
    pn.add_argument("--store", type=pathlib.Path, required=True)
    st = sub.add_parser("stage", help="here: copy the next parts to carry into --into")
    st.add_argument("pieces", nargs="+", metavar="PIECE")
    st.add_argument("--store", type=pathlib.Path, required=True)
    st.add_argument("--into", type=pathlib.Path, required=True)
    st.add_argument("--beside", type=pathlib.Path, nargs="*", default=[], metavar="PATH",
                    help="the other paths this call carries (e.g. the wheels' folders): the room is 64 MiB less them "
                         "and the tracked tree")
    st.add_argument("--first", action="store_true", help="the loan's first call: stage from its first part")
    ab = sub.add_parser("absorb", help="here: keep what a call brought back")
    ab.add_argument("files_at", type=pathlib.Path)
    ab.add_argument("--store", type=pathlib.Path, required=True)
    sz = sub.add_parser("sizes", help="what a piece's checkpoint takes at the preset's sizes (needs ale-py)")
    sz.add_argument("--games", nargs="+", default=list(GAMES), choices=GAMES)
    sz.add_argument("--arms", nargs="+", default=list(ARMS), choices=ARMS)
    sz.add_argument("--seeds", type=int, default=SEEDS)
    sz.add_argument("--out", type=pathlib.Path, required=True, help="a directory for the checkpoints written")
    mg = sub.add_parser("merge", help="here: one run directory per game for the report")
    mg.add_argument("--store", type=pathlib.Path, required=True)
    mg.add_argument("--out", type=pathlib.Path, required=True)
    args = p.parse_args(argv)
    if args.command == "pin":
        _pin(args.cpus, args.argv)
    if args.command == "start":
        end_in = _end_in(args.end_in)
        from benchmarks.common import gpu_count

        gpus = args.gpus if args.gpus is not None else gpu_count()
        from cdjax.agents.atari.ale import usable_cores

        print(f"{len(os.sched_getaffinity(0))} cores, {gpus} GPUs; the pieces end, packed, within {end_in} s "
              f"({usable_cores()} usable)")
        try:
            start(args.pieces, args.work, args.carried, end_in, max(gpus, 1), sorted(os.sched_getaffinity(0)),
                  args.param)
        except ValueError as err:
            p.error(str(err))
        return 0
    if args.command == "poll":
        return poll(args.work, args.wait)
    if args.command == "send":
        if not any(args.work.glob("*/queue.json")):
            print(f"{args.work}: nothing started there", file=sys.stderr)
            return 2
        left = send(outbox(args.work), args.out, again=args.again)
        for path in sorted(args.out.iterdir()):
            print(f"{path.name} {path.stat().st_size:,}")
        running = [q.parent.name for q in args.work.glob("*/queue.json") if not (q.parent / "done").exists()]
        print(f"MORE: {len(left)} files wait; call send again" if left else
              f"RUNNING: {', '.join(running)} not yet packed; poll, then send again" if running else "ALL SENT")
        return 0
    if args.command == "pack":
        for path in pack(args.run_dir, args.dest, args.name, logs=args.log, every=args.every):
            print(f"{path} {path.stat().st_size:,}")
        return 0
    if args.command == "plan":
        print("| piece | updates | of | parts kept | bytes | evaluated |\n|---|---:|---:|---:|---:|---|")
        for piece, info in progress(args.store).items():
            print(f"| {piece} | {info['updates']:,} | {info['of']:,} | {info['parts']} | {info['bytes']:,} | "
                  f"{'yes' if info['evaluated'] else 'no'} |")
        return 0
    if args.command == "stage":
        room = CALL_MAX - tree_bytes(pathlib.Path.cwd(), args.beside)  # `into` is ignored by git: not counted twice
        stage(args.pieces, args.store, args.into, room, args.first)
        return 0
    if args.command == "absorb":
        absorb(args.files_at, args.store)
        return 0
    if args.command == "sizes":
        from cdjax import runtime

        runtime.apply_xla_defaults()
        for game in args.games:
            for arm in args.arms:
                print(game, arm, args.seeds, "runs:", state_size(game, arm, args.seeds, args.out / f"{game}-{arm}"),
                      flush=True)
        return 0
    merge(args.store, args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
