"""Shared test setup: JAX's persistent compilation cache (MJX compiles slowly on CPU), through cdjax.runtime, and
XLA's CPU backend at optimisation level 0 for the whole test session (and the processes it starts, which inherit
XLA_FLAGS): the tests' programs are tiny and compiling them is most of the suite's time; level 0 compiles them in
about half the time (test_train's compile-once tests: 96 s -> 47 s) and computes the same operations, so every
comparison the tests make (vmapped against alone, resumed against uninterrupted, fused against scanned) is made
between programs compiled alike. Set CDJAX_TEST_XLA_OPT=default to test with XLA's own optimisation level."""

import os
import pathlib

if os.environ.get("CDJAX_TEST_XLA_OPT", "0") != "default" and "xla_backend_optimization_level" not in os.environ.get(
        "XLA_FLAGS", ""):  # before JAX starts its backend (importing cdjax may)
    os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " --xla_backend_optimization_level=0").strip()

from cdjax import runtime  # noqa: E402

CACHE = pathlib.Path(os.environ.get(runtime.CACHE_ENV, pathlib.Path(__file__).resolve().parents[1] / ".jax_cache"))
runtime.configure(cache_dir=CACHE)
