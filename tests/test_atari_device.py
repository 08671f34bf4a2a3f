"""experiments/atari/device.sh's ALE tier units: each unit's command line (`--print-command`, nothing started or
installed) names the sweep it should, and a unit is started once, polled and packed into $OUT (a fake python: no
ale-py, no JAX)."""

import pathlib
import shlex
import subprocess
import tarfile
import time

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "experiments" / "atari" / "device.sh"


def _print_command(unit: str, **env) -> subprocess.CompletedProcess:
    return subprocess.run(["bash", str(SCRIPT), "--print-command", unit], cwd=ROOT, text=True, capture_output=True,
                          timeout=30, env={"PATH": "/usr/bin:/bin", **env})


def _sweep_argv(line: str) -> list[str]:
    """The `cdjax.cli sweep` arguments of a unit's command line (its first command)."""
    first = shlex.split(line.split(";")[0])
    return first[first.index("cdjax.cli") + 1:]


@pytest.mark.parametrize("game", ["breakout", "seaquest", "mspacman", "frostbite"])
def test_a_units_sweep_has_its_preset_arms_seeds_budget_and_time_limit(game):
    from cdjax import agents
    from cdjax.cli import build_parser

    done = _print_command(f"ale-{game}")
    assert done.returncode == 0, done.stderr
    line = done.stdout.strip()
    argv = _sweep_argv(line)

    def values(flag):
        i = argv.index(flag) + 1
        return argv[i:next((j for j in range(i, len(argv)) if argv[j].startswith("--")), len(argv))]

    assert argv[0] == "sweep" and values("--setting") == ["atari"] and values("--preset") == [game]
    assert values("--arms") == ["a2c", "a2c-cd"] and values("--seeds") == ["3"] and values("--steps") == ["1000000"]
    assert values("--time-limit") == ["1080"] and "--no-final-eval" in argv
    run = f"runs/atari-units/ale-{game}/{game}"
    assert values("--out") == [run]
    # the hang guard is the time limit + 120 s; then every run is evaluated, plotted and reported
    assert line.startswith("timeout -s INT -k 60 1200 python -m cdjax.cli sweep")
    assert f"python -m cdjax.cli eval {run} --episodes 100;" in line
    # the evaluation: up to 360 s, ending 120 s before 1380 s from the unit's start (plot and report: 50 s each)
    assert f"s=$(( 1380 - $(date +%s) + $(cat runs/atari-units/ale-{game}/started) - 120 ));" in line
    assert "timeout -k 10 $(( s > 360 ? 360 : s < 60 ? 60 : s )) python -m cdjax.cli eval" in line
    assert f"python -m experiments.atari.report {run} --out runs/atari-units/ale-{game}/report" in line
    args = vars(build_parser(agents.get("atari")).parse_args(argv))  # each option is the CLI's (the config: ale-py)
    assert (args["preset"], args["time_limit"], args["spec.seeds"]) == (game, 1080, 3)
    assert args["spec.arms"] == ["a2c", "a2c-cd"]
    assert (args["spec.total_env_steps"], args["spec.final_eval"], args["spec.progress"]) == (1_000_000, False, False)


def test_the_units_sweep_plans_two_arms_of_three_seeds_at_one_million_agent_steps():
    pytest.importorskip("ale_py", reason="the ALE config needs the extra `atari` (ale-py)")
    from cdjax import agents
    from cdjax.cli import build_parser, sweep_spec
    from cdjax.runner.plan import plan_arms

    argv = _sweep_argv(_print_command("ale-breakout").stdout)
    setting = agents.get("atari")
    plans = plan_arms(sweep_spec(build_parser(setting).parse_args(argv), setting))
    assert [p.name for p in plans] == ["a2c", "a2c-cd"]
    assert all(p.config.num_updates == 12_500 and p.config.num_envs == 16 for p in plans)  # 1M / (16 x 5)


def test_the_limits_follow_the_environment_and_unknown_units_are_refused():
    line = _print_command("ale-frostbite", LIMIT_S="900", END_S="1300", EVAL_S="200", ALE_STEPS="500000").stdout
    argv = _sweep_argv(line)
    assert argv[argv.index("--time-limit") + 1] == "900" and argv[argv.index("--steps") + 1] == "500000"
    assert "timeout -s INT -k 60 1020 " in line
    assert "s=$(( 1300 - $(date +%s) + $(cat runs/atari-units/ale-frostbite/started) - 120 ));" in line
    assert "timeout -k 10 $(( s > 200 ? 200 : s < 60 ? 60 : s )) python -m cdjax.cli eval" in line
    for unit in ("ale-pong", "ale-"):
        done = _print_command(unit)
        assert done.returncode == 2 and "unknown ALE unit" in done.stderr and not done.stdout
    assert not (ROOT / "runs" / "atari-units" / "ale-pong").exists()


