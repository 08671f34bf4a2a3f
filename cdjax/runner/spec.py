"""`SweepSpec`: what a sweep is asked to do (recorded whole in run.json, so that a resumed sweep is the same
run), and the bounds of its counts."""

from __future__ import annotations

import dataclasses
import pathlib
from typing import Any, Mapping, Sequence

from cdjax import agents
from cdjax.checks import INT32_MAX  # update counters are int32 on the device (cli and plan take it from here)
from cdjax.protocol import ConfigError, Setting

SEED_MAX = 2**63 - 1  # jax.random.key takes a 64-bit seed


def preset_spec(out: str | pathlib.Path, setting: str = agents.DEFAULT, preset: str | None = None, *,
                config: Mapping[str, Any] | None = None, hparams: Mapping[str, Any] | None = None,
                phase: Mapping[str, Any] | None = None, phase_on: bool | None = None, **spec: Any) -> "SweepSpec":
    """The SweepSpec `cdjax sweep` builds from its options: the setting's defaults < a preset < the values given.

    preset: a name in the setting's presets; None: the one the setting picks for the given config (the observation
    space's: its env's, e.g. "ant" for env="ant" or no env). config: Config field -> value; hparams: HParams field ->
    a value or a tuple of values (a grid); phase: the setting's phase fields (given: the phase runs); phase_on: run the
    phase or not (None: when phase fields are given or the preset has one); spec: SweepSpec fields (arms, seeds,
    total_env_steps, ...). `SweepSpec(...)` itself applies no preset."""
    chosen = agents.get(setting)
    config, hparams, phase = dict(config or {}), dict(hparams or {}), dict(phase or {})
    if preset is not None and preset not in chosen.presets:
        raise ConfigError(f"Unknown preset {preset!r}; choose one of: {', '.join(chosen.presets)}.")
    base = chosen.presets.get(preset or chosen.default_preset(config) or "")
    grid = {**(base.hparams if base else {}),
            **{name: tuple(v) if isinstance(v, (list, tuple)) else (v,) for name, v in hparams.items()}}
    values = {**(base.sweep if base else {}), **spec}
    values["arms"] = tuple(values.get("arms", ()))
    on = phase_on if phase_on is not None else bool(phase) or bool(base and base.phase is not None)
    if phase and phase_on is False:
        raise ConfigError("phase_on=False contradicts the phase fields given.")
    if on and chosen.phase is None:
        raise ConfigError(f"The {chosen.name} setting has no phase to run.")
    return SweepSpec(out=out, setting=chosen.name,
                     config=chosen.config_type(**{**(base.config if base else {}), **config}), grid=grid,
                     phase=chosen.phase.spec_type(**{**((base.phase or {}) if base else {}), **phase}) if on else None,
                     **values)


