"""Experiments built on cdjax: one package per paper setting (run with `python -m experiments.<name>`)."""
