"""A run directory is never destroyed or misread, and every setting and the library refuse bad values alike.

One tiny finished run per setting (the point mass, MinAtar Breakout at cpu-minatar's sizes, the pixel setting on
test_pixel_model's synthetic world: the programs other test files compile, so JAX's persistent cache serves
them) is copied for each case. Each case asserts the exit status, the sentence, and that the directory's files
are byte for byte as they were wherever nothing should change:

- checkpoints are evidence: one of another run than run.json's (a changed shape, seed count, setting) is refused
  before anything is read or written; an arm none of whose checkpoints can be read is trained again only with
  --restart-arm, its checkpoints kept (an unreadable latest one is moved aside, never deleted: test_runner);
  --steps below what is done is refused;
- one validation per setting: every field of every Config and HParams refuses a bad value with one ConfigError
  naming it, from the constructor, the trainer's init and the command line alike (the same code);
- non-finite training is counted per run, said while training and flagged in the summary, in all three settings;
- every reader of the run directory skips (plot), trims (resume) or refuses (run.json) what it cannot read;
- SIGTERM is the first Ctrl-C (checkpoint, one sentence, exit 143) and a resumed run equals an uninterrupted one;
  every interrupt's sentence is true for its command and names the directory;
- paths and the cache directory are checked before anything is written.
"""

from __future__ import annotations

import contextlib
import dataclasses
import gzip
import json
import lzma
import math
import os
import pathlib
import shutil
import signal
import subprocess
import sys
import threading
import time
from io import StringIO

import jax
import numpy as np
import pytest

from cdjax import Config, ConfigError, HParams, agents, io, make_train, stack_hparams
from cdjax.agents.atari import AtariConfig, AtariHParams
from cdjax.agents.pixel import PixelConfig, PixelHParams
from cdjax.checks import Count, Flag, Real, Text, Widths
from cdjax.cli import main
from cdjax.runner import SweepSpec, run_sweep

from _shared import POINT, TINY_ARGS, fail_in_one_sentence, logged_rows
from conftest import CACHE
from test_pixel_model import HP as PIXEL_HP  # (importing it registers the synthetic pixel setting)

OBS = [*TINY_ARGS, "--arms", "cd", "--alpha", "0", "1", "--eval-every", "1", "--eval-episodes", "2",
       "--bootstrap-reps", "50"]  # test_failures' (and test_cli's) programs: 4 runs, chunks of 2 updates
OBS_STEPS = str(4 * 192)
ATARI = ["--setting", "atari", "--preset", "cpu-minatar", "--arms", "a2c-cd", "--chunk-updates", "4", "--no-final-eval",
         "--bootstrap-reps", "50", "--no-progress"]  # test_atari_cli's a2c-cd sweep: 2 runs, chunks of 4 updates
ATARI_STEPS = str(8 * 128)
PIXEL = ["--setting", "pixel-synthetic", "--preset", "pixel-tiny", "--arms", "ltq-cd", "--encoder", "l2",
         "--conv-layers", "2", "--imitation-coef", str(PIXEL_HP.imitation_coef), "--bootstrap-reps", "50",
         "--no-progress", "--no-final-eval"]  # test_pixel_model's sweep: 2 runs, chunks of 3 updates
PIXEL_STEPS = str(3 * 12)
LR = {"obs": "--lr-policy", "atari": "--lr", "pixel": "--lr"}
GOOD_LR = {"obs": None, "atari": None, "pixel": str(PIXEL_HP.lr)}
# The finished runs of atari and pixel are trained at a learning rate of 1e30 (finite, so allowed): the parameters
# blow up and every run skips steps, which the non-finite test reads; the other cases only need a finished run.
FIXTURE_LR = {"obs": None, "atari": "1e30", "pixel": "1e30"}


def _argv(setting: str, out, lr: str | None = None, extra=()) -> list[str]:
    args, steps = {"obs": (OBS, OBS_STEPS), "atari": (ATARI, ATARI_STEPS), "pixel": (PIXEL, PIXEL_STEPS)}[setting]
    lr = lr or GOOD_LR[setting]
    return ["sweep", *args, *([LR[setting], lr] if lr else []), "--steps", steps, *extra, "--out", str(out)]


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """setting -> a finished run directory (built on first use, once per module); `runs.said[setting]` is what its
    sweep wrote on stderr (with a progress line: the atari and pixel runs are the non-finite ones)."""
    made: dict[str, pathlib.Path] = {}

    def get(setting: str) -> pathlib.Path:
        if setting not in made:
            out = tmp_path_factory.mktemp(setting) / "run"
            argv = _argv(setting, out, lr=FIXTURE_LR[setting])
            with contextlib.redirect_stderr(StringIO()) as err:
                main([a for a in argv if a != "--no-progress"] if FIXTURE_LR[setting] else argv)
                if FIXTURE_LR[setting]:  # these sweeps stop before their evaluation and plots
                    main(["plot", str(out), "--bootstrap-reps", "50"])
            get.said[setting] = err.getvalue()
            made[setting] = out
        return made[setting]

    get.said = {}
    return get


def _copy(runs, setting, tmp_path) -> pathlib.Path:
    out = tmp_path / "run"
    shutil.copytree(runs(setting), out)
    return out


def snapshot(path: pathlib.Path) -> dict[str, bytes]:
    """Every file under `path` with its bytes (checkpoints, logs, run.json, summary, plots)."""
    return {str(p.relative_to(path)): p.read_bytes() for p in sorted(path.rglob("*")) if p.is_file()}


