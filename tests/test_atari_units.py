"""experiments/atari/units.py: each ALE tier unit's steps (built without running anything) name the sweep they
should, its hang guard, the evaluation in the time left, the plot and the report; a MinAtar unit evaluates only a
run its sweep did not."""

import pathlib
import time

import pytest

from experiments.launch import Context, unit_main
from experiments.atari import units as atari_units

UNITS = atari_units.UNITS


def _steps(unit: str, limit: int = 1080, end: int = 1380, **params):
    u = UNITS[unit]
    ctx = u.context(pathlib.Path("runs/atari-units") / unit, limit, end, [f"{k}={v}" for k, v in params.items()])
    return ctx, u.steps(ctx)


def _sweep_argv(step) -> list[str]:
    return list(step.argv[step.argv.index("cdjax.cli") + 1:])


@pytest.mark.parametrize("game", ["breakout", "seaquest", "mspacman", "frostbite"])
def test_a_units_sweep_has_its_preset_arms_seeds_budget_and_time_limit(game):
    from cdjax import agents
    from cdjax.cli import build_parser

    ctx, (sweep, evaluate, plot, report) = _steps(f"ale-{game}")
    argv = _sweep_argv(sweep)

    def values(flag):
        i = argv.index(flag) + 1
        return argv[i:next((j for j in range(i, len(argv)) if argv[j].startswith("--")), len(argv))]

    assert argv[0] == "sweep" and values("--setting") == ["atari"] and values("--preset") == [game]
    assert values("--arms") == ["a2c", "a2c-cd"] and values("--seeds") == ["3"] and values("--steps") == ["1000000"]
    assert values("--time-limit") == ["1080"] and "--no-final-eval" in argv
    run = f"runs/atari-units/ale-{game}/{game}"
    assert values("--out") == [run]
    # the hang guard is the time limit + 120 s; then every run is evaluated, plotted and reported
    assert sweep.timeout == 1200
    assert evaluate.argv[2:] == ("cdjax.cli", "eval", run, "--episodes", "100")
    # the evaluation: up to 360 s, ending 120 s before 1380 s from the unit's start (plot and report: 50 s each)
    assert evaluate.timeout(ctx) == 360 and (plot.timeout, report.timeout) == (50, 50)
    assert report.argv[2:] == ("experiments.atari.report", run, "--out", f"runs/atari-units/ale-{game}/report")
    args = vars(build_parser(agents.get("atari")).parse_args(argv))  # each option is the CLI's (the config: ale-py)
    assert (args["preset"], args["time_limit"], args["spec.seeds"]) == (game, 1080, 3)
    assert args["spec.arms"] == ["a2c", "a2c-cd"]
    assert (args["spec.total_env_steps"], args["spec.final_eval"], args["spec.progress"]) == (1_000_000, False, False)


def test_the_units_sweep_plans_two_arms_of_three_seeds_at_one_million_agent_steps():
    pytest.importorskip("ale_py", reason="the ALE config needs the extra `atari` (ale-py)")
    from cdjax import agents
    from cdjax.cli import build_parser, sweep_spec
    from cdjax.runner.plan import plan_arms

    _, steps = _steps("ale-breakout")
    setting = agents.get("atari")
    plans = plan_arms(sweep_spec(build_parser(setting).parse_args(_sweep_argv(steps[0])), setting))
    assert [p.name for p in plans] == ["a2c", "a2c-cd"]
    assert all(p.config.num_updates == 12_500 and p.config.num_envs == 16 for p in plans)  # 1M / (16 x 5)


def test_the_limits_follow_the_options_and_unknown_units_are_refused(capsys):
    ctx, (sweep, evaluate, *_) = _steps("ale-frostbite", limit=900, end=1300, eval_s=200, steps=500000)
    argv = _sweep_argv(sweep)
    assert argv[argv.index("--time-limit") + 1] == "900" and argv[argv.index("--steps") + 1] == "500000"
    assert sweep.timeout == 1020 and evaluate.timeout(ctx) == 200
    late = Context(ctx.out, ctx.limit, ctx.end, ctx.params, started=time.monotonic() - 1100)
    assert 1300 - 1100 - 120 - 2 <= evaluate.timeout(late) <= 1300 - 1100 - 120
    assert evaluate.timeout(Context(ctx.out, ctx.limit, ctx.end, ctx.params, started=time.monotonic() - 1300)) == 60
    for unit in ("ale-pong", "ale-"):
        with pytest.raises(SystemExit) as stop:
            unit_main("python -m experiments.atari", UNITS, 1080, 1380, ["run", unit, "--out", "unused"])
        assert stop.value.code == 2 and "invalid choice" in capsys.readouterr().err
    assert not pathlib.Path("unused").exists()


def test_a_minatar_unit_evaluates_only_a_run_its_sweep_stopped_before_its_final_evaluation(tmp_path):
    from cdjax import agents
    from cdjax.cli import build_parser

    u = UNITS["minatar-breakout"]
    ctx = u.context(tmp_path, 500, 800)
    sweep, evaluate, report = u.steps(ctx)
    args = vars(build_parser(agents.get("atari")).parse_args(_sweep_argv(sweep)))
    assert (args["preset"], args["time_limit"]) == ("minatar-breakout", 500) and "--no-final-eval" not in sweep.argv
    assert evaluate.when(ctx)  # no evaluation yet
    (tmp_path / "breakout").mkdir()
    (tmp_path / "breakout" / "eval.jsonl").write_text('{"episodes": 100, "return": 1.0}\n')
    assert not evaluate.when(ctx)
    assert report.argv[2] == "experiments.atari.report"