def test_a_unit_starts_once_is_polled_and_packs_its_files_into_out(tmp_path):
    """python and python3 are fakes: imports succeed (nothing to install), a module run prints its arguments."""
    bin_dir, out = tmp_path / "bin", tmp_path / "out"
    bin_dir.mkdir()
    for name in ("python", "python3"):
        fake = bin_dir / name
        fake.write_text('#!/usr/bin/env bash\nif [ "$1" = -c ]; then exit 0; fi\necho "ran python $*"\nsleep 1\n')
        fake.chmod(0o755)
    env = {"PATH": f"{bin_dir}:/usr/bin:/bin", "OUT": str(out), "SITE": str(tmp_path / "site")}

    def call(wait_s):
        return subprocess.run(["bash", str(SCRIPT), "ale-seaquest", str(wait_s)], cwd=tmp_path, text=True,
                              capture_output=True, timeout=60, env=env).stdout

    first = call(0)  # starts the unit and returns at once
    assert "STARTED" in first and "RUNNING" in first and "bash experiments/atari/device.sh ale-seaquest" in first
    work = tmp_path / "runs" / "atari-units" / "ale-seaquest"
    deadline = time.monotonic() + 30
    while not (work / "exit_code").exists() and time.monotonic() < deadline:
        time.sleep(0.2)
    last = call(30)  # a poll: not started again, packs
    assert "STARTED" not in last and "DONE: unit ale-seaquest, exit status 0" in last
    log = (work / "unit.log").read_text().splitlines()
    modules = ["cdjax.cli sweep", "cdjax.cli eval", "cdjax.cli plot", "experiments.atari.report"]
    assert [line.startswith(f"ran python -m {m} ") for line, m in zip(log, modules)] == [True] * 4 and len(log) == 4
    assert sorted(p.name for p in out.iterdir()) == ["ale-seaquest.log", "ale-seaquest.tar.gz"]  # no report made
    with tarfile.open(out / "ale-seaquest.tar.gz") as tar:
        assert "seaquest/log.txt" in tar.getnames()


def test_carry_size_counts_the_tracked_the_untracked_not_ignored_and_the_carried_files(tmp_path):
    """experiments/lease.sh carry_size: what a device call would send, against its 64 MiB, counted as the device tool
    counts (each file a tar member: a 512-byte header and its bytes in whole 512-byte blocks)."""
    lease = ROOT / "experiments" / "lease.sh"
    subprocess.run(["git", "init", "-q", str(tmp_path)], check=True)
    (tmp_path / ".gitignore").write_text("/.whl-x/\n")  # 9 bytes
    (tmp_path / "tracked").write_bytes(b"t" * 1000)
    subprocess.run(["git", "-C", str(tmp_path), "add", ".gitignore", "tracked"], check=True)
    (tmp_path / "untracked").write_bytes(b"u" * 500)
    (tmp_path / ".whl-x").mkdir()
    (tmp_path / ".whl-x" / "w.whl").write_bytes(b"w" * 2000)

    def size(*carry):
        done = subprocess.run(["bash", "-c", f". {lease}; carry_size {' '.join(carry)}"], cwd=tmp_path, text=True,
                              capture_output=True, timeout=30)
        return done.returncode, done.stdout

    member = lambda n: 512 + -(-n // 512) * 512  # noqa: E731
    sent = member(9) + member(1000) + member(500)  # 3,584
    assert size() == (0, f"{sent:,} bytes (0.0 MiB) would travel, {64 * 2**20 - sent:,} bytes under 64 MiB\n")
    assert size(".whl-x")[1].startswith(f"{sent + member(2000):,} bytes")
    with open(tmp_path / ".whl-x" / "big.whl", "wb") as f:  # sparse: 64 MiB on paper, nothing on disk
        f.truncate(64 * 2**20)
    rc, out = size(".whl-x")
    over = sent + member(2000) + member(64 * 2**20) - 64 * 2**20
    assert rc == 1 and out.endswith(f"would travel: {over:,} bytes over 64 MiB\n")