def _edit_run(out: pathlib.Path, change) -> None:
    run = json.loads((out / "run.json").read_text())
    change(run)
    (out / "run.json").write_text(json.dumps(run, indent=2) + "\n")


def _set_config(field, value):
    """A Config field changed everywhere run.json records it (the base config and each arm's): the record stays
    self-consistent, so only the checkpoints can tell."""
    def change(run):
        run["base_config"][field] = value
        for arm in run["arms"]:
            arm["config"][field] = value
    return change


def _set_hparam(field, value):
    """A hyper-parameter of one value changed in the grid and in every run's record (labels do not show it)."""
    def change(run):
        run["grid"][field] = [value]
        for arm in run["arms"]:
            for hp in arm["hparams"]:
                hp[field] = value
    return change


def _set_seeds(n):
    def change(run):
        run["seeds"] = n
    return change


def _fails(capsys, argv) -> str:
    """Exit status 2 after progress sentences, the last line the one `cdjax:` sentence, no traceback."""
    with pytest.raises(SystemExit) as info:
        main(argv)
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.strip()]
    assert info.value.code == 2 and "Traceback" not in err, err
    assert [line for line in lines if line.startswith("cdjax:")] == lines[-1:] and lines[-1].endswith("."), err
    return lines[-1]


# ---------------------------------------------------------------------------------------------------
# Checkpoints are evidence


@pytest.mark.parametrize("setting, change, words", [
    ("obs", _set_config("policy_hidden", [32]), "it was trained with policy_hidden [16] where run.json has [32]"),
    ("obs", _set_hparam("lr_policy", 0.002), "its alpha=0.0 runs were trained with lr_policy 0.001 where run.json "
                                             "has 0.002"),
    ("obs", _set_seeds(3), "it holds 4 runs (2 seeds x 2 hyper-parameter combinations) where run.json asks for 6 "
                           "runs (3 seeds x 2 hyper-parameter combinations)"),
    ("atari", _set_config("latent", 32), "it was trained with latent 64 where run.json has 32"),
    ("atari", _set_seeds(3), "it holds 2 runs (2 seeds x 1 hyper-parameter combinations) where run.json asks for 3"),
    ("pixel", _set_config("conv_channels", 8), "it was trained with conv_channels 4 where run.json has 8"),
    ("pixel", _set_seeds(1), "it holds 2 runs (2 seeds x 1 hyper-parameter combinations) where run.json asks for 1"),
])
def test_a_checkpoint_of_another_run_is_refused_and_nothing_is_touched(runs, tmp_path, capsys, setting, change,
                                                                      words):
    """run.json edited (what a changed default shape would also do) under a finished run: resume and eval refuse in
    one sentence naming the difference, before anything is read into memory or written (the issue's data loss:
    every checkpoint deleted, the logs cut and the run trained again; the fabricated third seed)."""
    out = _copy(runs, setting, tmp_path)
    _edit_run(out, change)
    before = snapshot(out)
    line = _fails(capsys, ["sweep", "--out", str(out), "--resume"])
    assert f"checkpoints/{json.loads((out / 'run.json').read_text())['arms'][0]['name']}/" in line, line
    assert "does not belong to the run asked for" in line and words in line and "nothing was changed" in line, line
    assert snapshot(out) == before
    if setting == "obs":  # eval reads the same way
        assert words in _fails(capsys, ["eval", str(out), "--episodes", "2"])
        assert snapshot(out) == before


def test_an_older_checkpoint_without_its_run_record_is_checked_leaf_by_leaf(runs, tmp_path, capsys, monkeypatch):
    """A checkpoint written before runs and leaf shapes were recorded: orbax's own metadata says the shapes (read
    with a relative --out, as a user types it)."""
    out = _copy(runs, "obs", tmp_path)
    monkeypatch.chdir(tmp_path)
    for record in (out / "checkpoints" / "cd").glob("*/progress/metadata"):
        progress = json.loads(record.read_text())
        del progress["run"], progress["layout"]["shapes"]
        record.write_text(json.dumps(progress))
    _edit_run(out, _set_config("policy_hidden", [32]))
    before = snapshot(out)
    line = _fails(capsys, ["sweep", "--out", "run", "--resume"])
    assert line.startswith("cdjax: checkpoint run/checkpoints/cd/4 does not belong to the run asked for: its leaf "
                           "params.policy.params.MLP_0.Dense_0.bias is [4, 16] float32 where this run's state has "
                           "[4, 32] float32; nothing was changed"), line
    assert snapshot(out) == before


def _damage(checkpoint: pathlib.Path, what: str) -> None:
    for path in (checkpoint / what).rglob("*"):
        if path.is_file():
            path.write_bytes(b"\x00garbage" * 3)


def test_no_readable_checkpoint_stops_until_the_arm_is_restarted_and_nothing_is_deleted(runs, tmp_path, capsys):
    out = _copy(runs, "obs", tmp_path)
    for step in ("2", "4"):
        _damage(out / "checkpoints" / "cd" / step, "progress")
    before = snapshot(out)
    line = _fails(capsys, ["sweep", "--out", str(out), "--resume"])
    assert line.startswith(f"cdjax: {out}: no checkpoint of arm 'cd' can be read (4: ") and "2: " in line, line
    assert "nothing was changed: add --restart-arm cd to train it again from update 0" in line
    assert snapshot(out) == before
    for bad in (["--restart-arm", "mbmf"], ["--restart-arm"]):
        assert "--restart-arm" in _fails(capsys, ["sweep", "--out", str(out), "--resume", *bad])
    assert snapshot(out) == before

    main(["sweep", "--out", str(out), "--resume", "--restart-arm", "cd"])  # trained again, the same numbers
    said = capsys.readouterr().err
    assert "Restarting arm cd from update 0; its checkpoints were moved aside (4.restarted, 2.restarted)" in said
    assert logged_rows(out) == logged_rows(runs("obs"))
    for step in ("2", "4"):  # kept, byte for byte
        kept = snapshot(out / "checkpoints" / "cd" / f"{step}.restarted")
        assert kept == {k.split("/", 3)[3]: v for k, v in before.items() if k.startswith(f"checkpoints/cd/{step}/")}


