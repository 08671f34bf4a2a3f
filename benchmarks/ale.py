"""ALE throughput in one process: cdjax's ALE sweep against ale-py's own vector environment at the same number of
emulators.

    python -m benchmarks.ale --out DIR            # GPU host: 16, 64 and 256 emulators, 16 per seed; a2c and a2c-cd
    python -m benchmarks.ale --tiny --out DIR     # CPU smoke (2 and 4 emulators, 2 per seed; numbers mean nothing)

For each total T of emulators (`--totals`), with E emulators per seed (`--envs-per-seed`), so T / E seeds:
- `ale-py`: ale-py's `AtariVectorEnv` of T emulators stepped from Python with random actions (`step(actions)`, the
  loop a Python A2C would run; no network), with the preset's preprocessing and one thread per core;
- `in jit`: cdjax's `AleEnv` stepped with random actions in a jitted `lax.scan`, vmapped over the T / E runs (their
  emulators folded into one vector environment of T): the emulators as cdjax drives them, without learning;
- `cdjax ARM`: the sweep of T / E seeds x E envs of the ALE preset's config (`cdjax.sweep.make_sweep`, one chunk
  program of `--chunk-updates` updates, timed after one warm-up chunk): acting, stepping and learning, all runs.

Rates are agent steps per second of all runs together (one agent step = `frame_skip` emulator frames); `vs ale-py`
is a case's rate over ale-py's at the same T. Each case is timed for about `--seconds`. Writes DIR/results.json
(rewritten after every case) and DIR/results.md, and prints the table.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import pathlib
import sys
import time

if __package__ in (None, ""):  # `python benchmarks/ale.py` as well as `python -m benchmarks.ale`
    sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

from benchmarks.common import Parser, device_info, refuse  # noqa: E402
from cdjax.options import positive, seconds  # noqa: E402

PROG = "python -m benchmarks.ale"

# CPU smoke sizes: the preset's config with small networks, short games and 2 emulators per seed (the ALE tests use
# the same config, so that the chunk program comes from the compilation cache).
TINY_CONFIG = dict(num_envs=2, latent=32, model_hidden=32, encoder_dim=8, episode_length=200)


def ale_presets() -> list[str]:
    """The atari setting's presets of ALE games (the names --game takes)."""
    from cdjax import agents
    from cdjax.agents.atari.config import ALE_PREFIX

    return [name for name, preset in agents.get("atari").presets.items()
            if str(preset.config.get("env", "")).startswith(ALE_PREFIX)]


def parse(argv):
    p = Parser(prog=PROG, description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter,
               epilog=__doc__)
    p.add_argument("--game", default="breakout", choices=ale_presets(), help="ALE preset (default breakout)")
    p.add_argument("--totals", type=positive, nargs="+", help="emulators in total (default 16 64 256; tiny 2 4)")
    p.add_argument("--envs-per-seed", type=positive, help="emulators per seed (default 16; tiny 2)")
    p.add_argument("--arms", nargs="+", default=["a2c", "a2c-cd"], help="cdjax arms (default a2c a2c-cd)")
    p.add_argument("--chunk-updates", type=positive, help="updates per timed call of a sweep (default 25; tiny 2)")
    p.add_argument("--seconds", type=seconds, help="timed seconds per case, at least 2 calls (default 20; tiny 0.5)")
    p.add_argument("--tiny", action="store_true", help="CPU smoke sizes")
    p.add_argument("--cache-dir", help="JAX's persistent compilation cache (default: $CDJAX_JAX_CACHE, else none)")
    p.add_argument("--out", help="output directory (default benchmarks/results/<date>-<device>-ale)")
    args = p.parse_args(argv)
    args.totals = args.totals or ([2, 4] if args.tiny else [16, 64, 256])
    args.envs_per_seed = args.envs_per_seed or (2 if args.tiny else 16)
    args.chunk_updates = args.chunk_updates or (2 if args.tiny else 25)
    args.seconds = args.seconds if args.seconds is not None else (0.5 if args.tiny else 20.0)
    bad = [t for t in args.totals if t % args.envs_per_seed]
    if bad:
        p.error(f"--totals {bad} are not multiples of --envs-per-seed {args.envs_per_seed}")
    return args


def preset_config(game: str, arm: str, envs_per_seed: int, tiny: bool):
    from cdjax import agents
    from cdjax.agents.atari import AtariConfig

    preset = agents.get("atari").presets[game]
    return AtariConfig(**{**preset.config, **(TINY_CONFIG if tiny else {}), "num_envs": envs_per_seed, "arm": arm})


