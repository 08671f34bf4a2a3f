"""Planning a sweep: arms with their configs, hyper-parameter grids and budgets; the run.json record; what a
resume may and may not change. Nothing here compiles, allocates or writes."""

from __future__ import annotations

import dataclasses
import functools
import itertools
import math
import pathlib
import subprocess
from typing import Any, Mapping, Sequence

from cdjax import agents, io
from cdjax.envs import playground
from cdjax.protocol import ConfigError, Setting
from cdjax.runner.spec import INT32_MAX, SweepSpec, check_bounds, resolve


@dataclasses.dataclass(frozen=True)
class ArmPlan:
    name: str  # e.g. "cd" or "cd-k5"
    config: Any  # the arm's config (its arm fields and num_updates set)
    hparams: tuple  # one HParams per hp combination
    labels: tuple[str, ...]  # "alpha=1.0,lr_model=0.001"; "default" when nothing varies
    phase: Any = None  # the phase spec this arm runs before its updates
    phase_steps: int = 0  # env steps of that phase per run
    ignored: tuple[str, ...] = ()  # grid fields given several values that this arm has no use for (one run covers them)

    @property
    def total_env_steps(self) -> int:
        return self.phase_steps + self.config.num_updates * self.config.env_steps_per_update


def validate_grid(setting: Setting, grid: Mapping[str, Sequence[float]]) -> dict[str, tuple[float, ...]]:
    """Check names and values of a hyper-parameter grid (ConfigError, one sentence)."""
    fields = {f.name for f in dataclasses.fields(setting.hparams_type)}
    out = {}
    for name, values in grid.items():
        if name not in fields:
            raise ConfigError(f"Unknown hyper-parameter {name!r}; choose from: {', '.join(sorted(fields))}.")
        raw = values if isinstance(values, (list, tuple)) else (values,)
        try:
            values = tuple(float(v) for v in raw)
        except (TypeError, ValueError):
            raise ConfigError(f"{name} takes numbers, got {list(raw)!r}.") from None
        if not values:
            raise ConfigError(f"{name} needs at least one value.")
        if len(set(values)) != len(values):
            raise ConfigError(f"{name} lists a value twice: {list(values)}.")
        for v in values:
            setting.check_hparam(name, v)
        out[name] = values
    return out


def _label(value: float) -> str:
    return repr(float(value))


def plan_arms(spec: SweepSpec, setting: Setting | None = None) -> list[ArmPlan]:
    """The arms of a spec of `setting` (None: the one it names); ConfigError (one sentence) for anything that
    cannot run."""
    spec, setting = resolve(spec) if setting is None else (spec.resolved(setting), setting)
    check_bounds(spec)
    grid = validate_grid(setting, spec.grid)
    if spec.phase is not None and setting.phase is None:
        raise ConfigError(f"The {setting.name} setting has no pre-update phase.")
    plans = [_plan_arm(setting, spec, name, grid) for name in spec.arms]
    same: dict[str, str] = {}  # two names for one arm (cd and cd-k4 where k is 4; cd-k05 and cd-k5) train it twice
    for plan in plans:
        first = same.setdefault(repr((plan.config, plan.hparams, plan.phase)), plan.name)
        if first != plan.name:
            raise ConfigError(f"Arms {first} and {plan.name} are one configuration with the same hyper-parameters, so "
                              f"their runs would be the same runs twice; keep one of them.")
    return plans


def return_note(setting: Setting, plans: Sequence[ArmPlan | Mapping]) -> str | None:
    """A note when the arms' return (the figure the summary ranks them by) is measured at different values of the
    setting's `Metrics.ret_field`, e.g. pixel likelihoods at k = 10 and at k = 5; None otherwise. `plans`: the arms'
    ArmPlans (a sweep), or run.json's records of them (`run_record`'s "arms": `recorded_return_note`); a record
    without the field counts for nothing."""
    field, metrics = setting.metrics.ret_field, setting.metrics
    values = {}
    for plan in plans if field else ():
        if isinstance(plan, ArmPlan):
            values[plan.name] = getattr(plan.config, field)
        elif field in (config := plan.get("config") or {}):  # as dataclass_from_json reads it
            values[plan.get("name")] = tuple(config[field]) if isinstance(config[field], list) else config[field]
    if len(set(values.values())) < 2:
        return None
    return (f"Note: the arms' return ({metrics.ret}, which ranks them in the summary) is measured at each arm's own "
            f"{field} ({', '.join(f'{name} {value}' for name, value in values.items())}), so the ranking sets "
            f"different measures side by side; the discounted return ({metrics.discounted_ret}) is one measure for "
            "all of them.")


