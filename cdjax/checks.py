"""One validation per setting: what every field of a setting's Config and HParams may hold, declared once and
checked by the same code wherever a value becomes concrete (a Config when it is built, HParams when `init` gets
them, the command line's grid when it is planned). Each failure is one sentence (`ConfigError`) naming the field.

A setting declares its Config's fields (`Fields`: a `Count`, `Real`, `Widths`, `Choice`, `Flag` or `Text` per
field; a field it does not name gets the kind its annotation gives, with no range) and its HParams' ranges
(`HParamRanges`: a `Range` per field, the rest `NON_NEGATIVE`):

    FIELDS = Fields(Config, num_envs=Count(1), cc_windows=Count(0, zero="all windows"), min_std=Real(POSITIVE))
    HP_RANGES = HParamRanges(HParams, gamma=UNIT, init_log_std=ANY)
    FIELDS.check(config)        # in Config.__post_init__
    HP_RANGES.check(hp)         # in the trainer's init: concrete values are checked, traced ones (under jit) skipped

Config fields are named as the dataclass spells them (`num_envs`), HParams as the command line does (`--lr-policy`),
as the messages always have.
"""

from __future__ import annotations

import dataclasses
import math
import numbers
import typing
from typing import Callable, Literal, Mapping

import numpy as np
from jax.core import Tracer

from cdjax.protocol import ConfigError


@dataclasses.dataclass(frozen=True)
class Range:
    """The values a float may take: finite, from `low` to `high` (an end itself excluded if `open_low` /
    `open_high`)."""

    low: float = 0.0
    high: float = math.inf
    open_low: bool = False
    open_high: bool = False

    def holds(self, value: float) -> bool:
        above = value > self.low if self.open_low else value >= self.low
        below = value < self.high if self.open_high else value <= self.high
        return math.isfinite(value) and above and below

    def describe(self) -> str:
        """What a value must do, after "must": "not be negative", "be between 0 and 1", ..."""
        if self.low == 0.0 and self.high == math.inf:
            return "be positive" if self.open_low else "not be negative"
        if self.high == math.inf:
            return f"be {'above' if self.open_low else 'at least'} {self.low:g}"
        if self.low == -math.inf:
            return f"be {'below' if self.open_high else 'at most'} {self.high:g}"
        if self.open_low or self.open_high:
            return f"be in {'(' if self.open_low else '['}{self.low:g}, {self.high:g}{')' if self.open_high else ']'}"
        return f"be between {self.low:g} and {self.high:g}"


INT32_MAX = 2 ** 31 - 1  # the largest count an int32 counter holds (an episode's steps, a run's updates)

NON_NEGATIVE = Range()
POSITIVE = Range(open_low=True)
UNIT = Range(0.0, 1.0)  # a discount, a lambda, a decay
PROBABILITY_BELOW_1 = Range(0.0, 1.0, open_high=True)
ANY = Range(-math.inf)  # any finite value (e.g. a log standard deviation)


def flag(name: str) -> str:
    """The command-line option of a field: alpha -> --alpha, lr_model -> --lr-model."""
    return "--" + name.replace("_", "-")


def _is_int(value) -> bool:
    return isinstance(value, numbers.Integral) and not isinstance(value, (bool, np.bool_))


def _is_real(value) -> bool:
    return isinstance(value, numbers.Real) and not isinstance(value, (bool, np.bool_))


# ---------------------------------------------------------------------------------------------------
# Config fields: one kind per field


