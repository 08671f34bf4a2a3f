"""experiments/pixel/units.py: each unit of the re-run at the presets' length names the sweep it should (its steps,
built without running anything), and that sweep's command line plans the runs it should, with nothing compiled."""

import pathlib
import time

import pytest

from experiments.launch import Context, unit_main
from experiments.pixel import units as pixel_units

UNITS = pixel_units.UNITS
OUT = pathlib.Path("runs/pixel-units")


def _steps(unit: str, limit: int = 1260, end: int = 1680, **params):
    u = UNITS[unit]
    ctx = u.context(OUT / unit, limit, end, [f"{k}={v}" for k, v in params.items()])
    return ctx, u.steps(ctx)


def _sweep_argv(step) -> list[str]:
    """The `cdjax.cli sweep` arguments of a step."""
    return list(step.argv[step.argv.index("cdjax.cli") + 1:])


@pytest.mark.parametrize("unit, arms, cc_policy, runs", [
    ("halfcheetah-ltq", ["ltq"], None, 10),
    ("halfcheetah-ltq-cd", ["ltq-cd"], None, 20),
    ("halfcheetah-ltq-cd0", ["ltq-cd"], ["0"], 10),
    ("reacher-ltq-cd1", ["ltq-cd"], ["1"], 10),
    ("pusher-ltq-cd0", ["ltq-cd"], ["0"], 10),
])
def test_a_units_sweep_has_its_arms_preset_and_time_limit_and_plans_its_runs(unit, arms, cc_policy, runs):
    from cdjax import agents
    from cdjax.cli import build_parser, sweep_spec
    from cdjax.runner.plan import plan_arms

    _, steps = _steps(unit, limit=900)
    argv = _sweep_argv(steps[0])
    task = unit.split("-")[0]

    def values(flag):
        if flag not in argv:
            return None
        i = argv.index(flag) + 1
        return argv[i:next((j for j in range(i, len(argv)) if argv[j].startswith("--")), len(argv))]

    assert argv[0] == "sweep" and values("--preset") == [f"pixel-{task}"] and values("--time-limit") == ["900"]
    assert values("--arms") == arms and values("--cc-policy") == cc_policy
    assert values("--out") == [f"runs/pixel-units/{unit}/pixel"]  # each unit its own work directory and tarball
    assert values("--expert") == [f"experiments/pixel/data/three-tasks-x2/{task}/expert.msgpack"]
    assert steps[0].timeout == 900 + 300  # the hang guard
    assert steps[1].argv[2:] == ("cdjax.cli", "eval", f"runs/pixel-units/{unit}/pixel", "--episodes", "4")
    assert steps[3].argv[2:5] == ("experiments.pixel.report", "--strips", f"runs/pixel-units/{unit}/pixel")

    setting = agents.get("pixel")
    (plan,) = plan_arms(sweep_spec(build_parser(setting).parse_args(argv), setting))
    assert plan.name == arms[0] and plan.config.num_updates == 10_000
    assert (plan.config.compute_dtype, plan.config.conv_impl, plan.config.core_impl, plan.config.output_grad) == (
        "bfloat16", "per-run", "fused", "compute")
    assert len(plan.hparams) * 10 == runs  # 10 seeds per hyper-parameter set
    if arms == ["ltq-cd"]:  # the grounded encoder's own loss (4cf108f); unused by ltq
        assert {h.enc_aux_coef for h in plan.hparams} == {10.0}
    if cc_policy is not None:
        assert [h.cc_policy for h in plan.hparams] == [float(cc_policy[0])]
        # one value is not shown in the label: experiments.pixel.report adds it back where units of an arm differ
        # (tests/test_pixel_report.py builds its units with these labels)
        assert plan.labels == ("alpha=100.0",)


