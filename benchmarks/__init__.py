"""Throughput and scaling benchmarks of cdjax against raw MJX stepping and Brax's PPO trainer.

One entry command: `python -m benchmarks.run --help` (see benchmarks/README.md).
"""