def preset_hparams(game: str):
    from cdjax import agents
    from cdjax.agents.atari import AtariHParams

    return AtariHParams(**{k: v[0] for k, v in agents.get("atari").presets[game].hparams.items()})


def timed(call, seconds: float, min_calls: int = 2) -> tuple[int, float]:
    """Call `call()` (it blocks until done) until `seconds` have passed and at least `min_calls` calls: (calls, s)."""
    calls, t0 = 0, time.perf_counter()
    while calls < min_calls or time.perf_counter() - t0 < seconds:
        call()
        calls += 1
    return calls, time.perf_counter() - t0


def ale_py_python(config, total: int, seconds: float) -> dict:
    """ale-py's vector env of `total` emulators stepped from Python with random actions."""
    from ale_py.vector_env import AtariVectorEnv

    from cdjax.agents.atari.ale import vector_env

    env = vector_env(AtariVectorEnv, config, total)
    env.reset(seed=np.arange(total, dtype=np.int32))
    rng = np.random.default_rng(0)
    n = int(env.single_action_space.n)
    for _ in range(10):  # warm-up
        env.step(rng.integers(0, n, total, dtype=np.int32))
    steps = 50
    calls, wall = timed(lambda: [env.step(rng.integers(0, n, total, dtype=np.int32)) for _ in range(steps)], seconds)
    return {"agent_steps_per_s": total * steps * calls / wall, "calls": calls, "timed_s": wall}


def in_jit(config, seeds: int, seconds: float) -> dict:
    """cdjax's AleEnv stepped with random actions in a jitted scan, vmapped over `seeds` runs."""
    import jax

    from cdjax.agents.atari.ale import AleEnv

    env, steps = AleEnv(config, config.num_envs), 50

    def play(state, key):
        def step(state, key):
            action = jax.random.randint(key, (config.num_envs,), 0, env.num_actions)
            return env.step(state, action)[0], None

        return jax.lax.scan(step, state, jax.random.split(key, steps))[0]

    keys = jax.random.split(jax.random.key(0), seeds)
    t0 = time.perf_counter()
    state = jax.block_until_ready(jax.jit(jax.vmap(env.reset))(keys))
    run = jax.jit(jax.vmap(play), donate_argnums=0).lower(state, keys).compile()
    compile_s = time.perf_counter() - t0
    box = [jax.block_until_ready(run(state, keys))]

    def call():
        box[0] = jax.block_until_ready(run(box[0], keys))

    calls, wall = timed(call, seconds)
    return {"agent_steps_per_s": seeds * config.num_envs * steps * calls / wall, "calls": calls, "timed_s": wall,
            "compile_s": compile_s}


def cdjax_sweep(config, hp, seeds: int, chunk: int, seconds: float) -> dict:
    """The sweep of `seeds` runs of `config`: compile, one warm-up chunk, then timed chunks of `chunk` updates."""
    import jax
    import jax.numpy as jnp

    from cdjax.agents.atari import make_trainer
    from cdjax.runner import budget
    from cdjax.sweep import make_sweep

    sweep = make_sweep(make_trainer(config))
    keys, hps = sweep.grid(seed=0, num_seeds=seeds, hps=[hp])
    t0 = time.perf_counter()
    state = jax.block_until_ready(sweep.init(keys, hps))
    init_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    program, _ = budget.compile_fitting(sweep.lower_chunk(state, hps, chunk))  # as a sweep compiles it
    compile_s = time.perf_counter() - t0
    n = jnp.int32(chunk)
    box = [jax.block_until_ready(program(state, hps, n))]  # warm-up chunk

    def call():
        box[0] = jax.block_until_ready(program(box[0][0], hps, n))

    calls, wall = timed(call, seconds)
    returns = np.asarray(box[0][1]["episode/return"])
    steps = seeds * config.env_steps_per_update * chunk * calls
    return {"agent_steps_per_s": steps / wall, "calls": calls, "timed_s": wall, "compile_s": compile_s,
            "init_s": init_s, "mean_return": float(np.nanmean(returns)) if np.isfinite(returns).any() else None}


