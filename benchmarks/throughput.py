"""Steady-state throughput of one case, in this process: the MJX ceiling, cdjax's rollout alone, and
cdjax's update for each arm and consistency setting.

Every function returns one result row (a flat dict); `benchmarks.run` strings them into suites.
A case compiles its jitted function once with `jit(f).lower(*args).compile()` (lower and XLA
compile seconds recorded apart), runs `Timing.warmup` calls, then times calls one by one with a
device sync after each; `env_steps_per_s` is env steps per call / the median call. The memory of a
case is XLA's buffer assignment of the compiled call (`common.compiled_footprint`).
"""

from __future__ import annotations

import os
from typing import Callable

from benchmarks.common import Spec, Timing, compile_timed, compiled_footprint, process_peak, steady, time_calls

# cdjax cases at the matched config: name -> (description, Config overrides, HParams overrides).
# cc_unroll is the horizon k (the whole k-step open-loop scan unrolled).
DESIGNATED_CD = "cd-fast"  # the row the CD targets are evaluated on
PAPER_CD = "cd-paper"  # the paper's schedule (l_cc in every SGD step): its wall-clock against Mb-Mf's is a target


def cdjax_cases(spec: Spec) -> dict[str, tuple[str, dict, dict]]:
    k = min(spec.horizon, spec.unroll_length)
    w = min(2, spec.unroll_length - k + 1)  # windows per sequence of unroll_length steps
    # The paper adds alpha * l_cc to the loss of every gradient step, over the k-step sub-sequences of the sampled
    # trajectories: every window of every sequence (L - k + 1 of them; one at the matched spec, where L = k = 20).
    n = spec.unroll_length - k + 1
    return {
        "model-free": ("PPO only, no model", dict(arm="model-free"), dict()),
        "mbmf": ("PPO + model NLL, alpha = 0 (Mb-Mf)", dict(arm="mbmf"), dict(alpha=0.0)),
        "cd-fast": (f"CD k={k}: {w} windows/sequence/minibatch, unroll {k}, consistency in epoch 1 only",
                    dict(arm="cd", cc_windows=w, cc_unroll=k, cc_epochs=1), dict(alpha=1.0)),
        "cd-paper": (f"CD k={k}, the paper's schedule: l_cc in every minibatch of every epoch, all {n} "
                     f"window(s)/sequence, unroll {k}", dict(arm="cd", cc_windows=0, cc_unroll=k, cc_epochs=0),
                     dict(alpha=1.0)),
        "cd-w2-unroll": (f"CD k={k}: {w} windows/sequence/minibatch, unroll {k}, every epoch",
                         dict(arm="cd", cc_windows=w, cc_unroll=k), dict(alpha=1.0)),
        "cd-default": (f"CD k={k}: default settings (all windows, every epoch, unroll 1)",
                       dict(arm="cd"), dict(alpha=1.0)),
    }


def _row(kind: str, case: str, spec: Spec, **fields) -> dict:
    return {"case": case, "kind": kind, "env": spec.env, "num_envs": spec.num_envs, "seeds": 1,
            "rollout_len": spec.rollout_len, "status": "ok", **fields}


def ceiling(spec: Spec, timing: Timing, length: int = 200) -> dict:
    """Raw MJX stepping: `length`-step lax.scan of vmapped env.step with uniform random actions in [-1, 1]
    (no policy, no auto-reset, no NaN guard) over spec.num_envs copies of the single env."""
    import jax
    import jax.numpy as jnp

    from cdjax.envs import make_single_env

    env = make_single_env(spec.env)
    B = spec.num_envs
    strong = lambda t: jax.tree.map(lambda x: jnp.asarray(x, x.dtype), t)  # noqa: E731
    state = strong(jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.key(0), B)))

    def roll(state, key):
        key, key_scan = jax.random.split(key)

        def body(s, k):
            a = jax.random.uniform(k, (B, env.action_size), minval=-1.0, maxval=1.0)
            return strong(jax.vmap(env.step)(s, a)), None

        return jax.lax.scan(body, state, jax.random.split(key_scan, length))[0], key

    compiled, lower_s, compile_s, _ = compile_timed(jax.jit(roll, donate_argnums=0), state, jax.random.key(1),
                                                   ours=False)  # the physics as XLA compiles it
    _, times = time_calls(lambda c: compiled(*c), (state, jax.random.key(1)), timing)
    return _row("ceiling", "ceiling", spec, what=f"raw MJX env.step, random actions, {length}-step scan",
                lower_s=lower_s, xla_compile_s=compile_s, compile_s=lower_s + compile_s,
                **steady(times, B * length), mem_bytes=compiled_footprint(compiled), mem_source="compiled",
                process_peak_bytes=process_peak())


