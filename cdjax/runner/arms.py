"""One arm on the host side: its trainer and compiled programs, its runs' state and progress; building,
compiling and restoring arms (evaluating them: cdjax.runner.evaluations)."""

from __future__ import annotations

import concurrent.futures
import contextlib
import dataclasses
import json
import math
import os
import pathlib
import time
from typing import Any, Callable

import jax
import numpy as np

from cdjax import budget, io, runtime
from cdjax.protocol import ConfigError, Setting, Trainer
from cdjax.runner.plan import ArmPlan, plan_arms, recorded
from cdjax.runner.spec import SweepSpec
from cdjax.sweep import Sweep, make_sweep

# This process's trainers, sweeps and compiled programs, by what they are built from: a second run_sweep of the
# same spec (a notebook's next cell, a resume in the same process) builds, traces and compiles nothing again.
_BUILT: dict = {}
_COMPILED: dict = {}


def timed(timings: io.Timings | None, arm: str, what: str, step: str):
    """A context that times its block as a row of `timings` (cdjax.io.timings); None: not timed."""
    return contextlib.nullcontext() if timings is None else timings.time(arm, what, step)


def _timed(arm, what: str, step: str, t0: float) -> None:
    """A row of the arm's timings (cdjax.io.timings) for a step that began at time.perf_counter() t0 and ends now;
    nothing for an arm that keeps none (a caller's stand-in)."""
    timings = getattr(arm, "timings", None)
    if timings is not None:
        timings.add(arm.name, what, step, t0)


@dataclasses.dataclass
class Arm:
    """One arm's host-side state during a sweep."""

    plan: ArmPlan
    trainer: Trainer
    sweep: Sweep
    keys: jax.Array  # [R_padded] the runs' training keys
    hps: Any  # HParams with leaves [R_padded]
    num_runs: int  # R: hp combinations x seeds (without the device padding)
    ckpt: io.Checkpoints | None = None
    state: Any = None  # the runs' state [R_padded], committed (logged)
    abstract: Any = None  # ShapeDtypeStructs (with shardings) of `state`
    updates: int = 0  # updates done (and logged)
    saved: int = -1  # updates held by the newest checkpoint
    wall_offset: float = 0.0  # training seconds of earlier processes (restored)
    pending: tuple | None = None  # (future of (new_state, metrics), n, wall_start) dispatched, not yet logged
    unlogged: tuple | None = None  # (metrics, rows) of a chunk fetched (its state is `state`), not yet written
    programs: dict = dataclasses.field(default_factory=dict)  # "init", "phase", "chunk" -> compiled program
    chunk: int = 0  # updates the chunk program holds (it runs any n <= chunk of them)
    state_bytes: int = 0  # one run's state (check_memory)
    last_return: float = float("nan")
    phase_done: bool = True  # False until this arm's phase has run (or been restored)
    warned: int = 0  # how many runs the setting's watch last spoke of (it speaks again when more are concerned)
    identity: dict = dataclasses.field(default_factory=dict)  # the runs as run.json records them (in checkpoints)
    skipped: Any = None  # [R] optimiser steps each run skipped for a non-finite loss or gradient, so far
    skipped_said: int = 0  # how many runs the last sentence about skipped steps named
    room: int | None = None  # bytes a program may take beside every arm's states (None: no limit; _compiled)
    in_order: dict = dataclasses.field(default_factory=dict)  # program -> (bytes scheduled by data flow, in order)
    timings: io.Timings | None = None  # where the sweep's time goes (run_sweep's record; None: not timed)
    evaluating: concurrent.futures.Future | None = None  # its evaluator compiling in the background (compile_evaluators)

    @property
    def name(self) -> str:
        return self.plan.name

    @property
    def steps_per_update(self) -> int:
        return self.plan.config.env_steps_per_update

    @property
    def num_updates(self) -> int:
        return self.plan.config.num_updates

    def env_steps(self, updates: int | None = None) -> int:
        """Env steps per run after `updates` updates (default: those done), the phase included."""
        return self.plan.phase_steps + (self.updates if updates is None else updates) * self.steps_per_update

    def phase_program(self):
        """The compiled phase (compiled now if it was not in advance, e.g. every checkpoint was unreadable)."""
        if "phase" not in self.programs:
            self.programs["phase"] = _compiled(self, "phase", self.sweep.trace_phase, self.abstract, self.hps)
        return self.programs.pop("phase")

    def chunk_program(self):
        """The compiled program of up to `chunk` updates, called (state, hps, n) (compiled now if it was not in
        advance)."""
        if "chunk" not in self.programs:
            self.programs["chunk"] = _compiled(self, "chunk", self.sweep.trace_chunk, self.abstract, self.hps,
                                               self.chunk)
        return self.programs["chunk"]