def markdown(rows: list[dict], meta: dict) -> str:
    base = {r["total_envs"]: r["agent_steps_per_s"] for r in rows if r["case"] == "ale-py" and r.get("agent_steps_per_s")}
    lines = ["| emulators | seeds x envs | case | agent steps/s | vs ale-py | compile s |", "|---:|---|---|---:|---:|---:|"]
    for r in rows:
        rate = r.get("agent_steps_per_s")
        ratio = f"{rate / base[r['total_envs']]:.2f}" if rate and base.get(r["total_envs"]) else ""
        shown = f"{rate:,.0f}" if rate else r.get("status", "")
        compile_s = f"{r['compile_s']:.1f}" if r.get("compile_s") is not None else ""
        lines.append(f"| {r['total_envs']} | {r['seeds']} x {r['envs_per_seed']} | {r['case']} | {shown} | {ratio} | "
                     f"{compile_s} |")
    lines += ["", f"{meta['game']}, {meta['device']} ({meta['platform']}), {meta['cpu_count']} CPU cores, ale-py "
              f"{meta['ale_py']}, jax {meta['versions'].get('jax')}; chunks of {meta['chunk_updates']} updates of "
              f"{meta['rollout_len']} steps; each case timed ~{meta['seconds']:g} s. Agent steps of all runs per "
              "second (x4 frames)."]
    return "\n".join(lines) + "\n"


def main(argv=None) -> dict:
    args = parse(argv)
    from cdjax import io, runtime

    runtime.apply_xla_defaults()  # before JAX's backends start (its XLA:CPU flag)
    from cdjax.protocol import ConfigError

    out = pathlib.Path(args.out) if args.out else None
    try:  # every arm's config first: without the `atari` extra, the install hint `cdjax sweep` gives
        configs = {arm: preset_config(args.game, arm, args.envs_per_seed, args.tiny) for arm in args.arms}
        if out is not None:
            io.RunDir(out).check_writable()
        cache = args.cache_dir or os.environ.get(runtime.CACHE_ENV)
        if cache:
            runtime.configure(cache_dir=cache, cache_source="--cache-dir" if args.cache_dir else f"${runtime.CACHE_ENV}")
    except (ConfigError, io.RunDirError) as err:
        refuse(PROG, str(err))
    import ale_py

    meta = {**device_info(), "game": args.game, "cpu_count": os.cpu_count(), "ale_py": ale_py.__version__,
            "chunk_updates": args.chunk_updates, "seconds": args.seconds, "tiny": args.tiny,
            "command": "python -m benchmarks.ale " + " ".join(argv if argv is not None else sys.argv[1:]),
            "date": datetime.date.today().isoformat()}
    base = configs[args.arms[0]]
    meta["rollout_len"] = base.rollout_len
    out = out or pathlib.Path(f"benchmarks/results/{meta['date']}-{meta['device'].replace(' ', '_')}-ale")
    out.mkdir(parents=True, exist_ok=True)
    rows: list[dict] = []

    def record(case: str, total: int, fn) -> None:
        row = {"case": case, "total_envs": total, "seeds": total // args.envs_per_seed, "envs_per_seed": args.envs_per_seed}
        if case == "ale-py":
            row.update(seeds=1, envs_per_seed=total)
        t0 = time.perf_counter()
        try:
            row.update(fn(), status="ok")
        except Exception as e:  # noqa: BLE001 - a failed case is a result; the others go on
            row["status"] = f"failed: {type(e).__name__}: {str(e).splitlines()[0][:200] if str(e) else ''}"
        row["case_wall_s"] = round(time.perf_counter() - t0, 2)
        rows.append(row)
        (out / "results.json").write_text(json.dumps({"meta": meta, "rows": rows}, indent=1, default=str))
        rate = row.get("agent_steps_per_s")
        print(f"{case} at {total} emulators: " + (f"{rate:,.0f} agent steps/s" if rate else row["status"]), flush=True)

    for total in args.totals:
        seeds = total // args.envs_per_seed
        record("ale-py", total, lambda t=total: ale_py_python(base, t, args.seconds))
        record("in jit", total, lambda s=seeds: in_jit(base, s, args.seconds))
        for arm, config in configs.items():
            record(f"cdjax {arm}", total, lambda c=config, s=seeds: cdjax_sweep(
                c, preset_hparams(args.game), s, args.chunk_updates, args.seconds))
    text = markdown(rows, meta)
    (out / "results.md").write_text(text)
    print(text)
    print(f"Wrote {out / 'results.json'} and {out / 'results.md'}")
    return {"meta": meta, "rows": rows}


if __name__ == "__main__":
    main()
