"""Throughput and scaling benchmarks of cdjax against raw MJX stepping and Brax's PPO trainer.

One entry command: `python -m benchmarks.run --help` (see benchmarks/README.md).
"""

from cdjax import runtime as _runtime

_runtime.apply_xla_defaults()  # first: cdjax's XLA flags, before any benchmark starts a JAX backend
