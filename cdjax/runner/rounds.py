"""The rounds of a sweep: `Loop` trains every arm in compiled chunks, one round of chunks at a time, logging,
checkpointing and evaluating between them (`cdjax.runner.loop.run_sweep` builds it); `Interrupted` and `TimeLimit`
are how a sweep is stopped early.
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import dataclasses
import math
import os
import pathlib
import shlex
import time
from typing import Callable, Mapping

import jax
import numpy as np

from cdjax import io, multihost, runtime
from cdjax.protocol import Setting
from cdjax.runner.arms import Arm, nanmean, restore, unreadable_text
from cdjax.runner.console import Clock, Progress, StopFlag
from cdjax.runner.evaluations import evaluate_arms, finished_evaluation
from cdjax.runner.plan import return_note
from cdjax.runner.spec import SweepSpec
from cdjax.sweep import unpad

AfterChunk = Callable[[int, dict[str, int]], "bool | None"]


class TimeLimit:
    """An `after_chunk` that stops a sweep before the round of chunks that would end `seconds` after `start` (a
    reading of `clock`; default: when this object is made), assuming the next round takes as long as the last
    one (evaluations between rounds included).

    Its first call (before the process's first round) only starts the clock of that round, so the compilation
    does not count as a round's length; it stops there only if the limit is already past. `reached` says
    whether it stopped the sweep.
    """

    def __init__(self, seconds: float, clock: Callable[[], float] = time.monotonic, start: float | None = None):
        if not seconds > 0:
            raise ValueError(f"a time limit must be positive, not {seconds}")
        self.seconds, self.clock = float(seconds), clock
        self.start = clock() if start is None else start
        self.last = self.start
        self.reached = self.started = False

    def __call__(self, rounds: int, updates: dict[str, int]) -> bool:
        now = self.clock()
        last_round = now - self.last if self.started else 0.0
        self.started = True
        self.last = now
        self.reached = now - self.start + last_round > self.seconds
        return self.reached


class Interrupted(KeyboardInterrupt):
    """The sweep stopped early (Ctrl-C, SIGTERM, or `after_chunk` said so) after saving its last completed chunk;
    `signum` is the signal that asked (None: `after_chunk`)."""

    def __init__(self, run_dir: pathlib.Path, updates: dict[str, int], signum: int | None = None):
        super().__init__(f"interrupted after {updates} updates")
        self.run_dir = run_dir
        self.updates = updates
        self.signum = signum


def _resume_hint(rd: io.RunDir) -> str:
    return f"cdjax sweep --out {shlex.quote(str(rd.path))} --resume{multihost.resume_flags()}"


@dataclasses.dataclass
class Loop:
    """The chunk loop's shared state and its steps."""

    rd: io.RunDir
    spec: SweepSpec
    setting: Setting
    arms: list[Arm]
    chunk: int  # updates per chunk
    progress: Progress
    after_chunk: AfterChunk | None = None
    clock: Clock = dataclasses.field(default_factory=Clock)
    tb: io.TensorBoard | None = None
    flag: StopFlag | None = None
    rounds: int = 0  # rounds of chunks done, counted from the start of the run (also across resumes)
    steps_this_process: int = 0  # env steps trained by this process (for its rate)
    extra_compile: float = 0.0  # seconds compiling chunk sizes that were not compiled in advance
    between_chunks: float = 0.0  # training seconds with no chunk of this process on its devices (`round`)
    snapshots: bool = True  # the devices have room for a copy of the states: a checkpoint need not hold the next chunk
    fetched_at: float = 0.0  # perf_counter when the last chunk's metrics reached the host
    launcher: concurrent.futures.ThreadPoolExecutor = dataclasses.field(  # calls the chunk programs (`dispatch`)
        default_factory=lambda: concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="cdjax-chunk"))
    complete_at_start: bool = False  # a resume found every arm done
    record: dict | None = None  # run.json to write (a resume writes it once every arm is restored)
    restart: set = dataclasses.field(default_factory=set)  # arms a resume trains again from update 0
    started: bool = False  # `start` is done
    writer: bool = dataclasses.field(default_factory=multihost.is_writer)  # this process writes the run directory
    timings: io.Timings = dataclasses.field(default_factory=io.Timings)  # where the time goes (timings.jsonl)

    def say(self, text: str) -> None:
        self.progress.say(text)

    def start(self, resume: bool, t_compile: float) -> None:
        """Initialise every arm (and restore it when resuming), write run.json, trim the logs to the checkpoints,
        say the plan."""
        t0 = time.perf_counter()
        multihost.tail(lambda: f"; {self.intact('')}")  # a lost process's sentence names the intact checkpoints
        for arm in self.arms:
            with self.timings.time(arm.name, "init", "init"):  # one arm's init at a time, to time each
                arm.state = jax.block_until_ready(arm.programs.pop("init")(arm.keys, arm.hps))
            arm.ckpt = io.Checkpoints(self.rd.checkpoints(arm.name))
            if not resume:
                continue
            if arm.name in self.restart:
                moved = arm.ckpt.set_aside_all("restarted")
                self.say(f"Restarting arm {arm.name} from update 0"
                         + (f"; its checkpoints were moved aside ({', '.join(p.name for p in moved)})." if moved
                            else "."))
                continue
            with self.timings.time(arm.name, "checkpoint", "restore"):
                restored = restore(arm)
            if not restored and arm.ckpt.unreadable:
                raise io.RunDirError(
                    f"{self.rd.path}: no checkpoint of arm {arm.name!r} can be read "
                    f"({unreadable_text(arm.ckpt.unreadable)}; moved aside, kept); add --restart-arm {arm.name} to "
                    "train it again from update 0.")
        if resume:
            with multihost.together():
                if self.writer:
                    self.rd.write(self.record)  # only now: a resume that refused above left run.json as it was
                    self._trim_logs()
        jax.block_until_ready([a.state for a in self.arms])
        self.rounds = max(math.ceil(a.updates / self.chunk) for a in self.arms)
        self.complete_at_start = resume and all(a.updates >= a.num_updates for a in self.arms)
        phased = [a for a in self.arms if a.plan.phase is not None]
        ignored = lambda a: (f"; the grid's {', '.join(a.plan.ignored)} "  # noqa: E731
                             f"{'does' if len(a.plan.ignored) == 1 else 'do'} not apply to it" if a.plan.ignored else "")
        self.say(f"Arms {', '.join(f'{a.name} ({a.num_runs} runs{ignored(a)})' for a in self.arms)}: "
                 + ", ".join(f"{a.name} {a.num_updates}" for a in self.arms)
                 + f" updates of {self.arms[0].steps_per_update:,} env steps per run in chunks of {self.chunk}"
                 + (f", after a {self.setting.phase.title} of {phased[0].plan.phase_steps:,} env steps "
                    f"({', '.join(a.name for a in phased)})" if phased else "")
                 + f"; setup {time.perf_counter() - t0:.1f} s, compile {t_compile:.1f} s"
                 + ("" if (mode := runtime.compile_mode()) == "default" else f" (compile mode {mode})")
                 + (f" with ${runtime.OPTIONS_ENV} {os.environ[runtime.OPTIONS_ENV].strip()}."
                    if runtime.environment_options() else "."))
        if note := return_note(self.setting, [a.plan for a in self.arms]):
            self.say(note)
        purge = {a.name: a.env_steps(a.updates + 1) for a in self.arms} if resume else None
        self.tb = io.TensorBoard(self.rd, purge_steps=purge)
        self.timings.add("all", "setup", "host", t0)
        self.started = True

    def _trim_logs(self) -> None:
        """Cut every log to the restored checkpoints (an arm started again from update 0 keeps no row), and count
        the steps each run skipped so far."""
        done = {a.name: a.updates if a.saved >= 0 else -1 for a in self.arms}
        dropped, torn = io.truncate_jsonl(self.rd.metrics, done)
        for path in (self.rd.eval, self.rd.phase):
            more, more_torn = io.truncate_jsonl(path, done)
            dropped, torn = dropped + more, torn + more_torn
        rows = io.read_jsonl(self.rd.metrics)
        skipped = self.setting.metrics.skipped
        if skipped is not None:
            by_arm = {a.name: a for a in self.arms}
            for row in rows:
                arm = by_arm.get(row["arm"])
                labels = arm.plan.labels if arm is not None else ()
                if arm is not None and row.get(skipped) and row.get("hp") in labels and row["seed"] < self.spec.seeds:
                    arm.skipped[labels.index(row["hp"]) * self.spec.seeds + int(row["seed"])] += row[skipped]
        progress = ", ".join(f"{a.name} {a.updates}/{a.num_updates}" for a in self.arms)
        note = ""
        if dropped:
            note = f"; dropped {dropped} log rows written after the last checkpoint" + (
                f" ({torn} of them a torn line left by a process killed while writing, or a line that is not a "
                "row: bytes that are not UTF-8, fields of the wrong types)" if torn else "")
        self.say(f"Resuming {self.rd.path}: updates done per arm: {progress}{note}.")
        self._say_stale(rows)
        for arm in self.arms:
            self._say_skipped(arm)

    def _say_stale(self, metric_rows) -> None:
        """A note (training goes on) when the directory holds logs or checkpoints of arms run.json does not name, e.g.
        an arm removed from run.json by hand: nothing of theirs is trimmed or trained, but the plots read them."""
        if note := self.rd.unnamed_arms((a.name for a in self.arms), metric_rows):
            self.say(note)

    def intact(self, when: str = " once that is fixed") -> str:
        """Which checkpoints survive a failed write (or a stop), and how to go on."""
        steps = {a.name: a.ckpt.latest() for a in self.arms if a.ckpt is not None}
        kept = [f"{name} at update {step}" for name, step in steps.items() if step is not None]
        where = (f"the previous checkpoints are intact ({', '.join(kept)})" if kept
                 else "no checkpoint had been written yet")
        return f"{where}; resume with `{_resume_hint(self.rd)}`{when}."

    # -- one step of the loop each ---------------------------------------------------------------------

    def run_phase(self, arm: Arm) -> None:
        """The phase of every run of `arm`: logged as update 0, checkpointed as step 0."""
        wall_start = arm.wall_offset + self.clock.now()
        state, info = arm.phase_program()(arm.state, arm.hps)  # donates arm.state
        info = unpad(multihost.fetch(info), arm.num_runs)
        arm.state, arm.phase_done = state, True
        took = info.pop("env_steps")
        if not np.all(took == arm.plan.phase_steps):
            raise RuntimeError(f"arm {arm.name}: the phase took {sorted(set(took.tolist()))} env steps, "
                               f"planned {arm.plan.phase_steps}")
        wall_end = arm.wall_offset + self.clock.now()
        phase = self.setting.phase
        rows = io.phase_rows(arm.name, arm.plan.labels, self.spec.seeds, info, arm.plan.phase_steps, wall_start,
                             wall_end, phase.as_metrics)
        with multihost.together():
            if self.writer:
                io.append_jsonl(self.rd.metrics, rows)
                io.append_jsonl(self.rd.phase, rows)
                self.tb.write(rows)
        self.steps_this_process += arm.plan.phase_steps * arm.num_runs
        ret = next((info[k] for k, v in phase.as_metrics.items() if v == self.setting.metrics.ret and k in info), None)
        if ret is not None and np.isfinite(ret).any():
            arm.last_return = nanmean(ret)
        self.say(f"{phase.title} of {arm.name}: {arm.plan.phase_steps:,} env steps per run in "
                 f"{wall_end - wall_start:.1f} s; {phase.describe({k: nanmean(v) for k, v in info.items()})}")
        self.save(arm)  # step 0: a resumed run restores it instead of running the phase again

    def dispatch(self, arm: Arm) -> None:
        """Start the arm's next chunk (asynchronously): `chunk` updates, or those left; `commit` (or `fetch`, then
        `log`) takes its results."""
        n = min(self.chunk, arm.num_updates - arm.updates)
        wall_start = arm.wall_offset + self.clock.now()
        program, state = arm.chunk_program(), arm.state
        arm.state = None  # the chunk donates it
        if multihost.count() == 1:
            # Launched from a thread of its own: on a GPU the call returns only once the chunk's loop has been run
            # (XLA launches its kernels from the calling thread, iteration after iteration), so called here it would
            # hold the host's logs and checkpoints until the chunk ends.
            launched = self.launcher.submit(program, state, arm.hps, np.int32(n))
        else:
            # Several processes issue their collectives (the chunk's, the metrics' gather, the exchanges around
            # writes and checkpoints) in the same order, or they wait on each other for ever: all from this thread.
            launched = concurrent.futures.Future()
            launched.set_result(program(state, arm.hps, np.int32(n)))
        arm.pending = (launched, n, wall_start)

    def commit(self, arm: Arm) -> None:
        """Fetch the pending chunk's metrics, log them, make its state the arm's state."""
        self.fetch(arm)
        self.log(arm)

    def fetch(self, arm: Arm) -> None:
        """Wait for the pending chunk: its metrics to the host (kept in arm.unlogged for `log`), its state the
        arm's state."""
        launched, n, wall_start = arm.pending
        new_state, metrics = launched.result()
        metrics = {name: m[:, :n] for name, m in unpad(multihost.fetch(metrics), arm.num_runs).items()}  # [R, n]
        self.fetched_at = time.perf_counter()
        wall_end = arm.wall_offset + self.clock.now()
        rows = io.metric_rows(arm.name, arm.plan.labels, self.spec.seeds, metrics, arm.updates, arm.steps_per_update,
                              wall_start, wall_end, steps_offset=arm.plan.phase_steps)
        arm.state, arm.updates, arm.pending, arm.unlogged = new_state, arm.updates + n, None, (metrics, rows)
        self.steps_this_process += n * arm.steps_per_update * arm.num_runs

    def log(self, arm: Arm) -> None:
        """Write the fetched chunk's rows (metrics.jsonl, TensorBoard) and say what its metrics call for."""
        metrics, rows = arm.unlogged
        arm.unlogged = None
        with multihost.together():  # a failed write ends every process before any checkpoint holds its updates
            if self.writer:
                with self.timings.time(arm.name, "metrics.jsonl", "write"):
                    io.append_jsonl(self.rd.metrics, rows)
                with self.timings.time(arm.name, "tensorboard", "write"):
                    self.tb.write(rows)
        ret = self.setting.metrics.ret
        if ret in metrics:
            arm.last_return = nanmean(metrics[ret][:, -1])
        skipped = self.setting.metrics.skipped
        if skipped in metrics:
            arm.skipped = arm.skipped + np.nan_to_num(np.asarray(metrics[skipped], float)).sum(axis=1)
            self._say_skipped(arm)
        self._say_watch(arm, metrics)

    def _say_watch(self, arm: Arm, metrics: Mapping) -> None:
        """The setting's watch on a chunk's metrics: said when it concerns more runs than it last said (a collapse
        that reaches 2 of 10 runs in the first chunk and all 10 later is said twice, not once)."""
        if self.setting.watch is None:
            return
        found = self.setting.watch(arm.name, arm.plan.config, metrics)
        if found is not None and found[0] > arm.warned:
            arm.warned = found[0]
            self.say(found[1])

    def _say_skipped(self, arm: Arm) -> None:
        """Say (once per new count of runs) which runs skipped optimiser steps for a non-finite loss or gradient."""
        bad = np.flatnonzero(arm.skipped > 0)
        if len(bad) <= arm.skipped_said:
            return
        arm.skipped_said = len(bad)
        seeds = self.spec.seeds
        runs = ", ".join(f"{arm.plan.labels[r // seeds]} seed {r % seeds}: {int(arm.skipped[r])} steps" for r in bad[:6])
        self.say(f"Arm {arm.name}: {len(bad)} of {arm.num_runs} runs skipped optimiser steps whose loss or gradient "
                 f"was not finite ({runs}{', ...' if len(bad) > 6 else ''}); those steps left the parameters as "
                 f"they were ({self.setting.metrics.skipped} in metrics.jsonl counts them).")

    def nonfinite_note(self) -> str:
        """For the progress line: the arms some of whose runs skipped non-finite steps."""
        bad = [f"{a.name} {int((a.skipped > 0).sum())}/{a.num_runs}" for a in self.arms if (a.skipped > 0).any()]
        return f"non-finite steps skipped in runs: {', '.join(bad)}" if bad else ""

    def save(self, arm: Arm, state=None) -> None:
        """Checkpoint the arm's state at its updates (`state`: a `io.snapshot` of it, taken before the next chunk
        donated it)."""
        if arm.saved != arm.updates:
            done = {"updates": arm.updates, "env_steps": arm.env_steps(), "wall_s": arm.wall_offset + self.clock.now(),
                    "chunk_updates": self.chunk, "run": arm.identity}
            with self.timings.time(arm.name, "checkpoint", "write"):  # the host's part: orbax writes in a thread
                arm.ckpt.save(arm.updates, arm.state if state is None else state, done, keep=self._keep(arm))
            arm.saved = arm.updates

    @staticmethod
    def _keep(arm: Arm):
        return arm.trainer.saved_leaves() if arm.trainer.saved_leaves is not None else None

    def stop(self) -> None:
        """Log and checkpoint what is done, then raise Interrupted."""
        for arm in self.arms:
            if arm.unlogged is not None:  # fetched, its rows not yet written (an interrupt in a round's host work)
                self.log(arm)
            if arm.pending is not None:
                self.commit(arm)
            self.save(arm)
        for arm in self.arms:
            arm.ckpt.wait()
        raise Interrupted(self.rd.path, {a.name: a.updates for a in self.arms}, self.flag.signum if self.flag else None)

    def round(self) -> tuple[bool, bool | None]:
        """One chunk of every arm with updates left (dispatched by the round before where it could be), logged and
        (every checkpoint_every rounds) saved; returns (whether it was the last, whether to stop: None when an
        evaluation comes first, after which `run` asks).

        The next round's chunks are dispatched as soon as this round's metrics are on the host and the sweep goes
        on, before this round's logs and checkpoints are written, so the devices do not wait for the host. A
        checkpoint then saves a copy of the state made on the devices before the next chunk donated it
        (`io.snapshot`, where the devices have room for it: `self.snapshots`), else its copy to the host is made
        first. Not dispatched ahead: after the last round, before a stop, and before an evaluation between rounds.
        """
        active = [a for a in self.arms if a.updates < a.num_updates]
        for arm in active:
            if "chunk" not in arm.programs:  # not compiled in advance (e.g. a resume that found nothing left)
                t0 = time.perf_counter()
                arm.chunk_program()
                self.extra_compile += time.perf_counter() - t0
        with self.clock.running():
            for arm in active:
                if arm.pending is None:
                    self.dispatch(arm)
            for arm in active:
                self.fetch(arm)
            self.rounds += 1
            last = all(a.updates >= a.num_updates for a in self.arms)
            # After the last round the time limit has nothing left to stop: a sweep that finished is complete, not
            # "stopped before the time limit" (only Ctrl-C or SIGTERM still stop it here). Before an evaluation
            # between rounds, `run` asks after it (the time limit counts it).
            evaluate = self.evaluates()
            stop = self.stop_requested() if last or evaluate else self.stop_asked()
            save = self.rounds % self.spec.checkpoint_every == 0 or last or stop
            ahead = not (last or stop or evaluate)
            copies = {}
            if save and ahead and self.snapshots:
                copies = {arm.name: io.snapshot(arm.state, self._keep(arm)) for arm in active}
            elif save and ahead:  # no room for a copy on the devices: to the host before the next chunk donates it
                for arm in active:
                    self.save(arm)
                    arm.ckpt.release()
            if ahead:
                for arm in self.arms:
                    if arm.updates < arm.num_updates:
                        self.dispatch(arm)
                # From the last chunk's metrics on the host to here no chunk of this process ran on its devices
                # (said in the "Trained in" line); the logs and checkpoints below are written while the next runs.
                self.between_chunks += time.perf_counter() - self.fetched_at
            for arm in active:
                self.log(arm)
            if save:
                for arm in active:
                    self.save(arm, copies.get(arm.name))
            for arm in active:  # the next chunk donates the saved buffers: free them; the last round's writes end here
                arm.ckpt.wait() if last else arm.ckpt.release()
            if not ahead:  # the devices waited for all of it
                self.between_chunks += time.perf_counter() - self.fetched_at
        return last, None if evaluate else stop

    def evaluates(self) -> bool:
        """Whether an evaluation comes after this round (eval_every; not after the last: the final one does)."""
        return (bool(self.spec.eval_every) and self.rounds % self.spec.eval_every == 0
                and any(a.updates < a.num_updates for a in self.arms))

    def report_progress(self) -> None:
        rate = self.steps_this_process / max(self.clock.total, 1e-9)
        left = sum((a.num_updates - a.updates) * a.steps_per_update * a.num_runs for a in self.arms)
        self.progress.update(min(a.env_steps() for a in self.arms), rate, {a.name: a.last_return for a in self.arms},
                             left / rate if rate > 0 else math.inf, self.nonfinite_note())

    def stop_asked(self) -> bool:
        asked = self.after_chunk is not None and self.after_chunk(self.rounds, {a.name: a.updates for a in self.arms})
        if multihost.count() == 1:
            return bool(asked) or self.flag.requested
        return self._agree_stop(bool(asked))

    def stop_requested(self) -> bool:
        """Whether Ctrl-C or SIGTERM asked to stop (several processes: any of them; the same answer on all)."""
        return self.flag.requested if multihost.count() == 1 else self._agree_stop(False)

    def _agree_stop(self, asked: bool) -> bool:
        """Several processes: stop if any process was asked to (its after_chunk, or a signal); a process stopped by
        another's signal takes that signal as its own (its sentence and exit status are the same)."""
        said = multihost.exchange(f"{int(asked)} {self.flag.signum if self.flag.requested else 0}")
        signals = [int(text.split()[1]) for text in said if int(text.split()[1])]
        if signals and not self.flag.requested:
            self.flag.requested, self.flag.signum = True, signals[0]
        return any(text.startswith("1") for text in said) or bool(signals)

    def run(self) -> None:
        with self.progress, StopFlag(self.say) as self.flag:
            try:
                for arm in self.arms:
                    if not arm.phase_done:
                        with self.clock.running():
                            self.run_phase(arm)
                            arm.ckpt.wait()
                        if self.stop_requested():
                            self.stop()
                if self.stop_asked():  # before this process's first round (after the phases)
                    self.stop()
                while any(a.updates < a.num_updates for a in self.arms):
                    last, stop = self.round()
                    self.report_progress()
                    if stop is None:  # an evaluation between rounds, then the question whether to stop
                        evaluate_arms(self.rd, self.arms, self.spec.seeds, self.spec.eval_episodes,
                                      not self.setting.eval_sampled, self.say)
                        stop = self.stop_asked()
                    if stop:
                        self.stop()
            except KeyboardInterrupt as err:
                if isinstance(err, Interrupted) or self.flag.forced:
                    raise
                self.stop()

    def close(self) -> None:
        self.launcher.shutdown(wait=False, cancel_futures=True)  # a chunk still running (a forced stop): at exit
        if self.tb is not None:
            self.tb.close()
        for arm in self.arms:
            if arm.ckpt is not None:
                arm.ckpt.close()
        # Called on the way out of an error too: a failure to write the timings must not hide the error in flight
        # (a full disk is said by the write that met it), so it is passed over here and said by `finish`'s write.
        with contextlib.suppress(io.WriteError):
            self.write_timings()

    def write_timings(self) -> None:
        """Append the timings not yet written to timings.jsonl (process 0, once run.json is there)."""
        if self.writer and self.rd.exists():
            self.timings.flush(self.rd.timings)

    def finish(self) -> None:
        """Say how training went; the final evaluation (once per run) and the plots (process 0)."""
        if self.complete_at_start:
            self.say(f"{self.rd.path} is complete: every arm has done its {self.arms[0].num_updates} updates.")
        else:
            rate = self.steps_this_process / max(self.clock.total, 1e-9)
            note = self.nonfinite_note()
            self.say(f"Trained in {self.clock.total:.1f} s ({rate:,.0f} env steps/s over all runs; "
                     f"{self.between_chunks:.1f} s of it between chunks: logs and checkpoints); "
                     f"compile {self.extra_compile:.1f} s more" + (f"; {note}." if note else "."))
        if not self.spec.final_eval:
            return
        deterministic = not self.setting.eval_sampled
        done = self.writer and finished_evaluation(self.rd, self.arms, self.spec.seeds, self.spec.eval_episodes,
                                                   deterministic)
        if multihost.from_writer("done" if done else "") == "done":  # process 0 reads eval.jsonl, for all
            self.say("The final evaluation is already in eval.jsonl.")
        else:
            evaluate_arms(self.rd, self.arms, self.spec.seeds, self.spec.eval_episodes, deterministic, self.say)
        if not self.writer:
            return
        try:
            from cdjax.plots import plot_run
        except ImportError as err:  # an install without the plotting stack (e.g. a bare GPU image)
            self.say(f"No plots or summary: {err}; `cdjax plot {self.rd.path}` makes them where it is installed.")
            return
        note = return_note(self.setting, [a.plan for a in self.arms])  # said at the start, kept under the table
        with self.timings.time("all", "plots", "write"):
            written = plot_run(self.rd.path, reps=self.spec.bootstrap_reps, say=self.say, notes=[note] if note else [])
        self.say(f"Wrote {', '.join(str(p) for p in written.values())}.")
