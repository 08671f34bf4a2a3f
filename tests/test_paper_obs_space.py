"""experiments.paper_obs_space: `train` runs the preset's arms with the Mb-Mf phase; the report compares arms
at a common env-step budget, rebuilds itself from the kept data, and states verdicts from the intervals."""

import json
import math

import numpy as np
import pytest

from experiments.paper_obs_space import __main__ as cli
from experiments.paper_obs_space import report

# The paper-swimmer preset shrunk to tests/_shared.POINT with test_runner's Mb-Mf phase (2 arms, 4 updates in
# chunks of 2): the same programs as test_runner's phase sweep, so the compilation cache serves the second. Every
# config field the preset sets is set back to POINT's (the preset's tanh activation and gru encoder too: with them
# the programs differ from test_runner's and compile again).
TINY = ["--env", "point", "--num-envs", "16", "--rollout-len", "12", "--horizon", "4", "--num-epochs", "2",
        "--num-minibatches", "2", "--episode-length", "40", "--policy-hidden", "16", "--value-hidden", "16",
        "--model-hidden", "32", "--encoder-dim", "8", "--eval-horizon", "10", "--eval-envs", "4",
        "--cc-windows", "0", "--cc-unroll", "1", "--activation", "swish", "--encoder", "grounded-gru",
        "--arms", "model-free", "cd-k3", "--seeds", "2", "--steps", "768",
        "--chunk-updates", "2", "--phase-num-envs", "4", "--phase-random-steps", "12",
        "--phase-aggregation-iters", "1", "--phase-mpc-steps-per-iter", "6", "--phase-model-epochs", "2",
        "--phase-model-minibatch", "32", "--phase-mpc-horizon", "3", "--phase-mpc-candidates", "8",
        "--phase-distill-iters", "1", "--phase-distill-steps-per-iter", "4", "--phase-distill-epochs", "2",
        "--phase-distill-minibatch", "16", "--phase-value-epochs", "1", "--phase-relabel-chunk", "1024",
        "--eval-episodes", "2", "--bootstrap-reps", "50", "--no-progress"]


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    runs = tmp_path_factory.mktemp("paper")
    assert cli.main(["train", "--task", "swimmer", "--out", str(runs / "swimmer"), *TINY]) == 0
    return runs


def test_train_runs_the_preset_with_the_phase_and_records_the_machine(trained):
    run = json.loads((trained / "swimmer" / "run.json").read_text())
    assert run["command"].startswith("cdjax sweep --preset paper-swimmer")
    assert run["phase"]["mpc_candidates"] == 8 and run["grid"]["gamma"] == [0.995]  # preset value kept
    arms = {a["name"]: a for a in run["arms"]}
    assert arms["model-free"]["num_updates"] == 4 and arms["model-free"]["phase_env_steps"] == 0
    assert arms["cd-k3"]["num_updates"] == 4 and arms["cd-k3"]["phase_env_steps"] == 4 * (12 + 6 + 4)
    assert arms["cd-k3"]["config"]["horizon"] == 3
    machine = json.loads((trained / "swimmer" / "machine.json").read_text())
    assert machine["exit_code"] == 0 and machine["device"].endswith("(cpu)")


def test_report_tables_and_a_rebuild_from_the_kept_data(trained, tmp_path):
    out = tmp_path / "out"
    assert cli.main(["report", "--runs", str(trained), "--out", str(out), "--reps", "200"]) == 0
    text = (out / "RESULTS.md").read_text()
    assert "| swimmer | model-free | 2 | 768 | 0 | 4 |" in text
    assert "| swimmer | cd-k3 | 2 | 856 | 88 | 4 |" in text  # the phase's 88 env steps + 4 x 192
    rows = json.loads((out / "data" / "summary.json").read_text())
    assert {r["arm"] for r in rows} == {"model-free", "cd-k3"}
    for name in ("figures/returns.png", "figures/returns.csv", "figures/all_arms.png", "data/swimmer/metrics.jsonl.gz",
                 "data/swimmer/run.json", "data/swimmer/phase.jsonl", "data/swimmer/eval.jsonl"):
        assert (out / name).exists(), name
    again = tmp_path / "again"  # only the kept data, no run directory
    assert cli.main(["report", "--runs", str(out / "data"), "--out", str(again), "--reps", "200"]) == 0
    assert json.loads((again / "data" / "summary.json").read_text()) == rows


def _synthetic(run_dir, arms, updates, spu=100, phase=0):
    """A run directory by hand: arm -> (level, updates logged); return = level + seed, every update."""
    run_dir.mkdir(parents=True)
    info = {"version": 1, "base_config": {"env": "ant"}, "seeds": 5, "seed": 0, "env_steps_per_update": spu,
            "requested_env_steps": updates * spu, "command": "by hand",
            "arms": [{"name": a, "arm": "cd", "config": {}, "hparams": [{}], "hp_labels": ["default"],
                      "total_env_steps": updates * spu, "phase_env_steps": 0} for a in arms]}
    (run_dir / "run.json").write_text(json.dumps(info))
    with (run_dir / "metrics.jsonl").open("w") as f:
        for arm, (level, logged) in arms.items():
            for s in range(5):
                for u in range(1, logged + 1):
                    f.write(json.dumps({"arm": arm, "hp": "default", "seed": s, "update": u, "env_steps": u * spu,
                                        "episode/return": level * u + s,
                                        "episode/discounted_return": 0.1 * (level * u + s)}) + "\n")


def test_a_stopped_run_is_compared_at_the_env_steps_every_arm_reached(tmp_path):
    _synthetic(tmp_path / "ant", {"mbmf": (1.0, 20), "cd-k20": (2.0, 12)}, updates=20)
    task = report.load_task(tmp_path / "ant", "ant")
    assert not task.complete and task.budget == 1200
    assert task.curves["mbmf"].updates.max() == 12 and task.curves["cd-k20"].updates.max() == 12
    rows = {r["arm"]: r for r in report.arm_rows(task, reps=200)}
    # final = mean of the last 10% (2 points: updates 11, 12) per seed, IQM over 5 seeds = middle three
    assert rows["mbmf"]["final_return"][0] == pytest.approx(np.mean([11.5 + s for s in (1, 2, 3)]))
    assert rows["cd-k20"]["final_return"][0] == pytest.approx(np.mean([23.0 + s for s in (1, 2, 3)]))
    assert rows["mbmf"]["env_steps"] == 1200


def test_verdicts_follow_the_intervals():
    row = lambda arm, iqm, lo, hi: {"arm": arm, "final_return": (iqm, lo, hi)}  # noqa: E731
    assert report.verdict([row("cd-k20", 10, 8, 12), row("mbmf", 5, 3, 7)], "cd-k20", "mbmf").startswith("CD k=20 > Mb-Mf")
    assert report.verdict([row("cd-k20", 4, 3, 5), row("mbmf", 9, 6, 12)], "cd-k20", "mbmf").startswith("CD k=20 < Mb-Mf")
    assert report.verdict([row("cd-k20", 10, 6, 12), row("mbmf", 9, 7, 11)], "cd-k20", "mbmf").startswith("no clear")
    assert report.verdict([row("cd-k20", math.nan, math.nan, math.nan), row("mbmf", 9, 7, 11)], "cd-k20", "mbmf") == "n/a"
    assert report.verdict([row("mbmf", 9, 7, 11)], "cd-k20", "mbmf") == "n/a"
