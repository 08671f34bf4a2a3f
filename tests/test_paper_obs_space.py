"""experiments.paper_obs_space: a unit runs its sweep(s) with the preset, the phase and a record of the machine; the
report rebuilds RESULTS.md from the kept data, compares arms at a common budget and gives the across-task statistics
(rliable) and the diagnostics of a fake experiment's units."""

import json
import re
import math

import numpy as np
import pytest

from cdjax import plots
from experiments.paper_obs_space import CONFIRM_SEED, UNITS
from experiments.paper_obs_space import __main__ as cli
from experiments.paper_obs_space import report

# The paper-swimmer preset shrunk to tests/_shared.POINT with test_runner's Mb-Mf phase (2 arms, 4 updates in
# chunks of 2): the same programs as test_runner's phase sweep, so the compilation cache serves the second. Every
# config and phase field the preset sets is set back to POINT's and test_runner's (with them the programs differ
# from test_runner's and compile again).
TINY = ["--env", "point", "--num-envs", "16", "--rollout-len", "12", "--horizon", "4", "--num-epochs", "2",
        "--num-minibatches", "2", "--episode-length", "40", "--policy-hidden", "16", "--value-hidden", "16",
        "--model-hidden", "32", "--encoder-dim", "8", "--eval-horizon", "10", "--eval-envs", "4",
        "--cc-windows", "0", "--cc-unroll", "1", "--cc-epochs", "0", "--segment-len", "0", "--stagger-resets", "false",
        "--arms", "model-free", "cd-k3", "--seeds", "2", "--steps", "768",
        "--chunk-updates", "2", "--phase-num-envs", "4", "--phase-random-steps", "12",
        "--phase-aggregation-iters", "1", "--phase-mpc-steps-per-iter", "6", "--phase-model-epochs", "2",
        "--phase-model-minibatch", "32", "--phase-mpc-horizon", "3", "--phase-mpc-candidates", "8",
        "--phase-distill-iters", "1", "--phase-distill-steps-per-iter", "4", "--phase-distill-epochs", "2",
        "--phase-distill-minibatch", "16", "--phase-value-epochs", "1", "--phase-relabel-chunk", "1024",
        "--phase-onpolicy-fraction", "0", "--phase-mpc-reward", "model", "--phase-mpc-elites", "1",
        "--phase-dagger-deterministic", "false", "--phase-handover-steps", "0",
        "--eval-episodes", "2", "--bootstrap-reps", "50"]


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    units = tmp_path_factory.mktemp("units")
    assert cli.main(["run", "swimmer-1", "--out", str(units / "swimmer-1"), *TINY]) == 0
    return units


def test_a_unit_runs_its_part_with_the_preset_and_the_phase_and_records_the_machine(trained):
    part = trained / "swimmer-1" / "mf-mbmf"
    run = json.loads((part / "run.json").read_text())
    assert run["command"].startswith("cdjax sweep --preset paper-swimmer")
    assert run["phase"]["mpc_candidates"] == 8 and run["grid"]["gamma"] == [0.995]  # preset value kept
    arms = {a["name"]: a for a in run["arms"]}
    assert arms["model-free"]["num_updates"] == 4 and arms["cd-k3"]["phase_env_steps"] == 4 * (12 + 6 + 4)
    machine = json.loads((part / "machine.json").read_text())
    assert machine["exit_code"] == 0 and machine["device"].endswith("(cpu)")
    unit = json.loads((trained / "swimmer-1" / "unit.json").read_text())
    assert unit["unit"] == "swimmer-1" and unit["parts"][0]["exit_code"] == 0 and unit["limit_s"] > 0
    assert unit["parts"][0]["command"] == run["command"]  # the whole command: --out and --yardstick too


