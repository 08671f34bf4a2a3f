"""Experiments built on cdjax: one package per paper setting (run with `python -m experiments.<name>`)."""

import cdjax  # noqa: F401 - first: its XLA flags go into XLA_FLAGS before any experiment starts a JAX backend
