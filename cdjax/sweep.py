"""Seed and hyper-parameter sweeps: many runs of one Config in one compiled program.

A sweep has R runs (e.g. seeds x an alpha grid). Each run has its own PRNG key and its own HParams;
`jax.vmap` batches them and `jax.sharding` splits the run axis over all local devices (a 1-D `Mesh`
named "runs"): each device trains R / num_devices runs. How the update programs are split (`split`):
  "partition"  XLA's partitioner places the vmapped program (the default). For the point-mass trainer the compiled
               chunk holds no collective (tests/test_sweep.py), but it all-gathers the pixel model's vmapped
               convolutions (grouped convolutions with per-run weights): 102 all-gathers, and slower on 4 GPUs
               than on one;
  "local"      the update programs (run, chunk) are a `jax.shard_map` over the run axis: each device runs the vmap
               of its own runs, with no collective (tests/_sharded_pixel_sweep.py). Init and the phase stay
               partitioned: XLA:GPU (jax 0.11.2) crashed compiling the MJX trainers' init under shard_map.
A trainer asks for "local" with `runs_split` (cdjax.protocol.Trainer; the pixel setting does). The state is laid
out alike either way (the run axis over the mesh), so checkpoints move between the two and between device counts.

    sweep = make_sweep(make_trainer(config))        # any trainer with init(key, hp) and update(state, hp)
    keys, hps = sweep.grid(seed=0, num_seeds=8, hps=[HParams(alpha=0.0), HParams(alpha=1.0)])
    state = sweep.init(keys, hps)                       # leaves [R, ...], sharded over devices
    state, metrics = sweep.run(state, hps, 10)          # 10 updates; metrics leaves [R, 10]

Several processes (hosts, or one per GPU: `cdjax sweep --distributed`, cdjax.multihost): once every process has
joined (`cdjax.multihost.initialize`, before anything else runs in JAX), `jax.devices()` lists every process's
devices and the default mesh spans them all; `grid` gives every process the same global keys and HParams, each
process computing the runs on its own devices, and R is padded to a multiple of the global device count. Every
process must then call the same programs in the same order; `cdjax.multihost.fetch` brings results back whole.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any, Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from cdjax import multihost

AXIS = "runs"
State = Any  # the trainer's state pytree
HP = Any  # the trainer's HParams


def runs_mesh(devices: Sequence[jax.Device] | None = None) -> Mesh:
    """A 1-D mesh over `devices` (default: all devices) whose one axis carries the runs."""
    return Mesh(np.asarray(devices if devices is not None else jax.devices()), (AXIS,))


def stack(hps: Sequence[HP]) -> HP:
    """HParams (any flax.struct dataclass of floats) stacked into one with float32 leaves [len(hps)]."""
    return jax.tree.map(lambda *values: jnp.asarray(values, jnp.float32), *hps)


@dataclasses.dataclass(frozen=True)
class Sweep:
    trainer: Any  # what it was built from: init(key, hp) and update(state, hp)
    mesh: Mesh
    init: Callable[[jax.Array, HP], State]  # (keys [R], hps [R]) -> state [R]
    _run: Callable  # jitted (state, hps, num_updates) -> (state, metrics [R, n])
    _phase: Callable | None = None  # jitted (state, hps) -> (state, info [R]): the pre-update phase of every run
    _chunk: Callable | None = None  # jitted (state, hps, length, n) -> (state, metrics [R, length]): n <= length run
    split: str = "partition"  # how the update programs split the runs over the devices (make_sweep)
    # With a trainer that offers reset/init_from (cdjax.protocol.Trainer), init(keys, hps) is
    # init_from(keys, hps, reset(keys)): `reset` (keys [R]) -> the runs' environments, one jitted function shared
    # by every sweep of an equal env_key on the same mesh (so its program is compiled once); `init_from` (keys,
    # hps, environments) -> state, jitted. None: init is one program.
    reset: Callable | None = None
    init_from: Callable | None = None

    @property
    def sharding(self) -> NamedSharding:
        """The sharding of every leaf of the runs' state, hps and metrics: the run axis over the mesh."""
        return NamedSharding(self.mesh, PartitionSpec(AXIS))

    @property
    def num_devices(self) -> int:
        return self.mesh.devices.size

    def run(self, state: State, hps: HP, num_updates: int):
        """`num_updates` updates of every run: (state [R], metrics {name: [R, num_updates]})."""
        return self._run(state, hps, num_updates)

    def lower(self, state: State, hps: HP, num_updates: int):
        """The lowered chunk program (call .compile() on it to time compilation apart)."""
        return self._run.lower(state, hps, num_updates)

    def lower_chunk(self, state: State, hps: HP, length: int):
        """The lowered program of up to `length` updates: compiled, it is called as (state, hps, n) and runs the
        first n <= length of them (metrics [R, length], rows n.. NaN). One program serves a run's full chunks and
        its last, shorter one."""
        return self.trace_chunk(state, hps, length).lower()

    def trace_chunk(self, state: State, hps: HP, length: int):
        """The traced program of `lower_chunk` (call .lower() on it to time tracing and lowering apart)."""
        return self._chunk.trace(state, hps, length, jnp.int32(length))

    def phase(self, state: State, hps: HP):
        """The phase of every run: (state [R] ready for the updates, info {name: [R]})."""
        return self._phase_program()(state, hps)

    def lower_phase(self, state: State, hps: HP):
        """The lowered phase program (call .compile() on it to time compilation apart)."""
        return self.trace_phase(state, hps).lower()

    def trace_phase(self, state: State, hps: HP):
        """The traced phase program (call .lower() on it to time tracing and lowering apart)."""
        return self._phase_program().trace(state, hps)

    def _phase_program(self) -> Callable:
        if self._phase is None:
            raise ValueError("this sweep was built without a phase (make_sweep(trainer, phase=...))")
        return self._phase

    def key_shapes(self, num_runs: int) -> jax.ShapeDtypeStruct:
        """What `grid`'s keys for `num_runs` runs are, without drawing them: [R padded] PRNG keys over the mesh (a
        program traced for these shapes is traced once for the keys themselves too: JAX keeps a jitted function's
        trace per input shapes and shardings)."""
        padded = num_runs + (-num_runs) % self.num_devices
        return jax.ShapeDtypeStruct((padded,), jax.random.key(0).dtype, sharding=self.sharding)

    def grid(self, seed: int, num_seeds: int, hps: Sequence[HP]) -> tuple[jax.Array, HP]:
        """Runs for every (hp, seed) pair, hp-major: run r = i * num_seeds + s.

        Seed s gets the same key under every hp, so arms are compared on the same seeds. The run axis
        is padded to a multiple of the device count by repeating the last run (drop with `unpad`).
        """
        seed_keys = jax.random.split(jax.random.key(seed), num_seeds)
        keys = jnp.concatenate([seed_keys] * len(hps))
        stacked = stack([h for h in hps for _ in range(num_seeds)])
        pad = (-keys.shape[0]) % self.num_devices
        if pad:
            keys = jnp.concatenate([keys, jnp.repeat(keys[-1:], pad, axis=0)])
            stacked = jax.tree.map(lambda x: jnp.concatenate([x, jnp.repeat(x[-1:], pad)]), stacked)
        sharding = NamedSharding(self.mesh, PartitionSpec(AXIS))
        return multihost.put(keys, sharding), multihost.put(stacked, sharding)  # (jax.device_put in one process)


