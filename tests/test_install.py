"""`pip install -e .` into an environment that already holds a supported JAX keeps it: pyproject.toml declares
ranges, not pins (CI's exact set is constraints.txt). Checked with pip's own resolver (`--dry-run --report`), in
this environment, without installing anything."""

from __future__ import annotations

import json
import pathlib
import subprocess
import sys
import tomllib
from importlib import metadata

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
PROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
KEPT = ("jax", "jaxlib", "numpy", "pandas", "brax", "mujoco", "mujoco-mjx", "flax", "optax")


def requirement(name: str):
    from packaging.requirements import Requirement

    (found,) = [Requirement(r) for r in PROJECT["dependencies"] if Requirement(r).name == name]
    return found


def test_dependencies_are_ranges_that_hold_the_tested_versions_and_the_constraints_pin_each():
    pins = dict(line.split("==") for line in (ROOT / "constraints.txt").read_text().splitlines()
                if "==" in line and not line.startswith("#"))
    pins = {name.lower().replace("_", "-"): version for name, version in pins.items()}
    for text in PROJECT["dependencies"]:
        from packaging.requirements import Requirement

        req = Requirement(text)
        assert not any(spec.operator == "==" for spec in req.specifier), f"{text}: a range, not a pin"
        name = req.name.lower().replace("_", "-")
        assert name in pins and req.specifier.contains(pins[name]), f"constraints.txt's {req.name}"
    # the GPU image's JAX (0.11.x) and CI's (0.10.2) are both in range
    for version in ("0.10.2", "0.11.2"):
        assert requirement("jax").specifier.contains(version) and requirement("jaxlib").specifier.contains(version)
    assert PROJECT["optional-dependencies"]["cuda12"][0].startswith("jax[cuda12]")


def test_pip_install_e_keeps_the_installed_jax(tmp_path):
    installed = {}
    for name in KEPT:
        try:
            installed[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            pytest.skip(f"{name} is not installed here")
    report = tmp_path / "report.json"
    done = subprocess.run([sys.executable, "-m", "pip", "install", "--dry-run", "--quiet", "--report", str(report),
                           "-e", str(ROOT)], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    chosen = {item["metadata"]["name"].lower(): item["metadata"]["version"] for item in json.loads(report.read_text())["install"]}
    assert "cdjax" in chosen
    for name, version in installed.items():
        assert name not in chosen, f"pip would replace {name} {version} with {chosen.get(name)}"