def test_logged_updates_without_a_checkpoint_are_not_trained_over(runs, tmp_path, capsys):
    out = _copy(runs, "obs", tmp_path)
    shutil.rmtree(out / "checkpoints")
    before = snapshot(out)
    line = _fails(capsys, ["sweep", "--out", str(out), "--resume"])
    assert "arm 'cd' has 16 logged rows but no checkpoint; nothing was changed: add --restart-arm cd" in line
    assert snapshot(out) == before


@pytest.mark.parametrize("setting", ["obs", "atari"])
def test_resume_with_steps_below_what_is_done_is_refused(runs, tmp_path, capsys, setting):
    out = _copy(runs, setting, tmp_path)
    before = snapshot(out)
    per_update = 192 if setting == "obs" else 128
    line = _fails(capsys, ["sweep", "--out", str(out), "--resume", "--steps", str(2 * per_update)])
    done = 4 if setting == "obs" else 8
    assert f"has done {done} updates, more than the 2 that --steps gives it; nothing was changed: give --steps of at " \
           f"least {done * per_update:,}" in line, line
    assert snapshot(out) == before


# ---------------------------------------------------------------------------------------------------
# One validation per setting


SETTINGS = {"obs": (Config, HParams), "atari": (AtariConfig, AtariHParams), "pixel": (PixelConfig, PixelHParams)}


def _config_module(setting):
    return sys.modules[agents.get(setting).config_type.__module__]


@pytest.mark.parametrize("setting", SETTINGS)
def test_every_field_refuses_a_bad_value_with_one_config_error_naming_it(setting):
    """Each numeric field is declared with its range; every field refuses values of the wrong kind (None, text,
    a list, NaN, a float for an integer, a bool) and below its range with one ConfigError, never another
    exception, from the constructor (the CLI and the library build Configs the same way)."""
    config_type, hparams_type = SETTINGS[setting]
    module = _config_module(setting)
    kinds = module.FIELDS.kinds
    numeric = {f.name for f in dataclasses.fields(config_type) if f.type in ("int", "float", int, float)}
    assert numeric <= set(module.FIELDS.declared), numeric - set(module.FIELDS.declared)
    base = config_type(env="point") if setting == "obs" else config_type()
    for name, kind in kinds.items():
        bad = [None, [1], math.nan] + ([] if isinstance(kind, Text) else ["x"]) + (
            [] if isinstance(kind, Flag) else [True])
        if isinstance(kind, Count) and kind.low is not None:
            bad += [kind.low - 1 if not kind.zero else -1, 2.5] + ([kind.high + 1] if kind.high else [])
        elif isinstance(kind, Real):
            bad += [kind.allowed.low - 1 if math.isfinite(kind.allowed.low) else math.inf, math.inf]
        elif isinstance(kind, Widths):
            bad += [(), (0,), (2.5,)]
        for value in bad:
            with pytest.raises(ConfigError) as info:
                dataclasses.replace(base, **{name: value})
            text = str(info.value)
            assert name in text and text.endswith(".") and ". " not in text.rstrip("."), (name, value, text)
    for field in dataclasses.fields(hparams_type):
        for value in (math.nan, math.inf, -1.0 if module.HP_RANGES.ranges[field.name].low >= 0 else math.nan):
            with pytest.raises(ConfigError, match=f"--{field.name.replace('_', '-')} must"):
                module.HP_RANGES.check(hparams_type(**{field.name: value}))


@pytest.mark.parametrize("setting, argv, words", [
    ("pixel", ["--min-std", "-1"], "min_std must be positive, got -1.0"),
    ("pixel", ["--burn-in", "-1"], "burn_in must be a non-negative integer, got -1"),
    ("pixel", ["--conv-layers", "-1"], "conv_layers must be an integer from 1 to 16, got -1"),
    ("pixel", ["--image-size", "0"], "image_size must be a positive integer, got 0"),
    ("pixel", ["--conv-channels", "0"], "conv_channels must be a positive integer, got 0"),
    ("pixel", ["--policy-hidden", "0"], "policy_hidden must be a non-empty tuple of positive integers, got (0,)"),
    ("pixel", ["--mlp", "0"], "mlp must be a positive integer, got 0"),
    ("pixel", ["--lr", "0"], "--lr must be positive, got 0.0"),
    ("pixel", ["--cc-windows", "9"], "cc_windows=9 is more than the 4 k-step windows a sequence of seq_len=6 holds"),
    ("atari", ["--num-envs", "0"], "num_envs must be a positive integer, got 0"),
    ("atari", ["--sticky-prob", "1"], "sticky_prob must be in [0, 1), got 1.0"),
    ("atari", ["--rms-decay", "2"], "--rms-decay must be between 0 and 1, got 2.0"),
    ("atari", ["--lr", "nan"], "--lr must be finite, got nan"),
    ("obs", ["--lr-policy", "-1"], "--lr-policy must not be negative, got -1.0"),
    ("obs", ["--gamma", "5"], "--gamma must be between 0 and 1, got 5.0"),
    ("obs", ["--alpha", "0", "nan"], "--alpha must be finite, got nan"),
    ("obs", ["--alpha", "1e40"], "--alpha must be finite in float32, which it trains in"),
    ("obs", ["--max-grad-norm", "1e-50"], "--max-grad-norm must be positive in float32, which it trains in, got 1e-50"),
    ("obs", ["--episode-length", "10000000000"], "episode_length must be an integer from 1 to 2147483647"),
    ("obs", ["--action-repeat", "1000"], "action_repeat=1000 is more than episode_length="),
    ("obs", ["--eval-horizon", "1000"], "eval_horizon=1000 is longer than an episode (50 agent steps)"),
    ("obs", ["--arms", "cd", "cd-k4"], "Arms cd and cd-k4 are one configuration with the same hyper-parameters"),
    ("atari", ["--episode-length", "10000000000"], "episode_length must be an integer from 1 to 2147483647"),
    ("atari", ["--frame-skip", "8"], "frame_skip=8 is the ALE's (emulator frames per agent step)"),
    ("atari", ["--env", "ale-bogus"], "Unknown ALE game 'ale-bogus'; choose one of ale-breakout"),
])
def test_the_command_line_refuses_what_the_library_refuses(capsys, tmp_path, setting, argv, words):
    out = tmp_path / "run"
    base = {"obs": ["--preset", "point"], "atari": ["--preset", "cpu-minatar"], "pixel": ["--preset", "pixel-tiny"]}
    line = fail_in_one_sentence(capsys, main, ["sweep", "--setting", setting, *base[setting], *argv, "--out", str(out)])
    assert words in line and not out.exists(), line


