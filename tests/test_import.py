"""Importing cdjax changes nothing in the process and imports no setting; its entry points apply the XLA defaults.

Each check runs in a fresh interpreter (the test process has imported everything already)."""

from __future__ import annotations

import json
import os
import pathlib
import subprocess
import sys

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
HEAVY = ("brax", "mujoco", "jax", "flax", "optax", "orbax")


def python(code: str, xla_flags: str | None = None) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    if xla_flags is not None:
        env["XLA_FLAGS"] = xla_flags
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(ROOT), env.get("PYTHONPATH")]))
    return subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True,
                          cwd=ROOT, timeout=300)


LOADED = "import json, sys; print(json.dumps(sorted({m.split('.')[0] for m in sys.modules} & set(%r))))" % (HEAVY,)


@pytest.mark.parametrize("before", [None, "--xla_force_host_platform_device_count=3"])
def test_import_cdjax_leaves_xla_flags_stdout_and_logging_as_they_were(before):
    code = ("import logging, os; handlers = list(logging.root.handlers); level = logging.root.level\n"
            "import cdjax\n"
            "assert logging.root.handlers == handlers and logging.root.level == level\n"
            "print(repr(os.environ.get('XLA_FLAGS')))")
    done = python(code, before)
    assert done.stdout == repr(before) + "\n"  # the only output is the script's own line
    assert done.stderr == ""


def test_import_cdjax_is_lazy_and_its_names_load_on_use():
    loaded = python("import cdjax\n" + LOADED).stdout.splitlines()[-1]
    assert json.loads(loaded) == []  # not even JAX
    names = python("import cdjax\n"
                   "print(all(hasattr(cdjax, n) for n in cdjax.__all__), 'make_train' in cdjax.__all__)\n"
                   "print(cdjax.Config.__module__, cdjax.runtime.__name__)").stdout.split()
    assert names[-4:] == ["True", "True", "cdjax.agents.obs.config", "cdjax.runtime"]
    with pytest.raises(subprocess.CalledProcessError) as err:
        python("import cdjax; cdjax.no_such_name")
    assert "has no attribute 'no_such_name'" in err.value.stderr


def test_make_train_and_make_trainer_are_the_registrys_dispatch():
    import cdjax
    from cdjax import agents

    assert cdjax.make_train is agents.make_train and cdjax.make_trainer is agents.make_trainer


def test_the_atari_setting_imports_neither_brax_nor_mujoco():
    loaded = json.loads(python("import cdjax.agents.atari\n" + LOADED).stdout.splitlines()[-1])
    assert "brax" not in loaded and "mujoco" not in loaded and "jax" in loaded


def test_the_cdjax_command_and_run_sweep_apply_the_xla_defaults():
    from cdjax import runtime

    # the command: `cdjax --help` exits after parsing; the flags are in XLA_FLAGS by then, a user's own kept first
    code = ("import os, sys\nfrom cdjax import cli\n"
            "try:\n    cli.main(['sweep', '--help'])\nexcept SystemExit:\n    pass\n"
            "print('FLAGS', os.environ['XLA_FLAGS'])")
    line = [ln for ln in python(code, "--xla_gpu_autotune_level=4").stdout.splitlines() if ln.startswith("FLAGS")][0]
    assert line.split()[1:] == ["--xla_gpu_autotune_level=4", runtime.CPU_SCHEDULER_FLAG, runtime.GPU_GEMM_TILINGS_FLAG]
    # run_sweep applies them first thing, before it reads its spec (a spec it refuses still leaves them set)
    code = ("import os\nfrom cdjax.runner import loop\n"
            "try:\n    loop.run_sweep(None)\nexcept Exception:\n    pass\n"
            "print('FLAGS', os.environ['XLA_FLAGS'])")
    line = [ln for ln in python(code).stdout.splitlines() if ln.startswith("FLAGS")][0]
    assert line.split()[1:] == list(runtime.XLA_DEFAULTS)


def test_a_notebook_opts_in_with_one_call_and_is_told_when_it_is_too_late():
    done = python("import os, cdjax; cdjax.runtime.apply_xla_defaults(); print(os.environ['XLA_FLAGS'])")
    from cdjax import runtime

    assert done.stdout.split() == list(runtime.XLA_DEFAULTS)
    late = python("import jax; jax.devices(); import cdjax; cdjax.runtime.apply_xla_defaults()").stderr
    assert "A JAX backend started before cdjax.runtime.apply_xla_defaults() was called" in late
    assert runtime.GPU_AUTOTUNE_FLAG in late


def test_versions_names_the_packages_a_result_record_needs():
    from importlib import metadata

    import jax

    import cdjax
    from cdjax import runtime

    record = runtime.versions()
    assert list(record) == ["cdjax", "jax", "jaxlib", "brax", "mujoco", "mujoco-mjx", "backend"]
    assert record["cdjax"] == cdjax.__version__ and record["jax"] == jax.__version__
    assert record["mujoco-mjx"] == metadata.version("mujoco-mjx") and record["backend"] == jax.default_backend()
    assert "backend" not in runtime.versions(backend=False)
    assert runtime.installed("no-such-distribution-here") is None


def test_run_records_and_benchmark_records_name_the_versions():
    from benchmarks.common import device_info
    from cdjax import runtime
    from cdjax.runner import plan

    expected = runtime.versions()
    code = plan.code_record()
    assert {name: code[name] for name in expected} == expected  # run.json's "code" entry
    recorded = device_info()["versions"]
    assert {name: recorded[name] for name in runtime.VERSIONED} == {name: expected[name] for name in runtime.VERSIONED}
    assert recorded["cdjax"] == expected["cdjax"]
