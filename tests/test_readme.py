"""Every snippet of README.md runs on a CPU, as a reader would run it.

The install lines (`pip install ...`) are not run: CI performs the install itself (.ci/run, with the README's test
command), and here they are checked against pyproject.toml (the extras they name exist) and against .ci/run (the
test command is CI's, word for word). The GPU block's sweep is parsed by the `cdjax` command's own parser (its
preset resolved), not trained. Every other shell line runs in a temporary directory with `cdjax` as the command
(the installed entry point's `cdjax.cli.main`); the Python block runs in a fresh interpreter."""

from __future__ import annotations

import json
import os
import pathlib
import re
import shlex
import subprocess
import sys

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text()
BLOCKS = [(lang, body) for lang, body in re.findall(r"^```(\w*)\n(.*?)^```", README, flags=re.S | re.M)]
CDJAX = f'cdjax() {{ {shlex.quote(sys.executable)} -c "from cdjax.cli import main; main()" "$@"; }}'


def shell_blocks() -> list[list[str]]:
    return [[ln for ln in body.splitlines() if ln.strip()] for lang, body in BLOCKS if lang == "bash"]


def run_shell(lines: list[str], cwd: pathlib.Path) -> str:
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])))
    script = "\n".join(["set -euo pipefail", CDJAX, *lines])
    done = subprocess.run(["bash", "-c", script], cwd=cwd, env=env, capture_output=True, text=True, timeout=900)
    assert done.returncode == 0, f"{lines}\n{done.stdout[-3000:]}\n{done.stderr[-3000:]}"
    return done.stdout


def test_the_readme_is_short_and_its_first_two_blocks_install_for_a_cpu_and_a_gpu():
    import tomllib

    assert len(README.splitlines()) <= 250
    cpu, gpu = shell_blocks()[:2]
    assert cpu[0] == "pip install -e ." and gpu[0] == 'pip install -e ".[cuda12]"'
    extras = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["optional-dependencies"]
    for line in re.findall(r"pip install [^\n`]*", README):
        for named in re.findall(r"\[([\w,]+)\]", line):
            assert set(named.split(",")) <= set(extras), line
    assert "jax[cuda12]" in " ".join(extras["cuda12"])


def test_the_readme_test_command_is_cis():
    (command,) = [body.strip() for lang, body in BLOCKS if "pytest" in body]
    assert command in (ROOT / ".ci" / "run").read_text().splitlines()
    assert "-c constraints.txt" in command and (ROOT / "constraints.txt").is_file()


def test_the_readme_links_name_files_of_the_repository():
    for target in re.findall(r"\]\(([^)#\s]+)\)", README):
        if "://" not in target:
            assert (ROOT / target).exists(), target


def test_the_gpu_sweep_parses_and_resolves_its_preset():
    from cdjax import agents
    from cdjax.cli import build_parser, setting_of, sweep_spec

    gpu = shell_blocks()[1]
    argv = shlex.split(gpu[1])
    assert argv[0] == "cdjax"
    spec = sweep_spec(build_parser().parse_args(argv[1:]), setting_of(argv[1:]))
    assert spec.config.env == "ant" and str(spec.out) == "runs/ant" and spec.seeds >= 1
    assert setting_of(argv[1:]) is agents.get("obs")


def test_the_cpu_install_block_and_the_command_line_block_run(tmp_path):
    cpu = shell_blocks()[0]
    command_line = next(lines for lines in shell_blocks() if any("--resume" in ln for ln in lines))
    run_shell(cpu[1:] + command_line, tmp_path)
    first = tmp_path / "runs" / "point"
    record = json.loads((first / "run.json").read_text())
    assert record["arms"][0]["num_updates"] == 80  # resumed on to --steps 40960 (the preset's 20,480 twice)
    code = record["code"][-1]  # the versions it ran with
    assert code["jax"] and code["brax"] and code["mujoco-mjx"] and code["backend"] == "cpu"
    assert list((first).glob("*.png")) or list(first.rglob("*.png"))  # `cdjax plot` drew the curves


def test_the_library_snippet_runs():
    (code,) = [body for lang, body in BLOCKS if lang == "python"]
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])))
    done = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    assert done.stdout.strip().splitlines()[-1] == "(3, 5)"


def test_the_benchmarks_snippet_runs(tmp_path):
    bench = next(lines for lines in shell_blocks() if any("benchmarks.run" in ln for ln in lines))
    env_root = f"cd {shlex.quote(str(ROOT))} && "  # `python -m benchmarks.run` runs from the repository's root
    out = tmp_path / "bench"
    lines = [env_root + ln.replace("python ", f"{shlex.quote(sys.executable)} ", 1).replace("runs/bench", str(out))
             for ln in bench]
    run_shell(lines, tmp_path)
    results = json.loads((out / "results.json").read_text())
    assert results and (out / "results.md").is_file()


def test_the_experiments_block_lists_the_units_it_runs_one_of():
    """The `list` line runs (and names the unit); the `run` line trains on a GPU, so here its unit is checked to
    exist and its arguments to be the experiment's own parser's (`run UNIT --out DIR`)."""
    lines = next(lines for lines in shell_blocks() if any("experiments." in ln for ln in lines))
    listed, run = (shlex.split(ln.split("#")[0]) for ln in lines)
    assert listed[:3] == ["python", "-m", "experiments.paper_obs_space"] and listed[3:] == ["list"]
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])))
    done = subprocess.run([sys.executable, *listed[1:]], cwd=ROOT, env=env, capture_output=True, text=True,
                          timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    from experiments.paper_obs_space import UNITS

    assert run[:4] == listed[:3] + ["run"] and run[4] in UNITS and f"| {run[4]} |" in done.stdout
    assert run[5:] == ["--out", "runs/ant-1"]


def test_the_citation_names_the_paper_and_cdjax():
    cff = (ROOT / "CITATION.cff").read_text()
    (bib,) = [body for lang, body in BLOCKS if lang == "bibtex"]
    title = re.search(r"title\s*=\s*\{(.*?)\}", bib).group(1)
    assert f'title: "{title}"' in cff and "1906.09654" in bib and "1906.09654" in cff
    for author in ("Sodhani", "Goyal", "Deleu", "Bengio", "Levine", "Tang"):
        assert author in bib and f"family-names: {author}" in cff
