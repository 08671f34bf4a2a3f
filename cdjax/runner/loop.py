"""The chunk loop: `run_sweep(spec)` plans, checks memory, compiles, then trains every arm in compiled chunks,
logging, checkpointing and evaluating between them.

Everything that can be refused (bad options, a directory holding another run, a sweep that cannot fit
in memory) is refused before the run directory is touched. A resumed sweep restores the newest readable
checkpoint of each arm, drops the log rows written after it and continues: on CPU the numbers equal
those of an uninterrupted run. Ctrl-C finishes the chunk in flight, saves it and raises `Interrupted`; a
second Ctrl-C stops at once, keeping the previous checkpoint. `after_chunk=TimeLimit(seconds)` stops the same
way before a round of chunks that would end past a wall-clock budget (a cluster job's, a leased machine's). A
write that fails (a full disk) raises io.WriteError naming the file and the checkpoints that are intact.
"""

from __future__ import annotations

import dataclasses
import math
import pathlib
import time
from typing import Callable

import jax
import numpy as np

from cdjax import io
from cdjax.protocol import Setting
from cdjax.runner import budget
from cdjax.runner.arms import (Arm, build, check_memory, compile_all, evaluate_arms, finished_evaluation, nanmean,
                               restore)
from cdjax.runner.console import Clock, Progress, StopFlag, library_log
from cdjax.runner.plan import plan_arms, run_record, same_run
from cdjax.runner.spec import SweepSpec, resolve
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
    """The sweep stopped early (Ctrl-C, or `after_chunk` said so) after saving its last completed chunk."""

    def __init__(self, run_dir: pathlib.Path, updates: dict[str, int]):
        super().__init__(f"interrupted after {updates} updates")
        self.run_dir = run_dir
        self.updates = updates


def prepare(spec: SweepSpec, resume: bool) -> tuple[SweepSpec, list, dict]:
    """Plan the sweep and check it against its directory: (resolved spec, plans, run.json); writes nothing."""
    spec, _, plans, record = _prepare(spec, resume)
    return spec, plans, record


def _prepare(spec: SweepSpec, resume: bool) -> tuple[SweepSpec, Setting, list, dict]:
    """`prepare`, with the setting it resolved (once) for the rest of the sweep."""
    rd = io.RunDir(pathlib.Path(spec.out))
    spec, setting = resolve(spec)
    old = None
    if resume:
        old = rd.read()
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
    elif rd.exists():
        raise io.RunDirError(f"{rd.path} already holds a run; continue it with --resume, or choose another --out.")
    elif rd.path.is_dir() and any(rd.path.iterdir()):
        raise io.RunDirError(f"{rd.path} exists and is not empty; choose another --out.")
    rd.check_writable()
    return spec, setting, plans, record


def _checkpointed(rd: io.RunDir, name: str) -> int:
    """Updates of the newest checkpoint directory of an arm (-1: none), read without opening it."""
    return max(io.checkpoints.step_dirs(rd.checkpoints(name)), default=-1)


