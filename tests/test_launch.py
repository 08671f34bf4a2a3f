"""experiments.launch (units run in the foreground, or started once in the background, polled and collected) and
experiments/wheels.sh (the carried wheels installed on a GPU machine). No JAX: the units here are small Python
commands of a fake experiment package."""

import json
import pathlib
import signal
import subprocess
import sys
import tarfile
import textwrap
import time

import pytest

from experiments import launch
from experiments.launch import Context, Step, Unit

ROOT = pathlib.Path(__file__).resolve().parents[1]
WHEELS = ROOT / "experiments" / "wheels.sh"


def _ctx(tmp_path, limit=100, end=200, **params):
    return Context(out=tmp_path / "unit", limit=limit, end=end, params=params)


def test_a_units_steps_run_in_turn_a_failure_does_not_stop_the_next_and_a_hang_is_stopped(tmp_path, capsys):
    """Each step's output goes to its log (or the unit's); a step past its timeout gets its signal (the sweep's
    SIGINT: it checkpoints and stops) and 124; a `when` that says no skips the step; the first failure is the
    unit's exit status; `show` prints the files named."""
    handler = ("import signal, sys, time\n"
               "signal.signal(signal.SIGINT, lambda *a: (print('interrupted', flush=True), sys.exit(130)))\n"
               "time.sleep(30)")
    seen = []

    def steps(ctx):
        return [Step(("python", "-c", "print('one'); raise SystemExit(5)"), log="one.log"),
                Step(("python", "-c", handler), log="hang.log", timeout=lambda c: seen.append(c.limit) or 1),
                Step(("python", "-c", "print('never')"), when=lambda c: False),
                Step(("python", "-c", "import os; print('three', os.environ['CDJAX_X'])"), log="three.log",
                     env={"CDJAX_X": "1"})]

    unit = Unit("u", "a test", 1, steps, show=lambda c: ["one.log", "missing.md"])
    ctx = _ctx(tmp_path)
    t0 = time.monotonic()
    assert launch.run_unit(unit, ctx) == 5
    assert time.monotonic() - t0 < 20 and seen == [100]
    out = ctx.out
    assert (out / "one.log").read_text() == "one\n" and (out / "three.log").read_text() == "three 1\n"
    assert (out / "hang.log").read_text() == "interrupted\n"
    printed = capsys.readouterr().out
    assert "exit status 5" in printed and "exit status 124" in printed and "never" not in printed
    assert "CDJAX_X=1 python -c" in printed and "== one.log\none\n" in printed and "missing.md" not in printed


def test_a_step_that_ignores_its_signal_is_killed(tmp_path):
    ignore = ("import signal, time; signal.signal(signal.SIGTERM, signal.SIG_IGN); print('up', flush=True); "
              "time.sleep(30)")
    step = Step(("python", "-c", ignore), log="l", timeout=1, signal=signal.SIGTERM, kill_after=1)
    ctx = _ctx(tmp_path)
    ctx.out.mkdir()
    t0 = time.monotonic()
    assert launch._run_step(step, ctx) == 124 and time.monotonic() - t0 < 10


def test_a_units_parameters_are_its_own_and_run_takes_the_limits(tmp_path, capsys):
    got = []
    unit = Unit("u", "a test", 1, lambda c: got.append(c) or [], {"updates": "200"})
    units = {"u": unit}
    assert launch.unit_main("prog", units, 1260, 1680, ["run", "u", "--out", str(tmp_path / "d"),
                                                        "--param", "updates=150", "--time-limit", "900"]) == 0
    (ctx,) = got
    assert (ctx.out, ctx.limit, ctx.end, dict(ctx.params)) == (tmp_path / "d", 900, 1320, {"updates": "150"})
    for argv in (["run", "u", "--param", "steps=5"], ["run", "u", "--param", "updates"], ["run", "nothing"]):
        with pytest.raises(SystemExit) as stop:
            launch.unit_main("prog", units, 1260, 1680, argv)
        assert stop.value.code == 2
    assert "unit u has no parameter 'steps' (its parameters: updates)" in capsys.readouterr().err
    assert launch.unit_main("prog", units, 1260, 1680, ["list"]) == 0
    assert "| u | a test | 1 min | updates='200' |" in capsys.readouterr().out