def test_the_library_checks_hyper_parameters_where_they_become_concrete():
    """make_train(cfg)(key, hp) refuses what `cdjax sweep` refuses, with the same sentence (one declaration, used by
    both); under jit the values are traced and not checked there (the grid, the caller's HParams are)."""
    from cdjax.agents.atari import make_trainer as atari_trainer
    from cdjax.agents.obs.config import HP_RANGES

    assert agents.get("obs").check_hparam == HP_RANGES.check_one
    train = make_train(POINT)
    key = jax.random.key(0)
    for name, value, words in (("alpha", math.nan, "--alpha must be finite, got nan."),
                               ("lr_policy", -1.0, "--lr-policy must not be negative, got -1.0."),
                               ("gamma", 5.0, "--gamma must be between 0 and 1, got 5.0."),
                               ("max_grad_norm", 0.0, "--max-grad-norm must be positive, got 0.0.")):
        with pytest.raises(ConfigError) as library:
            train(key, HParams(**{name: value}))
        with pytest.raises(ConfigError) as command_line:
            agents.get("obs").check_hparam(name, value)
        assert str(library.value) == str(command_line.value) == words
    with pytest.raises(ConfigError, match="--alpha must not be negative, got -1.0"):  # stacked runs
        train(key, HParams(alpha=np.array([0.0, -1.0])))
    # valid stacked runs not vmapped: one sentence, not a shape error deep in the trace
    with pytest.raises(ConfigError, match=r"^alpha holds 2 values \(stacked hyper-parameters\) where init takes one"):
        train(key, stack_hparams([HParams(), HParams(alpha=0.0)]))
    with pytest.raises(ConfigError, match="--init-log-std must be between -20 and 20, got 89.0."):  # exp() overflows
        train(key, HParams(init_log_std=89.0))
    with pytest.raises(ConfigError, match="stack_hparams was given no HParams"):
        stack_hparams([])
    with pytest.raises(ConfigError, match="must be a cdjax.agents.obs.config.HParams, got a "
                                          "cdjax.agents.atari.config.AtariHParams"):
        train(key, AtariHParams())
    assert float(jax.jit(lambda hp: (HP_RANGES.check(hp), hp.alpha)[1])(HParams(alpha=0.5))) == 0.5  # traced: skipped
    with pytest.raises(ConfigError, match="num_envs must be a positive integer, got 2.5"):
        AtariConfig(num_envs=2.5)
    with pytest.raises(ConfigError, match="--lr must not be negative, got -1.0"):
        atari_trainer(AtariConfig(num_envs=2, rollout_len=4, horizon=2)).init(key, AtariHParams(lr=-1.0))
    with pytest.raises(ConfigError, match="must be a cdjax.agents.obs.config.Config, got a "
                                          "cdjax.agents.atari.config.AtariConfig"):
        agents.get("obs").make_trainer(AtariConfig())  # the obs setting's own (cdjax.make_trainer dispatches)


def test_a_config_of_another_setting_is_one_sentence(tmp_path, capsys):
    with pytest.raises(ConfigError) as info:
        run_sweep(SweepSpec(out=tmp_path / "run", config=PixelConfig()))
    assert str(info.value) == ("The obs setting takes a Config as its config, not a PixelConfig; give the setting "
                               "that config belongs to (SweepSpec(setting=...), --setting) or a Config.")
    assert not (tmp_path / "run").exists()


# ---------------------------------------------------------------------------------------------------
# Non-finite training is visible


