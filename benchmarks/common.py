"""What every benchmark part shares: the matched configuration, timing, memory and device facts.

The matched configuration is written once, in Brax PPO's terms (`Spec`), and translated to both
trainers, so that Brax PPO and cdjax collect the same environment steps per update and run the same
SGD schedule:

    Brax: each training step collects batch_size * num_minibatches / num_envs unrolls of
          unroll_length steps per env, then num_epochs ("num_updates_per_batch") x num_minibatches
          minibatches of batch_size sequences of unroll_length steps;
    cdjax: rollout_len = unroll_length * batch_size * num_minibatches / num_envs steps per env, then
          num_epochs x num_minibatches minibatches of num_envs / num_minibatches envs x rollout_len steps.

At the default (ant, 4096 envs, unroll 20, batch 512, 32 minibatches, 8 epochs) both take
327,680 env steps per update and SGD over 8 x 32 minibatches of 10,240 samples.
"""

from __future__ import annotations

import dataclasses
import gc
import math
import os
import pathlib
import statistics
import sys
import time
from typing import Any, Callable, NoReturn

from cdjax import cli

# Brax's ppo_networks.make_ppo_networks defaults (brax 0.14.2): policy (32,)*4, value (256,)*5.
BRAX_POLICY_HIDDEN = (32,) * 4
BRAX_VALUE_HIDDEN = (256,) * 5


class Parser(cli.Parser):
    """The `cdjax` command's parser (one line, no usage block) for a benchmark's own `main`, which no `cdjax` main
    catches for: `<prog>: <one sentence>` on stderr and exit status 2. Counts take cdjax.options' types
    (`positive`, `non_negative`, `seconds`)."""

    def error(self, message: str) -> NoReturn:
        try:
            super().error(message)
        except cli.UsageError as err:
            refuse(self.prog, str(err))


def refuse(prog: str, sentence: str) -> NoReturn:
    """End a command that cannot run as asked: `<prog>: <sentence>.` on stderr and exit status 2."""
    print(f"{prog}: {sentence.rstrip('.')}.", file=sys.stderr)
    raise SystemExit(2)


def unwritable_file(path: str | pathlib.Path) -> str | None:
    """Why a file could not be written at `path` (a clause naming it), or None; touches nothing. An output file's
    directory is not made for it (a mistyped one would be): it must exist."""
    path = pathlib.Path(path)
    folder = path.absolute().parent
    if path.is_dir():
        return f"{path} is a directory; name a file"
    if not folder.exists():
        return f"its directory {folder} does not exist"
    if not folder.is_dir():
        return f"{folder} is a file, not a directory"
    if not os.access(folder, os.W_OK | os.X_OK):
        return f"cannot write into {folder}"
    return None