def test_report_of_the_unit_and_a_rebuild_from_the_kept_data(trained, tmp_path):
    out = tmp_path / "out"
    assert cli.main(["report", "--runs", str(trained), "--out", str(out), "--reps", "100", "--keep"]) == 0
    text = (out / "RESULTS.md").read_text()
    assert "| point | model-free | 2 | 768 |" in text and "| point | cd-k3 | 2 | 856 |" in text  # 88 + 4 x 192
    kept = out / "data" / "swimmer-1" / "mf-mbmf"
    for name in ("metrics.jsonl.xz", "run.json", "phase.jsonl", "eval.jsonl", "machine.json"):
        assert (kept / name).exists(), name
    assert (out / "data" / "swimmer-1" / "unit.json").exists()
    rows = json.loads((out / "data" / "summary.json").read_text())
    again = tmp_path / "again"  # only the kept data, no run directory
    assert cli.main(["report", "--runs", str(out / "data"), "--out", str(again), "--reps", "100"]) == 0
    assert json.loads((again / "data" / "summary.json").read_text()) == rows


# ---------------------------------------------------------------------------------------------------
# A fake experiment: two tasks, the units' arms written by hand.

LEVELS = {"model-free": 1.0, "mbmf": 1.2, "cd-k5": 1.4, "cd-k20-paper": 2.0, "cd-k20": 1.1, "cd-k20-paper-schedule": 1.6,
          "mbmf-value0": 1.3, "mbmf-model-only": 0.9}
ABLATED = {"mbmf-value0", "mbmf-model-only"}  # halfcheetah-5 only


def _arm(name, kind, horizon, hps, cc_epochs=1, steps=2000, phase=100):
    return {"name": name, "arm": kind, "config": {"env": "?", "horizon": horizon, "cc_epochs": cc_epochs, "num_epochs": 4},
            "hparams": hps, "hp_labels": [f"cc_policy={h.get('cc_policy', 0.1)}" for h in hps],
            "total_env_steps": steps, "phase_env_steps": 0 if kind == "model-free" else phase}


def _fake_part(root, task, unit, part, arms, seeds=10, updates=20, spu=100, cut=None, phase=None, base_seed=0):
    """A run directory by hand: return = level x update x (1 + 0.01 seed); every diagnostic logged."""
    d = root / unit / part
    d.mkdir(parents=True)
    info = {"version": 1, "base_config": {"env": task}, "seeds": seeds, "seed": base_seed, "env_steps_per_update": spu,
            "requested_env_steps": updates * spu, "total_env_steps": updates * spu,
            "command": f"cdjax sweep --preset paper-{task} ...", "arms": arms}
    if phase is not None:
        info["phase"] = phase
    for a in arms:
        a["config"]["env"] = task
    (d / "run.json").write_text(json.dumps(info))
    (d / "machine.json").write_text(json.dumps({"device": "FAKE GPU x1 (gpu)", "wall_s": 600.0, "exit_code": 0}))
    (d.parent / "unit.json").write_text(json.dumps({"unit": unit, "task": task, "parts": [{"name": part}]}))
    rows, phase, evals = [], [], []
    for a in arms:
        for hp, label in zip(a["hparams"], a["hp_labels"]):
            key = report.arm_key(a, hp, info.get("phase"))
            level = LEVELS[key]
            for s in range(seeds):
                if a["arm"] != "model-free":
                    row = {"arm": a["name"], "hp": label, "seed": s, "update": 0, "env_steps": 100,
                           "phase/random/reward_mean": -0.3, "phase/mpc/reward_mean_last": 0.2 + 0.01 * s,
                           "phase/dagger/reward_mean_last": 0.1, "phase/labels/self_error": 0.13,
                           "phase/labels/mean_abs": 0.11, "phase/distill/abs_error_mean": 0.05,
                           "phase/distill/abs_error_zero": 0.15, "phase/model/heldout_mse_last": 0.02,
                           "phase/handover/sampled_reward_mean": 0.3, "phase/fresh/sampled_reward_mean": -0.1,
                           "phase/handover/mean_action_reward_mean": 0.5, "phase/fresh/mean_action_reward_mean": 0.0}
                    phase.append(row)
                for u in range(1, (cut or updates) + 1):
                    r = level * u * (1 + 0.01 * s)
                    rows.append({"arm": a["name"], "hp": label, "seed": s, "update": u,
                                 "env_steps": u * spu + (0 if a["arm"] == "model-free" else 0), "wall_s": 1.0 * u,
                                 "episode/return": r, "episode/discounted_return": 0.1 * r, "episode/count": 3,
                                 "env/reward_mean": level * (1 if a["arm"] == "model-free" else 2),
                                 "model/openloop_mse_k": 0.1, "model/openloop_mse_50": 0.5,
                                 "model/yardstick_mse_k": 0.2 / level, "model/yardstick_mse_50": 1.0 / level,
                                 "loss/consistency": 0.05, "encoder/spread_real": 0.5,
                                 "consistency/masked_fraction": 0.1, "grad/consistency/policy": 0.1,
                                 "grad/ppo/policy": 1.0, "grad/consistency/model": 0.01, "grad/model_nll/model": 1.0})
                evals.append({"arm": a["name"], "hp": label, "seed": s, "update": updates, "deterministic": True,
                              "eval/return": level * 10 + s, "eval/discounted_return": level, "episodes": 10})
    for name, data in (("metrics.jsonl", rows), ("phase.jsonl", phase), ("eval.jsonl", evals)):
        (d / name).write_text("".join(json.dumps(r) + "\n" for r in data))
    return d


