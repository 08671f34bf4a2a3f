"""The chunk loop: `run_sweep(spec)` plans, checks memory, compiles, then trains every arm in compiled chunks,
logging, checkpointing and evaluating between them (the rounds themselves: cdjax.runner.rounds).

Everything that can be refused (bad options, a directory holding another run, a sweep that cannot fit
in memory, a checkpoint of another run than run.json's, `--steps` below what is done) is refused before the run
directory is touched. A resumed sweep restores the newest readable checkpoint of each arm (checked against the
run first: `survey`), drops the log rows written after it and continues: on CPU the numbers equal those of an
uninterrupted run. Ctrl-C or SIGTERM finishes the chunk in flight, saves it and raises `Interrupted`; a
second Ctrl-C stops at once, keeping the previous checkpoint. `after_chunk=TimeLimit(seconds)` stops the same
way before a round of chunks that would end past a wall-clock budget (a cluster job's, a leased machine's). A
write that fails (a full disk) raises io.WriteError naming the file and the checkpoints that are intact.

Several processes (`cdjax sweep --distributed`, cdjax.multihost): every process runs this same loop on its own
devices' share of the runs. Process 0 alone writes the run directory and holds its lock; results are brought back
whole to every process (`multihost.fetch`), and what one process alone meets (a refusal, a failed write, a signal,
its time limit) is exchanged where every process is at the same point, so that all refuse, fail or stop after the
same chunk, with the same checkpoint. A process that is lost ends the others with `multihost.PeerLost`.
"""

from __future__ import annotations

import collections
import contextlib
import dataclasses
import importlib
import pathlib
import threading
import time
from typing import Sequence

from cdjax import budget, io, multihost, runtime
from cdjax.protocol import ConfigError, Setting
from cdjax.runner.arms import Arm, abstract_state, build, check_memory, compile_all, expectation, unreadable_text
from cdjax.runner.console import Progress, Stopped, library_log, stopped
from cdjax.runner.evaluations import check_evaluation, compile_evaluators
from cdjax.runner.plan import plan_arms, run_record, same_run, without_retired
from cdjax.runner.rounds import (  # noqa: F401  (TimeLimit: importable from here as before)
    AfterChunk, Interrupted, Loop, TimeLimit, _resume_hint)
from cdjax.runner.spec import SweepSpec, out_dir, resolve


def prepare(spec: SweepSpec, resume: bool) -> tuple[SweepSpec, list, dict]:
    """Plan the sweep and check it against its directory: (resolved spec, plans, run.json); writes nothing."""
    spec, _, plans, record = _prepare(spec, resume)
    return spec, plans, record


def _prepare(spec: SweepSpec, resume: bool) -> tuple[SweepSpec, Setting, list, dict]:
    """`prepare`, with the setting it resolved (once) for the rest of the sweep."""
    rd = io.RunDir(out_dir(spec))
    rd.check_name()  # before anything reads or writes there
    spec, setting = resolve(spec)
    old = None
    if resume:
        old = without_retired(rd.read(), rd.run_json)
        if old.get("version") != io.RUN_VERSION:
            raise io.RunDirError(f"{rd.path} was written by an older cdjax (run.json version {old.get('version')}); "
                                 "it can be plotted and evaluated but not resumed.")
        if not spec.chunk_updates:  # "about 5%" of a longer run would change the chunks: keep the recorded ones
            spec = dataclasses.replace(spec, chunk_updates=old.get("chunk_updates", 0))
    plans = plan_arms(spec, setting)
    record = run_record(spec, plans, setting)
    if resume:
        if not same_run(old, record):
            raise io.RunDirError(f"{rd.path} holds a different run than the one asked to resume; "
                                 "resume it without changing its settings (only --steps may change).")
        record["command"] = old.get("command", "")
        before = old.get("code")  # the code the run was started and resumed with, the first first; a resume
        before = before if isinstance(before, list) else []  # with the same code as the last adds nothing
        record["code"] = before if before[-1:] == record["code"] else before + record["code"]
    elif rd.exists():
        raise io.RunDirError(f"{rd.path} already holds a run; continue it with --resume, or choose another --out.")
    elif rd.path.is_dir() and any(not io.left_before_a_run(p.name) for p in rd.path.iterdir()):
        raise io.RunDirError(f"{rd.path} exists and is not empty; choose another --out.")
    rd.check_writable()
    return spec, setting, plans, record


