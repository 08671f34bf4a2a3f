"""experiments/atari/units.py: each ALE tier unit's steps (built without running anything) name the sweep they
should, its hang guard, the evaluation in the time left, the plot and the report; a MinAtar unit evaluates only a
run its sweep did not. The 40M-frame pieces (experiments/atari/ale40m.py): a piece starts its sweep or resumes the
run its directory holds, evaluates once it reached its budget, packs, all on its own cores; pieces side by side get
disjoint cores and their GPUs."""

import json
import os
import pathlib
import shutil
import subprocess
import sys
import time

import pytest

from experiments.launch import Context, unit_main
from experiments.atari import ale40m, units as atari_units

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


# --- the ALE tier at 40M frames (experiments/atari/ale40m.py): pieces, their cores, their state across machines


def _piece(tmp_path, name="ale40m-seaquest-a2c-cd", limit=900, end=1200, **params):
    u = UNITS[name]
    ctx = u.context(tmp_path / name, limit, end, [f"{k}={v}" for k, v in params.items()])
    return ctx, u.steps(ctx)


def _fake_run(run_dir, done: int, of: int = ale40m.UPDATES, arm: str = "a2c-cd", seeds: int = 3, evals=()):
    """A run directory as the sweep leaves it: run.json, an arm's checkpoint directory at `done` updates and an
    older one, eval rows `evals` of (seed, update, episodes)."""
    run_dir.mkdir(parents=True)
    (run_dir / "run.json").write_text(json.dumps({"seeds": seeds, "arms": [{"name": arm, "num_updates": of}]}))
    for step in (done - 250, done):
        (run_dir / "checkpoints" / arm / str(step)).mkdir(parents=True)
        (run_dir / "checkpoints" / arm / str(step) / "state").write_bytes(bytes(range(256)) * 40 + str(step).encode())
    (run_dir / "eval.jsonl").write_text("".join(json.dumps({"arm": arm, "hp": "alpha=1.0", "seed": s, "update": u,
                                                            "env_steps": u * 80, "episodes": e}) + "\n"
                                                for s, u, e in evals))


def test_a_piece_starts_its_sweep_or_resumes_it_then_evaluates_once_at_its_budget_and_packs(tmp_path):
    from cdjax import agents
    from cdjax.cli import build_parser

    ctx, (sweep, evaluate, pack) = _piece(tmp_path, cpus="16-31", outbox=str(tmp_path / "box"))
    run = tmp_path / "ale40m-seaquest-a2c-cd" / "seaquest"
    # every step runs on the piece's cores: `ale40m pin 16-31 python -m ...`
    pin = ("python", "-m", "experiments.atari.ale40m", "pin", "16-31")
    assert all(s.argv[:5] == pin for s in (sweep, evaluate, pack))
    argv = list(sweep.argv[sweep.argv.index("cdjax.cli") + 1:])
    args = vars(build_parser(agents.get("atari")).parse_args(argv))
    assert (args["preset"], args["spec.arms"], args["spec.seeds"], args["spec.total_env_steps"]) == \
        ("seaquest", ["a2c-cd"], 3, 10_000_000)
    assert (args["time_limit"], args["spec.final_eval"], args["spec.progress"], args["out"]) == \
        (900, False, False, str(run))
    assert sweep.timeout == 1020 and sweep.when(ctx) and not evaluate.when(ctx) and not pack.when(ctx)
    assert evaluate.timeout(ctx) == ale40m.EVAL_S  # 1200 s from its start: the evaluation and packing fit
    assert pack.argv[5:] == ("python", "-m", "experiments.atari.ale40m", "pack", str(run), str(tmp_path / "box"),
                             "--name", "ale40m-seaquest-a2c-cd", "--log", str(ctx.out / "unit.log"))

    _fake_run(run, done=40_000)  # brought back from an earlier machine, a third of the way
    ctx, (sweep, evaluate, pack) = _piece(tmp_path, limit=600)
    assert sweep.argv == ("python", "-m", "cdjax.cli", "sweep", "--out", str(run), "--resume", "--no-progress",
                          "--time-limit", "600")  # no cores given: as it is; the run's own settings from run.json
    assert sweep.when(ctx) and not evaluate.when(ctx) and pack.when(ctx)
    assert pack.argv[-5:-2] == (str(ctx.out / "outbox"), "--name", "ale40m-seaquest-a2c-cd")  # default outbox

    shutil.rmtree(run)
    _fake_run(run, done=ale40m.UPDATES, evals=[(s, 40_000, 100) for s in range(3)])  # at its budget, evaluated earlier
    assert not sweep.when(ctx) and evaluate.when(ctx) and pack.when(ctx)
    late = Context(ctx.out, ctx.limit, ctx.end, ctx.params, started=time.monotonic() - 1100)
    assert evaluate.timeout(late) == 30  # the packing's time is kept; the evaluation gets what is left, 30 s at least
    with (run / "eval.jsonl").open("a") as f:
        f.writelines(json.dumps({"arm": "a2c-cd", "hp": "alpha=1.0", "seed": s, "update": ale40m.UPDATES,
                                 "env_steps": ale40m.STEPS, "episodes": 100}) + "\n" for s in range(3))
    assert not sweep.when(ctx) and not evaluate.when(ctx) and pack.when(ctx)  # nothing left but the packing


@pytest.mark.parametrize("cores, gpus, pieces, each", [(64, 4, 4, 16), (128, 8, 8, 16), (64, 4, 8, 8), (16, 1, 1, 16),
                                                       (66, 4, 4, 16)])
def test_pieces_side_by_side_get_their_own_cores_and_gpus(cores, gpus, pieces, each):
    got = ale40m.shares(range(cores), gpus, pieces)
    sets = [ale40m.parse_cpus(cpus) for _, cpus in got]
    assert [gpu for gpu, _ in got] == [i % gpus for i in range(pieces)]
    assert all(len(s) == each for s in sets) and len(set().union(*sets)) == each * pieces  # disjoint, equal shares
    assert ale40m.shares([3, 5, 6, 7], 2, 2) == [(0, "3,5"), (1, "6-7")]  # the usable cores, not 0..n-1
    with pytest.raises(ValueError, match="cannot share"):
        ale40m.shares(range(4), 4, 8)


def test_pin_runs_a_command_on_the_given_cores():
    cores = sorted(os.sched_getaffinity(0))
    out = subprocess.run([sys.executable, "-m", "experiments.atari.ale40m", "pin", ale40m.cpu_list(cores[:1]),
                          "python", "-c", "import os; print(sorted(os.sched_getaffinity(0)))"],
                         capture_output=True, text=True, check=True, cwd=pathlib.Path(__file__).parents[1]).stdout
    assert out.strip() == str(cores[:1])
