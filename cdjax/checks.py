"""Checks of concrete hyper-parameter values that every setting uses: each failure is one sentence
(`ConfigError`) that names the option as the command line spells it.

A setting declares the range of each of its HParams fields (`Range`; fields it does not name take the
default range) and gets its `check_hparam(name, value)` from `hparam_checker`.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Callable, Mapping

from cdjax.protocol import ConfigError


@dataclasses.dataclass(frozen=True)
class Range:
    """The values a float option may take: finite, from `low` to `high` (`low` itself excluded if `open_low`)."""

    low: float = 0.0
    high: float = math.inf
    open_low: bool = False

    def holds(self, value: float) -> bool:
        above = value > self.low if self.open_low else value >= self.low
        return math.isfinite(value) and above and value <= self.high

    def describe(self) -> str:
        """What a value must do, after "must": "not be negative", "be between 0 and 1", ..."""
        if self.low == 0.0 and self.high == math.inf:
            return "be positive" if self.open_low else "not be negative"
        if self.high == math.inf:
            return f"be {'above' if self.open_low else 'at least'} {self.low:g}"
        if self.low == -math.inf:
            return f"be at most {self.high:g}"
        return f"be between {self.low:g} and {self.high:g}"


NON_NEGATIVE = Range()
POSITIVE = Range(open_low=True)
UNIT = Range(0.0, 1.0)  # a discount, a lambda, a decay
ANY = Range(-math.inf)  # any finite value (e.g. a log standard deviation)


def flag(name: str) -> str:
    """The command-line option of a field: alpha -> --alpha, lr_model -> --lr-model."""
    return "--" + name.replace("_", "-")


def check_value(name: str, value: float, allowed: Range) -> None:
    """ConfigError (one sentence naming the option) unless `value` is finite and inside `allowed`."""
    if not math.isfinite(value):
        raise ConfigError(f"{flag(name)} must be finite, got {value}.")
    if not allowed.holds(value):
        raise ConfigError(f"{flag(name)} must {allowed.describe()}, got {value}.")


def hparam_checker(ranges: Mapping[str, Range], default: Range = NON_NEGATIVE) -> Callable[[str, float], None]:
    """check_hparam(name, value) for a setting whose HParams fields take `ranges[name]` (else `default`)."""

    def check_hparam(name: str, value: float) -> None:
        check_value(name, value, ranges.get(name, default))

    return check_hparam
