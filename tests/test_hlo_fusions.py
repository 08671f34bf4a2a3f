"""benchmarks.hlo_fusions: a profiled kernel's name leads to its fused computation and the JAX source lines."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from benchmarks import hlo_fusions
from _shared import benchmark_refuses


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


def test_a_profile_kernel_name_finds_its_own_instruction_and_the_profile_names_the_top_fusions(tmp_path):
    """A GPU profile writes `loop_pad_fusion.2` as `loop_pad_fusion_2`: that name finds instruction .2, not .1 (which a
    plain prefix would also take); --profile takes the fusion kernels of a trace, costliest first, with their launch."""
    import gzip
    import json

    hlo = "\n".join([
        "HloModule jit_update", "",
        "%fused_pad.1 (p.1: f32[4]) -> f32[8] {", "  %p.1 = f32[4]{0} parameter(0)",
        '  ROOT %pad.1 = f32[8]{0} pad(%p.1, %c), padding=0_4, metadata={op_name="jit(f)/one"}', "}", "",
        "%fused_pad.2 (p.2: f32[4]) -> f32[8] {", "  %p.2 = f32[4]{0} parameter(0)",
        '  ROOT %pad.2 = f32[8]{0} pad(%p.2, %c), padding=4_0, metadata={op_name="jit(f)/two"}', "}", "",
        "ENTRY %main (x: f32[4]) -> (f32[8], f32[8]) {", "  %x = f32[4]{0} parameter(0)",
        "  %loop_pad_fusion.1 = f32[8]{0} fusion(%x), kind=kLoop, calls=%fused_pad.1",
        "  %loop_pad_fusion.2 = f32[8]{0} fusion(%x), kind=kLoop, calls=%fused_pad.2",
        "  ROOT %t = (f32[8]{0}, f32[8]{0}) tuple(%loop_pad_fusion.1, %loop_pad_fusion.2)", "}", ""])
    path = tmp_path / "module.after_optimizations.txt"
    path.write_text(hlo)
    (found,) = hlo_fusions.find(path, [], ["loop_pad_fusion_2"])
    assert found["name"] == "loop_pad_fusion.2" and [op for op, _ in found["sources"]] == ["jit(f)/two"]
    assert [f["name"] for f in hlo_fusions.find(path, ["loop_pad_fusion"])] == ["loop_pad_fusion.1", "loop_pad_fusion.2"]
    assert hlo_fusions.find(path, [], ["loop_pad_fusion"]) == []  # a kernel name is one instruction, not a prefix

    details = "regs:32 static_shared:0 dynamic_shared:0 grid:1,1,1 block:1024,1,1 occ_pct:3.1"
    events = [
        {"ph": "M", "pid": 1, "name": "process_name", "args": {"name": "/device:GPU:0"}},
        {"ph": "M", "pid": 1, "tid": 7, "name": "thread_name", "args": {"name": "Stream #7(Compute)"}},
        {"ph": "X", "pid": 1, "tid": 7, "ts": 0.0, "dur": 50.0, "name": "gemm_fusion_dot_3", "args": {}},
        {"ph": "X", "pid": 1, "tid": 7, "ts": 60.0, "dur": 30.0, "name": "loop_pad_fusion_2",
         "args": {"kernel_details": details}},
        {"ph": "X", "pid": 1, "tid": 7, "ts": 100.0, "dur": 5.0, "name": "loop_pad_fusion_1", "args": {}},
    ]
    run = tmp_path / "trace" / "plugins" / "profile" / "run1"
    run.mkdir(parents=True)
    with gzip.open(run / "perfetto_trace.json.gz", "wt") as f:
        json.dump({"traceEvents": events}, f)
    text = hlo_fusions.main([str(path), "--profile", str(tmp_path / "trace"), "--top", "1"])
    assert text.splitlines()[0] == "loop_pad_fusion_2: 0.030 ms in 1 calls (35.3%), launch 1 x 1,024 (3%)"
    assert "== loop_pad_fusion.2 " in text and "== loop_pad_fusion.1 " not in text and "gemm_fusion" not in text


def test_loops_count_each_bodys_launches_by_group_and_not_the_fused_insides(tmp_path):
    """--loops: per while body and the entry, the instructions that launch work (fusions by name without numbers,
    library calls and unfused operations by opcode), not parameters, tuples, bitcasts or the fused computations'
    own instructions; the largest body first."""
    hlo = "\n".join([
        "HloModule jit_update", "",
        "%fused_add.1 (p: f32[4]) -> f32[4] {", "  %p = f32[4]{0} parameter(0)",
        "  %e = f32[4]{0} exponential(%p)", "  ROOT %a = f32[4]{0} add(%e, %e)", "}", "",
        "%body.7 (c: (s32[], f32[4])) -> (s32[], f32[4]) {", "  %c = (s32[], f32[4]{0}) parameter(0)",
        "  %i = s32[] get-tuple-element(%c), index=0", "  %v = f32[4]{0} get-tuple-element(%c), index=1",
        "  %loop_add_fusion.3 = f32[4]{0} fusion(%v), kind=kLoop, calls=%fused_add.1",
        "  %loop_add_fusion.12 = f32[4]{0} fusion(%loop_add_fusion.3), kind=kLoop, calls=%fused_add.1",
        '  %gemm = (f32[4]{0}, s8[8]{0}) custom-call(%v), custom_call_target="__cublas$gemm"',
        "  %copy.2 = f32[4]{0} copy(%loop_add_fusion.12)", "  %b = f32[2,2]{1,0} bitcast(%copy.2)",
        "  ROOT %t = (s32[], f32[4]{0}) tuple(%i, %copy.2)", "}", "",
        "%cond.7 (c: (s32[], f32[4])) -> pred[] {", "  %c = (s32[], f32[4]{0}) parameter(0)",
        "  %i = s32[] get-tuple-element(%c), index=0", "  %n = s32[] constant(3)",
        "  ROOT %lt = pred[] compare(%i, %n), direction=LT", "}", "",
        "ENTRY %main (x: f32[4]) -> (s32[], f32[4]) {", "  %x = f32[4]{0} parameter(0)", "  %z = s32[] constant(0)",
        "  %init = (s32[], f32[4]{0}) tuple(%z, %x)",
        "  ROOT %w = (s32[], f32[4]{0}) while(%init), condition=%cond.7, body=%body.7, "
        'backend_config={"known_trip_count":{"n":"3"}}', "}", ""])
    path = tmp_path / "module.after_optimizations.txt"
    path.write_text(hlo)
    body, entry = hlo_fusions.loop_kernels(path)
    assert body["computation"] == "body.7" and not body["entry"]
    assert body["kernels"] == 4 and dict(body["groups"]) == {"loop_add_fusion": 2, "custom-call": 1, "copy": 1}
    assert entry["computation"] == "main" and entry["entry"] and entry["kernels"] == 0
    text = hlo_fusions.main([str(path), "--loops", "--top", "1"])
    assert text.splitlines()[:3] == ["body.7 (loop body, module.after_optimizations.txt): 4 kernels per pass, 3 passes",
                                     "      2  loop_add_fusion", "      2  (2 other groups)"]
    assert body["trips"] == 3 and body["passes"] == 3
    assert text.splitlines()[-1].startswith("module.after_optimizations.txt: 12 kernels per run")  # 0 + 4 x 3
    path.write_text(hlo.replace(', backend_config={"known_trip_count":{"n":"3"}}', ""))
    body, _ = hlo_fusions.loop_kernels(path)
    assert body["trips"] is None and body["passes"] == 1


def test_bad_arguments_are_refused_in_one_sentence_before_anything_is_read(tmp_path, capsys):
    """A DUMP that does not exist or holds no optimised HLO (it answered "no instruction with that name"), a --profile
    without a trace, --top below 1, --loops with what only the fusion listing uses (it ignored them), nothing to look
    for: one sentence naming it, exit status 2, nothing on stdout."""
    dump, empty = tmp_path / "dump", tmp_path / "empty"
    dump.mkdir()
    empty.mkdir()
    (dump / "m.after_optimizations.txt").write_text("HloModule m\n")

    def refused(argv, said):
        benchmark_refuses(capsys, hlo_fusions.main, argv, "hlo_fusions", said, quiet=True)

    refused([str(tmp_path / "none"), "loop_fusion"], f"DUMP {tmp_path / 'none'} does not exist")
    refused([str(empty), "loop_fusion"], f"DUMP {empty} holds no *after_optimizations.txt file")
    refused([str(dump), "--profile", str(tmp_path / "none")], f"--profile {tmp_path / 'none'} does not exist")
    refused([str(dump), "--profile", str(empty)], f"--profile {empty} holds no profiler trace")
    refused([str(dump), "loop_fusion", "--top", "0"], "argument --top: '0' is not a whole number of at least 1")
    refused([str(dump), "--loops", "loop_fusion"], "PREFIX is for: give it without --loops")
    refused([str(dump), "--loops", "--profile", str(empty), "--max-lines", "3"], "--profile and --max-lines are for")
    refused([str(dump)], "name instruction-name PREFIXes, --profile TRACE or --loops")
    assert hlo_fusions.main([str(dump), "--max-lines", "3", "loop_fusion"]) == "no instruction with that name"
