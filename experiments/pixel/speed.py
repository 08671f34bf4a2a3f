"""How the pixel update's throughput depends on how the runs of a sweep share the device.

    python -m experiments.pixel.speed --env halfcheetah --runs 10 --out speed.json

A sweep vmaps its runs. The runs' convolutions then have different weights per run, which XLA lowers to one
grouped convolution (feature_group_count = runs) and its grouped gradients. This measures, for the same R runs
of the same configuration (each as compile + steady-state seconds per update, and frames/s):

  vmap     jax.vmap over the runs (what the sweep does today);
  map      jax.lax.map over the runs: one run after another inside one program, ungrouped convolutions;
  single   one run alone (R = 1), for the per-run ceiling.

Arms: ltq-cd (the default) or ltq (--arm ltq). CPU options shrink everything (--set image_size=16 ...).

With --devices N [N ...] it measures instead the sweep itself (cdjax.sweep, the pixel trainer's own split of the
runs over devices) on the first N devices for each N, in one process: compile, then steady-state seconds per chunk
of --chunk updates and frames/s (issue 25: 1, 2 and 4 GPUs, `--runs 32 --devices 1 2 4`).

With --loops it measures, on one device and the same runs, what a sweep's chunk adds to the update (issue 22: the
sweeps trained ~13% below the update timed alone): --chunk updates as
  update   the vmapped update called --chunk times, one program call per update (what the roofline times);
  scan     the sweep's plain scan of --chunk updates (Sweep.run);
  chunk    the sweep's chunk program, the scan with each update under a cond on the updates left (what a sweep runs:
           one program serves full chunks and the last, shorter one).
With --trace DIR, two steady-state calls of each are traced and summarised in DIR/MODE.md (benchmarks.profile_summary).
"""

from __future__ import annotations

import argparse
import pathlib

import jax
import jax.numpy as jnp

from cdjax import agents, runtime
from experiments.pixel.data_cost import overrides, timed, write_json


def measure(config, runs: int, modes: list[str], trace: str = "") -> dict:
    setting = agents.get("pixel")
    learner = setting.make_trainer(config).inner
    hp = setting.hparams_type()
    hps = jax.tree.map(lambda x: jnp.full((runs,), x, jnp.float32), hp)
    keys = jax.random.split(jax.random.key(0), runs)
    states = jax.jit(jax.vmap(learner.init))(keys, hps)
    frames = config.batch_size * config.seq_len
    out = {"env": config.env, "arm": config.arm, "image_size": config.image_size, "runs": runs,
           "device": jax.devices()[0].device_kind, "frames_per_update_per_run": frames}
    programs = {
        "vmap": (jax.jit(jax.vmap(learner.update)), states, hps, runs),
        "map": (jax.jit(lambda s, h: jax.lax.map(lambda sh: learner.update(*sh), (s, h))), states, hps, runs),
        "single": (jax.jit(learner.update), jax.tree.map(lambda x: x[0], states), jax.tree.map(lambda x: x[0], hps), 1),
    }
    for mode in modes:
        fn, s, h, n = programs[mode]
        first, steady = timed(lambda s: fn(s, h)[1], s)
        out[mode] = {"compile_and_first_s": round(first, 2), "update_s": round(steady, 5),
                     "frames_per_s": round(n * frames / steady)}
        print(mode, out[mode], flush=True)
        if trace:  # an op-level trace of two steady-state updates of each mode (benchmarks.profile_summary reads it)
            with jax.profiler.trace(str(pathlib.Path(trace) / mode), create_perfetto_trace=True):
                for _ in range(2):
                    jax.block_until_ready(fn(s, h)[1])
    return out


def measure_devices(config, runs: int, counts: list[int], chunk: int) -> dict:
    """frames/s of the pixel sweep's chunk of `chunk` updates of `runs` runs on the first N devices, per N."""
    from cdjax.runner import budget
    from cdjax.sweep import make_sweep, runs_mesh

    setting = agents.get("pixel")
    trainer = setting.make_trainer(config)
    out = {"env": config.env, "arm": config.arm, "runs": runs, "chunk_updates": chunk,
           "device": jax.devices()[0].device_kind, "frames_per_update_per_run": config.batch_size * config.seq_len}
    for n in counts:
        sweep = make_sweep(trainer, mesh=runs_mesh(jax.devices()[:n]))
        keys, hps = sweep.grid(seed=0, num_seeds=runs, hps=[setting.hparams_type()])
        state = sweep.init(keys, hps)
        program, _ = budget.compile_fitting(sweep.lower_chunk(state, hps, chunk))  # as a sweep compiles it
        length = jnp.int32(chunk)

        def call(carry, program=program, hps=hps, length=length):
            return program(carry[0], hps, length)

        first, carry = timed_chain(call, (state, None))
        steady, _ = timed_chain(call, carry, repeats=3)
        frames = runs * chunk * out["frames_per_update_per_run"]
        out[f"{n}_devices"] = {"split": sweep.split, "padded_runs": int(keys.shape[0]), "first_chunk_s": round(first, 2),
                               "chunk_s": round(steady, 4), "frames_per_s": round(frames / steady)}
        print(n, out[f"{n}_devices"], flush=True)
        del carry
    base = out[f"{counts[0]}_devices"]["frames_per_s"]
    for n in counts:
        out[f"{n}_devices"]["speedup"] = round(out[f"{n}_devices"]["frames_per_s"] / base, 3)
    return out


