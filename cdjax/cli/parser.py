"""The `cdjax` command's options: every option of `sweep` derived from a dataclass field (cdjax.options), and the
SweepSpec they describe."""

from __future__ import annotations

import argparse
import pathlib
from typing import Sequence

from cdjax import agents, io, multihost, options, runtime
from cdjax.options import Parser, UsageError
from cdjax.protocol import Setting
from cdjax.runner.spec import FLAGS, SweepSpec

SPEC_SKIP = ("out", "config", "grid", "phase", "command")  # SweepSpec fields that are not options of their own
RESUME_OPTIONS = ("total_env_steps", "progress")  # options a resume may give (the rest is read from run.json)


def _runtime_options() -> argparse.ArgumentParser:
    parent = argparse.ArgumentParser(add_help=False)
    group = parent.add_argument_group("runtime (cdjax.runtime.configure)")
    group.add_argument("--cache-dir", metavar="DIR", help="JAX's persistent compilation cache (default "
                       f"${runtime.CACHE_ENV}, else ~/.cache/cdjax/jax)")
    group.add_argument("--compile-mode", choices=list(runtime.COMPILE_MODES),
                       help="what cdjax asks of XLA for its programs: default (the XLA flags cdjax sets, which "
                            "shorten GPU compiles), fast (on a GPU, Triton's GEMM fusions off: a quarter to half less "
                            "cold compile time, each update 5-19%% slower as measured: for short runs), tuned (on a "
                            "GPU, XLA's full autotuning: compiles about a quarter longer, the paper's CD 10%% faster "
                            "at 10 seeds as measured: for long sweeps) or deterministic (on a GPU, no atomic sums and "
                            "no autotuning, so that another process repeats the run bit for bit; updates 1.7-1.9x "
                            "longer as measured); default $" + runtime.MODE_ENV + ", else default. $"
                            + runtime.OPTIONS_ENV + " adds XLA options (NAME=VALUE ...) to cdjax's programs only")
    group.add_argument("--debug-nans", action="store_true", help="stop at the first operation that makes a NaN")
    group.add_argument("--disable-jit", action="store_true", help="run op by op (slow; for debugging)")
    return parent


def _distributed_options() -> argparse.ArgumentParser:
    parent = argparse.ArgumentParser(add_help=False)
    group = parent.add_argument_group(
        "several processes (cdjax.multihost): one per node or per GPU, each running this same command; --out on a "
        "file system they all see")
    group.add_argument("--distributed", action="store_true",
                       help="join the other processes (jax.distributed.initialize) and share the runs over every "
                            "process's devices; process 0 writes the run directory")
    group.add_argument("--coordinator", metavar="HOST:PORT",
                       help="with --distributed: process 0's address and a free port (default: found by JAX under "
                            "SLURM, Open MPI and Cloud TPU)")
    group.add_argument("--num-processes", type=options.count, metavar="N",
                       help="with --distributed: how many processes (default: found by JAX, as --coordinator)")
    group.add_argument("--process-id", type=options.count, metavar="I",
                       help="with --distributed: this process's number, 0 to N-1 (default: found by JAX)")
    group.add_argument("--heartbeat-timeout", type=options.seconds, metavar="SECONDS",
                       help=f"with --distributed: a process silent this long counts as lost, and the others end "
                            f"with exit status 69 (default {multihost.DEFAULT_HEARTBEAT_S}; JAX's runtime, which would "
                            "abort them instead, is given twice as long)")
    group.add_argument("--join-timeout", type=options.seconds, metavar="SECONDS",
                       help=f"with --distributed: how long the processes wait for one another to join, and for JAX's "
                            f"start-up, before ending with one sentence (default {multihost.DEFAULT_JOIN_S})")
    return parent


