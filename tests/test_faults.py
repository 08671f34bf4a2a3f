"""Faults a demanding user meets, each ending in one sentence with nothing of another run touched (issue 72): plot
outputs that would land on another run, compressed logs read one way by every reader and the resume, writes checked
before training, backend and XLA_FLAGS problems, the library's checks of states and hyper-parameters, and the
processes of one sweep refusing to start apart (cdjax.multihost.join). One tiny point-mass run serves the module."""

import lzma
import os
import pathlib
import shutil
import subprocess
import sys
import textwrap
import time

import jax
import jax.numpy as jnp
import pytest

from _shared import POINT, TINY_ARGS, ended as _ended, fail_in_one_sentence, logged_rows
from conftest import CACHE

from cdjax import io, multihost
from cdjax.cli import main
from cdjax.protocol import ConfigError, Trainer, scanned_train

ARGS = [*TINY_ARGS, "--arms", "model-free", "--eval-episodes", "2", "--bootstrap-reps", "50"]
STEPS, MORE = str(4 * 192), str(6 * 192)  # 4 updates (2 chunks), then a resume to 6
THREE_SEEDS = [a if ARGS[i - 1] != "--seeds" else "3" for i, a in enumerate(ARGS)]  # ARGS but --seeds 3


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    out = tmp_path_factory.mktemp("faults") / "run"
    main(["sweep", *ARGS, "--steps", STEPS, "--out", str(out)])
    return out


def _copy(run, tmp_path, name="copy") -> pathlib.Path:
    return pathlib.Path(shutil.copytree(run, tmp_path / name))


def snapshot(path: pathlib.Path) -> dict:
    return {str(p.relative_to(path)): p.read_bytes() for p in sorted(path.rglob("*")) if p.is_file()}


def test_plot_writes_only_into_its_own_run_or_a_directory_of_no_run(run, tmp_path, capsys):
    other = _copy(run, tmp_path, "other")
    (other / "summary.md").write_text("another run's summary")
    before = snapshot(other)
    line = fail_in_one_sentence(capsys, main, ["plot", str(run), "--out", str(other), "--bootstrap-reps", "50"])
    assert line == (f"cdjax: --out {other} holds another run (its run.json or checkpoints/), whose summary and "
                    "plots these would replace; name that run's own directory or one that holds no run."), line
    assert snapshot(other) == before
    fresh = tmp_path / "fresh"  # a directory of no run, and the run's own, are written
    main(["plot", str(run), "--out", str(fresh), "--bootstrap-reps", "50"])
    assert (fresh / "summary.md").is_file() and not (fresh / "run.json").exists()
    main(["plot", str(run), "--out", str(run), "--bootstrap-reps", "50"])


def test_a_dangling_symbolic_link_is_named(tmp_path, capsys):
    link = tmp_path / "L"
    link.symlink_to(tmp_path / "nowhere")
    for argv in (["sweep", *ARGS, "--out", str(link)], ["sweep", *ARGS, "--out", str(link / "run")],
                 ["plot", str(link)]):
        line = fail_in_one_sentence(capsys, main, argv)
        assert f"{link} is a symbolic link to {tmp_path / 'nowhere'}, which does not exist" in line, line
    assert not (tmp_path / "nowhere").exists()


def test_a_compressed_log_is_read_and_resumed_as_the_plain_one(run, tmp_path, capsys):
    """One rule: every reader sees the same rows, and a resume of a run whose metrics.jsonl was compressed (as kept
    data is) logs the same rows as the resume of the plain one, into the plain file, the copy folded in."""
    plain, packed = _copy(run, tmp_path, "plain"), _copy(run, tmp_path, "packed")
    io.write_packed(packed / "metrics.jsonl", (packed / "metrics.jsonl").read_bytes())
    (packed / "metrics.jsonl").unlink()
    assert io.read_jsonl(packed / "metrics.jsonl") == io.read_jsonl(plain / "metrics.jsonl")
    for out in (plain, packed):
        main(["sweep", "--out", str(out), "--resume", "--steps", MORE])
    assert not (packed / "metrics.jsonl.xz").exists()
    assert logged_rows(packed) == logged_rows(plain) and {r["update"] for r in logged_rows(packed)} == set(range(1, 7))
    assert (packed / "summary.csv").read_text() == (plain / "summary.csv").read_text()