@dataclasses.dataclass(frozen=True)
class Spec:
    """One benchmark configuration in Brax PPO's terms; `config()` and `brax_kwargs()` translate it."""

    env: str = "ant"  # task name, both in cdjax.envs and brax.envs (backend="mjx")
    num_envs: int = 4096  # environments stepped in parallel (per seed)
    unroll_length: int = 20  # Brax unroll length; cdjax's consistency horizon is separate (`horizon`)
    batch_size: int = 512  # Brax: sequences per minibatch
    num_minibatches: int = 32  # minibatches per epoch (both)
    num_epochs: int = 8  # SGD passes over each rollout (Brax: num_updates_per_batch)
    horizon: int = 20  # cdjax k: open-loop length of the consistency windows
    episode_length: int = 1000  # time-out in physics steps (both)
    action_repeat: int = 1  # physics steps per agent step (both)
    discounting: float = 0.97  # gamma (both)
    reward_scaling: float = 10.0  # reward multiplier seen by the learner (both)
    entropy_cost: float = 1e-2  # entropy bonus weight (both)
    learning_rate: float = 3e-4  # Adam learning rate (Brax: one optimiser; cdjax: policy and value alike)
    clipping_epsilon: float = 0.3  # PPO ratio clipping (Brax's default)
    max_grad_norm: float | None = 1.0  # gradient clipping (Brax: global; cdjax: per parameter group); None: none
    policy_hidden: tuple[int, ...] = BRAX_POLICY_HIDDEN  # policy MLP widths (both)
    value_hidden: tuple[int, ...] = BRAX_VALUE_HIDDEN  # value MLP widths (both)
    model_hidden: tuple[int, ...] = (500,)  # cdjax dynamics model widths (Mb-Mf: one layer of 500)
    encoder_dim: int = 128  # cdjax GRU size
    eval_envs: int = 8  # cdjax: envs whose history feeds the open-loop error metrics
    eval_horizon: int = 50  # cdjax: long open-loop horizon of that metric

    def __post_init__(self):
        if (self.batch_size * self.num_minibatches) % self.num_envs:
            raise ValueError(f"batch_size * num_minibatches = {self.batch_size * self.num_minibatches} is not a "
                             f"multiple of num_envs = {self.num_envs} (Brax needs whole unrolls per env).")

    @property
    def unrolls_per_env(self) -> int:
        return self.batch_size * self.num_minibatches // self.num_envs

    @property
    def rollout_len(self) -> int:
        """cdjax T: the env steps per env per update."""
        return self.unroll_length * self.unrolls_per_env

    @property
    def env_steps_per_update(self) -> int:
        """Physics steps per update (Brax counts env steps x action_repeat)."""
        return self.num_envs * self.rollout_len * self.action_repeat

    @property
    def samples_per_minibatch(self) -> int:
        return self.batch_size * self.unroll_length

    def with_num_envs(self, num_envs: int) -> "Spec":
        """The same rollout length and SGD schedule at another num_envs (batch_size follows)."""
        batch = num_envs * self.unrolls_per_env // self.num_minibatches
        return dataclasses.replace(self, num_envs=num_envs, batch_size=batch)

    def config(self, **overrides):
        """The cdjax Config of this spec (overrides: arm, cc_windows, ...).

        Minibatches are made of sequences of `unroll_length` steps (segment_len), as Brax's are.
        """
        from cdjax import Config

        fields = dict(env=self.env, num_envs=self.num_envs, rollout_len=self.rollout_len,
                      segment_len=self.unroll_length, horizon=min(self.horizon, self.unroll_length),
                      num_epochs=self.num_epochs, num_minibatches=self.num_minibatches,
                      episode_length=self.episode_length, action_repeat=self.action_repeat,
                      policy_hidden=self.policy_hidden, value_hidden=self.value_hidden,
                      model_hidden=self.model_hidden, encoder_dim=self.encoder_dim, eval_envs=self.eval_envs,
                      eval_horizon=self.eval_horizon)
        return Config(**{**fields, **overrides})

    def hparams(self, **overrides):
        """The cdjax HParams of this spec (Brax's value loss 0.25 * err^2 is cdjax's vf_coef 0.5 * 0.5 * err^2)."""
        from cdjax import HParams

        fields = dict(gamma=self.discounting, reward_scale=self.reward_scaling, ent_coef=self.entropy_cost,
                      lr_policy=self.learning_rate, lr_value=self.learning_rate, clip_eps=self.clipping_epsilon,
                      max_grad_norm=1e30 if self.max_grad_norm is None else self.max_grad_norm, gae_lambda=0.95,
                      vf_coef=0.5)
        return HParams(**{**fields, **overrides})

    def brax_kwargs(self) -> dict:
        """Arguments of brax.training.agents.ppo.train.train for this spec."""
        return dict(num_envs=self.num_envs, unroll_length=self.unroll_length, batch_size=self.batch_size,
                    num_minibatches=self.num_minibatches, num_updates_per_batch=self.num_epochs,
                    episode_length=self.episode_length, action_repeat=self.action_repeat,
                    normalize_observations=True, max_grad_norm=self.max_grad_norm,
                    learning_rate=self.learning_rate, entropy_cost=self.entropy_cost,
                    discounting=self.discounting, reward_scaling=self.reward_scaling,
                    clipping_epsilon=self.clipping_epsilon, gae_lambda=0.95)

    def describe(self) -> dict:
        return {**dataclasses.asdict(self), "unrolls_per_env": self.unrolls_per_env, "rollout_len": self.rollout_len,
                "env_steps_per_update": self.env_steps_per_update,
                "samples_per_minibatch": self.samples_per_minibatch}


FULL = Spec()
# CPU smoke sizes: cdjax's pure-JAX point mass (it has the Brax Env interface, so Brax PPO runs on it too).
TINY = Spec(env="point", num_envs=16, unroll_length=4, batch_size=16, num_minibatches=2, num_epochs=2, horizon=4,
            episode_length=100, policy_hidden=(16,), value_hidden=(16,), model_hidden=(32,), encoder_dim=8,
            eval_envs=2, eval_horizon=10)


@dataclasses.dataclass
class Timing:
    """How a case is timed: warm-up calls, then up to `updates` timed calls, stopping early (after at
    least `min_updates`) once the timed calls have used `max_seconds`."""

    updates: int = 5
    min_updates: int = 2
    max_seconds: float = 20.0
    warmup: int = 1


def time_calls(step: Callable[[Any], Any], carry: Any, timing: Timing) -> tuple[Any, list[float]]:
    """Call `carry = step(carry)` with a device sync after each; returns (carry, seconds of timed calls).

    `step` must return the new carry; everything it returns is blocked on.
    """
    import jax

    for _ in range(timing.warmup):
        carry = jax.block_until_ready(step(carry))
    times: list[float] = []
    while len(times) < timing.updates:
        t0 = time.perf_counter()
        carry = jax.block_until_ready(step(carry))
        times.append(time.perf_counter() - t0)
        if len(times) >= timing.min_updates and sum(times) > timing.max_seconds:
            break
    return carry, times


