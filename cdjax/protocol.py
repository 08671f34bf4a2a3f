"""The contract between a setting (one of the paper's agents) and the host side of cdjax.

The sweep, the checkpoints, the evaluation, the logs, the plots and the `cdjax` command are written
against these types alone. A setting plugs in by registering a `Setting` (cdjax.agents.register):

    Setting(name="obs", config_type=Config, hparams_type=HParams, make_trainer=..., arm_config=..., ...)

Its Config is a frozen dataclass (hashed into the compiled programs) with a `num_updates: int` field and an
`env_steps_per_update` attribute; its HParams is a `flax.struct` dataclass of float32 scalars (vmapped with
the seeds). `make_trainer(config)` gives a `Trainer`: pure functions, never jitted or vmapped here.

    trainer = setting.make_trainer(config)
    state = trainer.init(key, hp)                        # any pytree
    state, metrics = trainer.update(state, hp)           # metrics: {name: scalar}
    actions = trainer.act(trainer.policy(state), obs, key)   # key None: the deterministic action

An optional `Phase` is a program a setting's arms may run once per run before their updates (the Mb-Mf
model-based phase of the observation-space setting); its env steps are charged to the arm's budget.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable, Hashable, Mapping

import jax


class ConfigError(ValueError):
    """A configuration or input that cannot run; the message is one sentence meant for the user."""

State = Any  # a setting's training state: a pytree (leading run axis in a sweep)
HP = Any  # a setting's HParams
ConfigT = Any  # a setting's Config


@dataclasses.dataclass(frozen=True)
class Trainer:
    """What the host side needs of a learner built for one Config; every function is pure."""

    config: ConfigT  # the Config it was built from
    init: Callable[[jax.Array, HP], State]  # (key, hp) -> state
    update: Callable[[State, HP], tuple[State, dict]]  # (state, hp) -> (state, {metric name: scalar}), one update
    policy: Callable[[State], Any]  # state -> what `act` needs of it (parameters, normalisation), a pytree
    act: Callable[[Any, jax.Array, jax.Array | None], jax.Array]  # (policy, obs [B, ...], key | None) -> actions [B, ...]
    # num_envs -> the batched env evaluation plays: reset(key) -> state with .obs, step(state, actions) ->
    # (state, cdjax.envs.Step), episode_length (its time-out), as cdjax.envs.BatchedEnv
    eval_env: Callable[[int], Any]
    # () -> pytree of bool shaped like init's state: the leaves a checkpoint holds; None: all. A leaf left out
    # must be one that no later update reads, or one that `init` of the same run gives again bit for bit.
    saved_leaves: Callable[[], Any] | None = None
    # key -> an untrained policy (what `act` takes) without building the rest of the state; None: not offered
    fresh_policy: Callable[[jax.Array], Any] | None = None
    inner: Any = None  # the setting's own learner object, opaque to the host (its phase may use it)
    # Optional, so that the arms of a sweep that act in the same environments compile their reset (the physics)
    # once: reset(key) -> the environments' part of init's state, init_from(key, hp, that) -> the state, with
    # init(key, hp) == init_from(key, hp, reset(key)); env_key (hashable) is equal exactly for trainers whose reset
    # is the same function. Without them each arm's init program holds its own reset.
    reset: Callable[[jax.Array], Any] | None = None
    init_from: Callable[[jax.Array, HP, Any], State] | None = None
    env_key: Hashable | None = None
    # how a sweep splits its runs over devices (cdjax.sweep): "partition" (XLA's partitioner places the vmapped
    # programs) or "local" (each device runs its own runs in a shard_map of the update programs: no collective)
    runs_split: str = "partition"

    def __post_init__(self):  # the library's checks of what init and update are given (`guarded`), for every setting
        init, update = guarded(self.init, self.update)
        object.__setattr__(self, "init", init)
        object.__setattr__(self, "update", update)


@dataclasses.dataclass(frozen=True)
class Phase:
    """A program run once per run before the updates, by the arms it applies to."""

    title: str  # how messages name it, e.g. "Mb-Mf phase"
    flag: str  # the command line's on/off option, --<flag> / --no-<flag>; its fields are --phase-<field>
    spec_type: type  # frozen dataclass of its static sizes (recorded in run.json)
    applies: Callable[[ConfigT], bool]  # whether the arm with this config runs it
    validate: Callable[[ConfigT, Any], None]  # (config, spec) -> None, or ConfigError (one sentence)
    env_steps: Callable[[ConfigT, Any], int]  # (config, spec) -> env steps it takes per run, statically
    make: Callable[[Trainer, Any], Callable[[State, HP], tuple[State, dict]]]  # -> run(state, hp) -> (state, info)
    describe: Callable[[Mapping[str, float]], str]  # info averaged over runs -> a console sentence
    as_metrics: Mapping[str, str] = dataclasses.field(default_factory=dict)  # info name -> metric name (update 0)


@dataclasses.dataclass(frozen=True)
class Metrics:
    """Metric names the host reads (progress, summaries, plots)."""

    ret: str  # the undiscounted return of finished episodes
    discounted_ret: str  # the discounted return
    panels: tuple[tuple[str, str, bool], ...] = ()  # (metric, title, log scale) of the diagnostics figure
    # the metric counting the optimiser steps an update skipped because its loss or gradient was not finite: the
    # host sums it per run and names the runs that skipped any (progress, summary); None: not reported
    skipped: str | None = None
    # a Config field the return metric is measured at (the pixel setting's likelihood "at k": its horizon): arms that
    # differ in it are ranked on different measures, which the sweep says (`cdjax.runner.plan.return_note`)
    ret_field: str | None = None


@dataclasses.dataclass(frozen=True)
class Preset:
    """A named set of explicit overrides of a setting's defaults: dataclass defaults < preset < command-line flags."""

    about: str  # one line shown by `cdjax sweep --help`
    config: dict[str, Any]  # Config field -> value
    hparams: dict[str, tuple[float, ...]]  # HParams field -> values (several values make a grid)
    sweep: dict[str, Any]  # SweepSpec field -> value (arms, seeds, total_env_steps, chunk_updates, ...)
    phase: dict[str, Any] | None = None  # the setting's Phase spec field -> value; None: no phase unless asked for


