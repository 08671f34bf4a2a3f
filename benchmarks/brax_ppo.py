"""Brax's own PPO trainer (`brax.training.agents.ppo.train.train`) at the matched config, timed by
Brax's own per-epoch timer.

What is timed. Brax's training loop calls its pmapped `training_epoch` (a lax.scan of
`steps_per_epoch` training steps; each collects spec.env_steps_per_update env steps and runs
num_epochs x num_minibatches SGD minibatches) once per evaluation interval, timing each call until
its metrics are ready and reporting `training/sps` to `progress_fn`. Evaluation is off
(run_evals=False), so nothing else runs inside the timed region. The first `warmup_epochs` epochs are
discarded: the first includes compilation, and Brax 0.14.2 compiles `training_epoch` a second time on
its second call (the env state's pytree changes after the first epoch; seen with jax_log_compiles).
Steady state is the median of the remaining epochs; `compile_s` is estimated as the warm-up epochs'
time minus as many steady epochs. One device (max_devices_per_host=1), like the cdjax rows.

Brax 0.14.2 calls `jax.device_put_replicated`, which current JAX removed; `install_shim` defines it
with `jnp.stack` (replicas stacked on a new leading axis, which pmap then splits over devices).
"""

from __future__ import annotations

import functools
import time

from benchmarks.common import Spec, median, process_peak


def install_shim() -> bool:
    """Define jax.device_put_replicated if this JAX lacks it; returns whether the shim was installed."""
    import jax
    import jax.numpy as jnp

    if hasattr(jax, "device_put_replicated"):
        return False

    def device_put_replicated(x, devices):
        return jax.tree.map(lambda a: jnp.stack([jnp.asarray(a)] * len(devices)), x)

    jax.device_put_replicated = device_put_replicated
    return True


def brax_ppo(spec: Spec, steps_per_epoch: int = 2, steady_epochs: int = 3, warmup_epochs: int = 2) -> dict:
    shim = install_shim()
    from brax.training.agents.ppo import networks as ppo_networks
    from brax.training.agents.ppo import train as ppo

    from cdjax.envs import make_single_env

    env = make_single_env(spec.env)  # brax.envs.get_environment(name, backend="mjx") for Brax tasks
    epochs = warmup_epochs + steady_epochs
    per_step = spec.env_steps_per_update
    per_epoch = steps_per_epoch * per_step
    records: list[tuple[float, int, float]] = []

    def progress(step, metrics):
        records.append((time.perf_counter(), int(step), float(metrics["training/sps"])))

    network_factory = functools.partial(ppo_networks.make_ppo_networks,
                                        policy_hidden_layer_sizes=spec.policy_hidden,
                                        value_hidden_layer_sizes=spec.value_hidden)
    kwargs = spec.brax_kwargs()
    t0 = time.perf_counter()
    ppo.train(environment=env, num_timesteps=epochs * per_epoch, num_evals=epochs + 1, run_evals=False,
              progress_fn=progress, max_devices_per_host=1, seed=0, network_factory=network_factory, **kwargs)
    total_s = time.perf_counter() - t0
    if len(records) != epochs or any(r[1] != (i + 1) * per_epoch for i, r in enumerate(records)):
        raise RuntimeError(f"Brax ran {[r[1] for r in records]} env steps at its callbacks; expected "
                           f"{epochs} epochs of {per_epoch}: the epoch arithmetic of this brax version differs.")
    epoch_s = [per_epoch / sps for _, _, sps in records]
    steady_s = median(epoch_s[warmup_epochs:])
    walls = [b[0] - a[0] for a, b in zip(records[warmup_epochs:], records[warmup_epochs + 1:])]
    return {
        "case": "brax-ppo", "kind": "brax", "env": spec.env, "num_envs": spec.num_envs, "seeds": 1,
        "rollout_len": spec.rollout_len, "status": "ok",
        "what": (f"brax.training.agents.ppo: unroll {spec.unroll_length}, batch {spec.batch_size}, "
                 f"{spec.num_minibatches} minibatches x {spec.num_epochs} epochs"),
        "env_class": type(env).__name__, "brax_kwargs": kwargs, "shim_installed": shim,
        "steps_per_epoch": steps_per_epoch, "epoch_s_all": [round(s, 5) for s in epoch_s],
        "update_s": steady_s / steps_per_epoch, "steps_per_update": per_step,
        "env_steps_per_s": per_epoch / steady_s,
        "env_steps_per_s_wall": per_epoch / median(walls) if walls else None,
        "compile_s": sum(epoch_s[:warmup_epochs]) - warmup_epochs * steady_s,
        "train_call_s": total_s,
        "mem_bytes": process_peak(), "mem_source": "process-peak", "process_peak_bytes": process_peak(),
    }