def recorded_return_note(runs: Sequence[Mapping]) -> str | None:
    """`return_note` of the arms that run.json records: `runs`, the run.json of one run directory or of several of one
    setting whose seeds `cdjax plot` pools (an arm recorded in several counts once: pooled runs agree on its config).
    Read from the records, not planned again, so that a run.json that plots but would not plan (an arm's config that
    this cdjax refuses) still plots; None also for a setting this process does not know (registered by another
    program), whose plots need only run.json's metric names."""
    if not runs:
        return None
    try:
        setting = agents.get(runs[0].get("setting", agents.DEFAULT))
    except ConfigError:
        return None
    arms = {}
    for run in runs:
        for arm in run.get("arms", ()):
            arms.setdefault(arm.get("name"), arm)
    return return_note(setting, list(arms.values()))


def _plan_arm(setting: Setting, spec: SweepSpec, name: str, grid: dict) -> ArmPlan:
    config = setting.arm_config(name, spec.config)
    phase = spec.phase if spec.phase is not None and setting.phase.applies(config) else None
    phase_steps = 0
    if phase is not None:
        setting.phase.validate(config, phase)
        phase_steps = setting.phase.env_steps(config, phase)
        if phase_steps >= spec.total_env_steps:
            raise ConfigError(f"--steps={spec.total_env_steps:,} leaves no updates after the {setting.phase.title}'s "
                              f"{phase_steps:,} env steps; raise --steps or shrink the phase.")
    # Whole updates: rounded up without a phase; with one, to the nearest count (at least 1), so the arm's
    # total is within half an update of the arms without the phase.
    left = (spec.total_env_steps - phase_steps) / config.env_steps_per_update
    num_updates = math.ceil(left) if phase is None else max(1, round(left))
    if num_updates > INT32_MAX:
        raise ConfigError(f"--steps={spec.total_env_steps:,} is {num_updates:,} updates of arm {name!r}, more than "
                          f"the {INT32_MAX:,} its update counter (int32) holds.")
    unused = setting.unused_hparams(config, phase is not None)
    own = {k: v for k, v in grid.items() if k not in unused}
    fixed = {k: v for k, v in unused.items() if v is not None}
    names = list(own)
    always = setting.shown_hparams(config)
    shown = [k for k in names if len(own[k]) > 1 or k in always]
    shown = [k for k in always if k not in names] + shown
    hps, labels = [], []
    for combo in itertools.product(*(own[k] for k in names)):
        hp = setting.hparams_type(**dict(zip(names, combo)), **fixed)
        hps.append(hp)
        labels.append(",".join(f"{k}={_label(getattr(hp, k))}" for k in shown) or "default")
    ignored = tuple(k for k, v in grid.items() if k in unused and len(v) > 1)
    return ArmPlan(name, dataclasses.replace(config, num_updates=num_updates), tuple(hps), tuple(labels), phase,
                   phase_steps, ignored)


def chunk_size(spec: SweepSpec, num_updates: int) -> int:
    """Updates per chunk: as given, else about 5% of the run (at least 1)."""
    return spec.chunk_updates or max(1, math.ceil(num_updates / 20))


def code_record() -> dict:
    """The code a run is trained with: cdjax's and JAX's versions and, when cdjax is imported from a git checkout,
    its commit and whether tracked files differ from it (None where git cannot tell); and `matmul_precision` where
    JAX's default matmul precision is set (JAX_DEFAULT_MATMUL_PRECISION or jax.default_matmul_precision: "highest"
    keeps a GPU's float32 products out of TF32), absent at JAX's default, so the records of before still match."""
    import jax

    precision = jax.config.jax_default_matmul_precision
    return {**_checkout(), **({} if precision is None else {"matmul_precision": str(precision)})}


