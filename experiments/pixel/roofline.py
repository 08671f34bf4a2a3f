"""The pixel update against the device's limits: FLOPs per frame, achieved TFLOP/s and the device's peak, per
arrangement of the model's convolutions (issue 22).

    python -m experiments.pixel.roofline --env halfcheetah --runs 30 --out roofline.json --profile prof/
    python -m experiments.pixel.roofline --tiny            # a CPU check of the tool: pixel-tiny, 2 runs, synthetic

For each variant COMPUTE_DTYPE/CONV_IMPL (PixelConfig.compute_dtype and conv_impl; default: float32/grouped, the
model of before, and bfloat16 with each arrangement), the update of R runs as a sweep runs it (jit(vmap(update)) on
one device, the runs' batches together) is compiled and timed (compile and first call, then the mean of later
calls), and:

  flops_per_frame    floating-point operations of one update per trained frame (R x batch_size x seq_len frames),
                     counted on the update's jaxpr (dead code removed): every matrix product and convolution as 2 x
                     its multiply-adds
                     (how XLA counts them; a strided convolution's input gradient without the zeros it inserts), a
                     scanned body times its length. Elementwise work is left out (it runs
                     at memory speed, not on the matrix units the peak measures).
  xla_flops_per_frame  XLA's own cost analysis of the compiled program, which counts a loop's body once (the
                     50-step LSTM scan as one step): kept beside as a check, not the figure to use
  xla_bytes_per_frame  XLA's bytes accessed (also loops once)
  achieved_tflops    flops per update / seconds per update
  peak_tflops        measured: a chain of n x n matrix products in the variant's dtype at JAX's default precision
                     (what this device gives a dense product); spec: the datasheet's dense peak where the device is
                     known (SPEC; None elsewhere, e.g. a CPU)
  of_peak            achieved / measured peak
  frames_per_s       trained frames per second

With --profile DIR each variant's two steady-state updates are traced (benchmarks.profile_summary) and DIR/VARIANT.md
says where the device time goes (matrix products, fusions, copies, ...).
"""

from __future__ import annotations

import argparse
import json
import math
import pathlib
import time

import jax
import jax.numpy as jnp

from cdjax import agents, runtime
from experiments.pixel.data_cost import overrides, timed, write_json

# matmul (data/roofline-h200/): as slow as float32/grouped and near the memory limit; ask for it
# by name
VARIANTS = ("float32/grouped", "float32/auto", "bfloat16/grouped", "bfloat16/per-run", "bfloat16/auto")

# Dense (no sparsity) peaks from NVIDIA's datasheets, TFLOP/s; "tf32" is float32 on the tensor cores (what XLA:GPU
# may use for float32 products at JAX's default precision), "float32" the CUDA cores'. HBM in TB/s. The H100 row is
# the SXM part (device_kind "NVIDIA H100 80GB HBM3"); the H200 has the H100's compute and faster memory.
SPEC = {
    "NVIDIA H100 80GB HBM3": {"bfloat16": 989.4, "tf32": 494.7, "float32": 66.9, "hbm_tb_per_s": 3.35},
    "NVIDIA H200": {"bfloat16": 989.4, "tf32": 494.7, "float32": 66.9, "hbm_tb_per_s": 4.8},
}


# ------------------------------------------------------------------------------------------- counting

def _sub_jaxprs(params: dict):
    """The jaxprs an equation's parameters hold (a scan's body, a cond's branches, a pjit's or a remat's callee)."""
    for value in params.values():
        for v in value if isinstance(value, (tuple, list)) else (value,):
            if hasattr(v, "eqns"):
                yield v
            elif hasattr(v, "jaxpr") and hasattr(v.jaxpr, "eqns"):
                yield v.jaxpr


def matrix_flops(jaxpr) -> tuple[float, int]:
    """(FLOPs of the matrix products and convolutions of a jaxpr, 2 per multiply-add, scanned bodies times their
    length, a cond's costliest branch; the number of while loops met, whose bodies are counted once)."""
    total, whiles = 0.0, 0
    for eqn in jaxpr.eqns:
        name = eqn.primitive.name
        out = math.prod(eqn.outvars[0].aval.shape) if name in ("dot_general", "conv_general_dilated") else 0
        if name == "dot_general":
            (contracting, _), _ = eqn.params["dimension_numbers"]
            lhs = eqn.invars[0].aval.shape
            total += 2.0 * out * math.prod(lhs[d] for d in contracting)
        elif name == "conv_general_dilated":
            # each output element sums the kernel's window x its input features; an input dilated by d (the input
            # gradient of a stride-d convolution) holds zeros but in 1 / prod(d) of those taps, which are not counted
            rhs, spec = eqn.invars[1].aval.shape, eqn.params["dimension_numbers"].rhs_spec
            dilation = math.prod(eqn.params.get("lhs_dilation") or (1,))
            total += 2.0 * out * rhs[spec[1]] * math.prod(rhs[d] for d in spec[2:]) / dilation
        subs = [matrix_flops(sub) for sub in _sub_jaxprs(eqn.params)]
        whiles += (name == "while") + sum(w for _, w in subs)
        if name == "cond":
            total += max((f for f, _ in subs), default=0.0)
        else:
            total += (eqn.params["length"] if name == "scan" else 1) * sum(f for f, _ in subs)
    return total, whiles


