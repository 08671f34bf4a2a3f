"""Seed and hyper-parameter sweeps: many runs of one Config in one compiled program.

A sweep has R runs (e.g. seeds x an alpha grid). Each run has its own PRNG key and its own HParams;
`jax.vmap` batches them and `jax.sharding` splits the run axis over all local devices (a 1-D `Mesh`
named "runs"): each device trains R / num_devices runs, with no communication between them.

    sweep = make_sweep(config)
    keys, hps = sweep.grid(seed=0, num_seeds=8, hps=[HParams(alpha=0.0), HParams(alpha=1.0)])
    state = sweep.init(keys, hps)                       # leaves [R, ...], sharded over devices
    state, metrics = sweep.run(state, hps, 10)          # 10 updates; metrics leaves [R, 10]

Several hosts: call `jax.distributed.initialize()` in every process before anything else; then
`jax.devices()` lists every host's devices, `make_sweep(config, mesh=runs_mesh())` builds a mesh over
all of them and each process feeds the same global arrays (`jax.make_array_from_process_local_data`
for inputs that differ per host). R must then be a multiple of the global device count; the sweep pads
it here on one host only.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import TYPE_CHECKING, Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from cdjax.config import Config, HParams, stack_hparams
from cdjax.train import TrainState, Trainer, make_trainer

if TYPE_CHECKING:
    from cdjax.mbmf import MbMfPhase

AXIS = "runs"


def runs_mesh(devices: Sequence[jax.Device] | None = None) -> Mesh:
    """A 1-D mesh over `devices` (default: all devices) whose one axis carries the runs."""
    return Mesh(np.asarray(devices if devices is not None else jax.devices()), (AXIS,))


@dataclasses.dataclass(frozen=True)
class Sweep:
    config: Config
    trainer: Trainer
    mesh: Mesh
    init: Callable[[jax.Array, HParams], TrainState]  # (keys [R], hps [R]) -> state [R]
    _run: Callable  # jitted (state, hps, num_updates) -> (state, metrics [R, n])
    _phase: Callable | None = None  # jitted (state, hps) -> (state, info [R]): the Mb-Mf phase of every run

    @property
    def num_devices(self) -> int:
        return self.mesh.devices.size

    def run(self, state: TrainState, hps: HParams, num_updates: int):
        """`num_updates` updates of every run: (state [R], metrics {name: [R, num_updates]})."""
        return self._run(state, hps, num_updates)

    def lower(self, state: TrainState, hps: HParams, num_updates: int):
        """The lowered chunk program (call .compile() on it to time compilation apart)."""
        return self._run.lower(state, hps, num_updates)

    def phase(self, state: TrainState, hps: HParams):
        """The Mb-Mf phase of every run (cdjax.mbmf): (state [R] ready for PPO, info {name: [R]})."""
        return self._phase_program()(state, hps)

    def lower_phase(self, state: TrainState, hps: HParams):
        """The lowered phase program (call .compile() on it to time compilation apart)."""
        return self._phase_program().lower(state, hps)

    def _phase_program(self) -> Callable:
        if self._phase is None:
            raise ValueError("this sweep was built without an Mb-Mf phase (make_sweep(config, phase=...))")
        return self._phase

    def grid(self, seed: int, num_seeds: int, hps: Sequence[HParams]) -> tuple[jax.Array, HParams]:
        """Runs for every (hp, seed) pair, hp-major: run r = i * num_seeds + s.

        Seed s gets the same key under every hp, so arms are compared on the same seeds. The run axis
        is padded to a multiple of the device count by repeating the last run (drop with `unpad`).
        """
        seed_keys = jax.random.split(jax.random.key(seed), num_seeds)
        keys = jnp.concatenate([seed_keys] * len(hps))
        stacked = stack_hparams([h for h in hps for _ in range(num_seeds)])
        pad = (-keys.shape[0]) % self.num_devices
        if pad:
            keys = jnp.concatenate([keys, jnp.repeat(keys[-1:], pad, axis=0)])
            stacked = jax.tree.map(lambda x: jnp.concatenate([x, jnp.repeat(x[-1:], pad)]), stacked)
        sharding = NamedSharding(self.mesh, PartitionSpec(AXIS))
        return jax.device_put(keys, sharding), jax.device_put(stacked, sharding)


def unpad(tree, num_runs: int):
    """Drop the padding runs that `Sweep.grid` added."""
    return jax.tree.map(lambda x: x[:num_runs], tree)


def make_sweep(config: Config, mesh: Mesh | None = None, phase: "MbMfPhase | None" = None) -> Sweep:
    """The sweep programs of `config`; with `phase`, also the Mb-Mf phase (run it before the updates)."""
    trainer = make_trainer(config)
    mesh = mesh if mesh is not None else runs_mesh()
    sharded = NamedSharding(mesh, PartitionSpec(AXIS))

    def place(tree):
        return jax.tree.map(lambda x: jax.lax.with_sharding_constraint(x, sharded), tree)

    @jax.jit
    def init(keys, hps):
        return place(jax.vmap(trainer.init)(keys, hps))

    @functools.partial(jax.jit, static_argnums=2, donate_argnums=0)
    def run(state, hps, num_updates):
        def one_run(state, hp):
            return jax.lax.scan(lambda s, _: trainer.update(s, hp), state, None, length=num_updates)

        state, metrics = jax.vmap(one_run)(state, hps)
        return place(state), place(metrics)

    phase_run = None
    if phase is not None:
        from cdjax.mbmf import make_mbmf_phase

        one_phase = make_mbmf_phase(config, phase, trainer)

        @functools.partial(jax.jit, donate_argnums=0)
        def phase_run(state, hps):
            state, info = jax.vmap(one_phase)(state, hps)
            return place(state), place(info)

    return Sweep(config=config, trainer=trainer, mesh=mesh, init=init, _run=run, _phase=phase_run)
