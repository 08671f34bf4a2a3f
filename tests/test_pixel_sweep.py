"""The pixel setting through `cdjax sweep` on the real rendered task (MJX reacher at 16x16, pixel-tiny): expert data
rendered in jit, training, checkpoint, resume, evaluation of the imitation policy from pixels, plots, and the
image strips of a restored run. One arm (ltq-cd) keeps it to one set of compiled programs; ltq is the same
code path with the consistency switch off (tests/test_pixel_model.py runs both)."""

from __future__ import annotations

import json

import jax
import numpy as np
import pytest

from cdjax import io
from cdjax.agents.pixel.expert import load_expert, save_expert, untrained_expert
from cdjax.agents.pixel.strips import write_strips
from cdjax.cli import main
from cdjax.runner import restore_arms

from _shared import logged_rows


@pytest.fixture(scope="module")
def expert_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("expert") / "reacher.msgpack"
    expert = untrained_expert("reacher", jax.random.key(3))
    save_expert(path, expert)
    back = load_expert(path)
    assert back.config == expert.config and np.isnan(back.eval_return)
    for a, b in zip(jax.tree.leaves(expert.policy), jax.tree.leaves(back.policy)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    return path


def test_a_pixel_sweep_runs_resumes_evaluates_and_draws(tmp_path, expert_file, capsys):
    out = tmp_path / "px"
    base = ["sweep", "--setting", "pixel", "--preset", "pixel-tiny", "--arms", "ltq-cd", "--expert", str(expert_file),
            "--bootstrap-reps", "50", "--no-progress"]
    main(base + ["--steps", str(3 * 12), "--no-final-eval", "--out", str(out)])  # 3 updates (12 frames each)
    run = json.loads((out / "run.json").read_text())
    assert run["setting"] == "pixel" and run["base_config"]["image_size"] == 16
    assert run["metrics"]["return"] == "heldout/loglik_k"
    main(["sweep", "--out", str(out), "--resume", "--steps", str(6 * 12), "--no-progress"])
    main(["eval", str(out), "--episodes", "2"])  # the imitation policy from pixels (the spec has no final eval)
    main(["plot", str(out), "--bootstrap-reps", "50"])
    rows = logged_rows(out)
    assert sorted({r["update"] for r in rows}) == list(range(1, 7)) and len(rows) == 2 * 6  # 2 seeds x 6 updates
    for r in rows:
        for name in ("heldout/loglik_k", "heldout/loglik_50", "heldout/imitation", "loss/consistency"):
            assert np.isfinite(r[name]), (name, r)
    evals = io.read_jsonl(out / "eval.jsonl")
    assert len(evals) == 2 and all(e["update"] == 6 and e["episodes"] == 2 for e in evals)
    assert all(e["lengths"] == [3, 3] and np.isfinite(e["eval/return"]) for e in evals)  # the time-out
    assert (out / "summary.md").exists() and (out / "plots" / "model.png").exists()

    spec, arms = restore_arms(out)
    arm = arms[0]
    one = jax.tree.map(lambda x: x[0], arm.state)
    assert int(one.step) == 6 and one.data.frames.dtype == np.uint8 and np.asarray(one.data.frames).std() > 1.0  # rendered
    path = write_strips(arm.trainer.inner, one.params, one.heldout, jax.random.key(0), tmp_path / "strip.png")
    import imageio.v3 as iio

    image = iio.imread(path)
    c = arm.plan.config
    assert image.shape == (2 * 3 * (c.image_size + 2), (c.context + c.eval_horizon) * (c.image_size + 2), 3)
