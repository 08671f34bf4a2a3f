"""The `cdjax` command: sweep, eval, plot, envs.

    cdjax sweep --env ant --seeds 16 --alpha 0 1.0 --horizon 20 --steps 50_000_000 --out runs/ant-cd
    cdjax sweep --out runs/ant-cd --resume
    cdjax eval  runs/ant-cd --episodes 100
    cdjax plot  runs/ant-cd
    srun cdjax sweep --distributed --env ant --seeds 64 --out /shared/runs/ant   # one process per node (cdjax.multihost)

Every option of `sweep` comes from a dataclass field (cdjax.options): the SweepSpec's, one per field of the
setting's Config (except the fields an arm name sets and `num_updates`, derived from --steps), one per
HParams field taking one or several values (their Cartesian product is the grid, vmapped with the seeds)
and one per field of the setting's phase (--phase-<field>). `--setting` picks the agent (cdjax.agents).

Bad input ends with one sentence on stderr and exit status 2; an interrupted command says in one sentence what is
true for it (a sweep checkpoints the chunk in flight first) and exits with 130 after Ctrl-C, 143 after SIGTERM (what
SLURM, Kubernetes and `timeout` send: handled as the first Ctrl-C); a sweep stopped by its --time-limit exits with 75
(EX_TEMPFAIL: continue it with --resume). A sweep of several processes (--distributed) whose process was lost ends
the others with one sentence and exit status 69 (EX_UNAVAILABLE: continue it with --resume).
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import math
import os
import pathlib
import shlex
import signal
import sys
import time
from typing import Sequence

from cdjax import agents, io, multihost, options, runtime
from cdjax.options import Parser, UsageError  # noqa: F401  (cdjax.cli.Parser for the benchmarks' commands)
from cdjax.protocol import ConfigError, Setting
from cdjax.runner.spec import FLAGS, INT32_MAX, SweepSpec

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
                       help=f"with --distributed: a process silent this long counts as lost (default "
                            f"{multihost.DEFAULT_HEARTBEAT_S}, JAX's)")
    return parent


def _join(args: argparse.Namespace) -> None:
    """--distributed: join the other processes before anything runs in JAX; its options alone are refused."""
    given = [flag for flag, value in (("--coordinator", args.coordinator), ("--num-processes", args.num_processes),
                                      ("--process-id", args.process_id), ("--heartbeat-timeout",
                                                                          args.heartbeat_timeout)) if value is not None]
    if not args.distributed:
        if given:
            raise UsageError(f"{given[0]} goes with --distributed (every process of the sweep runs the same command "
                             "with --distributed).")
        return
    if args.command == "eval" and args.video:
        raise UsageError("--video renders on one process: run `cdjax eval RUN_DIR --video` without --distributed (one "
                         "process reads checkpoints that several wrote).")
    heartbeat = math.ceil(args.heartbeat_timeout) if args.heartbeat_timeout is not None else None
    multihost.initialize(args.coordinator, args.num_processes, args.process_id, heartbeat)


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


def cmd_sweep(args: argparse.Namespace, setting: Setting, command: str, limit=None) -> None:
    from cdjax.runner import run_sweep

    io.RunDir(pathlib.Path(args.out)).check_name()
    out = run_sweep(sweep_spec(args, setting, command), resume=args.resume, after_chunk=limit,
                    restart=tuple(args.restart_arm))
    if multihost.is_writer():
        print(f"Done: {out}")


def say(text: str) -> None:
    print(text, file=sys.stderr, flush=True)


def _say_unnamed_arms(rd: io.RunDir, tell=say) -> None:
    """`cdjax eval` and `cdjax plot` say, as a resume does (cdjax.runner.loop), when the directory holds logs or
    checkpoints of arms its run.json does not name (`RunDir.unnamed_arms`): a note, the command goes on."""
    if note := rd.unnamed_arms():
        tell(note)


def cmd_eval(args: argparse.Namespace) -> None:
    import jax

    from cdjax.evaluate import render_video
    from cdjax.runner import evaluate_arms, restore_arms
    from cdjax.runner.console import library_log, stopped

    if not 1 <= args.episodes <= INT32_MAX:
        raise UsageError(f"--episodes must be an integer from 1 to {INT32_MAX:,}, got {args.episodes}.")
    rd = io.RunDir(pathlib.Path(args.run_dir))
    writer = multihost.is_writer()
    tell = say if writer else (lambda text: None)  # several processes: process 0 speaks for all
    with multihost.together():
        rd.check_name("RUN_DIR")
        rd.read()  # a clear error for a directory that holds no run
    try:
        with contextlib.ExitStack() as held, library_log(rd.process_log(multihost.index()), tell):
            with multihost.together():
                if writer:  # a live sweep turns its checkpoints over and appends to eval.jsonl: not beside it
                    held.enter_context(rd.lock("evaluate it when it has ended (its checkpoints turn over while it "
                                               "trains)"))
                    _say_unnamed_arms(rd, tell)
                spec, arms = restore_arms(args.run_dir)
            sampled = args.stochastic or (agents.get(spec.setting).eval_sampled and not args.deterministic)
            records = evaluate_arms(rd, arms, spec.seeds, args.episodes, not sampled, tell)
    except KeyboardInterrupt as err:
        raise stopped(err, f"Interrupted before the evaluation was done; nothing was added to {rd.eval}.") from None
    except multihost.PeerLost as err:
        raise multihost.PeerLost(f"{err}; nothing was added to {rd.eval}.", complete=True) from None
    if not writer:
        return
    _print_eval(records)
    print(f"Appended {len(records)} records to {rd.eval}")
    if args.video:
        try:
            for arm in arms:
                for i, label in enumerate(arm.plan.labels):
                    policy = jax.tree.map(lambda x: x[i * spec.seeds], arm.trainer.policy(arm.state))  # seed 0
                    path = render_video(arm.trainer, policy, jax.random.key(spec.seed),
                                        rd.path / "videos" / f"{arm.name}-{label}-seed0.mp4",
                                        steps=arm.trainer.eval_env(1).episode_length)
                    if path is not None:
                        print(f"Wrote {path}")
        except KeyboardInterrupt as err:
            raise stopped(err, f"Interrupted while rendering videos into {rd.path / 'videos'}; the evaluation is in "
                               f"{rd.eval}.") from None


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
    from cdjax.plots import plot_run, plot_runs
    from cdjax.runner.console import stopped
    from cdjax.runner.plan import recorded_return_note

    dirs, runs = [], []
    for run_dir in args.run_dirs:
        rd = io.RunDir(pathlib.Path(run_dir))
        rd.check_name("RUN_DIR")
        runs.append(rd.read())  # a clear error for a directory that holds no run
        _say_unnamed_arms(rd)
        dirs.append(rd.path)
    if len(set(d.resolve() for d in dirs)) < len(dirs):
        raise UsageError("a RUN_DIR is named twice; name each run once.")
    if len(dirs) > 1 and args.out is None:
        raise UsageError("several RUN_DIRs are pooled into one summary: name where it goes with --out DIR.")
    if not 1 <= args.bootstrap_reps <= INT32_MAX:
        raise UsageError(f"--bootstrap-reps must be an integer from 1 to {INT32_MAX:,}, got {args.bootstrap_reps}.")
    out = dirs[0] if args.out is None else pathlib.Path(args.out)
    if args.out is not None:
        io.RunDir(out).check_name("--out")
        if out.exists() and not out.is_dir():
            raise UsageError(f"--out {out} is a file; name a directory.")
        if len(dirs) > 1 and out.resolve() in {d.resolve() for d in dirs}:
            raise UsageError(f"--out {out} is one of the runs, whose own summary the pooled one would replace; "
                             "name another directory.")
    again = " ".join(shlex.quote(str(a)) for a in (*dirs, *(("--out", out) if args.out is not None else ())))
    notes = [note] if (note := recorded_return_note(runs)) else []  # what the sweep said of its ranking, as recorded
    try:
        if len(dirs) == 1 and args.out is None:
            written = plot_run(out, reps=args.bootstrap_reps, say=say, notes=notes)
        else:
            written = plot_runs(dirs, out, reps=args.bootstrap_reps, say=say, notes=notes)
    except KeyboardInterrupt as err:
        raise stopped(err, f"Interrupted while plotting; the plots and summary of {out} may be partly rewritten: "
                           f"run `cdjax plot {again}` again.") from None
    for path in written.values():
        print(f"Wrote {path}")


def cmd_envs() -> None:
    """Print every env name `--env` takes, one a line, with what it is (cdjax.envs.describe)."""
    from cdjax import envs

    for name, about in envs.describe().items():
        print(f"{name:<29} {about}")


class _QuietForeignThreads:
    """sys.stderr for the `cdjax` command: once a write has failed (io.WRITE_FAILED), text written from any thread
    but the main one (tensorstore's callbacks and orbax's own threads finishing its abandoned checkpoint writes:
    "Event loop is closed" tracebacks and absl's "RESOURCE_EXHAUSTED" errors, printed before the command's one
    sentence) is dropped; everything else passes."""

    def __init__(self, stream):
        self._stream = stream

    def write(self, text: str) -> int:
        import threading

        if io.WRITE_FAILED.is_set() and threading.current_thread() is not threading.main_thread():
            return len(text)
        return self._stream.write(text)

    def __getattr__(self, name):  # flush, fileno, isatty, encoding, ...
        return getattr(self._stream, name)


def _say_last(sentence: str) -> None:
    """Write the one sentence that ends the process, and nothing after it: stderr (fd 2) is sent to /dev/null
    first and the sentence written to a copy of the original. A sweep stopped by a write error can leave a
    library's background threads (orbax's asyncio loop) printing tracebacks while the interpreter shuts down,
    and they started in the middle of the sentence when it was printed first; none of that is for the user."""
    sys.stderr.flush()
    original = os.dup(2)
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, 2)
    os.close(devnull)
    os.write(original, (sentence + "\n").encode())
    os.close(original)


def _cache_dir(args: argparse.Namespace) -> tuple[str | None, str]:
    """(the persistent compilation cache to use, where it came from in words)."""
    import jax

    if args.cache_dir:
        return args.cache_dir, "--cache-dir"
    if jax.config.jax_compilation_cache_dir:  # set by the caller (a notebook, the tests)
        return jax.config.jax_compilation_cache_dir, "the compilation cache"
    if os.environ.get(runtime.CACHE_ENV):
        return os.environ[runtime.CACHE_ENV], f"${runtime.CACHE_ENV}"
    return runtime.default_cache_dir(), "the default compilation cache"


def _configure(args: argparse.Namespace) -> None:
    cache, source = _cache_dir(args)
    # the flag, else $CDJAX_COMPILE_MODE (checked before anything runs), else default: never an earlier call's flag
    mode = args.compile_mode or runtime.environment_compile_mode()
    try:
        runtime.configure(cache_dir=cache, debug_nans=args.debug_nans, disable_jit=args.disable_jit,
                          cache_source=source, compile_mode=mode)
    except ConfigError:
        if source != "the default compilation cache":
            raise
        runtime.configure(debug_nans=args.debug_nans, disable_jit=args.disable_jit,  # run without the cache
                          compile_mode=mode)
        say(f"Note: {cache} cannot hold JAX's compilation cache; compiling without it (--cache-dir names another).")
    # $CDJAX_XLA_OPTIONS checked before anything runs too; after the cache is set, since XLA checks them by
    # compiling, and JAX settles whether the persistent cache is used at a process's first compile
    runtime.environment_options()


def _refused(sentence: str, as_program: bool) -> None:
    """End a command that cannot run: `cdjax: <sentence>` and exit status 2."""
    if as_program:  # stderr goes quiet first, and the sentence is written to a copy of it
        _say_last(f"cdjax: {sentence}")
    else:
        print(f"cdjax: {sentence}", file=sys.stderr)
    raise SystemExit(2) from None


def _interrupted(sentence: str, status: int, as_program: bool) -> None:
    """End an interrupted command with its sentence. As a program, the process then ends at once: XLA's threads may
    still be compiling or running the program the signal interrupted, and tearing the interpreter down under them
    crashes (SIGSEGV instead of 130/143). Whatever had to be written was written and closed before this point."""
    print(sentence, file=sys.stderr)
    if as_program:
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(status)
    raise SystemExit(status) from None


def main(argv: Sequence[str] | None = None) -> None:
    """The `cdjax` command; argv None: this process's arguments (and the process ends after it)."""
    started = time.monotonic()  # --time-limit counts from here (the imports before are not counted)
    as_program = argv is None
    argv = list(sys.argv[1:] if argv is None else argv)
    runtime.apply_xla_defaults()  # cdjax's XLA flags, before a backend starts (importing cdjax adds none)
    if as_program and not isinstance(sys.stderr, _QuietForeignThreads):
        quiet = _QuietForeignThreads(sys.stderr)
        for handler in logging.getLogger().handlers:  # orbax's import gives the root logger a handler on stderr
            if isinstance(handler, logging.StreamHandler) and handler.stream is sys.stderr:
                handler.setStream(quiet)
        sys.stderr = quiet
    from cdjax.runner import Interrupted, TimeLimit
    from cdjax.runner.console import Stopped, Terminated, raise_on_sigterm

    limit = None
    try:
        with raise_on_sigterm():
            setting = setting_of(argv)
            try:
                args = build_parser(setting).parse_args(argv)
            except UsageError as err:  # unknown options are reported by the top parser: name the subcommand
                if argv and argv[0] in ("sweep", "eval", "plot", "envs"):
                    raise UsageError(str(err).replace("`cdjax --help`", f"`cdjax {argv[0]} --help`")) from None
                raise
            if args.command == "envs":
                return cmd_envs()
            _configure(args)
            if args.command in ("sweep", "eval"):
                _join(args)
            if args.command == "sweep":
                limit = TimeLimit(args.time_limit, start=started) if args.time_limit else None
                cmd_sweep(args, setting, " ".join(["cdjax"] + [shlex.quote(a) for a in argv]), limit)
            elif args.command == "eval":
                cmd_eval(args)
            else:
                cmd_plot(args)
    except (UsageError, ConfigError, io.RunDirError) as err:
        _refused(str(err), as_program)
    except Interrupted as err:
        done = ", ".join(f"{arm} {n}" for arm, n in err.updates.items())
        again = f"cdjax sweep --out {shlex.quote(str(err.run_dir))} --resume{multihost.resume_flags()}"
        if limit is not None and err.signum is None:  # (several processes: any process's time limit stops all)
            print(f"Stopped before the time limit ({args.time_limit:g} s); checkpoint saved (updates per arm: {done}). "
                  f"Continue with: {again}", file=sys.stderr)
            raise SystemExit(75) from None
        terminated = err.signum == signal.SIGTERM
        print(f"{'Stopped by SIGTERM' if terminated else 'Interrupted'}; checkpoint saved in {err.run_dir} (updates "
              f"per arm: {done}). Resume with: {again}", file=sys.stderr)
        raise SystemExit(143 if terminated else 130) from None
    except Stopped as err:
        _interrupted(err.sentence, 143 if err.terminated else 130, as_program)
    except multihost.PeerLost as err:  # ends at once: JAX's own shutdown would wait for the process that is gone
        _interrupted(f"cdjax: {err}", multihost.PEER_LOST_STATUS, as_program)
    except KeyboardInterrupt as err:  # before a command started (parsing, imports, the cache)
        _interrupted("Interrupted before the command started; nothing was written.",
                     143 if isinstance(err, Terminated) else 130, as_program)


if __name__ == "__main__":
    main()
