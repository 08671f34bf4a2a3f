"""Policy evaluation on fresh episodes, for any setting's `cdjax.protocol.Trainer`, and its records.

`evaluate` is pure (jit/vmap it yourself, or use `make_evaluator`): it runs `episodes` environments of
`trainer.eval_env` side by side, each for exactly one episode, acting with `trainer.act`, and returns
per-episode undiscounted and discounted returns (discount: hp.gamma where the HParams have one) and
lengths. `render_video` writes one episode as a video (cdjax.envs.render); when that is not possible it
says why in one sentence and returns None.

    evaluator = make_evaluator(trainer, episodes=10, deterministic=True)
    results = evaluator(trainer.policy(state), keys, hps)      # every input with a leading run axis [R]
    io.append_jsonl(run_dir / "eval.jsonl", eval_records(results, arm="cd", hp_labels=labels,
                                                         seeds=range(num_seeds), deterministic=True))
"""

from __future__ import annotations

import functools
import hashlib
import os
import pathlib
import threading
import time
from typing import Any, Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from cdjax import budget
from cdjax.io import json_float
from cdjax.io.timings import Timings
from cdjax.protocol import Trainer


# Agent steps of one evaluation episode past which a sweep does not evaluate (cdjax.runner.arms.check_evaluation): the
# loop steps every episode's environments one step after another until each has ended, so an episode's time-out is
# the evaluation's length on any device. The presets' episodes are 1,000 agent steps (pixel reacher's 250, ALE's
# time-out 27,000); this is 1,000 times theirs.
MAX_EVAL_EPISODE_STEPS = 1_000_000


