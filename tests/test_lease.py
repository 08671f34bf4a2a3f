"""experiments/lease.sh: a unit started once as its own process session, polled by later calls, outliving them."""

import pathlib
import subprocess
import time

LEASE = pathlib.Path(__file__).resolve().parents[1] / "experiments" / "lease.sh"


def _call(work, cmd, wait_s):
    script = f'. {LEASE}; unit_run {work} "{cmd}" {wait_s} $(date +%s) "call me again"; echo "status $?"'
    return subprocess.run(["bash", "-c", script], capture_output=True, text=True, timeout=60).stdout


def test_a_unit_starts_once_outlives_the_call_and_a_later_call_finds_it_done(tmp_path):
    work = tmp_path / "unit"
    marker = tmp_path / "runs"
    cmd = f"echo x >> {marker}; sleep 2; echo finished; exit 7"
    first = _call(work, cmd, 0)  # returns at once: still running
    assert "STARTED" in first and "RUNNING" in first and "call me again" in first and first.endswith("status 3\n")
    second = _call(work, cmd, 0)  # a poll does not start it again
    assert "STARTED" not in second and second.endswith("status 3\n")
    deadline = time.monotonic() + 30
    while not (work / "exit_code").exists() and time.monotonic() < deadline:
        time.sleep(0.2)
    third = _call(work, cmd, 5)
    assert third.endswith("status 0\n") and "RUNNING" not in third
    assert (work / "exit_code").read_text().strip() == "7" and (work / "unit.log").read_text() == "finished\n"
    assert marker.read_text() == "x\n" and (work / "command").read_text().strip() == cmd