def unpad(tree, num_runs: int):
    """Drop the padding runs that `Sweep.grid` added."""
    return jax.tree.map(lambda x: x[:num_runs], tree)


SPLITS = ("partition", "local")


def make_sweep(trainer, mesh: Mesh | None = None, phase: Callable | None = None, split: str | None = None) -> Sweep:
    """The sweep programs of `trainer` (anything with pure init(key, hp) and update(state, hp), e.g.
    `cdjax.make_trainer(config)`); with `phase` (a pure run(state, hp) -> (state, info)), also that phase,
    run before the updates. split: "partition" or "local" (the module docstring); default: the trainer's
    `runs_split`, else "partition"."""
    mesh = mesh if mesh is not None else runs_mesh()
    split = split or getattr(trainer, "runs_split", None) or "partition"
    if split not in SPLITS:
        raise ValueError(f"split {split!r}: choose one of {SPLITS}")
    # Every program's outputs are declared on the run axis (out_shardings), the empty leaves too (MJX's data holds
    # arrays of size 0): XLA would give those a replicated sharding, which the next program, compiled for the run
    # axis, refuses on several devices.
    sharded = NamedSharding(mesh, PartitionSpec(AXIS))

    def place(tree):
        return jax.tree.map(lambda x: jax.lax.with_sharding_constraint(x, sharded), tree)

    def over_runs(per_device: Callable, *static) -> Callable:
        """(state, hps, *replicated) -> per_device(state, hps, *replicated, *static) on each device's own runs
        ("local": a shard_map, no collective), or on all runs with the partitioner placing them ("partition")."""
        if split == "partition":
            return lambda state, hps, *rest: place(per_device(state, hps, *rest, *static))
        runs, replicated = PartitionSpec(AXIS), PartitionSpec()
        return lambda state, hps, *rest: jax.shard_map(
            lambda s, h, *r: per_device(s, h, *r, *static), mesh=mesh,
            in_specs=(runs, runs) + (replicated,) * len(rest), out_specs=runs, check_vma=False)(state, hps, *rest)

    if getattr(trainer, "reset", None) is not None and getattr(trainer, "init_from", None) is not None:
        reset = shared_reset(trainer, mesh, place)

        @functools.partial(jax.jit, out_shardings=sharded)
        def init_from(keys, hps, env_state):
            return place(jax.vmap(trainer.init_from)(keys, hps, env_state))

        def init(keys, hps):
            return init_from(keys, hps, reset(keys))
    else:
        reset = init_from = None

        @functools.partial(jax.jit, out_shardings=sharded)
        def init(keys, hps):
            return place(jax.vmap(trainer.init)(keys, hps))

    def updates(state, hps, num_updates):
        def one_run(state, hp):
            return jax.lax.scan(lambda s, _: trainer.update(s, hp), state, None, length=num_updates)

        return jax.vmap(one_run)(state, hps)

    @functools.partial(jax.jit, static_argnums=2, donate_argnums=0, out_shardings=sharded)
    def run(state, hps, num_updates):
        return over_runs(updates, num_updates)(state, hps)

    update = jax.jit(trainer.update)  # a jit here only so that its trace serves both branches' shapes below

    def first_updates(state, hps, n, length):
        def one_run(state, hp):
            _, skipped = jax.eval_shape(update, state, hp)  # the metrics' shapes (update's trace is cached)
            nan = jax.tree.map(lambda m: jnp.full(m.shape, jnp.nan, m.dtype), skipped)

            def step(s, i):  # updates from the n-th on leave the state as it is (an unbatched predicate: a cond)
                return jax.lax.cond(i < n, lambda s: update(s, hp), lambda s: (s, nan), s)

            return jax.lax.scan(step, state, jnp.arange(length))

        return jax.vmap(one_run)(state, hps)

    @functools.partial(jax.jit, static_argnums=2, donate_argnums=0, out_shardings=sharded)
    def chunk(state, hps, length, n):
        return over_runs(first_updates, length)(state, hps, n)

    if phase is not None:

        @functools.partial(jax.jit, donate_argnums=0, out_shardings=sharded)
        def phase_run(state, hps):
            state, info = jax.vmap(phase)(state, hps)
            return place(state), place(info)
    else:
        phase_run = None

    return Sweep(trainer=trainer, mesh=mesh, init=init, _run=run, _phase=phase_run, _chunk=chunk, split=split,
                 reset=reset, init_from=init_from)


# env_key, mesh -> the jitted reset of the runs' environments that every sweep of them shares (shared_reset)
_RESETS: dict = {}


def shared_reset(trainer, mesh: Mesh, place: Callable) -> Callable:
    """jit(keys [R] -> the runs' environments, placed over the mesh by `place`), one function object per
    (trainer.env_key, mesh): the sweeps of several arms in the same environments call (and so compile) one reset
    program. Built from the first such trainer's reset; env_key says they are all the same function."""
    env_key = getattr(trainer, "env_key", None)  # None (e.g. an agent passed as it is): a reset of its own
    cache_key = (env_key, tuple(d.id for d in mesh.devices.flat), mesh.axis_names)
    if env_key is None or cache_key not in _RESETS:

        @functools.partial(jax.jit, out_shardings=NamedSharding(mesh, PartitionSpec(AXIS)))
        def reset(keys):
            return place(jax.vmap(trainer.reset)(keys))

        if env_key is None:
            return reset
        _RESETS[cache_key] = reset
    return _RESETS[cache_key]
