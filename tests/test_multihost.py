"""One sweep, several processes (`cdjax sweep --distributed`, cdjax.multihost): two processes of the tiny point-mass
sweep on this machine (coordinator on 127.0.0.1, one CPU device each), one of them killed, leave a directory that two
processes resume to the numbers of one process on two devices, bit for bit, with process 0 the only writer. What the
processes agree on (a stop, a refusal) is checked with the exchange faked; the options of --distributed refuse in one
sentence."""

import json
import os
import pathlib
import re
import shlex
import signal
import socket
import subprocess
import sys
import threading
import time
import types

import pytest
from _shared import TINY_ARGS, ended as _ended, fail_in_one_sentence, logged_rows
from conftest import CACHE

from cdjax import io, multihost
from cdjax.cli import main
from cdjax.multihost import watch
from cdjax.protocol import ConfigError
from cdjax.runner import loop

# The tiny point-mass sweep (tests/_shared.TINY_ARGS) of the cheapest arm to compile, 4 seeds (2 on each process's
# device), with the final evaluation and plots; 12 updates in all, in chunks of 2.
ARGS = [*TINY_ARGS[:TINY_ARGS.index("--seeds")], "--seeds", "4", *TINY_ARGS[TINY_ARGS.index("--seeds") + 2:],
        "--arms", "model-free", "--eval-episodes", "2", "--bootstrap-reps", "50"]
FINAL = str(12 * 192)
README = pathlib.Path(__file__).resolve().parents[1] / "docs" / "sweeps.md"  # the docs page with the two-process example
KILLS_ITSELF = pathlib.Path(__file__).with_name("_multihost_process.py")
PARTS = pathlib.Path(__file__).with_name("_multihost_parts.py")


def _env(devices: int) -> dict:
    return dict(os.environ, CDJAX_JAX_CACHE=str(CACHE), JAX_PLATFORMS="cpu",
                XLA_FLAGS=f"{os.environ.get('XLA_FLAGS', '')} --xla_force_host_platform_device_count={devices}".strip())


def _port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def distributed(port: int, process: int) -> list[str]:
    """The options that make a `cdjax` command process `process` of two on this machine."""
    return ["--distributed", "--coordinator", f"127.0.0.1:{port}", "--num-processes", "2", "--process-id", str(process)]


def _start(argv: list[str], devices: int = 1, program: list[str] | None = None, **env: str) -> subprocess.Popen:
    program = program or ["-m", "cdjax.cli"]
    return subprocess.Popen([sys.executable, *program, *argv], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, env={**_env(devices), **env})


def _two(argv: list[str], program_of_1: list[str] | None = None) -> list[subprocess.Popen]:
    """`cdjax <argv>` as processes 0 and 1 of one sweep (process 1 run by `program_of_1` when given)."""
    port = _port()
    return [_start([*argv, *distributed(port, 0)]), _start([*argv, *distributed(port, 1)], program=program_of_1)]


def _steps(out: pathlib.Path) -> list[int]:
    return sorted(int(p.name) for p in (out / "checkpoints" / "model-free").iterdir() if p.name.isdigit())


def _last_line(err: str) -> str:
    return [line for line in err.splitlines() if line.strip()][-1]