@pytest.mark.parametrize("setting", ["obs", "atari", "pixel"])
def test_non_finite_training_is_counted_said_and_flagged(runs, tmp_path, capsys, setting):
    """A learning rate of 1e30 (finite, so allowed) blows the parameters up: every run skips steps. The metric
    counts them per run, the sweep says which runs while training and on its progress line, the summary flags
    them. The runs and shapes are the finished runs' (the compiled programs are shared); for atari and pixel the
    finished run is this one."""
    if setting == "obs":
        out = tmp_path / "run"
        main([a for a in _argv(setting, out, lr="1e30") if a != "--no-progress"])
        err = capsys.readouterr().err
    else:
        out = runs(setting)
        err = runs.said[setting]
    metric = agents.get(setting if setting != "pixel" else "pixel-synthetic").metrics.skipped
    per_run: dict = {}
    for row in logged_rows(out):
        key = (row["hp"], row["seed"])
        per_run[key] = per_run.get(key, 0) + row[metric]
    assert per_run and all(v > 0 for v in per_run.values()), per_run
    assert "runs skipped optimiser steps whose loss or gradient was not finite" in err, err
    assert any("env steps per run" in line and "non-finite steps skipped in runs:" in line
               for line in err.splitlines()), err  # the progress line
    assert "non-finite steps skipped in runs:" in [line for line in err.splitlines() if "Trained in" in line][0]
    summary = (out / "summary.md").read_text()
    assert "| non-finite |" in summary and "**Non-finite training**" in summary
    table = {r["hp"]: r for r in _csv_rows(out / "summary.csv")}
    assert all(int(r["nonfinite_seeds"]) == 2 and int(r["skipped_steps"]) > 0 for r in table.values()), table


def _csv_rows(path):
    import csv

    with open(path) as f:
        return list(csv.DictReader(f))


# ---------------------------------------------------------------------------------------------------
# Every reader of the run directory


BAD_ROWS = [b'{"arm": "cd", "hp": "alpha=0.0", "seed": 0, "update": 1, "loss/total": 1.0}\xff\xfe\n',
            b'\xc3\x28 not utf-8\n',
            b'{"arm": 5, "hp": "alpha=0.0", "seed": 0, "update": 1}\n',
            b'{"arm": "cd", "hp": "alpha=0.0", "seed": "x", "update": 1}\n',
            b'{"arm": "cd", "hp": "alpha=0.0", "seed": 0, "update": [1]}\n',
            b'{"arm": "cd", "hp": ["alpha=0.0"], "seed": 0, "update": 1}\n',
            b'{"arm": "cd", "hp": "alpha=0.0", "seed": 0, "update": 2, "episode/return": "high"}\n',
            b'[1, 2, 3]\n',
            b'{"arm": "cd", "hp": "alpha=0.0", "seed": 0, "upd']


def test_unreadable_log_lines_are_skipped_by_plot_and_trimmed_by_resume(runs, tmp_path, capsys):
    out = _copy(runs, "obs", tmp_path)
    good = (out / "metrics.jsonl").read_bytes()
    lines = good.splitlines(keepends=True)
    mixed = b"".join(lines[:5] + BAD_ROWS[:-1] + lines[5:]) + BAD_ROWS[-1]
    (out / "metrics.jsonl").write_bytes(mixed)
    (out / "eval.jsonl").write_bytes((out / "eval.jsonl").read_bytes() + b"\xff\n" + b'{"arm": "cd", "seed": -1}\n')
    summary = (out / "summary.csv").read_bytes()
    main(["plot", str(out), "--bootstrap-reps", "50"])
    err = capsys.readouterr().err
    assert f"{out}/metrics.jsonl: left out {len(BAD_ROWS)} line(s) that do not parse as rows" in err, err
    assert f"{out}/eval.jsonl: left out 2 line(s)" in err, err
    assert (out / "summary.csv").read_bytes() == summary  # the same table as from the clean logs

    main(["sweep", "--out", str(out), "--resume", "--no-progress"])  # finished: nothing to train, the logs trimmed
    err = capsys.readouterr().err
    assert f"dropped {len(BAD_ROWS) + 2} log rows written after the last checkpoint ({len(BAD_ROWS) + 2} of them a " \
           "torn line" in err, err
    assert (out / "metrics.jsonl").read_bytes() == good
    assert logged_rows(out, "eval.jsonl") == logged_rows(runs("obs"), "eval.jsonl")


@pytest.mark.parametrize("damage, words", [
    (lambda p: p.write_bytes(p.read_bytes().replace(b'"seeds": 2', b'"seeds": 2, "note": "\xff"')),
     "run.json is not UTF-8 text (byte 0xff at offset"),
    (lambda p: p.write_text(p.read_text().replace('"setting": "obs"', '"setting": ["obs"]')),
     "run.json: setting must be a setting's name, got ['obs']"),
    (lambda p: p.write_text(p.read_text().replace('"seeds": 2', '"seeds": "2"')),
     "run.json: seeds must be a positive integer, got '2'"),
    (lambda p: p.write_text(p.read_text().replace('"hp_labels": [', '"hp_labels": [7, ')),
     "run.json: arms[0].hp_labels must be a list of strings"),
    (lambda p: _edit_run(p.parent, lambda run: run["base_config"].update(policy_hidden="wide")),
     "policy_hidden must be a non-empty tuple of positive integers, got 'wide'"),
    (lambda p: p.write_bytes(b"\x00" * 10), "run.json is not valid JSON"),
    (lambda p: _edit_run(p.parent, lambda run: run["arms"][0].pop("name")),
     "run.json: arms[0].name must be an arm's name, got no name"),
])
@pytest.mark.parametrize("command", ["resume", "eval", "plot"])
def test_a_damaged_run_json_is_one_sentence_for_every_command(runs, tmp_path, capsys, damage, words, command):
    out = _copy(runs, "obs", tmp_path)
    if command == "plot" and "policy_hidden" in words:
        pytest.skip("plot reads run.json's fields, not a Config: an invalid Config is no obstacle to plotting")
    damage(out / "run.json")
    before = snapshot(out)
    argv = {"resume": ["sweep", "--out", str(out), "--resume"], "eval": ["eval", str(out)],
            "plot": ["plot", str(out)]}[command]
    line = fail_in_one_sentence(capsys, main, argv)
    assert words in line, line
    assert snapshot(out) == before