def build(plan: ArmPlan, spec: SweepSpec, setting: Setting) -> Arm:
    """The arm's trainer and (uncompiled) programs; nothing is allocated on the devices yet. The same setting,
    config and phase in this process get the same trainer and sweep (and so their compiled programs)."""
    key = (setting.name, plan.config, plan.phase, tuple(jax.devices()))
    if key not in _BUILT:
        trainer = setting.make_trainer(plan.config)
        phase = setting.phase.make(trainer, plan.phase) if plan.phase is not None else None
        _BUILT[key] = (trainer, make_sweep(trainer, phase=phase))
    trainer, sweep = _BUILT[key]
    num_runs = len(plan.hparams) * spec.seeds
    identity = {"setting": setting.name, "arm": plan.name,
                "config": {k: v for k, v in io.dataclass_to_json(plan.config).items() if k != "num_updates"},
                "seeds": spec.seeds, "seed": spec.seed, "hp_labels": list(plan.labels),
                "hparams": [io.hparams_to_json(h) for h in plan.hparams], "num_runs": num_runs}
    return Arm(plan, trainer, sweep, keys=None, hps=None, num_runs=num_runs, phase_done=plan.phase is None,
               identity=identity, skipped=np.zeros(num_runs))


def _json(value) -> str:
    return json.dumps(value) if not isinstance(value, str) else repr(value)


def expectation(arm: Arm) -> Callable[[dict | None], str | None]:
    """expect(the run a checkpoint records) -> how it differs from the arm's runs as run.json gives them, or None.
    A checkpoint written before runs were recorded gives None: its leaves are still checked."""
    mine = arm.identity

    def expect(saved: dict | None) -> str | None:
        if saved is None:
            return None
        if not isinstance(saved, dict):
            return f"its run record is {_json(saved)}"
        for key, what in (("setting", "setting"), ("arm", "arm")):
            if saved.get(key, mine[key]) != mine[key]:
                return f"it is of the {what} {_json(saved[key])} where run.json has {_json(mine[key])}"
        theirs = saved.get("config") if isinstance(saved.get("config"), dict) else {}
        for name, value in mine["config"].items():
            if name in theirs and theirs[name] != value:
                return f"it was trained with {name} {_json(theirs[name])} where run.json has {_json(value)}"
        runs = (saved.get("num_runs"), saved.get("seeds"), saved.get("hp_labels"))
        if runs != (mine["num_runs"], mine["seeds"], mine["hp_labels"]):
            n, seeds, labels = runs

            def count(n, seeds, labels):
                combos = len(labels) if isinstance(labels, list) else "?"
                return f"{n} runs ({seeds} seeds x {combos} hyper-parameter combinations)"

            if n == mine["num_runs"] and seeds == mine["seeds"]:
                return f"its hyper-parameter labels are {_json(labels)} where run.json has {_json(mine['hp_labels'])}"
            return (f"it holds {count(n, seeds, labels)} where run.json asks for "
                    f"{count(mine['num_runs'], mine['seeds'], mine['hp_labels'])}")
        if saved.get("seed", mine["seed"]) != mine["seed"]:
            return f"its base seed is {_json(saved['seed'])} where run.json has {mine['seed']}"
        theirs = saved.get("hparams") if isinstance(saved.get("hparams"), list) else mine["hparams"]
        if len(theirs) != len(mine["hparams"]):
            return f"it holds {len(theirs)} hyper-parameter combinations where run.json has {len(mine['hparams'])}"
        for label, a, b in zip(mine["hp_labels"], theirs, mine["hparams"]):  # fields both know (a newer cdjax may add)
            if not isinstance(a, dict):
                return f"its hyper-parameter record is {_json(a)}"
            diff = sorted(k for k in set(a) & set(b) if a[k] != b[k])
            if diff:
                return (f"its {label} runs were trained with {diff[0]} {_json(a.get(diff[0]))} where run.json has "
                        f"{_json(b.get(diff[0]))}")
        return None

    return expect


def _lowered(arm: Arm, what: str, lower: Callable, *args, owner=None):
    """lower(*args) of arm's sweep (or of `owner`, a function several sweeps share), from this process's cache when
    it was lowered before for the same inputs. `lower` may also be a trace (a jitted function's `.trace`, a sweep's
    `trace_*`): its result is lowered here, and the trace and the lowering are timed apart."""
    owner = arm.sweep if owner is None else owner
    key = (id(owner), what, "lowered", budget.signature(args))
    if key not in _COMPILED:
        t0 = time.perf_counter()
        staged = lower(*args)
        if isinstance(staged, jax.stages.Traced):
            _timed(arm, what, "trace", t0)
            t0 = time.perf_counter()
            staged = staged.lower()
        _COMPILED[key] = (owner, staged)  # the owner held: its id stays its own while the entry lives
        _timed(arm, what, "lower", t0)
    return _COMPILED[key][1]


