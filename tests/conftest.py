"""Shared test setup: JAX's persistent compilation cache (MJX compiles slowly on CPU), through cdjax.runtime, and XLA's
CPU backend at optimisation level 0 with its older fusion emitters for the whole test session (and the processes it
starts, which inherit XLA_FLAGS), with cdjax's own XLA defaults on top (as its entry points apply them): the tests'
programs are tiny and compiling them is most of the suite's time; level 0 compiles them in about half the time
(test_train's compile-once tests: 96 s -> 47 s) and computes the same operations, so every comparison the tests make
(vmapped against alone, resumed against uninterrupted, fused against scanned) is made between programs compiled
alike (two different programs compared bit for bit are compiled with XLA's own emitters: _shared.EXACT). Set
CDJAX_TEST_XLA_OPT=default to test with XLA's own optimisation level and emitters."""

import os
import pathlib
from importlib.metadata import version


def _add_xla_flag(flag: str) -> None:
    """Append `flag` to XLA_FLAGS unless XLA_FLAGS names its option already (before JAX starts its backend)."""
    if flag.split("=")[0] not in os.environ.get("XLA_FLAGS", ""):
        os.environ["XLA_FLAGS"] = f"{os.environ.get('XLA_FLAGS', '')} {flag}".strip()


if os.environ.get("CDJAX_TEST_XLA_OPT", "0") != "default":  # before JAX starts its backend (importing cdjax may)
    _add_xla_flag("--xla_backend_optimization_level=0")
    # XLA:CPU's older fusion emitters: they compile the tests' programs in about 40% less CPU time than the MLIR
    # fusion emitters (test_train, test_consistency and test_losses: 236 s -> 144 s of user time) and pass the same
    # tests. An unknown XLA flag is fatal, so only with the jaxlib known to have it (CI's).
    if version("jaxlib").startswith("0.10."):
        _add_xla_flag("--xla_cpu_use_fusion_emitters=false")

from cdjax import runtime  # noqa: E402

runtime.apply_xla_defaults()  # as the `cdjax` command does: XLA:CPU's scheduler flag keeps vmapped programs from hanging

CACHE = pathlib.Path(os.environ.get(runtime.CACHE_ENV, pathlib.Path(__file__).resolve().parents[1] / ".jax_cache"))
runtime.configure(cache_dir=CACHE)

# The files that take longest first, longest first (the sums of their slowest tests in a whole-suite run with -n 2;
# from test_consistency.py on, the sums of each file's tests run alone with -n 0): the suite runs on two workers, a
# file to a worker (--dist loadfile) in collection order (--no-loadscope-reorder in pyproject.toml), each worker
# taking the next file when it is free, so a long file handed out last would leave one worker finishing alone. Files
# not named keep their order after these. test_paper_obs_space.py stays well after test_runner.py, whose phase sweep
# it runs again (the compilation cache serves it once test_runner.py has compiled it).
HEAVY_FIRST = ("test_train.py", "test_benchmarks.py", "test_readme.py", "test_learner.py",
               "test_pixel_model.py", "test_runner.py", "test_sweep.py", "test_swimmer.py", "test_settings_face.py",
               "test_run_dir.py",
               "test_offpolicy.py", "test_mbmf.py", "test_atari_cli.py", "test_multihost.py", "test_docs.py",
               "test_mpc.py", "test_cli.py", "test_offpolicy_host.py", "test_playground.py", "test_playground_bench.py",
               "test_failures.py", "test_consistency.py", "test_mbmf_options.py", "test_paper_obs_space.py",
               "test_pixels.py", "test_evaluate.py", "test_offpolicy_bench.py", "test_faults.py", "test_startup.py",
               "test_env_resume.py", "test_losses.py", "test_atari.py", "test_launch.py", "test_offpolicy_experiment.py")


def pytest_collection_modifyitems(session, config, items):
    rank = {name: i for i, name in enumerate(HEAVY_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(HEAVY_FIRST)))  # stable: each file's order kept