@functools.lru_cache(maxsize=1)
def _checkout() -> dict:
    """code_record's versions (cdjax, jax, jaxlib, brax, mujoco, mujoco-mjx, the backend) and git state, read once per
    process."""
    from cdjax import runtime

    here = pathlib.Path(__file__).resolve().parents[1]

    def git(*args: str) -> str | None:
        try:
            done = subprocess.run(["git", "-C", str(here), *args], capture_output=True, text=True, timeout=10)
        except (OSError, subprocess.SubprocessError):
            return None
        return done.stdout.strip() if done.returncode == 0 else None

    # a checkout that tracks cdjax itself (not a project whose repository holds a virtual environment cdjax is in)
    commit = git("rev-parse", "HEAD") if git("ls-files", "--error-unmatch", "__init__.py") is not None else None
    status = git("status", "--porcelain", "--untracked-files=no") if commit else None
    return {**runtime.versions(), "commit": commit,
            "modified": None if status is None else bool(status)}


def run_record(spec: SweepSpec, plans: list[ArmPlan], setting: Setting) -> dict:
    """run.json of a resolved spec of `setting`: the whole spec, each arm's plan, the metric names, the command."""
    num_updates = max(p.config.num_updates for p in plans)
    m = setting.metrics
    return {
        "version": io.RUN_VERSION,
        "setting": spec.setting,
        "base_config": io.dataclass_to_json(dataclasses.replace(spec.config, num_updates=num_updates)),
        "arms": [{"name": p.name, "arm": getattr(p.config, "arm", p.name), "config": io.dataclass_to_json(p.config),
                  "hparams": [io.hparams_to_json(h) for h in p.hparams], "hp_labels": list(p.labels),
                  "num_updates": p.config.num_updates, "phase_env_steps": p.phase_steps,
                  "total_env_steps": p.total_env_steps} for p in plans],
        "grid": {k: list(v) for k, v in validate_grid(setting, spec.grid).items()},
        "seeds": spec.seeds,
        "seed": spec.seed,
        "phase": io.dataclass_to_json(spec.phase) if spec.phase is not None else None,
        "total_env_steps": max(p.total_env_steps for p in plans),
        "requested_env_steps": spec.total_env_steps,
        "num_updates": num_updates,
        "env_steps_per_update": spec.config.env_steps_per_update,
        "chunk_updates": chunk_size(spec, math.ceil(spec.total_env_steps / spec.config.env_steps_per_update)),
        "checkpoint_every": spec.checkpoint_every,
        "eval_every": spec.eval_every,
        "eval_episodes": spec.eval_episodes,
        "final_eval": spec.final_eval,
        "bootstrap_reps": spec.bootstrap_reps,
        "metrics": {"return": m.ret, "discounted_return": m.discounted_ret, "panels": [list(p) for p in m.panels],
                    **({"skipped": m.skipped} if m.skipped is not None else {})},
        "command": spec.command,
        # a resume with other code (or, for a Playground task, another physics backend) adds it (runner.loop)
        "code": [code_record() | playground.backend_record(spec.config)],
    }


# What may differ between the run.json of a directory and the spec that resumes it: the length of the run (and the
# setting's metric names, rewritten from the setting as it is now), and the code that runs it.
MAY_CHANGE = ("command", "total_env_steps", "requested_env_steps", "num_updates", "metrics", "code")
ARM_MAY_CHANGE = ("num_updates", "total_env_steps")


def same_run(old: dict, new: dict) -> bool:
    """Whether `new` (the record a resume would write) is the run `old` records, but for its length. A key the old
    record lacks (a Config, HParams, phase or sweep field added to cdjax after the run was made) is not a
    difference: reading the old record gives it its default, which is how the run was trained."""
    def strip(run):
        out = {k: v for k, v in run.items() if k not in MAY_CHANGE}
        out["base_config"] = {k: v for k, v in run["base_config"].items() if k != "num_updates"}
        out["arms"] = [{**{k: v for k, v in a.items() if k not in ARM_MAY_CHANGE},
                        "config": {k: v for k, v in a["config"].items() if k != "num_updates"}} for a in run["arms"]]
        return out

    return _known(strip(old), strip(new)) == strip(old)