def test_a_damaged_compressed_log_is_refused_by_plot_and_resume_with_what_was_read(run, tmp_path, capsys):
    out = _copy(run, tmp_path)
    data = (out / "metrics.jsonl").read_bytes()
    packed = lzma.compress(data, preset=0)
    (out / "metrics.jsonl").unlink()
    (out / "metrics.jsonl.xz").write_bytes(packed[: len(packed) * 2 // 3])
    rows = io.read_jsonl(out / "metrics.jsonl")
    assert 0 < len(rows) < len(data.splitlines()) and rows.damaged
    before = snapshot(out)
    said = (f"{out / 'metrics.jsonl.xz'} is damaged: it decompresses only in part ({len(rows)} rows read; the last "
            f"row read is model-free update {rows[-1]['update']})")
    for argv, then in ((["plot", str(out)], "nothing was plotted"),
                       (["sweep", "--out", str(out), "--resume", "--steps", MORE], "nothing was changed")):
        line = fail_in_one_sentence(capsys, main, argv)
        assert line.startswith(f"cdjax: {said}") and then in line, line
    assert snapshot(out) == before


def _read_only(path: pathlib.Path):
    """Make `path` unwritable even to root (chattr +i) where that can be done; else chmod, which binds others."""
    if os.geteuid() == 0:
        if shutil.which("chattr") is None or subprocess.run(["chattr", "+i", str(path)]).returncode:
            pytest.skip("root writes anywhere, and chattr cannot make a file immutable here")
        return lambda: subprocess.run(["chattr", "-i", str(path)], check=True)
    mode = path.stat().st_mode
    path.chmod(0o500 if path.is_dir() else 0o400)
    return lambda: path.chmod(mode)


@pytest.mark.parametrize("where", ["checkpoints/model-free", "metrics.jsonl"])
def test_a_write_the_resume_needs_is_checked_before_training(run, tmp_path, capsys, where):
    out = _copy(run, tmp_path)
    target = out / where
    undo = _read_only(target)
    try:
        before = snapshot(out)
        started = time.monotonic()
        line = fail_in_one_sentence(capsys, main, ["sweep", "--out", str(out), "--resume", "--steps", MORE])
        assert str(target) in line and "nothing was started" in line, line
        assert time.monotonic() - started < 30 and snapshot(out) == before
    finally:
        undo()


def test_backend_and_xla_flags_are_named_in_one_sentence(run, tmp_path):
    """In a fresh process (XLA reads its flags, and JAX picks its backend, once per process): each refusal comes
    before JAX's backend starts, naming the variable and its value, with no traceback and no native abort."""
    script = textwrap.dedent(f"""
        import os, sys
        import jax
        from cdjax.cli import main
        for flags in ("--xla_force_host_platform_device_count=0", "--no_such_xla_flag=3", "no-such-flags-file"):
            os.environ["XLA_FLAGS"] = flags
            try:
                main(["eval", {str(run)!r}, "--episodes", "2"])
            except SystemExit as stop:
                print("status", stop.code, file=sys.stderr)
        os.environ["XLA_FLAGS"] = "--xla_force_host_platform_device_count=1"
        os.environ["JAX_PLATFORMS"] = "gpu"
        jax.config.update("jax_platforms", "gpu")
        try:
            main(["eval", {str(run)!r}, "--episodes", "2"])
        except SystemExit as stop:
            print("status", stop.code, file=sys.stderr)
    """)
    env = dict(os.environ, CDJAX_JAX_CACHE=str(CACHE), JAX_PLATFORMS="cpu")
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env, timeout=300,
                          cwd=pathlib.Path(__file__).parent)
    lines = [line for line in done.stderr.splitlines() if line.strip()]
    assert done.returncode == 0 and "Traceback" not in done.stderr, done.stderr
    assert lines[1::2] == ["status 2"] * 4, done.stderr
    count, unknown, file, gpu = lines[0::2]
    assert count.startswith("cdjax: XLA_FLAGS sets --xla_force_host_platform_device_count=0, which leaves the CPU "
                            "backend no device"), count
    assert unknown.startswith("cdjax: XLA_FLAGS='--no_such_xla_flag=3' is refused by XLA (") \
        and "--no_such_xla_flag=3" in unknown[40:], unknown
    assert file.startswith("cdjax: XLA_FLAGS='no-such-flags-file' is refused by XLA (") and "open" in file, file
    assert gpu.startswith("cdjax: JAX_PLATFORMS=gpu names a backend JAX cannot start on this machine (") \
        and "the backends it can start here: cpu" in gpu, gpu


def test_the_protocol_checks_states_and_hyper_parameters_for_every_setting():
    """Trainer and scanned_train (what every setting's make_trainer and make_train go through) refuse a state of
    another Config and a hyper-parameter field that is not one number per run, naming the leaf or field; under jit
    the state is not compared (nothing is added to the program)."""
    from cdjax import HParams, make_train, make_trainer

    small, wide = make_trainer(POINT), make_trainer(POINT.replace(policy_hidden=(8,)))
    hp = HParams()
    state = jax.eval_shape(small.init, jax.random.key(0), hp)  # shapes are all the check reads
    with pytest.raises(ConfigError, match=r"update got a state whose leaf .*\['policy'\].* has shape \(16,\) where "
                                          r"this trainer's Config makes \(8,\)"):
        wide.update(state, hp)
    keys = jax.random.split(jax.random.key(0), 2)
    stacked = jax.tree.map(lambda x: jnp.full((2,), x), hp)
    train = make_train(POINT.replace(num_updates=1))
    with pytest.raises(ConfigError, match=r"HParams field alpha has shape \(2,\) where one run takes one number"):
        jax.eval_shape(jax.vmap(train, in_axes=(0, None)), keys, stacked)
    with pytest.raises(ConfigError, match=r"HParams field gamma has shape \(3,\)"):
        jax.eval_shape(jax.vmap(train), keys, stacked.replace(gamma=jnp.full((2, 3), 0.99)))

    calls = []  # the same checks for any setting's functions, through the protocol alone

    def init(key, hp):
        return {"w": jnp.zeros((3,))}

    def update(state, hp):
        calls.append(1)
        return state, {}

    toy = Trainer(config=None, init=init, update=update, policy=lambda s: s, act=None, eval_env=None)
    with pytest.raises(ConfigError, match=r"leaf \['w'\] has shape \(4,\) where this trainer's Config makes \(3,\)"):
        toy.update({"w": jnp.zeros((4,))}, hp)
    with pytest.raises(ConfigError, match="laid out unlike"):
        toy.update({"v": jnp.zeros((3,))}, hp)
    assert not calls
    toy.update({"w": jnp.zeros((3,))}, hp)
    jax.jit(toy.update)({"w": jnp.zeros((3,))}, hp)
    assert len(calls) == 2 and Trainer(**{**toy.__dict__}).update.__wrapped__ is update  # wrapped once only
    with pytest.raises(ConfigError, match="HParams field lr_policy"):
        scanned_train(init, update, 2)(jax.random.key(0), hp.replace(lr_policy=jnp.ones(2)))


def _port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _process(argv, process: int, port: int, count: int = 2) -> subprocess.Popen:
    env = dict(os.environ, CDJAX_JAX_CACHE=str(CACHE), JAX_PLATFORMS="cpu",
               XLA_FLAGS="--xla_force_host_platform_device_count=1")
    return subprocess.Popen([sys.executable, "-m", "cdjax.cli", *argv, "--distributed", "--coordinator",
                             f"127.0.0.1:{port}", "--num-processes", str(count), "--process-id", str(process)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)


def _sentence(err: str) -> str:
    return [line for line in err.splitlines() if line.strip()][-1]


def test_processes_of_one_sweep_refuse_to_start_apart(tmp_path):
    """Before JAX starts, with no training: different --seeds refused by both processes with one sentence (exit 2),
    both given --process-id 0 refused by both, and a process 0 whose peer never comes ends after --join-timeout
    with exit 69, having said what it waits for. Nothing is written."""
    out = tmp_path / "run"
    started = time.monotonic()
    port = _port()
    seeds = [_process(["sweep", *ARGS, "--steps", STEPS, "--out", str(out), "--join-timeout", "60"], 0, port),
             _process(["sweep", *THREE_SEEDS, "--steps", STEPS, "--out", str(out), "--join-timeout", "60"], 1, port)]
    port = _port()
    twice = [_process(["eval", str(out), "--join-timeout", "60"], 0, port)]
    time.sleep(0.5)  # the first process 0 holds the port; the second joins it as a client
    twice.append(_process(["eval", str(out), "--join-timeout", "60"], 0, port))
    alone = [_process(["sweep", *ARGS, "--steps", STEPS, "--out", str(out), "--join-timeout", "3"], 0, _port())]
    (s0, _, e0), (s1, _, e1) = _ended(seeds, 120)
    said = ("cdjax: the processes of this sweep were given different arguments: process 1's --seeds is 3 where "
            "process 0's is 2; every process runs the same command (only --process-id differs), so none was started.")
    assert (s0, s1) == (2, 2) and _sentence(e0) == _sentence(e1) == said, (e0, e1)
    (t0, _, f0), (t1, _, f1) = _ended(twice, 120)
    said = ("cdjax: two processes of this sweep were given --process-id 0; give each process its own number from 0 "
            "to 1; none was started.")
    assert (t0, t1) == (2, 2) and _sentence(f0) == _sentence(f1) == said, (f0, f1)
    [(a, _, g)] = _ended(alone, 120)
    assert a == multihost.PEER_LOST_STATUS and "waiting up to 3 s (--join-timeout) for process(es) 1" in g, g
    assert _sentence(g).startswith("cdjax: Process 0 of 2 stopped: process(es) 1 did not join within 3 s"), g
    assert "Traceback" not in e0 + e1 + f0 + f1 + g and not out.exists()
    assert time.monotonic() - started < 90


def test_a_process_coming_to_a_port_held_by_a_started_sweep_or_another_program_is_refused_alone(tmp_path, capsys,
                                                                                                monkeypatch):
    """The coordinator's port held by JAX's coordination service (a sweep that has started: a duplicate
    --process-id, or a command run twice) or by another program: the process comes as a client, is answered in another
    protocol, and refuses in one sentence, before JAX starts and without touching what holds the port."""
    from jax._src import xla_bridge
    from jax._src.lib import _jax

    monkeypatch.setattr(xla_bridge, "backends_are_initialized", lambda: False)  # JAX has started in pytest's process
    port = _port()
    service = _jax.get_distributed_runtime_service(f"[::]:{port}", 2)  # what process 0 of a started sweep runs

    def joined(process: int, port: int) -> str:
        return fail_in_one_sentence(capsys, main, ["eval", str(tmp_path / "run"), "--distributed", "--coordinator",
                                                   f"127.0.0.1:{port}", "--num-processes", "2", "--process-id",
                                                   str(process), "--join-timeout", "20"])

    try:
        for process in (0, 1):  # process 0 cannot listen on the port either, and comes as a client
            started = time.monotonic()
            line = joined(process, port)
            assert line == (f"cdjax: the coordinator's port 127.0.0.1:{port} answers, but not as process 0 of a cdjax "
                            "sweep waiting for its processes: a sweep given this --coordinator has already started "
                            f"(JAX's service holds the port, and --process-id {process} of it is taken), or another "
                            "program holds the port; give every process of this sweep a free port; nothing was "
                            "started."), line
            assert time.monotonic() - started < 10
    finally:
        service.shutdown()
    import socket
    import threading

    other = socket.create_server(("127.0.0.1", 0))  # another program: answers anything with a line of its own

    def answer():
        conn, _ = other.accept()
        with conn:
            conn.recv(4096)
            conn.sendall(b"HTTP/1.1 400 Bad Request\r\n\r\n")

    threading.Thread(target=answer, daemon=True).start()
    with other:
        assert "answers, but not as process 0 of a cdjax sweep" in joined(1, other.getsockname()[1])