@dataclasses.dataclass(frozen=True)
class Setting:
    """One of the paper's settings as the host sees it."""

    name: str  # registry key, recorded in run.json
    about: str  # one line for `cdjax sweep --help`
    config_type: type  # frozen dataclass: shapes, loop lengths, env; has `num_updates` and `env_steps_per_update`
    hparams_type: type  # flax.struct dataclass of float scalars
    make_trainer: Callable[[ConfigT], Trainer]
    arm_config: Callable[[str, ConfigT], ConfigT]  # (arm name, base config) -> the arm's config, or ConfigError
    arm_fields: tuple[str, ...]  # Config fields set by the arm name (not command-line options)
    arms_help: str  # how arms are named, for help and messages
    default_arms: tuple[str, ...]
    # (arm config, runs a phase) -> {hp name: value} the arm does not use: kept out of its grid, set to the
    # value (None: the field's default) so that they do not multiply its runs
    unused_hparams: Callable[[ConfigT, bool], Mapping[str, float | None]]
    shown_hparams: Callable[[ConfigT], tuple[str, ...]]  # hp names every run label of the arm shows
    check_hparam: Callable[[str, float], None]  # (name, value) -> None, or ConfigError (one sentence)
    metrics: Metrics
    presets: Mapping[str, Preset]  # name -> Preset (about, config, hparams, sweep, phase)
    default_preset: Callable[[Mapping[str, Any]], str | None]  # given Config values -> the preset used without --preset
    phase: Phase | None = None
    # (arm, config, chunk metrics [R, n]) -> None, or (how many runs it concerns, a warning): said when that number
    # grows, so a fault that spreads over a sweep's runs after its first warning is said again
    watch: Callable[[str, ConfigT, Mapping], tuple[int, str] | None] | None = None
    # the sweep's evaluations (and `cdjax eval` by default) sample the policy's actions; False: its deterministic
    # action. A greedy discrete policy can stall for a whole episode (Atari: not pressing FIRE under sticky actions),
    # and A2C's literature reports the sampling policy.
    eval_sampled: bool = False
    # config -> train(key, hp) -> (final state, metrics [num_updates]): the whole run as one pure function (PureJaxRL
    # style, the caller jits/vmaps it); `cdjax.agents.make_train` dispatches on the Config's type to it. None: the
    # setting has no such function (e.g. its environment lives outside JAX).
    make_train: Callable[[ConfigT], Callable] | None = None


__all__ = ["ConfigError", "Metrics", "Phase", "Preset", "Setting", "Trainer", "check_one_run_hparams", "check_state",
           "guarded", "scanned_train"]


