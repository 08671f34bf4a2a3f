"""Shared test setup: JAX's persistent compilation cache (MJX compiles slowly on CPU)."""

import os
import pathlib

import jax

CACHE = pathlib.Path(os.environ.get("CDJAX_JAX_CACHE", pathlib.Path(__file__).resolve().parents[1] / ".jax_cache"))
CACHE.mkdir(exist_ok=True)
jax.config.update("jax_compilation_cache_dir", str(CACHE))
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)
