"""The settings the host side can run, by name: each is a `cdjax.protocol.Setting`.

    from cdjax import agents
    setting = agents.get("obs")            # the observation-space agent (PPO + dynamics model + consistency)
    agents.register(my_setting)            # a new setting: the sweep, checkpoints, eval, plots and CLI take it

The observation-space setting is registered on first use (importing it pulls in brax and MJX).
"""

from __future__ import annotations

import importlib

from cdjax.protocol import ConfigError, Setting

DEFAULT = "obs"  # the setting of `cdjax sweep` without --setting
_BUILTIN = {"obs": "cdjax.agents.obs", "atari": "cdjax.agents.atari",  # name -> module defining SETTING
            "pixel": "cdjax.agents.pixel", "offpolicy": "cdjax.agents.offpolicy"}
_REGISTRY: dict[str, Setting] = {}


def register(setting: Setting) -> Setting:
    """Make `setting` available under setting.name (replacing one of that name)."""
    _REGISTRY[setting.name] = setting
    return setting


def get(name: str) -> Setting:
    """The setting registered as `name` (ConfigError, one sentence, for an unknown name)."""
    if not isinstance(name, str):
        raise ConfigError(f"A setting is named by a string, got {name!r}; choose one of: {', '.join(names())}.")
    if name not in _REGISTRY and name in _BUILTIN:
        register(importlib.import_module(_BUILTIN[name]).SETTING)
    if name not in _REGISTRY:
        raise ConfigError(f"Unknown setting {name!r}; choose one of: {', '.join(names())}.")
    return _REGISTRY[name]


def names() -> list[str]:
    return sorted(set(_BUILTIN) | set(_REGISTRY))