def _compiled(arm: Arm, what: str, lower: Callable, *args, pool=None, owner=None):
    """The compiled program `what` of arm's sweep (or of `owner`, as _lowered) for these inputs (static ints
    included): from this process's cache, else lowered now and compiled (in `pool`, returning a future, when
    given). Compiled with runtime.compiler_options; where those schedule the GPU's kernels by data flow and the
    program would not fit in `arm.room` bytes, in XLA's program order instead (as budget.compile_fitting; noted in
    `arm.in_order`)."""
    owner = arm.sweep if owner is None else owner
    mode = runtime.compile_mode()  # read once per call: a notebook may change it between sweeps
    options = runtime.compiler_options(mode)
    key = (id(owner), what, budget.signature(args), mode, tuple(sorted(options.items())))
    # init's and reset's outputs are the states themselves (budget.check_programs leaves them out alike)
    room = None if what in ("init", "reset") else getattr(arm, "room", None)

    def cached():  # the program held for these inputs that fits `room` (the in-order one when the other does not)
        first = _COMPILED.get(key)
        if first is None:
            return None
        if not runtime.concurrent(options) or budget.fits(first[1], room):
            return first[1]
        second = _COMPILED.get(key + ("in order",))
        if second is not None:
            _note_in_order(arm, what, first[1], second[1])
        return None if second is None else second[1]

    if (program := cached()) is not None:
        return program
    lowered = _lowered(arm, what, lower, *args, owner=owner)

    def compile_():
        t0 = time.perf_counter()
        if key not in _COMPILED:
            _COMPILED[key] = (owner, lowered.compile(options))
            _timed(arm, what, "compile", t0)
        if (program := cached()) is not None:
            return program
        t0 = time.perf_counter()
        second = lowered.compile(runtime.compiler_options(mode, in_order=True))
        _COMPILED[key + ("in order",)] = (owner, second)
        _timed(arm, what, "compile in order", t0)
        _note_in_order(arm, what, _COMPILED[key][1], second)
        return second

    return compile_() if pool is None else pool.submit(compile_)


def _note_in_order(arm, what: str, first, second) -> None:
    """Record on `arm` (where it keeps such notes) that `what` runs in program order: the bytes of both programs."""
    notes = getattr(arm, "in_order", None)
    if notes is not None:
        notes[what] = (budget.program_bytes(first), budget.program_bytes(second))


def _shared_shape(trainer: Trainer, what: tuple, make: Callable):
    """make()'s shapes, computed once for every trainer of the same environments (`Trainer.env_key`): tracing a
    physics reset takes a second or more, and the arms of a sweep mostly act in the same environments."""
    if trainer.env_key is None:
        return make()
    key = ("shape", trainer.env_key) + what
    if key not in _COMPILED:
        _COMPILED[key] = (None, make())
    return _COMPILED[key][1]


def _init_shape(arm: Arm, key: jax.Array, hp):
    """ShapeDtypeStructs of one run's init(key, hp): init_from over the shared reset's shapes where the trainer offers
    it. Those come from the sweep's own reset program over the shapes of the arm's runs' keys (`Sweep.key_shapes`;
    the keys are drawn after this check, which must refuse absurd run counts in seconds): compile_all lowers that
    program for the keys, and JAX keeps a jitted function's trace per input shapes and shardings, so the physics reset
    is traced once for both (a trace of the trainer's reset alone would not serve the program: under the vmap over
    runs JAX traces the physics' jitted reset again). An MJX reset takes a second or more to trace."""
    trainer = arm.trainer
    if trainer.reset is None or trainer.init_from is None:
        return jax.eval_shape(trainer.init, key, hp)
    if arm.sweep.reset is None:
        envs = _shared_shape(trainer, ("reset",), lambda: jax.eval_shape(trainer.reset, key))
    else:
        keys = arm.sweep.key_shapes(arm.num_runs)
        runs = _shared_shape(trainer, ("reset", id(arm.sweep.reset), budget.signature((keys,))),
                             lambda: jax.eval_shape(arm.sweep.reset, keys))
        envs = jax.tree.map(lambda s: jax.ShapeDtypeStruct(s.shape[1:], s.dtype), runs)
    return jax.eval_shape(trainer.init_from, key, hp, envs)