def run_sweep(spec: SweepSpec, resume: bool = False, after_chunk: AfterChunk | None = None) -> pathlib.Path:
    """Train every arm of `spec` in chunks, logging and checkpointing into spec.out; returns the run dir.

    `after_chunk(rounds done, updates per arm)` is called before this process's first round of chunks (after the
    phases; rounds counts those of earlier processes of a resumed run) and after each round; True stops the
    sweep as Ctrl-C does. Raises ConfigError / io.RunDirError (one sentence) for input that cannot run,
    `Interrupted` when stopped early (after saving a checkpoint of every arm).
    """
    spec, setting, plans, record = _prepare(spec, resume)
    rd = io.RunDir(pathlib.Path(spec.out))
    progress = Progress(spec.progress, record["total_env_steps"])
    arms = [build(plan, spec, setting) for plan in plans]
    states = check_memory(arms, spec)
    for arm in arms:
        arm.keys, arm.hps = arm.sweep.grid(spec.seed, spec.seeds, arm.plan.hparams)
    if setting.multi_device_note and arms and arms[0].sweep.num_devices > 1:
        progress.say(f"Note: {setting.multi_device_note}")
    progress.say(f"Compiling the programs of {', '.join(a.name for a in arms)} (nothing is written before they "
                 "are compiled and fit in memory).")
    t_compile = time.perf_counter()
    done = {arm.name: _checkpointed(rd, arm.name) for arm in arms} if resume else {}
    compile_all(arms, record["chunk_updates"], done)
    t_compile = time.perf_counter() - t_compile
    # init's output is the state, already counted; the phase and chunk programs donate it and return it
    budget.check_programs(states, {f"{arm.name} {what}": p for arm in arms for what, p in arm.programs.items()
                                   if what != "init"})

    rd.create()  # the first write: everything above could still refuse
    with rd.lock():
        if not resume and rd.exists():  # another process started this run while we compiled
            raise io.RunDirError(f"{rd.path} already holds a run; continue it with --resume, or choose another --out.")
        rd.write(record)
        return _train(Loop(rd, spec, setting, arms, record["chunk_updates"], progress, after_chunk), resume,
                      t_compile)