@pytest.fixture(scope="module")
def fake(tmp_path_factory):
    root = tmp_path_factory.mktemp("fake")
    for task in ("ant", "halfcheetah"):
        _fake_part(root, task, f"{task}-1", "mf-mbmf", [_arm("model-free", "model-free", 20, [{}]),
                                                         _arm("mbmf", "mbmf", 20, [{}])])
        _fake_part(root, task, f"{task}-2", "cd-k20", [_arm("cd-k20", "cd", 20, [{"cc_policy": 1.0, "cc_model": 1.0},
                                                                                  {"cc_policy": 0.1, "cc_model": 1.0}])])
        _fake_part(root, task, f"{task}-3", "cd-k5", [_arm("cd-k5", "cd", 5, [{"cc_policy": 1.0}])])
        _fake_part(root, task, f"{task}-3", "schedule", [_arm("cd-k20", "cd", 20, [{"cc_policy": 0.1}], cc_epochs=0)],
                   seeds=5)
    for part, spec in (("value0", {"value_epochs": 0}), ("model-only", {"value_epochs": 0, "hand_policy": False})):
        _fake_part(root, "halfcheetah", "halfcheetah-5", part, [_arm("mbmf", "mbmf", 20, [{}])], seeds=5, phase=spec)
    return root


def test_a_report_of_cd_arms_alone_says_it_has_no_comparison(fake, tmp_path):
    """A check that re-ran some arms alone (e.g. CD k=20 at another matmul precision) has no pair to compare: the
    report says so in a sentence each, not with a table of n/a or an empty one, and names the tasks it lacks."""
    out = tmp_path / "cd-only"
    assert cli.main(["report", "--runs", str(fake / "halfcheetah-2"), "--out", str(out), "--reps", "50"]) == 0
    text = (out / "RESULTS.md").read_text()
    verdicts = text[text.index("## Verdicts per task"):text.index("## Across tasks")]
    assert "None: no task here has both arms of CD k=20 (paper's weights) vs Mb-Mf;" in verdicts and "|" not in verdicts
    across = text[text.index("## Across tasks"):text.index("## Returns")]
    assert "None: no task here has both arms of any compared pair." in across and "| X | Y |" not in across
    assert "- not in this data: ant" in text and "| halfcheetah | CD k=20 (paper's weights) | 10 |" in text