def _eval_reset_shape(arm: Arm, episodes: int, key: jax.Array):
    """ShapeDtypeStructs of one run's evaluation environments' reset for `episodes` episodes (shared as _init_shape's).
    Traced as the evaluator calls it, under the vmap over the arm's runs' keys (`Sweep.key_shapes`): the env's physics
    reset is then the trace the runs' reset already made (`cdjax.envs.physics`), only batched again."""
    trainer = arm.trainer
    if arm.sweep.reset is None:
        return _shared_shape(trainer, ("eval", episodes), lambda: jax.eval_shape(trainer.eval_env(episodes).reset, key))
    keys = arm.sweep.key_shapes(arm.num_runs)
    runs = _shared_shape(trainer, ("eval", episodes, budget.signature((keys,))),
                         lambda: jax.eval_shape(jax.vmap(trainer.eval_env(episodes).reset), keys))
    return jax.tree.map(lambda s: jax.ShapeDtypeStruct(s.shape[1:], s.dtype), runs)


def check_memory(arms: list[Arm], spec: SweepSpec) -> int:
    """budget.check_states from the shapes of one run's state and evaluation; returns the states' bytes. Nothing is
    drawn or computed for the runs (the reset program's trace is shared with compile_all: _init_shape)."""
    key = jax.random.key(0)
    rows = []
    for arm in arms:
        hp = arm.plan.hparams[0]
        evaluated = spec.final_eval or spec.eval_every
        cache = (id(arm.sweep), "bytes", spec.eval_episodes if evaluated else 0, budget.signature(hp))
        if cache not in _COMPILED:
            state = budget.tree_bytes(_init_shape(arm, key, hp))
            evaluation = budget.tree_bytes(_eval_reset_shape(arm, spec.eval_episodes, key)) if evaluated else 0
            _COMPILED[cache] = (arm.sweep, (state, evaluation))
        state, evaluation = _COMPILED[cache][1]
        arm.state_bytes = state
        rows.append((arm.name, arm.num_runs, state, evaluation))
    return budget.check_states(rows, jax.device_count())


