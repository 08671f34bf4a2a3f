"""Will a sweep fit in memory? Estimated before anything is allocated or written, refused in one sentence.

Two checks per device (the runs of an arm are spread over the local devices):

1. `check_states`, from shapes alone (`jax.eval_shape` of one run's init): every arm's state is held at
   once, and an evaluation adds `episodes` environments per run; this refuses absurd sizes in seconds.
2. `check_programs`, from XLA's own accounting of the compiled programs (`memory_analysis()`): the states
   plus the largest program's outputs and temporaries.

The memory a device has is `memory_stats()["bytes_limit"]` minus what is in use where the backend
reports it (GPUs), else the host's available memory (CPU).
"""

from __future__ import annotations

import math
import os
from typing import Sequence

import jax
import numpy as np

from cdjax import runtime
from cdjax.protocol import ConfigError


def tree_bytes(tree) -> int:
    """Bytes of the arrays (or ShapeDtypeStructs) of a pytree; PRNG keys count their key data."""
    total = 0
    for x in jax.tree.leaves(tree):
        if jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key):
            x = jax.eval_shape(jax.random.key_data, x)
        total += math.prod(x.shape) * np.dtype(x.dtype).itemsize
    return total


def available(device: jax.Device | None = None) -> tuple[int, str]:
    """(bytes a sweep may use on `device`, what that is) — the device's free memory, else the host's."""
    device = device or jax.local_devices()[0]  # (of this process: the others' are not addressable here)
    try:
        stats = device.memory_stats()
    except Exception:  # noqa: BLE001 - backends without memory statistics
        stats = None
    if stats and "bytes_limit" in stats:
        return int(stats["bytes_limit"]) - int(stats.get("bytes_in_use", 0)), f"free on {device.device_kind}"
    try:
        with open("/proc/meminfo") as f:
            info = dict(line.split(":", 1) for line in f)
        return int(info["MemAvailable"].split()[0]) * 1024, "of available host memory"
    except (OSError, KeyError, ValueError):
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"), "of available host memory"


def gb(n: float) -> str:
    return f"{n / 1e9:,.2f} GB" if n < 1e12 else f"{n / 1e12:,.1f} TB"


def _refuse(need: int, have: int, where: str, detail: str) -> None:
    raise ConfigError(f"The sweep needs about {gb(need)} per device ({detail}) but there are {gb(have)} {where}; "
                      "use fewer --seeds, fewer hyper-parameter values, fewer or smaller environments "
                      "(--num-envs), narrower networks or shorter horizons (the widths, --eval-horizon), or fewer "
                      "--eval-episodes.")


def check_states(arms: Sequence[tuple[str, int, int, int]], devices: int, have: tuple[int, str] | None = None) -> int:
    """arms: (name, runs, state bytes per run, eval-env bytes per run at the evaluation's episodes).

    Returns the bytes per device that the states take; ConfigError when states, or states plus an
    evaluation, cannot fit."""
    have, where = have or available()
    per_device = [(name, math.ceil(runs / devices), state, ev) for name, runs, state, ev in arms]
    states = sum(runs * state for _, runs, state, _ in per_device)
    evaluation = max(runs * ev for _, runs, _, ev in per_device)
    if states + evaluation > have:
        worst = max(per_device, key=lambda a: a[1] * a[2])
        _refuse(states + evaluation, have, where,
                f"states {gb(states)}, largest arm {worst[0]}: {worst[1]:,} runs x {gb(worst[2])}; "
                f"evaluation {gb(evaluation)}")
    return states


def program_bytes(compiled) -> int | None:
    """Outputs not aliased to inputs plus temporaries of a compiled program, per device (None: unknown)."""
    try:
        m = compiled.memory_analysis()
    except Exception:  # noqa: BLE001 - backends without the analysis
        return None
    if m is None:
        return None
    return int(m.output_size_in_bytes) - int(m.alias_size_in_bytes) + int(m.temp_size_in_bytes)


def signature(tree) -> tuple:
    """What a compiled program's inputs must be: the tree's structure, shapes, dtypes and shardings (static
    values as they are). A key for the programs compiled for those inputs."""
    leaves, treedef = jax.tree.flatten(tree)
    return treedef, tuple((x.shape, str(x.dtype), getattr(x, "sharding", None)) if hasattr(x, "shape") else x
                          for x in leaves)


def fits(program, room: int | None) -> bool:
    """Whether a compiled program's outputs and temporaries (program_bytes) fit in `room` bytes (None, or a size the
    backend does not report: yes)."""
    need = program_bytes(program)
    return room is None or need is None or need <= room


def compile_fitting(lowered, room: int | None = None, mode: str | None = None) -> tuple[object, bool]:
    """(compiled program, whether in program order): `lowered` compiled with runtime.compiler_options(mode) and, where
    those schedule the GPU's kernels by data flow (runtime.SCHEDULING) and the program's outputs and temporaries
    exceed `room` bytes (default: what is free on the device now, beside the arrays it holds), compiled again in
    XLA's program order, which reuses buffers between kernels (about half the bytes; the updates run somewhat slower,
    as measured in benchmarks/README.md). For a program compiled outside a sweep (a benchmark's, a notebook's); a
    sweep does the same per program (cdjax.runner.arms._compiled)."""
    options = runtime.compiler_options(mode)
    program = lowered.compile(options)
    if not runtime.concurrent(options) or fits(program, available()[0] if room is None else room):
        return program, False
    return lowered.compile(runtime.compiler_options(mode, in_order=True)), True


def check_programs(states: int, programs: dict[str, object], have: tuple[int, str] | None = None) -> int:
    """ConfigError when the states plus the most demanding compiled program (by name) cannot fit; else the bytes
    per device left beside them (the loop copies the states there for a checkpoint when they fit: `Loop.round`)."""
    have, where = have or available()
    sizes = {name: b for name, p in programs.items() if (b := program_bytes(p)) is not None}
    if not sizes:
        return have - states
    name = max(sizes, key=sizes.get)
    if states + sizes[name] > have:
        _refuse(states + sizes[name], have, where, f"states {gb(states)}, program {name} {gb(sizes[name])}")
    return have - states - sizes[name]
