"""The environment layer: the only place that imports brax.envs or mujoco.

`make_env(config)` returns a `BatchedEnv`: `num_envs` copies of a single-environment Brax `Env`
(physics through MJX, `backend="mjx"`), stepped with `jax.vmap`, with

- time-outs kept apart from terminations (`Step.truncated` vs `Step.terminated`),
- the true observation after the action (`Step.next_obs`), even when the episode ends and the env
  is reset (the policy sees the reset observation in `EnvState.obs`),
- automatic resets, either to each environment's own first start (as Brax's AutoResetWrapper does;
  cheap) or to a fresh random start (one more reset per step),
- optionally staggered starts (`stagger=True`): `reset` puts each environment at its own random point of
  the time limit, so that its first episode is cut short and later episode ends are spread out instead of
  all falling on the same step (`EpisodeStats.create(B, skip=state.t > 0)` keeps those shortened first
  episodes out of the logged returns),
- a guard against non-finite physics: an environment whose state, observation or reward is not
  finite is reset, its transition is marked `valid=False` and its numbers are replaced by zeros,
  so that no NaN reaches a loss or a parameter.

Beside it: `episodes.py` (every setting's running returns, `EpisodeStats`), `render.py` (videos from
MuJoCo's renderer), `resume.py` (which leaves of the state a resumed run needs), `swimmer.py` and
`point.py` (tasks), `playground.py` (MuJoCo Playground's DM Control Suite, `dmc-*`; an optional extra).
Brax prints that its environments are no longer maintained; replacing them means replacing this package, nothing
else.
"""

from __future__ import annotations

import contextlib
import functools
from typing import Any, Callable

import jax
import jax.numpy as jnp
from flax import struct

from cdjax.envs.episodes import EpisodeStats  # noqa: F401  (re-exported: every setting's running returns)
from cdjax.envs import playground

# Action repeats up to this many are unrolled in the step's program (the presets' 1 and 4); more run as one loop, so
# that a large repeat does not grow the program (at 1000 unrolled point-mass steps the compile ran out of 24 GB).
UNROLLED_REPEATS = 8

# Brax tasks that run on MJX (brax's own swimmer has no mjx backend: see cdjax/envs/swimmer.py).
BRAX_MJX_ENVS = (
    "ant", "halfcheetah", "hopper", "humanoid", "humanoidstandup", "inverted_pendulum",
    "inverted_double_pendulum", "pusher", "reacher", "walker2d",
)


def _quiet_import(module: str):
    """Import a module whose import prints to stdout (mujoco.mjx announces its optional warp backend)."""
    import importlib
    import io

    with contextlib.redirect_stdout(io.StringIO()):
        return importlib.import_module(module)


def _brax_env(name: str, **kwargs):
    brax_envs = _quiet_import("brax.envs")
    return brax_envs.get_environment(name, backend="mjx", **kwargs)


def _point(**kwargs):
    from cdjax.envs.point import PointMass  # here, not at the top: its Brax base class must not load with cdjax.envs

    return PointMass(**kwargs)


def _swimmer(**kwargs):
    return _quiet_import("cdjax.envs.swimmer").Swimmer(**kwargs)


def _registry() -> dict[str, Callable[..., Any]]:
    table: dict[str, Callable[..., Any]] = {name: functools.partial(_brax_env, name) for name in BRAX_MJX_ENVS}
    table["point"] = _point  # tiny deterministic pure-JAX system for plumbing tests
    table["swimmer"] = _swimmer  # an MJX swimmer (cdjax/envs/swimmer.py)
    # MuJoCo Playground's DM Control Suite (cdjax/envs/playground.py; the `playground` extra)
    table.update({name: functools.partial(playground.PlaygroundEnv, name) for name in playground.NAMES})
    return table


def available_envs() -> tuple[str, ...]:
    return tuple(_registry())


