"""The Atari setting through the host side: `cdjax sweep --setting atari --preset cpu-minatar --arms a2c` (2 seeds
vmapped) learns MinAtar Breakout; its vmapped runs equal each seed alone, whose update compiles once and skips a step
whose gradient is not finite; an a2c-cd sweep interrupted after its first chunk and resumed is bit-identical to an
uninterrupted one; without ale-py an ALE preset is refused in one sentence naming the extra."""

from __future__ import annotations

import dataclasses
import json
import math

import jax
import numpy as np
import pytest

from cdjax import agents, io, runtime
from cdjax.agents.atari import AtariConfig, AtariHParams, make_trainer
from cdjax.agents.atari.config import ale_available
from cdjax.cli import main
from cdjax.runner import Interrupted, restore_arms, resume_spec, run_sweep

from _shared import OPTIMISED, logged_rows

UPDATES, CHUNK = 320, 40  # 320 updates of 16 envs x 8 steps: 40,960 env steps per run
ARGS = ["sweep", "--setting", "atari", "--preset", "cpu-minatar", "--arms", "a2c", "--steps", str(UPDATES * 128),
        "--chunk-updates", str(CHUNK), "--bootstrap-reps", "50", "--no-progress"]


# The learning sweep runs long enough (320 updates) for executing its programs to cost more than compiling them, so
# they are compiled at XLA's default optimisation level (tests/_shared.OPTIMISED, through $CDJAX_XLA_OPTIONS, which
# reaches only cdjax's programs), not the session's 0; the test comparing its seeds with each seed alone compiles the
# seed's programs with the same options.
OPTIMISED_ENV = " ".join(f"{name}={value}" for name, value in OPTIMISED.items())


@pytest.fixture(scope="module")
def whole(tmp_path_factory):
    out = tmp_path_factory.mktemp("atari") / "whole"
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv(runtime.OPTIONS_ENV, OPTIMISED_ENV)
        main(ARGS + ["--out", str(out)])
    return out


def _returns(rows, arm, seed, first, last):
    values = [r["episode/return"] for r in rows if r["arm"] == arm and r["seed"] == seed and first <= r["update"] <= last]
    return np.nanmean([math.nan if v is None else v for v in values])


def test_the_cli_trains_a2c_and_breakout_is_learnt(whole):
    run = json.loads((whole / "run.json").read_text())
    assert run["setting"] == "atari" and run["seeds"] == 2 and run["base_config"]["env"] == "breakout"
    (arm,) = run["arms"]
    assert arm["name"] == "a2c" and arm["num_updates"] == UPDATES and arm["hp_labels"] == ["default"]
    assert arm["hparams"][0]["alpha"] == 0.0 and arm["hparams"][0]["lr"] == pytest.approx(3e-3)  # unused; the preset's
    rows = logged_rows(whole)
    assert len(rows) == 2 * UPDATES and all("loss/consistency" not in r for r in rows)
    # learning: the first 32 updates act with a near-uniform policy (~0.4 points a game, random play); the last 32
    # score more than 3 times that in both runs, and so does the final evaluation, which samples the policy's actions
    # (the atari setting's evaluation mode)
    early = [_returns(rows, "a2c", seed, 1, 32) for seed in range(2)]
    for seed in range(2):
        late = _returns(rows, "a2c", seed, UPDATES - 31, UPDATES)
        assert early[seed] < 1.0 and late > 3 * early[seed], (seed, early, late)
    evals = io.read_jsonl(whole / "eval.jsonl")
    assert len(evals) == 2 and all(e["episodes"] == 10 and not e["deterministic"] for e in evals)
    assert all(e["eval/return"] > 3 * early[e["seed"]] for e in evals), evals
    assert (whole / "summary.md").exists() and (whole / "plots" / "return.png").exists()


def test_vmapped_runs_equal_each_seed_alone_whose_update_compiles_once_and_skips_a_nan(whole):
    run = json.loads((whole / "run.json").read_text())
    arm = next(a for a in run["arms"] if a["name"] == "a2c")
    config, hp = AtariConfig(**arm["config"]), AtariHParams(**arm["hparams"][0])
    trainer = make_trainer(config)
    rows = [r for r in logged_rows(whole) if r["arm"] == "a2c" and r["update"] <= 3]
    with pytest.MonkeyPatch.context() as patch:  # the options the sweep compiled its programs with
        patch.setenv(runtime.OPTIONS_ENV, OPTIMISED_ENV)
        options = runtime.compiler_options()
    init, update = jax.jit(trainer.init, compiler_options=options), jax.jit(trainer.update, compiler_options=options)
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


def test_an_a2c_cd_sweep_interrupted_and_resumed_is_the_same_run(whole, tmp_path):
    """Two chunks of 4 updates of the a2c-cd arm at cpu-minatar's sizes: straight, and cut after the first chunk then
    resumed (the second and third sweeps take the first's programs from the compilation cache)."""
    spec = dataclasses.replace(resume_spec(whole, progress=False), arms=("a2c-cd",), total_env_steps=8 * 128,
                               chunk_updates=4, final_eval=False)
    run_sweep(dataclasses.replace(spec, out=tmp_path / "straight"))
    with pytest.raises(Interrupted):
        run_sweep(dataclasses.replace(spec, out=tmp_path / "cut"), after_chunk=lambda chunks, updates: chunks >= 1)
    run_sweep(resume_spec(tmp_path / "cut", progress=False), resume=True)
    rows = logged_rows(tmp_path / "cut")
    assert rows == logged_rows(tmp_path / "straight") and len(rows) == 2 * 8
    assert all(np.isfinite(r["loss/consistency"]) and np.isfinite(r["model/latent_mse"]) for r in rows)
    assert all(r["encoder/spread_real"] > 1e-3 for r in rows)  # the grounded encoder has not collapsed
    for a, b in zip(restore_arms(tmp_path / "cut")[1], restore_arms(tmp_path / "straight")[1]):
        assert a.updates == b.updates == 8
        for x, y in zip(jax.tree.leaves(a.state), jax.tree.leaves(b.state)):
            x, y = (jax.random.key_data(v) if jax.dtypes.issubdtype(v.dtype, jax.dtypes.prng_key) else v
                    for v in (x, y))
            np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


@pytest.mark.skipif(ale_available(), reason="ale-py is installed: the ALE games are offered")
def test_without_the_extra_an_ale_preset_says_what_to_install(tmp_path, capsys):
    with pytest.raises(SystemExit):
        main(["sweep", "--setting", "atari", "--preset", "seaquest", "--out", str(tmp_path / "ale")])
    err = capsys.readouterr().err
    assert 'pip install -e ".[atari]"' in err and err.count("\n") <= 2, err
    assert not (tmp_path / "ale").exists()
    assert {"breakout", "seaquest", "mspacman", "frostbite", "minatar-breakout"} <= set(agents.get("atari").presets)
