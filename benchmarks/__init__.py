"""Throughput and scaling benchmarks of cdjax against raw MJX stepping and Brax's PPO trainer.

One entry command: `python -m benchmarks.run --help` (see benchmarks/README.md).
"""

import cdjax  # noqa: F401 - first: its XLA flags go into XLA_FLAGS before any benchmark starts a JAX backend