FAKE = '''
from experiments.launch import Step, Unit

WRITE = """
import json, pathlib, sys
out = pathlib.Path(sys.argv[1]); run = out / "run"
(run / "checkpoints").mkdir(parents=True, exist_ok=True)
(run / "checkpoints" / "big").write_text("x")
(run / "run.json").write_text("{}")
rows = [{"arm": "a", "hp": "h", "seed": 0, "update": u} for u in range(1, 101)]
(run / "metrics.jsonl").write_text("".join(json.dumps(r) + "\\\\n" for r in rows))
(out / "note.md").write_text(sys.argv[2])
"""

def _write(ctx):
    return [Step(("python", "-c", "import time; time.sleep(1.5)")),
            Step(("python", "-c", WRITE, str(ctx.out), f"limit {ctx.limit}"))]

def _fail(ctx):
    return [Step(("python", "-c", "raise SystemExit(7)"))]

UNITS = {"write": Unit("write", "writes a run", 1, _write), "fail": Unit("fail", "fails", 1, _fail)}
THIN = {"points": 10, "tail": 5}
'''
MAIN = '''
from experiments import launch
from fakeexp import UNITS
raise SystemExit(launch.unit_main("fakeexp", UNITS, 100, 200))
'''


def test_units_start_once_in_the_background_are_polled_and_collected_thinned(tmp_path, monkeypatch, capsys):
    pkg = tmp_path / "fakeexp"
    pkg.mkdir()
    (pkg / "__init__.py").write_text(textwrap.dedent(FAKE))
    (pkg / "__main__.py").write_text(MAIN)
    monkeypatch.setenv("PYTHONPATH", f"{tmp_path}:{ROOT}")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.chdir(tmp_path)
    work = tmp_path / "queue"
    with pytest.raises(ValueError, match="fakeexp has no unit nothing"):
        launch.start("fakeexp", ["nothing"], work, 60)
    assert launch.start("fakeexp", ["write", "fail"], work, 60, gpu=3)
    assert launch.poll(work, 0) == launch.RUNNING  # returns at once: the first unit sleeps
    assert not launch.start("fakeexp", ["write"], work, 60)  # a second start finds the queue
    assert launch.poll(work, 60) == 0
    assert launch.state(work) == {"write": "exit 0", "fail": "exit 7"}
    printed = capsys.readouterr().out
    assert "RUNNING: poll again" in printed and printed.rstrip().endswith("DONE")
    command = (work / "write" / "command").read_text()
    assert command.startswith("python -m fakeexp run write --out") and "--time-limit" in command
    assert json.loads((work / "queue.json").read_text())["env"] == {"CUDA_VISIBLE_DEVICES": "3"}
    assert "note.md" in {p.name for p in (work / "write").iterdir()}
    left = int((work / "write" / "note.md").read_text().split()[1])
    assert 50 <= left <= 60  # the time limit, less what had passed when the unit started

    back = tmp_path / "back"
    assert sorted(p.name for p in launch.collect(work, back)) == ["fail.tar.gz", "write.tar.gz"]
    assert (back / "write.log").read_text() == (work / "write" / "unit.log").read_text()
    with tarfile.open(back / "write.tar.gz") as tar:
        names = set(tar.getnames())
        assert {"write/note.md", "write/unit.log", "write/exit_code", "write/command", "write/run/run.json",
                "write/run/metrics.jsonl.xz"} <= names
        assert not any("checkpoints" in n for n in names) and "write/run/metrics.jsonl" not in names
        tar.extractall(tmp_path / "unpacked", filter="data")
    from cdjax import io

    rows = list(io.read_jsonl(tmp_path / "unpacked" / "write" / "run" / "metrics.jsonl"))
    assert 10 <= len(rows) <= 14 and [r["update"] for r in rows[-5:]] == [96, 97, 98, 99, 100]  # THIN's

    # a unit left less than --min-s is skipped, not started
    late = tmp_path / "late"
    assert launch.start("fakeexp", ["fail"], late, 5, min_s=30)
    assert launch.poll(late, 30) == 0 and launch.state(late) == {"fail": f"exit {launch.SKIPPED}"}
    assert "skipped" in (late / "fail" / "unit.log").read_text()
    # without a time limit each unit runs at its own default (the fake experiment's 100 s)
    free = tmp_path / "free"
    assert launch.start("fakeexp", ["write"], free)
    assert launch.poll(free, 60) == 0 and (free / "write" / "note.md").read_text() == "limit 100"
    assert "--time-limit" not in (free / "write" / "command").read_text()


def test_poll_of_nothing_started_says_so(tmp_path, capsys):
    assert launch.poll(tmp_path / "none") == 2 and "nothing started" in capsys.readouterr().err


