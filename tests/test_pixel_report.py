"""experiments.pixel.report: the sweeps of experiments/pixel/units.py (one per task and arm, unpacked side by side)
read as one task, their arms compared at the update all of them reached, as the sweep of every arm reads."""

import json

import pytest

from experiments.pixel import report

LTQ = {"alpha": 1.0, "cc_policy": 1.0, "lr": 1e-4}  # the fields an hparams record has (a few of them)
CD = [{**LTQ, "alpha": 100.0, "cc_policy": c} for c in (0.0, 1.0)]
CONFIG = {"env": "halfcheetah", "batch_size": 2, "seq_len": 5, "horizon": 10}


def _value(arm: str, cc_policy: float, seed: int, update: int) -> float:
    """Each run's metrics: a level per arm, a spread over seeds, and past update 20 a value far off any level."""
    if update > 20:
        return 1e6
    return {"ltq": 10.0, "ltq-cd": 20.0 + 10.0 * cc_policy}[arm] + 0.1 * seed


def _sweep(path, arms, experts, seeds=4):
    """A pixel run directory: arms is [(name, [(hp label, hparams, last update)])], the labels as a sweep gives them
    (cc_policy is shown only where the sweep ran both values)."""
    path.mkdir(parents=True)
    rows, evals = [], []
    for name, sets in arms:
        for label, hp, last in sets:
            for s in range(seeds):
                v = lambda u, s=s: _value(name, hp["cc_policy"], s, u)  # noqa: E731
                rows += [{"arm": name, "hp": label, "seed": s, "update": u, "wall_s": 0.5 * u,
                          **{m: v(u) for m, _ in report.SCORES}} for u in range(1, last + 1)]
                evals.append({"arm": name, "hp": label, "seed": s, "update": last, "deterministic": True,
                              "eval/return": v(20)})
    run = {"base_config": {**CONFIG, "expert": str(experts / "halfcheetah" / "expert.msgpack")}, "seeds": seeds,
           "arms": [{"name": name, "config": CONFIG, "hp_labels": [label for label, _, _ in sets],
                     "hparams": [hp for _, hp, _ in sets]} for name, sets in arms]}
    (path / "pixel").mkdir()
    (path / "pixel" / "run.json").write_text(json.dumps(run))
    (path / "pixel" / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    (path / "pixel" / "eval.jsonl").write_text("".join(json.dumps(e) + "\n" for e in evals))


def _experts(tmp_path):
    experts = tmp_path / "experts"
    (experts / "halfcheetah").mkdir(parents=True)  # cost.json beside the expert run.json names (no expert file)
    (experts / "halfcheetah" / "cost.json").write_text(json.dumps(
        {"data_bytes_all_runs": 2**30, "once_compile_and_run_s": 3.0, "fly_per_update_s": 1.5, "update_s": 0.1}))
    return experts


def test_units_of_one_task_are_merged_and_compared_at_the_update_all_reached(tmp_path):
    experts = _experts(tmp_path)
    units = tmp_path / "units"
    _sweep(units / "halfcheetah-ltq", [("ltq", [("default", LTQ, 30)])], experts)
    _sweep(units / "halfcheetah-ltq-cd0", [("ltq-cd", [("alpha=100.0", CD[0], 25)])], experts)
    _sweep(units / "halfcheetah-ltq-cd1", [("ltq-cd", [("alpha=100.0", CD[1], 20)])], experts)
    # the same runs as the sweep of every arm writes them (the earlier passes' OUT/TASK/pixel)
    whole = tmp_path / "whole"
    _sweep(whole / "halfcheetah", [("ltq", [("default", LTQ, 30)]),
                                   ("ltq-cd", [("alpha=100.0,cc_policy=0.0", CD[0], 25),
                                               ("alpha=100.0,cc_policy=1.0", CD[1], 20)])], experts)

    tasks = report.units_of(units)
    assert list(tasks) == ["halfcheetah"] and [d.name for d in tasks["halfcheetah"]] == [
        "halfcheetah-ltq", "halfcheetah-ltq-cd0", "halfcheetah-ltq-cd1"]
    table, info = report.task_report(tasks["halfcheetah"], reps=100)
    arms = {r["arm"]: r for r in table}
    assert set(arms) == {"ltq", "ltq-cd alpha=100.0,cc_policy=0.0", "ltq-cd alpha=100.0,cc_policy=1.0"}
    assert {r["task"] for r in table} == {"halfcheetah"} and {r["update"] for r in table} == {20}
    # the window ends at update 20 (no 1e6 from the longer units) and every arm keeps its own level and seeds
    for arm, level in (("ltq", 10.0), ("ltq-cd alpha=100.0,cc_policy=0.0", 20.0),
                       ("ltq-cd alpha=100.0,cc_policy=1.0", 30.0)):
        est, _, high, n = arms[arm]["heldout/imitation"]
        assert n == 4 and high < level + 1 and est == pytest.approx(level + 0.15)
        assert arms[arm]["eval/return"][0] == pytest.approx(level + 0.15)
    assert info["last_update"] == 20 and info["cost"]["update_s"] == 0.1  # cost.json found beside the expert
    assert set(info["frames_per_s"]) == {"halfcheetah-ltq", "halfcheetah-ltq-cd0", "halfcheetah-ltq-cd1"}
    assert info["frames_per_s"]["halfcheetah-ltq"] == pytest.approx(4 * 30 * 10 / 15.0)  # its own wall clock

    # the sweep of every arm gives the same table
    (whole_dir,) = report.units_of(whole)["halfcheetah"]
    whole_table, whole_info = report.task_report(whole_dir, reps=100)
    assert [(r["arm"], r["update"]) for r in whole_table] == [(r["arm"], r["update"]) for r in table]
    for a, b in zip(whole_table, table):
        assert a["heldout/imitation"][0] == b["heldout/imitation"][0]
    assert len(whole_info["frames_per_s"]) == 1

    # the markdown names both arms under the one task, says where the units stopped, and a frames/s per unit
    text = report.markdown([table], [info])
    assert "| halfcheetah | ltq (n=4) | 20 |" in text
    assert "| halfcheetah | ltq-cd alpha=100.0,cc_policy=0.0 (n=4) | 20 |" in text
    assert "| halfcheetah | ltq-cd alpha=100.0,cc_policy=1.0 (n=4) | 20 |" in text
    assert "3 separate sweeps, compared at update 20" in text
    assert "halfcheetah-ltq 30, halfcheetah-ltq-cd0 25, halfcheetah-ltq-cd1 20" in text
    assert "halfcheetah-ltq-cd0 " in text.splitlines()[-1]
    assert "separate sweeps" not in report.markdown([whole_table], [whole_info])


def test_two_units_holding_the_same_arm_are_refused(tmp_path):
    experts = _experts(tmp_path)
    for name in ("halfcheetah-ltq", "halfcheetah-ltq-again"):
        _sweep(tmp_path / "units" / name, [("ltq", [("default", LTQ, 5)])], experts, seeds=1)
    with pytest.raises(ValueError, match="both hold arm 'ltq'"):
        report.task_report(report.units_of(tmp_path / "units")["halfcheetah"], reps=10)
