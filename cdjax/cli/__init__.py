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
import logging
import math
import os
import shlex
import signal
import sys
import time
from typing import Sequence

from cdjax import io, multihost, runtime
from cdjax.cli.commands import cmd_envs, cmd_eval, cmd_plot, cmd_sweep, say  # noqa: F401
from cdjax.cli.parser import build_parser, setting_of, sweep_spec  # noqa: F401
from cdjax.options import Parser, UsageError  # noqa: F401  (cdjax.cli.Parser for the benchmarks' commands)
from cdjax.protocol import ConfigError

def _join(args: argparse.Namespace) -> None:
    """--distributed: join the other processes before anything runs in JAX; its options alone are refused."""
    given = [flag for flag, value in (("--coordinator", args.coordinator), ("--num-processes", args.num_processes),
                                      ("--process-id", args.process_id), ("--heartbeat-timeout",
                                                                          args.heartbeat_timeout),
                                      ("--join-timeout", args.join_timeout)) if value is not None]
    if not args.distributed:
        if given:
            raise UsageError(f"{given[0]} goes with --distributed (every process of the sweep runs the same command "
                             "with --distributed).")
        return
    if args.command == "eval" and args.video:
        raise UsageError("--video renders on one process: run `cdjax eval RUN_DIR --video` without --distributed (one "
                         "process reads checkpoints that several wrote).")
    heartbeat = math.ceil(args.heartbeat_timeout) if args.heartbeat_timeout is not None else None
    join = args.join_timeout if args.join_timeout is not None else multihost.DEFAULT_JOIN_S
    multihost.initialize(args.coordinator, args.num_processes, args.process_id, heartbeat, arguments=_agreed(args),
                         join_s=join, say=say)


# Options that may differ between the processes of one sweep: each process's own number and waits, where its
# compilation cache is, how it compiles and reports, its own time limit (any process's stops all of them).
_OWN = {"process_id", "heartbeat_timeout", "join_timeout", "cache_dir", "compile_mode", "debug_nans", "disable_jit",
        "time_limit", "spec.progress", "coordinator"}


def _agreed(args: argparse.Namespace) -> dict:
    """What every process of a sweep must be given alike (out, arms, seeds, steps, config, grid, ...), as option
    name -> value in words, exchanged when they join (cdjax.multihost.join)."""
    def name(key: str) -> str:
        return "--" + key.split(".", 1)[-1].replace("_", "-") if key not in ("command", "run_dir", "run_dirs") else key

    def words(key: str, value) -> str:
        return os.path.normpath(value) if key in ("out", "run_dir") and isinstance(value, str) else repr(value)

    return {name(k): words(k, v) for k, v in sorted(vars(args).items()) if k not in _OWN}


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
    multihost.ending(2)
    if as_program:  # stderr goes quiet first, and the sentence is written to a copy of it
        _say_last(f"cdjax: {sentence}")
    else:
        print(f"cdjax: {sentence}", file=sys.stderr)
    raise SystemExit(2) from None


def _interrupted(sentence: str, status: int, as_program: bool) -> None:
    """End an interrupted command with its sentence. As a program, the process then ends at once: XLA's threads may
    still be compiling or running the program the signal interrupted, and tearing the interpreter down under them
    crashes (SIGSEGV instead of 130/143). Whatever had to be written was written and closed before this point."""
    multihost.ending(status)
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
            runtime.check_xla_flags()  # before JAX's backend starts: XLA would end the process on a bad flag
            _configure(args)
            if args.command in ("sweep", "eval"):
                _join(args)
                runtime.check_backend()  # JAX_PLATFORMS naming a backend this machine lacks: one sentence
            if args.command == "sweep":
                limit = TimeLimit(args.time_limit, start=started) if args.time_limit else None
                cmd_sweep(args, setting, " ".join(["cdjax"] + [shlex.quote(a) for a in argv]), limit)
            elif args.command == "eval":
                cmd_eval(args)
            else:
                cmd_plot(args)
            multihost.ending(0)  # the other processes of a sweep stop watching this one
    except (UsageError, ConfigError, io.RunDirError) as err:
        _refused(str(err), as_program)
    except Interrupted as err:
        done = ", ".join(f"{arm} {n}" for arm, n in err.updates.items())
        again = f"cdjax sweep --out {shlex.quote(str(err.run_dir))} --resume{multihost.resume_flags()}"
        if limit is not None and err.signum is None:  # (several processes: any process's time limit stops all)
            multihost.ending(75)
            print(f"Stopped before the time limit ({args.time_limit:g} s); checkpoint saved (updates per arm: {done}). "
                  f"Continue with: {again}", file=sys.stderr)
            raise SystemExit(75) from None
        terminated = err.signum == signal.SIGTERM
        multihost.ending(143 if terminated else 130)
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
    except Exception:  # a bug: its traceback follows; the other processes of a sweep are told this one ended
        multihost.ending(1)
        raise

