"""The expert whose pixel trajectories the pixel setting learns from: a policy of cdjax's own model-free arm
(the observation-space setting, PPO on the state), saved to one file. It joins two settings (the obs setting's policy,
the pixel setting's data), so it lives beside the registry, not in either: the pixel setting loads it, the host side's
`cdjax.runner.export_expert` writes it from an obs run directory.

    cdjax sweep --setting obs --preset halfcheetah --arms model-free --seeds 1 --out runs/expert-hc
    python -m cdjax.runner.export_expert runs/expert-hc experts/halfcheetah.msgpack   # the best run's policy
    cdjax sweep --setting pixel --preset pixel-halfcheetah --expert experts/halfcheetah.msgpack ...

The file holds the observation-space Config (JSON), the policy's parameters, the observation statistics and
the run's deterministic evaluation return: the two parts of what the obs setting's `Trainer.policy(state)`
gives, `{"params": {"policy": ...}, "norms": ...}`. This module reaches that setting through the registry
(`cdjax.agents.get("obs")`) and acts through its protocol `Trainer`, never by importing its package.
`Config.expert = ""` stands for an untrained policy (tests). Exporting the best policy of an observation-space run
directory reads a sweep's checkpoints, so it lives on the host side (`cdjax.runner.export_expert`).
"""

from __future__ import annotations

import dataclasses
import json
import pathlib
from typing import Any, Callable

import jax
import numpy as np
from flax import serialization

from cdjax.normalize import Norms
from cdjax.protocol import ConfigError, Setting

STATE_SETTING = "obs"  # the setting whose model-free policy the expert is


def _state_setting() -> Setting:
    from cdjax import agents  # the registry (a host-side module) at call time: it imports every setting lazily

    return agents.get(STATE_SETTING)


@dataclasses.dataclass(frozen=True)
class Expert:
    config: Any  # the observation-space Config it was trained with (env, network sizes)
    policy: Any  # the policy's flax variables
    norms: Norms  # observation statistics the policy reads its input through
    eval_return: float  # its deterministic evaluation return (NaN for the untrained policy)

    @property
    def acting(self) -> dict:
        """What the obs setting's `Trainer.act` takes: its `Trainer.policy(state)` of this expert."""
        return {"params": {"policy": self.policy}, "norms": self.norms}


def _obs_config(env: str):
    return _state_setting().config_type(env=env, arm="model-free", num_envs=8, num_minibatches=1)


def untrained_expert(env: str, key: jax.Array) -> Expert:
    """A freshly initialised model-free policy (observation statistics at their initial values)."""
    config = _obs_config(env)
    fresh = _state_setting().make_trainer(config).fresh_policy(key)
    return Expert(config, fresh["params"]["policy"], fresh["norms"], float("nan"))


def save_expert(path: str | pathlib.Path, expert: Expert) -> pathlib.Path:
    path = pathlib.Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    blob = {"config": json.dumps(dataclasses.asdict(expert.config)), "policy": serialization.to_state_dict(expert.policy),
            "norms": serialization.to_state_dict(expert.norms), "eval_return": np.float64(expert.eval_return)}
    path.write_bytes(serialization.msgpack_serialize(jax.device_get(blob)))
    return path


def load_expert(path: str | pathlib.Path) -> Expert:
    path = pathlib.Path(path)
    if not path.is_file():
        raise ConfigError(f"--expert {str(path)!r} is not a file (write one with python -m cdjax.runner.export_expert).")
    try:
        blob = serialization.msgpack_restore(path.read_bytes())
        fields = {k: tuple(v) if isinstance(v, list) else v for k, v in json.loads(blob["config"]).items()}
        config = _state_setting().config_type(**fields)
        norms = serialization.from_state_dict(Norms.create(int(np.asarray(blob["norms"]["obs"]["mean"]).shape[-1])),
                                              blob["norms"])
        return Expert(config, blob["policy"], norms, float(blob["eval_return"]))
    except ConfigError as err:
        raise ConfigError(f"--expert {str(path)!r} holds a configuration this cdjax refuses: {err}") from None
    except Exception as err:  # noqa: BLE001 - msgpack, json, a missing key, a wrong type: the file is not an expert
        raise ConfigError(f"--expert {str(path)!r} is not an expert file ({type(err).__name__}: {err}); write one "
                          "with python -m cdjax.runner.export_expert.") from None


def expert_for(env: str, path: str) -> Expert:
    """The expert of a pixel Config: loaded from `path`, or the untrained policy of `env` when path is ""."""
    expert = untrained_expert(env, jax.random.key(0)) if not path else load_expert(path)
    if expert.config.env != env:
        raise ConfigError(f"--expert {path!r} was trained on {expert.config.env}, not on --env {env}.")
    return expert


def actor(expert: Expert) -> Callable[[jax.Array, jax.Array | None], jax.Array]:
    """act(obs [B, O], key or None) -> actions [B, A] in [-1, 1] (None: the deterministic action)."""
    trainer = _state_setting().make_trainer(expert.config)
    acting = dict(expert.acting, params={"policy": jax.tree.map(np.asarray, expert.policy)})
    return lambda obs, key: trainer.act(acting, obs, key)
