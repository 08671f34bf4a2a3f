"""The docs site builds in strict mode (a broken link, a missing API object or a failing notebook fails it), with its
notebooks executed; the notebooks are committed without outputs and their executed pages show what they compute.

It replaces the notebook test: the build executes the same notebooks (docs/notebooks/)."""

from __future__ import annotations

import contextlib
import os
import pathlib
import re
import shutil
import subprocess
import sys

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
NOTEBOOKS = sorted((ROOT / "docs" / "notebooks").glob("*.ipynb"))


def mkdocs() -> list[str] | None:
    """How to run mkdocs here (the docs extra installed), else None."""
    try:
        import material  # noqa: F401
        import mkdocs  # noqa: F401
        import mkdocs_jupyter  # noqa: F401
        import mkdocstrings  # noqa: F401
    except ImportError:
        return None
    return [sys.executable, "-m", "mkdocs"]


@contextlib.contextmanager
def one_cpu():
    """Pin this process (and so the build and the notebook kernels it starts) to one CPU, then restore: on a 2-core
    CPU, jaxlib 0.10.2's XLA:CPU runtime has deadlocked now and then executing vmapped training of several runs;
    pinned to one CPU it has always completed."""
    if not hasattr(os, "sched_setaffinity"):
        yield
        return
    before = os.sched_getaffinity(0)
    os.sched_setaffinity(0, {min(before)})
    try:
        yield
    finally:
        os.sched_setaffinity(0, before)


def test_notebooks_are_committed_without_outputs():
    nbformat = pytest.importorskip("nbformat")
    assert {p.name for p in NOTEBOOKS} >= {"quickstart.ipynb", "atari.ipynb", "pixel.ipynb"}
    for path in NOTEBOOKS:
        for cell in nbformat.read(path, as_version=4).cells:
            if cell.cell_type == "code":
                assert not cell.outputs and cell.execution_count is None, f"clear {path.name}'s outputs"


def test_the_site_builds_strictly_with_executed_notebooks_and_the_api_reference(tmp_path):
    command = mkdocs()
    if command is None:
        pytest.skip("the docs extra is not installed (pip install -e '.[docs]'); CI installs it")
    site = tmp_path / "site"
    env = dict(os.environ, NO_MKDOCS_2_WARNING="1",
               PYTHONPATH=os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])))
    work = tmp_path / "work"  # mkdocs-jupyter writes nothing into the repository from here
    work.mkdir()
    with one_cpu():
        done = subprocess.run([*command, "build", "--strict", "-f", str(ROOT / "mkdocs.yml"), "-d", str(site)],
                              cwd=work, env=env, capture_output=True, text=True, timeout=900)
    assert done.returncode == 0, done.stderr[-6000:]

    # the API reference holds the public names, rendered from their docstrings
    api = (site / "api" / "index.html").read_text()
    for name in ("apply_xla_defaults", "versions", "run_sweep", "Trainer", "make_trainer"):
        assert name in api, name
    assert "Add cdjax" in api  # apply_xla_defaults' docstring, not only its name
    # the results page shows the figures the hook copies from where the results keep them
    assert (site / "figures" / "obs-returns.png").stat().st_size > 1000

    # the executed notebooks: figures, and the numbers they print
    quick = (site / "notebooks" / "quickstart" / "index.html").read_text()
    assert quick.count("data:image/png") >= 2, "expected the return and open-loop error figures"
    finals = re.findall(r"final mean return, alpha=([\d.]+): (\S+?)<", quick) or re.findall(
        r"final mean return, alpha=([\d.]+): (\S+)", quick)
    assert [alpha for alpha, _ in finals] == ["0.0", "1.0"]
    for _, value in finals:
        assert value not in ("nan", "inf", "-inf") and float(value) == float(value)
    assert re.search(r"eval return, alpha=1\.0: .* mean -?\d+\.\d+", quick)
    atari = (site / "notebooks" / "atari" / "index.html").read_text()
    assert "30 updates of 2 seeds in" in atari and "data:image/png" in atari
    pixel = (site / "notebooks" / "pixel" / "index.html").read_text()
    assert "20 updates in" in pixel and "data:image/png" in pixel
    assert "Traceback" not in quick + atari + pixel
    shutil.rmtree(work, ignore_errors=True)
