"""Experiments built on cdjax: one package per paper setting (run with `python -m experiments.<name>`)."""

from cdjax import runtime as _runtime

_runtime.apply_xla_defaults()  # first: cdjax's XLA flags, before any experiment starts a JAX backend
