"""The chunked training loop: resume reproduces the uninterrupted run, interrupts keep logs and
checkpoints, a corrupt latest checkpoint is skipped (and kept, moved aside), arms x hp grid x seeds equal each run
alone."""

import dataclasses
import json
import pathlib

import jax
import numpy as np
import pytest

from cdjax import HParams, io, make_train
from cdjax.runner import Interrupted, SweepSpec, TimeLimit, plan_arms, prepare, restore_arms, resume_spec, run_sweep

from _shared import POINT, logged_rows

CHUNK, UPDATES = 2, 6
SPEC = SweepSpec(out="unset", config=POINT, arms=("mbmf", "cd"), grid={"alpha": (0.0, 1.0)}, seeds=2, seed=7,
                 total_env_steps=UPDATES * POINT.env_steps_per_update, chunk_updates=CHUNK, final_eval=False,
                 progress=False)


def _rows(run_dir) -> list[dict]:
    return logged_rows(run_dir)


def _write_record(spec) -> None:
    """What a sweep writes first: run.json (nothing compiled)."""
    spec, plans, record = prepare(spec, resume=False)
    rd = io.RunDir(pathlib.Path(spec.out))
    rd.create()
    rd.write(record)


def _states(run_dir):
    _, arms = restore_arms(run_dir)
    return {arm.name: (arm.updates, arm.state) for arm in arms}


def _assert_same_states(a, b):
    assert a.keys() == b.keys()
    for name in a:
        assert a[name][0] == b[name][0], name
        for x, y in zip(jax.tree.leaves(a[name][1]), jax.tree.leaves(b[name][1])):
            if jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key):
                x, y = jax.random.key_data(x), jax.random.key_data(y)
            np.testing.assert_array_equal(np.asarray(x), np.asarray(y), err_msg=name)


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory):
    out = tmp_path_factory.mktemp("runs") / "whole"
    run_sweep(dataclasses.replace(SPEC, out=out))
    return out


def test_uninterrupted_run_writes_the_run_directory(uninterrupted):
    run = json.loads((uninterrupted / "run.json").read_text())
    assert run["version"] == 2 and run["seeds"] == 2 and run["seed"] == 7 and run["chunk_updates"] == CHUNK
    assert run["setting"] == "obs" and run["metrics"]["return"] == "episode/return"
    assert (run["eval_every"], run["eval_episodes"], run["final_eval"]) == (0, 10, False)  # the whole spec
    assert run["total_env_steps"] == UPDATES * POINT.env_steps_per_update
    assert [a["name"] for a in run["arms"]] == ["mbmf", "cd"]
    mbmf, cd = run["arms"]
    assert mbmf["hp_labels"] == ["default"] and mbmf["hparams"][0]["alpha"] == 0.0  # alpha is not mbmf's
    assert cd["hp_labels"] == ["alpha=0.0", "alpha=1.0"] and [h["alpha"] for h in cd["hparams"]] == [0.0, 1.0]
    assert cd["config"]["arm"] == "cd" and cd["config"]["env"] == "point" and cd["config"]["policy_hidden"] == [16]
    rows = _rows(uninterrupted)
    # one row per (arm, hp, seed, update): mbmf 1 x 2 seeds, cd 2 x 2 seeds, 6 updates each
    keys = {(r["arm"], r["hp"], r["seed"], r["update"]) for r in rows}
    assert len(rows) == len(keys) == (1 + 2) * 2 * UPDATES
    last = [r for r in rows if r["update"] == UPDATES]
    assert all(r["env_steps"] == UPDATES * POINT.env_steps_per_update for r in last)
    assert all(isinstance(r["loss/total"], float) for r in rows)
    assert all("loss/consistency" in r for r in rows if r["arm"] == "cd")
    for arm in ("mbmf", "cd"):
        steps = sorted(int(p.name) for p in (uninterrupted / "checkpoints" / arm).iterdir() if p.name.isdigit())
        assert steps == [4, 6]  # max_to_keep=2
    events = list((uninterrupted / "tb").rglob("events.out.tfevents.*"))
    assert {p.parent.relative_to(uninterrupted / "tb").as_posix() for p in events} == {
        "mbmf/default/seed0", "mbmf/default/seed1", "cd/alpha=0.0/seed0", "cd/alpha=0.0/seed1",
        "cd/alpha=1.0/seed0", "cd/alpha=1.0/seed1"}


def _tb_scalars(directory) -> dict[tuple[str, int], float]:
    """{(tag, step): value} of a run's TensorBoard event files (TFRecord: length, its CRC, the event, its CRC)."""
    import struct

    from tensorboardX.proto.event_pb2 import Event

    out = {}
    for path in sorted(pathlib.Path(directory).glob("events.out.tfevents.*")):
        data, at = path.read_bytes(), 0
        while at < len(data):
            (length,) = struct.unpack("<Q", data[at:at + 8])
            event = Event.FromString(data[at + 12:at + 12 + length])
            at += 12 + length + 4
            for value in event.summary.value:
                out[(value.tag, event.step)] = value.simple_value
    return out


def test_tensorboard_holds_every_logged_scalar_of_each_run(uninterrupted):
    """Each run's event file holds every metric of metrics.jsonl at its env steps (float32), nothing more."""
    rows = io.read_jsonl(uninterrupted / "metrics.jsonl")  # wall_s included
    for arm, hp, seed in {(r["arm"], r["hp"], r["seed"]) for r in rows}:
        expected = {(name, r["env_steps"]): value for r in rows if (r["arm"], r["hp"], r["seed"]) == (arm, hp, seed)
                    for name, value in r.items()
                    if name not in ("arm", "hp", "seed", "update", "env_steps") and value is not None}
        got = _tb_scalars(uninterrupted / "tb" / arm / hp / f"seed{seed}")
        assert got.keys() == expected.keys(), (arm, hp, seed)
        for key, value in expected.items():
            assert got[key] == np.float32(value) or (np.isnan(got[key]) and np.isnan(value)), (arm, hp, seed, key)