def describe() -> dict[str, str]:
    """Every name of available_envs() -> where the task comes from, in words; whether the Mb-Mf phase's MPC can
    score with its true reward (cdjax.envs.rewards); for the dmc-* tasks, whether their extra is missing."""
    from cdjax.envs import rewards  # here: the listing is the only user of rewards in this module

    try:
        playground.check("auto")
        missing = ""
    except playground.ConfigError:
        missing = '; needs the playground extra: pip install -e ".[playground]"'
    about = {name: "Brax, MJX" for name in BRAX_MJX_ENVS}
    about |= {"point": "cdjax.envs.point", "swimmer": "cdjax.envs.swimmer"}
    about |= {name: f"MuJoCo Playground {task}{missing}" for name, task in playground.NAMES.items()}
    return {name: about[name] + ("; true reward for MPC" if rewards.reward_fn(name) else "")
            for name in available_envs()}


@contextlib.contextmanager
def _models_on_this_process():
    """MJX puts a model on `jax.devices()[0]` unless given a device. With several processes (`--distributed`) that
    is process 0's first device: the other processes hold no data of it, and every program that closes over the
    model fails to compile there ("Closing over jax.Array that spans non-addressable devices"). While an environment
    is built here, a model put without a device goes on this process's own first device (the same device in one
    process)."""
    if jax.process_count() == 1:
        yield
        return
    mjx = _quiet_import("mujoco.mjx")
    put_model, device = mjx.put_model, jax.local_devices()[0]

    def put_model_here(m, *args, **kwargs):  # put_model(m, device=None, impl=None, ...)
        if not args and kwargs.get("device") is None:
            kwargs["device"] = device
        return put_model(m, *args, **kwargs)

    mjx.put_model = put_model_here
    try:
        yield
    finally:
        mjx.put_model = put_model


def make_single_env(name: str, **kwargs):
    """One (unbatched) Brax-style environment with reset(key) -> State and step(State, a) -> State."""
    table = _registry()
    if name not in table:
        raise KeyError(f"unknown env {name!r}")
    with _models_on_this_process():
        return table[name](**kwargs)


@struct.dataclass
class EnvState:
    """Batched state of `BatchedEnv`; every leaf has a leading [B] axis except `key`."""

    core: Any  # the wrapped env's State, batched [B]
    first: Any  # each env's first start, the target of a "cached" reset, batched [B]
    obs: jax.Array  # [B, obs] observation the policy acts on (after any reset)
    t: jax.Array  # [B] int32 physics steps into the current episode (agent steps x action_repeat)
    key: jax.Array  # PRNG key for fresh resets


@struct.dataclass
class Step:
    """What one batched step returns besides the new state. Leaves are [B] or [B, obs]."""

    next_obs: jax.Array  # observation right after the action, before any reset (zeros if invalid)
    reward: jax.Array  # float32 reward (zero if invalid)
    terminated: jax.Array  # bool: the task ended (no bootstrapping)
    truncated: jax.Array  # bool: time-out, not a termination (bootstrap from next_obs)
    valid: jax.Array  # bool: False when the physics went non-finite; the transition must be masked


def strong_types(tree):
    """Drop weak types (Brax returns weak-typed reward/done), so that a jitted carry compiles once."""

    def cast(x):
        if not hasattr(x, "dtype") or jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key):
            return x
        return jnp.asarray(x, dtype=x.dtype)

    return jax.tree.map(cast, tree)


def _where(mask, a, b):
    """Per-env select over pytrees with a leading [B] axis."""

    def pick(x, y):
        m = mask.reshape(mask.shape + (1,) * (x.ndim - 1))
        return jnp.where(m, x, y)

    return jax.tree.map(pick, a, b)


def _all_finite(tree, batch: int) -> jax.Array:
    ok = jnp.ones((batch,), bool)
    for leaf in jax.tree.leaves(tree):
        if hasattr(leaf, "dtype") and jnp.issubdtype(leaf.dtype, jnp.floating):
            ok &= jnp.isfinite(leaf.reshape(batch, -1)).all(axis=-1)
    return ok


_PHYSICS: dict[int, tuple[Any, Callable, Callable, Callable]] = {}


