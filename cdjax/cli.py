"""The `cdjax` command: sweep, eval, plot.

    cdjax sweep --env ant --seeds 16 --alpha 0 1.0 --horizon 20 --steps 50_000_000 --out runs/ant-cd
    cdjax sweep --out runs/ant-cd --resume
    cdjax eval  runs/ant-cd --episodes 100
    cdjax plot  runs/ant-cd

The options of `sweep` are generated from the dataclasses: one option per `Config` field (except `arm`,
chosen by --arms, and `num_updates`, derived from --steps) and one per `HParams` field, which takes
one or several values (their Cartesian product is the hyper-parameter grid, vmapped with the seeds).
Help texts are the field comments of cdjax/config.py. Only the sweep's own options are written here.

Bad input ends with one sentence on stderr and exit status 2; an interrupted sweep exits with 130.
"""

from __future__ import annotations

import argparse
import dataclasses
import inspect
import os
import pathlib
import re
import shlex
import sys
import typing
from typing import Any, Literal, Sequence

from cdjax import io, presets
from cdjax.config import Config, ConfigError, HParams

# Config fields that are not options: the arm comes from --arms, the number of updates from --steps.
NOT_OPTIONS = ("arm", "num_updates")
# Sweep options that may be given with --resume (everything else is read from run.json).
RESUME_OPTIONS = ("steps", "eval_every", "eval_episodes")
# Sweep options (argparse dest) that map onto SweepSpec fields.
SPEC_OPTIONS = {"arms": "arms", "seeds": "seeds", "seed": "seed", "steps": "total_env_steps",
                "chunk_updates": "chunk_updates", "checkpoint_every": "checkpoint_every",
                "eval_every": "eval_every", "eval_episodes": "eval_episodes"}


class UsageError(ValueError):
    """Command-line input that cannot run; one sentence."""


class _Parser(argparse.ArgumentParser):
    """argparse that reports errors in one line (no usage block) and exits with status 2."""

    def error(self, message: str):
        message = re.sub(r"^unrecognized arguments: ", "unknown option(s): ", message)
        message = message.replace("\n", " ")
        raise UsageError(f"{message}; see `{self.prog} --help`.")


# ---------------------------------------------------------------------------------------------------
# Options derived from the dataclasses


def field_comments(cls) -> dict[str, str]:
    """The `# comment` after each field of a dataclass, as help text."""
    out = {}
    for line in inspect.getsource(cls).splitlines():
        match = re.match(r"\s+(\w+):[^#]*?=[^#]*#\s*(.+)$", line)
        if match:
            out[match.group(1)] = match.group(2).strip()
    return out


def _flag(name: str) -> str:
    return "--" + name.replace("_", "-")


def _count(text: str) -> int:
    """An integer count: 50_000_000, 5e7 or 50000000."""
    try:
        return int(text)
    except ValueError:
        pass
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
    if not value.is_integer():
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number")
    return int(value)


def _float(text: str) -> float:
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None


