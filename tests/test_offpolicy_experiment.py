"""The off-policy experiment (experiments/offpolicy): every unit's sweep plans as the experiment says, and the report
of hand-made run directories gives the tables, the diagnostics' ratios and the across-task statistics."""

from __future__ import annotations

import json

import numpy as np
import pytest

from experiments.offpolicy import ALPHAS, SEEDS, STEPS, TASKS, report
from experiments.offpolicy.units import INPUTS, PARTS, UNITS, sweep_args


@pytest.mark.parametrize("name", sorted(UNITS))
def test_every_units_sweep_plans_the_arms_grid_and_budget_it_names(name):
    from cdjax import agents
    from cdjax.cli import build_parser, sweep_spec
    from cdjax.runner.plan import plan_arms

    task, part = name.rsplit("-", 1)
    arms, horizon = PARTS[part]
    setting = agents.get("offpolicy")
    spec = sweep_spec(build_parser(setting).parse_args(["sweep", *sweep_args(task, part, str(STEPS), "unused")]),
                      setting)
    plans = plan_arms(spec)
    assert task in TASKS and [p.name for p in plans] == list(arms) and spec.seeds == SEEDS
    from cdjax.agents.offpolicy import Config

    for plan in plans:
        assert plan.config.env == task and plan.config.diagnostics
        assert plan.config.inputs == INPUTS.get(part, Config().inputs)
        assert abs(plan.total_env_steps - STEPS) <= plan.config.env_steps_per_update
        if horizon is None:
            assert len(plan.hparams) == 1
        else:
            assert plan.config.horizon == horizon
            assert sorted(float(h.alpha) for h in plan.hparams) == sorted(ALPHAS)


LEVEL = {"model-free": 1.0, "model": 2.0, "paper-cd-k3-a0.1": 2.1, "paper-cd-k3-a1": 0.5, "self-pred-k3-a0.1": 2.0,
         "self-pred-k3-a1": 3.0}


def _run_dir(root, task, name, arms, seeds=4, updates=20, spu=100, cut=None):
    """A run directory by hand: the return of key K at update u of seed s is LEVEL[K] x u x (1 + 0.01 s)."""
    d = root / task / name
    d.mkdir(parents=True)
    info = {"version": 1, "setting": "offpolicy", "base_config": {"env": task}, "seeds": seeds, "seed": 0,
            "env_steps_per_update": spu, "total_env_steps": updates * spu, "command": f"cdjax sweep {name}",
            "arms": arms}
    (d / "run.json").write_text(json.dumps(info))
    rows, evals = [], []
    for a in arms:
        for hp, label in zip(a["hparams"], a["hp_labels"]):
            level = LEVEL[report.arm_key(a, hp)]
            for s in range(seeds):
                for u in range(1, (cut or updates) + 1):
                    rows.append({"arm": a["name"], "hp": label, "seed": s, "update": u, "env_steps": u * spu,
                                 "episode/return": level * u * (1 + 0.01 * s), "episode/discounted_return": level,
                                 "grad/actor/actor": 2.0, "grad/critic/encoder": 4.0, "grad/consistency/actor": 0.5,
                                 "grad/consistency/encoder": 1.0, "grad/self_pred/encoder": 2.0,
                                 "heldout/open_loop_mse_1": 0.1 * level, "heldout/open_loop_mse_3": 0.3 * level,
                                 "latent/spread": 0.7})
                evals.append({"arm": a["name"], "hp": label, "seed": s, "update": updates, "deterministic": True,
                              "eval/return": 10 * level + s, "eval/discounted_return": level, "episodes": 10})
    (d / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    (d / "eval.jsonl").write_text("".join(json.dumps(r) + "\n" for r in evals))


def _arm(name, horizon=3, alphas=(0.0,)):
    return {"name": name, "arm": name, "config": {"arm": name, "horizon": horizon},
            "hparams": [{"alpha": a} for a in alphas], "hp_labels": [f"alpha={a:g}" for a in alphas]}


@pytest.fixture(scope="module")
def results(tmp_path_factory):
    root = tmp_path_factory.mktemp("runs")
    for task in ("ant", "hopper"):
        _run_dir(root, task, "base", [_arm("model-free"), _arm("model")])
        _run_dir(root, task, "k3", [_arm("paper-cd", 3, (0.1, 1.0)), _arm("self-pred", 3, (0.1, 1.0))],
                 cut=15 if task == "hopper" else None)
    out = tmp_path_factory.mktemp("out")
    return report.load([root]), report.write_results(report.load([root]), out, reps=200).read_text(), out


def test_arm_keys_name_the_arm_its_horizon_and_weight():
    assert report.arm_key(_arm("model-free"), {"alpha": 0.0}) == "model-free"
    assert report.arm_key(_arm("model"), {"alpha": 0.0}) == "model"
    on_obs = _arm("model-free")
    on_obs["config"]["inputs"] = "obs"  # the TASK-obs unit's
    assert report.arm_key(on_obs, {"alpha": 0.0}) == "model-free-obs"
    assert report.arm_key(_arm("self-pred", 5), {"alpha": 0.1}) == "self-pred-k5-a0.1"


def test_the_report_compares_every_arm_where_all_got_and_ranks_them(results):
    tasks, text, out = results
    ant, hopper = tasks
    assert ant.complete and ant.budget == 2000 and set(ant.curves) == set(LEVEL)
    assert not hopper.complete and hopper.budget == 1500  # the k3 runs stopped at update 15: all arms cut there
    assert all(c.env_steps.max() == 1500 for c in hopper.curves.values())
    assert all(e is None for e in hopper.evals.values())  # evaluated at each run's end, not at the common budget
    assert "hopper: 2,000 env steps per run planned, cut at 1,500 env steps" in text
    rows = {(r["task"], r["arm"]): r for r in report.task_rows(ant, reps=200)}
    # final return: the last 10% of env steps (updates 19 and 20) -> level x 19.5 x (1 + 0.01 s), IQM over 4 seeds
    expected = np.mean([LEVEL["model"] * 19.5 * (1 + 0.01 * s) for s in (1, 2)])
    assert rows[("ant", "model")]["final"][0] == pytest.approx(expected, rel=1e-6)
    assert rows[("ant", "model")]["p_model-free"][0] == 1.0 and rows[("ant", "paper-cd-k3-a1")]["p_model"][0] == 0.0
    assert rows[("ant", "self-pred-k3-a1")]["eval"][0] == pytest.approx(30 + 1.5)
    # the gradient ratios and the held-out error at the horizon's last step
    assert rows[("ant", "paper-cd-k3-a1")]["ratio/policy_path"][0] == pytest.approx(0.25)
    assert rows[("ant", "paper-cd-k3-a1")]["ratio/model_path"][0] == pytest.approx(0.25)
    assert rows[("ant", "self-pred-k3-a1")]["ratio/self_pred"][0] == pytest.approx(0.5)
    assert rows[("ant", "model")]["heldout/open_loop_mse_k"][0] == pytest.approx(0.3 * LEVEL["model"])
    assert "## Across tasks" in text and (out / "figures" / "profiles.png").exists()
    line = next(x for x in text.splitlines() if x.startswith("| self-pred-k3-a1 | model-free |"))
    assert line.endswith("| 1 [1, 1] |")  # it beats model-free on every seed of both tasks: P = 1 in every resample
