"""Shared test setup: JAX's persistent compilation cache (MJX compiles slowly on CPU), through cdjax.runtime."""

import os
import pathlib

from cdjax import runtime

CACHE = pathlib.Path(os.environ.get(runtime.CACHE_ENV, pathlib.Path(__file__).resolve().parents[1] / ".jax_cache"))
runtime.configure(cache_dir=CACHE)

# The files with the longest tests (pytest --durations on a fresh 2-core clone), run first: pytest-xdist's
# --dist loadfile hands whole files to its two workers in collection order, so a long file collected last (they
# sort late by name: test_runner, test_swimmer, test_train) would leave one worker running alone at the end.
LONGEST_FIRST = ("test_cli.py", "test_swimmer.py", "test_runner.py", "test_train.py", "test_benchmarks.py",
                 "test_sweep.py", "test_paper_obs_space.py", "test_pixel_model.py", "test_notebook.py")


def pytest_collection_modifyitems(config, items):
    rank = {name: i for i, name in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))  # stable: the rest keep their order