def _single_physics(env) -> tuple[Callable, Callable, Callable]:
    """env's reset and step, each one `jax.jit` function of ONE environment per env object in this process, and their
    batched forms (`physics`). JAX keeps a jitted function's trace per input shapes, and vmap batches that trace (its
    operations) without running the env's Python again: so an MJX reset or step (thousands of operations, a second or
    more of Python to trace) is traced once per process for every batch size that calls it (the training envs, the
    evaluation envs, the runs' vmap), and the trace that learns the observation size is the one they all reuse. XLA
    inlines the calls, so the compiled programs compute the same numbers."""
    if id(env) not in _PHYSICS:  # the env is held in the entry, so its id stays its own while the entry lives
        reset_one, step_one = jax.jit(env.reset), jax.jit(env.step)
        _PHYSICS[id(env)] = (env, reset_one,
                             jax.jit(lambda keys: strong_types(jax.vmap(reset_one)(keys))),
                             jax.jit(lambda core, action: strong_types(jax.vmap(step_one)(core, action))))
    return _PHYSICS[id(env)][1:]


def physics(env) -> tuple[Callable, Callable]:
    """env's batched reset (keys [B] -> State [B]) and step ((State [B], actions [B, act]) -> State [B]), each one
    `jax.jit` function per env object in this process (strong-typed). Every program that calls them, in any arm,
    chunk or evaluation, then traces the env's physics once (`_single_physics`), where a plain call is traced anew in
    every program (an MJX step is thousands of operations). XLA inlines the calls, so the compiled programs are the
    same."""
    return _single_physics(env)[1:]