def compile_timed(jitted, *args, ours: bool = True) -> tuple[Any, float, float, bool]:
    """(compiled, lower seconds, compile seconds, in program order): tracing/lowering and XLA compilation timed apart.
    `ours`: compiled as cdjax compiles its programs (cdjax.runner.budget.compile_fitting: runtime.compiler_options,
    the GPU's kernels in program order only where the program would not fit beside what the device holds), else
    with XLA's own options (a reference such as the raw physics)."""
    from cdjax.runner import budget

    t0 = time.perf_counter()
    lowered = jitted.lower(*args)
    t1 = time.perf_counter()
    compiled, in_order = budget.compile_fitting(lowered) if ours else (lowered.compile(), False)
    t2 = time.perf_counter()
    return compiled, t1 - t0, t2 - t1, in_order


def compiled_footprint(compiled) -> int | None:
    """Device bytes one call of a compiled program holds at its peak, by XLA's buffer assignment:
    arguments + outputs - donated aliases + temporaries (per device when sharded). None if unknown."""
    try:
        m = compiled.memory_analysis()
        return int(m.argument_size_in_bytes + m.output_size_in_bytes - m.alias_size_in_bytes + m.temp_size_in_bytes)
    except Exception:  # noqa: BLE001 - a backend without memory analysis (or None): unknown
        return None


def memory_stats() -> dict:
    import jax

    try:
        return jax.local_devices()[0].memory_stats() or {}
    except Exception:  # noqa: BLE001
        return {}


def process_peak() -> int | None:
    """Process-wide peak device bytes of device 0 (monotone over the process; None on CPU)."""
    return memory_stats().get("peak_bytes_in_use")


def bytes_limit() -> int | None:
    return memory_stats().get("bytes_limit")


def is_oom(error: BaseException) -> bool:
    text = f"{type(error).__name__}: {error}"
    return any(s in text for s in ("RESOURCE_EXHAUSTED", "Out of memory", "out of memory", "OOM"))


def median(xs: list[float]) -> float:
    return float(statistics.median(xs))


def steady(times: list[float], steps: int) -> dict:
    """Summary of timed calls that each take `steps` env steps."""
    med = median(times)
    return {"update_s": med, "update_s_all": [round(t, 5) for t in times],
            "env_steps_per_s": steps / med, "steps_per_update": steps}


def cleanup():
    gc.collect()


def gpu_count() -> int:
    """The host's GPUs as `nvidia-smi -L` lists them (0 where it cannot run), without starting JAX."""
    import subprocess

    try:
        listed = subprocess.run(["nvidia-smi", "-L"], capture_output=True, text=True, timeout=60).stdout
    except (OSError, subprocess.TimeoutExpired):
        return 0
    return sum(line.startswith("GPU ") for line in listed.splitlines())


def device_info() -> dict:
    import jax

    from cdjax import runtime

    devs = jax.devices()
    versions = {**runtime.versions(backend=False), **{name: runtime.installed(name) for name in ("flax", "optax")}}
    return {
        "device": getattr(devs[0], "device_kind", str(devs[0])),
        "platform": devs[0].platform,
        "device_count": jax.device_count(),
        "local_device_count": jax.local_device_count(),
        "process_count": jax.process_count(),
        "bytes_limit": bytes_limit(),
        "versions": versions,
        "xla_flags": os.environ.get("XLA_FLAGS", ""),
        # what cdjax's own programs are compiled with beside the flags (compile mode, data-flow scheduling)
        "compile_mode": runtime.compile_mode(),
        "compiler_options": runtime.compiler_options(),
        "mem_fraction": os.environ.get("XLA_PYTHON_CLIENT_MEM_FRACTION", ""),
        "preallocate": os.environ.get("XLA_PYTHON_CLIENT_PREALLOCATE", ""),
    }


def process_started_at() -> float | None:
    """When this process was launched (Unix time, the kernel's record: before Python's imports), or None where
    /proc does not say (not Linux)."""
    try:
        ticks = int(pathlib.Path("/proc/self/stat").read_text().rsplit(")", 1)[1].split()[19])  # field 22: starttime
        boot = next(float(line.split()[1]) for line in pathlib.Path("/proc/stat").read_text().splitlines()
                    if line.startswith("btime "))
        return boot + ticks / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError, StopIteration):
        return None


def finite(x: float | None) -> bool:
    return x is not None and isinstance(x, (int, float)) and math.isfinite(x)