def episode_steps(env) -> int:
    """Agent steps of an episode of `env` that times out: its `episode_length` counts physics steps (agent steps x
    action_repeat, as Brax)."""
    return -(-env.episode_length // getattr(env, "action_repeat", 1))


@struct.dataclass
class _EvalCarry:
    env_state: Any  # the eval env's state
    t: jax.Array  # [] int32 agent steps taken
    ret: jax.Array  # [E] undiscounted return, frozen once the episode ended
    disc_ret: jax.Array  # [E] discounted return, frozen once the episode ended
    disc: jax.Array  # [E] gamma^t of the next reward
    length: jax.Array  # [E] int32 agent steps inside the episode
    done: jax.Array  # [E] bool: the episode ended (termination, time-out or non-finite physics)
    terminated: jax.Array  # [E] bool: it ended by a task termination
    invalid: jax.Array  # [E] bool: it ended because the physics went non-finite
    key: jax.Array


def evaluate(trainer: Trainer, policy: Any, key: jax.Array, *, episodes: int, hp: Any, deterministic: bool,
             max_steps: int | None = None) -> dict[str, jax.Array]:
    """One episode in each of `episodes` fresh environments, acting with `trainer.act(policy, ...)`.

    deterministic=True acts with `trainer.act(policy, obs, None)` (e.g. tanh(mean)); otherwise with a
    sampled action. The loop stops when every environment has ended its first episode (termination,
    the env's time-out `episode_length`, or non-finite physics) or after `max_steps` agent steps
    (episodes still running then are cut: `finished` is False). Rewards after an episode's end are ignored.

    Returns arrays [E]: "return", "discounted_return" (discount hp.gamma, the first reward undiscounted),
    "length" (int32), "terminated", "finished", "valid" (bool), "initial_obs" [E, O]; and scalars
    "return_mean", "discounted_return_mean", "length_mean".
    """
    env = trainer.eval_env(episodes)
    agent_steps = episode_steps(env)  # the loop counts agent steps
    horizon = agent_steps if max_steps is None else min(int(max_steps), agent_steps)
    gamma = jnp.asarray(getattr(hp, "gamma", 1.0), jnp.float32)
    key_reset, key_act = jax.random.split(key)
    del key
    env_state = env.reset(key_reset)
    zeros = jnp.zeros((episodes,), jnp.float32)
    false = jnp.zeros((episodes,), bool)
    carry = _EvalCarry(env_state=env_state, t=jnp.zeros((), jnp.int32), ret=zeros, disc_ret=zeros,
                       disc=jnp.ones((episodes,), jnp.float32), length=jnp.zeros((episodes,), jnp.int32),
                       done=false, terminated=false, invalid=false, key=key_act)

    def running(c: _EvalCarry) -> jax.Array:
        return (c.t < horizon) & ~c.done.all()

    def step(c: _EvalCarry) -> _EvalCarry:
        key, key_step = jax.random.split(c.key)
        action = trainer.act(policy, c.env_state.obs, None if deterministic else key_step)
        env_state, out = env.step(c.env_state, action)
        live = ~c.done
        reward = jnp.where(live, out.reward, 0.0)
        ended = out.terminated | out.truncated | ~out.valid
        return _EvalCarry(
            env_state=env_state,
            t=c.t + 1,
            ret=c.ret + reward,
            disc_ret=c.disc_ret + c.disc * reward,
            disc=jnp.where(live, c.disc * gamma, c.disc),
            length=c.length + live.astype(jnp.int32),
            done=c.done | ended,
            terminated=c.terminated | (live & out.terminated),
            invalid=c.invalid | (live & ~out.valid),
            key=key,
        )

    final = jax.lax.while_loop(running, step, carry)
    return {
        "return": final.ret,
        "discounted_return": final.disc_ret,
        "length": final.length,
        "terminated": final.terminated,
        "finished": final.done,
        "valid": ~final.invalid,
        "initial_obs": env_state.obs,
        "return_mean": final.ret.mean(),
        "discounted_return_mean": final.disc_ret.mean(),
        "length_mean": final.length.astype(jnp.float32).mean(),
    }


def make_evaluator(trainer: Trainer, episodes: int, deterministic: bool, max_steps: int | None = None,
                   timings: Timings | None = None, arm: str = "all") -> "Evaluator":
    """jit(vmap(evaluate)) over runs: fn(policy [R], keys [R], hps [R]) -> results [R, ...] (an `Evaluator`).

    Feed it `trainer.policy(state)` of a sweep's state and the stacked HParams of the same runs. Compiled as cdjax
    compiles its other programs, once per kind of input (`cdjax.budget.compile_fitting`): with the compile
    mode in force when it was made (so `--compile-mode deterministic` reaches the evaluations too) and the GPU's
    data-flow scheduling, in program order where that would not fit in the device's free memory. Evaluators whose
    programs lower to the same module (two arms whose policies differ only in values) share one compiled program in
    this process. Called inside a trace (under your own jit), it is the plain jit(vmap(evaluate)). `timings`: where
    the trace, lowering and compilation of each of its programs are timed (rows of `arm`, what "evaluator";
    cdjax.io.timings).
    """
    from cdjax import runtime

    def one(policy, key, hp):
        return evaluate(trainer, policy, key, episodes=episodes, hp=hp, deterministic=deterministic,
                        max_steps=max_steps)

    return Evaluator(jax.jit(jax.vmap(one)), runtime.compile_mode(), timings, arm)


# This process's compiled evaluation programs, by what XLA compiles: (a digest of the lowered module, the compile
# mode). Arms whose policies differ only in values lower to the same module and so share one program; an arm whose
# policy network, environment, episodes or run count differs lowers to another module and compiles its own.
_PROGRAMS: dict[tuple[str, str], Any] = {}
_COMPILING = threading.Lock()  # one evaluator program compiled at a time (a sweep's background thread, a caller)


class Evaluator:
    """A jitted evaluation program and its compiled forms, one per kind of input (`make_evaluator`)."""

    def __init__(self, program: Callable, mode: str, timings: Timings | None, arm: str):
        self.program = program  # jit(vmap(evaluate))
        self.mode = mode  # the compile mode of its programs (cdjax.runtime)
        self.timings = timings
        self.arm = arm
        self._compiled: dict = {}  # budget.signature of the inputs -> compiled program
        self.compiles = 0  # programs this evaluator compiled itself (not taken from another's)

    def __call__(self, policy, keys, hps) -> dict[str, jax.Array]:
        args = (policy, keys, hps)
        if any(_is_tracer(x) for x in jax.tree.leaves(args)):
            return self.program(*args)
        return self.compiled(args)(*args)

    def compiled(self, args: tuple, room: int | None = None):
        """The compiled program for inputs like `args` ((policy, keys, hps): arrays or ShapeDtypeStructs with their
        shardings), traced, lowered and compiled now if this evaluator has none yet; taken from this process's
        programs when another evaluator lowered the same module. `room`: the bytes it may take (as
        budget.compile_fitting; default: what is free on the device now)."""
        key = budget.signature(args)
        if key in self._compiled:
            return self._compiled[key]
        with _COMPILING:
            if key not in self._compiled:
                t0 = time.perf_counter()
                traced = self.program.trace(*args)
                t1 = time.perf_counter()
                lowered = traced.lower()
                digest = hashlib.sha256(lowered.as_text().encode()).hexdigest()
                t2 = time.perf_counter()
                self._timed("trace", t0, t1)
                self._timed("lower", t1, t2)
                shared = (digest, self.mode)
                if shared not in _PROGRAMS:
                    _PROGRAMS[shared] = budget.compile_fitting(lowered, room=room, mode=self.mode)[0]
                    self.compiles += 1
                    self._timed("compile", t2, time.perf_counter())
                self._compiled[key] = _PROGRAMS[shared]
        return self._compiled[key]

    def _timed(self, step: str, t0: float, end: float) -> None:
        if self.timings is not None:
            self.timings.add(self.arm, "evaluator", step, t0, end)


def _is_tracer(x) -> bool:
    """Whether x is a JAX tracer (an abstract value while a function is traced), not an array."""
    return isinstance(x, _tracer_type())


@functools.cache
def _tracer_type() -> type:
    """JAX's Tracer class, looked up once."""
    try:
        from jax.core import Tracer
    except ImportError:  # a JAX that no longer exports it there
        from jax._src.core import Tracer
    return Tracer


# ---------------------------------------------------------------------------------------------------
# eval.jsonl


def eval_records(results: dict, *, arm: str, hp_labels: Sequence[str], seeds: Sequence[int],
                 deterministic: bool, **extra) -> list[dict]:
    """One JSON-ready record per run of a `make_evaluator` result (leaves [R, E], runs hp-major).

    Run r = i * len(seeds) + s belongs to hp_labels[i] and seeds[s]; runs past len(hp_labels) *
    len(seeds) (device padding) are dropped. `extra` (e.g. update=..., env_steps=...) is copied into
    every record. Keys: arm, hp, seed, deterministic, episodes, eval/return, eval/discounted_return,
    eval/length (means over episodes), eval/terminated_fraction, and the per-episode lists
    returns, discounted_returns, lengths.
    """
    host = {name: np.asarray(value) for name, value in results.items()}
    seeds = list(seeds)
    records = []
    for i, label in enumerate(hp_labels):
        for s, seed in enumerate(seeds):
            r = i * len(seeds) + s
            ret, disc, length = host["return"][r], host["discounted_return"][r], host["length"][r]
            records.append({
                "arm": arm, "hp": label, "seed": int(seed), **extra,
                "deterministic": bool(deterministic), "episodes": int(ret.shape[0]),
                "eval/return": json_float(ret.mean()),
                "eval/discounted_return": json_float(disc.mean()),
                "eval/length": float(length.mean()),
                "eval/terminated_fraction": float(host["terminated"][r].mean()),
                "returns": [json_float(x) for x in ret],
                "discounted_returns": [json_float(x) for x in disc],
                "lengths": [int(x) for x in length],
            })
    return records


def render_video(trainer: Trainer, policy: Any, key: jax.Array, path: str | os.PathLike, *, steps: int,
                 deterministic: bool = True, width: int = 320, height: int = 240) -> pathlib.Path | None:
    """One episode (at most `steps` agent steps) of one eval environment as a video (cdjax.envs.render).

    Returns the written path, or None after printing one sentence saying why there is none (an env
    without a MuJoCo model, no OpenGL context: start Python with MUJOCO_GL=egl or osmesa).
    """
    from cdjax.envs.render import render_episode

    act = lambda obs, key: trainer.act(policy, obs, key)  # noqa: E731
    return render_episode(trainer.eval_env(1), act, key, pathlib.Path(path), steps=steps,
                          deterministic=deterministic, width=width, height=height)
