"""How the pixel update's throughput depends on how the runs of a sweep share the device.

    python -m experiments.pixel.speed --env halfcheetah --runs 10 --out speed.json

A sweep vmaps its runs. The runs' convolutions then have different weights per run, which XLA lowers to one
grouped convolution (feature_group_count = runs) and its grouped gradients. This measures, for the same R runs
of the same configuration (each as compile + steady-state seconds per update, and frames/s):

  vmap     jax.vmap over the runs (what the sweep does today);
  map      jax.lax.map over the runs: one run after another inside one program, ungrouped convolutions;
  single   one run alone (R = 1), for the per-run ceiling.

Arms: ltq-cd (the default) or ltq (--arm ltq). CPU options shrink everything (--set image_size=16 ...).
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


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="halfcheetah")
    parser.add_argument("--arm", default="ltq-cd")
    parser.add_argument("--runs", type=int, default=10)
    parser.add_argument("--modes", nargs="*", default=["single", "map", "vmap"])
    parser.add_argument("--set", nargs="*", default=[], help="PixelConfig overrides NAME=VALUE, e.g. image_size=16 upsample=subpixel")
    parser.add_argument("--out", default="")
    parser.add_argument("--trace", default="", help="write a jax.profiler trace of each mode under this directory")
    args = parser.parse_args(argv)
    runtime.configure(cache_dir=runtime.default_cache_dir())
    setting = agents.get("pixel")
    given = dict(setting.presets[f"pixel-{args.env}"].config, arm=args.arm) | overrides(args.set)
    result = measure(setting.config_type(**given), args.runs, args.modes, args.trace)
    write_json(result, args.out)
    return result


if __name__ == "__main__":
    main()