def test_arm_keys_name_what_the_arms_are():
    assert report.arm_key(_arm("cd-k20", "cd", 20, []), {"cc_policy": 1.0, "cc_model": 1.0}) == "cd-k20-paper"
    assert report.arm_key(_arm("cd-k20", "cd", 20, []), {"cc_policy": 0.1}) == "cd-k20"
    assert report.arm_key(_arm("cd-k20", "cd", 20, [], cc_epochs=0), {"cc_policy": 0.1}) == "cd-k20-paper-schedule"
    assert report.arm_key(_arm("cd-k5", "cd", 5, []), {"cc_policy": 1.0}) == "cd-k5"
    assert report.arm_key(_arm("x", "mbmf", 20, []), {}) == "mbmf"
    assert report.arm_key(_arm("x", "mbmf", 20, []), {}, {"value_epochs": 10, "hand_policy": True}) == "mbmf"
    assert report.arm_key(_arm("x", "mbmf", 20, []), {}, {"value_epochs": 0, "hand_policy": True}) == "mbmf-value0"
    assert report.arm_key(_arm("x", "mbmf", 20, []), {}, {"value_epochs": 0, "hand_policy": False}) == "mbmf-model-only"
    assert report.arm_key(_arm("x", "model-free", 20, []), {}, {"value_epochs": 0}) == "model-free"