def test_interrupted_run_keeps_logs_and_checkpoints_and_resume_gives_the_same_numbers(uninterrupted, tmp_path):
    out = tmp_path / "cut"

    def ctrl_c(chunks, updates):
        if chunks == 1:
            raise KeyboardInterrupt

    with pytest.raises(Interrupted) as info:
        run_sweep(dataclasses.replace(SPEC, out=out), after_chunk=ctrl_c)
    assert info.value.updates == {"mbmf": CHUNK, "cd": CHUNK}
    rows = _rows(out)
    assert rows == [r for r in _rows(uninterrupted) if r["update"] <= CHUNK]  # logs of the done chunk, flushed
    for arm in ("mbmf", "cd"):
        assert [int(p.name) for p in (out / "checkpoints" / arm).iterdir() if p.name.isdigit()] == [CHUNK]

    run_sweep(resume_spec(out, progress=False, final_eval=False), resume=True)
    assert _rows(out) == _rows(uninterrupted)  # every metric of every update, bit for bit
    _assert_same_states(_states(out), _states(uninterrupted))


def test_the_timings_record_says_where_each_process_of_a_sweep_spent_its_time(tmp_path, monkeypatch):
    """timings.jsonl: the first process's rows (each arm's programs traced, lowered and compiled; init; log and
    checkpoint writes) kept by the interrupt, then the resume's (restores, the evaluator compiled once for both arms,
    in the background while training ran, apart from the evaluation itself, eval.jsonl and plots), each process
    opening with its plan; `Timings` sums them. The evaluations in eval.jsonl equal, bit for bit, what
    cdjax.evaluate.make_evaluator gives when called directly on the same states and keys."""
    import threading

    import cdjax.evaluate
    import cdjax.runner.arms as arms
    import cdjax.runner.evaluations as evaluations
    from cdjax.runner import EVAL_TAG

    monkeypatch.setattr(arms, "_BUILT", {})  # nothing from this process's cache: every program traced and compiled
    monkeypatch.setattr(arms, "_COMPILED", {})
    monkeypatch.setattr(evaluations, "_EVALUATORS", {})
    monkeypatch.setattr(cdjax.evaluate, "_PROGRAMS", {})
    out = tmp_path / "timed"

    def ctrl_c(chunks, updates):
        if chunks == 1:
            raise KeyboardInterrupt

    with pytest.raises(Interrupted):
        # one alpha: both arms have 2 runs, the evaluation's shapes, and policies that differ only in values
        run_sweep(dataclasses.replace(SPEC, out=out, grid={}, eval_episodes=1, final_eval=True), after_chunk=ctrl_c)
    for thread in threading.enumerate():  # the evaluators it began compiling in the background
        if thread.name == "cdjax-evaluators":
            thread.join()
    first = io.read_timings(out)
    assert first and first.skipped == 0 and first[0]["what"] == "plan" and {r["process"] for r in first} == {0}
    assert all(r["s"] >= 0 and r["start"] >= 0 for r in first)
    assert all(abs((r["at"] - first[0]["at"]) - (r["start"] - first[0]["start"])) < 1e-3 for r in first)
    steps = {(r["arm"], r["what"], r["step"]) for r in first}
    assert {("all", what, "host") for what in ("plan", "build", "memory", "programs", "setup")} <= steps
    assert not {("all", what, "host") for what in ("interpreter", "imports")} & steps  # not the `cdjax` command
    for arm in SPEC.arms:
        for what in ("init", "chunk"):
            assert {(arm, what, "trace"), (arm, what, "lower")} <= steps, (arm, what)
        assert {(arm, "init", "init"), (arm, "metrics.jsonl", "write"), (arm, "checkpoint", "write")} <= steps, arm
        assert (arm, "checkpoint", "restore") not in steps
    compiled = [r["what"] for r in first if r["step"] == "compile"]
    assert "chunk" in compiled and "init" in compiled
    # a compile row ends after the trace and lowering of the same program began
    for arm in SPEC.arms:
        traced = next(r for r in first if (r["arm"], r["what"], r["step"]) == (arm, "chunk", "trace"))
        lowered = next(r for r in first if (r["arm"], r["what"], r["step"]) == (arm, "chunk", "lower"))
        assert traced["start"] + traced["s"] <= lowered["start"] + 1e-6

    # the resume as a new process would: its evaluators made and compiled again (its training programs are cached)
    monkeypatch.setattr(evaluations, "_EVALUATORS", {})
    monkeypatch.setattr(cdjax.evaluate, "_PROGRAMS", {})
    run_sweep(resume_spec(out, progress=False), resume=True)
    rows = io.read_timings(out)
    assert rows[:len(first)] == list(first)  # appended after the first process's rows
    second = rows[len(first):]
    assert second[0]["what"] == "plan"
    steps = {(r["arm"], r["what"], r["step"]) for r in second}
    for arm in SPEC.arms:
        assert {(arm, "checkpoint", "restore"), (arm, "evaluator", "trace"), (arm, "evaluator", "lower"),
                (arm, "evaluator", "wait"), (arm, "evaluation", "evaluate")} <= steps, arm
    assert {("all", "eval.jsonl", "write"), ("all", "plots", "write"), ("all", "evaluation", "host")} <= steps
    # the arms' policies differ only in values: one evaluation program, compiled once, beginning before the
    # evaluation (while training ran)
    compiles = [r for r in second if (r["what"], r["step"]) == ("evaluator", "compile")]
    evaluation = next(r for r in second if (r["arm"], r["what"], r["step"]) == ("all", "evaluation", "host"))
    assert len(compiles) == 1 and len(cdjax.evaluate._PROGRAMS) == 1
    assert min(r["start"] for r in second if r["what"] == "evaluator") < evaluation["start"]

    # the same evaluations from the evaluator called directly on the restored states and keys, compiled alone
    monkeypatch.setattr(cdjax.evaluate, "_PROGRAMS", {})
    kept = {(r["arm"], r["hp"], r["seed"]): r for r in io.read_jsonl(out / "eval.jsonl")}
    _, restored = restore_arms(out)
    for arm in restored:
        evaluator = cdjax.evaluate.make_evaluator(arm.trainer, episodes=1, deterministic=True)
        keys = jax.vmap(lambda k: jax.random.fold_in(k, EVAL_TAG))(arm.keys)
        direct = cdjax.evaluate.eval_records(evaluator(arm.trainer.policy(arm.state), keys, arm.hps), arm=arm.name,
                                             hp_labels=list(arm.plan.labels), seeds=range(SPEC.seeds),
                                             deterministic=True)
        for record in direct:
            saved = kept[(record["arm"], record["hp"], record["seed"])]
            assert saved["returns"] == record["returns"] and saved["lengths"] == record["lengths"], record["arm"]
            assert saved["discounted_returns"] == record["discounted_returns"]
    timings = io.Timings()
    timings.add("a", "chunk", "compile", 0.0, 2.0)
    timings.add("b", "chunk", "compile", 1.0, 2.5)
    assert timings.total("compile") == 3.5 and timings.total("compile", arm="b") == 1.5
    with pytest.raises(ValueError, match="timing step 'nap'"):
        timings.add("a", "chunk", "nap", 0.0)


