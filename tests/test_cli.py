"""The `cdjax` command: options derived from the dataclasses, presets, bad input as one sentence with
exit status 2, an end-to-end sweep / resume / eval / plot, and Ctrl-C in a real process."""

import dataclasses
import json
import os
import pathlib
import re
import signal
import subprocess
import sys
import time

import jax
import pytest

import cdjax
from cdjax import Config, HParams, agents, io
from cdjax.cli import build_parser, main, sweep_spec
from cdjax.protocol import ConfigError
from cdjax.runner import SweepSpec, plan, prepare, preset_spec

from _shared import POINT, TINY_ARGS, fail_in_one_sentence
from conftest import CACHE

# A tiny point-mass sweep on the command line (2 updates per chunk of 192 env steps): tests/_shared.TINY_ARGS.
TINY = TINY_ARGS


def _fail(capsys, argv) -> str:
    return fail_in_one_sentence(capsys, main, argv)


@pytest.fixture
def other_run(tmp_path):
    """A directory that holds a run (run.json only; nothing compiled)."""
    out = tmp_path / "other"
    _, _, record = prepare(SweepSpec(out=out, config=POINT, seeds=2, total_env_steps=2000), resume=False)
    io.RunDir(out).create()
    io.RunDir(out).write(record)
    return out


@pytest.mark.parametrize("argv, words", [
    (["sweep", "--out", "{d}/a", "--env", "antt"], "Unknown env 'antt'"),
    (["sweep", "--out", "{d}/a", "--preset", "nope"], "Unknown preset 'nope'"),
    (["sweep", "--out", "{d}/a", "--bogus", "3"], "unknown option(s): --bogus 3; see `cdjax sweep --help`"),
    (["sweep", "--out", "{d}/a", "--alhpa", "1"], "unknown option(s): --alhpa"),
    (["sweep", "--out", "{d}/a", "--alpha", "0", "-1"], "--alpha must not be negative, got -1.0"),
    (["sweep", "--out", "{d}/a", "--gamma", "1.5"], "--gamma must be between 0 and 1"),
    (["sweep", "--out", "{d}/a", "--arms", "dreamer"], "Unknown arm 'dreamer'"),
    (["sweep", "--out", "{d}/a", "--steps", "1.5"], "not a whole number"),
    (["sweep", "--out", "{d}/a", "--horizon", "40", "--rollout-len", "80"], "longer than the minibatch sequences"),
    (["sweep", "--out", "{d}/a", "--encoder", "lstm"], "invalid choice: 'lstm'"),
    (["sweep", "--env", "point"], "the following arguments are required: --out"),
    (["sweep", "--out", "{d}", "--resume"], "holds no run (has no run.json)"),
    (["eval", "{d}"], "holds no run (has no run.json)"),
    (["eval", "{d}/missing"], "holds no run (does not exist); a run directory is the --out of a sweep"),
    (["plot", "{d}"], "holds no run"),
    (["frobnicate"], "invalid choice: 'frobnicate'"),
    (["sweep", "--out", "{d}/a", "--arms", "cd-kx"], "Unknown arm 'cd-kx'"),
    (["sweep", "--out", "{d}/a", "--arms", "model-free-k5"], "the model-free arm has no horizon"),
    (["sweep", "--out", "{d}/a", "--preset", "point", "--arms", "cd-k40"], "Arm 'cd-k40': horizon (k=40) is longer"),
    (["sweep", "--out", "{d}/a", "--preset", "point", "--phase-mpc-horizon", "0"],
     "MbMfPhase.mpc_horizon must be a positive integer, got 0"),
    (["sweep", "--out", "{d}/a", "--no-mbmf-phase", "--phase-mpc-horizon", "3"], "contradicts"),
    (["sweep", "--out", "{d}/a", "--preset", "point", "--arms", "mbmf", "--phase-random-steps", "10000"],
     "leaves no updates after the Mb-Mf phase"),
])
def test_bad_input_is_one_sentence_and_exit_2(capsys, tmp_path, argv, words):
    line = _fail(capsys, [a.replace("{d}", str(tmp_path)) for a in argv])
    assert words in line


def test_a_sweep_whose_evaluation_episodes_would_never_end_is_refused_before_anything_is_written(capsys, tmp_path,
                                                                                                 monkeypatch):
    from cdjax.evaluate import MAX_EVAL_EPISODE_STEPS
    from cdjax.runner import loop

    def compile_all(*args):
        raise AssertionError("compiled: the sweep was not refused at start-up")

    monkeypatch.setattr(loop, "compile_all", compile_all)
    out = tmp_path / "a"
    long = str(10 * MAX_EVAL_EPISODE_STEPS)
    argv = ["sweep", "--out", str(out), *TINY, "--arms", "cd", "--episode-length", long]
    line = _fail(capsys, argv)
    assert "(--episode-length" in line and "give a shorter --episode-length, or --no-final-eval" in line, line
    assert not out.exists()