def test_a_lost_process_leaves_a_run_that_two_processes_resume_to_one_process_numbers(tmp_path):
    """The README's two-process command with process 1 killed; its resume by two processes; the same sweep in one
    process on two CPU devices, uninterrupted (run alongside)."""
    alone = tmp_path / "one-process"
    one = _start(["sweep", *ARGS, "--steps", FINAL, "--out", str(alone)], devices=2)
    out = tmp_path / "run"
    try:
        # process 1 is killed (SIGKILL) after its second round of chunks: process 0 finds it gone at its next exchange
        # and ends with one sentence and exit status 69, the lock released, the logs and newest checkpoint at update 4
        (status, stdout, err), (killed, _, _) = _ended(
            _two(["sweep", *ARGS, "--steps", FINAL, "--out", str(out)], program_of_1=[str(KILLS_ITSELF)]))
        assert killed == -signal.SIGKILL
        assert status == multihost.PEER_LOST_STATUS and "Traceback" not in err and stdout == "", err[-3000:]
        assert _last_line(err) == (
            "cdjax: Process 0 of 2 stopped: another process of the sweep stopped answering (killed, or its host failed: "
            "its connection closed); the previous checkpoints are intact (model-free at update 4); resume with `cdjax "
            f"sweep --out {out} --resume --distributed`.")
        assert _steps(out) == [2, 4]
        assert max(r["update"] for r in io.read_jsonl(out / "metrics.jsonl")) == 4
        with io.RunDir(out).lock():  # released
            pass

        # resumed by two processes, to the end: every row and the final evaluation equal the one-process run's
        procs = _two(["sweep", "--out", str(out), "--resume", "--no-progress", "--heartbeat-timeout", "20"])
        (status0, stdout0, err0), (status1, stdout1, err1) = _ended(procs)
        assert status0 == 0 and status1 == 0, (err0[-3000:], err1[-3000:])
        assert stdout0 == f"Done: {out}\n" and stdout1 == "" and "Traceback" not in err1  # process 0 speaks for both
        # process 1 shows no progress and no sentence, but the line saying what it waits for when it came before
        # process 0 listened (cdjax.multihost.join: every wait is said)
        assert all(re.fullmatch(r"Process 1 of 2: waiting up to \d+ s \(--join-timeout\) for process 0 at [\d.]+:\d+\.",
                                line) for line in err1.splitlines()), err1
        (status, _, err), = _ended([one])
        assert status == 0, err[-3000:]
        assert logged_rows(out) == logged_rows(alone)
        assert logged_rows(out, "eval.jsonl") == logged_rows(alone, "eval.jsonl")
        assert _steps(out) == [10, 12]
        for name in ("summary.md", "summary.csv", "plots/return.png"):
            assert (out / name).stat().st_size > 0, name
        # written by process 0 alone: one TensorBoard file per run for each of the two commands (a resumed run adds
        # one), run.json as the first command wrote it
        for seed in range(4):
            assert len(list((out / "tb" / "model-free" / "default" / f"seed{seed}").glob("events.out.tfevents.*"))) == 2
        command = io.RunDir(out).read()["command"]
        assert command.startswith(f"cdjax sweep {shlex.join([*ARGS, '--steps', FINAL, '--out', str(out)])} "
                                  "--distributed --coordinator 127.0.0.1:"), command
        assert command.endswith(" --num-processes 2 --process-id 0"), command
    finally:
        if one.poll() is None:
            one.kill()


def test_each_process_builds_its_own_environment_model_and_arms_checkpoint_the_same_step_at_once(tmp_path):
    """Two processes (tests/_multihost_parts.py): each holds the MJX model of the environment it built on its own
    device, and two arms' checkpoints of the same step, saved at once, are both complete."""
    port, script = _port(), str(PARTS)
    procs = [subprocess.Popen([sys.executable, script, str(port), str(i), str(tmp_path)], stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True, env=_env(1)) for i in (0, 1)]
    for i, (status, stdout, err) in enumerate(_ended(procs, timeout=300)):
        assert status == 0, err[-3000:]
        said = json.loads(stdout.strip().splitlines()[-1])
        assert said == {"model_processes": [i], "saved": [1, 1]}, (i, said)


def test_the_readme_runs_what_these_tests_run():
    """The docs' two-process example (docs/sweeps.md) is this file's command (another --out and port)."""
    text = README.read_text()
    block = re.search(r"```bash\n(for i in 0 1; do.*?--process-id \$i &\ndone; wait)\n```", text, re.DOTALL)
    assert block, "docs/sweeps.md has no two-process example"
    words = shlex.split(block.group(1).replace("\\\n", " "))
    command = words[words.index("cdjax") + 1:words.index("&")]
    port = int(command[command.index("--coordinator") + 1].split(":")[1])
    out = command[command.index("--out") + 1]
    assert command == ["sweep", *ARGS, "--steps", FINAL, "--out", out, *distributed(port, "$i")]
    assert "XLA_FLAGS=--xla_force_host_platform_device_count=1" in words


@pytest.mark.parametrize("argv, words", [
    (["--coordinator", "127.0.0.1:1234"], "--coordinator goes with --distributed"),
    (["--process-id", "1"], "--process-id goes with --distributed"),
    (["--distributed", "--coordinator", "node0"], "--coordinator must be HOST:PORT"),
    (["--distributed", "--coordinator", "node0:1234", "--num-processes", "2", "--process-id", "2"],
     "--process-id must be from 0 to --num-processes - 1, got 2 of 2"),
    (["--distributed", "--num-processes", "0"], "--num-processes must be at least 1"),
])
def test_distributed_options_refuse_in_one_sentence(capsys, tmp_path, argv, words):
    line = fail_in_one_sentence(capsys, main, ["sweep", *TINY_ARGS, "--out", str(tmp_path / "run"), *argv])
    assert words in line and not (tmp_path / "run").exists()