def xla_costs(compiled) -> dict:
    """XLA's cost analysis of a compiled program (flops, bytes accessed), each loop's body counted once."""
    costs = compiled.cost_analysis()
    costs = costs[0] if isinstance(costs, (list, tuple)) else costs
    return {"flops": float(costs.get("flops", 0.0)), "bytes": float(costs.get("bytes accessed", 0.0))}


def measured_peak(dtype: str, n: int, chain: int = 8) -> float:
    """TFLOP/s of `chain` dependent n x n matrix products in `dtype` in one program (JAX's default precision)."""
    a = jax.random.normal(jax.random.key(0), (n, n), dtype) / math.sqrt(n)

    @jax.jit
    def products(x):
        return jax.lax.scan(lambda c, _: ((c @ a).astype(dtype), None), x, None, length=chain)[0]

    _, seconds = timed(products, a)
    return 2.0 * n ** 3 * chain / seconds / 1e12


def spec_peak(device_kind: str, dtype: str) -> dict:
    """The datasheet's peaks for the dtype ({} for a device SPEC does not know)."""
    spec = SPEC.get(device_kind)
    if not spec:
        return {}
    out = {"spec_tflops": spec[dtype], "spec_hbm_tb_per_s": spec["hbm_tb_per_s"]}
    if dtype == "float32":
        out["spec_tf32_tflops"] = spec["tf32"]
    return out


def program_flops(fn, *args) -> tuple[float, int]:
    """matrix_flops of fn(*args)'s jaxpr without its dead code (e.g. a custom rule's input gradient of the frames,
    which XLA drops too: conv_impl per-run would otherwise count 60 % more than the same model grouped)."""
    # jaxpr dead-code elimination, which has no public name yet
    from jax._src.interpreters import partial_eval as pe

    jaxpr = jax.make_jaxpr(fn)(*args).jaxpr
    live, _ = pe.dce_jaxpr(jaxpr, [True] * len(jaxpr.outvars))
    return matrix_flops(live)


def roofline(fn, args, frames: int, peak: float, repeats: int = 3) -> dict:
    """The roofline figures of fn(*args) (jit-able; `frames` trained per call) against a measured `peak`."""
    flops, whiles = program_flops(fn, *args)
    from cdjax.runner import budget

    compiled, in_order = budget.compile_fitting(jax.jit(fn).lower(*args))  # as a sweep compiles it
    xla = xla_costs(compiled)
    first, seconds = timed(compiled, *args, repeats=repeats)
    achieved = flops / seconds / 1e12
    return {"flops_per_frame": flops / frames, "xla_flops_per_frame": xla["flops"] / frames,
            "xla_bytes_per_frame": xla["bytes"] / frames, "while_loops_counted_once": whiles,
            "in_order": in_order, "compile_and_first_s": round(first, 3), "update_s": seconds, "frames_per_s": frames / seconds,
            "achieved_tflops": achieved, "measured_peak_tflops": peak, "of_peak": achieved / peak}


# ------------------------------------------------------------------------------------------ the update

def learner_of(config, synthetic: bool):
    """The pixel learner of `config`: on the rendered task, or (synthetic) on SyntheticWorld's frames, which the
    update cannot tell apart (it reads the kept data; only the action size, 2 there, differs from a task's)."""
    if synthetic:
        from cdjax.agents.pixel.learner import PixelLearner
        from cdjax.agents.pixel.synthetic import SyntheticWorld

        return PixelLearner(config, world=SyntheticWorld(config))
    return agents.get("pixel").make_trainer(config).inner


