"""benchmarks.hlo_fusions: a profiled kernel's name leads to its fused computation and the JAX source lines."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from benchmarks import hlo_fusions


def _masked_scaled_sum(x, m):
    return jnp.where(m, -x * 3.0, 0.0).sum(0)  # the line the fusion's metadata must name


def test_a_fusion_is_found_with_its_body_and_the_source_line_it_came_from(tmp_path):
    text = jax.jit(_masked_scaled_sum).lower(jnp.ones((64, 8)), jnp.ones((64, 8), bool)).compile().as_text()
    dump = tmp_path / "dump"
    dump.mkdir()
    (dump / "module_0001.jit__masked_scaled_sum.after_optimizations.txt").write_text(text)
    (dump / "module_0001.jit__masked_scaled_sum.before_optimizations.txt").write_text("HloModule ignored\n")
    fusions = [line.split("=")[0].strip().lstrip("ROOT").strip().lstrip("%")
               for line in text.splitlines() if " fusion(" in line]
    assert fusions, text  # XLA fused something here; the test then asks for each by the first word of its name
    select = [name for name in fusions if "select" in name]
    assert select, fusions
    found = hlo_fusions.find(dump, [select[0]])
    assert [f["name"] for f in found] == [select[0]]
    (f,) = found
    assert f["calls"] and any(" select(" in line for line in f["body"]) and any(" negate(" in line for line in f["body"])
    line_no = _masked_scaled_sum.__code__.co_firstlineno + 1
    assert any(src.startswith(f"{__file__}:{line_no} (_masked_scaled_sum)") for _, src in f["sources"]), f["sources"]
    assert any(op.endswith("/select_n") for op, _ in f["sources"])
    text_report = hlo_fusions.report(found)
    assert f"{__file__}:{line_no}" in text_report and "select(" in text_report
    assert hlo_fusions.find(dump, ["no_such_kernel"]) == []
    assert hlo_fusions.report([]) == "no instruction with that name"