def _add_sweep(sub, setting: Setting, parents: list) -> None:
    presets = "\n".join(f"  {name:<18} {p.about}" for name, p in setting.presets.items())
    plain = setting.default_preset({})  # the preset a sweep without --preset or --env takes
    precedence = ("Precedence: the defaults shown below < --preset (without one, the preset the setting picks, named "
                  "like --env where one is" + (f"; with no option at all, {plain}" if plain else "") + ") < options "
                  "given here. So a default shown below is what a run gets only where no preset applies.")
    sweep = sub.add_parser(
        "sweep", help="train arms x hyper-parameter grid x seeds, chunked, with logs and checkpoints",
        allow_abbrev=False, formatter_class=argparse.RawDescriptionHelpFormatter, parents=parents,
        description="Train every arm (one compiled program each) on the grid of the hyper-parameters given "
                    "as lists times --seeds, vmapped; log, checkpoint and show progress between chunks.\n"
                    f"Setting {setting.name}: {setting.about}; arms: {setting.arms_help}.\n" + precedence,
        epilog=f"presets:\n{presets}\n\nenv names (--env): `cdjax envs` lists them; docs/envs.md says what each is.")
    run = sweep.add_argument_group("sweep (cdjax.runner.SweepSpec)")
    run.add_argument("--out", required=True, metavar="DIR", help="run directory (refuses one that holds another run)")
    run.add_argument("--resume", action="store_true", help="continue the run in --out from its latest checkpoint")
    run.add_argument("--restart-arm", nargs="+", metavar="ARM", default=(),
                     help="with --resume: train these arms again from update 0 (their checkpoints are moved aside, "
                          "their log rows dropped), e.g. when none of their checkpoints can be read")
    run.add_argument("--time-limit", type=options.seconds, metavar="SECONDS",
                     help="stop, checkpointed, before the chunk that would end SECONDS after this command started "
                          "(not recorded: each --resume gives its own; exit status 75)")
    run.add_argument("--preset", metavar="NAME",
                     help="named overrides, listed below (default: the one the setting picks, e.g. named like --env)")
    options.add_options(run, SweepSpec, dest="spec.", skip=SPEC_SKIP, switches=True, flags=FLAGS,
                        shown={"arms": setting.default_arms})
    options.add_options(
        sweep.add_argument_group(f"environment and agent ({setting.config_type.__module__}."
                                 f"{setting.config_type.__name__}; changing one recompiles)"),
        setting.config_type, dest="config.", skip=("num_updates",) + setting.arm_fields)
    options.add_options(
        sweep.add_argument_group(f"hyper-parameters ({setting.hparams_type.__module__}.{setting.hparams_type.__name__};"
                                 " traced): several values make a grid, vmapped with the seeds"),
        setting.hparams_type, dest="hp.", grid=True)
    phase = setting.phase
    if phase is not None:
        group = sweep.add_argument_group(f"{phase.title} ({phase.spec_type.__module__}.{phase.spec_type.__name__}): "
                                         "run by the arms it applies to before their updates, its env steps counted "
                                         "in --steps; any --phase-* option turns it on")
        onoff = group.add_mutually_exclusive_group()
        onoff.add_argument(f"--{phase.flag}", action="store_true", default=None, dest="phase_on",
                           help="run it (default: as the preset says; off without one)")
        onoff.add_argument(f"--no-{phase.flag}", action="store_false", dest="phase_on", help="do not run it")
        options.add_options(group, phase.spec_type, dest="phase.", prefix="--phase-")