def add_config_options(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group("environment and agent (cdjax.config.Config; changing one recompiles)")
    hints = typing.get_type_hints(Config)
    comments = field_comments(Config)
    defaults = Config.__dataclass_fields__
    for field in dataclasses.fields(Config):
        if field.name in NOT_OPTIONS:
            continue
        hint, default = hints[field.name], defaults[field.name].default
        kwargs: dict[str, Any] = dict(default=None, dest=f"config.{field.name}")
        if typing.get_origin(hint) is Literal:
            kwargs.update(choices=typing.get_args(hint), metavar="{" + ",".join(typing.get_args(hint)) + "}")
        elif typing.get_origin(hint) is tuple:
            (item, _) = typing.get_args(hint)
            kwargs.update(type=item, nargs="+", metavar=item.__name__.upper())
            default = " ".join(map(str, default))
        elif hint is bool:
            kwargs.update(type=_bool, metavar="{true,false}")
        elif hint in (int, str, float):
            kwargs.update(type=_count if hint is int else _float if hint is float else str,
                          metavar=hint.__name__.upper())
        else:  # pragma: no cover - a new kind of field needs a line here
            raise TypeError(f"Config.{field.name}: no command-line form for {hint}")
        help_text = comments.get(field.name, "")
        group.add_argument(_flag(field.name), help=f"{help_text} (default {default})".replace("%", "%%"), **kwargs)


def add_phase_options(parser: argparse.ArgumentParser) -> None:
    """--mbmf-phase on/off and one --phase-<field> option per MbMfPhase field (any of them turns it on)."""
    from cdjax.mbmf import MbMfPhase

    group = parser.add_argument_group(
        "Mb-Mf phase (cdjax.mbmf.MbMfPhase): random data, model, random-shooting MPC, distillation; run by the "
        "arms with a model before PPO, its env steps counted in --steps")
    onoff = group.add_mutually_exclusive_group()
    onoff.add_argument("--mbmf-phase", action="store_true", default=None, dest="phase_on",
                       help="run the phase (default: as the preset says; off without one)")
    onoff.add_argument("--no-mbmf-phase", action="store_false", dest="phase_on", help="do not run the phase")
    hints = typing.get_type_hints(MbMfPhase)
    comments = field_comments(MbMfPhase)
    for field in dataclasses.fields(MbMfPhase):
        hint = hints[field.name]
        kwargs: dict[str, Any] = dict(default=None, dest=f"phase.{field.name}")
        if typing.get_origin(hint) is Literal:
            kwargs.update(choices=typing.get_args(hint), metavar="{" + ",".join(typing.get_args(hint)) + "}")
        elif hint is bool:
            kwargs.update(type=_bool, metavar="{true,false}")
        elif hint in (int, float):
            kwargs.update(type=_count if hint is int else _float, metavar=hint.__name__.upper())
        else:  # pragma: no cover - a new kind of field needs a line here
            raise TypeError(f"MbMfPhase.{field.name}: no command-line form for {hint}")
        group.add_argument("--phase-" + field.name.replace("_", "-"),
                           help=f"{comments.get(field.name, '')} (default {field.default})".replace("%", "%%"),
                           **kwargs)


def _bool(text: str) -> bool:
    if text.lower() in ("true", "1", "yes"):
        return True
    if text.lower() in ("false", "0", "no"):
        return False
    raise argparse.ArgumentTypeError(f"{text!r} is not true or false")


def add_hparam_options(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group(
        "hyper-parameters (cdjax.config.HParams; traced): several values make a grid, vmapped with the seeds")
    comments = field_comments(HParams)
    for field in dataclasses.fields(HParams):
        group.add_argument(_flag(field.name), type=_float, nargs="+", default=None, metavar="X",
                           dest=f"hp.{field.name}",
                           help=f"{comments.get(field.name, '')} (default {field.default})".replace("%", "%%"))


# ---------------------------------------------------------------------------------------------------
# The parser


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="cdjax", allow_abbrev=False,
                     description="Consistent dynamics models (Sodhani et al., 2019) on MuJoCo-MJX in JAX.")
    sub = parser.add_subparsers(dest="command", metavar="{sweep,eval,plot}", required=True, parser_class=_Parser)

    preset_lines = "\n".join(f"  {name:<18} {p.about}" for name, p in presets.PRESETS.items())
    sweep = sub.add_parser(
        "sweep", help="train arms x hyper-parameter grid x seeds, chunked, with logs and checkpoints",
        allow_abbrev=False, formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Train every arm (one compiled program each) on the grid of the hyper-parameters given "
                    "as lists times --seeds, vmapped; log, checkpoint and show progress between chunks.\n"
                    "Precedence: defaults < --preset < options given here.",
        epilog=f"presets:\n{preset_lines}")
    run = sweep.add_argument_group("sweep")
    run.add_argument("--out", required=True, metavar="DIR", help="run directory (refuses one that holds another run)")
    run.add_argument("--resume", action="store_true", help="continue the run in --out from its latest checkpoint")
    run.add_argument("--preset", metavar="NAME",
                     help="named overrides, listed below (default: the preset named like --env, if any)")
    run.add_argument("--arms", nargs="+", metavar="ARM", default=None,
                     help="arms to train: model-free, mbmf, cd, or cd-kN for cd with horizon N (default: mbmf cd)")
    run.add_argument("--seeds", type=_count, default=None, metavar="N", help="seeds per hp combination (default 3)")
    run.add_argument("--seed", type=_count, default=None, metavar="S", help="base seed (default 0)")
    run.add_argument("--steps", type=_count, default=None, metavar="N",
                     help="environment steps per run, e.g. 50_000_000 (default 1_000_000)")
    run.add_argument("--chunk-updates", type=_count, default=None, metavar="N",
                     help="updates per compiled chunk (default: about 5%% of the run)")
    run.add_argument("--checkpoint-every", type=_count, default=None, metavar="K",
                     help="chunks between checkpoints (default 1)")
    run.add_argument("--eval-every", type=_count, default=None, metavar="K",
                     help="chunks between evaluations (default 0: only at the end)")
    run.add_argument("--eval-episodes", type=_count, default=None, metavar="N",
                     help="episodes per run in evaluations (default 10)")
    run.add_argument("--no-progress", action="store_true", help="no progress display")
    add_config_options(sweep)
    add_hparam_options(sweep)
    add_phase_options(sweep)

    ev = sub.add_parser("eval", help="evaluate the saved policies of a run, per seed and per arm", allow_abbrev=False)
    ev.add_argument("run_dir", metavar="RUN_DIR")
    ev.add_argument("--episodes", type=_count, default=100, metavar="N", help="episodes per run (default 100)")
    ev.add_argument("--stochastic", action="store_true", help="sample actions (default: the mean action)")
    ev.add_argument("--video", action="store_true", help="also render a video of one episode per arm")

    plot = sub.add_parser("plot", help="curves and the summary table again from the logs", allow_abbrev=False)
    plot.add_argument("run_dir", metavar="RUN_DIR")
    return parser


# ---------------------------------------------------------------------------------------------------
# Parsed options -> SweepSpec


def _given(args: argparse.Namespace, prefix: str) -> dict[str, Any]:
    out = {}
    for dest, value in vars(args).items():
        if dest.startswith(prefix) and value is not None:
            out[dest[len(prefix):]] = tuple(value) if isinstance(value, list) else value
    return out


def sweep_spec(args: argparse.Namespace, command: str = ""):
    """The SweepSpec that the sweep options describe (defaults < preset < explicit options)."""
    from cdjax.mbmf import MbMfPhase
    from cdjax.runner import SweepSpec, resume_spec

    config_given, hp_given, phase_given = _given(args, "config."), _given(args, "hp."), _given(args, "phase.")
    spec_given = {field: getattr(args, opt) for opt, field in SPEC_OPTIONS.items() if getattr(args, opt) is not None}
    if args.resume:
        extra = sorted({_flag(k) for k in config_given} | {_flag(k) for k in hp_given}
                       | {"--phase-" + k.replace("_", "-") for k in phase_given}
                       | ({"--mbmf-phase" if args.phase_on else "--no-mbmf-phase"} if args.phase_on is not None else set())
                       | {_flag(opt) for opt in SPEC_OPTIONS if getattr(args, opt) is not None
                          and opt not in RESUME_OPTIONS} | ({"--preset"} if args.preset else set()))
        if extra:
            raise UsageError(f"--resume continues the run recorded in {args.out}/run.json, so {', '.join(extra)} "
                             f"cannot be changed (only --steps, --eval-every, --eval-episodes, --no-progress).")
        return resume_spec(args.out, progress=not args.no_progress, **spec_given)

    if args.preset is not None:
        preset = presets.get(args.preset)
    else:
        preset = presets.PRESETS.get(config_given.get("env", Config.env))
    config_values = {**(preset.config if preset else {}), **config_given}
    config = Config(**config_values)
    grid = {**(preset.hparams if preset else {}), **hp_given}
    spec_values = {**(preset.sweep if preset else {}), **spec_given}
    if "arms" in spec_values:
        spec_values["arms"] = tuple(spec_values["arms"])
    phase_values = {**(preset.phase or {} if preset else {}), **phase_given}
    on = args.phase_on if args.phase_on is not None else bool(phase_given) or bool(preset and preset.phase is not None)
    if phase_given and args.phase_on is False:
        raise UsageError("--no-mbmf-phase contradicts the --phase-* options given.")
    spec_values["phase"] = MbMfPhase(**phase_values) if on else None
    return SweepSpec(out=args.out, config=config, grid=grid, progress=not args.no_progress, command=command,
                     **spec_values)


# ---------------------------------------------------------------------------------------------------
# Subcommands


def cmd_sweep(args: argparse.Namespace, command: str) -> None:
    from cdjax import runner

    spec = sweep_spec(args, command)
    out = runner.run_sweep(spec, resume=args.resume)
    print(f"Done: {out}")


def cmd_eval(args: argparse.Namespace) -> None:
    from cdjax import runner

    if not runner._have_evaluate():
        raise UsageError("cdjax eval needs cdjax.evaluate, which this installation does not have.")
    spec, arms = runner.restore_arms(args.run_dir)
    rd = io.RunDir(pathlib.Path(args.run_dir))
    say = lambda text: print(text, file=sys.stderr, flush=True)  # noqa: E731
    records = runner.evaluate_arms(rd, arms, spec.seeds, args.episodes, not args.stochastic, say)
    _print_eval(records)
    print(f"Appended {len(records)} records to {rd.eval}")
    if args.video:
        import jax

        from cdjax.evaluate import render_video

        for arm in arms:
            for i, label in enumerate(arm.plan.labels):
                r = i * spec.seeds  # seed 0 of this hp combination
                pick = lambda x: x[r]  # noqa: E731
                path = render_video(arm.sweep.trainer, {"policy": jax.tree.map(pick, arm.state.params["policy"])},
                                    jax.tree.map(pick, arm.state.norms), jax.random.key(spec.seed),
                                    rd.path / "videos" / f"{arm.name}-{label}-seed0.mp4",
                                    steps=arm.plan.config.episode_length)
                if path is not None:
                    print(f"Wrote {path}")


def _print_eval(records: list[dict]) -> None:
    import numpy as np

    groups: dict[tuple[str, str], list[float]] = {}
    for row in records:
        groups.setdefault((row["arm"], row["hp"]), [])
        if row.get("eval/return") is not None:
            groups[(row["arm"], row["hp"])].append(float(row["eval/return"]))
    width = max([len(a) + len(h) + 3 for a, h in groups] + [8])
    print(f"{'arm / hp':<{width}}  {'seeds':>5}  {'mean return':>11}  {'std over seeds':>14}")
    for (arm, hp), values in groups.items():
        mean, std = (np.mean(values), np.std(values)) if values else (float("nan"), float("nan"))
        print(f"{arm + ' / ' + hp:<{width}}  {len(values):>5}  {mean:>11.2f}  {std:>14.2f}")


def cmd_plot(args: argparse.Namespace) -> None:
    rd = io.RunDir(pathlib.Path(args.run_dir))
    rd.read()  # a clear error for a directory that holds no run
    try:
        from cdjax.plots import plot_run
    except ImportError:
        raise UsageError("cdjax plot needs cdjax.plots, which this installation does not have.") from None
    for path in plot_run(rd.path).values():
        print(f"Wrote {path}")


def setup_jax() -> None:
    """The persistent compilation cache (CDJAX_JAX_CACHE, default ~/.cache/cdjax/jax), unless already set,
    and no Brax deprecation notice on every run."""
    import warnings

    import jax

    warnings.filterwarnings("ignore", message="Brax System", category=UserWarning)

    if not jax.config.jax_compilation_cache_dir:
        cache = os.environ.get("CDJAX_JAX_CACHE", str(pathlib.Path.home() / ".cache" / "cdjax" / "jax"))
        jax.config.update("jax_compilation_cache_dir", cache)
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)