def test_ensure_wheels_installs_the_carried_wheels_once_and_puts_them_on_the_path(tmp_path):
    """A fake python3 on PATH: its import of brax fails (the GPU image), its pip records the call and makes the
    package directory. The first call installs from .whl/, a later one (the same machine) only sets PYTHONPATH;
    without .whl/ or .whl-site/ it says so and fails; with .whl-site/ alone it unpacks the tarball."""
    bin_dir, repo, site, calls = tmp_path / "bin", tmp_path / "repo", tmp_path / "site", tmp_path / "calls"
    bin_dir.mkdir()
    (repo / ".whl").mkdir(parents=True)
    (repo / ".whl" / "brax-0-py3-none-any.whl").write_text("")
    fake = bin_dir / "python3"
    fake.write_text(f'#!/usr/bin/env bash\nif [ "$1" = -c ]; then exit 1; fi\necho "$@" >> {calls}\nmkdir -p {site}/brax\n')
    fake.chmod(0o755)
    script = f'export PATH={bin_dir}:$PATH SITE={site}; unset PYTHONPATH; . {WHEELS}; ensure_wheels; echo "rc $? $PYTHONPATH"'

    def call(cwd):
        return subprocess.run(["bash", "-c", script], capture_output=True, text=True, timeout=60, cwd=cwd).stdout

    assert call(repo).strip().endswith(f"rc 0 {site}:{repo}")
    assert "--target " + str(site) in calls.read_text() and ".whl/brax-0-py3-none-any.whl" in calls.read_text()
    assert call(repo).strip().endswith(f"rc 0 {site}:{repo}") and len(calls.read_text().splitlines()) == 1
    (site / "brax").rmdir()
    bare = tmp_path / "bare"
    bare.mkdir()
    out = call(bare)
    assert "neither .whl/ nor .whl-site/" in out and out.strip().endswith("rc 1")
    # the packed form (pack_site): a tarball of the unpacked wheels, unpacked into $SITE without pip
    packed = tmp_path / "packed"
    (packed / ".whl-site").mkdir(parents=True)
    (tmp_path / "tree" / "brax").mkdir(parents=True)
    (tmp_path / "tree" / "brax" / "__init__.py").write_text("# brax\n")
    subprocess.run(["tar", "-cJf", str(packed / ".whl-site" / "site.tar.xz"), "-C", str(tmp_path / "tree"), "."],
                   check=True)
    before = calls.read_text()
    assert call(packed).strip().endswith(f"rc 0 {site}:{packed}")
    assert (site / "brax" / "__init__.py").read_text() == "# brax\n" and calls.read_text() == before  # no pip


def test_carry_size_counts_the_tracked_the_untracked_not_ignored_and_the_carried_files(tmp_path):
    """carry_size: what a device call would send, against its 64 MiB, counted as the device tool counts (each file
    a tar member: a 512-byte header and its bytes in whole 512-byte blocks)."""
    subprocess.run(["git", "init", "-q", str(tmp_path)], check=True)
    (tmp_path / ".gitignore").write_text("/.whl-x/\n")  # 9 bytes
    (tmp_path / "tracked").write_bytes(b"t" * 1000)
    subprocess.run(["git", "-C", str(tmp_path), "add", ".gitignore", "tracked"], check=True)
    (tmp_path / "untracked").write_bytes(b"u" * 500)
    (tmp_path / ".whl-x").mkdir()
    (tmp_path / ".whl-x" / "w.whl").write_bytes(b"w" * 2000)

    def size(*carry):
        done = subprocess.run(["bash", "-c", f". {WHEELS}; carry_size {' '.join(carry)}"], cwd=tmp_path, text=True,
                              capture_output=True, timeout=30)
        return done.returncode, done.stdout

    member = lambda n: 512 + -(-n // 512) * 512  # noqa: E731
    sent = member(9) + member(1000) + member(500)  # 3,584
    assert size() == (0, f"{sent:,} bytes (0.0 MiB) would travel, {64 * 2**20 - sent:,} bytes under 64 MiB\n")
    assert size(".whl-x")[1].startswith(f"{sent + member(2000):,} bytes")
    with open(tmp_path / ".whl-x" / "big.whl", "wb") as f:  # sparse: 64 MiB on paper, nothing on disk
        f.truncate(64 * 2**20)
    rc, out = size(".whl-x")
    over = sent + member(2000) + member(64 * 2**20) - 64 * 2**20
    assert rc == 1 and out.endswith(f"would travel: {over:,} bytes over 64 MiB\n")


def test_every_experiments_units_are_listed_by_its_plain_command():
    for name in launch.EXPERIMENTS:
        done = subprocess.run([sys.executable, "-m", f"experiments.{name}", "list"], cwd=ROOT, text=True,
                              capture_output=True, timeout=120)
        assert done.returncode == 0, done.stderr
        for unit in launch.experiment(name).UNITS:
            assert f"| {unit} |" in done.stdout