def test_fake_units_give_every_table_and_the_across_task_statistics(fake, tmp_path):
    out = tmp_path / "out"
    assert cli.main(["report", "--runs", str(fake), "--out", str(out), "--reps", "50", "--keep"]) == 0
    text = (out / "RESULTS.md").read_text()
    tasks = report.load([fake])
    assert [t.name for t in tasks] == ["ant", "halfcheetah"] and all(t.complete for t in tasks)
    assert set(tasks[0].curves) == set(LEVELS) - ABLATED and set(tasks[1].curves) == set(LEVELS)
    rows = {r["arm"]: r for r in report.arm_rows(tasks[0], 50)}
    # final = the last 10% of 20 updates (19, 20) per seed, IQM over 10 seeds; AUC = the env-step-weighted mean
    middle = np.mean(1 + 0.01 * np.arange(2, 8))  # the IQM of 10 seeds: the mean of the middle six
    assert rows["cd-k20-paper"]["final_return"][0] == pytest.approx(2.0 * 19.5 * middle)
    assert rows["cd-k20-paper"]["auc_return"][0] == pytest.approx(2.0 * 10.5 * middle)
    assert rows["mbmf"]["ratio/policy"][0] == pytest.approx(0.1) and rows["cd-k5"]["ratio/model"][0] == pytest.approx(0.01)
    assert rows["model-free"]["start_reward"][0] == pytest.approx(1.0) and rows["mbmf"]["start_reward"][0] == pytest.approx(2.4)
    assert "CD k=20 (paper's weights) > Mb-Mf" in text
    # across tasks: CD k=20 (paper's weights) beats Mb-Mf in every seed of both tasks
    scores = report.final_scores(tasks)
    imp = {(p["x"], p["y"]): p for p in report.improvement(scores, reps=50)}
    assert imp[("cd-k20-paper", "mbmf")]["p"] == pytest.approx(1.0) and imp[("cd-k20-paper", "mbmf")]["tasks"] == [
        "ant", "halfcheetah"]
    assert imp[("mbmf", "model-free")]["p"] == pytest.approx(1.0)
    per_task = text[text.index("The same per task"):text.index("## Returns")]  # each task's seeds alone
    for task in ("ant", "halfcheetah"):
        assert re.search(rf"\| {task} \| 1 \[1, 1\] \|", per_task), per_task
    agg, profiles = report.aggregate(report.normalised(scores), reps=50)
    best = max(agg, key=lambda a: a["iqm"])
    assert best["arm"] == "cd-k20-paper" and 0.0 <= best["low"] <= best["iqm"] <= best["high"] <= 1.0
    assert set(profiles) == {"model-free", "mbmf", "cd-k5", "cd-k20-paper", "cd-k20"}
    assert "| ant | 0.3 [0.3, 0.3] | -0.1 [-0.1, -0.1] | 0.5 [0.5, 0.5] | 0 [0, 0] | 1 [1, 1] | 2.4 [2.4, 2.4] |" in text
    # the schedule: the paper's (1.6) above the presets' (1.1) in every seed; the hand-over ablation on halfcheetah only
    schedule = text[text.index("Per task, the paper's schedule"):text.index("## Why the Mb-Mf start")]
    assert re.search(r"\| ant \| CD k=20 \(paper's schedule\) > CD k=20 \(cdjax's weights\) \([\d.]+ vs [\d.]+, "
                     r"disjoint\) \| 1 \[1, 1\] \|", schedule)
    assert "| ant, halfcheetah (across) | | 1 [1, 1] |" in schedule  # both tasks' seeds, rliable's stratified bootstrap
    ablation = text[text.index("## Why the Mb-Mf start"):text.index("## Units")]
    assert "| halfcheetah | Mb-Mf, value not fitted | 5 |" in ablation and "| ant |" not in ablation
    assert ablation.index("| halfcheetah | model-free |") < ablation.index("| halfcheetah | Mb-Mf, model only")
    # P(arm > Mb-Mf), P(arm > model-free) over seeds: value not fitted (1.3) above both, model only (0.9) below both
    # (Mb-Mf's 10 seeds reach 1.2 x 1.09: value not fitted's 5 seeds, 1.3 x 1.0-1.04, beat most of them, not all)
    cells = {line.split(" | ")[1]: line.rstrip(" |").split(" | ")[-2:] for line in ablation.splitlines()
             if line.startswith("| halfcheetah |")}
    point = lambda cell: float(cell.split(" [")[0])  # noqa: E731
    assert 0.9 < point(cells["Mb-Mf, value not fitted"][0]) < 1 and cells["Mb-Mf, value not fitted"][1] == "1 [1, 1]"
    assert cells["Mb-Mf, model only (untrained policy)"] == ["0 [0, 0]", "0 [0, 0]"]
    assert cells["Mb-Mf"] == ["n/a", "1 [1, 1]"] and cells["model-free"] == ["0 [0, 0]", "n/a"]
    for needle in ("## Across tasks (rliable)", "P(X > Y)", "## The Mb-Mf phase", "## The consistency schedule",
                   "CD k=20 (paper's schedule)", "open-loop MSE at 50 (yardstick)", "## Units", "FAKE GPU",
                   "figures/profiles.png", "figures/returns.png"):
        assert needle in text, needle
    for name in ("figures/returns.png", "figures/returns.csv", "figures/profiles.png", "figures/profiles.csv",
                 "data/ant-3/schedule/metrics.jsonl.xz", "data/ant-3/unit.json"):
        assert (out / name).exists(), name
    again = tmp_path / "again"  # RESULTS.md again from the kept data alone, by one command
    assert cli.main(["report", "--runs", str(out / "data"), "--out", str(again), "--reps", "50"]) == 0
    assert json.loads((again / "data" / "summary.json").read_text()) == json.loads((out / "data" / "summary.json").read_text())


def test_a_unit_cut_short_is_compared_where_every_arm_got(tmp_path):
    _fake_part(tmp_path, "ant", "ant-1", "mf-mbmf", [_arm("model-free", "model-free", 20, [{}]),
                                                     _arm("mbmf", "mbmf", 20, [{}])])
    _fake_part(tmp_path, "ant", "ant-2", "cd-k20", [_arm("cd-k20", "cd", 20, [{"cc_policy": 0.1}])], cut=12)
    (task,) = report.load([tmp_path])
    assert not task.complete and task.budget == 1200
    assert all(c.updates.max() == 12 for c in task.curves.values())
    assert all(v is None for v in task.evals.values())  # evaluated at each run's end, not at the common budget
    text = report.write_results([task], tmp_path / "out", reps=50).read_text()
    assert "not every arm reached it" in text and "(cut)" in text


