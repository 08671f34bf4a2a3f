"""The Atari setting through the host side: `cdjax sweep --setting atari --preset cpu-minatar` with both A2C arms,
its run directory, evaluation and plots; a sweep interrupted after its first chunk and resumed is bit-identical
to the uninterrupted one; without ale-py an ALE game is refused in one sentence naming the extra."""

from __future__ import annotations

import dataclasses
import json

import jax
import numpy as np
import pytest

from cdjax import agents, io
from cdjax.agents.atari.config import ale_available
from cdjax.cli import main
from cdjax.runner import Interrupted, restore_arms, resume_spec, run_sweep

from _shared import logged_rows

# cpu-minatar, shrunk: 8 envs x 4 steps, 12 updates in chunks of 4, evaluation episodes of at most 100 steps
ARGS = ["sweep", "--setting", "atari", "--preset", "cpu-minatar", "--num-envs", "8", "--rollout-len", "4",
        "--horizon", "2", "--episode-length", "100", "--steps", str(12 * 8 * 4), "--chunk-updates", "4",
        "--eval-episodes", "3", "--bootstrap-reps", "50", "--no-progress"]


@pytest.fixture(scope="module")
def whole(tmp_path_factory):
    out = tmp_path_factory.mktemp("atari") / "whole"
    main(ARGS + ["--out", str(out)])
    return out


def test_the_cli_runs_both_arms_of_the_atari_setting(whole):
    run = json.loads((whole / "run.json").read_text())
    assert run["setting"] == "atari" and run["seeds"] == 2 and run["base_config"]["env"] == "breakout"
    arms = {a["name"]: a for a in run["arms"]}
    assert set(arms) == {"a2c", "a2c-cd"} and all(a["num_updates"] == 12 for a in arms.values())
    assert arms["a2c-cd"]["hp_labels"] == ["alpha=1.0"] and arms["a2c"]["hp_labels"] == ["default"]
    assert arms["a2c"]["hparams"][0]["alpha"] == 0.0  # not used by the arm: fixed, not gridded
    rows = logged_rows(whole)
    assert len(rows) == 2 * 2 * 12 and {r["update"] for r in rows} == set(range(1, 13))
    cd = [r for r in rows if r["arm"] == "a2c-cd"]
    assert all(np.isfinite(r["loss/consistency"]) and np.isfinite(r["model/latent_mse"]) for r in cd)
    assert all("loss/consistency" not in r for r in rows if r["arm"] == "a2c")
    evals = io.read_jsonl(whole / "eval.jsonl")
    assert len(evals) == 4 and all(e["episodes"] == 3 and e["deterministic"] for e in evals)
    assert all(max(e["lengths"]) <= 100 and all(np.isfinite(e["returns"])) for e in evals)
    assert (whole / "summary.md").exists() and (whole / "plots" / "model.png").exists()


def test_interrupted_and_resumed_is_the_same_run(whole, tmp_path):
    spec = dataclasses.replace(resume_spec(whole, progress=False), out=tmp_path / "cut")
    with pytest.raises(Interrupted):
        run_sweep(spec, after_chunk=lambda chunks, updates: chunks >= 1)
    run_sweep(resume_spec(tmp_path / "cut", progress=False), resume=True)
    assert logged_rows(tmp_path / "cut") == logged_rows(whole)
    assert logged_rows(tmp_path / "cut", "eval.jsonl") == logged_rows(whole, "eval.jsonl")
    for a, b in zip(restore_arms(tmp_path / "cut")[1], restore_arms(whole)[1]):
        for x, y in zip(jax.tree.leaves(a.state), jax.tree.leaves(b.state)):
            x, y = (jax.random.key_data(v) if jax.dtypes.issubdtype(v.dtype, jax.dtypes.prng_key) else v
                    for v in (x, y))
            np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


@pytest.mark.skipif(ale_available(), reason="ale-py is installed: the ALE games are offered")
def test_without_the_extra_an_ale_game_says_what_to_install(tmp_path, capsys):
    with pytest.raises(SystemExit):
        main(["sweep", "--setting", "atari", "--preset", "seaquest", "--out", str(tmp_path / "ale")])
    err = capsys.readouterr().err
    assert 'pip install -e ".[atari]"' in err and err.count("\n") <= 2, err
    assert not (tmp_path / "ale").exists()
    assert {"breakout", "seaquest", "mspacman", "frostbite", "minatar-breakout"} <= set(agents.get("atari").presets)
