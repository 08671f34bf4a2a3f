"""The README's example on a CPU-sized config: 2 seeds of the CD agent trained in one compiled program.

    python experiments/readme_example.py                 # inverted pendulum (MJX), 2 seeds, ~1 min on CPU
    python experiments/readme_example.py --env ant --num-envs 4096 --rollout-len 32 --horizon 20 --updates 200
"""

import argparse
import time

import jax
import numpy as np

from cdjax import Config, HParams, make_train, runtime


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--env", default="inverted_pendulum")
    p.add_argument("--num-envs", type=int, default=32)
    p.add_argument("--rollout-len", type=int, default=32)
    p.add_argument("--horizon", type=int, default=8)
    p.add_argument("--updates", type=int, default=60)
    p.add_argument("--seeds", type=int, default=2)
    p.add_argument("--alpha", type=float, default=1.0)
    args = p.parse_args()

    runtime.configure(cache_dir=".jax_cache")
    config = Config(env=args.env, num_envs=args.num_envs, rollout_len=args.rollout_len, horizon=args.horizon,
                    num_updates=args.updates, num_minibatches=4, episode_length=200, model_hidden=(64,),
                    value_hidden=(64, 64), encoder_dim=32)
    train = make_train(config)
    keys = jax.random.split(jax.random.key(0), args.seeds)
    start = time.perf_counter()
    state, metrics = jax.jit(jax.vmap(train, in_axes=(0, None)))(keys, HParams(alpha=args.alpha, lr_policy=1e-3,
                                                                                  lr_value=1e-3))
    jax.block_until_ready(metrics)
    print(f"{args.seeds} seeds x {args.updates} updates x {config.env_steps_per_update} env steps "
          f"in {time.perf_counter() - start:.1f} s (compile included)")
    ret = np.asarray(metrics["episode/return"])  # [seeds, updates]
    err = np.asarray(metrics["model/openloop_mse_k"])
    for s in range(args.seeds):
        first = ret[s][np.isfinite(ret[s])][:3].mean()
        print(f"seed {s}: return {first:.1f} -> {ret[s, -5:].mean():.1f}; open-loop MSE at k "
              f"{np.nanmean(err[s, :10]):.4f} -> {np.nanmean(err[s, -5:]):.4f}; "
              f"l_cc {float(metrics['loss/consistency'][s, -1]):.4f}")


if __name__ == "__main__":
    main()
