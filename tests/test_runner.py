"""The chunked training loop: resume reproduces the uninterrupted run, interrupts keep logs and
checkpoints, a corrupt latest checkpoint is skipped, arms x hp grid x seeds equal each run alone."""

import dataclasses
import json
import pathlib

import jax
import numpy as np
import pytest

from cdjax import HParams, io, make_train
from cdjax.runner import Interrupted, SweepSpec, plan_arms, prepare, restore_arms, resume_spec, run_sweep

from _shared import POINT

CHUNK, UPDATES = 2, 6
SPEC = SweepSpec(out="unset", config=POINT, arms=("mbmf", "cd"), grid={"alpha": (0.0, 1.0)}, seeds=2, seed=7,
                 total_env_steps=UPDATES * POINT.env_steps_per_update, chunk_updates=CHUNK, final_eval=False,
                 progress=False)


def _rows(run_dir) -> list[dict]:
    """metrics.jsonl without the wall-clock (the only field that differs between two runs), in a fixed
    order (arms that resume from different updates interleave their chunks differently)."""
    rows = io.read_jsonl(pathlib.Path(run_dir) / "metrics.jsonl")
    rows = [{k: v for k, v in row.items() if k != "wall_s"} for row in rows]
    return sorted(rows, key=lambda r: (r["arm"], r["hp"], r["seed"], r["update"]))


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
    assert run["version"] == 1 and run["seeds"] == 2 and run["seed"] == 7 and run["chunk_updates"] == CHUNK
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


def test_interrupted_run_keeps_logs_and_checkpoints_and_resume_gives_the_same_numbers(uninterrupted, tmp_path):
    out = tmp_path / "cut"

    def ctrl_c(chunks, updates):
        if chunks == 1:
            raise KeyboardInterrupt

    with pytest.raises(Interrupted) as info:
        run_sweep(dataclasses.replace(SPEC, out=out, on_chunk=ctrl_c))
    assert info.value.updates == {"mbmf": CHUNK, "cd": CHUNK}
    rows = _rows(out)
    assert rows == [r for r in _rows(uninterrupted) if r["update"] <= CHUNK]  # logs of the done chunk, flushed
    for arm in ("mbmf", "cd"):
        assert [int(p.name) for p in (out / "checkpoints" / arm).iterdir() if p.name.isdigit()] == [CHUNK]

    run_sweep(resume_spec(out, progress=False, final_eval=False), resume=True)
    assert _rows(out) == _rows(uninterrupted)  # every metric of every update, bit for bit
    _assert_same_states(_states(out), _states(uninterrupted))


def test_killed_run_with_corrupt_latest_checkpoint_falls_back_and_still_reproduces(uninterrupted, tmp_path):
    out = tmp_path / "killed"
    with pytest.raises(Interrupted):
        run_sweep(dataclasses.replace(SPEC, out=out, stop_after_chunks=2))
    # A process killed while writing chunk 3: its rows partly logged (last line torn), and the
    # latest checkpoint (4 updates) damaged on disk.
    extra = [r for r in io.read_jsonl(uninterrupted / "metrics.jsonl") if r["update"] == 5]
    with (out / "metrics.jsonl").open("a") as f:
        f.write("".join(json.dumps(r) + "\n" for r in extra) + '{"arm": "cd", "hp": "alp')
    damaged = [p for p in (out / "checkpoints" / "cd" / "4" / "state").rglob("*") if p.is_file()]
    assert damaged
    for path in damaged:
        path.write_bytes(b"\x00garbage" * 7)

    with pytest.warns(io.CheckpointWarning, match="cannot be restored"):
        run_sweep(resume_spec(out, progress=False, final_eval=False), resume=True)
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

    prepare(spec, resume=False)
    with pytest.raises(io.RunDirError, match="already holds a run"):
        prepare(spec, resume=False)
    with pytest.raises(io.RunDirError, match="holds a different run"):
        prepare(dataclasses.replace(spec, seeds=4), resume=True)
    prepare(dataclasses.replace(spec, total_env_steps=2_000_000), resume=True)  # only the length may change
    with pytest.raises(io.RunDirError, match="holds no run"):
        prepare(dataclasses.replace(spec, out=tmp_path / "b"), resume=True)