def _fields(tree) -> list[tuple[str, Any]]:
    """(name, leaf) of a pytree: a dataclass's field names (HParams), else JAX's key paths."""
    if dataclasses.is_dataclass(tree):
        return [(f.name, getattr(tree, f.name)) for f in dataclasses.fields(tree)]
    return [(jax.tree_util.keystr(path), leaf) for path, leaf in jax.tree_util.tree_flatten_with_path(tree)[0]]


def check_one_run_hparams(hp, traced_only: bool = False) -> None:
    """ConfigError naming the first HParams field that is not one number: init, update and train take one run's
    hyper-parameters (vmapped, a stacked field arrives one value at a time). Shapes only: free under jit and vmap.
    `traced_only`: only the fields traced under jit or vmap (a setting's init checks concrete ones itself, values
    and types first, `cdjax.checks.HParamRanges`)."""
    for name, value in _fields(hp):
        if traced_only and not isinstance(value, jax.core.Tracer):
            continue
        shape = getattr(value, "shape", ())
        if shape != ():
            raise ConfigError(f"HParams field {name} has shape {tuple(shape)} where one run takes one number: to train "
                              "several runs, stack every field with one value per key and vmap both, "
                              "jax.vmap(train)(keys, hps), each field of length len(keys).")


def _is_traced(tree) -> bool:
    return any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree.leaves(tree))


def check_state(state, expected, what: str = "update") -> None:
    """ConfigError naming the first leaf of `state` whose place or shape differs from `expected` (shapes, e.g.
    `jax.eval_shape` of init): a state made for another Config or setting."""
    got, want = _fields_of_state(state), _fields_of_state(expected)
    if set(got) != set(want):
        missing = sorted(set(want) - set(got))[:3] or sorted(set(got) - set(want))[:3]
        raise ConfigError(f"{what} got a state laid out unlike the one this trainer's init makes (leaves "
                          f"{', '.join(missing)} differ): it was made for another Config or setting; pass the state "
                          "of this trainer's init.")
    for name, leaf in got.items():
        if tuple(leaf) != tuple(want[name]):
            raise ConfigError(f"{what} got a state whose leaf {name} has shape {tuple(leaf)} where this trainer's "
                              f"Config makes {tuple(want[name])}: it was made for another Config (a field that sets "
                              "shapes differs); pass the state of this trainer's init.")


def _fields_of_state(tree) -> dict[str, tuple]:
    return {jax.tree_util.keystr(path): tuple(getattr(leaf, "shape", ()))
            for path, leaf in jax.tree_util.tree_flatten_with_path(tree)[0]}


def guarded(init: Callable, update: Callable) -> tuple[Callable, Callable]:
    """(init, update) that first check what they are given, each failure one ConfigError naming the field: every
    HParams field one number (`check_one_run_hparams`), and, for update called outside jit and vmap, the state's
    leaves shaped as init makes them for this Config (`check_state`; init's shapes are traced once, at the first such
    call). Under jit and vmap only shapes are looked at, at trace time: nothing is added to the compiled program."""
    if getattr(update, "guarded", False):
        return init, update
    expected: list = []

    def checked_init(key, hp):
        check_one_run_hparams(hp, traced_only=True)
        return init(key, hp)

    def checked_update(state, hp):
        check_one_run_hparams(hp)
        if not _is_traced(state):
            if not expected:
                try:
                    expected.append(jax.eval_shape(init, jax.random.key(0), hp))
                except Exception:  # noqa: BLE001 - an init that takes another kind of key: nothing to compare with
                    expected.append(None)
            if expected[0] is not None:
                check_state(state, expected[0])
        return update(state, hp)

    checked_init.guarded = checked_update.guarded = True
    checked_init.__wrapped__, checked_update.__wrapped__ = init, update
    return checked_init, checked_update


def scanned_train(init: Callable, update: Callable, num_updates: int) -> Callable:
    """Every setting's `make_train`: train(key, hp) -> (final state, metrics with leaves [num_updates]), `init`
    followed by a `lax.scan` of `update`; pure, the caller jits and vmaps it. The HParams are checked as `guarded`
    does (one number per field: a vmapped train whose fields are not stacked like the keys names the field)."""
    init, update = guarded(init, update)

    def train(key, hp):
        state = init(key, hp)
        return jax.lax.scan(lambda s, _: update(s, hp), state, None, length=num_updates)

    return train