def test_a_second_sweep_in_the_process_builds_traces_and_compiles_nothing(uninterrupted, tmp_path, monkeypatch):
    """run_sweep of the same spec again in this process (another --out): every trainer, sweep and program comes
    from the process's cache (nothing is built, lowered or compiled), and the run is the same."""
    import cdjax.runner.arms as arms

    def refuse(*args, **kwargs):
        raise AssertionError("built again")

    monkeypatch.setattr(arms, "make_sweep", refuse)
    entries = len(arms._COMPILED)
    out = tmp_path / "again"
    run_sweep(dataclasses.replace(SPEC, out=out))
    assert len(arms._COMPILED) == entries
    assert _rows(out) == _rows(uninterrupted)
    _assert_same_states(_states(out), _states(uninterrupted))


def test_a_sweep_whose_programs_would_not_fit_runs_them_in_program_order_and_says_so(uninterrupted, tmp_path,
                                                                                     monkeypatch, capsys):
    """Where a program scheduled by data flow (cdjax's default on a GPU) would not fit beside the states, the sweep
    compiles it in XLA's program order, says so per arm and program, and trains the same run."""
    from cdjax.runner import budget

    monkeypatch.setattr(budget, "fits", lambda program, room: room is None)  # nothing fits a room
    capsys.readouterr()
    out = tmp_path / "in-order"
    run_sweep(dataclasses.replace(SPEC, out=out))
    said = [line for line in capsys.readouterr().err.splitlines() if "XLA's program order" in line]
    assert sorted(line.split("'s ")[0].split()[-1] for line in said) == sorted(SPEC.arms), said
    assert all(" chunk program runs" in line and "beside the states'" in line for line in said)
    assert _rows(out) == _rows(uninterrupted)
    _assert_same_states(_states(out), _states(uninterrupted))


def test_time_limit_stops_before_the_round_that_would_end_past_it():
    now = [100.0]
    limit = TimeLimit(60, clock=lambda: now[0])
    now[0] += 30  # compilation and the phases (or the rounds of an earlier process): not a round's length
    assert limit(4, {}) is False
    now[0] += 10  # round 1 took 10 s: 40 s used, 50 after another such round
    assert limit(5, {}) is False
    now[0] += 12  # round 2 took 12 s: 52 s used, 64 after another: stop now
    assert limit(6, {}) is True and limit.reached
    late = TimeLimit(5, clock=lambda: now[0])
    now[0] += 6  # the limit is past before the first round
    assert late(0, {}) is True
    with pytest.raises(ValueError):
        TimeLimit(0)


