"""Shared test setup: JAX's persistent compilation cache (MJX compiles slowly on CPU), through cdjax.runtime."""

import os
import pathlib

from cdjax import runtime

CACHE = pathlib.Path(os.environ.get(runtime.CACHE_ENV, pathlib.Path(__file__).resolve().parents[1] / ".jax_cache"))
runtime.configure(cache_dir=CACHE)
