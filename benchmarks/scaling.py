"""Seed scaling (vmapped runs through cdjax.sweep, sharded over devices) and num_envs scaling.

Seed scaling: R runs of one Config in one compiled program, `cdjax.sweep.make_sweep` (jit of vmap
over runs; the run axis sharded over a 1-D device mesh). One timed call is one update of every run;
aggregate env steps/s counts the R real runs only (the sweep pads R to a multiple of the device count
with copies that are computed but not counted). Counts grow until one fails with
RESOURCE_EXHAUSTED (recorded as "OOM"; larger counts of that arm are not tried).
"""

from __future__ import annotations

import dataclasses
import math
import os
from typing import Iterator

from benchmarks.common import (Spec, Timing, cleanup, compile_timed, compiled_footprint, is_oom, process_peak,
                               steady, time_calls)
from benchmarks.throughput import cdjax_cases


def sweep_case(spec: Spec, case: str, runs: int, timing: Timing, mesh_devices: int | None = None,
               trace_dir: str | None = None) -> dict:
    """`runs` vmapped seeds of cdjax case `case` at spec (spec.num_envs envs per seed), one update per call; with
    `trace_dir`, a jax.profiler trace of one more call into trace_dir/<case>-x<runs> (`trace_dir` in the row)."""
    import jax
    import numpy as np

    from cdjax import make_agent, multihost
    from cdjax.sweep import make_sweep, runs_mesh

    what, overrides, hp_overrides = cdjax_cases(spec)[case]
    config = spec.config(**overrides)
    # all devices (of every process, with --distributed), or the first of this process's own
    devices = jax.devices() if not mesh_devices or mesh_devices >= jax.device_count() else \
        jax.local_devices()[:mesh_devices]
    spans_processes = len({d.process_index for d in devices}) > 1
    if spans_processes:  # every process makes the same calls of the program: no early stop on this one's clock
        timing = dataclasses.replace(timing, max_seconds=math.inf)
    sweep = make_sweep(make_agent(config), mesh=runs_mesh(devices))
    keys, hps = sweep.grid(seed=0, num_seeds=runs, hps=[spec.hparams(**hp_overrides)])
    state = sweep.init(keys, hps)
    # Sweep.lower gives the chunk program (state, hps, num_updates) -> (state, metrics); num_updates is static.
    compiled, lower_s, compile_s, in_order = compile_timed(sweep, state, hps, 1)
    step = lambda c: compiled(c[0], hps)  # noqa: E731
    carry, times = time_calls(step, (state, None), timing)
    traced = {}
    if trace_dir:
        from benchmarks import profile_summary

        traced["trace_dir"] = os.path.join(trace_dir, f"{case}-x{runs}")
        with profile_summary.trace(traced["trace_dir"], compiled):
            carry = jax.block_until_ready(step(carry))
    fetch = multihost.fetch if spans_processes else jax.device_get  # whole, on every process
    ok = bool(np.isfinite(np.asarray(fetch(carry[1]["loss/total"]))[:runs]).all())
    return {"case": case, "kind": "sweep", "env": spec.env, "num_envs": spec.num_envs, "seeds": runs,
            "padded_runs": int(keys.shape[0]), "mesh_devices": len(devices), "rollout_len": spec.rollout_len,
            "status": "ok", "what": what, "in_order": in_order, "lower_s": lower_s, "xla_compile_s": compile_s,
            "compile_s": lower_s + compile_s, **steady(times, runs * config.env_steps_per_update),
            "mem_bytes": compiled_footprint(compiled), "mem_source": "compiled (per device)",
            "process_peak_bytes": process_peak(), "finite": ok, **traced}


def seed_scaling(spec: Spec, cases: list[str], counts: list[int], timing: Timing, run_case,
                 mesh_devices: int | None = None, trace_dir: str | None = None) -> Iterator[dict]:
    """Yields a row per (case, count): counts in increasing order until one is out of memory.
    `run_case(label, fn)` wraps a call with the suite's error and time-budget handling, returning a row.
    `trace_dir`: each row's call also traced (sweep_case)."""
    for case in cases:
        oom = False
        for runs in sorted(counts):
            label = f"{case} x{runs}" + (f" on {mesh_devices} device(s)" if mesh_devices else "")
            if oom:
                yield {"case": case, "kind": "sweep", "seeds": runs, "num_envs": spec.num_envs,
                       "mesh_devices": mesh_devices, "status": "not tried (smaller count was OOM)"}
                continue
            row = run_case(label, lambda: sweep_case(spec, case, runs, timing, mesh_devices, trace_dir))
            row.update(case=case, kind="sweep", seeds=runs, num_envs=spec.num_envs)  # also for failed rows
            row.setdefault("mesh_devices", mesh_devices)
            oom = row.get("status") == "OOM"
            cleanup()
            yield row


def classify_error(error: BaseException) -> str:
    return "OOM" if is_oom(error) else "error"