def test_an_arm_run_on_other_seeds_is_pooled_and_one_run_again_is_named_and_left_out(tmp_path):
    """The same arm in runs of other base seeds (`--seed`, e.g. a replication on fresh seeds) joins into one arm of
    all their seeds, its seed ids kept apart; a run of it on seeds already found (a unit run again) is left out and
    named; `--arms` keeps only the arms named."""
    two = [_arm("model-free", "model-free", 20, [{}]), _arm("mbmf", "mbmf", 20, [{}])]
    _fake_part(tmp_path, "ant", "ant-1", "mf-mbmf", two)
    _fake_part(tmp_path, "ant", "ant-6", "confirm", [_arm("mbmf", "mbmf", 20, [{}])], seeds=4, base_seed=1)
    _fake_part(tmp_path, "ant", "ant-9", "again", [_arm("mbmf", "mbmf", 20, [{}])], seeds=3)  # base seed 0 again
    (task,) = report.load([tmp_path])
    mbmf = task.curves["mbmf"]
    assert mbmf.metrics["episode/return"].shape == (14, 20) and list(mbmf.seeds) == list(range(14))
    assert task.pooled == {"mbmf": [0, 1]} and len(task.curves["model-free"].seeds) == 10
    assert len(task.evals["mbmf"]["return"]) == 14 and len(task.phase["mbmf"]["random/reward_mean"]) == 14
    assert list(task.evals["mbmf"]["seeds"]) == list(range(14))
    assert len(task.dropped) == 1 and "ant-9" in task.dropped[0]
    text = report.write_results([task], tmp_path / "out", reps=50).read_text()
    assert "Pooled: Mb-Mf holds the seeds of runs of base seeds 0, 1 (14 seeds)" in text and "ant-9/again" in text
    assert "| ant | Mb-Mf | 14 |" in text
    (only,) = report.load([tmp_path], arms=["mbmf"])
    assert set(only.curves) == {"mbmf"} and [r.path.name for r in only.runs] == ["mf-mbmf", "confirm", "again"]
    assert cli.main(["report", "--runs", str(tmp_path), "--arms", "mbmf", "cd-k99", "--out", str(tmp_path / "x")]) == 2
    out = tmp_path / "m"
    assert cli.main(["report", "--runs", str(tmp_path), "--arms", "mbmf", "--out", str(out), "--reps", "50"]) == 0
    head = (out / "RESULTS.md").read_text().split("\n\n")[1]  # where the runs came from: not copied there
    assert f"from the runs under `{tmp_path}` (not copied here" in head and "kept data" not in head


def test_pooled_curves_line_up_on_the_updates_either_run_logged():
    """Runs that logged different updates: the union, NaN and not present where a run did not log."""
    def curves(seeds, updates):
        u = np.array(updates)
        return plots.Curves(arm="a", hp="", arm_type="mbmf", seeds=np.array(seeds), updates=u, env_steps=100.0 * u,
                            present=np.ones((len(seeds), len(u)), bool),
                            metrics={"r": np.tile(u.astype(float), (len(seeds), 1))})

    pooled, offset = plots.pool_curves(curves([0, 1], [1, 2, 4]), curves([0], [2, 3]))
    assert offset == 2 and list(pooled.seeds) == [0, 1, 2] and list(pooled.updates) == [1, 2, 3, 4]
    assert list(pooled.env_steps) == [100.0, 200.0, 300.0, 400.0]
    assert pooled.present.tolist() == [[True, True, False, True]] * 2 + [[False, True, True, False]]
    np.testing.assert_array_equal(pooled.metrics["r"][2], [np.nan, 2.0, 3.0, np.nan])