def _known(old, new):
    """`new` without the dictionary keys `old` lacks, at every depth (lists compared element by element)."""
    if isinstance(old, dict) and isinstance(new, dict):
        return {k: _known(old[k], v) for k, v in new.items() if k in old}
    if isinstance(old, list) and isinstance(new, list) and len(old) == len(new):
        return [_known(o, n) for o, n in zip(old, new)]
    return new


# Config fields that cdjax no longer has but a run.json written before their removal names: field -> (the value that
# trained its runs as cdjax trains them now, what the other values were). A record holding that value is read
# without the field; another value is refused.
RETIRED = {
    "cc_chain_impl": ("xla", "the consistency chain as Pallas kernels, since removed: slower than XLA's chain"),
    "cc_clip": (True, "the consistency term without the normalisation's clip, since removed"),
}


def without_retired(run: dict, where: str | pathlib.Path) -> dict:
    """run.json's record `run` without the retired Config fields (RETIRED) of its base config and arms' configs
    (a copy; the record is not changed); RunDirError (one sentence) for one that holds another value than the kept
    one."""
    def config(fields):
        if not isinstance(fields, dict):
            return fields
        for name, (kept, gone) in RETIRED.items():
            if name in fields and fields[name] != kept:
                raise io.RunDirError(f"{where} names {name} {fields[name]!r} ({gone}): this cdjax can plot its runs "
                                     "but not resume or evaluate them.")
        return {k: v for k, v in fields.items() if k not in RETIRED}

    out = dict(run)
    if "base_config" in out:
        out["base_config"] = config(out["base_config"])
    if isinstance(out.get("arms"), list):
        out["arms"] = [{**a, "config": config(a["config"])} if isinstance(a, dict) and "config" in a else a
                       for a in out["arms"]]
    return out


def spec_of(run: dict, out: str | pathlib.Path, **changes) -> SweepSpec:
    """The SweepSpec a run.json records (version 1 records: the options they lack take their defaults)."""
    return recorded(run, out, **changes)[0]


def recorded(run: dict, out: str | pathlib.Path, **changes) -> tuple[SweepSpec, Setting]:
    """(the SweepSpec a run.json records, resolved, and its setting): the setting is looked up by the name the
    record holds, once."""
    defaults = SweepSpec(out=out)
    run = without_retired(run, f"{out}/run.json")
    try:
        setting = agents.get(run.get("setting", agents.DEFAULT))
        phase = run.get("phase")
        if phase is not None:
            phase = io.dataclass_from_json(setting.phase.spec_type, phase)
        spec = SweepSpec(
            out=out, setting=setting.name, config=io.dataclass_from_json(setting.config_type, run["base_config"]),
            arms=tuple(a["name"] for a in run["arms"]), grid={k: tuple(v) for k, v in run["grid"].items()},
            seeds=run["seeds"], seed=run["seed"], total_env_steps=run["requested_env_steps"],
            chunk_updates=run["chunk_updates"], checkpoint_every=run["checkpoint_every"],
            eval_every=run.get("eval_every", defaults.eval_every),
            eval_episodes=run.get("eval_episodes", defaults.eval_episodes),
            final_eval=run.get("final_eval", defaults.final_eval), phase=phase, command=run.get("command", ""),
            bootstrap_reps=run.get("bootstrap_reps", defaults.bootstrap_reps))
    except (KeyError, TypeError, AttributeError, ConfigError) as err:
        raise io.RunDirError(f"{out}/run.json is not a run this cdjax can read ({type(err).__name__}: {err}).") from None
    return dataclasses.replace(spec, **changes).resolved(setting), setting


def resume_spec(out: str | pathlib.Path, **changes) -> SweepSpec:
    """The SweepSpec recorded in `out`/run.json (RunDirError if there is none, or if a compressed log of the run is
    damaged: a resume would log over the gap), with `changes` applied."""
    rd = io.RunDir(pathlib.Path(out))
    record = rd.read()
    rd.check_logs("nothing was changed: restore it, or decompress its readable part into the plain "
                  "log beside it (xz -dc or gzip -dc) and remove it, to resume without the missing rows.")
    return spec_of(record, out, **changes)