def measure_loops(config, runs: int, chunk: int, trace: str = "") -> dict:
    """ms per update and frames/s of `chunk` updates of `runs` runs as the vmapped update called `chunk` times, the
    sweep's plain scan and its chunk program (the scan with a cond per update), all on one device."""
    from cdjax.runner import budget
    from cdjax.sweep import make_sweep, runs_mesh

    setting = agents.get("pixel")
    trainer = setting.make_trainer(config)
    sweep = make_sweep(trainer, mesh=runs_mesh(jax.devices()[:1]))
    keys, hps = sweep.grid(seed=0, num_seeds=runs, hps=[setting.hparams_type()])
    frames = runs * chunk * config.batch_size * config.seq_len
    out = {"env": config.env, "arm": config.arm, "runs": runs, "chunk_updates": chunk,
           "device": jax.devices()[0].device_kind, "frames_per_update_per_run": config.batch_size * config.seq_len}
    state = sweep.init(keys, hps)
    update, _ = budget.compile_fitting(jax.jit(jax.vmap(trainer.update), donate_argnums=0).lower(state, hps))
    scan, _ = budget.compile_fitting(sweep.lower(state, hps, chunk))
    chunked, _ = budget.compile_fitting(sweep.lower_chunk(state, hps, chunk))
    programs = {"update": (update, lambda c: _updates(update, c[0], hps, chunk)),
                "scan": (scan, lambda c: scan(c[0], hps)),
                "chunk": (chunked, lambda c: chunked(c[0], hps, jnp.int32(chunk)))}
    carry = (state, None)
    for mode, (compiled, call) in programs.items():
        first, carry = timed_chain(call, carry)
        steady, carry = timed_chain(call, carry, repeats=3)
        out[mode] = {"first_s": round(first, 3), "ms_per_update": round(1e3 * steady / chunk, 3),
                     "frames_per_s": round(frames / steady)}
        print(mode, out[mode], flush=True)
        if trace:  # two steady-state calls, summarised beside the trace (DIR/MODE.md)
            from benchmarks import profile_summary

            where = pathlib.Path(trace) / mode
            with profile_summary.trace(where, compiled):
                _, carry = timed_chain(call, carry, repeats=2)
            where.with_suffix(".md").write_text(profile_summary.markdown(profile_summary.summarize(where)))
    for mode in programs:
        out[mode]["vs_update"] = round(out["update"]["ms_per_update"] / out[mode]["ms_per_update"], 3)
    return out


def _updates(update, state, hps, n: int):
    """n calls of the compiled vmapped update, each on the last's state: (state, the last call's metrics)."""
    metrics = None
    for _ in range(n):
        state, metrics = update(state, hps)
    return state, metrics


def timed_chain(call, carry, repeats: int = 1):
    """(mean seconds of `repeats` calls, each on the last's output: the chunk donates its state, last carry)."""
    import time

    start = time.perf_counter()
    for _ in range(repeats):
        carry = call(carry)
    jax.block_until_ready(carry[1])
    return (time.perf_counter() - start) / repeats, carry


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="halfcheetah")
    parser.add_argument("--arm", default="ltq-cd")
    parser.add_argument("--runs", type=int, default=10)
    parser.add_argument("--modes", nargs="*", default=["single", "map", "vmap"])
    parser.add_argument("--set", nargs="*", default=[], help="PixelConfig overrides NAME=VALUE, e.g. image_size=16 upsample=subpixel")
    parser.add_argument("--out", default="")
    parser.add_argument("--trace", default="", help="write a jax.profiler trace of each mode under this directory")
    parser.add_argument("--devices", nargs="*", type=int, default=[],
                        help="measure the sweep on the first N devices for each N instead (e.g. 1 2 4)")
    parser.add_argument("--chunk", type=int, default=20, help="updates per timed chunk (with --devices or --loops)")
    parser.add_argument("--loops", action="store_true",
                        help="the update alone against the sweep's scan and chunk programs, one device (see above)")
    args = parser.parse_args(argv)
    runtime.configure(cache_dir=runtime.default_cache_dir())
    setting = agents.get("pixel")
    given = dict(setting.presets[f"pixel-{args.env}"].config, arm=args.arm) | overrides(args.set)
    if args.loops:
        result = measure_loops(setting.config_type(**given), args.runs, args.chunk, args.trace)
        write_json(result, args.out)
        return result
    if args.devices:
        result = measure_devices(setting.config_type(**given), args.runs, args.devices, args.chunk)
        write_json(result, args.out)
        return result
    result = measure(setting.config_type(**given), args.runs, args.modes, args.trace)
    write_json(result, args.out)
    return result


if __name__ == "__main__":
    main()