@pytest.mark.parametrize("setup", ["missing", "garbage-gz", "garbage-xz", "no-rows"])
def test_plot_refuses_rather_than_overwrite_a_summary_from_no_data(runs, tmp_path, capsys, setup):
    out = _copy(runs, "obs", tmp_path)
    metrics = out / "metrics.jsonl"
    if setup == "garbage-gz":
        metrics.unlink()
        (out / "metrics.jsonl.gz").write_bytes(b"\x1f\x8b\x08 not really gzip")
    elif setup == "garbage-xz":
        metrics.unlink()
        (out / "metrics.jsonl.xz").write_bytes(b"\xfd7zXZ\x00 not really xz")
    elif setup == "no-rows":
        metrics.write_bytes(b"\xff\xfe\n{}\n")
    else:
        metrics.unlink()
    before = snapshot(out)
    line = _fails(capsys, ["plot", str(out)])  # after a sentence counting the unreadable lines, if any
    if setup.startswith("garbage"):  # a compressed copy that does not decompress: damaged, one rule for every reader
        packed = out / f"metrics.jsonl.{setup[-2:]}"
        assert line.startswith(f"cdjax: {packed} is damaged: it decompresses only in part (0 rows read; no row could "
                               "be read)") and "nothing was plotted" in line, line
    else:
        state = "is missing" if setup == "missing" else "holds no readable row"
        assert line == (f"cdjax: {metrics} {state}, so there is nothing to plot; {out}/summary.md and plots/ were left "
                        "as they were."), line
    assert snapshot(out) == before


