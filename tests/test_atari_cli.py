"""The Atari setting through the host side: `cdjax sweep --setting atari --preset cpu-minatar` (a2c and a2c-cd, 2
seeds vmapped) learns MinAtar Breakout; its vmapped runs equal each seed alone, whose update compiles once and skips
a step whose gradient is not finite; a sweep interrupted after its first chunk and resumed is bit-identical to an
uninterrupted run; without ale-py an ALE preset is refused in one sentence naming the extra."""

from __future__ import annotations

import dataclasses
import json
import math

import jax
import numpy as np
import pytest

from cdjax import agents, io
from cdjax.agents.atari import AtariConfig, AtariHParams, make_trainer
from cdjax.agents.atari.config import ale_available
from cdjax.cli import main
from cdjax.runner import Interrupted, restore_arms, resume_spec, run_sweep

from _shared import logged_rows

UPDATES, CHUNK = 320, 40  # 320 updates of 16 envs x 8 steps: 40,960 env steps per run
ARGS = ["sweep", "--setting", "atari", "--preset", "cpu-minatar", "--steps", str(UPDATES * 128), "--chunk-updates",
        str(CHUNK), "--bootstrap-reps", "50", "--no-progress"]


@pytest.fixture(scope="module")
def whole(tmp_path_factory):
    out = tmp_path_factory.mktemp("atari") / "whole"
    main(ARGS + ["--out", str(out)])
    return out


def _returns(rows, arm, seed, first, last):
    values = [r["episode/return"] for r in rows if r["arm"] == arm and r["seed"] == seed and first <= r["update"] <= last]
    return np.nanmean([math.nan if v is None else v for v in values])


def test_the_cli_trains_both_arms_and_breakout_is_learnt(whole):
    run = json.loads((whole / "run.json").read_text())
    assert run["setting"] == "atari" and run["seeds"] == 2 and run["base_config"]["env"] == "breakout"
    arms = {a["name"]: a for a in run["arms"]}
    assert set(arms) == {"a2c", "a2c-cd"} and all(a["num_updates"] == UPDATES for a in arms.values())
    assert arms["a2c-cd"]["hp_labels"] == ["alpha=1.0"] and arms["a2c"]["hp_labels"] == ["default"]
    assert arms["a2c"]["hparams"][0]["alpha"] == 0.0  # not used by the arm: fixed, not gridded
    rows = logged_rows(whole)
    assert len(rows) == 2 * 2 * UPDATES
    cd = [r for r in rows if r["arm"] == "a2c-cd"]
    assert all(np.isfinite(r["loss/consistency"]) and np.isfinite(r["model/latent_mse"]) for r in cd)
    assert all(r["encoder/spread_real"] > 1e-3 for r in cd)  # the grounded encoder has not collapsed
    assert all("loss/consistency" not in r for r in rows if r["arm"] == "a2c")
    # learning: the first 32 updates act with a near-uniform policy (~0.4 points a game, random play); the last 32
    # score several times that in every run of both arms
    for arm in arms:
        for seed in range(2):
            early, late = _returns(rows, arm, seed, 1, 32), _returns(rows, arm, seed, UPDATES - 31, UPDATES)
            assert early < 1.0 and late > 3 * early, (arm, seed, early, late)
    evals = io.read_jsonl(whole / "eval.jsonl")
    assert len(evals) == 4 and all(e["episodes"] == 10 and e["deterministic"] for e in evals)
    a2c_eval = np.mean([e["eval/return"] for e in evals if e["arm"] == "a2c"])
    assert a2c_eval > 3 * np.mean([_returns(rows, "a2c", s, 1, 32) for s in range(2)]), a2c_eval
    assert (whole / "summary.md").exists() and (whole / "plots" / "model.png").exists()


def test_vmapped_runs_equal_each_seed_alone_whose_update_compiles_once_and_skips_a_nan(whole):
    run = json.loads((whole / "run.json").read_text())
    arm = next(a for a in run["arms"] if a["name"] == "a2c")
    config, hp = AtariConfig(**arm["config"]), AtariHParams(**arm["hparams"][0])
    trainer = make_trainer(config)
    rows = [r for r in logged_rows(whole) if r["arm"] == "a2c" and r["update"] <= 3]
    init, update = jax.jit(trainer.init), jax.jit(trainer.update)
    for seed, key in enumerate(jax.random.split(jax.random.key(run["seed"]), run["seeds"])):
        state = init(key, hp)
        for u in range(1, 4):
            state, metrics = update(state, hp)
            row = next(r for r in rows if r["seed"] == seed and r["update"] == u)
            for name in ("loss/total", "loss/policy", "loss/value", "policy/entropy"):
                np.testing.assert_allclose(row[name], metrics[name], rtol=2e-5, atol=1e-6, err_msg=name)
    skipped, metrics = update(state, hp.replace(ent_coef=math.nan))  # a NaN loss: the step is skipped
    assert not np.isfinite(metrics["loss/total"]) and metrics["train/skipped_step"] == 1
    for a, b in zip(jax.tree.leaves(skipped.params), jax.tree.leaves(state.params)):
        np.testing.assert_array_equal(a, b)
    after, _ = update(skipped, hp)
    assert all(np.isfinite(x).all() for x in jax.tree.leaves(after.params))
    assert any((a != b).any() for a, b in zip(jax.tree.leaves(after.params), jax.tree.leaves(state.params)))
    assert update._cache_size() == 1  # one program, whatever the float values


def test_interrupted_and_resumed_is_the_same_run(whole, tmp_path):
    """The a2c-cd arm cut after its first chunk and resumed logs, update for update, what the uninterrupted run
    logged (the programs are the whole run's, from the compilation cache), and its state is the same as that of
    one uninterrupted chunk followed by one more in the same process."""
    spec = dataclasses.replace(resume_spec(whole, progress=False), arms=("a2c-cd",), total_env_steps=2 * CHUNK * 128,
                               final_eval=False, out=tmp_path / "cut")
    with pytest.raises(Interrupted):
        run_sweep(spec, after_chunk=lambda chunks, updates: chunks >= 1)
    run_sweep(resume_spec(tmp_path / "cut", progress=False), resume=True)
    assert logged_rows(tmp_path / "cut") == [r for r in logged_rows(whole) if r["arm"] == "a2c-cd"
                                             and r["update"] <= 2 * CHUNK]
    _, (arm,) = restore_arms(tmp_path / "cut")
    assert arm.updates == 2 * CHUNK and int(np.asarray(arm.state.step)[0]) == 2 * CHUNK


@pytest.mark.skipif(ale_available(), reason="ale-py is installed: the ALE games are offered")
def test_without_the_extra_an_ale_preset_says_what_to_install(tmp_path, capsys):
    with pytest.raises(SystemExit):
        main(["sweep", "--setting", "atari", "--preset", "seaquest", "--out", str(tmp_path / "ale")])
    err = capsys.readouterr().err
    assert 'pip install -e ".[atari]"' in err and err.count("\n") <= 2, err
    assert not (tmp_path / "ale").exists()
    assert {"breakout", "seaquest", "mspacman", "frostbite", "minatar-breakout"} <= set(agents.get("atari").presets)
