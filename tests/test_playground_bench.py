"""The Playground parity harness of benchmarks.learning (issue 70): Playground's published Brax PPO configuration
mapped onto both learners, units that resume, and both sides on the tiny pendulum writing rows at equal env steps.
Everything but the resume test needs the `playground` extra and is skipped without it."""

from __future__ import annotations

import importlib.util
import json
import math

import pytest

from benchmarks import learning
from cdjax import io

needs_playground = pytest.mark.skipif(importlib.util.find_spec("mujoco_playground") is None,
                                      reason="the playground extra is not installed")


@needs_playground
@pytest.mark.parametrize("name", learning.PLAYGROUND)
def test_playgrounds_config_is_what_both_learners_get(name):
    from mujoco_playground.config import dm_control_suite_params

    from cdjax.envs.playground import NAMES

    c = dm_control_suite_params.brax_ppo_config(NAMES[name])
    task = learning.playground_task(name)
    kw = task.spec.brax_kwargs()
    for key in ("num_envs", "unroll_length", "batch_size", "num_minibatches", "num_updates_per_batch", "discounting",
                "learning_rate", "entropy_cost", "reward_scaling", "episode_length", "action_repeat",
                "normalize_observations"):
        assert kw[key] == c[key], key
    assert kw["max_grad_norm"] is None and kw["clipping_epsilon"] == 0.3  # Brax's defaults: Playground sets neither
    # Brax's epoch arithmetic: (num_evals - 1) evaluations, each after num_resets_per_eval epochs of
    # ceil(num_timesteps / (evaluations x env steps per update x resets)) updates; the budget is where it ends
    per_update = c.num_envs * c.unroll_length * c.batch_size * c.num_minibatches // c.num_envs * c.action_repeat
    epoch = math.ceil(c.num_timesteps / ((c.num_evals - 1) * per_update * c.num_resets_per_eval))
    assert (task.evals, task.updates_per_eval, task.resets_per_eval) == (
        c.num_evals - 1, epoch * c.num_resets_per_eval, c.num_resets_per_eval)
    assert task.budget == task.evals * task.updates_per_eval * per_update >= c.num_timesteps
    config, hp = learning.cdjax_config(task, "default"), task.spec.hparams()
    assert config.env_steps_per_update == per_update and config.segment_len == c.unroll_length
    assert config.num_envs * config.rollout_len // config.segment_len // config.num_minibatches == c.batch_size
    assert (config.num_epochs, config.episode_length, config.action_repeat) == (
        c.num_updates_per_batch, c.episode_length, c.action_repeat)
    assert (float(hp.gamma), float(hp.lr_policy), float(hp.ent_coef), float(hp.reward_scale)) == pytest.approx(
        (c.discounting, c.learning_rate, c.entropy_cost, c.reward_scaling))
    assert hp.max_grad_norm >= 1e30  # no clipping, as Brax's None


def test_a_unit_skips_finished_seeds_and_reruns_one_stopped_short(tmp_path):
    """Rows.done: seeds with a row at the final env steps are done (the unit skips them); a seed that stopped short
    is not, and its rows move to rows-stopped.jsonl so that its rerun's rows are the only ones of it."""
    rows = learning.Rows(tmp_path)
    for seed, last in ((0, 20), (1, 10)):  # seed 1 stopped after its first evaluation
        for steps in range(0, last + 1, 10):
            rows.add(task="t", framework="brax", variant="brax-ppo", seed=seed, env_steps=steps, eval_return=1.0)
    rows.add(task="t", framework="cdjax", variant="default", seed=1, env_steps=0, eval_return=2.0)
    assert rows.done("t", "brax", "brax-ppo", [0], 20)
    assert io.read_jsonl(rows.path, check=None) and not (tmp_path / "rows-stopped.jsonl").exists()
    assert not rows.done("t", "brax", "brax-ppo", [1], 20)
    stopped = io.read_jsonl(tmp_path / "rows-stopped.jsonl", check=None)
    assert [(r["seed"], r["env_steps"]) for r in stopped] == [(1, 0), (1, 10)]
    kept = io.read_jsonl(rows.path, check=None)
    assert [(r["framework"], r["seed"], r["env_steps"]) for r in kept] == [
        ("brax", 0, 0), ("brax", 0, 10), ("brax", 0, 20), ("cdjax", 1, 0)]
    assert not rows.done("t", "brax", "brax-ppo", [0, 1], 20)  # one of the two is missing: both run again


@needs_playground
def test_tiny_playground_parity_runs_both_sides_at_equal_env_steps(tmp_path, monkeypatch):
    """`--suite playground --tiny`: cdjax's model-free PPO and Brax's PPO (through Playground's
    wrap_for_brax_training, resetting its envs between updates as num_resets_per_eval says) on the pendulum, both
    evaluated at the same env steps; a second unit with the same --out finds every row there and runs nothing."""
    from conftest import CACHE

    out = tmp_path / "pg"
    argv = ["--suite", "playground", "--tiny", "--seeds", "1", "--evals", "1", "--out", str(out),
            "--cache-dir", str(CACHE)]
    assert learning.main(argv) == 0
    rows = io.read_jsonl(out / "rows.jsonl", check=None)
    task = learning.playground_task("dmc-pendulum-swingup", tiny=True)
    expected = [0, task.updates_per_eval * task.spec.env_steps_per_update]
    steps = {}
    for r in rows:
        steps.setdefault((r["framework"], r["seed"]), []).append(r["env_steps"])
        assert r["task"] == "dmc-pendulum-swingup" and math.isfinite(r["eval_return"])
    assert steps == {("cdjax", 0): expected, ("brax", 0): expected}
    brax = [r for r in rows if r["framework"] == "brax"]
    assert brax[0]["train_s"] == 0 < brax[1]["train_s"] and brax[1]["eval_s"] > brax[0]["eval_s"] > 0
    meta = json.loads((out / "meta.json").read_text())
    assert meta["physics_backend"] == {"dmc-pendulum-swingup": "jax"}
    assert meta["tasks"]["dmc-pendulum-swingup"]["resets_per_eval"] == task.resets_per_eval > 0

    def never(*args, **kwargs):
        pytest.fail("a finished run started again")

    monkeypatch.setattr(learning, "run_sweep", never)
    import brax.training.agents.ppo.train as ppo

    monkeypatch.setattr(ppo, "train", never)
    assert learning.main(argv) == 0
    assert io.read_jsonl(out / "rows.jsonl", check=None) == rows
    assert json.loads((out / "meta.json").read_text())["earlier"][0]["command"] == meta["command"]