@dataclasses.dataclass(frozen=True)
class Count:
    """A whole number from `low` (to `high`; None: any); `zero` says what 0 means where 0 is allowed as a special
    value."""

    low: int | None = 1
    high: int | None = None
    zero: str = ""  # e.g. "all windows": 0 is allowed and means that (low is then the smallest other value)

    def check(self, name: str, value) -> None:
        ok = _is_int(value) and (self.low is None or value >= self.low or (self.zero and value == 0)) and (
            self.high is None or value <= self.high)
        if ok:
            return
        if self.low is None:
            what = "a whole number"
        elif self.zero:
            what = f"0 ({self.zero}) or an integer of at least {self.low}" if self.low > 1 else (
                f"0 ({self.zero}) or a positive integer")
        elif self.high is not None:
            what = f"an integer from {self.low} to {self.high}"
        else:
            what = {1: "a positive integer", 0: "a non-negative integer"}.get(self.low,
                                                                               f"an integer of at least {self.low}")
        raise ConfigError(f"{name} must be {what}, got {value!r}.")


@dataclasses.dataclass(frozen=True)
class Real:
    """A finite number in `allowed`."""

    allowed: Range = NON_NEGATIVE

    def check(self, name: str, value) -> None:
        if not _is_real(value):
            raise ConfigError(f"{name} must be a number, got {value!r}.")
        if not math.isfinite(value):
            raise ConfigError(f"{name} must be finite, got {value!r}.")
        if not self.allowed.holds(float(value)):
            raise ConfigError(f"{name} must {self.allowed.describe()}, got {value!r}.")


@dataclasses.dataclass(frozen=True)
class Widths:
    """Layer widths: a non-empty tuple of positive integers."""

    def check(self, name: str, value) -> None:
        if not (isinstance(value, tuple) and value and all(_is_int(w) and w > 0 for w in value)):
            raise ConfigError(f"{name} must be a non-empty tuple of positive integers, got {value!r}.")


@dataclasses.dataclass(frozen=True)
class Choice:
    """One of the given words."""

    values: tuple[str, ...]

    def check(self, name: str, value) -> None:
        if not isinstance(value, str) or value not in self.values:
            raise ConfigError(f"Unknown {name} {value!r}; choose one of: {', '.join(self.values)}.")


@dataclasses.dataclass(frozen=True)
class Flag:
    """True or False."""

    def check(self, name: str, value) -> None:
        if not isinstance(value, (bool, np.bool_)):
            raise ConfigError(f"{name} must be true or false, got {value!r}.")


@dataclasses.dataclass(frozen=True)
class Text:
    """A string (what it must name is the setting's own check, e.g. a known env)."""

    def check(self, name: str, value) -> None:
        if not isinstance(value, str):
            raise ConfigError(f"{name} must be a string, got {value!r}.")


Kind = Count | Real | Widths | Choice | Flag | Text


def kind_of(hint) -> Kind:
    """The kind a field's annotation gives, with no range beyond its type (a field a setting leaves undeclared)."""
    if typing.get_origin(hint) is Literal:
        return Choice(tuple(typing.get_args(hint)))
    if typing.get_origin(hint) is tuple:
        return Widths()
    return {bool: Flag(), int: Count(None), float: Real(ANY), str: Text()}.get(hint, Text())


class Fields:
    """The kind of every field of a frozen-dataclass Config: declared ones, and the rest from their annotations."""

    def __init__(self, cls: type, **declared: Kind):
        hints = typing.get_type_hints(cls)
        names = [f.name for f in dataclasses.fields(cls)]
        unknown = sorted(set(declared) - set(names))
        if unknown:  # a programming error: fail at import
            raise TypeError(f"{cls.__name__} has no field(s) {', '.join(unknown)}")
        self.cls = cls
        self.declared = dict(declared)
        self.kinds = {name: declared.get(name) or kind_of(hints[name]) for name in names}

    def check(self, config) -> None:
        """ConfigError (one sentence naming the field) for the first field whose value is not of its kind."""
        for name, kind in self.kinds.items():
            kind.check(name, getattr(config, name))


def check_type(value, cls: type, what: str = "config") -> None:
    """ConfigError unless `value` is a `cls` (e.g. a Config of another setting given to this one)."""
    if not isinstance(value, cls):
        raise ConfigError(f"This {what} must be a {cls.__module__}.{cls.__name__}, got a "
                          f"{type(value).__module__}.{type(value).__name__}; each setting takes its own.")


