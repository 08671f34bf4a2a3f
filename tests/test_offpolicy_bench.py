"""The Brax SAC harness's plumbing on a CPU (benchmarks/brax_sac.py): the stand-in for jax.device_put_replicated, and
both learners on the point mass writing their evaluation rows at the task's env-step counts."""

from __future__ import annotations

import jax
import numpy as np
import pytest

from benchmarks import brax_sac
from cdjax import io


def test_the_stand_in_replicates_a_tree_onto_one_device():
    device = jax.devices()[0]
    out = brax_sac.replicate_on_one({"a": np.ones((2, 3)), "b": 1.5}, [device])
    assert out["a"].shape == (1, 2, 3) and out["b"].shape == (1,) and float(out["b"][0]) == 1.5
    assert all(leaf.devices() == {device} for leaf in jax.tree.leaves(out))
    with pytest.raises(ValueError, match="one device"):
        brax_sac.replicate_on_one({"a": 1.0}, [device, device])


def test_both_learners_run_the_tiny_task(tmp_path):
    assert brax_sac.main(["--tiny", "--out", str(tmp_path)]) == 0
    rows = io.read_jsonl(tmp_path / "rows.jsonl")
    task = brax_sac.TASKS["point"]
    mine = [r for r in rows if r["framework"] == "cdjax"]
    brax = [r for r in rows if r["framework"] == "brax"]
    assert [r["env_steps"] for r in mine] == [i * task.steps_per_eval for i in range(task.evals + 1)]
    assert len(brax) == task.evals + 1 and brax[-1]["env_steps"] >= task.budget - task.num_envs
    assert all(np.isfinite(r["eval_return"]) for r in rows)
    config = brax_sac.cdjax_config(task)  # equal update-to-data ratio and replay on both sides
    assert config.updates_per_step == brax_sac.brax_kwargs(task)["grad_updates_per_step"]
    assert config.buffer_steps * config.num_envs >= task.max_replay and config.learning_starts == task.min_replay