def _train(loop: "Loop", resume: bool, t_compile: float) -> pathlib.Path:
    """Run the loop; a failed write names the checkpoints that are intact."""
    with library_log(loop.rd.log, loop.say):
        try:
            loop.start(resume, t_compile)
            try:
                loop.run()
            finally:
                loop.close()
            loop.finish()
        except io.WriteError as err:
            raise io.WriteError(f"{err}; {loop.intact()}") from None
    return loop.rd.path


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
    complete_at_start: bool = False  # a resume found every arm done

    def say(self, text: str) -> None:
        self.progress.say(text)

    def start(self, resume: bool, t_compile: float) -> None:
        """Initialise every arm (and restore it when resuming), trim the logs to the checkpoints, say the plan."""
        t0 = time.perf_counter()
        for arm in self.arms:
            arm.state = arm.programs.pop("init")(arm.keys, arm.hps)
            arm.ckpt = io.Checkpoints(self.rd.checkpoints(arm.name))
            if not (resume and restore(arm)):
                arm.ckpt.delete_all()  # a fresh start of this arm: older checkpoints are stale
        if resume:
            self._trim_logs()
        jax.block_until_ready([a.state for a in self.arms])
        self.rounds = max(math.ceil(a.updates / self.chunk) for a in self.arms)
        self.complete_at_start = resume and all(a.updates >= a.num_updates for a in self.arms)
        phased = [a for a in self.arms if a.plan.phase is not None]
        self.say(f"Arms {', '.join(f'{a.name} ({a.num_runs} runs)' for a in self.arms)}: "
                 + ", ".join(f"{a.name} {a.num_updates}" for a in self.arms)
                 + f" updates of {self.arms[0].steps_per_update:,} env steps per run in chunks of {self.chunk}"
                 + (f", after a {self.setting.phase.title} of {phased[0].plan.phase_steps:,} env steps "
                    f"({', '.join(a.name for a in phased)})" if phased else "")
                 + f"; setup {time.perf_counter() - t0:.1f} s, compile {t_compile:.1f} s.")
        purge = {a.name: a.env_steps(a.updates + 1) for a in self.arms} if resume else None
        self.tb = io.TensorBoard(self.rd, purge_steps=purge)

    def _trim_logs(self) -> None:
        done = {a.name: a.updates for a in self.arms}
        dropped, torn = io.truncate_jsonl(self.rd.metrics, done)
        io.truncate_jsonl(self.rd.eval, done)
        progress = ", ".join(f"{a.name} {a.updates}/{a.num_updates}" for a in self.arms)
        note = ""
        if dropped:
            note = f"; dropped {dropped} log rows written after the last checkpoint" + (
                f" ({torn} of them a torn line left by a process killed while writing)" if torn else "")
        self.say(f"Resuming {self.rd.path}: updates done per arm: {progress}{note}.")

    def intact(self) -> str:
        """Which checkpoints survive a failed write, and how to go on."""
        steps = {a.name: a.ckpt.latest() for a in self.arms if a.ckpt is not None}
        kept = [f"{name} at update {step}" for name, step in steps.items() if step is not None]
        where = (f"the previous checkpoints are intact ({', '.join(kept)})" if kept
                 else "no checkpoint had been written yet")
        return f"{where}; resume with `cdjax sweep --out {self.rd.path} --resume` once that is fixed."

    # -- one step of the loop each ---------------------------------------------------------------------

    def run_phase(self, arm: Arm) -> None:
        """The phase of every run of `arm`: logged as update 0, checkpointed as step 0."""
        wall_start = arm.wall_offset + self.clock.now()
        state, info = arm.phase_program()(arm.state, arm.hps)  # donates arm.state
        info = io.host(unpad(info, arm.num_runs))
        arm.state, arm.phase_done = state, True
        took = info.pop("env_steps")
        if not np.all(took == arm.plan.phase_steps):
            raise RuntimeError(f"arm {arm.name}: the phase took {sorted(set(took.tolist()))} env steps, "
                               f"planned {arm.plan.phase_steps}")
        wall_end = arm.wall_offset + self.clock.now()
        phase = self.setting.phase
        rows = io.phase_rows(arm.name, arm.plan.labels, self.spec.seeds, info, arm.plan.phase_steps, wall_start,
                             wall_end, phase.as_metrics)
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

    def dispatch(self, arm: Arm, n: int) -> None:
        """Start a chunk of n updates (asynchronously); `commit` logs it."""
        wall_start = arm.wall_offset + self.clock.now()
        new_state, metrics = arm.chunk_program()(arm.state, arm.hps, np.int32(n))  # donates arm.state
        arm.state, arm.pending = None, (new_state, metrics, n, wall_start)

    def commit(self, arm: Arm) -> None:
        """Fetch the pending chunk's metrics, log them, make its state the arm's state."""
        new_state, metrics, n, wall_start = arm.pending
        metrics = {name: m[:, :n] for name, m in io.host(unpad(metrics, arm.num_runs)).items()}  # [R, chunk] -> n
        wall_end = arm.wall_offset + self.clock.now()
        rows = io.metric_rows(arm.name, arm.plan.labels, self.spec.seeds, metrics, arm.updates, arm.steps_per_update,
                              wall_start, wall_end, steps_offset=arm.plan.phase_steps)
        arm.state, arm.updates, arm.pending = new_state, arm.updates + n, None
        io.append_jsonl(self.rd.metrics, rows)
        self.tb.write(rows)
        self.steps_this_process += n * arm.steps_per_update * arm.num_runs
        ret = self.setting.metrics.ret
        if ret in metrics:
            arm.last_return = nanmean(metrics[ret][:, -1])
        if self.setting.watch is not None and not arm.warned:
            warning = self.setting.watch(arm.name, arm.plan.config, metrics)
            if warning is not None:
                self.say(warning)
                arm.warned = True

    def save(self, arm: Arm) -> None:
        if arm.saved != arm.updates:
            done = {"updates": arm.updates, "env_steps": arm.env_steps(), "wall_s": arm.wall_offset + self.clock.now(),
                    "chunk_updates": self.chunk}
            keep = arm.trainer.saved_leaves() if arm.trainer.saved_leaves is not None else None
            arm.ckpt.save(arm.updates, arm.state, done, keep=keep)
            arm.saved = arm.updates

    def stop(self) -> None:
        """Log and checkpoint what is done, then raise Interrupted."""
        for arm in self.arms:
            if arm.pending is not None:
                self.commit(arm)
            self.save(arm)
        for arm in self.arms:
            arm.ckpt.wait()
        raise Interrupted(self.rd.path, {a.name: a.updates for a in self.arms})

    def round(self) -> bool:
        """One chunk of every arm with updates left, logged and (every checkpoint_every rounds) saved;
        returns whether it was the last."""
        active = [a for a in self.arms if a.updates < a.num_updates]
        sizes = {a.name: min(self.chunk, a.num_updates - a.updates) for a in active}
        for arm in active:
            if "chunk" not in arm.programs:  # not compiled in advance (e.g. a resume that found nothing left)
                t0 = time.perf_counter()
                arm.chunk_program()
                self.extra_compile += time.perf_counter() - t0
        with self.clock.running():
            for arm in active:
                self.dispatch(arm, sizes[arm.name])
            for arm in active:
                self.commit(arm)
            self.rounds += 1
            last = all(a.updates >= a.num_updates for a in self.arms)
            if self.rounds % self.spec.checkpoint_every == 0 or last or self.flag.requested:
                for arm in active:
                    self.save(arm)
            for arm in active:
                arm.ckpt.wait()  # the next chunk donates the saved buffers
        return last

    def report_progress(self) -> None:
        rate = self.steps_this_process / max(self.clock.total, 1e-9)
        left = sum((a.num_updates - a.updates) * a.steps_per_update * a.num_runs for a in self.arms)
        self.progress.update(min(a.env_steps() for a in self.arms), rate, {a.name: a.last_return for a in self.arms},
                             left / rate if rate > 0 else math.inf)

    def stop_asked(self) -> bool:
        asked = self.after_chunk is not None and self.after_chunk(self.rounds, {a.name: a.updates for a in self.arms})
        return bool(asked) or self.flag.requested

    def run(self) -> None:
        with self.progress, StopFlag(self.say) as self.flag:
            try:
                for arm in self.arms:
                    if not arm.phase_done:
                        with self.clock.running():
                            self.run_phase(arm)
                            arm.ckpt.wait()
                        if self.flag.requested:
                            self.stop()
                if self.stop_asked():  # before this process's first round (after the phases)
                    self.stop()
                while any(a.updates < a.num_updates for a in self.arms):
                    last = self.round()
                    self.report_progress()
                    if self.spec.eval_every and self.rounds % self.spec.eval_every == 0 and not last:
                        evaluate_arms(self.rd, self.arms, self.spec.seeds, self.spec.eval_episodes,
                                      not self.setting.eval_sampled, self.say)
                    if self.stop_asked():
                        self.stop()
            except KeyboardInterrupt as err:
                if isinstance(err, Interrupted) or self.flag.forced:
                    raise
                self.stop()

    def close(self) -> None:
        if self.tb is not None:
            self.tb.close()
        for arm in self.arms:
            if arm.ckpt is not None:
                arm.ckpt.close()

    def finish(self) -> None:
        """Say how training went; the final evaluation (once per run) and the plots."""
        if self.complete_at_start:
            self.say(f"{self.rd.path} is complete: every arm has done its {self.arms[0].num_updates} updates.")
        else:
            rate = self.steps_this_process / max(self.clock.total, 1e-9)
            self.say(f"Trained in {self.clock.total:.1f} s ({rate:,.0f} env steps/s over all runs); "
                     f"compile {self.extra_compile:.1f} s more.")
        if not self.spec.final_eval:
            return
        deterministic = not self.setting.eval_sampled
        if finished_evaluation(self.rd, self.arms, self.spec.seeds, self.spec.eval_episodes, deterministic):
            self.say("The final evaluation is already in eval.jsonl.")
        else:
            evaluate_arms(self.rd, self.arms, self.spec.seeds, self.spec.eval_episodes, deterministic, self.say)
        try:
            from cdjax.plots import plot_run
        except ImportError as err:  # an install without the plotting stack (e.g. a bare GPU image)
            self.say(f"No plots or summary: {err}; `cdjax plot {self.rd.path}` makes them where it is installed.")
            return
        written = plot_run(self.rd.path, reps=self.spec.bootstrap_reps, say=self.say)
        self.say(f"Wrote {', '.join(str(p) for p in written.values())}.")