def test_verdicts_follow_the_intervals():
    row = lambda arm, iqm, lo, hi: {"arm": arm, "final_return": (iqm, lo, hi)}  # noqa: E731
    assert report.verdict([row("cd-k20-paper", 10, 8, 12), row("mbmf", 5, 3, 7)], "cd-k20-paper", "mbmf").startswith(
        "CD k=20 (paper's weights) > Mb-Mf")
    assert report.verdict([row("cd-k20", 4, 3, 5), row("mbmf", 9, 6, 12)], "cd-k20", "mbmf").startswith("CD k=20 (cdjax's weights) <")
    assert report.verdict([row("cd-k20", 10, 6, 12), row("mbmf", 9, 7, 11)], "cd-k20", "mbmf").startswith("no clear")
    assert report.verdict([row("cd-k20", math.nan, math.nan, math.nan), row("mbmf", 9, 7, 11)], "cd-k20", "mbmf") == "n/a"


def test_every_unit_fits_a_lease_by_its_estimate():
    """The plan's units: one task each, >= 10 seeds per arm (the schedule's and the hand-over ablation's >= 5),
    estimated inside the time limit."""
    assert {u.task for u in UNITS.values()} == {"ant", "humanoid", "halfcheetah", "swimmer"}
    for unit in UNITS.values():
        assert unit.estimate()["total"] < cli.UNIT_LIMIT_S * 0.9, unit.name
        for part in unit.parts:
            assert part.seeds >= (5 if part.name in ("schedule", "value0", "model-only") else 10)
    assert cli.main(["list"]) == 0


def test_the_command_refuses_what_it_cannot_take_in_one_sentence(tmp_path, capsys, monkeypatch):
    """`run` of a unit that does not exist or with a --time-limit below 1 second, `train` without --task, `report`
    of a --runs that does not exist or with --reps 0: one sentence naming the option and exit status 2; no sweep
    started, nothing written."""
    monkeypatch.setattr(cli, "sweep", lambda *args: pytest.fail("a sweep started"))
    out = tmp_path / "out"
    for argv, said in (
            (["run", "ant-9"], "argument UNIT: invalid choice: 'ant-9'"),
            (["run", "ant-1", "--time-limit", "-5"], "argument --time-limit: '-5' is not a positive number"),
            (["train", "--unit", "ant-1"], "the following arguments are required: --task"),
            (["report", "--runs", str(tmp_path / "none"), "--out", str(out)], f"--runs {tmp_path / 'none'}: no such"),
            (["report", "--runs", str(tmp_path), "--reps", "0", "--out", str(out)], "argument --reps: '0' is not"),
            (["report", "--runs", str(tmp_path), "--bogus", "--out", str(out)], "`python -m experiments.paper_obs_space "
                                                                               "report --help`")):
        capsys.readouterr()
        assert cli.main([*argv, *(["--out", str(out)] if argv[0] in ("run", "train") else [])]) == 2
        err = capsys.readouterr().err
        assert err.startswith("python -m experiments.paper_obs_space") and err.count("\n") == 1 and said in err, err
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("name", sorted(UNITS))
def test_every_units_sweeps_plan_without_an_error(name):
    """Each part's `cdjax sweep` command line, as `run UNIT` builds it, plans (arms, grid, phase, budget) with
    no ConfigError; nothing is compiled."""
    from cdjax import agents
    from cdjax.cli import build_parser, sweep_spec
    from cdjax.runner.plan import plan_arms

    unit = UNITS[name]
    setting = agents.get("obs")
    for part in unit.parts:
        argv = ["sweep", "--preset", f"paper-{unit.task}", "--out", "unused", *cli.yardstick_option(unit.task, []),
                "--arms", *part.arms, "--seeds", str(part.seeds), "--steps", str(unit.budget.steps), *part.options]
        spec = sweep_spec(build_parser(setting).parse_args(argv), setting)
        plans = plan_arms(spec)
        assert {p.name for p in plans} == set(part.arms)
        # fresh seeds for the confirmation units only: the others pair seed by seed on base seed 0
        assert spec.seed == (CONFIRM_SEED if part.name == "confirm" else 0)
        for plan in plans:
            assert plan.config.stagger_resets and plan.config.yardstick.endswith(f"{unit.task}.npz")
            assert len(plan.hparams) == part.runs_per_arm
            assert (plan.phase is not None) == (plan.config.arm != "model-free")
            assert abs(plan.total_env_steps - unit.budget.steps) <= plan.config.env_steps_per_update
            if "--cc-epochs" in part.options:
                assert plan.config.cc_epochs == 0
            if part.name == "confirm" and plan.name == "cd-k20":  # the arm of the finding: cdjax's weights
                assert [float(h.cc_policy) for h in plan.hparams] == [0.1]


