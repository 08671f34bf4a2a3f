"""experiments/pixel/units.sh: each unit of the re-run at the presets' length names the sweep it should (`--print-command`
starts and writes nothing), and that sweep's command line plans the runs it should, with nothing compiled."""

import pathlib
import shlex
import subprocess

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]


def _command(unit: str, **env) -> subprocess.CompletedProcess:
    return subprocess.run(["bash", "experiments/pixel/units.sh", "--print-command", unit], cwd=ROOT, text=True,
                          capture_output=True, timeout=30, env={"PATH": "/usr/bin:/bin", **env})


def _sweep_argv(line: str) -> list[str]:
    """The `cdjax.cli sweep` arguments of a unit's command line (its first command)."""
    first = shlex.split(line.split(";")[0])
    return first[first.index("cdjax.cli") + 1:]


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

    done = _command(unit, LIMIT_S="900")
    assert done.returncode == 0, done.stderr
    line = done.stdout.strip()
    argv = _sweep_argv(line)
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
    assert f"cdjax.cli eval runs/pixel-units/{unit}/pixel" in line and "--strips" in line

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

    done = _command("sweep-speed", SPEED_UPDATES="150")
    assert done.returncode == 0, done.stderr
    commands = [c for c in done.stdout.split(";") if "cdjax.cli sweep" in c]
    assert len(commands) == 2 and "Trained in" in done.stdout
    setting = agents.get("pixel")
    plans = []
    for line in commands:
        first = shlex.split(line)
        argv = first[first.index("cdjax.cli") + 1:first.index(">")]
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

    done = _command("sweep-long", LONG_LIMIT_S="400")
    assert done.returncode == 0, done.stderr
    argv = _sweep_argv(done.stdout)
    assert argv[argv.index("--time-limit") + 1] == "400" and "--no-final-eval" in argv
    assert done.stdout.startswith("timeout -s INT -k 60 520 ")
    setting = agents.get("pixel")
    spec = sweep_spec(build_parser(setting).parse_args(argv[:argv.index(">")]), setting)
    arms = plan_arms(spec)
    assert sum(len(p.hparams) * spec.seeds for p in arms) == 30 and {p.config.num_updates for p in arms} == {1400}
    assert {(p.config.compute_dtype, p.config.conv_impl, p.config.core_impl, p.config.output_grad) for p in arms} == {
        ("bfloat16", "per-run", "fused", "compute")}


def test_the_evaluation_gets_what_is_left_before_the_units_end_and_unknown_units_are_refused():
    line = _command("pusher-ltq", END_S="1700", EVAL_S="280").stdout
    assert "s=$(( 1700 - $(date +%s) + $(cat runs/pixel-units/pusher-ltq/started) - 180 ));" in line
    assert "timeout -k 30 $(( s > 280 ? 280 : s < 120 ? 120 : s )) python -m cdjax.cli eval" in line
    for unit in ("pusher-ltq-cd2", "walker-ltq", "nothing"):
        done = _command(unit)
        assert done.returncode == 2 and "unknown" in done.stderr and not done.stdout
    assert not (ROOT / "runs" / "pixel-units" / "nothing").exists()