def build_parser(setting: Setting | None = None) -> Parser:
    setting = setting or agents.get(agents.DEFAULT)
    parser = Parser(prog="cdjax", allow_abbrev=False,
                    description="Consistent dynamics models (Sodhani et al., 2019) on MuJoCo-MJX in JAX.")
    sub = parser.add_subparsers(dest="command", metavar="{sweep,eval,plot,envs}", required=True, parser_class=Parser)
    runtime_parent = _runtime_options()
    distributed_parent = _distributed_options()
    _add_sweep(sub, setting, [runtime_parent, distributed_parent])
    ev = sub.add_parser("eval", help="evaluate the saved policies of a run, per seed and per arm", allow_abbrev=False,
                        parents=[runtime_parent, distributed_parent])
    ev.add_argument("run_dir", metavar="RUN_DIR")
    ev.add_argument("--episodes", type=options.count, default=100, metavar="N", help="episodes per run (default 100)")
    mode = ev.add_mutually_exclusive_group()
    mode.add_argument("--stochastic", action="store_true",
                      help="sample actions (the default of settings whose sweeps evaluate so, e.g. atari)")
    mode.add_argument("--deterministic", action="store_true",
                      help="the deterministic action: the mean, or the most probable (the default elsewhere)")
    ev.add_argument("--video", action="store_true", help="also render a video of one episode per arm")
    plot = sub.add_parser("plot", help="curves and the summary table again from the logs", allow_abbrev=False,
                          parents=[runtime_parent])
    plot.add_argument("run_dirs", nargs="+", metavar="RUN_DIR",
                      help="a run directory; or several runs of one sweep started with other --seed values, whose "
                           "seeds are pooled (with --out)")
    plot.add_argument("--out", metavar="DIR",
                      help="write plots/ and summary.{md,csv} here (needed for several RUN_DIRs; default RUN_DIR)")
    plot.add_argument("--bootstrap-reps", type=options.count, default=2000, metavar="N",
                      help="bootstrap replications of the 95%% intervals (default 2000)")
    sub.add_parser("envs", help="list the env names --env takes", allow_abbrev=False)
    return parser


def setting_of(argv: Sequence[str]) -> Setting:
    """The setting whose options `cdjax sweep` offers: --setting, else the resumed run's, else the default."""
    pre = argparse.ArgumentParser(add_help=False)
    pre.add_argument("--setting")
    pre.add_argument("--out")
    pre.add_argument("--resume", action="store_true")
    known, _ = pre.parse_known_args(list(argv)[1:] if argv and argv[0] == "sweep" else [])
    name = known.setting
    if name is None and known.resume and known.out:
        try:
            name = io.RunDir(pathlib.Path(known.out)).read().get("setting")
        except io.RunDirError:
            name = None  # said when the sweep reads run.json
    return agents.get(name or agents.DEFAULT)


def sweep_spec(args: argparse.Namespace, setting: Setting, command: str = "") -> SweepSpec:
    """The SweepSpec that the sweep options describe (defaults < preset < explicit options)."""
    from cdjax.runner import preset_spec, resume_spec

    config_given, hp_given = options.given(args, "config."), options.given(args, "hp.")
    phase_given, spec_given = options.given(args, "phase."), options.given(args, "spec.")
    phase_on = getattr(args, "phase_on", None)
    if args.resume:
        flag = lambda prefix, name: prefix + name.replace("_", "-")  # noqa: E731
        extra = sorted({flag("--", k) for k in {**config_given, **hp_given}}
                       | {flag("--phase-", k) for k in phase_given}
                       | ({f"--{'' if phase_on else 'no-'}{setting.phase.flag}"} if phase_on is not None else set())
                       | {FLAGS.get(k, flag("--", k)) for k in spec_given if k not in RESUME_OPTIONS}
                       | ({"--preset"} if args.preset else set()))
        if extra:
            raise UsageError(f"--resume continues the run recorded in {args.out}/run.json, so {', '.join(extra)} "
                             "cannot be changed (only --steps and --no-progress, besides --time-limit and "
                             "--restart-arm).")
        return resume_spec(args.out, **spec_given)

    if setting.phase is not None and phase_given and phase_on is False:
        raise UsageError(f"--no-{setting.phase.flag} contradicts the --phase-* options given.")
    return preset_spec(args.out, setting.name, args.preset, config=config_given, hparams=hp_given,
                       phase=phase_given if setting.phase is not None else None,
                       phase_on=phase_on if setting.phase is not None else False, command=command,
                       **{k: v for k, v in spec_given.items() if k != "setting"})  # --setting: chose `setting`
