"""`pip install -e .` into an environment that already holds a supported JAX keeps it: pyproject.toml declares
ranges, not pins (CI's exact set is constraints.txt). Checked with pip's own resolver (`--dry-run --report`),
without installing anything, against an environment that holds another supported JAX than CI's.

That environment is constructed: JAX 0.11 needs Python 3.12 (the GPU image's), so no second supported JAX installs
on CI's Python 3.11. pip decides what to keep from the installed distributions' metadata, so a folder put ahead of
site-packages on PYTHONPATH holds the metadata (name, version, requirements as their wheels declare them) of jax and
jaxlib 0.11.2 and of pandas 3.0.6 (the GPU image's); pip takes them as installed, and everything else as it is here."""

from __future__ import annotations

import json
import os
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
    from packaging.requirements import Requirement

    # the dependencies and the extras CI installs (test brings rliable's, which caps pandas there and only there)
    extras = PROJECT["optional-dependencies"]
    for text in PROJECT["dependencies"] + extras["rliable"] + extras["test"] + extras["docs"] + extras["playground"]:
        req = Requirement(text)
        if req.name == PROJECT["name"]:
            continue
        assert not any(spec.operator == "==" for spec in req.specifier), f"{text}: a range, not a pin"
        name = req.name.lower().replace("_", "-")
        assert name in pins and req.specifier.contains(pins[name]), f"constraints.txt's {req.name}"
    assert "cdjax[rliable]" in extras["test"]
    # cdjax itself needs no pandas, so pandas 3 stays where it is installed (rliable 1.2's arch<8 fails under it)
    assert "pandas" not in {Requirement(r).name for r in PROJECT["dependencies"]}
    # the GPU image's JAX (0.11.x) and CI's (0.10.2) are both in range
    for version in ("0.10.2", "0.11.2"):
        assert requirement("jax").specifier.contains(version) and requirement("jaxlib").specifier.contains(version)
    assert PROJECT["optional-dependencies"]["cuda12"][0].startswith("jax[cuda12]")


# Distributions pip is shown as installed: name -> (version, Requires-Dist of its wheel, extras' left out).
CONSTRUCTED = {
    "jax": ("0.11.2", ["jaxlib<=0.11.2,>=0.11.2", "ml_dtypes>=0.5.0", "numpy>=2.1", "opt_einsum", "scipy>=1.15"]),
    "jaxlib": ("0.11.2", ["scipy>=1.14", "numpy>=2.0", "ml_dtypes>=0.5.0"]),
    "pandas": ("3.0.6", ['numpy>=1.26.0; python_version < "3.14"', 'numpy>=2.3.3; python_version >= "3.14"',
                         "python-dateutil>=2.8.2"]),
}


def constructed_site(folder: pathlib.Path) -> pathlib.Path:
    """A folder of .dist-info metadata for CONSTRUCTED, as an installer leaves it (METADATA, INSTALLER)."""
    for name, (version, requires) in CONSTRUCTED.items():
        info = folder / f"{name}-{version}.dist-info"
        info.mkdir(parents=True)
        lines = ["Metadata-Version: 2.1", f"Name: {name}", f"Version: {version}", *(f"Requires-Dist: {r}" for r in requires)]
        (info / "METADATA").write_text("\n".join(lines) + "\n")
        (info / "INSTALLER").write_text("pip\n")
    return folder


def test_pip_install_e_keeps_another_supported_jax_and_pandas_3(tmp_path):
    installed = {}
    for name in KEPT:
        try:
            installed[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            pytest.skip(f"{name} is not installed here")
    site = constructed_site(tmp_path / "site")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [str(site), os.environ.get("PYTHONPATH")])))
    seen = subprocess.run([sys.executable, "-m", "pip", "inspect"], env=env, capture_output=True, text=True, timeout=120)
    assert seen.returncode == 0, seen.stderr[-3000:]
    seen = {d["metadata"]["name"].lower(): d["metadata"]["version"] for d in json.loads(seen.stdout)["installed"]}
    for name, (version, _) in CONSTRUCTED.items():
        assert seen[name] == version, f"pip does not see the constructed {name} {version} ({seen.get(name)})"
    installed.update((name, version) for name, (version, _) in CONSTRUCTED.items())
    report = tmp_path / "report.json"
    done = subprocess.run([sys.executable, "-m", "pip", "install", "--dry-run", "--quiet", "--report", str(report),
                           "-e", str(ROOT)], env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    chosen = {item["metadata"]["name"].lower(): item["metadata"]["version"] for item in json.loads(report.read_text())["install"]}
    assert "cdjax" in chosen
    for name, version in installed.items():
        assert name not in chosen, f"pip would replace {name} {version} with {chosen.get(name)}"
