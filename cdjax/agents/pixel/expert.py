"""The expert whose pixel trajectories the pixel setting learns from: a policy of cdjax's own model-free arm
(the observation-space setting, PPO on the state), saved to one file.

    cdjax sweep --setting obs --preset halfcheetah --arms model-free --seeds 1 --out runs/expert-hc
    python -m cdjax.agents.pixel.export_expert runs/expert-hc experts/halfcheetah.msgpack   # the best run's policy
    cdjax sweep --setting pixel --preset pixel-halfcheetah --expert experts/halfcheetah.msgpack ...

The file holds the observation-space Config (JSON), the policy's parameters, the observation statistics and
the run's deterministic evaluation return. `Config.expert = ""` stands for an untrained policy (tests).
"""

from __future__ import annotations

import dataclasses
import json
import pathlib
from typing import Any, Callable

import jax
import numpy as np
from flax import serialization

from cdjax.config import Config, ConfigError
from cdjax.normalize import Norms


@dataclasses.dataclass(frozen=True)
class Expert:
    config: Config  # the observation-space Config it was trained with (env, network sizes)
    policy: Any  # the policy's flax variables
    norms: Norms  # observation statistics the policy reads its input through
    eval_return: float  # its deterministic evaluation return (NaN for the untrained policy)


def _obs_config(env: str) -> Config:
    return Config(env=env, arm="model-free", num_envs=8, num_minibatches=1)


def untrained_expert(env: str, key: jax.Array) -> Expert:
    """A freshly initialised model-free policy (observation statistics at their initial values)."""
    from cdjax.train import ObsAgent

    agent = ObsAgent(_obs_config(env))
    params = agent.modules["policy"].init(key, np.zeros((1, agent.O), np.float32))
    return Expert(agent.config, params, Norms.create(agent.O), float("nan"))


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
        raise ConfigError(f"--expert {str(path)!r} is not a file (write one with python -m cdjax.agents.pixel.export_expert).")
    blob = serialization.msgpack_restore(path.read_bytes())
    fields = {k: tuple(v) if isinstance(v, list) else v for k, v in json.loads(blob["config"]).items()}
    config = Config(**fields)
    norms = serialization.from_state_dict(Norms.create(int(np.asarray(blob["norms"]["obs"]["mean"]).shape[-1])),
                                          blob["norms"])
    return Expert(config, blob["policy"], norms, float(blob["eval_return"]))


def expert_for(env: str, path: str) -> Expert:
    """The expert of a pixel Config: loaded from `path`, or the untrained policy of `env` when path is ""."""
    expert = untrained_expert(env, jax.random.key(0)) if not path else load_expert(path)
    if expert.config.env != env:
        raise ConfigError(f"--expert {path!r} was trained on {expert.config.env}, not on --env {env}.")
    return expert


def actor(expert: Expert) -> Callable[[jax.Array, jax.Array | None], jax.Array]:
    """act(obs [B, O], key or None) -> actions [B, A] in [-1, 1] (None: the deterministic action)."""
    from cdjax.train import ObsAgent

    agent = ObsAgent(expert.config)
    params = {"policy": jax.tree.map(np.asarray, expert.policy)}
    return lambda obs, key: agent.act(params, expert.norms, obs, key)


def export_from_run(run_dir: str | pathlib.Path, path: str | pathlib.Path, arm: str = "model-free") -> Expert:
    """The policy of `arm`'s run with the best deterministic evaluation return in an observation-space sweep."""
    from cdjax import io
    from cdjax.runner import restore_arms

    run_dir = pathlib.Path(run_dir)
    evals = [e for e in io.read_jsonl(run_dir / "eval.jsonl") if e["arm"] == arm and e["deterministic"]]
    if not evals:
        raise ConfigError(f"{run_dir} has no deterministic evaluation of arm {arm!r}.")
    _, arms = restore_arms(run_dir)
    found = next(a for a in arms if a.name == arm)
    labels = list(found.plan.labels)
    seeds = sorted({e["seed"] for e in evals})
    best = max(evals, key=lambda e: e["eval/return"])
    run = labels.index(best["hp"]) * len(seeds) + seeds.index(best["seed"])
    policy, norms = jax.device_get(jax.tree.map(lambda x: x[run], (found.state.params["policy"], found.state.norms)))
    expert = Expert(found.plan.config, policy, norms, float(best["eval/return"]))
    save_expert(path, expert)
    return expert