def test_out_holding_another_run_is_refused(capsys, other_run):
    before = (other_run / "run.json").read_text()
    line = _fail(capsys, ["sweep", "--out", str(other_run), "--preset", "point"])
    assert "already holds a run; continue it with --resume" in line
    line = _fail(capsys, ["sweep", "--out", str(other_run), "--resume", "--horizon", "3"])
    assert "--horizon cannot be changed" in line
    assert (other_run / "run.json").read_text() == before  # nothing overwritten
    (other_run / "run.json").write_text("{not json")
    assert "is not valid JSON" in _fail(capsys, ["sweep", "--out", str(other_run), "--resume"])


def test_options_are_derived_from_the_dataclasses(capsys):
    with pytest.raises(SystemExit) as info:
        main(["sweep", "--help"])
    assert info.value.code == 0
    text = " ".join(capsys.readouterr().out.split())
    for field in dataclasses.fields(Config):
        flag = "--" + field.name.replace("_", "-")
        listed = re.search(re.escape(flag) + r"(?![\w-])", text) is not None  # (--arm is not --arms)
        assert listed == (field.name not in ("arm", "num_updates")), flag
    for field in dataclasses.fields(HParams):
        assert f"--{field.name.replace('_', '-')} X [X ...]" in text
    assert "environments stepped in parallel per seed (default 2048)" in text  # the comment in config.py
    assert "weight of the consistency loss" in text
    assert "cpu-smoke" in text


def test_envs_lists_every_env_name_and_marks_the_missing_extra(capsys, monkeypatch):
    from cdjax import envs
    from cdjax.envs import playground, rewards

    def listed() -> dict[str, str]:
        main(["envs"])
        rows = [line.split(None, 1) for line in capsys.readouterr().out.splitlines()]
        return {name: about for name, about in rows}

    names = listed()
    assert list(names) == list(envs.available_envs())
    assert set(playground.NAMES) | {"ant", "point", "swimmer"} <= set(names)
    assert names["ant"].startswith("Brax, MJX") and names["dmc-cheetah-run"].startswith("MuJoCo Playground CheetahRun")
    for name, about in names.items():  # the MPC mark where cdjax.envs.rewards writes the task's reward, only there
        assert ("true reward for MPC" in about) == (rewards.reward_fn(name) is not None), name
    monkeypatch.setitem(sys.modules, "mujoco_playground", None)  # what an install without the extra sees
    hidden = listed()
    assert list(hidden) == list(names)
    for name, about in hidden.items():
        assert ('pip install -e ".[playground]"' in about) == name.startswith("dmc-"), name
    with pytest.raises(SystemExit):
        main(["sweep", "--help"])
    assert "`cdjax envs` lists them" in capsys.readouterr().out  # where sweep's help says the names are


def test_help_comes_from_the_field_comments_read_with_the_tokenizer():
    import dataclasses as dc

    from cdjax.options import field_docs

    @dc.dataclass
    class Tricky:
        text: str = "a # not a comment"  # the comment, not the string
        widths: tuple[int, ...] = (  # a default over two lines
            64, 64)
        bare: int = 1
        long: str = "x"  # a comment that goes on
        # on the line below (a continuation)

        # a header over the next field, after a blank line: no field's
        last: int = 2  # its own
        # and its continuation

        def method(self):  # a method's comment is no field's
            return self.bare

    assert field_docs(Tricky) == {"text": "the comment, not the string", "widths": "a default over two lines",
                                  "bare": "", "long": "a comment that goes on on the line below (a continuation)",
                                  "last": "its own and its continuation"}


def test_precedence_defaults_then_preset_then_flags():
    obs = agents.get("obs")
    parse = lambda *argv: sweep_spec(build_parser().parse_args(["sweep", "--out", "x", *argv]), obs)  # noqa: E731
    spec = parse("--preset", "cpu-smoke", "--num-envs", "16", "--alpha", "0", "0.5", "--seeds", "2")
    assert spec.config.env == "inverted_pendulum" and spec.config.rollout_len == 32  # preset
    assert spec.config.num_envs == 16 and spec.grid["alpha"] == (0.0, 0.5) and spec.seeds == 2  # flags
    assert spec.grid["lr_policy"] == (1e-3,) and spec.arms == ("mbmf", "cd")  # preset
    assert spec.config.encoder_dim == 32 and spec.config.cc_windows == Config().cc_windows  # preset, default
    spec = parse("--env", "point", "--steps", "50_000")  # the env's own preset applies without --preset
    assert spec.config.num_envs == 32 and spec.total_env_steps == 50_000 and spec.seeds == 2
    spec = parse("--env", "inverted_double_pendulum", "--steps", "5e6")  # no preset of that name: defaults
    assert spec.config.num_envs == Config().num_envs and spec.grid == {} and spec.total_env_steps == 5_000_000
    spec = parse("--preset", "ant", "--env", "halfcheetah")
    assert spec.config.env == "halfcheetah" and spec.config.horizon == 20 and spec.grid["reward_scale"] == (10.0,)


