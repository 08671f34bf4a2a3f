"""The settings the host side can run, by name: each is a `cdjax.protocol.Setting`.

    from cdjax import agents
    setting = agents.get("obs")            # the observation-space agent (PPO + dynamics model + consistency)
    agents.register(my_setting)            # a new setting: the sweep, checkpoints, eval, plots and CLI take it
    train = agents.make_train(config)      # any setting's Config: train(key, hp) -> (state, metrics)

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


def setting_of(config) -> Setting:
    """The setting whose Config type `config` is (ConfigError, one sentence, for an object of no setting's type)."""
    for name in names():
        setting = get(name)
        if type(config) is setting.config_type:
            return setting
    raise ConfigError(f"{type(config).__name__} is no setting's Config; give the Config of one of: {', '.join(names())}.")


def make_train(config):
    """train(key, hp) -> (final state, metrics) of the setting whose Config `config` is: pure, jit/vmap it yourself."""
    setting = setting_of(config)
    if setting.make_train is None:
        raise ConfigError(f"Setting {setting.name!r} has no make_train; run it with make_trainer or `cdjax sweep`.")
    return setting.make_train(config)


def make_trainer(config):
    """The protocol's Trainer (`cdjax.protocol.Trainer`) of the setting whose Config `config` is."""
    return setting_of(config).make_trainer(config)
