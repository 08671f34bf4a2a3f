"""The host side keeps its promises under faults: sizes are bounded before anything is written, a resumed run
keeps every sweep option, a full disk and paths that cannot be written end in one sentence (exit 2) with the
previous checkpoint named and intact, and evaluation arguments are checked."""

import errno
import os
import pathlib
import shutil
import subprocess
import sys

import orbax.checkpoint as ocp
import pytest

from cdjax import io
from cdjax.cli import main

from _shared import TINY_ARGS, fail_in_one_sentence, logged_rows
from conftest import CACHE

STEPS = str(4 * 192)  # 4 updates of the tiny point-mass config: 2 chunks
# cd over alpha 0 and 1 (4 runs): the arm and programs of test_cli's tiny sweep, so the compilation cache serves them.
ARGS = [*TINY_ARGS, "--arms", "cd", "--alpha", "0", "1", "--eval-every", "1", "--eval-episodes", "2",
        "--bootstrap-reps", "50"]


@pytest.mark.parametrize("argv, words", [
    (["--seeds", "1000000", "--num-envs", "4096"], "The sweep needs about"),  # states alone: terabytes
    (["--steps", "1e30"], "more than the 2,147,483,647 its update counter (int32) holds"),
    (["--seed", "1e30"], "--seed must be an integer from 0 to 9,223,372,036,854,775,807"),
    (["--seeds", "0"], "--seeds must be an integer from 1 to 2,147,483,647, got 0"),
    (["--eval-episodes", "0"], "--eval-episodes must be an integer from 1"),
    (["--cc-windows", "50"], "cc_windows=50 is more than the 13 k-step windows a sequence of 16 steps holds"),
])
def test_sizes_that_cannot_run_are_refused_before_anything_is_written(capsys, tmp_path, argv, words):
    out = tmp_path / "run"
    line = fail_in_one_sentence(capsys, main, ["sweep", "--preset", "point", *argv, "--out", str(out)])
    assert words in line
    assert not out.exists()


def test_the_memory_estimate_names_the_sizes(capsys, tmp_path):
    line = fail_in_one_sentence(capsys, main, ["sweep", "--preset", "point", "--seeds", "1000000", "--num-envs",
                                               "4096", "--out", str(tmp_path / "run")])
    assert "per device" in line and "cd: 1,000,000 runs x" in line and "use fewer --seeds" in line


def test_paths_that_cannot_be_written(capsys, tmp_path):
    a_file = tmp_path / "a-file"
    a_file.write_text("keep me")
    line = fail_in_one_sentence(capsys, main, ["sweep", "--preset", "point", "--out", str(a_file)])
    assert "is a file, not a directory; choose another --out" in line
    line = fail_in_one_sentence(capsys, main, ["sweep", "--preset", "point", "--out", str(a_file / "run")])
    assert f"cannot write into {a_file / 'run'}: Not a directory" in line
    assert a_file.read_text() == "keep me"
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o500)
    try:
        if os.access(locked, os.W_OK):  # root writes anywhere: nothing to check with permissions
            return
        line = fail_in_one_sentence(capsys, main, ["sweep", "--preset", "point", "--out", str(locked / "run")])
        assert "Permission denied" in line and not (locked / "run").exists()
    finally:
        locked.chmod(0o700)


@pytest.mark.parametrize("argv, words", [
    (["eval", "{run}", "--episodes", "0"], "--episodes must be an integer from 1 to 2,147,483,647, got 0"),
    (["eval", "{run}", "--episodes", "-3"], "--episodes must be an integer from 1"),
    (["eval", "{run}", "--episodes", "2.5"], "not a whole number"),
    (["plot", "{run}", "--bootstrap-reps", "0"], "--bootstrap-reps must be an integer from 1"),
])
def test_evaluation_arguments(capsys, tmp_path, argv, words):
    run = tmp_path / "run"
    io.RunDir(run).create()
    io.RunDir(run).write({"version": io.RUN_VERSION})
    assert words in fail_in_one_sentence(capsys, main, [a.replace("{run}", str(run)) for a in argv])


def _fails_mid_run(capsys, argv) -> str:
    """Like fail_in_one_sentence, for a sweep that fails while running: its progress sentences may come first,
    then one `cdjax:` sentence ends stderr; no traceback and no library message."""
    with pytest.raises(SystemExit) as info:
        main(argv)
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.strip()]
    assert info.value.code == 2 and "Traceback" not in err and "ERROR" not in err, err
    assert [line for line in lines if line.startswith("cdjax:")] == lines[-1:] and lines[-1].endswith("."), err
    return lines[-1]


def _eval_rows(out):
    return io.read_jsonl(out / "eval.jsonl")


