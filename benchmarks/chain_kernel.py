"""The chain's CUDA kernels (`cdjax.kernels.chain`) against XLA's fused chain on this GPU: accuracy and time (issue 21).

    python -m benchmarks.chain_kernel [--out DIR] [--windows 512 --seeds 10 --seed-windows 32 --calls 50]

Accuracy, at the ant's widths: the gradient of `benchmarks.chain_check`'s objective (a loss on both encodings and the
final state) with respect to every input, through the kernels and through XLA's fused chain at JAX's default matmul
precision, each against JAX's own gradient of the plain loop at the highest precision, with one normalised input for
the model and the encoder (`shared`) and with two. Then the same under vmap over seeds (each seed its own weights and
rows): the kernels' gradients against XLA's fused chain's at the highest precision, seed by seed.

Time: one jitted value-and-gradient of the objective, the forward and backward of the whole chain, XLA's fused chain
against the kernels: one seed of `--windows` rows (the compare suite's minibatch has 512), and `--seeds` vmapped seeds
of `--seed-windows` rows (the seeds suite's: 10 of 32). The median of `--calls` calls after a warm-up. Prints tables and
writes DIR/results.json.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import pathlib
import time

import jax
import jax.numpy as jnp
import numpy as np

from benchmarks import chain_check as cc_check
from cdjax import consistency as cc
from cdjax import normalize as nz
from cdjax.kernels import chain as chain_kernel


def _objective_fn(enc_obs, weights, scales, shared: bool, kernel: bool):
    def f(model, gru, s0, actions, x_re):
        return cc_check._objective(weights, *cc.fused_chain(model, gru, s0, actions, x_re, enc_obs, scales, shared,
                                                             kernel=kernel))
    return f


def _problem(windows: int, seed: int, shared: bool, sizes: dict):
    model, gru, s0, actions, x_re, enc_obs, weights = cc_check._problem(windows, seed=seed, **sizes)
    if not shared:  # the encoder's own statistics, unlike the model's
        enc_obs = nz.update(nz.RunningStats.create(s0.shape[-1]), 2.0 * jax.random.normal(jax.random.key(seed + 99),
                                                                                           (4096, s0.shape[-1])) + 0.5)
    return (model, gru, s0, actions, x_re), enc_obs, weights


# (row name, $CDJAX_CHAIN_KERNEL while the row's programs are traced; None: XLA's chain); main adds the cluster kernels
KERNELS = (("kernels", "1"),)


@contextlib.contextmanager
def _mode(mode: str | None):
    """$CDJAX_CHAIN_KERNEL = mode while the block traces (restored after); None leaves it."""
    before = os.environ.get(chain_kernel.SWITCH_ENV)
    if mode is not None:
        os.environ[chain_kernel.SWITCH_ENV] = mode
    try:
        yield
    finally:
        if before is None:
            os.environ.pop(chain_kernel.SWITCH_ENV, None)
        else:
            os.environ[chain_kernel.SWITCH_ENV] = before


def _cases(xla: str, kernels: tuple) -> tuple:
    return ((xla, None),) + tuple(kernels)


def accuracy(windows: int, sizes: dict, seed: int = 0, kernels: tuple = KERNELS) -> dict:
    scales = (1.0, 0.5)
    grad = lambda f: jax.jit(jax.value_and_grad(f, argnums=tuple(range(5))))  # noqa: E731
    rows = {}
    for shared in (True, False):
        args, enc_obs, weights = _problem(windows, seed, shared, sizes)
        plain = lambda *a: cc_check._plain(enc_obs, weights, scales, *a)  # noqa: E731
        with jax.default_matmul_precision("highest"):
            v_ref, g_ref = grad(plain)(*args)
        for name, mode in _cases("XLA's fused chain", kernels):
            with _mode(mode):
                v, g = grad(_objective_fn(enc_obs, weights, scales, shared, mode is not None))(*args)
            rows[f"{name}, shared={shared}"] = {"value": abs(float(v) - float(v_ref)) / abs(float(v_ref)),
                                                **cc_check._errors(g, g_ref)}
    return rows


def vmapped_accuracy(seeds: int, windows: int, sizes: dict, shared: bool = False, kernels: tuple = KERNELS) -> dict:
    """Per kernel row and input, the largest over seeds of max |g_kernel - g_xla| / max |g_xla| (XLA at the highest
    precision)."""
    scales = (1.0, 0.5)
    problems = [_problem(windows, s, shared, sizes) for s in range(seeds)]
    stack = lambda *xs: jax.tree.map(lambda *l: jnp.stack(l), *xs)  # noqa: E731
    args = stack(*[p[0] for p in problems])
    enc_obs, weights = problems[0][1], problems[0][2][:, :windows]

    def batched(kernel):
        f = jax.value_and_grad(_objective_fn(enc_obs, weights, scales, shared, kernel), argnums=tuple(range(5)))
        return jax.jit(jax.vmap(f))

    with jax.default_matmul_precision("highest"):
        _, g_x = batched(False)(*args)
    out = {}
    for row, mode in kernels:
        with _mode(mode):
            _, g_k = batched(True)(*args)
        worst = out[row] = {}
        for i in range(seeds):
            pick = lambda t: jax.tree.map(lambda x: x[i], t)  # noqa: E731
            for name, e in cc_check._errors(pick(g_k), pick(g_x)).items():
                worst[name] = max(worst.get(name, 0.0), e)
    return out


def _median_s(f, args, calls: int) -> float:
    jax.block_until_ready(f(*args))
    times = []
    for _ in range(calls):
        t0 = time.perf_counter()
        jax.block_until_ready(f(*args))
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def timing(windows: int, seeds: int, seed_windows: int, calls: int, sizes: dict, shared: bool = False,
           kernels: tuple = KERNELS) -> dict:
    scales = (1.0, 0.5)
    out = {}
    args, enc_obs, weights = _problem(windows, 0, shared, sizes)
    for name, mode in _cases("xla", kernels):
        with _mode(mode):
            f = jax.jit(jax.value_and_grad(_objective_fn(enc_obs, weights, scales, shared, mode is not None),
                                           argnums=tuple(range(5))))
            out[f"1 x {windows}, {name}"] = _median_s(f, args, calls)
            f = jax.jit(_objective_fn(enc_obs, weights, scales, shared, mode is not None))
            out[f"1 x {windows}, {name}, forward only"] = _median_s(f, args, calls)
    problems = [_problem(seed_windows, s, shared, sizes) for s in range(seeds)]
    bargs = jax.tree.map(lambda *l: jnp.stack(l), *[p[0] for p in problems])
    w = weights[:, :seed_windows]
    for name, mode in _cases("xla", kernels):
        with _mode(mode):
            f = jax.jit(jax.vmap(jax.value_and_grad(_objective_fn(enc_obs, w, scales, shared, mode is not None),
                                                    argnums=tuple(range(5)))))
            out[f"{seeds} x {seed_windows}, {name}"] = _median_s(f, bargs, calls)
    return out


FORWARD_OUTPUTS = ("u", "states", "xin", "both_im", "hh", "hs")
BACKWARD_OUTPUTS = ("dgi", "dhh", "dz", "dz1", "ds0")


def kernel_inputs(windows: int, sizes: dict, shared: bool, seed: int = 0) -> tuple:
    """The kernels' own inputs (`cdjax.kernels.chain.forward`'s arguments after `clip`) for `_problem`'s chain, as
    `consistency._chain_fwd` builds them."""
    (model, gru, s0, actions, x_re), enc_obs, _ = _problem(windows, seed, shared, sizes)
    (w_1, b_1), (w_out, b_out) = model.layers
    w_i, b_i, w_h, b_hn = gru
    O = s0.shape[-1]
    w_in = cc._input_weights(w_1, w_i, O, shared)
    stats = cc._kernel_stats(dict(model_obs=model.obs, enc_obs=enc_obs, delta=model.delta))
    return (s0, actions @ w_1[O:] + b_1, x_re @ w_i + b_i, w_in, w_out, b_out, w_h, b_i, b_hn, stats)


def compare_modes(windows: int, sizes: dict, modes=("1", "cluster")) -> dict:
    """The kernels' forward, then their backward on the first mode's residuals and a fixed cotangent, in each mode:
    per output, max |x - x_first| / max |x_first| against the first mode (which output a wrong index spoils)."""
    out = {}
    for shared in (True, False):
        args = kernel_inputs(windows, sizes, shared)
        s0, w_in, w_out, w_h, b_i, b_hn, stats = args[0], args[3], args[4], args[6], args[7], args[8], args[9]
        key_h, key_s = jax.random.split(jax.random.key(7))
        W, H = s0.shape[0], w_h.shape[0]
        dh, ds = jax.random.normal(key_h, (2 * W, H)), jax.random.normal(key_s, s0.shape)
        results = {}
        for mode in modes:
            with _mode(mode):
                fwd = jax.jit(lambda *a: chain_kernel.forward(nz.CLIP, *a))(*args)
                if mode == modes[0]:
                    residuals = fwd
                u, _, xin, both_im, hh, hs = residuals
                bwd = jax.jit(lambda *a: chain_kernel.backward(nz.CLIP, *a))(u, xin, both_im, hh, hs, args[2], w_in,
                                                                             w_out, w_h, b_i, b_hn, stats, dh, ds)
            results[mode] = dict(zip(FORWARD_OUTPUTS + BACKWARD_OUTPUTS, tuple(fwd) + tuple(bwd)))
        first = results[modes[0]]
        for mode in modes[1:]:
            out[f"{mode} vs {modes[0]}, shared={shared}"] = {
                name: float(jnp.abs(x - first[name]).max() / jnp.maximum(jnp.abs(first[name]).max(), 1e-30))
                for name, x in results[mode].items()}
    return out


def trace(directory: str, windows: int, sizes: dict, shared: bool = False) -> None:
    """jax.profiler traces of 5 calls of the single-seed value-and-gradient, XLA's chain (DIR/xla) and the kernels'
    (DIR/kernels), for `benchmarks.profile_summary`."""
    args, enc_obs, weights = _problem(windows, 0, shared, sizes)
    for name, kernel in (("xla", False), ("kernels", True)):
        f = jax.jit(jax.value_and_grad(_objective_fn(enc_obs, weights, (1.0, 0.5), shared, kernel),
                                       argnums=tuple(range(5))))
        jax.block_until_ready(f(*args))
        with jax.profiler.trace(str(pathlib.Path(directory) / name), create_perfetto_trace=True):
            for _ in range(5):
                jax.block_until_ready(f(*args))


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(prog="python -m benchmarks.chain_kernel", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", help="directory for results.json")
    p.add_argument("--windows", type=int, default=512)
    p.add_argument("--seeds", type=int, default=10)
    p.add_argument("--seed-windows", type=int, default=32)
    p.add_argument("--calls", type=int, default=50)
    p.add_argument("--horizon", type=int, default=20)
    p.add_argument("--trace", help="also profile 5 calls of each single-seed value-and-gradient into this directory")
    p.add_argument("--skip-accuracy", action="store_true", help="time (and trace) only")
    p.add_argument("--cluster", action="store_true",
                   help="also the cluster kernels (CDJAX_CHAIN_KERNEL=cluster), beside the plain ones")
    p.add_argument("--compare-modes", action="store_true",
                   help="only the plain and the cluster kernels' outputs on the same inputs, output by output")
    p.add_argument("--forward-probe", action="store_true",
                   help="time only the kernels' single-seed forward (with $CDJAX_CHAIN_PROBE: phases skipped)")
    a = p.parse_args(argv)
    os.environ[chain_kernel.SWITCH_ENV] = "1"
    kernels = KERNELS + ((("kernels, clusters", "cluster"),) if a.cluster else ())
    t0 = time.perf_counter()
    lib = chain_kernel.build(verbose=True)
    print(f"built {lib} in {time.perf_counter() - t0:.1f} s")
    sizes = dict(horizon=a.horizon, obs=27, act=8, hidden=500, enc=128)
    result = {"device": str(jax.devices()[0].device_kind), "sizes": sizes}
    if a.compare_modes:
        result["modes"] = compare_modes(a.windows, sizes)
        for row, errors in result["modes"].items():
            print(f"{row}: " + ", ".join(f"{k} {v:.2e}" for k, v in errors.items()))
        cc_check.write_results(a.out, result)
        return result
    if a.forward_probe:
        args, enc_obs, weights = _problem(a.windows, 0, False, sizes)
        f = jax.jit(_objective_fn(enc_obs, weights, (1.0, 0.5), False, True))
        probe = os.environ.get(chain_kernel.PROBE_ENV, "0")
        print(f"probe {probe}: forward {1e3 * _median_s(f, args, a.calls):.3f} ms")
        return result
    if a.trace:
        trace(a.trace, a.windows, sizes)
    if a.skip_accuracy:
        result["seconds"] = timing(a.windows, a.seeds, a.seed_windows, a.calls, sizes, kernels=kernels)
        print(json.dumps(result["seconds"], indent=1))
        return result
    result["accuracy"] = accuracy(a.windows, sizes, kernels=kernels)
    print(f"{result['device']}, {sizes}, {a.windows} rows: relative error against the plain loop at the highest "
          "precision")
    cc_check.print_errors(result["accuracy"])
    result["vmapped"] = vmapped_accuracy(3, a.seed_windows, sizes, kernels=kernels)
    for row, errors in result["vmapped"].items():
        print(f"vmapped (3 seeds x {a.seed_windows} rows, two inputs), {row} against XLA's fused chain at the highest "
              "precision: " + ", ".join(f"{k} {v:.2e}" for k, v in errors.items()))
    result["seconds"] = timing(a.windows, a.seeds, a.seed_windows, a.calls, sizes, kernels=kernels)
    print("| value and gradient of the chain | ms per call |\n| --- | ---: |")
    for name, s in result["seconds"].items():
        print(f"| {name} | {1e3 * s:.3f} |")
    cc_check.write_results(a.out, result)
    return result


if __name__ == "__main__":
    main()
