"""benchmarks.startup: a whole tiny `cdjax sweep` process (the point mass), its wall clock cut into consecutive
stretches from its timings.jsonl that sum to what was measured around it, and the table of them."""

import json
import os
import pathlib
import sys

import pytest

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))  # `benchmarks` is not an installed package
from benchmarks import startup  # noqa: E402

KEPT = pathlib.Path(__file__).resolve().parents[1] / "benchmarks/results/2026-11-29-h200-sweep-smoke/ant/timings.jsonl"


def test_the_phases_of_kept_rows_sum_to_the_wall_clock_and_the_table_gives_their_medians():
    """On an H200 sweep's kept rows (no start-up rows, no evaluation row of its own: the stretches they would bound
    are empty), placed in a wall clock a few seconds wider on each side."""
    rows = [json.loads(line) for line in KEPT.read_text().splitlines()]
    launched = rows[0]["at"] - 3.0
    ended = max(r["at"] + r["s"] for r in rows) + 2.0
    cut = startup.phases(rows, launched, ended)
    assert sum(cut.values()) == pytest.approx(ended - launched, abs=1e-6)
    assert all(v >= 0 for v in cut.values())
    programs = next(r for r in rows if r["what"] == "programs")
    first = min(r["at"] for r in rows if r["step"] == "trace")
    assert cut["compiling the training programs"] == pytest.approx(programs["at"] + programs["s"] - first, abs=1e-6)
    assert cut["exit"] == pytest.approx(2.0, abs=1e-6)
    detail = startup.details(rows, launched)
    assert detail["chunk compile (sum over arms)"] == pytest.approx(21.01 + 35.58, abs=0.01)
    assert detail["command to the first program in flight"] == pytest.approx(
        min(r["at"] for r in rows if r["step"] == "init") - launched)
    results = [{"run": i, "wall": ended - launched + i, "phases": dict(cut, exit=cut["exit"] + i), "details": detail}
               for i in range(3)]
    lines = startup.table(results, "cmd", "gpu", "cold").splitlines()
    exit_row = next(line for line in lines if line.startswith("| exit |"))
    assert exit_row == f"| exit | {cut['exit'] + 1:.2f} | {cut['exit']:.2f} | {cut['exit'] + 2:.2f} |"


def test_a_tiny_whole_process_is_cut_into_stretches_that_sum_to_its_wall_clock(tmp_path):
    """`--tiny` on CPU: one process of two point-mass arms through the test session's compilation cache (seconds);
    its start-up, compile, training, final evaluation (with the evaluator compiled once, shared by both arms) and
    exit are all there, and the table and rows say the same. The arms model-free and mbmf, set after `--` (the
    sweep's own arguments, which follow --tiny's): the phases and the shared evaluator are the same with any two
    arms, and mbmf's chunk compiles in about half of cd's time."""
    cache = os.environ.get("CDJAX_JAX_CACHE", str(pathlib.Path(__file__).resolve().parents[1] / ".jax_cache"))
    [result] = startup.main(["--tiny", "--runs", "1", "--out", str(tmp_path / "b"), "--cache-dir", cache,
                             "--", "--arms", "model-free", "mbmf"])
    cut = result["phases"]
    assert sum(cut.values()) == pytest.approx(result["wall"], abs=1e-6)
    for name in ("start-up: imports and arguments", "planning (envs built, shapes)", "training", "final evaluation"):
        assert cut[name] > 0, name
    detail = result["details"]
    assert 0 < detail["command to the first program in flight"] < result["wall"]
    timings = [json.loads(line) for line in (tmp_path / "b/run-0/timings.jsonl").read_text().splitlines()]
    assert [r["arm"] for r in timings if (r["what"], r["step"]) == ("evaluator", "trace")] == ["model-free", "mbmf"]
    assert len([r for r in timings if (r["what"], r["step"]) == ("evaluator", "compile")]) <= 1  # shared (or cached)
    rows = [json.loads(line) for line in (tmp_path / "b/rows.jsonl").read_text().splitlines()]
    assert sum(r["s"] for r in rows if r["kind"] == "phases") == pytest.approx(result["wall"], abs=1e-6)
    table = (tmp_path / "b/table.md").read_text()
    assert f"| total (wall clock) | {result['wall']:.2f} |" in table and "device: cpu" in table