def collect(spec: Spec, timing: Timing) -> dict:
    """cdjax's closed-loop rollout alone (policy + value forward, env layer with auto-reset and NaN
    guard, GAE) at the matched config: the rollout share of every arm's update."""
    import jax

    from cdjax import make_agent

    config = spec.config(arm="model-free")
    trainer = make_agent(config)
    hp = spec.hparams().as_float32()
    state = jax.jit(trainer.init)(jax.random.key(0), hp)

    def f(state, hp):
        key, key_roll = jax.random.split(state.key)
        env_state, episodes, _, batch = trainer.collect(state, hp, key_roll)
        return state.replace(env_state=env_state, episodes=episodes, key=key), batch

    compiled, lower_s, compile_s, in_order = compile_timed(jax.jit(f, donate_argnums=0), state, hp)
    _, times = time_calls(lambda c: compiled(c[0], hp), (state, None), timing)
    return _row("collect", "collect", spec, what=f"cdjax rollout of {config.rollout_len} steps + GAE, no learning",
                in_order=in_order, lower_s=lower_s, xla_compile_s=compile_s, compile_s=lower_s + compile_s,
                **steady(times, config.env_steps_per_update), mem_bytes=compiled_footprint(compiled),
                mem_source="compiled", process_peak_bytes=process_peak())


def cdjax_update(spec: Spec, case: str, timing: Timing, trace_dir: str | None = None) -> dict:
    """One jitted cdjax update (rollout + GAE + epochs x minibatches of SGD), one seed, default device."""
    import jax
    import jax.numpy as jnp

    from cdjax import make_agent

    what, overrides, hp_overrides = cdjax_cases(spec)[case]
    config = spec.config(**overrides)
    trainer = make_agent(config)
    hp = spec.hparams(**hp_overrides).as_float32()
    state = jax.jit(trainer.init)(jax.random.key(0), hp)
    compiled, lower_s, compile_s, in_order = compile_timed(jax.jit(trainer.update, donate_argnums=0), state, hp)
    step: Callable = lambda c: compiled(c[0], hp)  # noqa: E731
    carry, times = time_calls(step, (state, None), timing)
    traced = {}
    if trace_dir:
        from benchmarks import profile_summary

        traced["trace_dir"] = os.path.join(trace_dir, case)
        with profile_summary.trace(traced["trace_dir"], compiled):  # perfetto JSON + HLO text for the summary
            carry = jax.block_until_ready(step(carry))
    metrics = carry[1]
    ok = all(bool(jnp.isfinite(v).all()) for name, v in metrics.items() if name.startswith("loss/"))
    return _row("cdjax", case, spec, what=what, arm=config.arm, overrides=overrides, alpha=hp_overrides.get("alpha"),
                num_windows=config.num_windows if config.use_consistency else 0,
                sgd_steps=config.num_epochs * config.num_minibatches,
                in_order=in_order,
                lower_s=lower_s, xla_compile_s=compile_s, compile_s=lower_s + compile_s,
                **steady(times, config.env_steps_per_update), mem_bytes=compiled_footprint(compiled),
                mem_source="compiled", process_peak_bytes=process_peak(), finite=ok, **traced)