def compile_workers() -> int:
    """Threads compiling the arms' programs at once: half the CPU cores this process may run on (XLA compiles in
    C++, without the GIL; on a 2-core machine one, i.e. one after the other; a process pinned to some cores, by
    taskset or a batch scheduler, counts those), or CDJAX_COMPILE_WORKERS when set (a count >= 1)."""
    text = os.environ.get("CDJAX_COMPILE_WORKERS", "").strip()
    if text:
        if not text.isdigit() or int(text) < 1:
            raise ConfigError(f"CDJAX_COMPILE_WORKERS must be a whole number >= 1, got {text!r}.")
        return int(text)
    return max(1, usable_cores() // 2)


def usable_cores() -> int:
    """The CPU cores this process may run on (its affinity where the OS says it), else all of the machine's."""
    try:
        return len(os.sched_getaffinity(0)) or 1
    except (AttributeError, OSError):  # no sched_getaffinity (macOS, Windows)
        return os.cpu_count() or 1


def compile_all(arms: list[Arm], chunk: int, done: dict[str, int]) -> None:
    """Compile every arm's init, its phase (if it has yet to run) and its chunk program (of min(chunk, updates)
    updates: it also runs the last, shorter chunk), in parallel threads, from shapes alone.

    Each program is handed to a compiling thread as soon as it is traced, so the tracing of one (Python) overlaps
    the compilation of the others (XLA, without the GIL); the arms with the largest states (the largest programs,
    in practice) first. An arm's init goes before its chunk: its compile fills cores that the serial lowering of
    the chunks leaves idle, where inits queued after the chunks would compile beside them and slow them (measured in
    benchmarks/results/2026-11-27-h100-shared-physics/). Programs this process compiled before are taken from its
    cache.
    """
    order = sorted(arms, key=lambda a: -getattr(a, "state_bytes", 0))
    with concurrent.futures.ThreadPoolExecutor(compile_workers()) as pool:
        jobs = []
        resets = {}  # (shared reset, its inputs) -> its compile job: one per sweep, whichever arms share it
        for arm in order:

            def abstract(out, sharding=arm.sweep.sharding):  # a lowered program's outputs as ShapeDtypeStructs
                return jax.tree.map(lambda s: jax.ShapeDtypeStruct(s.shape, s.dtype, sharding=sharding), out)

            if arm.sweep.reset is None:
                lowered_init = _lowered(arm, "init", arm.sweep.init.trace, arm.keys, arm.hps)
                jobs.append((arm, "init", _compiled(arm, "init", arm.sweep.init.trace, arm.keys, arm.hps, pool=pool)))
            else:  # the environments' reset, shared by the arms in the same ones, then the rest of the init
                reset = arm.sweep.reset
                shared = (id(reset), budget.signature((arm.keys,)))
                if shared not in resets:
                    resets[shared] = _compiled(arm, "reset", reset.trace, arm.keys, pool=pool, owner=reset)
                envs = abstract(_lowered(arm, "reset", reset.trace, arm.keys, owner=reset).out_info)
                lowered_init = _lowered(arm, "init", arm.sweep.init_from.trace, arm.keys, arm.hps, envs)
                jobs.append((arm, "init", (resets[shared], _compiled(arm, "init", arm.sweep.init_from.trace, arm.keys,
                                                                     arm.hps, envs, pool=pool))))
            arm.abstract = abstract(lowered_init.out_info)
            start = done.get(arm.name, -1)  # updates of the checkpoint a resume will restore (-1: none)
            if not arm.phase_done and start < 0:
                jobs.append((arm, "phase", _compiled(arm, "phase", arm.sweep.trace_phase, arm.abstract, arm.hps,
                                                     pool=pool)))
            arm.chunk = min(chunk, arm.num_updates)
            if arm.num_updates - max(start, 0) > 0:
                jobs.append((arm, "chunk", _compiled(arm, "chunk", arm.sweep.trace_chunk, arm.abstract, arm.hps,
                                                     arm.chunk, pool=pool)))
        def done(job):
            return job.result() if isinstance(job, concurrent.futures.Future) else job

        for arm, what, job in jobs:
            if isinstance(job, tuple):  # init as reset, then init_from
                reset, init_from = done(job[0]), done(job[1])
                arm.programs[what] = lambda keys, hps, reset=reset, init_from=init_from: init_from(keys, hps, reset(keys))
            else:
                arm.programs[what] = done(job)


def restore(arm: Arm, set_aside: bool = True) -> bool:
    """Put the newest readable checkpoint into arm.state (a fresh init of the same runs fills what it does
    not hold); False when none can be read. io.CheckpointMismatch (one sentence) for a checkpoint of another run."""
    restored = arm.ckpt.restore(arm.state, expect=expectation(arm), set_aside=set_aside)
    if restored is None:
        return False
    arm.state, progress = restored
    arm.updates = arm.saved = int(progress["updates"])
    arm.wall_offset = float(progress.get("wall_s", 0.0))
    arm.phase_done = True
    return True


def abstract_state(arm: Arm):
    """ShapeDtypeStructs of the arm's runs' state (nothing is computed)."""
    return jax.eval_shape(arm.sweep.init, arm.keys, arm.hps)


def unreadable_text(unreadable: list[tuple[int, str]]) -> str:
    return "; ".join(f"{step}: {why}" for step, why in unreadable)


def restore_arms(run_dir: str | pathlib.Path) -> tuple[SweepSpec, list[Arm]]:
    """The spec of a run directory and its arms at the newest readable checkpoint (state leaves [R_padded]).

    Reads only: a checkpoint that cannot be read is passed over (said with a CheckpointWarning), not moved; one of
    another run than run.json's refuses (io.CheckpointMismatch, one sentence) before any array is computed."""
    rd = io.RunDir(pathlib.Path(run_dir))
    spec, setting = recorded(rd.read(), run_dir, progress=False)
    arms = []
    for plan in plan_arms(spec, setting):
        arm = build(plan, spec, setting)
        arm.keys, arm.hps = arm.sweep.grid(spec.seed, spec.seeds, plan.hparams)
        directory = rd.checkpoints(plan.name)
        if not io.checkpoints.step_dirs(directory):
            raise io.RunDirError(f"{rd.path} holds no checkpoint of arm {plan.name!r} yet.")
        arm.ckpt = io.Checkpoints(directory)
        try:
            step, unreadable = arm.ckpt.inspect(abstract_state(arm), expectation(arm))
            if step is None:
                raise io.RunDirError(f"{rd.path}: no checkpoint of arm {plan.name!r} can be read "
                                     f"({unreadable_text(unreadable)}).")
            arm.state = arm.sweep.init(arm.keys, arm.hps)
            found = restore(arm, set_aside=False)
        finally:
            arm.ckpt.close()
        if not found:
            raise io.RunDirError(f"{rd.path}: no checkpoint of arm {plan.name!r} can be read "
                                 f"({unreadable_text(arm.ckpt.unreadable)}).")
        arms.append(arm)
    return spec, arms


def nanmean(values) -> float:
    values = np.asarray(values, float)
    return float(np.nanmean(values)) if np.isfinite(values).any() else math.nan