class BatchedEnv:
    """`num_envs` auto-resetting copies of a single env. Not a pytree: close over it."""

    def __init__(self, env, num_envs: int, episode_length: int, action_repeat: int = 1,
                 reset_mode: str = "cached", stagger: bool = False, observation_size: int | None = None):
        self.env = env
        self.num_envs = num_envs
        self.episode_length = episode_length
        self.action_repeat = action_repeat
        self.reset_mode = reset_mode
        self.stagger = stagger  # reset() starts each env at its own random point of the time limit
        self.observation_size = observation_size if observation_size is not None else traced_observation_size(env)
        self.action_size = int(env.action_size)
        self._reset_many, self._step_many = physics(env)

    def max_timeouts(self, steps: int) -> int:
        """The most time-outs one env can have in `steps` agent steps: each needs a whole episode of agent
        steps since the env's last reset, the first of them possibly begun before."""
        agent_steps = -(-self.episode_length // self.action_repeat)
        return -(-steps // max(agent_steps, 1))

    def _reset_core(self, key):
        return self._reset_many(jax.random.split(key, self.num_envs))

    def reset(self, key: jax.Array) -> EnvState:
        """Every env at the start of an episode; with `stagger`, env i's clock starts at a uniform random agent
        step of the time limit (t counts physics steps), so its first episode is shorter than the others."""
        key_reset, key_next = jax.random.split(key)
        core = self._reset_core(key_reset)
        t = jnp.zeros((self.num_envs,), jnp.int32)
        if self.stagger:  # an extra split only here: unstaggered envs draw exactly what they always drew
            key_next, key_t = jax.random.split(key_next)
            agent_steps = max(-(-self.episode_length // self.action_repeat), 1)
            t = jax.random.randint(key_t, (self.num_envs,), 0, agent_steps).astype(jnp.int32) * self.action_repeat
        return EnvState(core=core, first=core, obs=core.obs.astype(jnp.float32), t=t, key=key_next)

    def restart_obs(self, state: EnvState) -> jax.Array | None:
        """[B, obs] observation that an env whose episode ends restarts from, where it is fixed in
        advance (cached resets: its own first start); None for fresh resets."""
        return state.first.obs.astype(jnp.float32) if self.reset_mode == "cached" else None

    def step(self, state: EnvState, action: jax.Array) -> tuple[EnvState, Step]:
        """action: [B, act] in [-1, 1]."""
        assert action.shape == (self.num_envs, self.action_size), action.shape
        B = self.num_envs
        core = state.core
        reward = jnp.zeros((B,), jnp.float32)
        done = jnp.zeros((B,), bool)

        def repeat(_, carry):
            core, reward, done = carry
            core = self._step_many(core, action)
            return core, reward + jnp.where(done, 0.0, core.reward.astype(jnp.float32)), done | (core.done > 0.5)

        if self.action_repeat <= UNROLLED_REPEATS:  # unrolled: the presets' few repeats, no loop around the physics
            for i in range(self.action_repeat):
                core, reward, done = repeat(i, (core, reward, done))
        else:  # one loop, so that the program does not grow with the repeats
            core, reward, done = jax.lax.fori_loop(0, self.action_repeat, repeat, (core, reward, done))
        next_obs = core.obs.astype(jnp.float32)
        physics = getattr(core, "pipeline_state", None)
        physics_q = (getattr(physics, "q", None), getattr(physics, "qd", None)) if physics is not None else ()
        valid = _all_finite((next_obs, reward, physics_q), B)
        t = state.t + self.action_repeat  # physics steps, as Brax's EpisodeWrapper counts them
        terminated = done & valid
        truncated = (t >= self.episode_length) & ~terminated & valid
        ended = terminated | truncated | ~valid

        key, key_reset = jax.random.split(state.key)
        if self.reset_mode == "fresh":
            restart = self._reset_core(key_reset)
        else:
            restart = state.first  # what restart_obs tells closed_loop
        new_core = _where(ended, restart, core)
        new_state = EnvState(
            core=new_core,
            first=state.first,
            obs=new_core.obs.astype(jnp.float32),
            t=jnp.where(ended, 0, t).astype(jnp.int32),
            key=key,
        )
        step = Step(
            next_obs=jnp.where(valid[:, None], next_obs, 0.0),
            reward=jnp.where(valid, reward, 0.0),
            terminated=terminated,
            truncated=truncated,
            valid=valid,
        )
        return new_state, step


def traced_observation_size(env) -> int:
    """The size of env's observation, from the shapes of its reset (`jax.eval_shape`: traced, nothing computed; Brax's
    observation_size property runs reset op by op, ~30 s for an MJX env on a CPU). The trace is the process's one
    trace of env's reset (`_single_physics`), which every batched reset of env then batches instead of tracing the
    env's Python again: learning the size costs no trace that a sweep would not make anyway."""
    reset_one = _single_physics(env)[0]
    return int(jax.eval_shape(reset_one, jax.random.key(0)).obs.shape[-1])


_OBSERVATION_SIZES: dict[str, int] = {}


def observation_size(name: str, env) -> int:
    """The observation size of `env`, made by make_single_env(name), traced once per name in this process: the arms
    of a sweep and their phases and evaluations all act in the same kind of env."""
    if name not in _OBSERVATION_SIZES:
        _OBSERVATION_SIZES[name] = traced_observation_size(env)
    return _OBSERVATION_SIZES[name]


_SHARED_ENVS: dict[str, Any] = {}


def shared_env(name: str, physics_backend: str = "auto"):
    """make_single_env(name), made once per name (and, for a Playground task, physics backend: `playground.BACKENDS`)
    in this process: the arms of a sweep, their phases and evaluations act in one env object, so they share its
    jitted physics (`physics`). The process keeps the object and its traced physics: after changing an env's code in
    a running notebook, restart it (or clear `_SHARED_ENVS`)."""
    kwargs = {"backend": physics_backend} if playground.is_playground(name) else {}
    key = f"{name}@{physics_backend}" if kwargs else name
    if key not in _SHARED_ENVS:
        _SHARED_ENVS[key] = make_single_env(name, **kwargs)
    return _SHARED_ENVS[key]


def batched(name: str, num_envs: int, episode_length: int, action_repeat: int = 1, reset_mode: str = "cached",
            stagger: bool = False, physics_backend: str = "auto") -> BatchedEnv:
    """`num_envs` auto-resetting copies of make_single_env(name) (BatchedEnv; the observation size traced once
    per name in this process)."""
    env = shared_env(name, physics_backend)
    return BatchedEnv(env, num_envs, episode_length, action_repeat, reset_mode, stagger,
                      observation_size(name, env))


def make_env(config) -> BatchedEnv:
    """The batched, auto-resetting environment that `config` describes."""
    return batched(config.env, config.num_envs, config.episode_length, config.action_repeat, config.reset_mode,
                   stagger=getattr(config, "stagger_resets", False),
                   physics_backend=getattr(config, "physics_backend", "auto"))
