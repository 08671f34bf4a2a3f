"""The real Atari games through ale-py's vector environment and its XLA interface (optional extra `atari`, GPL-2.0).

`AleEnv(config, num_envs, episodic_life)` has the interface of `cdjax.agents.atari.minatar.MinAtarEnv`: `reset(key)`,
`step(state, actions) -> (state, AleStep)`, `episode_length`, `obs_shape`, `num_actions`. Its reset and step are
ale-py's XLA custom calls (the FFI targets behind `AtariVectorEnv.xla()`): they run inside `jit` and `lax.scan`, and
the emulators live in C++ outside JAX, so:

- **Runs are folded into one vector environment.** Under `vmap` over R runs (a sweep's seeds and hyper-parameter
  combinations), the custom calls' batching rule (`jax.custom_batching.custom_vmap`) reshapes the runs' [R, B]
  actions and reset seeds into one axis of R x B and steps one ale-py vector environment of R x B emulators, with
  one thread per core the process may run on (its CPU affinity: `taskset -c 0-15` gives it 16); run r owns
  emulators r*B .. r*B+B-1. Nested vmaps fold again. Each emulator is seeded at reset from its run's key alone,
  so a run steps the same games whether it runs alone or among others (tests/test_atari_ale.py).
- **The emulators are made when a reset first runs**, not when it is traced: the reset's custom call takes its
  vector environment's handle from a host callback that makes (once) the vector environment of that many
  emulators for this `AleEnv`. Tracing for shapes (`jax.eval_shape`) makes none, and no compiled program holds
  a pointer. Each `AleEnv` owns its emulators: two arms, or training and evaluation, never step the same games.
  A state is stepped under the same vmaps that reset it (its handle names the vector environment of that size).
- **One device.** The R x B emulators are stepped by one custom call on one device; a sweep sharded over several
  devices would run the call on each of them. On a host with several GPUs, give the ALE sweep one
  (`CUDA_VISIBLE_DEVICES=0`); several ALE sweeps can share a host, one per GPU. Not with `--distributed` (one process).
- **A checkpoint cannot hold the emulators**: a resumed run starts fresh games (the env state and the running
  episode returns come from init), so an ALE resume continues training but is not bit-identical.

Preprocessing (ale-py's, the standard one of Mnih et al. 2015 / Machado et al. 2018): frame skip `frame_skip`
(4) with max-pooling of the last two frames, 84x84 grey, a stack of 4 frames, up to 30 no-op starts, FIRE at
reset where the game needs it, sticky actions with probability `sticky_prob` (ALE v5's 0.25 in the presets),
the minimal action set, a time-out after `episode_length` agent steps (a truncation). Rewards are the raw
scores (the learner clips them for learning; the reported returns are raw). Episodic life (training only): a
lost life is a termination for learning, while the game goes on and the reported return is the whole game's;
the game's own end is `game_over`.

ale-py resets a finished game on the step after its end (its NEXT_STEP autoreset): that step's transition,
from the last frame to a new game's first, is marked `valid=False` (masked out of every loss, as a non-finite
transition of the MinAtar tier) and the policy then acts on the new game.
"""

from __future__ import annotations

import atexit
import functools
import os
import threading
import weakref

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct
from jax.experimental import io_callback

from cdjax.protocol import ConfigError

GAMES = {"ale-breakout": "breakout", "ale-seaquest": "seaquest", "ale-mspacman": "ms_pacman",
         "ale-frostbite": "frostbite", "ale-pong": "pong", "ale-spaceinvaders": "space_invaders"}
INSTALL = "The ALE games need the optional extra `atari` (ale-py, GPL-2.0): pip install -e \".[atari]\"."
ONE_DEVICE = ("ALE games run on one device (the emulators of all runs are one vector environment on the host): "
              "make one visible, e.g. CUDA_VISIBLE_DEVICES=0.")
ONE_PROCESS = ("ALE games run in one process on one device (the emulators of all runs are one vector environment on "
               "its host): run this sweep without --distributed.")
RESET, STEP = "atari_vector_xla_reset", "atari_vector_xla_step"  # ale-py's FFI targets (ale_py.vector_env)
HANDLE = jax.ShapeDtypeStruct((8,), jnp.uint8)
FRAMES = (4, 84, 84)  # ale-py's observation of one emulator: a stack of 4 grey 84x84 frames
_LIVE: "weakref.WeakSet[AleEnv]" = weakref.WeakSet()  # every AleEnv of this process (their emulators close at exit)


@atexit.register
def _close_all() -> None:
    """Drop every emulator before the interpreter is torn down (ale-py's bindings otherwise report them leaked)."""
    for env in list(_LIVE):
        env._vectors.clear()