def main(argv: Sequence[str] | None = None) -> None:
    argv = list(sys.argv[1:] if argv is None else argv)
    from cdjax.runner import Interrupted

    try:
        try:
            args = build_parser().parse_args(argv)
        except UsageError as err:  # unknown options are reported by the top parser: name the subcommand
            if argv and argv[0] in ("sweep", "eval", "plot"):
                raise UsageError(str(err).replace("`cdjax --help`", f"`cdjax {argv[0]} --help`")) from None
            raise
        setup_jax()
        if args.command == "sweep":
            cmd_sweep(args, " ".join(["cdjax"] + [shlex.quote(a) for a in argv]))
        elif args.command == "eval":
            cmd_eval(args)
        else:
            cmd_plot(args)
    except (UsageError, ConfigError, io.RunDirError) as err:
        print(f"cdjax: {err}", file=sys.stderr)
        raise SystemExit(2) from None
    except Interrupted as err:
        done = ", ".join(f"{arm} {n}" for arm, n in err.updates.items())
        print(f"Interrupted; checkpoint saved (updates per arm: {done}). "
              f"Resume with: cdjax sweep --out {shlex.quote(str(err.run_dir))} --resume", file=sys.stderr)
        raise SystemExit(130) from None
    except KeyboardInterrupt:
        print("Interrupted; the latest complete checkpoint is kept (resume with cdjax sweep --out DIR --resume).",
              file=sys.stderr)
        raise SystemExit(130) from None


if __name__ == "__main__":
    main()
