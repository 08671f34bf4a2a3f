"""cdjax: consistent dynamics models (Sodhani et al., 2019) as one jitted JAX pipeline on MuJoCo-MJX.

One face for every setting (observation space, pixels, Atari, off-policy): `make_train(config)` takes any setting's Config and
gives `train(key, hp) -> (state, metrics)`, which the caller jits and vmaps:

    import cdjax
    cdjax.runtime.apply_xla_defaults()             # optional, first: cdjax's XLA flags (the `cdjax` command's)
    train = cdjax.make_train(cdjax.Config(env="ant"))

`make_trainer(config)` gives a setting as it gives itself to the host side (`cdjax.protocol.Trainer`);
`make_agent(config)` the observation-space agent's pieces (init, update, collect, loss, act, model_step, ...).

Importing cdjax changes nothing in the process (XLA_FLAGS, stdout, logging) and imports no setting: each name below
is imported on first use, so a MinAtar user never imports brax or MuJoCo.
"""

from __future__ import annotations

import importlib
import time as _time

_imported_at = _time.time()  # when this process imported cdjax (the `cdjax` command's start-up rows: cdjax.io.timings)

__version__ = "0.1.0"

# name -> the module it comes from, imported when the name is first asked for (PEP 562)
_LAZY = {
    "make_train": "cdjax.agents", "make_trainer": "cdjax.agents",  # dispatch on the Config's type (the registry)
    "ConfigError": "cdjax.protocol", "Trainer": "cdjax.protocol",
    **{name: "cdjax.agents.obs" for name in ("Config", "HParams", "MbMfPhase", "ObsAgent", "TrainState", "make_agent",
                                             "make_mbmf_phase", "stack_hparams", "total_env_steps")},
}
__all__ = sorted(_LAZY)


def __getattr__(name: str):
    if name in _LAZY:
        module = importlib.import_module(_LAZY[name])
        value = getattr(module, name)
        globals()[name] = value  # asked once
        return value
    try:  # a submodule, as `cdjax.runtime` after a plain `import cdjax`
        return importlib.import_module(f"{__name__}.{name}")
    except ModuleNotFoundError as err:
        if err.name != f"{__name__}.{name}":
            raise
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(_LAZY))