def survey(rd: io.RunDir, arms: list[Arm], restart: set[str]) -> dict[str, int]:
    """Updates of the checkpoint each arm will resume from (-1: it starts at update 0), read from the checkpoints'
    records alone (no array, nothing moved or written). One sentence (RunDirError) when a checkpoint belongs to
    another run than run.json's (io.CheckpointMismatch), when no checkpoint of an arm can be read or an arm has
    logged updates but no checkpoint (unless it is in `restart`), or when the run would end before what is done."""
    done, logged = {}, None
    for arm in arms:
        if arm.name in restart:
            done[arm.name] = -1
            continue
        step, unreadable = None, []
        if io.checkpoints.step_dirs(rd.checkpoints(arm.name)):
            ckpt = io.Checkpoints(rd.checkpoints(arm.name))
            try:
                step, unreadable = ckpt.inspect(abstract_state(arm), expectation(arm))
            finally:
                ckpt.close()
        if step is None:
            if logged is None:
                logged = collections.Counter(r["arm"] for r in io.read_jsonl(rd.metrics))
            lost = (f"no checkpoint of arm {arm.name!r} can be read ({unreadable_text(unreadable)})" if unreadable
                    else f"arm {arm.name!r} has {logged[arm.name]} logged rows but no checkpoint"
                    if logged[arm.name] else None)
            if lost is not None:
                raise io.RunDirError(f"{rd.path}: {lost}; nothing was changed: add --restart-arm {arm.name} to train "
                                     "it again from update 0 (its checkpoints are moved aside, its log rows dropped).")
        done[arm.name] = -1 if step is None else step
        if done[arm.name] > arm.num_updates:
            need = arm.plan.phase_steps + done[arm.name] * arm.steps_per_update
            raise io.RunDirError(f"{rd.path}: arm {arm.name!r} has done {done[arm.name]} updates, more than the "
                                 f"{arm.num_updates} that --steps gives it; nothing was changed: give --steps of at "
                                 f"least {need:,}, or leave --steps out.")
    return done


def run_sweep(spec: SweepSpec, resume: bool = False, after_chunk: AfterChunk | None = None,
              restart: Sequence[str] = ()) -> pathlib.Path:
    """Train every arm of `spec` in chunks, logging and checkpointing into spec.out; returns the run dir.

    `after_chunk(rounds done, updates per arm)` is called before this process's first round of chunks (after the
    phases; rounds counts those of earlier processes of a resumed run) and after each round; True stops the
    sweep as Ctrl-C does. `restart` (with `resume`): arms trained again from update 0, their checkpoints moved
    aside and their log rows dropped. Raises ConfigError / io.RunDirError (one sentence) for input that cannot
    run, `Interrupted` when stopped early (after saving a checkpoint of every arm), console.Stopped (a sentence
    true for the moment) when a KeyboardInterrupt comes outside the chunk loop.
    """
    runtime.apply_xla_defaults()  # cdjax's XLA flags (importing cdjax adds none); a no-op when the CLI applied them
    rd = io.RunDir(out_dir(spec))
    writer = multihost.is_writer()
    timings = io.Timings(multihost.index())
    try:
        with multihost.together():  # several processes: each refuses what one refuses (in one sentence)
            with timings.time("all", "plan", "host"):
                runtime.environment_options()  # $CDJAX_XLA_OPTIONS refused now, not after the build
                spec, setting, plans, record = _prepare(spec, resume)
            timings.add_startup()  # the `cdjax` command's start-up before this call, where it started the process
            rd = io.RunDir(pathlib.Path(spec.out))
            restart = set(restart)
            if restart and not resume:
                raise ConfigError("--restart-arm trains an arm of a run again: give it with --resume.")
            unknown = sorted(restart - {p.name for p in plans})
            if unknown:
                raise ConfigError(f"--restart-arm {unknown[0]}: the run has no such arm; its arms are "
                                  f"{', '.join(p.name for p in plans)}.")
            progress = Progress(spec.progress, record["total_env_steps"], quiet=not writer)
            with timings.time("all", "build", "host"):
                arms = [build(plan, spec, setting) for plan in plans]
            for arm in arms:
                arm.timings = timings
            check_evaluation(arms, spec, resume, progress.say)
            with timings.time("all", "memory", "host"):
                states = check_memory(arms, spec)
            for arm in arms:
                arm.keys, arm.hps = arm.sweep.grid(spec.seed, spec.seeds, arm.plan.hparams)
            done = survey(rd, arms, restart) if resume else {}
            progress.say(f"Compiling the programs of {', '.join(a.name for a in arms)} (nothing is written before "
                         "they are compiled and fit in memory).")
            t_compile = time.perf_counter()
            # orbax (most of two seconds of imports, which the first checkpoint manager would run between the arms'
            # inits) while the programs compile: the compiling threads leave this thread mostly waiting
            threading.Thread(target=_import_ahead, args=("orbax.checkpoint",), name="cdjax-orbax-import",
                             daemon=True).start()
            have, where = budget.available()
            for arm in arms:  # a program scheduled by data flow that would not fit is compiled in order instead
                arm.room = have - states
            compile_all(arms, record["chunk_updates"], done)
            t_compile = time.perf_counter() - t_compile
            if spec.final_eval or spec.eval_every:  # compiled while training runs, not after it
                compile_evaluators(arms, spec.eval_episodes, not setting.eval_sampled)
            if writer and spec.final_eval:  # the plots' imports (matplotlib: about a second) while training runs
                threading.Thread(target=_import_ahead, args=("cdjax.plots",), name="cdjax-plots-import",
                                 daemon=True).start()
            for arm in arms:
                for what, (wide, narrow) in arm.in_order.items():
                    progress.say(f"{arm.name}'s {what} program runs its GPU kernels in XLA's program order: with them "
                                 f"scheduled by data flow (cdjax's default, 10-20% faster) it needs "
                                 f"{budget.gb(wide or 0)} beside the states' {budget.gb(states)}, and there are "
                                 f"{budget.gb(have)} {where}; in order it needs {budget.gb(narrow or 0)}.")
            # init's output is the state, already counted; the phase and chunk programs donate it and return it
            with timings.time("all", "programs", "host"):
                spare = budget.check_programs(states, {f"{arm.name} {what}": p for arm in arms
                                                       for what, p in arm.programs.items() if what != "init"})
    except KeyboardInterrupt as err:
        where = (f"{rd.path} is as it was; resume with `{_resume_hint(rd)}`" if resume
                 else f"nothing was written to {rd.path}")
        raise stopped(err, f"Interrupted before training started (while planning or compiling); {where}.") from None
    except multihost.PeerLost as err:
        raise multihost.PeerLost(f"{err} before training started; " + (
            f"{rd.path} is as it was; resume with `{_resume_hint(rd)}`." if resume
            else f"nothing was written to {rd.path}.")) from None

    try:
        with contextlib.ExitStack() as held:
            with multihost.together():  # process 0 makes the directory, holds it and writes run.json
                if writer:
                    rd.create()  # the first write: everything above could still refuse
                    held.enter_context(rd.lock())
                    if not resume and rd.exists():  # another process started this run while we compiled
                        raise io.RunDirError(f"{rd.path} already holds a run; continue it with --resume, or choose "
                                             "another --out.")
                    if not resume:
                        rd.write(record)
            # A checkpoint's copy of the states on the devices (the next chunk starts before it goes to the host)
            # where they have room for it, with a tenth of the rest to spare.
            return _train(Loop(rd, spec, setting, arms, record["chunk_updates"], progress, after_chunk,
                               record=record, restart=restart, snapshots=states <= 0.9 * spare, timings=timings), resume,
                          t_compile)
    except (Interrupted, Stopped):
        raise
    except KeyboardInterrupt as err:  # between the compilation and the loop: run.json may be written, no update
        raise stopped(err, f"Interrupted before training started; no update was trained in {rd.path}"
                           + (f"; resume with `{_resume_hint(rd)}`." if rd.exists() else ".")) from None
    except multihost.PeerLost as err:
        if err.complete:  # said by _train, with the checkpoints that are intact
            raise
        raise multihost.PeerLost(f"{err} before training started; no update was trained in {rd.path}"
                                 + (f"; resume with `{_resume_hint(rd)}`." if resume or rd.exists() else ".")) from None