def test_the_header_names_the_policy_head_each_run_started_with():
    """run.json's policy_head_scale is stated (a run.json from before the field ran Brax's head, x1); runs at two
    scales are both named, each once."""
    def run(info):
        return report.Run(path=None, info=info, machine={}, unit={}, curves={}, evals={}, phase={}, planned={},
                          phase_steps={})

    def task(*runs):
        return report.TaskData(name="t", runs=list(runs), curves={}, evals={}, phase={}, budget=0, stated=0,
                               complete=True)

    old, new = run({"base_config": {"env": "t"}}), run({"base_config": {"env": "t", "policy_head_scale": 0.1}})
    assert "policy head x1 " in report._head_scales([task(old)])
    assert "policy head x0.1 " in report._head_scales([task(new)])
    assert "policy head x0.1 and x1 " in report._head_scales([task(old), task(new, new)])
    assert report._head_scales([]) == ""


def test_the_paired_table_sets_each_seed_beside_the_same_seed_of_the_other_data(tmp_path):
    """`report --paired DATA`: per (task, arm) in both, both IQMs and each side's seeds in order, with how many seeds
    are higher here; an arm whose seed counts differ is named, not paired; an arm only one side has is left out."""
    def row(arm, seeds, ids=None):
        out = dict(task="t", arm=arm, final_return=[1.0, 0.0, 2.0], final_return_seeds=seeds)
        return out if ids is None else dict(out, seed_ids=ids)

    here = [row("mbmf", [3.0, 1.0, 5.0], [0, 1, 2]), row("cd-k5", [1.0, 2.0], [0, 1]), row("model-free", [1.0]),
            row("cd-k20", [1.0, None], [0, 1]), row("cd-k20-paper", [1.0, 2.0], [0, 1])]
    there = [row("mbmf", [2.0, 2.0, 4.0]), row("cd-k5", [1.0, 2.0, 3.0]), row("cd-k20", [0.0, 0.0], [0, 1]),
             row("cd-k20-paper", [1.0, 2.0], [5, 6])]
    text = "\n".join(report.paired_table(here, there, "x1"))
    (line,) = [x for x in text.splitlines() if x.startswith("| t | Mb-Mf |")]
    assert "| 2 of 3 | 2, 2, 4 | 3, 1, 5 |" in line  # no ids there (an older summary): paired by position
    (line,) = [x for x in text.splitlines() if x.startswith("| t | CD k=20 (cdjax's weights) |")]
    assert "| 1 of 1 | 0, 0 | 1, n/a |" in line  # a seed without a final return is shown, not counted
    assert "CD k=5 (seeds 3 there, [0, 1] here)" in text and "model-free" not in text
    assert "CD k=20 (paper's weights) (seeds [5, 6] there, [0, 1] here)" in text  # other seeds: not paired
    assert cli.main(["report", "--runs", str(tmp_path), "--paired", str(tmp_path / "none")]) == 2
