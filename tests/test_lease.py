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
    script = f'export PATH={bin_dir}:$PATH SITE={site}; unset PYTHONPATH; . {LEASE}; ensure_wheels; echo "rc $? $PYTHONPATH"'

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