@pytest.mark.parametrize("suffix, compress", [(".gz", gzip.compress), (".xz", lzma.compress)])
def test_a_packed_log_cut_short_gives_its_readable_rows(runs, tmp_path, suffix, compress):
    out = _copy(runs, "obs", tmp_path)
    rows = io.read_jsonl(out / "metrics.jsonl")
    packed = compress((out / "metrics.jsonl").read_bytes())
    (out / "metrics.jsonl").unlink()
    (out / ("metrics.jsonl" + suffix)).write_bytes(packed[: len(packed) * 2 // 3])
    cut = io.read_jsonl(out / "metrics.jsonl")
    assert 0 < len(cut) < len(rows) and cut == rows[: len(cut)] and cut.skipped >= 1


def test_a_kept_log_is_written_as_xz_and_read_as_the_file_it_replaces(runs, tmp_path):
    """write_packed: the rows read back exactly (gzip's copy and the file itself alike), the same bytes on every
    write (no timestamp), and an older .gz copy beside it removed, so one file holds the rows."""
    out = _copy(runs, "obs", tmp_path)
    plain = out / "metrics.jsonl"
    data, rows = plain.read_bytes(), io.read_jsonl(plain)
    plain.unlink()
    (out / "metrics.jsonl.gz").write_bytes(gzip.compress(data, mtime=0))
    assert io.jsonl_source(plain) == out / "metrics.jsonl.gz" and io.read_jsonl(plain) == rows
    packed = io.write_packed(plain, data)
    assert packed == out / "metrics.jsonl.xz" and not (out / "metrics.jsonl.gz").exists()
    assert lzma.decompress(packed.read_bytes()) == data
    assert io.write_packed(plain, data).read_bytes() == packed.read_bytes()
    again = io.read_jsonl(plain)
    assert again == rows and again.skipped == rows.skipped == 0 and io.jsonl_exists(plain)
    half = data[: data.rindex(b"\n", 0, len(data) // 2) + 1]  # whole lines: rows a resume appended beside the copy
    plain.write_bytes(half)  # one rule: the compressed copy's rows, then the file's own
    assert io.jsonl_source(plain) == plain and io.read_jsonl(plain) == rows + rows[: len(half.splitlines())]


def test_phase_and_eval_logs_are_trimmed_like_the_metrics(tmp_path):
    """truncate_jsonl on each log of the run directory: rows past the checkpoint, torn lines, bytes that are not
    UTF-8 and rows of the wrong types go; an arm restarted (-1) keeps nothing; an arm the run does not name (a
    run.json edited by hand) is not the resume's to judge: its rows stay."""
    phase = tmp_path / "phase.jsonl"
    keep = [{"arm": "mbmf", "hp": "default", "seed": 0, "update": 0, "phase/x": 1.0},
            {"arm": "cd", "hp": "default", "seed": 1, "update": 0, "phase/x": None},
            {"arm": "not-in-this-run", "hp": "default", "seed": 0, "update": 9, "phase/x": 2.0}]
    text = b"".join(json.dumps(r).encode() + b"\n" for r in keep)
    phase.write_bytes(text + b'{"arm": "cd", "hp": "default", "seed": 0, "update": 0, "phase/x": "no"}\n\xff\n'
                      + json.dumps({**keep[0], "arm": "gone"}).encode() + b"\n" + b'{"arm"')
    assert io.truncate_jsonl(phase, {"mbmf": 0, "cd": 0, "gone": -1}) == (4, 3)
    assert phase.read_bytes() == text and io.read_jsonl(phase) == keep
    assert io.truncate_jsonl(phase, {"mbmf": 0, "cd": 0}) == (0, 0) and phase.read_bytes() == text  # untouched


def test_a_resume_notes_the_logs_and_checkpoints_of_an_arm_that_run_json_does_not_name(runs, tmp_path, capsys,
                                                                                        monkeypatch):
    """An arm removed from run.json by hand leaves its rows and checkpoints behind: the resume says so in one
    sentence and goes on (a note, not a refusal), leaving them and this run's own as they were; `cdjax plot` and
    `cdjax eval` say the same."""
    assert set(io.RunDir(runs("obs")).arms_held()) == {"cd"}  # a run's own directory holds only its arms
    out = _copy(runs, "obs", tmp_path)
    for name in ("metrics.jsonl", "eval.jsonl"):  # the removed arm: the run's own logged under another name
        with (out / name).open("a") as f:
            f.writelines(json.dumps(dict(row, arm="mbmf")) + "\n" for row in io.read_jsonl(out / name))
    shutil.copytree(out / "checkpoints" / "cd", out / "checkpoints" / "mbmf")
    logs = {name: (out / name).read_bytes() for name in ("metrics.jsonl", "eval.jsonl")}
    main(["sweep", "--out", str(out), "--resume", "--no-progress"])  # finished: nothing to train
    err = capsys.readouterr().err
    notes = [line for line in err.splitlines() if "run.json does not name" in line]
    assert len(notes) == 1 and notes[0].endswith(".") and notes[0].count(". ") == 0, err
    assert "mbmf (metrics.jsonl, eval.jsonl, checkpoints/mbmf)" in notes[0] and "cd (" not in notes[0], notes
    assert {name: (out / name).read_bytes() for name in logs} == logs
    assert snapshot(out / "checkpoints" / "mbmf") == snapshot(runs("obs") / "checkpoints" / "cd")
    main(["plot", str(out), "--bootstrap-reps", "20"])  # the plots, which rank them, say it too
    assert [line for line in capsys.readouterr().err.splitlines() if "run.json does not name" in line] == notes
    import cdjax.runner

    monkeypatch.setattr(cdjax.runner, "evaluate_arms", lambda *args: [])  # what is said before it, not its programs
    main(["eval", str(out), "--episodes", "2"])  # its rows land beside the unnamed arm's in eval.jsonl: it says so
    assert [line for line in capsys.readouterr().err.splitlines() if "run.json does not name" in line] == notes


# ---------------------------------------------------------------------------------------------------
# Signals and interrupts


def _env():
    return dict(os.environ, CDJAX_JAX_CACHE=str(CACHE), JAX_PLATFORMS="cpu")


def test_sigterm_checkpoints_like_ctrl_c_and_the_resumed_run_is_the_uninterrupted_one(runs, tmp_path):
    """SIGTERM (a scheduler's pre-emption) mid-training: the chunk in flight is saved, one sentence, exit 143, the
    lock released; resumed to the finished run's length, every logged row equals the uninterrupted run's."""
    whole = runs("obs")
    out = tmp_path / "term"
    cmd = [sys.executable, "-m", "cdjax.cli", *_argv("obs", out)[:-4], "--steps", str(100_000 * 192), "--out",
           str(out)]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=_env())
    try:
        deadline = time.time() + 300
        while time.time() < deadline and proc.poll() is None:
            if (out / "metrics.jsonl").exists() and (out / "metrics.jsonl").stat().st_size > 0:
                break
            time.sleep(0.2)
        assert proc.poll() is None, proc.communicate()[1][-3000:]
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=300)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 143 and "Traceback" not in err, err[-3000:]
    last = err.strip().splitlines()[-1]
    assert last.startswith(f"Stopped by SIGTERM; checkpoint saved in {out} (updates per arm: cd ") and last.endswith(
        f"Resume with: cdjax sweep --out {out} --resume"), last
    done = max(int(p.name) for p in (out / "checkpoints" / "cd").iterdir() if p.name.isdigit())
    assert done == max(r["update"] for r in io.read_jsonl(out / "metrics.jsonl"))  # the logs end at the checkpoint
    with io.RunDir(out).lock():  # released
        pass
    if done > 4:  # a fast machine: compare with an uninterrupted run as long as this one
        whole = tmp_path / "whole"
        main(_argv("obs", whole)[:-3] + [str(done * 192), "--out", str(whole)])
    main(["sweep", "--out", str(out), "--resume", "--steps", str(max(done, 4) * 192), "--no-progress"])
    assert logged_rows(out) == logged_rows(whole)
    assert logged_rows(out, "eval.jsonl") == logged_rows(whole, "eval.jsonl")


def _in_main_thread():
    if threading.current_thread() is not threading.main_thread():
        pytest.skip("signals reach the main thread only")


@pytest.mark.parametrize("signum, status", [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_an_interrupt_while_compiling_says_nothing_was_written(tmp_path, capsys, monkeypatch, signum, status):
    _in_main_thread()
    import cdjax.runner.loop as loop

    def interrupted(*args, **kwargs):
        os.kill(os.getpid(), signum)
        time.sleep(5)  # the handler raises here
        raise AssertionError("no signal")

    monkeypatch.setattr(loop, "compile_all", interrupted)
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)  # a test runner's worker may ignore it
    out = tmp_path / "run"
    try:
        with pytest.raises(SystemExit) as info:
            main(_argv("obs", out))
    finally:
        signal.signal(signal.SIGINT, previous)
    err = capsys.readouterr().err
    assert info.value.code == status, err
    assert err.strip().splitlines()[-1] == ("Interrupted before training started (while planning or compiling); "
                                            f"nothing was written to {out}.")
    assert not out.exists()


def test_each_interrupt_says_what_is_true_for_its_command(runs, tmp_path, capsys, monkeypatch):
    out = _copy(runs, "obs", tmp_path)
    before = snapshot(out)

    def ctrl_c(*args, **kwargs):
        raise KeyboardInterrupt

    import cdjax.plots
    import cdjax.runner

    monkeypatch.setattr(cdjax.runner, "evaluate_arms", ctrl_c)
    with pytest.raises(SystemExit) as info:
        main(["eval", str(out), "--episodes", "2"])
    assert info.value.code == 130
    assert capsys.readouterr().err.strip().splitlines()[-1] == (
        f"Interrupted before the evaluation was done; nothing was added to {out}/eval.jsonl.")
    monkeypatch.setattr(cdjax.plots, "plot_run", ctrl_c)
    with pytest.raises(SystemExit) as info:
        main(["plot", str(out)])
    assert info.value.code == 130 and capsys.readouterr().err.strip().splitlines()[-1] == (
        f"Interrupted while plotting; the plots and summary of {out} may be partly rewritten: run `cdjax plot {out}` "
        "again.")
    (out / "eval.jsonl").unlink()  # the finished run's final evaluation is to be made again: interrupted there
    with pytest.raises(SystemExit) as info:
        main(["sweep", "--out", str(out), "--resume", "--no-progress"])
    assert info.value.code == 130
    assert capsys.readouterr().err.strip().splitlines()[-1] == (
        "Interrupted after training (every arm is trained and checkpointed) during the final evaluation or plots; "
        f"`cdjax sweep --out {out} --resume` makes them.")
    logs = ("eval.jsonl", "cdjax.log", "timings.jsonl")  # what the resume's process said and timed is added
    assert {k: v for k, v in snapshot(out).items() if k not in logs} == {
        k: v for k, v in before.items() if k not in logs}


# ---------------------------------------------------------------------------------------------------
# Paths and the environment


def test_a_lock_left_before_run_json_does_not_block_a_fresh_start_but_other_files_do(tmp_path, capsys):
    """A sweep stopped after it made its directory and took the lock, before run.json, leaves `.lock` alone: the
    next fresh start trains there (and a directory with anything else of its own is still refused, untouched)."""
    out = tmp_path / "run"
    out.mkdir()
    (out / ".lock").write_text("")
    (out / ".cdjax-write-test.x1y2z3").write_text("")  # a write probe of a process killed while it probed
    with contextlib.redirect_stderr(StringIO()):
        main(_argv("obs", out, extra=["--no-final-eval"]))
    assert json.loads((out / "run.json").read_text())["arms"] and logged_rows(out)
    other = tmp_path / "other"
    other.mkdir()
    (other / ".lock").write_text("")
    (other / "notes.txt").write_text("mine")
    line = _fails(capsys, _argv("obs", other))
    assert line == f"cdjax: {other} exists and is not empty; choose another --out."
    assert snapshot(other) == {".lock": b"", "notes.txt": b"mine"}


def test_processes_checking_one_directory_at_once_do_not_remove_each_others_write_probe(tmp_path):
    """The processes of one sweep check the same run directory at the same time (CI saw the second one refuse with
    "No such file or directory" when both probed with one file name): each probe is its own file, and none is left."""
    import threading

    out = tmp_path / "run"
    for folder in ("checkpoints/cd", "tb", "plots"):
        (out / folder).mkdir(parents=True)
    errors = []

    def check():
        try:
            for _ in range(300):
                io.RunDir(out).check_run_writable()
        except io.RunDirError as err:
            errors.append(str(err))

    threads = [threading.Thread(target=check) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert errors == []
    assert not [p for p in out.rglob("*") if p.is_file()]


def test_paths_and_the_cache_directory_are_checked_before_anything_is_written(tmp_path, capsys, monkeypatch):
    a_file = tmp_path / "a-file"
    a_file.write_text("keep me")
    before = sorted(p.name for p in tmp_path.iterdir())
    long = tmp_path / ("x" * 300) / "run"
    line = fail_in_one_sentence(capsys, main, ["sweep", "--preset", "point", "--out", str(long)])
    assert line == f"cdjax: --out: the name {'x' * 40!r}... is 300 bytes, longer than the 255 this file system " \
                   "allows; choose a shorter one."
    for command in ("eval", "plot"):
        assert "longer than the 255" in fail_in_one_sentence(capsys, main, [command, str(long)])
    undecodable = tmp_path / os.fsdecode(b"run-\xff")
    line = fail_in_one_sentence(capsys, main, ["sweep", "--preset", "point", "--out", str(undecodable)])
    assert line == f"cdjax: --out {ascii(str(undecodable))} is not UTF-8 text; choose a name of UTF-8 characters."
    line = fail_in_one_sentence(capsys, main, ["sweep", "--preset", "point", "--cache-dir", str(a_file), "--out",
                                               str(tmp_path / "run")])
    assert line == f"cdjax: --cache-dir {a_file} is a file, not a directory; name a directory for JAX's compilation " \
                   "cache."
    previous = jax.config.jax_compilation_cache_dir
    jax.config.update("jax_compilation_cache_dir", None)  # as a fresh process: the variable is read
    try:
        monkeypatch.setenv("CDJAX_JAX_CACHE", str(a_file / "cache"))
        line = fail_in_one_sentence(capsys, main, ["sweep", "--preset", "point", "--out", str(tmp_path / "run")])
    finally:
        jax.config.update("jax_compilation_cache_dir", previous)
    assert line.startswith(f"cdjax: $CDJAX_JAX_CACHE {a_file / 'cache'} cannot be used (Not a directory)"), line
    assert sorted(p.name for p in tmp_path.iterdir()) == before and a_file.read_text() == "keep me"