# ---------------------------------------------------------------------------------------------------
# HParams: a range per float


def check_value(name: str, value, allowed: Range) -> None:
    """ConfigError (one sentence naming the option) unless `value` is a finite number inside `allowed`."""
    if not _is_real(value):
        raise ConfigError(f"{flag(name)} must be a number, got {value!r}.")
    if not math.isfinite(value):
        raise ConfigError(f"{flag(name)} must be finite, got {float(value)}.")
    if not allowed.holds(float(value)):
        raise ConfigError(f"{flag(name)} must {allowed.describe()}, got {float(value)}.")
    with np.errstate(over="ignore", under="ignore"):
        single = float(np.float32(value))  # hyper-parameters train as float32
    if not math.isfinite(single):
        raise ConfigError(f"{flag(name)} must be finite in float32, which it trains in (at most "
                          f"{float(np.finfo(np.float32).max):.3g} in size), got {float(value)}.")
    if not allowed.holds(single):
        raise ConfigError(f"{flag(name)} must {allowed.describe()} in float32, which it trains in, got "
                          f"{float(value)} ({single} in float32).")


def _as_array(value) -> np.ndarray | None:
    """A concrete value as a numpy array (None: not an array of anything)."""
    try:
        return np.asarray(value)
    except Exception:  # noqa: BLE001 - anything that is no array of numbers is said by the caller
        return None


class HParamRanges:
    """The range of every field of a setting's HParams (the ones not named: `default`)."""

    def __init__(self, cls: type, default: Range = NON_NEGATIVE, **ranges: Range):
        names = [f.name for f in dataclasses.fields(cls)]
        unknown = sorted(set(ranges) - set(names))
        if unknown:
            raise TypeError(f"{cls.__name__} has no field(s) {', '.join(unknown)}")
        self.cls = cls
        self.ranges = {name: ranges.get(name, default) for name in names}

    def check_one(self, name: str, value: float) -> None:
        """One value of one field (a grid value from the command line): ConfigError naming the option."""
        check_value(name, value, self.ranges.get(name, NON_NEGATIVE))

    def check(self, hp, one_run: bool = False) -> None:
        """Every concrete value of `hp` (scalars or stacked runs [R]); traced values are skipped. `one_run`: the
        values of one run, as a trainer's init takes them (vmapped, a stacked set's values arrive one at a time), so
        a concrete stacked value is refused, rather than failing deep in the trace on mismatched shapes."""
        check_type(hp, self.cls, "hyper-parameter set")
        for name, allowed in self.ranges.items():
            value = getattr(hp, name)
            if isinstance(value, Tracer):  # under jit or vmap: checked where it was concrete (the grid, the caller)
                continue
            array = _as_array(value)
            if array is None or array.dtype.kind not in "fiu":
                raise ConfigError(f"{flag(name)} must be a number, got {value!r}.")
            for element in array.reshape(-1).tolist():
                check_value(name, element, allowed)
            if one_run and array.ndim:
                raise ConfigError(f"{name} holds {array.size} values (stacked hyper-parameters) where init takes one "
                                  f"run's: vmap over them with the seeds, jax.vmap(train)(keys, stacked), or pass "
                                  f"one set.")


def hparam_checker(ranges: Mapping[str, Range], default: Range = NON_NEGATIVE) -> Callable[[str, float], None]:
    """check_hparam(name, value) for a setting whose HParams fields take `ranges[name]` (else `default`)."""

    def check_hparam(name: str, value: float) -> None:
        check_value(name, value, ranges.get(name, default))

    return check_hparam


__all__ = ["ANY", "Choice", "Count", "Fields", "Flag", "HParamRanges", "INT32_MAX", "NON_NEGATIVE", "POSITIVE",
           "PROBABILITY_BELOW_1", "Range", "Real", "Text", "UNIT", "Widths", "check_type", "check_value", "flag",
           "hparam_checker", "kind_of"]

