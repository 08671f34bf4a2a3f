"""MuJoCo Playground's DM Control Suite tasks as cdjax environments (the optional `playground` extra).

Names: `dmc-` and the Playground task's name in lower case with hyphens between its words, e.g. `CheetahRun` is
`dmc-cheetah-run`, `BallInCup` is `dmc-ball-in-cup`, `SwimmerSwimmer6` is `dmc-swimmer-swimmer6` (`TASKS` lists
the 25 of Playground 0.2.0; the tests check that list against Playground's own).

`PlaygroundEnv` calls the raw task's `reset` and `step` (never Playground's training wrappers, whose auto-reset
drops the observation at an episode's end): cdjax's `BatchedEnv` batches it and resets it, keeping the true final
observation, staggering starts and masking non-finite states as for every other task. The DM Control tasks end an
episode only at their time limit (`Config.episode_length`, Playground's is 1000 control steps) or when the physics
turns NaN (`done`), which BatchedEnv treats as a non-finite state: masked and reset, not a termination.

Observations: every DM Control task's is a flat array; a dict observation (Playground's vision variants, which
cdjax does not load) is flattened, its entries in sorted key order, each raveled.

Physics backend (`Config.physics_backend`): "jax" is MJX's JAX implementation, "warp" MuJoCo Warp (Playground's own
default, which needs the `mujoco_warp` package and an NVIDIA GPU), "auto" picks Warp where both are there and JAX
elsewhere. `resolve_backend` says which one a run gets.
"""

from __future__ import annotations

import importlib.util
import re
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
from flax import struct

from cdjax.protocol import ConfigError

MISSING = 'MuJoCo Playground is not installed; install cdjax\'s extra with pip install -e ".[playground]".'
BACKENDS = ("auto", "jax", "warp")

# Playground 0.2.0's mujoco_playground.dm_control_suite.ALL_ENVS, so that the names list without importing it.
TASKS = (
    "AcrobotSwingup", "AcrobotSwingupSparse", "BallInCup", "CartpoleBalance", "CartpoleBalanceSparse",
    "CartpoleSwingup", "CartpoleSwingupSparse", "CheetahRun", "FingerSpin", "FingerTurnEasy", "FingerTurnHard",
    "FishSwim", "HopperHop", "HopperStand", "HumanoidStand", "HumanoidWalk", "HumanoidRun", "PendulumSwingup",
    "PointMass", "ReacherEasy", "ReacherHard", "SwimmerSwimmer6", "WalkerRun", "WalkerStand", "WalkerWalk",
)


def cdjax_name(task: str) -> str:
    """CheetahRun -> dmc-cheetah-run (a capital starts a word; digits stay with theirs)."""
    return "dmc-" + "-".join(word.lower() for word in re.findall(r"[A-Z][a-z0-9]*", task))


NAMES: dict[str, str] = {cdjax_name(task): task for task in TASKS}  # cdjax name -> Playground task


def is_playground(name: str) -> bool:
    return name in NAMES


def _import_suite():
    try:
        from mujoco_playground import dm_control_suite
    except ImportError:
        raise ConfigError(MISSING) from None
    return dm_control_suite


def check(backend: str) -> None:
    """Raise ConfigError (one sentence) where a Playground task cannot run with `backend`; imports nothing heavy."""
    try:
        found = importlib.util.find_spec("mujoco_playground") is not None
    except ValueError:  # a module set to None in sys.modules (how the tests hide the extra)
        found = False
    if not found:
        raise ConfigError(MISSING)
    resolve_backend(backend)


def warp_available() -> bool:
    """MuJoCo Warp can run here: its package is installed and JAX's default device is an NVIDIA GPU."""
    return importlib.util.find_spec("mujoco_warp") is not None and jax.default_backend() == "gpu"


def resolve_backend(backend: str = "auto") -> str:
    """The physics backend that `backend` (one of BACKENDS) gives on this machine: "jax" or "warp"."""
    if backend not in BACKENDS:
        raise ConfigError(f"Unknown physics backend {backend!r}; choose one of {', '.join(BACKENDS)}.")
    if backend == "auto":
        return "warp" if warp_available() else "jax"
    if backend == "warp" and not warp_available():
        raise ConfigError("physics_backend='warp' needs the mujoco_warp package and an NVIDIA GPU; use 'jax' or "
                         "'auto'.")
    return backend


def backend_record(config) -> dict:
    """{"physics_backend": the backend a run of `config` gets here} for a Playground task, {} for the others (the run
    record's code entry; a resume on another machine adds its own)."""
    if not is_playground(getattr(config, "env", "")):
        return {}
    return {"physics_backend": resolve_backend(getattr(config, "physics_backend", "auto"))}


def flat_obs(obs) -> jax.Array:
    """An observation as one float32 vector: an array raveled, a dict's entries in sorted key order."""
    if isinstance(obs, dict):
        return jnp.concatenate([jnp.ravel(obs[k]).astype(jnp.float32) for k in sorted(obs)])
    return jnp.ravel(obs).astype(jnp.float32)


class Physics(NamedTuple):
    """What BatchedEnv checks for finite numbers besides the observation and reward (as Brax's q and qd)."""

    q: jax.Array
    qd: jax.Array


@struct.dataclass
class PlaygroundState:
    """A Playground State with its observation flattened (`flat_obs`); the fields a Brax State has that BatchedEnv
    reads (obs, reward, done, pipeline_state)."""

    data: Any  # mjx.Data
    obs: jax.Array  # [obs] float32
    reward: jax.Array
    done: jax.Array
    metrics: dict
    info: dict

    @property
    def pipeline_state(self) -> Physics:
        return Physics(self.data.qpos, self.data.qvel)


class PlaygroundEnv:
    """One (unbatched) Playground DM Control task with reset(key) and step(state, action), as a Brax Env."""

    def __init__(self, name: str, backend: str = "auto"):
        if name not in NAMES:
            raise KeyError(f"unknown Playground env {name!r}")
        suite = _import_suite()
        self.name = name
        self.task = NAMES[name]
        self.backend = resolve_backend(backend)
        self.raw = suite.load(self.task, config_overrides={"impl": self.backend})
        self.action_size = int(self.raw.action_size)

    @staticmethod
    def _wrap(s) -> PlaygroundState:
        return PlaygroundState(data=s.data, obs=flat_obs(s.obs), reward=jnp.asarray(s.reward, jnp.float32),
                               done=jnp.asarray(s.done, jnp.float32), metrics=s.metrics, info=s.info)

    def reset(self, key: jax.Array) -> PlaygroundState:
        return self._wrap(self.raw.reset(key))

    def step(self, state: PlaygroundState, action: jax.Array) -> PlaygroundState:
        from mujoco_playground import State  # imported by __init__ already: the extra is there

        # The DM Control tasks' step reads the state's data, metrics and info, never its observation.
        raw = State(data=state.data, obs=state.obs, reward=state.reward, done=state.done, metrics=state.metrics,
                    info=state.info)
        return self._wrap(self.raw.step(raw, action))