def test_a_time_limit_reached_in_the_last_round_leaves_the_sweep_complete(uninterrupted, tmp_path, capsys):
    """The after_chunk of the last round says stop (a time limit past by then): every update is done, so the sweep
    finishes as complete (its "Trained in" line, no Interrupted asking for a --resume) and equals the whole run."""
    out = tmp_path / "last"
    asked = []
    capsys.readouterr()
    run_sweep(dataclasses.replace(SPEC, out=out),
              after_chunk=lambda chunks, updates: asked.append(chunks) or chunks >= UPDATES // CHUNK)
    assert asked == list(range(UPDATES // CHUNK))  # consulted before each round, not after the last
    assert "Trained in" in capsys.readouterr().err
    _assert_same_states(_states(uninterrupted), _states(out))


@pytest.mark.parametrize("snapshots", [True, False])
def test_the_next_chunk_runs_while_a_round_is_logged_and_checkpointed(uninterrupted, tmp_path, capsys, monkeypatch,
                                                                      snapshots):
    """Each round's logs and checkpoint are written after the next round's chunks are dispatched (with the states
    copied on the devices for the checkpoint, or, without room for that copy, copied to the host first), so the
    devices do not wait for them; the run equals the uninterrupted one. The "Trained in" line says how long the
    devices did wait: with each TensorBoard write sleeping 1 s and each chunk call holding its caller 1 s (as on a
    GPU), the last round's two writes (nothing runs after them) and the host's other work between chunks (a first
    checkpoint's setup on a cold machine took 0.5 s), not the four writes before (a loop that writes before it
    dispatches counts all six: 6 s) nor the calls of the chunks dispatched ahead (a loop that calls them itself
    counts 4 s more: the writes wait for them). Measured 2.1-2.2 s on a 2-core CPU; the bound of 5 s leaves the host
    nearly 3 s for its own work on a loaded machine (with 0.5 s calls and a bound of 4 s it once failed there)."""
    import re
    import time

    from cdjax.runner import arms, loop

    events = []
    write, dispatch = io.TensorBoard.write, loop.Loop.dispatch
    monkeypatch.setattr(io.TensorBoard, "write", lambda self, rows: (
        events.append(("write", max(r["update"] for r in rows))), time.sleep(1.0), write(self, rows))[2])
    monkeypatch.setattr(loop.Loop, "dispatch", lambda self, arm: (
        events.append(("dispatch", arm.updates)), dispatch(self, arm))[1])
    # A GPU's chunk call returns only once its loop has run (XLA launches each iteration's kernels from the calling
    # thread): each call here holds its caller 1 s.
    chunk_program = arms.Arm.chunk_program
    monkeypatch.setattr(arms.Arm, "chunk_program", lambda self: (
        lambda *args, program=chunk_program(self): (time.sleep(1.0), program(*args))[1]))
    made = []
    monkeypatch.setattr(io, "snapshot", lambda *args, make=io.snapshot: made.append(1) or make(*args))
    if not snapshots:  # no room beside the states and programs
        monkeypatch.setattr(loop.budget, "check_programs", lambda states, programs: 0)
    capsys.readouterr()
    out = tmp_path / "overlap"
    run_sweep(dataclasses.replace(SPEC, out=out))
    rounds = UPDATES // CHUNK
    # Per round: two arms dispatched, then (but for the last) the next two, then the two arms' rows written.
    expected = [("dispatch", 0), ("dispatch", 0)]
    for r in range(1, rounds + 1):
        expected += [("dispatch", r * CHUNK)] * 2 * (r < rounds) + [("write", r * CHUNK)] * 2
    assert events == expected
    assert len(made) == (2 * (rounds - 1) if snapshots else 0)  # the last round saves the states themselves
    assert _rows(out) == _rows(uninterrupted)
    _assert_same_states(_states(out), _states(uninterrupted))
    line = next(line for line in capsys.readouterr().err.splitlines() if "Trained in" in line)
    total, between = re.search(r"Trained in ([\d.]+) s .*?; ([\d.]+) s of it between chunks", line).groups()
    assert 2.0 <= float(between) < 5.0 <= 6.0 <= float(total), line


def test_a_snapshot_copies_what_a_save_keeps_in_one_program_and_outlives_the_donated_state():
    """`io.snapshot`: the kept leaves (typed keys too) as fresh device buffers with the same values, the others as
    their shapes, other leaves as they are; all copies made by one compiled program, whatever their shapes (leaf by
    leaf, the first checkpoint of a sweep compiled one per shape: 2.3 s for 200 leaves on a 2-core CPU), into buffers
    of their own, which a chunk that donates the state after the snapshot leaves intact."""
    import jax.numpy as jnp

    from cdjax.io import checkpoints

    arrays = [jnp.arange(float(n * (n % 4 + 1))).reshape(n, n % 4 + 1) + 0.5 for n in range(3, 40)]  # 37 shapes
    tree = {"arrays": arrays, "key": jax.random.split(jax.random.key(7), 3), "dropped": jnp.ones((5, 2)),
            "empty": jnp.zeros((0, 3)), "step": 12}
    keep = {"arrays": [True] * len(arrays), "key": True, "dropped": False, "empty": True, "step": True}
    before = checkpoints._copies._cache_size()
    copy = io.snapshot(tree, keep)
    assert checkpoints._copies._cache_size() == before + 1
    assert copy["step"] == 12 and isinstance(copy["dropped"], jax.ShapeDtypeStruct)
    assert isinstance(copy["empty"], jax.ShapeDtypeStruct) and copy["empty"].shape == (0, 3)
    expected = [np.asarray(x) for x in arrays]
    key_data = np.asarray(jax.random.key_data(tree["key"]))
    assert jax.dtypes.issubdtype(copy["key"].dtype, jax.dtypes.prng_key)
    assert all(got.unsafe_buffer_pointer() != x.unsafe_buffer_pointer() for got, x in zip(copy["arrays"], arrays))
    donate = jax.jit(lambda t: jax.tree.map(lambda x: x * 2, t), donate_argnums=0)
    jax.block_until_ready(donate(tree["arrays"]))  # the next chunk donates the state's own buffers (where XLA can)
    for got, want in zip(copy["arrays"], expected):
        np.testing.assert_array_equal(np.asarray(got), want)
    np.testing.assert_array_equal(np.asarray(jax.random.key_data(copy["key"])), key_data)


def test_evaluations_between_rounds_see_each_round_and_a_stop_after_one_keeps_it(uninterrupted, tmp_path):
    """eval_every 1: an evaluation after every round but the last, of the state that round left (no chunk runs
    ahead of an evaluation); the stop question comes after it, once per round, and a stop then keeps that round's
    evaluation; the training itself equals the uninterrupted run."""
    spec = dataclasses.replace(SPEC, eval_every=1, eval_episodes=2)
    asked = []
    with pytest.raises(Interrupted) as info:
        run_sweep(dataclasses.replace(spec, out=tmp_path / "evals"),
                  after_chunk=lambda chunks, updates: asked.append((chunks, dict(updates))) or chunks >= 2)
    assert asked == [(r, {"mbmf": r * CHUNK, "cd": r * CHUNK}) for r in range(3)]
    assert info.value.updates == {"mbmf": 2 * CHUNK, "cd": 2 * CHUNK}
    evals = io.read_jsonl(tmp_path / "evals" / "eval.jsonl")
    assert sorted({(r["arm"], r["update"]) for r in evals}) == [(a, u) for a in ("cd", "mbmf") for u in (CHUNK, 2 * CHUNK)]
    run_sweep(resume_spec(tmp_path / "evals", progress=False), resume=True)
    evals = io.read_jsonl(tmp_path / "evals" / "eval.jsonl")
    assert sorted({r["update"] for r in evals}) == [CHUNK * r for r in range(1, UPDATES // CHUNK)]  # none after the last
    assert _rows(tmp_path / "evals") == _rows(uninterrupted)
    _assert_same_states(_states(tmp_path / "evals"), _states(uninterrupted))


def test_killed_run_with_corrupt_latest_checkpoint_falls_back_and_still_reproduces(uninterrupted, tmp_path, capsys):
    out = tmp_path / "killed"
    with pytest.raises(Interrupted):
        run_sweep(dataclasses.replace(SPEC, out=out), after_chunk=lambda chunks, updates: chunks >= 2)
    # A process killed while writing chunk 3: its rows partly logged (last line torn), and the
    # latest checkpoint (4 updates) damaged on disk.
    extra = [r for r in io.read_jsonl(uninterrupted / "metrics.jsonl") if r["update"] == 5]
    with (out / "metrics.jsonl").open("a") as f:
        f.write("".join(json.dumps(r) + "\n" for r in extra) + '{"arm": "cd", "hp": "alp')
    damaged = [p for p in (out / "checkpoints" / "cd" / "4" / "state").rglob("*") if p.is_file()]
    assert damaged
    for path in damaged:
        path.write_bytes(b"\x00garbage" * 7)
    kept = {p.relative_to(out / "checkpoints" / "cd" / "4"): p.read_bytes()
            for p in (out / "checkpoints" / "cd" / "4").rglob("*") if p.is_file()}

    capsys.readouterr()
    run_sweep(resume_spec(out, progress=False, final_eval=False), resume=True)
    said = capsys.readouterr().err.splitlines()
    fallback = [line for line in said if "cannot be restored" in line]  # one line each, the library's noise in cdjax.log
    assert len(fallback) == 1 and "checkpoints/cd/4 cannot be restored" in fallback[0], said
    assert "moved aside to 4.unreadable (kept)" in fallback[0], said  # evidence: renamed, never deleted
    aside = out / "checkpoints" / "cd" / "4.unreadable"
    assert {p.relative_to(aside): p.read_bytes() for p in aside.rglob("*") if p.is_file()} == kept
    assert sorted(p.name for p in (out / "checkpoints" / "cd").iterdir()) == ["4", "4.unreadable", "6"]
    assert "Traceback" not in "\n".join(said)
    assert any("(1 of them a torn line" in line for line in said), said  # the torn metrics line is reported
    assert _rows(out) == _rows(uninterrupted)
    _assert_same_states(_states(out), _states(uninterrupted))


def test_arms_and_seeds_vmapped_equal_each_run_alone(uninterrupted):
    """A run of the sweep (arm, hp, seed) equals make_train of the same arm, hp and seed key, run alone."""
    rows = io.read_jsonl(uninterrupted / "metrics.jsonl")
    plans = {p.name: p for p in plan_arms(dataclasses.replace(SPEC, out=uninterrupted))}
    names = ("loss/total", "loss/model_nll", "env/reward_mean", "model/openloop_mse_k")
    for arm, hp_index, seed in (("cd", 1, 1), ("mbmf", 0, 0)):
        plan = plans[arm]
        key = jax.random.split(jax.random.key(SPEC.seed), SPEC.seeds)[seed]
        _, alone = jax.jit(make_train(plan.config))(key, plan.hparams[hp_index])
        mine = sorted((r for r in rows if (r["arm"], r["hp"], r["seed"]) == (arm, plan.labels[hp_index], seed)),
                      key=lambda r: r["update"])
        assert len(mine) == UPDATES
        for name in names + (("loss/consistency",) if arm == "cd" else ()):
            logged = np.array([np.nan if r[name] is None else r[name] for r in mine])  # null = NaN
            np.testing.assert_allclose(logged, np.asarray(alone[name]), rtol=1e-4, atol=1e-6, err_msg=f"{arm} {name}")
    # and the runs in one program really are different runs
    cd_last = {(r["hp"], r["seed"]): r["loss/total"] for r in rows if r["arm"] == "cd" and r["update"] == UPDATES}
    assert len(set(cd_last.values())) == 4


def test_plan_grids_labels_and_refusals(tmp_path):
    spec = SweepSpec(out=tmp_path / "a", config=POINT, arms=("model-free", "mbmf", "cd"),
                     grid={"alpha": (0.0, 0.5), "lr_model": (1e-3, 3e-4), "gamma": (0.99,)}, seeds=3)
    plans = {p.name: p for p in plan_arms(spec)}
    assert plans["model-free"].labels == ("default",)  # alpha and lr_model do not touch model-free
    assert plans["mbmf"].labels == ("lr_model=0.001", "lr_model=0.0003")
    assert plans["cd"].labels == ("alpha=0.0,lr_model=0.001", "alpha=0.0,lr_model=0.0003",
                                  "alpha=0.5,lr_model=0.001", "alpha=0.5,lr_model=0.0003")
    assert all(h.gamma == 0.99 for p in plans.values() for h in p.hparams)
    assert plans["cd"].hparams[2] == HParams(alpha=0.5, lr_model=1e-3, gamma=0.99)
    assert plans["cd"].config.num_updates == plans["mbmf"].config.num_updates == 1_000_000 // 192 + 1

    _write_record(spec)
    with pytest.raises(io.RunDirError, match="already holds a run"):
        prepare(spec, resume=False)
    with pytest.raises(io.RunDirError, match="holds a different run"):
        prepare(dataclasses.replace(spec, seeds=4), resume=True)
    prepare(dataclasses.replace(spec, total_env_steps=2_000_000), resume=True)  # only the length may change
    with pytest.raises(io.RunDirError, match="holds no run"):
        prepare(dataclasses.replace(spec, out=tmp_path / "b"), resume=True)

    # A record of an older cdjax lacks the fields added since (here the newest Config, HParams and sweep fields):
    # it is the same run, and a resume reads them as their defaults; a recorded value that differs is not.
    path = tmp_path / "a" / "run.json"
    record = json.loads(path.read_text())
    older = json.loads(path.read_text())
    for config in [older["base_config"]] + [arm["config"] for arm in older["arms"]]:
        del config["yardstick"], config["stagger_resets"]
    for arm in older["arms"]:
        for hp in arm["hparams"]:
            del hp["lr_distill"]
    del older["bootstrap_reps"]
    path.write_text(json.dumps(older))
    prepare(spec, resume=True)
    older["arms"][1]["config"]["policy_hidden"] = [64]
    path.write_text(json.dumps(older))
    with pytest.raises(io.RunDirError, match="holds a different run"):
        prepare(spec, resume=True)
    path.write_text(json.dumps(record))


@pytest.mark.parametrize("field,kept,other", [("cc_chain_impl", "xla", "pallas"), ("cc_clip", True, False)])
def test_a_record_naming_a_removed_field_reads_as_cdjax_trains_now_and_refuses_another(tmp_path, field, kept, other):
    """A run.json written while Config had a field since removed (cc_chain_impl with the Pallas chain, cc_clip with
    the unclipped term) names it in its base config and each arm's: the value that trained as cdjax
    trains now is read without it (resume and the recorded spec); any other value is refused in one sentence."""
    spec = SweepSpec(out=tmp_path / "a", config=POINT, arms=("mbmf", "cd"), seeds=1)
    _write_record(spec)
    path = tmp_path / "a" / "run.json"
    record = json.loads(path.read_text())
    for config in [record["base_config"]] + [arm["config"] for arm in record["arms"]]:
        config[field] = kept
    path.write_text(json.dumps(record))
    assert resume_spec(tmp_path / "a", progress=False).config.replace(num_updates=POINT.num_updates) == POINT
    prepare(spec, resume=True)
    record["arms"][1]["config"][field] = other
    path.write_text(json.dumps(record))
    for read in (lambda: resume_spec(tmp_path / "a", progress=False), lambda: prepare(spec, resume=True)):
        with pytest.raises(io.RunDirError, match=f"names {field} {other!r}") as info:
            read()
        assert str(info.value).endswith(".") and str(info.value).count(". ") == 0  # one sentence


# ---------------------------------------------------------------------------------------------------
# The Mb-Mf phase inside a sweep: budgets, logs, the same numbers as the library phase, no repeat on resume.

from cdjax.agents.obs import MbMfPhase, make_mbmf_phase, total_env_steps  # noqa: E402

PHASE = MbMfPhase(num_envs=4, random_steps=12, aggregation_iters=1, mpc_steps_per_iter=6, model_epochs=2,
                  model_minibatch=32, mpc_horizon=3, mpc_candidates=8, distill_iters=1, distill_steps_per_iter=4,
                  distill_epochs=2, distill_minibatch=16, value_epochs=1)
PHASE_SPEC = dataclasses.replace(SPEC, arms=("model-free", "mbmf", "cd-k3"), grid={"alpha": (1.0,)}, phase=PHASE,
                                 total_env_steps=4 * POINT.env_steps_per_update)


@pytest.fixture(scope="module")
def phased(tmp_path_factory):
    out = tmp_path_factory.mktemp("runs") / "phased"
    run_sweep(dataclasses.replace(PHASE_SPEC, out=out))
    return out


def test_phase_arms_get_fewer_updates_and_the_same_env_step_budget(phased):
    spu, phase_steps = POINT.env_steps_per_update, total_env_steps(POINT, PHASE)
    assert phase_steps == 4 * (12 + 6 + 4) == 88
    run = json.loads((phased / "run.json").read_text())
    arms = {a["name"]: a for a in run["arms"]}
    assert arms["model-free"]["phase_env_steps"] == 0 and arms["model-free"]["num_updates"] == 4
    for name in ("mbmf", "cd-k3"):
        assert arms[name]["phase_env_steps"] == phase_steps
        assert arms[name]["num_updates"] == round((4 * spu - phase_steps) / spu) == 4  # 192 env steps/update
        assert abs(arms[name]["total_env_steps"] - 4 * spu) <= spu / 2
    assert arms["cd-k3"]["config"]["horizon"] == 3 and arms["cd-k3"]["arm"] == "cd"
    assert arms["mbmf"]["config"]["horizon"] == POINT.horizon
    assert run["phase"]["mpc_candidates"] == 8
    rows = _rows(phased)
    zero = [r for r in rows if r["update"] == 0]
    assert {(r["arm"], r["seed"]) for r in zero} == {("mbmf", 0), ("mbmf", 1), ("cd-k3", 0), ("cd-k3", 1)}
    assert all(r["env_steps"] == phase_steps and "phase/distill/abs_error" in r for r in zero)
    assert all(r["episode/return"] == r["phase/dagger/episode_return"] for r in zero)
    first = {r["arm"]: r["env_steps"] for r in rows if r["update"] == 1}
    assert first == {"model-free": spu, "mbmf": phase_steps + spu, "cd-k3": phase_steps + spu}
    assert len(io.read_jsonl(phased / "phase.jsonl")) == len(zero)


def test_phase_in_the_sweep_equals_the_library_phase_run_alone_and_is_not_repeated_on_resume(phased, tmp_path):
    """Stopped right after the phases: seed 1's state equals make_mbmf_phase run alone; resuming does not
    run the phase again and ends with the numbers of the uninterrupted run."""
    out = tmp_path / "cut-after-phase"
    with pytest.raises(Interrupted) as stopped:
        run_sweep(dataclasses.replace(PHASE_SPEC, out=out), after_chunk=lambda chunks, updates: True)
    assert stopped.value.updates == {"model-free": 0, "mbmf": 0, "cd-k3": 0}
    states = _states(out)
    assert states["mbmf"][0] == 0 and states["cd-k3"][0] == 0
    from cdjax import make_agent

    config = POINT.replace(arm="mbmf", num_updates=4)
    trainer = make_agent(config)
    hp = HParams(alpha=0.0)
    key = jax.random.split(jax.random.key(SPEC.seed), SPEC.seeds)[1]
    alone, info = jax.jit(make_mbmf_phase(config, PHASE, trainer))(jax.jit(trainer.init)(key, hp), hp)
    assert int(info["env_steps"]) == total_env_steps(POINT, PHASE)
    swept = states["mbmf"][1]
    for x, y in zip(jax.tree.leaves(alone.params), jax.tree.leaves(swept.params)):
        np.testing.assert_allclose(np.asarray(y)[1], np.asarray(x), rtol=1e-4, atol=1e-6)
    init = jax.jit(trainer.init)(key, hp)
    moved = [float(np.abs(np.asarray(a) - np.asarray(b)).max())
             for a, b in zip(jax.tree.leaves(init.params["policy"]), jax.tree.leaves(alone.params["policy"]))]
    assert max(moved) > 0  # the phase did train the policy (distillation)
    row = next(r for r in io.read_jsonl(out / "phase.jsonl") if r["seed"] == 1 and r["arm"] == "mbmf")
    assert row["phase/distill/abs_error"] == pytest.approx(float(info["distill/abs_error"]), rel=1e-4)

    phase_rows = len(io.read_jsonl(out / "phase.jsonl"))
    run_sweep(resume_spec(out, progress=False, final_eval=False), resume=True)
    assert len(io.read_jsonl(out / "phase.jsonl")) == phase_rows  # not run again
    assert _rows(out) == _rows(phased)
    _assert_same_states(_states(out), _states(phased))


def test_programs_compiled_in_parallel_threads_give_the_same_run(phased, tmp_path, monkeypatch):
    """The GPU path: the arms' chunk and phase programs compiled by 3 threads at once."""
    import cdjax.runner.arms as arms

    monkeypatch.setattr(arms, "compile_workers", lambda: 3)
    monkeypatch.setattr(arms, "_BUILT", {})  # nothing from this process's cache: every program compiled again
    monkeypatch.setattr(arms, "_COMPILED", {})
    out = tmp_path / "threads"
    run_sweep(dataclasses.replace(PHASE_SPEC, out=out))
    assert _rows(out) == _rows(phased)
    # the three arms act in the same environments: one reset program compiled for all, an init per arm
    compiled = [(r["what"], r["arm"]) for r in io.read_timings(out) if r["step"] == "compile"]
    assert [what for what, _ in compiled].count("reset") == 1
    assert sorted(arm for what, arm in compiled if what == "init") == sorted(PHASE_SPEC.arms)


def test_sweep_init_is_the_trainers_init_and_arms_share_a_reset_only_in_the_same_environments():
    """sweep.init (the shared reset, then init_from) gives init's state bit for bit; a trainer of other
    environments (another num_envs) gets a reset of its own, one of the same environments the same one."""
    from cdjax.agents.obs import make_trainer
    from cdjax.sweep import make_sweep

    trainer = make_trainer(POINT.replace(arm="cd"))
    sweep = make_sweep(trainer)
    keys, hps = sweep.grid(3, 2, [HParams(alpha=0.5)])
    alone = jax.jit(jax.vmap(trainer.init))(keys, hps)
    _assert_same_states({"cd": (0, sweep.init(keys, hps))}, {"cd": (0, alone)})
    assert make_sweep(make_trainer(POINT.replace(arm="mbmf"))).reset is sweep.reset
    other = make_trainer(POINT.replace(arm="cd", num_envs=2 * POINT.num_envs))
    assert other.env_key != trainer.env_key and make_sweep(other).reset is not sweep.reset


def test_memory_check_traces_a_shared_reset_once_and_counts_what_init_gives(monkeypatch):
    """check_memory's state bytes are those of each trainer's whole init, while the env's physics reset is traced
    once for its observation size and once more over the runs (their keys' shapes carry the sweep's mesh, which
    JAX's trace cache tells apart), and every batch of it batches one of those traces: the reset over the arms' runs,
    the evaluation environments' reset and the reset program compile_all lowers after them."""
    import cdjax.runner.arms as arms
    from cdjax import envs, sweep
    from cdjax.agents.obs import SETTING
    from cdjax.envs.point import PointMass
    from cdjax.runner import budget

    monkeypatch.setattr(arms, "_BUILT", {})
    monkeypatch.setattr(arms, "_COMPILED", {})
    monkeypatch.setattr(envs, "_SHARED_ENVS", {})  # a fresh point env whose physics is traced anew
    monkeypatch.setattr(envs, "_PHYSICS", {})
    monkeypatch.setattr(envs, "_OBSERVATION_SIZES", {})  # the size is learnt anew, from this env's reset
    monkeypatch.setattr(sweep, "_RESETS", {})
    traced = []
    reset = PointMass.reset
    monkeypatch.setattr(PointMass, "reset", lambda self, key: traced.append(1) or reset(self, key))
    spec = dataclasses.replace(SPEC, arms=("model-free", "mbmf", "cd-k3"), final_eval=True, eval_episodes=3)
    built = [arms.build(plan, spec, SETTING) for plan in plan_arms(spec)]
    assert len({id(arm.sweep.reset) for arm in built}) == 1
    assert len(traced) == 1  # building traced the env's reset once, for its observation size
    arms.check_memory(built, spec)  # from shapes: the runs' keys are not drawn yet
    assert len(traced) == 2  # the shared reset over the runs and the evaluation environments' reset, one trace
    arm = built[0]
    arm.keys, arm.hps = arm.sweep.grid(spec.seed, spec.seeds, arm.plan.hparams)
    arms._lowered(arm, "reset", arm.sweep.reset.trace, arm.keys, owner=arm.sweep.reset)  # as compile_all does
    assert len(traced) == 2  # the reset program batches it too
    key, hp = jax.random.key(0), HParams()
    for arm in built:
        assert arm.state_bytes == budget.tree_bytes(jax.eval_shape(arm.trainer.init, key, hp)) > 0
        assert (budget.tree_bytes(arms._eval_reset_shape(arm, 3, key))
                == budget.tree_bytes(jax.eval_shape(arm.trainer.eval_env(3).reset, key)) > 0)


class _Counted:
    """An environment whose reset says when it is traced."""

    def __init__(self, env, traced):
        self.env, self.traced = env, traced

    def reset(self, key):
        self.traced.append("eval")
        return self.env.reset(key)


def test_the_code_record_names_a_set_matmul_precision():
    """run.json's code record says when JAX's default matmul precision was set for the run ("highest": a GPU's float32
    products not rounded to TF32), and has no such key at JAX's default."""
    from cdjax.runner import plan

    assert "matmul_precision" not in plan.code_record()
    with jax.default_matmul_precision("highest"):
        assert plan.code_record()["matmul_precision"] == "highest"


def test_encoder_collapse_warning():
    """Said once the trainable GRU's spread stays below the threshold over the chunk's later updates in some run;
    not for a single low update among healthy ones (a noisy sample); never for other encoders. The sweep says it
    again when later chunks find it in more runs (on the GPU a collapse said for 2 of 10 runs at the first chunk
    reached all 10 by the end), and not again for the same or fewer."""
    import types

    from cdjax.consistency import COLLAPSE_SPREAD, collapse_warning
    from cdjax.runner.loop import Loop

    config = POINT.replace(arm="cd")
    low = COLLAPSE_SPREAD / 10
    healthy = {"encoder/spread_real": np.array([[0.3, 0.2, 0.25, 0.2], [0.4, 0.25, 0.3, 0.3]])}
    dips = {"encoder/spread_real": np.array([[0.3, 0.2, 0.25, 0.2], [0.4, 0.5, 0.6, low]])}  # the last update alone
    collapsed = {"encoder/spread_real": np.array([[0.3, 0.2, 0.25, 0.2], [0.01, low, low, low]])}
    assert collapse_warning("cd", config, healthy) is None
    assert collapse_warning("cd", config, dips) is None
    n, text = collapse_warning("cd", config, collapsed)
    assert n == 1 and "in 1 of 2 runs" in text and "1.0e-04" in text and "last 2 updates" in text
    assert "frozen-gru" in text
    assert collapse_warning("cd", config.replace(encoder="frozen-gru"), collapsed) is None
    assert collapse_warning("mbmf", POINT.replace(arm="mbmf"), {}) is None

    both = {"encoder/spread_real": np.array([[0.01, low, low, low], [0.01, low, low, low]])}
    said = []
    loop = types.SimpleNamespace(setting=types.SimpleNamespace(watch=collapse_warning), say=said.append)
    arm = types.SimpleNamespace(name="cd", plan=types.SimpleNamespace(config=config), warned=0)
    for chunk in (healthy, collapsed, collapsed, both, collapsed, both):
        Loop._say_watch(loop, arm, chunk)
    assert [("in 1 of 2" in t, "in 2 of 2" in t) for t in said] == [(True, False), (False, True)]
    assert arm.warned == 2


def _built(tmp_path, episode_length: int, **spec):
    """(arms, spec) of a one-arm point-mass sweep with evaluation episodes of `episode_length` physics steps at action
    repeat 2, built as a sweep builds them (nothing compiled)."""
    from cdjax import agents
    from cdjax.runner.arms import build

    config = dataclasses.replace(POINT, episode_length=episode_length, action_repeat=2)
    spec, plans, _ = prepare(SweepSpec(out=str(tmp_path / "run"), config=config, arms=("cd",), seeds=1,
                                       total_env_steps=2 * config.env_steps_per_update, progress=False, **spec),
                             resume=False)
    return [build(plan, spec, agents.get("obs")) for plan in plans], spec


def test_evaluation_episodes_past_the_limit_are_refused_and_a_resume_is_warned(tmp_path):
    """The limit counts agent steps (physics steps / action repeat): one past it is refused in one sentence naming the
    option and the way out, at it passes; a sweep that does not evaluate is not refused; a resume (whose options
    cannot change) is told and goes on."""
    from cdjax import ConfigError
    from cdjax.evaluate import MAX_EVAL_EPISODE_STEPS as LIMIT
    from cdjax.runner.evaluations import check_evaluation

    said = []
    arms, spec = _built(tmp_path, 2 * LIMIT + 2)  # LIMIT + 1 agent steps
    with pytest.raises(ConfigError) as info:
        check_evaluation(arms, spec, resume=False, say=said.append)
    message = str(info.value)
    assert f"up to {LIMIT + 1:,} agent steps (--episode-length {2 * LIMIT + 2:,})" in message, message
    assert "give a shorter --episode-length, or --no-final-eval" in message and message.endswith(".")
    check_evaluation(arms, spec, resume=True, say=said.append)
    assert len(said) == 1 and said[0].startswith(f"Warning: arm cd's evaluation episodes last up to {LIMIT + 1:,}")
    check_evaluation(*_built(tmp_path, 2 * LIMIT), resume=False, say=said.append)
    check_evaluation(*_built(tmp_path, 2 * LIMIT + 2, final_eval=False), resume=False, say=said.append)
    with pytest.raises(ConfigError, match="--no-final-eval"):
        check_evaluation(*_built(tmp_path, 2 * LIMIT + 2, final_eval=False, eval_every=1), resume=False, say=said.append)
    assert len(said) == 1


def test_an_evaluator_that_failed_to_compile_beside_training_is_compiled_again_for_the_evaluation(uninterrupted,
                                                                                                 tmp_path, monkeypatch):
    """The background compile of the evaluators (beside training, its memory in use) failed: the final evaluation
    compiles them again and evaluates every run, as a sweep whose evaluators compiled in time. (The training programs
    are the `uninterrupted` sweep's, from this process's cache.)"""
    import cdjax.runner.evaluations as evaluations
    import cdjax.runner.loop as loop

    monkeypatch.setattr(evaluations, "_EVALUATORS", {})
    failed = []

    def failing(arms, episodes, deterministic):  # what the background thread hands over for an out-of-memory compile
        for arm in arms:
            arm.evaluating = evaluations.concurrent.futures.Future()
            arm.evaluating.set_exception(RuntimeError("RESOURCE_EXHAUSTED: out of memory while compiling"))
            failed.append(arm.name)

    monkeypatch.setattr(loop, "compile_evaluators", failing)
    out = tmp_path / "again"
    run_sweep(dataclasses.replace(SPEC, out=out, eval_episodes=1, final_eval=True))
    assert failed == list(SPEC.arms)
    rows = io.read_jsonl(out / "eval.jsonl")
    assert len(rows) == 2 + 4 and {r["arm"] for r in rows} == set(SPEC.arms)  # mbmf: 2 runs; cd: 2 alphas x 2 seeds
    assert all(r["episodes"] == 1 and r["update"] == UPDATES and len(r["returns"]) == 1 for r in rows)
