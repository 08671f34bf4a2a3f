"""Does the Mb-Mf phase hand PPO a policy better than random actions? One seed, one task, variants side by side.

    python -m experiments.paper_obs_space.phase_check --task halfcheetah --variants best elite16 ... [--out FILE]

For each variant (a set of MbMfPhase overrides on the `paper-<task>` preset's phase, or on --phase-* given
here) the phase runs once from the same initial state, then every controller plays EVAL_STEPS steps in
`--envs` environments from the same reset states: uniform random actions, the zero action, the MPC on the
phase's final model, the distilled policy's mean action and the distilled policy sampling with PPO's initial
noise (what PPO's first rollout plays). Printed and written (--out, JSON): the reward per step of each, and
the phase's diagnostics (labels/*, distill/*: how noisy the MPC's labels are and how close the policy came to
their mean). Sizes can be shrunk for a CPU (--phase-* options, --envs, --steps).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time

VARIANTS = {  # name -> MbMfPhase overrides
    "best": dict(mpc_elites=1),
    "elite16": dict(mpc_elites=16),
    "elite64": dict(mpc_elites=64),
    "true-best": dict(mpc_reward="true", mpc_elites=1),
    "true-elite16": dict(mpc_reward="true", mpc_elites=16),
    "true-elite64": dict(mpc_reward="true", mpc_elites=64),
    "det-dagger": dict(dagger_deterministic=True),
    "onpolicy": dict(onpolicy_fraction=0.9),
    # all of Nagabandi et al.'s that the phase offers, with elite-mean labels
    "nagabandi-elite16": dict(mpc_reward="true", mpc_elites=16, dagger_deterministic=True, onpolicy_fraction=0.9),
    "nagabandi-elite64": dict(mpc_reward="true", mpc_elites=64, dagger_deterministic=True, onpolicy_fraction=0.9),
}
SOURCES = ("random", "zero", "mpc", "policy-mean", "policy-sampled")


def check(task: str, variants: list[str], phase_overrides: dict, envs: int, steps: int, seed: int = 0,
          config_overrides: dict | None = None) -> dict:
    import jax
    import jax.numpy as jnp

    from cdjax import HParams, make_agent
    from cdjax.agents.obs import PRESETS, Config
    from cdjax.agents.obs.mbmf import MbMfPhase, make_mbmf_phase, make_mpc_controller

    preset = PRESETS[f"paper-{task}"]
    config = Config(**{**preset.config, "num_envs": envs, "eval_envs": min(envs, 8), **(config_overrides or {})})
    hp = HParams(**{k: v[0] for k, v in preset.hparams.items()})
    agent = make_agent(config)
    start = jax.jit(agent.init)(jax.random.key(seed), hp)
    env = agent.env
    out = {"task": task, "envs": envs, "steps": steps, "variants": {}}
    for name in variants:
        phase = MbMfPhase(**{**preset.phase, **phase_overrides, **VARIANTS[name]})
        t0 = time.perf_counter()
        state, info = jax.jit(make_mbmf_phase(config, phase, agent))(start, hp)
        info = {k: float(v) for k, v in info.items()}
        took = time.perf_counter() - t0
        controller = make_mpc_controller(agent, phase)

        @jax.jit
        def play(source, state, key):
            def step(env_state, k):
                obs = env_state.obs
                shape = obs.shape[:1] + (env.action_size,)
                action = jax.lax.switch(source, [
                    lambda: jax.random.uniform(k, shape, minval=-1.0, maxval=1.0),
                    lambda: jnp.zeros(shape),
                    lambda: controller(state.params["model"], state.norms, obs, k),
                    lambda: agent.act(state.params, state.norms, obs, None),
                    lambda: agent.act(state.params, state.norms, obs, k),
                ])
                env_state, o = env.step(env_state, action)
                return env_state, jnp.where(o.valid, o.reward, jnp.nan)

            return jax.lax.scan(step, env.reset(jax.random.key(1000 + seed)), jax.random.split(key, steps))[1]

        rewards = {src: float(jnp.nanmean(play(i, state, jax.random.key(7)))) for i, src in enumerate(SOURCES)}
        out["variants"][name] = {"phase": dataclasses.asdict(phase), "phase_s": round(took, 1),
                                 "reward_per_step": rewards, "info": info}
        print(f"{name}: phase {took:.0f} s (compile included); reward/step "
              + ", ".join(f"{k} {v:.3f}" for k, v in rewards.items())
              + f"; labels: self-error {info['labels/self_error']:.3f}, |mean| {info['labels/mean_abs']:.3f}; "
              f"policy to mean label {info['distill/abs_error_mean']:.3f} (zero action "
              f"{info['distill/abs_error_zero']:.3f}); to single labels {info['distill/abs_error']:.3f}", flush=True)
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m experiments.paper_obs_space.phase_check", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--task", required=True)
    p.add_argument("--variants", nargs="+", default=["best", "elite16"], choices=sorted(VARIANTS))
    p.add_argument("--envs", type=int, default=16, help="environments of the evaluation rollouts (and PPO's)")
    p.add_argument("--steps", type=int, default=200, help="steps of each evaluation rollout")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--phase", nargs="*", default=[], metavar="FIELD=VALUE",
                   help="MbMfPhase overrides for every variant, e.g. num_envs=16 random_steps=200")
    p.add_argument("--out", help="write the results here (JSON)")
    args = p.parse_args(argv)
    import experiments  # noqa: F401  (cdjax's XLA flags before anything runs)
    from cdjax.agents.obs.mbmf import MbMfPhase

    types = {f.name: f.type for f in dataclasses.fields(MbMfPhase)}
    overrides = {}
    for item in args.phase:
        key, value = item.split("=", 1)
        kind = types[key]
        overrides[key] = (value.lower() in ("1", "true") if kind == "bool" else
                          int(value) if kind == "int" else float(value) if kind == "float" else value)
    result = check(args.task, args.variants, overrides, args.envs, args.steps, args.seed)
    if args.out:
        with open(args.out, "w") as f:
            json.dump(result, f, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