def test_joining_needs_a_cluster_or_the_coordinator_and_jax_not_started(capsys, tmp_path, monkeypatch):
    """Without SLURM, Open MPI or a TPU, --distributed alone names what is missing; in a process where JAX has
    already run (this one), joining is refused; --video renders on one process."""
    for name in [k for k in os.environ if k.startswith(("SLURM_", "OMPI_", "TPU_", "JAX_COORDINATOR"))]:
        monkeypatch.delenv(name)
    import jax
    from jax._src import xla_bridge

    jax.devices()  # JAX has started here
    line = fail_in_one_sentence(capsys, main, ["sweep", *TINY_ARGS, "--out", str(tmp_path / "run"), "--distributed"])
    assert "JAX has already started in this process" in line
    monkeypatch.setattr(xla_bridge, "backends_are_initialized", lambda: False)
    line = fail_in_one_sentence(capsys, main, ["sweep", *TINY_ARGS, "--out", str(tmp_path / "run"), "--distributed"])
    assert "--distributed could not find the coordinator's address" in line and "--coordinator HOST:PORT" in line
    line = fail_in_one_sentence(capsys, main, ["eval", str(tmp_path / "run"), "--video", "--distributed"])
    assert "--video renders on one process" in line


def test_one_process_exchanges_with_itself():
    """Without --distributed, every function of cdjax.multihost is what one process would do."""
    import jax.numpy as jnp
    import numpy as np

    assert multihost.count() == 1 and multihost.is_writer() and multihost.resume_flags() == ""
    assert multihost.exchange("x") == ["x"] and multihost.from_writer("y") == "y"
    with multihost.together():
        pass
    with pytest.raises(io.RunDirError, match="mine"), multihost.together():
        raise io.RunDirError("mine")
    np.testing.assert_array_equal(multihost.fetch({"a": jnp.arange(3)})["a"], np.arange(3))
    assert not multihost.is_peer_error(RuntimeError("Gloo AllGather failed: Connection reset by peer"))


def test_processes_stop_together_and_refuse_together(monkeypatch):
    """Two processes (the exchange faked: what process 1 says): SIGTERM to process 1 alone stops process 0 after the
    same chunk, as if the signal were its own; process 1's time limit stops both; a refusal of one is raised, with
    its sentence and class, by the other."""
    said = {}
    monkeypatch.setattr(multihost, "count", lambda: 2)
    monkeypatch.setattr(multihost, "exchange", lambda text: [text, said["1"]])

    def process_0(flag_requested=False):
        return types.SimpleNamespace(flag=types.SimpleNamespace(requested=flag_requested, signum=None))

    said["1"] = "0 0"
    me = process_0()
    assert not loop.Loop._agree_stop(me, False) and not me.flag.requested
    assert loop.Loop._agree_stop(me, True)  # its own time limit
    said["1"] = f"0 {int(signal.SIGTERM)}"
    assert loop.Loop._agree_stop(me, False) and me.flag.requested and me.flag.signum == signal.SIGTERM
    said["1"] = "1 0"
    me = process_0()
    assert loop.Loop._agree_stop(me, False) and not me.flag.requested  # the other's time limit: no signal taken

    said["1"] = "CThe other process refused."
    with pytest.raises(ConfigError, match="^The other process refused[.]$"), multihost.together():
        pass
    with pytest.raises(io.RunDirError, match="^mine$"), multihost.together():  # its own first, when both refused
        raise io.RunDirError("mine")
    said["1"] = "Wcannot write x: disk full"
    with pytest.raises(io.WriteError, match="^cannot write x: disk full$"):
        multihost.settle(None)
    said["1"] = ""
    with multihost.together():
        pass


def test_eval_says_where_the_run_stands_when_its_first_collective_finds_a_peer_gone(capsys, tmp_path, monkeypatch):
    """`cdjax eval` in two processes whose first collective (its checks, before any episode) fails because the other
    process is gone: the same sentence as a peer lost later, with what was (not) written, whichever of the watch and
    the collective notices first (the runtime's gloo error here)."""
    import contextlib

    @contextlib.contextmanager
    def peer_gone():  # together() settles what the block met (here: no run in RUN_DIR) in a collective, which fails
        try:
            yield
        except (ConfigError, io.RunDirError):
            pass
        raise multihost.lost(RuntimeError("Gloo AllGather failed: Connection closed by peer [127.0.0.1]:1"))

    monkeypatch.setattr(multihost, "together", peer_gone)
    monkeypatch.setattr(multihost, "LOST", threading.Event())  # lost() sets it: not the process's, for later tests
    run = tmp_path / "run"
    with pytest.raises(SystemExit) as ended:
        main(["eval", str(run)])
    assert ended.value.code == multihost.PEER_LOST_STATUS
    assert capsys.readouterr().err.strip().splitlines()[-1] == (
        "cdjax: Process 0 of 1 stopped: another process of the sweep stopped answering (killed, or its host failed: "
        f"its connection closed); nothing was added to {run / 'eval.jsonl'}.")