def _import_ahead(module: str) -> None:
    """Import `module` ahead of its use (which imports it again, then at once); an install without it says so
    there."""
    with contextlib.suppress(ImportError):
        importlib.import_module(module)


def _train(loop: Loop, resume: bool, t_compile: float) -> pathlib.Path:
    """Run the loop; a failed write or a lost process names the checkpoints that are intact; a KeyboardInterrupt
    outside the chunk loop (restoring, the final evaluation) becomes a Stopped that says what is true then."""
    with library_log(loop.rd.process_log(multihost.index()), loop.say):
        try:
            try:
                loop.start(resume, t_compile)
            except KeyboardInterrupt as err:
                raise stopped(err, f"Interrupted before training {'resumed' if resume else 'started'}; "
                                   f"{loop.rd.path} keeps {'its checkpoints' if resume else 'run.json and no update'}; "
                                   f"resume with `{_resume_hint(loop.rd)}`.") from None
            finally:
                if not loop.started:
                    loop.close()
            try:
                loop.run()
            except KeyboardInterrupt as err:
                if isinstance(err, Interrupted):
                    raise
                raise stopped(err, f"Stopped at once, without saving the chunk in flight; {loop.intact('')}") from None
            finally:
                loop.close()
            try:
                loop.finish()
                loop.write_timings()  # the final evaluation's and the plots' rows
            except KeyboardInterrupt as err:
                raise stopped(err, f"Interrupted after training (every arm is trained and checkpointed) during the "
                                   f"final evaluation or plots; `{_resume_hint(loop.rd)}` makes them.") from None
        except io.WriteError as err:
            raise io.WriteError(f"{err}; {loop.intact()}") from None
        except multihost.PeerLost as err:
            raise multihost.PeerLost(f"{err}; {loop.intact('')}", complete=True) from None
    return loop.rd.path
