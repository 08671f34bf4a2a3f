"""What keeping the expert dataset on the device costs against rendering it on the fly inside the update.

    python -m experiments.pixel.data_cost --env halfcheetah --expert EXPERT --runs 10 --out cost.json

Measures, for R runs vmapped (as a sweep runs them), each as compile + steady-state seconds:
  once     generating the N + M sequences of a run once (what `init` does), and its bytes on the device;
  update   one training update on batches drawn from the kept data;
  fly      rendering one update's batch afresh (B sequences of burn_in + L + F - 1 expert steps), which an
           on-the-fly design would add to every update.
The decision in cdjax: generate once, keep on the device (see README). CPU options shrink everything.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import time

import jax
import jax.numpy as jnp

from cdjax import agents, runtime


def timed(fn, *args, repeats: int = 3) -> tuple[float, float]:
    """(first call incl. compile, mean of `repeats` later calls) in seconds."""
    start = time.perf_counter()
    jax.block_until_ready(fn(*args))
    first = time.perf_counter() - start
    start = time.perf_counter()
    for _ in range(repeats):
        jax.block_until_ready(fn(*args))
    return first, (time.perf_counter() - start) / repeats


def measure(config, runs: int) -> dict:
    setting = agents.get("pixel")
    learner = setting.make_trainer(config).inner
    hp = setting.hparams_type()
    hps = jax.tree.map(lambda x: jnp.full((runs,), x, jnp.float32), hp)
    keys = jax.random.split(jax.random.key(0), runs)
    init = jax.jit(jax.vmap(learner.init))
    init_first, init_steady = timed(init, keys, hps, repeats=1)
    states = init(keys, hps)
    data_bytes = sum(x.nbytes for x in jax.tree.leaves((states.data, states.heldout)))
    update = jax.jit(jax.vmap(learner.update))
    update_first, update_steady = timed(lambda s: update(s, hps)[1], states)
    fly = jax.jit(jax.vmap(lambda k: learner.world.generate(k, config.batch_size, config.seq_len)))
    fly_first, fly_steady = timed(fly, keys)
    frames = config.batch_size * config.seq_len * runs
    return {
        "env": config.env, "image_size": config.image_size, "runs": runs, "device": str(jax.devices()[0]),
        "sequences_per_run": config.num_sequences + config.heldout_sequences, "data_bytes_all_runs": data_bytes,
        "once_compile_and_run_s": init_first, "once_run_s": init_steady,
        "update_compile_s": update_first, "update_s": update_steady, "frames_per_s": frames / update_steady,
        "fly_compile_s": fly_first, "fly_per_update_s": fly_steady,
        "fly_over_update": fly_steady / update_steady,
    }


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="halfcheetah")
    parser.add_argument("--preset", default="", help="a pixel preset (default: pixel-ENV)")
    parser.add_argument("--expert", default="")
    parser.add_argument("--runs", type=int, default=10)
    parser.add_argument("--set", nargs="*", default=[], help="PixelConfig overrides NAME=VALUE, e.g. image_size=16")
    parser.add_argument("--out", default="")
    args = parser.parse_args(argv)
    runtime.configure(cache_dir=runtime.default_cache_dir())
    setting = agents.get("pixel")
    preset = setting.presets[args.preset or f"pixel-{args.env}"]
    config = setting.config_type(**(dict(preset.config, expert=args.expert) | overrides(args.set)))
    result = measure(config, args.runs)
    print(json.dumps(result, indent=1))
    write_json(result, args.out)
    return result


def overrides(items: list[str]) -> dict:
    """NAME=VALUE items of --set as PixelConfig fields (integers where the value is one)."""
    out = {}
    for item in items:
        name, value = item.split("=", 1)
        out[name] = int(value) if value.lstrip("-").isdigit() else value
    return out


def write_json(result: dict, out: str) -> None:
    if out:
        pathlib.Path(out).parent.mkdir(parents=True, exist_ok=True)
        pathlib.Path(out).write_text(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
