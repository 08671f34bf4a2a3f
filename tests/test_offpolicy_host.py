"""The off-policy setting through the host side: a sweep (two arms, two seeds), evaluation, plots, and a run
interrupted after its first chunk and resumed by `cdjax sweep --resume` that equals the uninterrupted one, replay
buffer and all."""

from __future__ import annotations

import dataclasses
import json

import jax
import numpy as np
import pytest

from cdjax import io
from cdjax.agents.offpolicy import Config
from cdjax.cli import main
from cdjax.runner import Interrupted, SweepSpec, restore_arms, run_sweep

from _shared import logged_rows

CONFIG = Config(env="point", num_envs=4, steps_per_update=2, buffer_steps=32, batch_size=8, learning_starts=16,
                actor_hidden=(16,), critic_hidden=(16,), encoder_hidden=(16,), model_hidden=(16,), latent_dim=8,
                episode_length=20)
SPEC = SweepSpec(out="unset", setting="offpolicy", config=CONFIG, arms=("model-free", "self-pred"), seeds=2, seed=5,
                 total_env_steps=8 * 24, chunk_updates=8, eval_episodes=2, progress=False, bootstrap_reps=50)


@pytest.fixture(scope="module")
def whole(tmp_path_factory):
    out = tmp_path_factory.mktemp("offpolicy") / "whole"
    run_sweep(dataclasses.replace(SPEC, out=out))
    return out


def test_the_sweep_runs_the_offpolicy_arms(whole):
    run = json.loads((whole / "run.json").read_text())
    assert run["setting"] == "offpolicy" and [a["name"] for a in run["arms"]] == ["model-free", "self-pred"]
    assert all(a["num_updates"] == 24 for a in run["arms"])
    rows = logged_rows(whole)
    assert len(rows) == 2 * 2 * 24
    assert all(np.isfinite(r["loss/critic"]) for r in rows if r["update"] > 2)  # learning from the third update
    assert all("loss/self_predictive" in r for r in rows if r["arm"] == "self-pred")
    evals = io.read_jsonl(whole / "eval.jsonl")
    assert len(evals) == 4 and all(e["episodes"] == 2 and np.isfinite(e["eval/return"]) for e in evals)
    assert (whole / "summary.md").exists()


def test_interrupted_and_resumed_by_the_command_line_is_the_same_run(whole, tmp_path):
    out = tmp_path / "cut"
    with pytest.raises(Interrupted):
        run_sweep(dataclasses.replace(SPEC, out=out), after_chunk=lambda chunks, updates: chunks >= 1)
    main(["sweep", "--out", str(out), "--resume", "--no-progress"])
    assert logged_rows(out) == logged_rows(whole)
    assert logged_rows(out, "eval.jsonl") == logged_rows(whole, "eval.jsonl")
    for a, b in zip(restore_arms(out)[1], restore_arms(whole)[1]):
        for x, y in zip(jax.tree.leaves(a.state.buffer), jax.tree.leaves(b.state.buffer)):
            np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
        for x, y in zip(jax.tree.leaves(a.state.params), jax.tree.leaves(b.state.params)):
            np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def test_a_checkpoint_keeps_the_buffer_and_not_the_reset_targets():
    from cdjax.agents.offpolicy import make_trainer

    saved = make_trainer(CONFIG).saved_leaves()
    assert all(jax.tree.leaves(saved.buffer)) and all(jax.tree.leaves(saved.params))
    assert not any(jax.tree.leaves(saved.env_state.first)) and saved.env_state.obs