def test_a_full_disk_names_the_intact_checkpoint_and_a_resume_is_the_same_run(capsys, tmp_path, monkeypatch):
    """A write of the second chunk's metrics fails with ENOSPC; the resumed run, started without any option,
    ends with the evaluations (every chunk, 2 episodes) and summary of an uninterrupted run."""
    whole = tmp_path / "whole"
    main(["sweep", *ARGS, "--steps", STEPS, "--out", str(whole)])
    out = tmp_path / "cut"
    append = io.append_jsonl
    calls = {"metrics": 0}

    def full_disk(path, rows):
        if pathlib.Path(path).name == "metrics.jsonl":
            calls["metrics"] += 1
            if calls["metrics"] == 2:
                with io.writing(path):
                    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return append(path, rows)

    monkeypatch.setattr(io, "append_jsonl", full_disk)
    capsys.readouterr()
    line = _fails_mid_run(capsys, ["sweep", *ARGS, "--steps", STEPS, "--out", str(out)])
    said = (f"cdjax: cannot write {out / 'metrics.jsonl'}: No space left on device; the previous checkpoints are "
            f"intact (cd at update 2); resume with `cdjax sweep --out {out} --resume`")
    assert line.startswith(said), line
    monkeypatch.setattr(io, "append_jsonl", append)
    main(["sweep", "--out", str(out), "--resume"])
    assert logged_rows(out) == logged_rows(whole)
    assert _eval_rows(out) == _eval_rows(whole) and {r["episodes"] for r in _eval_rows(out)} == {2}
    assert (out / "summary.csv").read_text() == (whole / "summary.csv").read_text()

    before = (out / "eval.jsonl").read_text()
    capsys.readouterr()
    main(["sweep", "--out", str(out), "--resume"])  # a finished run: nothing trained, nothing evaluated twice
    assert "is complete" in capsys.readouterr().err and (out / "eval.jsonl").read_text() == before
    line = fail_in_one_sentence(capsys, main, ["sweep", "--out", str(out), "--resume", "--eval-episodes", "5"])
    assert "--eval-episodes cannot be changed" in line
    with io.RunDir(out).lock():  # as another process training in it would hold it
        line = _fails_mid_run(capsys, ["sweep", "--out", str(out), "--resume"])
    assert line == f"cdjax: {out} is in use by another cdjax process; wait for it to end or choose another --out."
    with io.RunDir(out).lock():  # an evaluation beside a live sweep would read checkpoints it turns over
        line = _fails_mid_run(capsys, ["eval", str(out), "--episodes", "2"])
    assert line == (f"cdjax: {out} is in use by another cdjax process; evaluate it when it has ended (its "
                    "checkpoints turn over while it trains).")
    assert (out / "eval.jsonl").read_text() == before


def test_a_checkpoint_that_cannot_be_written_is_named_with_the_previous_one(capsys, tmp_path, monkeypatch):
    save = ocp.CheckpointManager.save

    def full_disk(self, step, *args, **kwargs):
        if step == 4:  # what orbax raises from its writer threads when the disk is full
            raise ValueError("RESOURCE_EXHAUSTED: Error writing local file: Failed to write 130 bytes to file 23: "
                             "No space left on device [os_error_code='28']")
        return save(self, step, *args, **kwargs)

    monkeypatch.setattr(ocp.CheckpointManager, "save", full_disk)
    out = tmp_path / "run"
    line = _fails_mid_run(capsys, ["sweep", *ARGS, "--steps", STEPS, "--out", str(out)])
    assert f"cannot write the checkpoint {out / 'checkpoints' / 'cd' / '4'}: No space left on device" in line
    assert "the previous checkpoints are intact (cd at update 2)" in line
    assert sorted(p.name for p in (out / "checkpoints" / "cd").iterdir()) == ["2"]


def _mount_tmpfs(where: pathlib.Path, size: str) -> bool:
    where.mkdir()
    if shutil.which("mount") is None or os.geteuid() != 0:
        return False
    return subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(where)],
                          capture_output=True).returncode == 0


def test_a_real_full_disk_says_one_sentence_and_loses_at_most_a_chunk(tmp_path):
    disk = tmp_path / "disk"
    if not _mount_tmpfs(disk, "300k"):
        pytest.skip("mounting a small tmpfs needs root (the simulated full disks above run everywhere)")
    try:
        out = disk / "run"
        env = dict(os.environ, CDJAX_JAX_CACHE=str(CACHE), JAX_PLATFORMS="cpu")
        cmd = [sys.executable, "-m", "cdjax.cli", "sweep", *TINY_ARGS, "--arms", "cd", "--chunk-updates", "1",
               "--bootstrap-reps", "50",
               "--steps", str(100 * 192), "--out", str(out)]
        proc = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=600)
        lines = [line for line in proc.stderr.splitlines() if line.startswith("cdjax: ") or "Traceback" in line
                 or "ERROR" in line or "Exception" in line]
        assert proc.returncode == 2 and len(lines) == 1, proc.stderr[-3000:]
        assert "No space left on device" in lines[0] and "resume with" in lines[0]
        subprocess.run(["mount", "-o", "remount,size=64m", str(disk)], check=True)  # room again
        done = max(int(p.name) for p in (out / "checkpoints" / "cd").iterdir() if p.name.isdigit())
        assert f"cd at update {done}" in lines[0]
        proc = subprocess.run([sys.executable, "-m", "cdjax.cli", "sweep", "--out", str(out), "--resume",
                               "--steps", str((done + 1) * 192), "--no-progress"], capture_output=True, text=True,
                              env=env, timeout=600)
        assert proc.returncode == 0, proc.stderr[-3000:]
        rows = io.read_jsonl(out / "metrics.jsonl")
        assert sorted({r["update"] for r in rows if r["seed"] == 0}) == list(range(1, done + 2))
    finally:
        subprocess.run(["umount", str(disk)], capture_output=True)
