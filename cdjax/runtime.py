"""The one place for runtime switches: XLA workarounds, the compilation cache, NaN checks, disabling jit.

`cdjax` applies the CPU workaround when it is imported (before JAX starts its backends). Everything else
goes through `configure`, which the CLI (--cache-dir, --debug-nans, --disable-jit), the tests, the
benchmarks and the examples call:

    cdjax.runtime.configure(cache_dir=cdjax.runtime.default_cache_dir())
"""

from __future__ import annotations

import os
import pathlib
import warnings

# XLA:CPU's concurrency-optimised scheduler deadlocks some of cdjax's vmapped programs on a 2-core
# machine (seen with jax 0.10.2: 6 vmapped runs of the point-mass agent hang in BlockUntilReady every
# time, 2, 4 and 8 do not; with this flag, or pinned to one core, they run). It only affects the CPU backend.
CPU_SCHEDULER_FLAG = "--xla_cpu_enable_concurrency_optimized_scheduler=false"
CACHE_ENV = "CDJAX_JAX_CACHE"  # environment variable naming the persistent compilation cache


def apply_cpu_workaround() -> None:
    """Add the XLA:CPU scheduler flag to XLA_FLAGS unless the user set that option already."""
    flags = os.environ.get("XLA_FLAGS", "")
    if "xla_cpu_enable_concurrency_optimized_scheduler" not in flags:
        os.environ["XLA_FLAGS"] = f"{flags} {CPU_SCHEDULER_FLAG}".strip()


def default_cache_dir() -> str:
    """$CDJAX_JAX_CACHE, else ~/.cache/cdjax/jax."""
    return os.environ.get(CACHE_ENV, str(pathlib.Path.home() / ".cache" / "cdjax" / "jax"))


def configure(*, cache_dir: str | os.PathLike | None = None, debug_nans: bool = False, disable_jit: bool = False,
              min_compile_time_s: float = 0.5) -> None:
    """Persistent compilation cache (programs compiling longer than `min_compile_time_s` are kept), NaN
    checks on every operation, jit off (for debugging); and no Brax deprecation notice on every run."""
    import jax

    warnings.filterwarnings("ignore", message="Brax System", category=UserWarning)
    if cache_dir:
        os.makedirs(cache_dir, exist_ok=True)
        jax.config.update("jax_compilation_cache_dir", str(cache_dir))
        jax.config.update("jax_persistent_cache_min_compile_time_secs", min_compile_time_s)
    jax.config.update("jax_debug_nans", debug_nans)
    jax.config.update("jax_disable_jit", disable_jit)