def test_the_sweep_speed_unit_times_the_model_of_before_and_the_presets_on_the_same_30_runs():
    """Issue 22's before and after in one command: two sweeps of halfcheetah's preset, 30 runs each, the same
    updates; the first with every speed switch back (float32, grouped, flax, the policy at the model's rate)."""
    from cdjax import agents
    from cdjax.cli import build_parser, sweep_spec
    from cdjax.runner.plan import plan_arms

    _, steps = _steps("sweep-speed", updates=150)
    assert len(steps) == 2 and [s.log for s in steps] == ["before.log", "presets.log"]
    assert {s.timeout for s in steps} == {420}
    setting = agents.get("pixel")
    plans = []
    for step in steps:
        argv = _sweep_argv(step)
        plans.append(plan_arms(sweep_spec(build_parser(setting).parse_args(argv), setting)))
    before, after = plans
    for arms in plans:
        assert sum(len(p.hparams) * 10 for p in arms) == 30 and {p.config.num_updates for p in arms} == {150}

    def config(arms):
        return {(p.config.compute_dtype, p.config.conv_impl, p.config.core_impl, p.config.output_grad) for p in arms}

    # output_grad is the presets' there too: with float32 operands it changes nothing (test_pixel_model)
    assert config(before) == {("float32", "grouped", "flax", "compute")}
    assert config(after) == {("bfloat16", "per-run", "fused", "compute")}
    assert {h.lr_policy for p in before for h in p.hparams} == {0.0}
    assert {h.lr_policy for p in after for h in p.hparams} == {1e-3}


def test_the_sweep_long_unit_runs_the_presets_30_runs_at_the_length_of_the_sweep_before():
    """The after-figure at the length the 41,440 frames/s before it came from (1,400 updates of halfcheetah's 30
    runs): the presets as they are, no evaluation, stopped by its time limit inside the command's timeout."""
    from cdjax import agents
    from cdjax.cli import build_parser, sweep_spec
    from cdjax.runner.plan import plan_arms

    _, (step,) = _steps("sweep-long", limit_s=400)
    argv = _sweep_argv(step)
    assert argv[argv.index("--time-limit") + 1] == "400" and "--no-final-eval" in argv
    assert step.timeout == 520 and step.log == "presets.log"
    setting = agents.get("pixel")
    spec = sweep_spec(build_parser(setting).parse_args(argv), setting)
    arms = plan_arms(spec)
    assert sum(len(p.hparams) * spec.seeds for p in arms) == 30 and {p.config.num_updates for p in arms} == {1400}
    assert {(p.config.compute_dtype, p.config.conv_impl, p.config.core_impl, p.config.output_grad) for p in arms} == {
        ("bfloat16", "per-run", "fused", "compute")}


def test_the_evaluation_gets_what_is_left_before_the_units_end_and_unknown_units_are_refused(capsys):
    ctx, steps = _steps("pusher-ltq", end=1700, eval_s=280)
    evaluate = steps[1].timeout
    assert evaluate(ctx) == 280  # at the start: all of eval_s
    late = Context(ctx.out, ctx.limit, ctx.end, ctx.params, started=time.monotonic() - 1300)
    assert 1700 - 1300 - 180 - 2 <= evaluate(late) <= 1700 - 1300 - 180  # what is left before the end, less strips
    assert evaluate(Context(ctx.out, ctx.limit, ctx.end, ctx.params, started=time.monotonic() - 1600)) == 120
    for unit in ("pusher-ltq-cd2", "walker-ltq", "nothing"):
        with pytest.raises(SystemExit) as stop:
            unit_main("python -m experiments.pixel", UNITS, 1260, 1680, ["run", unit, "--out", "unused"])
        assert stop.value.code == 2 and "invalid choice" in capsys.readouterr().err
    assert not pathlib.Path("unused").exists()


def test_the_precision_unit_compares_its_reference_and_candidate_at_equal_updates_each_in_half_the_time():
    from cdjax import agents
    from cdjax.cli import build_parser, sweep_spec
    from cdjax.runner.plan import plan_arms

    ctx, steps = _steps("precision", limit=1000, updates=100)
    reference, candidate, compare = steps
    setting = agents.get("pixel")
    configs = []
    for step in (reference, candidate):
        argv = _sweep_argv(step)
        assert argv[argv.index("--time-limit") + 1] == "500" and step.timeout == 620
        arms = plan_arms(sweep_spec(build_parser(setting).parse_args(argv), setting))
        assert {p.config.num_updates for p in arms} == {100}
        configs.append({(p.config.compute_dtype, p.config.conv_impl) for p in arms})
    assert configs == [{("bfloat16", "per-run")}, {("bfloat16", "auto")}]  # the presets; the candidate's switches
    assert compare.argv[2] == "experiments.pixel.precision" and compare.argv[-5:] == (
        "--labels", "presets", "--compute-dtype bfloat16 --conv-impl auto", "--out", f"{ctx.out}/precision.md")
