"""The host-side training loop: compiled chunks of updates, and between chunks logs, progress, checkpoints.

    spec = SweepSpec(out="runs/pendulum", config=Config(env="inverted_pendulum", ...),
                     arms=("mbmf", "cd"), grid={"alpha": (0.0, 1.0)}, seeds=3, total_env_steps=100_000)
    run_dir = run_sweep(spec)                 # or run_sweep(resume_spec("runs/pendulum"), resume=True)

Arms are separate compiled programs (their parameter trees differ); inside an arm, every combination of
the grid's hyper-parameters times every seed is one run of one `make_sweep(config)` program (vmapped,
sharded over devices). Seed s has the same PRNG key in every arm and every hp combination. An arm name
is `model-free`, `mbmf` or `cd`, optionally with a horizon: `cd-k5` is the cd arm with k = 5 (the
paper's k ablation runs `cd-k5` and `cd-k20` side by side).

With `phase=MbMfPhase(...)` the arms that learn a model (mbmf, cd) first run the model-based phase of
Mb-Mf (cdjax.mbmf: random data, model, MPC aggregation, distillation into the policy), compiled and
vmapped like the updates, then PPO. The phase's env steps count towards the arm's budget: such an arm
gets ceil((steps - phase steps) / steps per update) PPO updates, so every arm is compared at the same
number of environment steps. The phase is logged as update 0 (metrics.jsonl, at env_steps = its
steps; its diagnostics also in phase.jsonl) and checkpointed as step 0, so a resumed run never
repeats it.

Each chunk runs `chunk_updates` updates of every run of every arm; between chunks the host writes
metrics.jsonl and TensorBoard, saves an orbax checkpoint per arm, updates the progress display and, if
asked, evaluates. The first chunk's compilation (lower + compile) is timed apart from training.

Interrupting (Ctrl-C / SIGINT) finishes the chunk in flight, saves it and raises `Interrupted`; a
second Ctrl-C stops at once, keeping the previous chunk's checkpoint. `run_sweep(..., resume=True)`
restores the newest readable checkpoint of each arm, drops the log rows written after it, and continues:
on CPU the numbers equal those of an uninterrupted run.
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import dataclasses
import itertools
import math
import os
import pathlib
import re
import signal
import sys
import threading
import time
from typing import Any, Callable, Mapping, Sequence

import jax
import numpy as np

from cdjax import io
from cdjax.config import Config, ConfigError, HParams
from cdjax.mbmf import MbMfPhase, total_env_steps as phase_env_steps, validate_phase
from cdjax.sweep import Sweep, make_sweep, unpad

ARMS = ("model-free", "mbmf", "cd")
# Hyper-parameters an arm does not use: fixed (not part of its grid) so they do not multiply its runs.
# lr_distill is the Mb-Mf phase's (cdjax.mbmf): unused without the phase.
CONSISTENCY_ONLY = ("alpha", "cc_model", "cc_policy", "enc_aux_coef")
UNUSED = {"model-free": CONSISTENCY_ONLY + ("lr_model", "model_coef", "lr_distill"),
          "mbmf": CONSISTENCY_ONLY + ("lr_distill",), "cd": ("lr_distill",)}
UNUSED_WITH_PHASE = {"model-free": UNUSED["model-free"], "mbmf": CONSISTENCY_ONLY, "cd": ()}
FIXED = {"alpha": 0.0}  # the value an unused hyper-parameter takes (others keep their default)
RETURN = "episode/return"
SPREAD = "encoder/spread_real"
# Below this output spread (std of the encodings across windows, averaged over features) a trainable GRU maps
# every window to nearly one point: l_cc then vanishes without the model becoming consistent. A fresh GRU
# spreads ~0.1-0.5; the collapsed ant runs of experiments/paper_obs_space ended at 5e-5 to 3e-4.
COLLAPSE_SPREAD = 1e-3
TRAINED_ENCODERS = ("gru", "grounded-gru")
LINE_EVERY_S = 5.0  # without a terminal, a progress line at most this often (and at the end)


class Interrupted(KeyboardInterrupt):
    """The sweep stopped early (Ctrl-C or a test hook) after saving its last completed chunk."""

    def __init__(self, run_dir: pathlib.Path, updates: dict[str, int]):
        super().__init__(f"interrupted after {updates} updates")
        self.run_dir = run_dir
        self.updates = updates


@dataclasses.dataclass
class SweepSpec:
    """Everything a sweep needs; the CLI only parses into this, a notebook can build it directly."""

    out: str | pathlib.Path  # the run directory
    config: Config = Config()  # base config: `arm` is set per arm, `num_updates` from total_env_steps
    arms: tuple[str, ...] = ("mbmf", "cd")  # arms to train, each its own compiled program
    grid: Mapping[str, Sequence[float]] = dataclasses.field(default_factory=dict)  # HParams field -> values
    seeds: int = 3  # runs per hp combination, seed s has the same key in every arm
    seed: int = 0  # base seed: seed s uses jax.random.split(jax.random.key(seed), seeds)[s]
    total_env_steps: int = 1_000_000  # env steps per run; rounded up to whole updates
    chunk_updates: int = 0  # updates per compiled chunk; 0 = about 5% of the run
    checkpoint_every: int = 1  # chunks between checkpoints (a killed process loses at most this many)
    eval_every: int = 0  # chunks between evaluations; 0 = only at the end
    eval_episodes: int = 10  # episodes per run in evaluations
    final_eval: bool = True  # evaluate and plot at the end (if cdjax.evaluate / cdjax.plots are present)
    progress: bool = True  # show a progress display (a line per chunk when stderr is not a terminal)
    command: str = ""  # the command line, recorded in run.json
    phase: MbMfPhase | None = None  # the Mb-Mf model-based phase run before PPO by the arms with a model
    stop_after_chunks: int | None = None  # test hook: stop as if interrupted after this many chunks (0: after the phases)
    on_chunk: Callable[[int, dict[str, int]], None] | None = None  # hook(chunks done, updates per arm)


@dataclasses.dataclass(frozen=True)
class ArmPlan:
    name: str  # e.g. "cd" or "cd-k5"
    config: Config  # the arm's config (arm, horizon and num_updates set)
    hparams: tuple[HParams, ...]  # one per hp combination
    labels: tuple[str, ...]  # "alpha=1.0,lr_model=0.001"; "default" when nothing varies
    phase: MbMfPhase | None = None  # the Mb-Mf phase this arm runs before PPO
    phase_steps: int = 0  # env steps of that phase per run

    @property
    def total_env_steps(self) -> int:
        return self.phase_steps + self.config.num_updates * self.config.env_steps_per_update


def parse_arm(name: str) -> tuple[str, dict]:
    """An arm name -> (arm, Config overrides): "cd" -> ("cd", {}), "cd-k5" -> ("cd", {"horizon": 5})."""
    match = re.fullmatch(r"(model-free|mbmf|cd)(?:-k(\d+))?", name)
    if match is None:
        raise ConfigError(f"Unknown arm {name!r}; choose from: {', '.join(ARMS)} (optionally with a horizon, "
                          "e.g. cd-k5).")
    arm, k = match.groups()
    if k is not None and arm == "model-free":
        raise ConfigError(f"Arm {name!r}: the model-free arm has no horizon.")
    if k is not None and int(k) <= 0:
        raise ConfigError(f"Arm {name!r}: the horizon must be a positive integer.")
    return arm, ({"horizon": int(k)} if k is not None else {})


# ---------------------------------------------------------------------------------------------------
# Planning: spec -> arms, hp grids, run.json


def validate_grid(grid: Mapping[str, Sequence[float]]) -> dict[str, tuple[float, ...]]:
    """Check names and values of a hyper-parameter grid (ConfigError, one sentence)."""
    fields = {f.name for f in dataclasses.fields(HParams)}
    out = {}
    for name, values in grid.items():
        if name not in fields:
            raise ConfigError(f"Unknown hyper-parameter {name!r}; choose from: {', '.join(sorted(fields))}.")
        values = tuple(float(v) for v in (values if isinstance(values, (list, tuple)) else (values,)))
        if not values:
            raise ConfigError(f"{name} needs at least one value.")
        if len(set(values)) != len(values):
            raise ConfigError(f"{name} lists a value twice: {list(values)}.")
        flag = "--" + name.replace("_", "-")
        for v in values:
            if not math.isfinite(v):
                raise ConfigError(f"{flag} must be finite, got {v}.")
            if name in ("gamma", "gae_lambda") and not 0.0 <= v <= 1.0:
                raise ConfigError(f"{flag} must be between 0 and 1, got {v}.")
            if name != "init_log_std" and v < 0:
                raise ConfigError(f"{flag} must not be negative, got {v}.")
        out[name] = values
    return out


def _label(value: float) -> str:
    return repr(float(value))


def plan_arms(spec: SweepSpec) -> list[ArmPlan]:
    grid = validate_grid(spec.grid)
    if not spec.arms:
        raise ConfigError("--arms needs at least one of: model-free, mbmf, cd.")
    parsed = [parse_arm(name) for name in spec.arms]
    if len(set(spec.arms)) != len(spec.arms):
        raise ConfigError(f"--arms lists an arm twice: {' '.join(spec.arms)}.")
    if not isinstance(spec.seeds, int) or spec.seeds <= 0:
        raise ConfigError(f"--seeds must be a positive integer, got {spec.seeds!r}.")
    if not isinstance(spec.total_env_steps, int) or spec.total_env_steps <= 0:
        raise ConfigError(f"--steps must be a positive integer, got {spec.total_env_steps!r}.")
    for name in ("chunk_updates", "eval_every"):
        if getattr(spec, name) < 0:
            raise ConfigError(f"--{name.replace('_', '-')} must not be negative, got {getattr(spec, name)}.")
    for name in ("checkpoint_every", "eval_episodes"):
        if getattr(spec, name) <= 0:
            raise ConfigError(f"--{name.replace('_', '-')} must be a positive integer, got {getattr(spec, name)}.")
    plans = []
    for name, (arm, overrides) in zip(spec.arms, parsed):
        try:
            config = spec.config.replace(arm=arm, **overrides)
        except ConfigError as err:
            raise ConfigError(f"Arm {name!r}: {err}") from None
        phase = spec.phase if config.use_model else None
        phase_steps = 0
        if phase is not None:
            validate_phase(config, phase)
            phase_steps = phase_env_steps(config, phase)
            if phase_steps >= spec.total_env_steps:
                raise ConfigError(f"--steps={spec.total_env_steps:,} leaves no PPO updates after the Mb-Mf phase's "
                                  f"{phase_steps:,} env steps; raise --steps or shrink the phase.")
        # Whole updates: rounded up without a phase; with one, to the nearest count (at least 1), so the
        # arm's total is within half an update of the arms without the phase.
        left = (spec.total_env_steps - phase_steps) / config.env_steps_per_update
        num_updates = math.ceil(left) if phase is None else max(1, round(left))
        unused = (UNUSED_WITH_PHASE if phase is not None else UNUSED)[arm]
        own = {k: v for k, v in grid.items() if k not in unused}
        fixed = {k: FIXED[k] for k in unused if k in FIXED}
        names = list(own)
        shown = [k for k in names if len(own[k]) > 1 or (k == "alpha" and arm == "cd")]
        if arm == "cd" and "alpha" not in names:
            shown.insert(0, "alpha")
        hps, labels = [], []
        for combo in itertools.product(*(own[k] for k in names)):
            values = dict(zip(names, combo))
            hp = HParams(**{**values, **fixed})
            hps.append(hp)
            labels.append(",".join(f"{k}={_label(getattr(hp, k))}" for k in shown) or "default")
        plans.append(ArmPlan(name, config.replace(num_updates=num_updates), tuple(hps), tuple(labels), phase,
                             phase_steps))
    return plans


def chunk_size(spec: SweepSpec, num_updates: int) -> int:
    """Updates per chunk: as given, else about 5% of the run (at least 1)."""
    if spec.chunk_updates:
        return spec.chunk_updates
    return max(1, math.ceil(num_updates / 20))


def run_record(spec: SweepSpec, plans: list[ArmPlan]) -> dict:
    num_updates = max(p.config.num_updates for p in plans)
    return {
        "version": io.RUN_VERSION,
        "base_config": io.config_to_json(spec.config.replace(num_updates=num_updates)),
        "arms": [{"name": p.name, "arm": p.config.arm, "config": io.config_to_json(p.config),
                  "hparams": [io.hparams_to_json(h) for h in p.hparams], "hp_labels": list(p.labels),
                  "num_updates": p.config.num_updates, "phase_env_steps": p.phase_steps,
                  "total_env_steps": p.total_env_steps}
                 for p in plans],
        "grid": {k: list(v) for k, v in validate_grid(spec.grid).items()},
        "seeds": spec.seeds,
        "seed": spec.seed,
        "phase": dataclasses.asdict(spec.phase) if spec.phase is not None else None,
        "total_env_steps": max(p.total_env_steps for p in plans),
        "requested_env_steps": spec.total_env_steps,
        "num_updates": num_updates,
        "env_steps_per_update": spec.config.env_steps_per_update,
        "chunk_updates": chunk_size(spec, math.ceil(spec.total_env_steps / spec.config.env_steps_per_update)),
        "checkpoint_every": spec.checkpoint_every,
        "command": spec.command,
    }


# What may differ between the run.json of a directory and the spec that resumes it.
_MAY_CHANGE = ("command", "total_env_steps", "requested_env_steps", "num_updates", "base_config", "arms")
_ARM_MAY_CHANGE = ("num_updates", "total_env_steps")


def _same_run(old: dict, new: dict) -> bool:
    def strip(run):
        out = {k: v for k, v in run.items() if k not in _MAY_CHANGE}
        out.setdefault("phase", None)  # run.json written before the phase existed
        out["base_config"] = {k: v for k, v in run["base_config"].items() if k != "num_updates"}
        out["arms"] = [{**{k: v for k, v in a.items() if k not in _ARM_MAY_CHANGE},
                        "config": {k: v for k, v in a["config"].items() if k != "num_updates"}}
                       for a in run["arms"]]
        for a in out["arms"]:
            a.setdefault("phase_env_steps", 0)
        return out

    return strip(old) == strip(new)


def resume_spec(out: str | pathlib.Path, **changes) -> SweepSpec:
    """The SweepSpec recorded in `out`/run.json (RunDirError if there is none), with `changes` applied."""
    run = io.RunDir(pathlib.Path(out)).read()
    try:
        config = io.config_from_json(run["base_config"])
        phase = MbMfPhase(**run["phase"]) if run.get("phase") else None
        spec = SweepSpec(out=out, config=config, arms=tuple(a["name"] for a in run["arms"]),
                         grid={k: tuple(v) for k, v in run["grid"].items()}, seeds=run["seeds"], seed=run["seed"],
                         total_env_steps=run["requested_env_steps"], chunk_updates=run["chunk_updates"],
                         checkpoint_every=run["checkpoint_every"], command=run["command"], phase=phase)
    except (KeyError, TypeError, ConfigError) as err:
        raise io.RunDirError(f"{out}/run.json is not a run this cdjax can resume ({err}).") from None
    return dataclasses.replace(spec, **changes)


# ---------------------------------------------------------------------------------------------------
# One arm's state on the host side


@dataclasses.dataclass
class _Arm:
    plan: ArmPlan
    sweep: Sweep
    keys: jax.Array
    hps: HParams
    num_runs: int
    ckpt: io.Checkpoints
    state: Any = None  # TrainState [R_padded], committed (logged) state
    updates: int = 0  # updates done (and logged)
    saved: int = -1  # updates held by the newest checkpoint
    wall_offset: float = 0.0  # training seconds of earlier processes (restored)
    pending: tuple | None = None  # (new_state, metrics, n) dispatched, not yet logged
    compiled: dict = dataclasses.field(default_factory=dict)  # n -> compiled chunk program
    last_return: float = float("nan")
    phase_done: bool = True  # False until this arm's Mb-Mf phase has run (or been restored)
    warned_collapse: bool = False  # the encoder-collapse warning was shown (once per arm and process)

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
        """Env steps per run after `updates` PPO updates (default: those done), the phase included."""
        return self.plan.phase_steps + (self.updates if updates is None else updates) * self.steps_per_update


def collapse_warning(arm_name: str, config: Config, metrics: dict) -> str | None:
    """A sentence when the trainable GRU encoder of some runs has collapsed at the latest update, else None.

    metrics: {name: [R, n]} on the host (one chunk). Only the trained encoders (gru, grounded-gru) are checked:
    `frozen-gru` does not train and `l2` has no encoder.
    """
    if config.encoder not in TRAINED_ENCODERS or SPREAD not in metrics:
        return None
    last = np.asarray(metrics[SPREAD])[:, -1]
    low = np.isfinite(last) & (last < COLLAPSE_SPREAD)
    if not low.any():
        return None
    return (f"Arm {arm_name}: the {config.encoder} encoder's output spread fell below {COLLAPSE_SPREAD:g} in {int(low.sum())} of "
            f"{last.size} runs (median {np.median(last[low]):.1e}); the encoder may have collapsed, which makes l_cc "
            "vanish without making the model consistent. The frozen-gru and l2 encoders (--encoder) cannot collapse.")


def _nanmean(values) -> float:
    values = np.asarray(values, float)
    return float(np.nanmean(values)) if np.isfinite(values).any() else float("nan")


def _new_arm(plan: ArmPlan, spec: SweepSpec, rd: io.RunDir) -> _Arm:
    sweep = make_sweep(plan.config, phase=plan.phase)
    keys, hps = sweep.grid(spec.seed, spec.seeds, plan.hparams)
    return _Arm(plan, sweep, keys, hps, len(plan.hparams) * spec.seeds, io.Checkpoints(rd.checkpoints(plan.name)))


def _like(state):
    """Shapes, dtypes and shardings of a state, as the target of a restore.

    Taken from a freshly initialised state rather than from `jax.eval_shape`: XLA may place a leaf
    of a one-device mesh as P() instead of P("runs"), and a restored state must match the fresh one
    exactly for the persistent compilation cache to serve the chunk program again.
    """
    return jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=x.sharding), state)


class _Clock:
    """Training wall-clock: the chunks with their logging and checkpoints; not setup, compilation, evaluation."""

    def __init__(self):
        self.total = 0.0
        self._start = None

    @contextlib.contextmanager
    def running(self):
        self._start = time.perf_counter()
        try:
            yield
        finally:
            self.total += time.perf_counter() - self._start
            self._start = None

    def now(self) -> float:
        return self.total + (time.perf_counter() - self._start if self._start is not None else 0.0)


class _StopFlag:
    """SIGINT sets a flag (the loop stops after the chunk in flight); a second SIGINT raises at once."""

    def __init__(self, say: Callable[[str], None]):
        self.requested = False
        self.forced = False
        self.say = say
        self._previous = None

    def __enter__(self):
        if threading.current_thread() is threading.main_thread():
            self._previous = signal.signal(signal.SIGINT, self._handle)
        return self

    def _handle(self, signum, frame):
        if self.requested:
            self.forced = True
            signal.signal(signal.SIGINT, self._previous or signal.default_int_handler)
            raise KeyboardInterrupt
        self.requested = True
        self.say("Stopping after the chunk in flight and saving a checkpoint (Ctrl-C again to stop now).")

    def __exit__(self, *exc):
        if self._previous is not None:
            signal.signal(signal.SIGINT, self._previous)
        return False


# ---------------------------------------------------------------------------------------------------
# Progress display


def _si(x: float) -> str:
    for unit, size in (("G", 1e9), ("M", 1e6), ("k", 1e3)):
        if abs(x) >= size:
            return f"{x / size:.3g}{unit}"
    return f"{x:.0f}"


class _Progress:
    def __init__(self, enabled: bool, total_steps: int):
        from rich.console import Console

        self.console = Console(stderr=True, highlight=False)
        self.enabled = enabled
        self.live = enabled and self.console.is_terminal
        self.total = total_steps
        self.bar = None
        self.last_line = -float("inf")
        if self.live:
            from rich.progress import BarColumn, Progress, TextColumn

            self.bar = Progress(BarColumn(bar_width=12), TextColumn("{task.fields[steps]}"),
                                TextColumn("{task.fields[rate]}"), TextColumn("{task.fields[eta]}"),
                                TextColumn("{task.fields[returns]}"), console=self.console)
            self.task = self.bar.add_task("training", total=total_steps, steps="", rate="", eta="", returns="")

    def say(self, text: str) -> None:
        if self.bar is not None:
            self.bar.console.print(text)
        else:
            print(text, file=sys.stderr, flush=True)

    def __enter__(self):
        if self.bar is not None:
            self.bar.start()
        return self

    def __exit__(self, *exc):
        if self.bar is not None:
            self.bar.stop()
        return False

    def update(self, steps_done: int, rate: float, returns: dict[str, float], eta_s: float) -> None:
        if not self.enabled:
            return
        eta = f"eta {int(eta_s) // 60}:{int(eta_s) % 60:02d}" if math.isfinite(eta_s) else ""
        ret = "  ".join(f"{arm} {value:.1f}" for arm, value in returns.items())
        rate_text = f"{rate:,.0f} steps/s"
        if self.bar is not None:
            self.bar.update(self.task, completed=steps_done, steps=f"{_si(steps_done)}/{_si(self.total)} steps",
                            rate=f"{_si(rate)} steps/s", eta=eta, returns=f"return {ret}")
        elif time.perf_counter() - self.last_line >= LINE_EVERY_S or steps_done >= self.total:
            self.last_line = time.perf_counter()
            pct = 100.0 * steps_done / max(self.total, 1)
            self.say(f"{steps_done:,}/{self.total:,} env steps per run ({pct:.0f}%)  {rate_text}  {eta}  return: {ret}")


# ---------------------------------------------------------------------------------------------------
# Evaluation (cdjax.evaluate, written separately; optional until it is installed)

EVAL_TAG = 0x0E7A1  # folded into each run's training key to get its evaluation key


def _have_evaluate() -> bool:
    try:
        import cdjax.evaluate  # noqa: F401
    except ImportError:
        return False
    return True


def evaluate_arms(rd: io.RunDir, arms: list[_Arm], num_seeds: int, episodes: int, deterministic: bool,
                  say: Callable[[str], None]) -> list[dict]:
    """Evaluate every run of every arm at its current state; append the records to eval.jsonl.

    One jit(vmap) program per arm over its runs (cdjax.evaluate.make_evaluator). Only the policy's
    parameters are passed, so arms with the same policy network share one compiled program.
    """
    from cdjax.evaluate import append_jsonl, eval_records, make_evaluator

    t0 = time.perf_counter()
    records = []
    for arm in arms:
        evaluator = make_evaluator(arm.sweep.trainer, episodes=episodes, deterministic=deterministic)
        keys = jax.vmap(lambda k: jax.random.fold_in(k, EVAL_TAG))(arm.keys)
        results = evaluator({"policy": arm.state.params["policy"]}, arm.state.norms, keys, arm.hps)
        records += eval_records(results, arm=arm.name, hp_labels=list(arm.plan.labels), seeds=range(num_seeds),
                                deterministic=deterministic, update=arm.updates, env_steps=arm.env_steps())
    append_jsonl(rd.eval, records)
    means: dict[str, list[float]] = {}
    for row in records:
        if row.get("eval/return") is not None:
            means.setdefault(row["arm"], []).append(row["eval/return"])
    text = "  ".join(f"{arm} {np.mean(v):.1f}" for arm, v in means.items())
    say(f"Evaluation ({episodes} episodes per run, {'mean' if deterministic else 'sampled'} actions, "
        f"{time.perf_counter() - t0:.1f} s): return {text}")
    return records


# ---------------------------------------------------------------------------------------------------
# The sweep


def prepare(spec: SweepSpec, resume: bool) -> tuple[io.RunDir, list[ArmPlan], dict]:
    """Validate the spec against the run directory and write run.json; no compilation."""
    plans = plan_arms(spec)
    rd = io.RunDir(pathlib.Path(spec.out))
    if resume:
        old = rd.read()
        if not spec.chunk_updates:  # "about 5%" of a longer run would change the chunks: keep the recorded ones
            spec = dataclasses.replace(spec, chunk_updates=old.get("chunk_updates", 0))
    record = run_record(spec, plans)
    if resume:
        if not _same_run(old, record):
            raise io.RunDirError(f"{rd.path} holds a different run than the one asked to resume; "
                                 "resume it without changing its settings (only --steps may change).")
        record["command"] = old.get("command", "")
    elif rd.exists():
        raise io.RunDirError(f"{rd.path} already holds a run; continue it with --resume, or choose another --out.")
    elif rd.path.exists() and any(rd.path.iterdir()):
        raise io.RunDirError(f"{rd.path} exists and is not empty; choose another --out.")
    rd.write(record)
    return rd, plans, record


def compile_workers() -> int:
    """Threads compiling the arms' programs at once: half the CPU cores (XLA compiles in C++, without the
    GIL; on a 2-core machine one, i.e. one after the other)."""
    return max(1, (os.cpu_count() or 1) // 2)


def compile_all(arms: list[_Arm], chunk: int) -> dict[str, Any]:
    """Lower every arm's chunk programs (full and last, shorter chunk) and its Mb-Mf phase (if it has yet
    to run) one after the other, then compile them in parallel threads. Fills arm.compiled; returns
    {arm name: compiled phase}."""
    jobs = []
    for arm in arms:
        if not arm.phase_done:
            jobs.append((arm, "phase", arm.sweep.lower_phase(arm.state, arm.hps)))
        left = arm.num_updates - arm.updates
        sizes = {min(chunk, left), left % chunk} if left > 0 else set()  # the first and the last (shorter) chunk
        for n in sorted(sizes - {0} - set(arm.compiled)):
            jobs.append((arm, n, arm.sweep.lower(arm.state, arm.hps, n)))
    workers = min(len(jobs), compile_workers())
    if workers > 1:
        with concurrent.futures.ThreadPoolExecutor(workers) as pool:
            programs = list(pool.map(lambda job: job[2].compile(), jobs))
    else:
        programs = [job[2].compile() for job in jobs]
    phases = {}
    for (arm, what, _), program in zip(jobs, programs):
        if what == "phase":
            phases[arm.name] = program
        else:
            arm.compiled[what] = program
    return phases


def run_sweep(spec: SweepSpec, resume: bool = False) -> pathlib.Path:
    """Train every arm of `spec` in chunks, logging and checkpointing into spec.out; returns the run dir.

    Raises ConfigError / io.RunDirError (one sentence) for input that cannot run, `Interrupted` when
    stopped early (after saving a checkpoint of every arm).
    """
    rd, plans, record = prepare(spec, resume)
    chunk = record["chunk_updates"]
    progress = _Progress(spec.progress, record["total_env_steps"])
    say = progress.say
    log = io.MetricsLog(rd.metrics)

    # Build (and restore) every arm; time setup and compilation apart from training.
    t_setup = time.perf_counter()
    arms: list[_Arm] = []
    for plan in plans:
        arm = _new_arm(plan, spec, rd)
        arm.state = arm.sweep.init(arm.keys, arm.hps)
        restored = arm.ckpt.restore(_like(arm.state)) if resume else None
        if restored is not None:
            arm.state, got = restored
            arm.updates = arm.saved = int(got["updates"])
            arm.wall_offset = float(got.get("wall_s", 0.0))
            arm.phase_done = True
        else:
            for step in arm.ckpt.steps():  # a fresh start of this arm: older checkpoints are stale
                arm.ckpt.manager.delete(step)
            arm.phase_done = plan.phase is None
        arms.append(arm)
    if resume:
        dropped = log.truncate({a.name: a.updates for a in arms})
        io.MetricsLog(rd.eval).truncate({a.name: a.updates for a in arms})
        done = ", ".join(f"{a.name} {a.updates}/{a.num_updates}" for a in arms)
        say(f"Resuming {rd.path}: updates done per arm: {done}"
            + (f"; dropped {dropped} log rows written after the last checkpoint." if dropped else "."))
    jax.block_until_ready([a.state for a in arms])
    t_init = time.perf_counter() - t_setup

    def compiled(arm: _Arm, n: int):
        if n not in arm.compiled:
            arm.compiled[n] = arm.sweep.lower(arm.state, arm.hps, n).compile()
        return arm.compiled[n]

    t_compile = time.perf_counter()
    phase_programs = compile_all(arms, chunk)
    t_compile = time.perf_counter() - t_compile
    phased = [a for a in arms if a.plan.phase is not None]
    say(f"Arms {', '.join(f'{a.name} ({a.num_runs} runs)' for a in arms)}: "
        + ", ".join(f"{a.name} {a.num_updates}" for a in arms)
        + f" updates of {plans[0].config.env_steps_per_update:,} env steps per run in chunks of {chunk}"
        + (f", after an Mb-Mf phase of {phased[0].plan.phase_steps:,} env steps ({', '.join(a.name for a in phased)})"
           if phased else "")
        + f"; setup {t_init:.1f} s, compile {t_compile:.1f} s.")

    purge = {a.name: a.env_steps(a.updates + 1) for a in arms} if resume else None
    tb = io.TensorBoard(rd, purge_steps=purge)
    clock = _Clock()
    evaluate = bool(spec.eval_every) and _have_evaluate()
    steps_this_process = 0
    chunks_done = 0
    extra_compile = 0.0

    def run_phase(arm: _Arm) -> None:
        """The Mb-Mf phase of every run of `arm`: logged as update 0, checkpointed as step 0."""
        nonlocal steps_this_process
        wall_start = arm.wall_offset + clock.now()
        state, info = phase_programs.pop(arm.name)(arm.state, arm.hps)  # donates arm.state
        info = io.host(unpad(info, arm.num_runs))
        arm.state, arm.phase_done = state, True
        took = info.pop("env_steps")
        if not np.all(took == arm.plan.phase_steps):
            raise RuntimeError(f"arm {arm.name}: the Mb-Mf phase took {sorted(set(took.tolist()))} env steps, "
                               f"planned {arm.plan.phase_steps}")
        wall_end = arm.wall_offset + clock.now()
        rows = io.phase_rows(arm.name, list(arm.plan.labels), spec.seeds, info, arm.plan.phase_steps,
                             wall_start, wall_end)
        log.append(rows)
        io.MetricsLog(rd.phase).append(rows)
        tb.write(rows)
        steps_this_process += arm.plan.phase_steps * arm.num_runs
        ret = info.get("dagger/episode_return")
        if ret is not None and np.isfinite(ret).any():
            arm.last_return = float(np.nanmean(ret))
        mean = lambda name: _nanmean(info.get(name, np.nan))  # noqa: E731
        say(f"Mb-Mf phase of {arm.name}: {arm.plan.phase_steps:,} env steps per run in {wall_end - wall_start:.1f} s; "
            f"episode return: random actions {mean('random/episode_return'):.1f}, MPC "
            f"{mean('mpc/episode_return'):.1f}, distilled policy {mean('dagger/episode_return'):.1f}.")
        save(arm)  # step 0: a resumed run restores it instead of running the phase again

    def commit(arm: _Arm) -> None:
        """Fetch the pending chunk's metrics, log them, make its state the arm's state."""
        nonlocal steps_this_process
        new_state, metrics, n, wall_start = arm.pending
        metrics = io.host(unpad(metrics, arm.num_runs))
        wall_end = arm.wall_offset + clock.now()
        rows = io.metric_rows(arm.name, list(arm.plan.labels), spec.seeds, metrics, arm.updates,
                              arm.steps_per_update, wall_start, wall_end, steps_offset=arm.plan.phase_steps)
        log.append(rows)
        arm.state, arm.updates, arm.pending = new_state, arm.updates + n, None
        tb.write(rows)
        steps_this_process += n * arm.steps_per_update * arm.num_runs
        if RETURN in metrics:
            last = metrics[RETURN][:, -1]
            arm.last_return = float(np.nanmean(last)) if np.isfinite(last).any() else float("nan")
        if not arm.warned_collapse:
            warning = collapse_warning(arm.name, arm.plan.config, metrics)
            if warning is not None:
                say(warning)
                arm.warned_collapse = True

    def save(arm: _Arm) -> None:
        if arm.saved != arm.updates:
            done = {"updates": arm.updates, "env_steps": arm.env_steps(),
                    "wall_s": arm.wall_offset + clock.now(), "chunk_updates": chunk}
            arm.ckpt.save(arm.updates, arm.state, done)
            arm.saved = arm.updates

    def stop() -> None:
        for arm in arms:
            if arm.pending is not None:
                commit(arm)
            save(arm)
        for arm in arms:
            arm.ckpt.wait()
        tb.flush()
        raise Interrupted(rd.path, {a.name: a.updates for a in arms})

    try:
        with progress, _StopFlag(say) as flag:
            try:
                for arm in arms:
                    if not arm.phase_done:
                        with clock.running():
                            run_phase(arm)
                            arm.ckpt.wait()
                        if flag.requested:
                            stop()
                if spec.stop_after_chunks == 0:
                    stop()
                while any(a.updates < a.num_updates for a in arms):
                    active = [a for a in arms if a.updates < a.num_updates]
                    sizes = {a.name: min(chunk, a.num_updates - a.updates) for a in active}
                    for arm in active:
                        if sizes[arm.name] not in arm.compiled:  # a shorter last chunk
                            t0 = time.perf_counter()
                            compiled(arm, sizes[arm.name])
                            extra_compile += time.perf_counter() - t0
                    with clock.running():
                        for arm in active:
                            n = sizes[arm.name]
                            wall_start = arm.wall_offset + clock.now()
                            new_state, metrics = arm.compiled[n](arm.state, arm.hps)  # donates arm.state
                            arm.state, arm.pending = None, (new_state, metrics, n, wall_start)
                        for arm in active:
                            commit(arm)
                        chunks_done += 1
                        last_round = all(a.updates >= a.num_updates for a in arms)
                        if chunks_done % spec.checkpoint_every == 0 or last_round or flag.requested:
                            for arm in active:
                                save(arm)
                        for arm in active:
                            arm.ckpt.wait()  # the next chunk donates the saved buffers
                    rate = steps_this_process / max(clock.total, 1e-9)
                    left = sum((a.num_updates - a.updates) * a.steps_per_update * a.num_runs for a in arms)
                    progress.update(min(a.env_steps() for a in arms), rate,
                                    {a.name: a.last_return for a in arms}, left / rate if rate > 0 else math.inf)
                    if evaluate and chunks_done % spec.eval_every == 0 and not last_round:
                        evaluate_arms(rd, arms, spec.seeds, spec.eval_episodes, True, say)
                    if spec.on_chunk is not None:
                        spec.on_chunk(chunks_done, {a.name: a.updates for a in arms})
                    if flag.requested:
                        stop()
                    if spec.stop_after_chunks is not None and chunks_done >= spec.stop_after_chunks:
                        stop()
            except KeyboardInterrupt as err:
                if isinstance(err, Interrupted) or flag.forced:
                    raise
                stop()
    finally:
        tb.close()
        for arm in arms:
            arm.ckpt.close()

    rate = steps_this_process / max(clock.total, 1e-9)
    say(f"Trained in {clock.total:.1f} s ({rate:,.0f} env steps/s over all runs); "
        f"compile {t_compile + extra_compile:.1f} s apart.")
    if spec.final_eval:
        finish(rd, arms, spec, say)
    return rd.path


def finish(rd: io.RunDir, arms: list[_Arm], spec: SweepSpec, say) -> None:
    """Final evaluation and plots, if cdjax.evaluate / cdjax.plots are present."""
    if _have_evaluate():
        evaluate_arms(rd, arms, spec.seeds, spec.eval_episodes, True, say)
    else:
        say("Skipping the final evaluation: cdjax.evaluate is not available.")
    try:
        from cdjax.plots import plot_run
    except ImportError:
        say("Skipping plots: cdjax.plots is not available.")
        return
    written = plot_run(rd.path)
    say(f"Wrote {', '.join(str(p) for p in written.values())}.")


def restore_arms(run_dir: str | pathlib.Path) -> tuple[SweepSpec, list[_Arm]]:
    """The spec of a run directory and its arms at the newest readable checkpoint (state leaves [R_padded])."""
    spec = resume_spec(run_dir, progress=False)
    rd = io.RunDir(pathlib.Path(run_dir))
    arms = []
    for plan in plan_arms(spec):
        arm = _new_arm(plan, spec, rd)
        restored = arm.ckpt.restore(_like(arm.sweep.init(arm.keys, arm.hps)), delete_bad=False)
        arm.ckpt.close()
        if restored is None:
            raise io.RunDirError(f"{rd.path} holds no checkpoint of arm {plan.name!r} yet.")
        arm.state, progress = restored
        arm.updates = arm.saved = int(progress["updates"])
        arms.append(arm)
    return spec, arms