@struct.dataclass
class AleState:
    handle: jax.Array  # [8] uint8: the vector env's handle (threads the custom calls' order)
    obs: jax.Array  # [B, 84, 84, 4] uint8: what the policy acts on
    lives: jax.Array  # [B] int32 lives left
    pending_reset: jax.Array  # [B] bool: the game ended on the last step; ale-py resets it on this one
    key: jax.Array


@struct.dataclass
class AleStep:
    """cdjax.envs.Step's fields, plus the game's own end (episodic life ends learning episodes at lost lives)."""

    next_obs: jax.Array  # [B, 84, 84, 4] uint8
    reward: jax.Array  # [B] float32 raw score
    terminated: jax.Array  # [B] bool: game over, or (episodic life) a lost life
    truncated: jax.Array  # [B] bool: time-out
    valid: jax.Array  # [B] bool: False for ale-py's reset step
    game_over: jax.Array  # [B] bool: the game itself ended (terminated or timed out)


@functools.cache
def _register() -> None:
    """ale-py's FFI targets registered with JAX (as `AtariVectorEnv.xla()` does; registering again is harmless)."""
    import ale_py

    lib = ale_py._ale_py
    jax.ffi.register_ffi_target(RESET, lib.VectorXLAReset(), platform="cpu")
    jax.ffi.register_ffi_target(STEP, lib.VectorXLAStep(), platform="cpu")
    if hasattr(lib, "VectorXLAResetGPU"):
        jax.ffi.register_ffi_target(RESET, lib.VectorXLAResetGPU(), platform="CUDA")
        jax.ffi.register_ffi_target(STEP, lib.VectorXLAStepGPU(), platform="CUDA")


@functools.cache
def _num_actions(game: str) -> int:
    """Actions of the game's minimal action set (what the vector env offers)."""
    from ale_py.vector_env import AtariVectorEnv

    return int(AtariVectorEnv(game, 1, num_threads=1).single_action_space.n)


def _folded(fn, shared_input: bool):
    """fn(*args) -> (handle, *per-env outputs [n, ...]), whose per-env inputs have a leading env axis [n], made
    batchable by folding: under vmap over R, the per-env inputs [R, n, ...] become [R * n, ...] of one call and the
    outputs are split back into [R, n, ...]; the handle output is the same for every run. With `shared_input`, the
    first input is a handle (one value for all runs)."""
    wrapped = jax.custom_batching.custom_vmap(fn)

    @wrapped.def_vmap
    def rule(axis_size, in_batched, *args):
        head = ()
        if shared_input:
            handle, batched = args[0], in_batched[0]
            head, args, in_batched = (handle[0] if batched else handle,), args[1:], in_batched[1:]
        flat = [_fold(x, b, axis_size) for x, b in zip(args, in_batched)]
        handle_out, *outs = wrapped(*head, *flat)
        outs = [y.reshape((axis_size, -1) + y.shape[1:]) for y in outs]
        handle_out = jnp.broadcast_to(handle_out, (axis_size,) + handle_out.shape)
        return (handle_out, *outs), (True,) * (1 + len(outs))

    return wrapped


def _fold(x: jax.Array, batched: bool, axis_size: int) -> jax.Array:
    """[R, n, ...] (or an unbatched [n, ...], the same for every run) -> [R * n, ...]."""
    if not batched:
        x = jnp.broadcast_to(x, (axis_size,) + x.shape)
    return x.reshape((-1,) + x.shape[2:])