@dataclasses.dataclass
class SweepSpec:
    """Everything a sweep needs; the CLI only parses into this, a notebook can build it directly."""

    out: str | pathlib.Path  # the run directory
    setting: str = agents.DEFAULT  # the agent (cdjax.agents): its Config, HParams, arms, presets and phase
    config: Any = None  # the setting's base Config (None: its defaults); arms set their fields, --steps num_updates
    arms: tuple[str, ...] = ()  # arms to train, each its own compiled program (empty: the setting's default arms)
    grid: Mapping[str, Sequence[float]] = dataclasses.field(default_factory=dict)  # HParams field -> values
    seeds: int = 3  # runs per hyper-parameter combination; seed s has the same key in every arm
    seed: int = 0  # base seed: seed s uses jax.random.split(jax.random.key(seed), seeds)[s]
    total_env_steps: int = 1_000_000  # environment steps per run, e.g. 50_000_000; rounded to whole updates
    chunk_updates: int = 0  # updates per compiled chunk; 0 = about 5% of the run
    checkpoint_every: int = 1  # chunks between checkpoints (a killed process loses at most this many)
    eval_every: int = 0  # chunks between evaluations; 0 = only at the end
    eval_episodes: int = 10  # episodes per run in evaluations
    final_eval: bool = True  # evaluate and plot when the sweep ends
    bootstrap_reps: int = 2000  # bootstrap replications of the 95% intervals in the final plots and summary
    phase: Any = None  # the setting's pre-update phase (e.g. cdjax.agents.obs.MbMfPhase), run by the arms it applies to
    progress: bool = True  # show a progress display (a line per chunk when stderr is not a terminal)
    command: str = ""  # the command line, recorded in run.json

    def resolved(self, setting: Setting) -> "SweepSpec":
        """The spec with its setting's defaults filled in (base config, arms); ConfigError (one sentence) for a
        config or phase of another setting."""
        config = self.config if self.config is not None else setting.config_type()
        arms = (self.arms,) if isinstance(self.arms, str) else self.arms
        if not isinstance(arms, (list, tuple)):
            raise ConfigError(f"--arms needs arm names, got {arms!r}.")
        if not isinstance(config, setting.config_type):
            raise ConfigError(f"The {setting.name} setting takes a {setting.config_type.__name__} as its config, not a "
                              f"{type(config).__name__}; give the setting that config belongs to "
                              f"(SweepSpec(setting=...), --setting) or a {setting.config_type.__name__}.")
        if self.phase is not None and setting.phase is not None and not isinstance(self.phase,
                                                                                     setting.phase.spec_type):
            raise ConfigError(f"The {setting.name} setting's phase takes a {setting.phase.spec_type.__name__}, not a "
                              f"{type(self.phase).__name__}.")
        return dataclasses.replace(self, config=config, arms=tuple(arms) or setting.default_arms)


def out_dir(spec: SweepSpec) -> pathlib.Path:
    """The run directory a spec names (ConfigError, one sentence, for anything that is not a path)."""
    if not isinstance(spec.out, (str, pathlib.PurePath)) or str(spec.out) == "":
        raise ConfigError(f"--out must name a directory, got {spec.out!r}.")
    return pathlib.Path(spec.out)


def resolve(spec: SweepSpec) -> tuple[SweepSpec, Setting]:
    """The setting a spec names, looked up once per sweep (and passed down to plan, arms and loop), and the spec
    with its defaults filled in; ConfigError (one sentence) for an unknown setting."""
    setting = agents.get(spec.setting)
    return spec.resolved(setting), setting


# SweepSpec field -> command-line option, where they differ.
FLAGS = {"total_env_steps": "--steps"}


def flag(name: str) -> str:
    return FLAGS.get(name, "--" + name.replace("_", "-"))


def check_bounds(spec: SweepSpec) -> None:
    """ConfigError (one sentence) for a count out of range; the sizes are checked against memory later."""
    counts = {"seeds": (1, INT32_MAX), "seed": (0, SEED_MAX), "total_env_steps": (1, None),
              "chunk_updates": (0, INT32_MAX), "checkpoint_every": (1, INT32_MAX), "eval_every": (0, INT32_MAX),
              "eval_episodes": (1, INT32_MAX), "bootstrap_reps": (1, INT32_MAX)}
    for name, (low, high) in counts.items():
        value = getattr(spec, name)
        if not isinstance(value, int) or isinstance(value, bool) or value < low or (high is not None and value > high):
            what = f"an integer from {low:,} to {high:,}" if high is not None else f"an integer of at least {low:,}"
            raise ConfigError(f"{flag(name)} must be {what}, got {value!r}.")
    for name in ("final_eval", "progress"):
        if not isinstance(getattr(spec, name), bool):
            raise ConfigError(f"SweepSpec.{name} must be true or false, got {getattr(spec, name)!r}.")
    out_dir(spec)
    if not isinstance(spec.grid, Mapping):
        raise ConfigError(f"SweepSpec.grid must map hyper-parameter names to values, got {spec.grid!r}.")
    if not isinstance(spec.command, str):
        raise ConfigError(f"SweepSpec.command must be a string, got {spec.command!r}.")
    if not spec.arms or not all(isinstance(a, str) for a in spec.arms):
        raise ConfigError(f"--arms needs at least one arm name, got {spec.arms!r}.")
    if len(set(spec.arms)) != len(spec.arms):
        raise ConfigError(f"--arms lists an arm twice: {' '.join(spec.arms)}.")