def test_the_processes_watch_one_another_over_the_connections_they_joined_on(monkeypatch):
    """cdjax.multihost.watch on socket pairs (this end, the peer's end): a peer whose connection closes without a word,
    or that falls silent while heartbeats go to it, ends this process with the sentence (`end` given here records it);
    a peer that finished (end 0) is let go, one that ended otherwise is given END_GRACE_S; this process's own end
    stands the watch down and tells the peer."""
    said = []

    def watched(silent_s=30.0):
        here, peer = socket.socketpair()
        watch.start({1: here}, 0, 2, silent_s, end=said.append)
        watch.tail(lambda: "; where the run stands.")
        return peer

    def waited(seconds=5.0):
        started = time.monotonic()
        while not said and time.monotonic() - started < seconds:
            time.sleep(0.02)
        return said.pop() if said else None

    lost = "Process 0 of 2 stopped: another process of the sweep stopped answering (killed, or its host failed: "
    watched().close()
    assert waited() == lost + "its connection closed); where the run stands."
    peer = watched(silent_s=0.4)
    assert waited() == lost + "it was silent for 0.4 s, --heartbeat-timeout); where the run stands."
    assert peer.recv(64).startswith(b".\n")  # its heartbeats reached the peer
    peer.close()
    peer = watched()
    peer.sendall(b".\nend 0\n")
    peer.close()
    assert waited(0.5) is None
    watch.ending(0)  # the watch had stood down: nothing waits
    monkeypatch.setattr(watch, "END_GRACE_S", 0.3)
    peer = watched()
    peer.sendall(b"end 2\n")
    peer.close()
    assert waited() == lost + "it ended with exit status 2 and this process did not within 0.3 s); where the run stands."
    peer = watched()
    watch.ending(143)
    assert peer.recv(64).endswith(b"end 143\n")
    peer.close()
    assert waited(0.5) is None


def test_a_process_that_falls_silent_after_jax_started_ends_the_other_with_one_sentence(tmp_path):
    """Process 1 stops itself (SIGSTOP) once it has joined and JAX has started, its connections open: process 0, waiting
    for it in its first exchange, ends after --heartbeat-timeout with exit 69 and one sentence (JAX's runtime, which
    would abort it natively, is given twice as long); process 1, continued, finds process 0 gone and ends alike."""
    port, out = _port(), tmp_path / "none"
    argv = ["eval", str(out), "--heartbeat-timeout", "3"]
    started = time.monotonic()
    procs = [_start([*argv, *distributed(port, 0)]),
             _start([*argv, *distributed(port, 1)], program=[str(KILLS_ITSELF)], CDJAX_TEST_STOP_AFTER_JOIN="1")]
    try:
        [(status, _, err)] = _ended(procs[:1], 120)
        took = time.monotonic() - started
        procs[1].send_signal(signal.SIGCONT)
        [(status1, _, err1)] = _ended(procs[1:], 60)
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
    tail = f"; nothing was added to {out / 'eval.jsonl'}."
    assert status == multihost.PEER_LOST_STATUS and "Traceback" not in err and "Check failure" not in err, err
    assert _last_line(err) == ("cdjax: Process 0 of 2 stopped: another process of the sweep stopped answering (killed, "
                               "or its host failed: it was silent for 3 s, --heartbeat-timeout)" + tail), err
    assert status1 == multihost.PEER_LOST_STATUS and "Traceback" not in err1, err1
    # continued, process 1's watch and its main thread run on together: the sentence says where the main thread was
    # when the watch found the connection closed (the eval command begun, or not yet, just after JAX's start-up)
    not_begun = " after JAX's start-up, before the command began; nothing was written, run the command again."
    assert _last_line(err1) in {"cdjax: Process 1 of 2 stopped: another process of the sweep stopped answering (killed, "
                                "or its host failed: its connection closed)" + end for end in (tail, not_begun)}, err1
    assert took < 90 and not out.exists()