class AleEnv:
    """`num_envs` games per run of ale-py's vector environment, stepped by XLA custom calls. Not a pytree."""

    def __init__(self, config, num_envs: int, episodic_life: bool = True):
        try:
            from ale_py.vector_env import AtariVectorEnv
        except ImportError:
            raise ConfigError(INSTALL) from None
        if config.env not in GAMES:
            raise ConfigError(f"Unknown ALE game {config.env!r}; choose one of {', '.join(GAMES)}.")
        if jax.process_count() > 1:
            raise ConfigError(ONE_PROCESS)
        if jax.device_count() > 1:
            raise ConfigError(ONE_DEVICE)
        _register()
        self.config, self._vector_type = config, AtariVectorEnv
        self.num_envs, self.episode_length, self.episodic_life = num_envs, config.episode_length, episodic_life
        self.obs_shape = FRAMES[1:] + FRAMES[:1]
        self.num_actions = _num_actions(GAMES[config.env])
        self._vectors: dict[int, object] = {}  # emulators -> this env's ale-py vector env of that many
        self._lock = threading.Lock()
        self._reset = _folded(self._reset_call, shared_input=False)
        self._step = _folded(self._step_call, shared_input=True)
        _LIVE.add(self)

    # --- the emulators and the custom calls

    def vector(self, n: int):
        """This env's ale-py vector env of `n` emulators (made on first use, then kept)."""
        with self._lock:
            if n not in self._vectors:
                self._vectors[n] = vector_env(self._vector_type, self.config, n)
            return self._vectors[n]

    def _handle(self, n: int) -> np.ndarray:
        return np.frombuffer(self.vector(n).ale.handle(), dtype=np.uint8).copy()

    def _reset_call(self, seeds: jax.Array):
        """seeds [n] int32 -> (handle, obs [n, 4, 84, 84] uint8, lives [n] int32): new games in n emulators."""
        n = seeds.shape[0]
        handle = io_callback(functools.partial(self._handle, n), HANDLE, ordered=False)
        per_env = jax.ShapeDtypeStruct((n,), jnp.int32)
        call = jax.ffi.ffi_call(RESET, (HANDLE, jax.ShapeDtypeStruct((n,) + FRAMES, jnp.uint8), per_env, per_env,
                                        per_env, per_env), has_side_effect=True)
        handle, obs, _, lives, _, _ = call(handle, jnp.arange(n, dtype=jnp.int32), seeds)
        return handle, obs, lives

    def _step_call(self, handle: jax.Array, actions: jax.Array):
        """(handle, actions [n] int32) -> (handle, obs [n, 4, 84, 84], reward [n] int32, terminated, truncated [n]
        bool, lives [n] int32): one agent step of the n emulators the handle names."""
        n = actions.shape[0]
        per_env, flag = jax.ShapeDtypeStruct((n,), jnp.int32), jax.ShapeDtypeStruct((n,), jnp.bool_)
        call = jax.ffi.ffi_call(STEP, (HANDLE, jax.ShapeDtypeStruct((n,) + FRAMES, jnp.uint8), per_env, flag, flag,
                                       per_env, per_env, per_env, per_env), has_side_effect=True)
        handle, obs, reward, term, trunc, _, lives, _, _ = call(handle, actions, jnp.ones((n,), jnp.float32))
        return handle, obs, reward, term, trunc, lives

    # --- the env interface

    @staticmethod
    def _frames(obs: jax.Array) -> jax.Array:
        return jnp.moveaxis(obs, 1, -1)  # ale-py's [B, 4, 84, 84] -> [B, 84, 84, 4]

    def reset(self, key: jax.Array) -> AleState:
        """New games, seeded from `key` (the same key gives the same games)."""
        key_seeds, key_next = jax.random.split(key)
        seeds = jax.random.randint(key_seeds, (self.num_envs,), 0, 2**31 - 1, jnp.int32)
        handle, obs, lives = self._reset(seeds)
        return AleState(handle=handle, obs=self._frames(obs), lives=lives.astype(jnp.int32),
                        pending_reset=jnp.zeros((self.num_envs,), bool), key=key_next)

    def step(self, state: AleState, action: jax.Array) -> tuple[AleState, AleStep]:
        assert action.shape == (self.num_envs,), action.shape
        handle, obs, reward, term, trunc, lives = self._step(state.handle, action.astype(jnp.int32))
        obs, lives = self._frames(obs), lives.astype(jnp.int32)
        valid = ~state.pending_reset
        game_end = term & valid
        truncated = trunc & valid & ~game_end
        life_lost = valid & (lives < state.lives) & ~game_end
        terminated = game_end | (life_lost if self.episodic_life else False)
        out = AleStep(next_obs=obs, reward=jnp.where(valid, reward.astype(jnp.float32), 0.0), terminated=terminated,
                      truncated=truncated & ~terminated, valid=valid, game_over=game_end | truncated)
        return AleState(handle=handle, obs=obs, lives=lives, pending_reset=(term | trunc) & valid,
                        key=state.key), out


def usable_cores() -> int:
    """The cores this process may run on (its CPU affinity: all of the host's, or those `taskset` gave it)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def vector_env(vector_type, config, num_envs: int, num_threads: int = 0):
    """ale-py's vector env (`vector_type`: ale_py.vector_env.AtariVectorEnv) with this module's preprocessing and
    `num_threads` threads (0: one per core this process may run on, at most one per emulator); its own Python-side
    reset(seed=...) and step(actions) step the same games as `AleEnv` does inside XLA. ale-py's own 0 would be one
    thread per core of the host (std::thread::hardware_concurrency ignores the affinity), so a sweep given 16 of 64
    cores by `taskset` would crowd 48 threads onto them."""
    num_threads = num_threads or min(num_envs, usable_cores())
    return vector_type(
        GAMES[config.env], num_envs, frameskip=config.frame_skip, maxpool=True, stack_num=4, img_height=84,
        img_width=84, grayscale=True, noop_max=30, use_fire_reset=True, episodic_life=False, reward_clipping=False,
        repeat_action_probability=config.sticky_prob, max_num_frames_per_episode=config.episode_length * config.frame_skip,
        num_threads=num_threads)
