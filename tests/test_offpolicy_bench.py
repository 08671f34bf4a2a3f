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


def test_the_learning_report_reads_brax_sac_rows_beside_ppo_rows(tmp_path, monkeypatch):
    """brax_sac's rows (its speed rows among them) in benchmarks.learning --report: cdjax's off-policy arm set against
    Brax SAC at their final evaluations (Brax's count its prefill, within 1%), the obs setting against Brax PPO, Brax
    PPO's env steps/s from the training time the harness measures, less its first interval (its compilation)."""
    import json

    from benchmarks import learning_report

    def row(framework, variant, seed, steps, ret, **timing):
        return dict(task="ant", framework=framework, variant=variant, seed=seed, env_steps=steps, eval_return=ret,
                    **timing)

    rows = [row("cdjax", "offpolicy-model-free", s, st, 100.0 + s + st / 1000, train_s=st / 1000, compile_s=5.0)
            for s in range(2) for st in (0, 1000)]
    rows += [row("brax", "brax-sac", s, st, 50.0 + s, sps=400.0, wall_s=1.0) for s in range(2) for st in (0, 1008)]
    rows.append(dict(task="ant", framework="cdjax", case="speed", seeds=10, env_steps_per_s=1e6))
    # Brax PPO, two intervals of 100 env steps: the first 10 s (with its compilation), the second 2 s: 50 steps/s
    rows += [row("brax", "brax-ppo", 0, st, 1.0, train_s=t, eval_s=1.0) for st, t in ((0, 0), (100, 10), (200, 12))]
    (tmp_path / "rows.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    text = learning_report.report([tmp_path], reps=50)
    assert "| ant | brax-sac | 2 | 1,008 |" in text and "| ant | cdjax offpolicy-model-free | 2 | 1,000 |" in text
    assert "cdjax offpolicy-model-free final IQM 101.5 >= Brax SAC's 50.5 at 1,000 env steps (Brax's at 1,008)" in text
    by = {e["learner"]: e for e in learning_report.table(learning_report.load([tmp_path])[0], reps=50)}
    assert by["brax-ppo"]["sps"] == 50.0 and by["brax-sac"]["sps"] == 400.0
    assert by["cdjax offpolicy-model-free"]["sps"] == 2 * 1000 / 1.0  # both seeds of its one run
    assert "training env steps/s 5.00x Brax's" in text
    # the same rows from a run that shared its device with other processes (benchmarks/lanes.sh sets the variable
    # that write_meta records): no speed is read
    from benchmarks import learning

    monkeypatch.setenv(learning.SHARED_ENV, "1")
    learning.Rows(tmp_path).write_meta("brax_sac", ["--tasks", "ant"])
    assert json.loads((tmp_path / "meta.json").read_text())["shared_device"] is True
    shared = learning_report.report([tmp_path], reps=50)
    assert "x Brax's" not in shared and "training env steps/s not compared (other processes shared" in shared
    assert "| ant | brax-sac | 2 | 1,008 | " in shared and "| not read |" in shared
    assert "cdjax offpolicy-model-free final IQM 101.5 >= Brax SAC's 50.5" in shared  # the returns still are


def test_the_report_times_cdjax_to_brax_final_return_from_each_process_launch(tmp_path):
    """Runs timed alone (their meta has the process's launch, no shared device): the report says when cdjax's IQM
    over its seeds, all in one process, first reached Brax's final IQM, against Brax's processes' times to their
    final evaluation (one seed each), for as many seeds one after another and for one."""
    import json

    from benchmarks import learning_report

    def write(d, rows, started):
        d.mkdir()
        (d / "rows.jsonl").write_text("".join(json.dumps(dict(task="ant", **r)) + "\n" for r in rows))
        (d / "meta.json").write_text(json.dumps({"device": "X", "shared_device": False, "process_started_at": started}))

    t0 = 1000.0
    write(tmp_path / "cdjax", [dict(framework="cdjax", variant="offpolicy-model-free", seed=s, env_steps=st,
                                    eval_return=r + s, train_s=1.0, at=t0 + at)
                               for s in range(2)
                               for st, r, at in ((0, 0.0, 10.0), (500, 40.0, 15.0), (1000, 60.0, 20.0))], t0)
    for seed, (start, end) in enumerate(((t0, t0 + 30.0), (t0 + 40.0, t0 + 70.0))):
        write(tmp_path / f"brax{seed}", [dict(framework="brax", variant="brax-sac", seed=seed, env_steps=st,
                                              eval_return=50.0 + seed, sps=10.0, at=at)
                                         for st, at in ((0, start + 5.0), (1008, end))], start)
    dirs = [tmp_path / n for n in ("cdjax", "brax0", "brax1")]
    text = learning_report.report(dirs, reps=50)
    # Brax: 30 s a seed; cdjax's IQM over its 2 seeds (40.5 at 500 steps, 60.5 at 1000) passes 50.5 at 1000: 20 s
    assert ("Brax 30 s a seed to its final evaluation (the mean over its 2 seeds' processes), so 2 seeds one after "
            "another 60 s; cdjax offpolicy-model-free, 2 seeds in one process, 20 s (its IQM over seeds first reached "
            "it at 1,000 env steps): 0.33x Brax's time for 2 seeds, 0.67x Brax's for one.") in text
    meta = json.loads((tmp_path / "brax1" / "meta.json").read_text())
    (tmp_path / "brax1" / "meta.json").write_text(json.dumps({**meta, "shared_device": True}))
    assert "wall-clock from the command" not in learning_report.report(dirs, reps=50)  # a process shared the device


def test_cdjax_set_puts_typed_fields_over_the_config_and_hparams_and_names_the_variant():
    """--cdjax-set: each value takes its field's type, lands in the Config or the HParams it belongs to, and is named
    in the rows' variant; an unknown field or a value of the wrong type is refused."""
    task = brax_sac.TASKS["point"]
    sets = brax_sac.parse_sets(["latent_dim=256", "layer_norm=false", "actor_hidden=32,32", "tau=0.01",
                                "inputs=obs+latent"])
    assert sets == {"latent_dim": 256, "layer_norm": False, "actor_hidden": (32, 32), "tau": 0.01,
                    "inputs": "obs+latent"}
    config = brax_sac.cdjax_config(task, sets=sets)
    assert (config.latent_dim, config.layer_norm, config.actor_hidden, config.inputs) == (256, False, (32, 32),
                                                                                          "obs+latent")
    assert config.critic_hidden == task.hidden  # untouched fields keep the task's
    assert float(brax_sac.cdjax_hparams(task, sets).tau) == 0.01
    assert brax_sac.variant_name("model-free", False, sets) == (
        "offpolicy-model-free+actor_hidden=32,32+inputs=obs+latent+latent_dim=256+layer_norm=False+tau=0.01")
    assert brax_sac.variant_name("model-free") == "offpolicy-model-free"
    for bad in (["nope=1"], ["latent_dim"], ["latent_dim=wide"], ["layer_norm=maybe"]):
        with pytest.raises(SystemExit):
            brax_sac.parse_sets(bad)
