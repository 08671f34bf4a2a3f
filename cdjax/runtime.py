"""The one place for runtime switches: XLA workarounds, compilation cache, NaN checks, disabling jit.

`cdjax` applies the CPU workaround when it is imported (before JAX starts its backends); everything
else is opt-in through `configure`.
"""

from __future__ import annotations

import os

# XLA:CPU's concurrency-optimised scheduler deadlocks some of cdjax's vmapped programs on a 2-core
# machine (seen with jax 0.10.2: 6 vmapped runs of the point-mass agent hang in BlockUntilReady every
# time, 2, 4 and 8 do not; with this flag, or pinned to one core, they run). It only affects the CPU backend.
CPU_SCHEDULER_FLAG = "--xla_cpu_enable_concurrency_optimized_scheduler=false"


def apply_cpu_workaround() -> None:
    """Add the XLA:CPU scheduler flag to XLA_FLAGS unless the user set that option already."""
    flags = os.environ.get("XLA_FLAGS", "")
    if "xla_cpu_enable_concurrency_optimized_scheduler" not in flags:
        os.environ["XLA_FLAGS"] = f"{flags} {CPU_SCHEDULER_FLAG}".strip()


def configure(*, cache_dir: str | None = None, debug_nans: bool = False, disable_jit: bool = False,
              min_compile_time_s: float = 0.5) -> None:
    """Opt-in switches: persistent compilation cache, NaN checks on every op, jit off (for debugging)."""
    import jax

    if cache_dir:
        os.makedirs(cache_dir, exist_ok=True)
        jax.config.update("jax_compilation_cache_dir", cache_dir)
        jax.config.update("jax_persistent_cache_min_compile_time_secs", min_compile_time_s)
    jax.config.update("jax_debug_nans", debug_nans)
    jax.config.update("jax_disable_jit", disable_jit)
