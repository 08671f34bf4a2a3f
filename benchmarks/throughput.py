"""Throughput of the cdjax update (and of the raw MJX ceiling), one case per process.

    python benchmarks/throughput.py --cases ceiling model-free mbmf cd --env ant --num-envs 4096
    python benchmarks/throughput.py --tiny          # CPU smoke test (CI): tiny sizes, point env

Each case runs in a fresh subprocess (so peak device memory is that case's own), compiles the jitted
update once (compile time reported apart), warms up, then times `--updates` updates and reports
steady-state environment steps per second. Results are printed as one JSON line per case and, with
--out, written as JSON and a markdown table.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time

CASES = {
    # name: (Config overrides, HParams overrides)
    "model-free": (dict(arm="model-free"), dict()),
    "mbmf": (dict(arm="mbmf"), dict(alpha=0.0)),
    "cd": (dict(arm="cd"), dict(alpha=1.0)),
    "cd-w2": (dict(arm="cd", cc_windows=2), dict(alpha=1.0)),
    "cd-unroll": (dict(arm="cd", cc_unroll=20), dict(alpha=1.0)),
    "cd-w2-unroll": (dict(arm="cd", cc_windows=2, cc_unroll=20), dict(alpha=1.0)),
    "cd-l2": (dict(arm="cd", encoder="l2"), dict(alpha=1.0)),
}


def _device_info():
    import jax

    dev = jax.devices()[0]
    return {"device": getattr(dev, "device_kind", str(dev)), "platform": dev.platform, "jax": jax.__version__,
            "num_devices": jax.device_count()}


def _peak_bytes():
    import jax

    stats = jax.devices()[0].memory_stats() or {}
    return stats.get("peak_bytes_in_use")


def run_case(name: str, args) -> dict:
    import jax

    from cdjax import Config, HParams, make_trainer

    if args.cache:
        jax.config.update("jax_compilation_cache_dir", args.cache)
    base = dict(env=args.env, num_envs=args.num_envs, rollout_len=args.rollout_len, horizon=args.horizon,
                num_epochs=args.epochs, num_minibatches=args.minibatches, episode_length=1000)
    if args.tiny:
        base.update(policy_hidden=(16,), value_hidden=(16,), model_hidden=(32,), encoder_dim=8, eval_envs=2,
                    eval_horizon=10)
    result = {"case": name, **_device_info(), **base, "seeds": args.seeds}
    if name == "ceiling":
        return {**result, **_ceiling(args)}
    overrides, hp_overrides = CASES[name]
    config = Config(**{**base, **overrides})
    hp = HParams(**hp_overrides)
    trainer = make_trainer(config)
    keys = jax.random.split(jax.random.key(0), args.seeds)
    init = jax.jit(jax.vmap(trainer.init, in_axes=(0, None)))
    update = jax.jit(jax.vmap(trainer.update, in_axes=(0, None)))
    state = jax.block_until_ready(init(keys, hp))
    t0 = time.perf_counter()
    compiled = update.lower(state, hp).compile()
    compile_s = time.perf_counter() - t0
    state, metrics = compiled(state, hp)
    jax.block_until_ready(metrics)
    times = []
    for _ in range(args.updates):
        t0 = time.perf_counter()
        state, metrics = compiled(state, hp)
        jax.block_until_ready(metrics)
        times.append(time.perf_counter() - t0)
    times.sort()
    median = times[len(times) // 2]
    steps = config.env_steps_per_update * args.seeds
    return {**result, **overrides, "compile_s": round(compile_s, 2), "update_s_median": round(median, 4),
            "env_steps_per_s": round(steps / median), "per_seed_steps_per_s": round(steps / median / args.seeds),
            "peak_bytes": _peak_bytes(), "finite": bool(all(bool(jax.numpy.isfinite(v).all())
                                                              for k, v in metrics.items() if k.startswith("loss/")))}


def _ceiling(args) -> dict:
    """Raw MJX stepping with uniform random actions: a 200-step scan of vmapped env.step."""
    import jax
    import jax.numpy as jnp

    from cdjax.envs import make_single_env

    env = make_single_env(args.env)
    B, L = args.num_envs, 200
    state = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.key(0), B))
    state = jax.tree.map(lambda x: jnp.asarray(x, x.dtype), state)

    def roll(state, key):
        def body(s, k):
            a = jax.random.uniform(k, (B, env.action_size), minval=-1.0, maxval=1.0)
            s = jax.vmap(env.step)(s, a)
            return jax.tree.map(lambda x: jnp.asarray(x, x.dtype), s), None

        return jax.lax.scan(body, state, jax.random.split(key, L))[0]

    t0 = time.perf_counter()
    compiled = jax.jit(roll).lower(state, jax.random.key(1)).compile()
    compile_s = time.perf_counter() - t0
    state = jax.block_until_ready(compiled(state, jax.random.key(1)))
    times = []
    for i in range(max(3, args.updates // 2)):
        t0 = time.perf_counter()
        state = jax.block_until_ready(compiled(state, jax.random.key(i + 2)))
        times.append(time.perf_counter() - t0)
    median = sorted(times)[len(times) // 2]
    return {"compile_s": round(compile_s, 2), "update_s_median": round(median, 4),
            "env_steps_per_s": round(B * L / median), "peak_bytes": _peak_bytes()}


def table(rows: list[dict]) -> str:
    ref = {r["case"]: r["env_steps_per_s"] for r in rows if "env_steps_per_s" in r}
    lines = ["| case | env | envs | T | k | epochs x minibatches | seeds | compile s | env steps/s | vs model-free | peak GiB |",
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in rows:
        if "error" in r:
            lines.append(f"| {r['case']} | error: {r['error'][:80]} |")
            continue
        ratio = r["env_steps_per_s"] / ref["model-free"] if "model-free" in ref else float("nan")
        peak = r.get("peak_bytes")
        lines.append(
            f"| {r['case']} | {r['env']} | {r['num_envs']} | {r['rollout_len']} | {r['horizon']} | "
            f"{r['num_epochs']} x {r['num_minibatches']} | {r['seeds']} | {r['compile_s']} | "
            f"{r['env_steps_per_s']:,} | {ratio:.2f} | {peak / 2**30 if peak else float('nan'):.2f} |")
    return "\n".join(lines)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--cases", nargs="+", default=["ceiling", "model-free", "mbmf", "cd"],
                   choices=["ceiling", *CASES])
    p.add_argument("--env", default="ant")
    p.add_argument("--num-envs", type=int, default=4096)
    p.add_argument("--rollout-len", type=int, default=32)
    p.add_argument("--horizon", type=int, default=20)
    p.add_argument("--epochs", type=int, default=4)
    p.add_argument("--minibatches", type=int, default=32)
    p.add_argument("--seeds", type=int, default=1)
    p.add_argument("--updates", type=int, default=10, help="timed updates per case")
    p.add_argument("--tiny", action="store_true", help="CPU smoke sizes: point env, 16 envs")
    p.add_argument("--cache", default=os.environ.get("CDJAX_JAX_CACHE"), help="persistent compilation cache dir")
    p.add_argument("--out", help="write <out>.json and <out>.md")
    p.add_argument("--one", help=argparse.SUPPRESS)  # internal: run one case in this process
    args = p.parse_args(argv)
    if args.tiny:
        args.env, args.num_envs, args.rollout_len, args.horizon = "point", 16, 8, 4
        args.epochs, args.minibatches, args.updates = 2, 2, 3
    if args.one:
        print("RESULT " + json.dumps(run_case(args.one, args)), flush=True)
        return
    rows = []
    for case in args.cases:
        cmd = [sys.executable, __file__, "--one", case] + [a for a in (argv or sys.argv[1:])]
        proc = subprocess.run(cmd, capture_output=True, text=True)
        lines = [line for line in proc.stdout.splitlines() if line.startswith("RESULT ")]
        if proc.returncode != 0 or not lines:
            row = {"case": case, "error": (proc.stderr.strip().splitlines() or ["no output"])[-1]}
        else:
            row = json.loads(lines[-1][len("RESULT "):])
        print(json.dumps(row), flush=True)
        rows.append(row)
    md = table(rows)
    print(md)
    if args.out:
        with open(args.out + ".json", "w") as f:
            json.dump(rows, f, indent=1)
        with open(args.out + ".md", "w") as f:
            f.write(md + "\n")
    if any("error" in r for r in rows):
        sys.exit(1)


if __name__ == "__main__":
    main()