def test_preset_spec_is_the_sweep_commands_spec_as_a_function():
    """`cdjax.runner.preset_spec` (a notebook's way to a preset) gives the spec `cdjax sweep` builds from the same
    options, the env's own preset included; `SweepSpec(...)` alone applies none; a phase contradicted or an unknown
    preset is one sentence."""
    from cdjax.agents.obs import MbMfPhase

    obs = agents.get("obs")
    parse = lambda *argv: sweep_spec(build_parser().parse_args(["sweep", "--out", "x", *argv]), obs)  # noqa: E731
    assert preset_spec("x", config={"env": "ant"}, seeds=5) == parse("--env", "ant", "--seeds", "5")
    assert preset_spec("x") == parse()  # no env: the default env's preset
    assert preset_spec("x", preset="cpu-smoke", config={"num_envs": 16}, hparams={"alpha": (0.0, 0.5), "gamma": 0.9},
                       phase={"mpc_candidates": 64}) == parse("--preset", "cpu-smoke", "--num-envs", "16", "--alpha",
                                                              "0", "0.5", "--gamma", "0.9", "--phase-mpc-candidates",
                                                              "64")
    assert preset_spec("x", config={"env": "ant"}).phase is None
    assert preset_spec("x", config={"env": "point"}, phase_on=True).phase == MbMfPhase()
    assert SweepSpec(out="x", config=Config(env="ant")).total_env_steps != preset_spec("x").total_env_steps
    with pytest.raises(ConfigError, match="contradicts"):
        preset_spec("x", phase={"mpc_candidates": 64}, phase_on=False)
    with pytest.raises(ConfigError, match="Unknown preset 'nope'"):
        preset_spec("x", preset="nope")


def test_an_arm_the_grid_does_not_apply_to_runs_once_and_the_plan_names_the_field():
    from cdjax.runner.plan import plan_arms

    obs = agents.get("obs")
    spec = sweep_spec(build_parser().parse_args(["sweep", "--out", "x", "--preset", "point", "--arms", "model-free",
                                                  "cd", "--alpha", "0", "1", "--lr-policy", "1e-3", "3e-4"]), obs)
    free, cd = plan_arms(spec, obs)
    assert free.ignored == ("alpha",) and len(free.hparams) == 2  # its own grid (lr_policy) still spans its runs
    assert cd.ignored == () and len(cd.hparams) == 4


def test_phase_options():
    from cdjax.agents.obs import MbMfPhase

    obs = agents.get("obs")
    parse = lambda *argv: sweep_spec(build_parser().parse_args(["sweep", "--out", "x", *argv]), obs)  # noqa: E731
    assert parse("--preset", "point").phase is None  # off unless asked for (or a preset says so)
    assert parse("--preset", "point", "--mbmf-phase").phase == MbMfPhase()
    spec = parse("--preset", "point", "--phase-mpc-candidates", "64", "--phase-relabel", "false",
                 "--arms", "model-free", "mbmf", "cd-k2")
    assert spec.phase == MbMfPhase(mpc_candidates=64, relabel=False) and spec.arms == ("model-free", "mbmf", "cd-k2")