def measure(config, runs: int, variants, peak_n: int, profile: str = "", synthetic: bool = False) -> dict:
    setting = agents.get("pixel")
    device = jax.devices()[0]
    out = {"env": "synthetic" if synthetic else config.env, "arm": config.arm, "core_impl": config.core_impl,
           "image_size": config.image_size, "runs": runs,
           "device": device.device_kind, "platform": device.platform, "jax": jax.__version__,
           "frames_per_update": runs * config.batch_size * config.seq_len, "variants": {}}
    peaks = {}
    for variant in variants:
        dtype, impl = variant.split("/")
        if dtype not in peaks:
            peaks[dtype] = measured_peak(dtype, peak_n)
        learner = learner_of(config.replace(compute_dtype=dtype, conv_impl=impl), synthetic)
        hps = jax.tree.map(lambda x: jnp.full((runs,), x, jnp.float32), setting.hparams_type())
        states = jax.jit(jax.vmap(learner.init))(jax.random.split(jax.random.key(0), runs), hps)
        update = jax.vmap(learner.update)
        row = roofline(update, (states, hps), out["frames_per_update"], peaks[dtype]) | spec_peak(device.device_kind,
                                                                                                  dtype)
        if profile:
            row["profile"] = profiled(update, states, hps, pathlib.Path(profile) / variant.replace("/", "-"))
        out["variants"][variant] = row
        print(variant, json.dumps({k: v for k, v in row.items() if k != "profile"}), flush=True)
    return out


def profiled(update, states, hps, where: pathlib.Path) -> dict:
    """Where the time of two steady-state updates goes (benchmarks.profile_summary's groups); DIR.md its tables."""
    from benchmarks import profile_summary

    from cdjax.runner import budget

    compiled, _ = budget.compile_fitting(jax.jit(update).lower(states, hps))
    jax.block_until_ready(compiled(states, hps))
    with profile_summary.trace(where, compiled):
        for _ in range(2):
            jax.block_until_ready(compiled(states, hps))
    summary = profile_summary.summarize(where)
    where.with_suffix(".md").write_text(profile_summary.markdown(summary))
    return {g["group"]: round(g["pct"], 1) for g in summary["groups"]}


def table(result: dict) -> str:
    """A markdown table of the variants."""
    lines = [(f"{result['device']} ({result['platform']}, jax {result['jax']}): {result['env']} {result['arm']}, "
              f"{result['runs']} runs, {result['frames_per_update']:,} frames per update, core_impl "
              f"{result.get('core_impl', 'flax')}"), "",
             ("| variant | GFLOP/frame | XLA GFLOP/frame (loops once) | ms/update | frames/s | TFLOP/s | measured peak "
              "| of peak | spec peak |"), "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for name, r in result["variants"].items():
        spec = r.get("spec_tflops")
        lines.append(f"| {name} | {r['flops_per_frame'] / 1e9:.3f} | {r['xla_flops_per_frame'] / 1e9:.3f} | "
                     f"{1e3 * r['update_s']:.2f} | {r['frames_per_s']:,.0f} | {r['achieved_tflops']:.3g} | "
                     f"{r['measured_peak_tflops']:.3g} | {100 * r['of_peak']:.1f} % | "
                     f"{'' if spec is None else f'{spec:g}'} |")
    return "\n".join(lines)


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="halfcheetah")
    parser.add_argument("--arm", default="ltq-cd")
    parser.add_argument("--runs", type=int, default=30, help="runs vmapped (halfcheetah's preset sweep: 30)")
    parser.add_argument("--variants", nargs="*", default=list(VARIANTS), help="COMPUTE_DTYPE/CONV_IMPL ...")
    parser.add_argument("--set", nargs="*", default=[], help="PixelConfig overrides NAME=VALUE")
    parser.add_argument("--peak-n", type=int, default=8192, help="size of the peak's matrix products")
    parser.add_argument("--synthetic", action="store_true", help="SyntheticWorld's frames instead of the task's")
    parser.add_argument("--tiny", action="store_true",
                        help="pixel-tiny on synthetic frames, 2 runs, 512 x 512 products (a CPU check of the tool)")
    parser.add_argument("--profile", default="", help="trace each variant under this directory (DIR/VARIANT.md)")
    parser.add_argument("--out", default="", help="the JSON result (and OUT with .md: the table)")
    args = parser.parse_args(argv)
    runtime.configure(cache_dir=runtime.default_cache_dir())
    setting = agents.get("pixel")
    preset = "pixel-tiny" if args.tiny else f"pixel-{args.env}"
    given = dict(setting.presets[preset].config, arm=args.arm) | overrides(args.set)
    runs, peak_n = (2, 512) if args.tiny else (args.runs, args.peak_n)
    start = time.perf_counter()
    result = measure(setting.config_type(**given), runs, args.variants, peak_n, args.profile,
                     synthetic=args.synthetic or args.tiny)
    result["wall_s"] = round(time.perf_counter() - start, 1)
    print(table(result))
    write_json(result, args.out)
    if args.out:
        pathlib.Path(args.out).with_suffix(".md").write_text(table(result) + "\n")
    return result


if __name__ == "__main__":
    main()