def test_sweep_then_resume_longer_then_eval_and_plot(tmp_path, capsys, monkeypatch):
    out = tmp_path / "run"
    main(["sweep", *TINY, "--alpha", "0", "1", "--steps", str(4 * 192), "--bootstrap-reps", "50", "--out", str(out)])
    captured = capsys.readouterr()
    assert "compile" in captured.err and "Trained in" in captured.err
    run = json.loads((out / "run.json").read_text())
    assert [a["name"] for a in run["arms"]] == ["mbmf", "cd"]
    assert run["arms"][1]["hp_labels"] == ["alpha=0.0", "alpha=1.0"]
    assert run["command"].startswith("cdjax sweep --env point")
    (code,) = run["code"]  # the code it was trained with: this checkout's commit when cdjax is imported from one
    head = subprocess.run(["git", "-C", str(pathlib.Path(cdjax.__file__).parent), "rev-parse", "HEAD"],
                          capture_output=True, text=True)
    assert code["cdjax"] == cdjax.__version__ and code["jax"] == jax.__version__
    assert code["commit"] == (head.stdout.strip() if head.returncode == 0 else None)
    assert isinstance(code["modified"], bool) if code["commit"] else code["modified"] is None
    assert "matmul_precision" not in code  # JAX's default precision: the key is absent (records of before match)
    rows = [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines()]
    assert len(rows) == (1 + 2) * 2 * 4 and max(r["update"] for r in rows) == 4
    assert sorted(p.name for p in (out / "checkpoints" / "cd").iterdir() if p.name.isdigit()) == ["2", "4"]
    assert list((out / "tb" / "cd" / "alpha=1.0" / "seed1").glob("events.out.tfevents.*"))

    # a time limit already past when the programs are compiled: stopped before any chunk, exit 75, resumable
    capsys.readouterr()
    with pytest.raises(SystemExit) as info:
        main(["sweep", "--out", str(out), "--resume", "--steps", str(6 * 192), "--no-progress", "--time-limit", "1e-6"])
    assert info.value.code == 75
    assert f"Continue with: cdjax sweep --out {out} --resume" in capsys.readouterr().err
    assert len((out / "metrics.jsonl").read_text().splitlines()) == (1 + 2) * 2 * 4

    main(["sweep", "--out", str(out), "--resume", "--steps", str(6 * 192), "--no-progress"])
    rows = [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines()]
    assert len(rows) == (1 + 2) * 2 * 6
    assert len({(r["arm"], r["hp"], r["seed"], r["update"]) for r in rows}) == len(rows)  # no update twice
    resumed = json.loads((out / "run.json").read_text())
    assert resumed["num_updates"] == 6
    assert resumed["code"] == [code]  # resumed with the same code: nothing added
    assert sorted(p.name for p in (out / "checkpoints" / "mbmf").iterdir() if p.name.isdigit()) == ["4", "6"]

    pytest.importorskip("cdjax.evaluate")
    capsys.readouterr()
    main(["eval", str(out), "--episodes", "3"])
    text = capsys.readouterr().out
    assert "cd / alpha=1.0" in text and "mbmf / default" in text
    evals = [json.loads(line) for line in (out / "eval.jsonl").read_text().splitlines()]
    assert {(e["arm"], e["hp"], e["seed"]) for e in evals if e["episodes"] == 3} == {
        ("mbmf", "default", 0), ("mbmf", "default", 1), ("cd", "alpha=0.0", 0), ("cd", "alpha=0.0", 1),
        ("cd", "alpha=1.0", 0), ("cd", "alpha=1.0", 1)}
    assert all(e["update"] == 6 and len(e["returns"]) == 3 for e in evals if e["episodes"] == 3)

    pytest.importorskip("cdjax.plots")
    for name in ("summary.md", "summary.csv", "plots/return.png"):
        (out / name).unlink()
    main(["plot", str(out), "--bootstrap-reps", "50"])  # the files, not the intervals' precision, are checked
    for name in ("summary.md", "summary.csv", "plots/return.png"):
        assert (out / name).stat().st_size > 0, name
    assert "cd" in (out / "summary.md").read_text()

    # resumed with other code: its record is added after the first
    other = dict(code, commit="0" * 40, modified=True)
    monkeypatch.setattr(plan, "code_record", lambda: other)
    main(["sweep", "--out", str(out), "--resume", "--steps", str(8 * 192), "--no-progress"])
    assert json.loads((out / "run.json").read_text())["code"] == [code, other]


def test_ctrl_c_saves_a_checkpoint_and_says_how_to_resume(tmp_path):
    out = tmp_path / "sigint"
    env = dict(os.environ, CDJAX_JAX_CACHE=str(CACHE), JAX_PLATFORMS="cpu")
    cmd = [sys.executable, "-m", "cdjax.cli", "sweep", *TINY, "--arms", "cd", "--chunk-updates", "1",
           "--steps", str(100_000 * 192), "--out", str(out)]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    try:
        deadline = time.time() + 240
        while time.time() < deadline and proc.poll() is None:
            metrics = out / "metrics.jsonl"
            if metrics.exists() and metrics.stat().st_size > 0:
                break
            time.sleep(0.5)
        assert proc.poll() is None, proc.communicate()[1][-2000:]
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130, err[-2000:]
    assert "Traceback" not in err
    assert f"Resume with: cdjax sweep --out {out} --resume" in err
    steps = sorted(int(p.name) for p in (out / "checkpoints" / "cd").iterdir() if p.name.isdigit())
    rows = [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines()]
    assert steps and steps[-1] == max(r["update"] for r in rows)  # the logs end where the checkpoint is
    assert steps[-1] < 100_000
