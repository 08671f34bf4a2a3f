"""The consistency term's fused k-step chain as two Pallas kernels: one launch for its forward, one for its backward.

`cdjax.consistency._chain` runs the chain (an MLPModel stepped k times from real start states, and one GRU over the
real and the imagined states) unrolled in XLA: ~17 small kernels per step, forward and backward, latency bound on a
GPU. Every row (window) is independent of every other row: the forward recursion (states, the model's hidden layers,
the GRU's hidden states) and the backward recursion of the per-row cotangents (of the states, the hidden states and
every layer's outputs). So each kernel runs the whole recursion over k for a tile of rows, one program per tile.
Only the weight gradients sum over rows; they stay what `_chain_bwd` does after its loop, in XLA: one matrix product
each over all steps and rows (`consistency._outer`).

    chain = make_chain()  # `pallas_chain` is make_chain()'s: the contract of consistency._chain
    h_re, h_im, s_k = consistency.fused_chain(model, gru, s0, actions, x_re, enc_obs, scales, shared, chain=chain)

Triton (Pallas' GPU lowering) wants power-of-two tiles and matrix-product operands of at least 16 in each dimension.
The wrapper zero-pads the rows to a multiple of the row tile, and O, H and every hidden width to the next power of two
of at least 16 (500 -> 512, 27 -> 32), and splits the GRU's 3H columns into its three gates. Padded lanes stay
exactly zero and never reach a real lane: relu(0) = 0; the padded statistics are mean 0 and std 1, so a zero state
lane normalises to 0 and a zero output lane denormalises to 0; a GRU lane with zero input, weights, bias and state
has gates r = z = 1/2 and n = 0, so it stays 0; and the weight rows that read padded lanes are zero. Padded rows
are sliced away. float32 throughout; the matrix products at the default precision, as the XLA chain's.

On a GPU the kernels are Triton's, named by passing Triton's compiler parameters (pallas_call's default GPU backend
is Mosaic GPU since jax 0.10). Off a GPU (`jax.default_backend() != "gpu"`) they run in Pallas' interpret mode: the
tests, on CPU, which also lower them for a GPU without one.

    python -m cdjax.kernels.chain  # outputs and gradients against the XLA chain, then both timed (meant for a GPU)
"""

from __future__ import annotations

import argparse
import functools
import time

import jax
import jax.numpy as jnp
import numpy as np
from jax.experimental import pallas as pl

from cdjax import consistency as cc
from cdjax import normalize as nz

BLOCK_ROWS = 16  # rows (windows) per program: the smallest operand dimension Triton's matrix products take
NUM_WARPS = 4  # Triton's warps per program (its default)
# Triton's software-pipelining stages of the kernels' loop over k: 1, none. Its default (3) would prefetch the next
# step's reads, weights included, into shared memory (the steps depend on each other through their carry anyway).
NUM_STAGES = 1
MIN_LANES = 16  # the smallest padded width (the same limit, on the other dimensions)
# The rows of the statistics matrix [8, O'] the kernels read (padded lanes: mean 0, std 1; rows 6-7 unused).
MODEL_MEAN, MODEL_STD, ENC_MEAN, ENC_STD, DELTA_MEAN, DELTA_STD = range(6)


def _lanes(n: int) -> int:
    """The padded width of n lanes: the next power of two, at least MIN_LANES."""
    return max(MIN_LANES, 1 << (n - 1).bit_length())


def _pad(x: jax.Array, shape: tuple, value: float = 0.0) -> jax.Array:
    """x padded at the end of every axis up to `shape` with `value`."""
    return jnp.pad(x, [(0, s - d) for d, s in zip(x.shape, shape)], constant_values=value)


def _gate_major(x: jax.Array, rows: int, lanes: int) -> jax.Array:
    """[..., W, 3H] (gates r, z, n side by side) -> [..., 3, rows, lanes], zero-padded."""
    *lead, W, three_h = x.shape
    x = jnp.moveaxis(x.reshape(*lead, W, 3, three_h // 3), -2, -3)
    return _pad(x, (*lead, 3, rows, lanes))


def _gates_last(x: jax.Array, W: int, H: int) -> jax.Array:
    """`_gate_major`'s inverse: [..., 3, W', H'] -> [..., W, 3H], the padding sliced away."""
    x = jnp.moveaxis(x[..., :W, :H], -3, -2)
    return x.reshape(*x.shape[:-2], 3 * H)


def _statistics(c: dict, lanes: int) -> jax.Array:
    """[8, lanes]: the means and standard deviations the chain normalises with, rows as MODEL_MEAN ... DELTA_STD."""
    rows = []
    for name in ("model_obs", "enc_obs", "delta"):
        rows += [_pad(c[name].mean, (lanes,)), _pad(c[name].std, (lanes,), 1.0)]
    return _pad(jnp.stack(rows), (8, lanes))


def _weights(p: dict, O: int, H: int, lanes: int, h_lanes: int, widths: list) -> dict:
    """The padded weights the kernels read: the first layer's state rows w1x [O', N1'], the middle layers
    [(kernel, bias [1, N'])], the output layer, and the GRU's per gate: w_i [3, O', H'], b_i [3, 1, H'],
    w_h [3, H', H'], b_hn [1, H']."""
    layers = p["layers"]
    gates = lambda w, n: _pad(jnp.moveaxis(w.reshape(w.shape[0], 3, H), 1, 0), (3, n, h_lanes))  # noqa: E731
    mid = tuple((_pad(kernel, (widths[j], widths[j + 1])), _pad(bias[None], (1, widths[j + 1])))
                for j, (kernel, bias) in enumerate(layers[1:-1]))
    w_out, b_out = layers[-1]
    return dict(w1x=_pad(layers[0][0][:O], (lanes, widths[0])), mid=mid, w_out=_pad(w_out, (widths[-1], lanes)),
                b_out=_pad(b_out[None], (1, lanes)), w_i=gates(p["w_i"], lanes),
                b_i=_pad(p["b_i"].reshape(3, 1, H), (3, 1, h_lanes)), w_h=gates(p["w_h"], h_lanes),
                b_hn=_pad(p["b_hn"][None], (1, h_lanes)))


def _row(stats_ref, row: int) -> jax.Array:
    """[1, O']: one row of the statistics matrix."""
    return stats_ref[row:row + 1, :]


def _normalize(stats_ref, row: int, s: jax.Array) -> jax.Array:
    """`normalize.normalize` of states s [rows, O'] by the statistics at rows `row` (mean) and `row` + 1 (std)."""
    return jnp.clip((s - _row(stats_ref, row)) / _row(stats_ref, row + 1), -nz.CLIP, nz.CLIP)


def _normalize_vjp(stats_ref, row: int, s: jax.Array, dx: jax.Array) -> jax.Array:
    """The cotangent of s from dx, that of `_normalize(stats_ref, row, s)`: jnp.clip's (1 inside, 1/2 on a bound as
    jnp.maximum/minimum give at a tie, 0 outside) divided by the std."""
    std = _row(stats_ref, row + 1)
    v = (s - _row(stats_ref, row)) / std
    inside = (v > -nz.CLIP) & (v < nz.CLIP)
    bound = (v == -nz.CLIP) | (v == nz.CLIP)
    return jnp.where(inside, dx, jnp.where(bound, 0.5 * dx, 0.0)) / std


def _dot_t(a: jax.Array, b: jax.Array) -> jax.Array:
    """a @ b.T, as one product."""
    return jax.lax.dot_general(a, b, (((1,), (1,)), ((), ())))


def _relu(x: jax.Array) -> jax.Array:
    return jnp.maximum(x, 0.0)


def _gru(gi: list, gh: list, h: jax.Array, b_hn: jax.Array) -> jax.Array:
    """`consistency.gru_gates` per gate: gi, gh the input and recurrent parts [rows, H'] of gates r, z, n (gh
    without b_hn)."""
    r = jax.nn.sigmoid(gi[0] + gh[0])
    z = jax.nn.sigmoid(gi[1] + gh[1])
    n = jnp.tanh(gi[2] + r * (gh[2] + b_hn))
    return (1.0 - z) * n + z * h


def _gru_vjp(gi: list, gh: list, h: jax.Array, b_hn: jax.Array, dh: jax.Array) -> tuple:
    """`_gru`'s backward from the cotangent dh of its output: (cotangents of gi per gate, of gh per gate, of h)."""
    r = jax.nn.sigmoid(gi[0] + gh[0])
    z = jax.nn.sigmoid(gi[1] + gh[1])
    gh_n = gh[2] + b_hn
    n = jnp.tanh(gi[2] + r * gh_n)
    da_n = dh * (1.0 - z) * (1.0 - n * n)  # of n's argument
    da_r = da_n * gh_n * r * (1.0 - r)  # of r's
    da_z = dh * (h - n) * z * (1.0 - z)  # of z's
    return (da_r, da_z, da_n), (da_r, da_z, da_n * r), dh * z


def _forward_kernel(n_mid: int, shared: bool, k: int, *refs):
    """One tile of rows through the k steps (see `chain_fwd` for the arrays, in this order)."""
    s0_ref, gi_re_ref, z1_ref, stats_ref, w1x_ref = refs[:5]
    mid = [(refs[5 + 2 * j], refs[6 + 2 * j]) for j in range(n_mid)]
    w_out_ref, b_out_ref, w_i_ref, b_i_ref, w_h_ref, b_hn_ref = refs[5 + 2 * n_mid:11 + 2 * n_mid]
    outs = list(refs[11 + 2 * n_mid:])
    states_ref, xm_ref = outs[:2]
    xe_ref = None if shared else outs[2]
    outs = outs[2 if shared else 3:]
    hidden_refs, (gi_im_ref, gh_ref, hs_ref) = outs[:n_mid + 1], outs[n_mid + 1:]

    s = s0_ref[...]
    xm = _normalize(stats_ref, MODEL_MEAN, s)
    states_ref[0] = s
    xm_ref[0] = xm
    h0 = jnp.zeros(hs_ref.shape[2:], jnp.float32)
    hs_ref[0, 0] = h0
    hs_ref[0, 1] = h0

    def step(t, carry):
        s, p1, h_re, h_im = carry
        u = _relu(p1 + z1_ref[t])
        hidden_refs[0][t] = u
        for j, (w_ref, b_ref) in enumerate(mid):
            u = _relu(jnp.dot(u, w_ref[...]) + b_ref[...])
            hidden_refs[j + 1][t] = u
        z = jnp.dot(u, w_out_ref[...]) + b_out_ref[...]
        s = s + (z * _row(stats_ref, DELTA_STD) + _row(stats_ref, DELTA_MEAN))
        states_ref[t + 1] = s
        xm = _normalize(stats_ref, MODEL_MEAN, s)
        xm_ref[t + 1] = xm
        xe = xm
        if not shared:
            xe = _normalize(stats_ref, ENC_MEAN, s)
            xe_ref[t] = xe
        gi_im = [jnp.dot(xe, w_i_ref[g]) + b_i_ref[g] for g in range(3)]
        hs, gh = (h_re, h_im), ([], [])
        for g in range(3):  # each gate's recurrent weights read once for both row kinds
            w = w_h_ref[g]
            for kind in range(2):
                gh[kind].append(jnp.dot(hs[kind], w))
                gh_ref[t, kind, g] = gh[kind][g]
            gi_im_ref[t, g] = gi_im[g]
        hs = [_gru(gi, gh[kind], hs[kind], b_hn_ref[...])
              for kind, gi in enumerate(([gi_re_ref[t, g] for g in range(3)], gi_im))]
        for kind in range(2):
            hs_ref[t + 1, kind] = hs[kind]
        return s, jnp.dot(xm, w1x_ref[...]), hs[0], hs[1]

    jax.lax.fori_loop(0, k, step, (s, jnp.dot(xm, w1x_ref[...]), h0, h0))


def _backward_kernel(n_mid: int, shared: bool, k: int, *refs):
    """One tile of rows back through the k steps (see `chain_bwd` for the arrays, in this order)."""
    dh_ref, ds_ref, states_ref = refs[:3]
    hidden_refs = refs[3:4 + n_mid]
    gi_re_ref, gi_im_ref, gh_ref, hs_ref, stats_ref, w1x_ref = refs[4 + n_mid:10 + n_mid]
    later = list(refs[10 + n_mid:11 + 2 * n_mid])  # layer j + 1's kernel for j = 0..n_mid (the last: the output's)
    w_i_ref, w_h_ref, b_hn_ref = refs[11 + 2 * n_mid:14 + 2 * n_mid]
    dgi_ref, dhh_ref = refs[14 + 2 * n_mid:16 + 2 * n_mid]
    dz_refs = refs[16 + 2 * n_mid:18 + 3 * n_mid]  # of every layer's output, the first layer's first
    ds0_ref = refs[18 + 3 * n_mid]

    def vjp(s, dxm, dxe):  # the cotangent of s from those of its model input and its encoder input
        if shared:
            return _normalize_vjp(stats_ref, MODEL_MEAN, s, dxm + dxe)
        return _normalize_vjp(stats_ref, MODEL_MEAN, s, dxm) + _normalize_vjp(stats_ref, ENC_MEAN, s, dxe)

    def step(i, carry):
        t = k - 1 - i
        dh_re, dh_im, ds, dp1 = carry  # dp1: the cotangent of step t + 1's first layer (zeros after the last step)
        dgi, dhh, dhs = [], [], []
        for kind, dh in enumerate((dh_re, dh_im)):
            gi = [(gi_re_ref if kind == 0 else gi_im_ref)[t, g] for g in range(3)]
            gh = [gh_ref[t, kind, g] for g in range(3)]
            d_gi, d_hh, dh = _gru_vjp(gi, gh, hs_ref[t, kind], b_hn_ref[...], dh)
            dgi.append(d_gi)
            dhh.append(d_hh)
            dhs.append(dh)
        for g in range(3):  # each gate's recurrent weights read once for both row kinds
            w = w_h_ref[g]
            for kind in range(2):
                dgi_ref[t, kind, g] = dgi[kind][g]
                dhh_ref[t, kind, g] = dhh[kind][g]
                dhs[kind] = dhs[kind] + _dot_t(dhh[kind][g], w)
        dxe = _dot_t(dgi[1][0], w_i_ref[0]) + _dot_t(dgi[1][1], w_i_ref[1]) + _dot_t(dgi[1][2], w_i_ref[2])  # imagined
        ds = ds + vjp(states_ref[t + 1], _dot_t(dp1, w1x_ref[...]), dxe)  # every path into s_{t+1}
        dz = ds * _row(stats_ref, DELTA_STD)  # the output layer's
        dz_refs[-1][t] = dz
        for j in reversed(range(n_mid + 1)):
            dz = jnp.where(hidden_refs[j][t] > 0, _dot_t(dz, later[j][...]), 0.0)
            dz_refs[j][t] = dz
        return dhs[0], dhs[1], ds, dz

    dp1 = jnp.zeros(hidden_refs[0].shape[1:], jnp.float32)
    _, _, ds, dp1 = jax.lax.fori_loop(0, k, step, (dh_ref[0], dh_ref[1], ds_ref[...], dp1))
    dxm = _dot_t(dp1, w1x_ref[...])
    ds0_ref[...] = ds + _normalize_vjp(stats_ref, MODEL_MEAN, states_ref[0], dxm)


def _over_row_tiles(kernel, tiled: list, whole: list, out_shapes: list, block_rows: int, interpret: bool | None,
                    num_warps: int | None, num_stages: int | None) -> list:
    """kernel on a grid of row tiles: `tiled` arrays and the outputs (shapes, float32) have their rows second to last
    (a block of `block_rows` of them per program), `whole` arrays are read whole by every program."""
    if interpret is None:
        interpret = jax.default_backend() != "gpu"
    rows = tiled[0].shape[-2]
    assert rows % block_rows == 0 and all(x.shape[-2] == rows for x in tiled), (rows, block_rows)

    def row_tile(shape):
        lead = len(shape) - 2
        return pl.BlockSpec(block_shape=(*shape[:-2], block_rows, shape[-1]),
                            index_map=lambda i: (0,) * lead + (i, 0))

    def every(shape):
        return pl.BlockSpec(block_shape=tuple(shape), index_map=lambda i: (0,) * len(shape))

    extra = {}
    if not interpret:  # Triton's parameters name the backend: pallas_call's default on GPU is Mosaic GPU (jax 0.10)
        from jax.experimental.pallas import triton as pl_triton

        tuned = {name: n for name, n in (("num_warps", num_warps), ("num_stages", num_stages)) if n is not None}
        extra["compiler_params"] = pl_triton.CompilerParams(**tuned)  # None: Triton's defaults
    call = pl.pallas_call(
        kernel, grid=(rows // block_rows,),
        in_specs=[row_tile(x.shape) for x in tiled] + [every(x.shape) for x in whole],
        out_specs=[row_tile(shape) for shape in out_shapes],
        out_shape=[jax.ShapeDtypeStruct(shape, jnp.float32) for shape in out_shapes],
        interpret=interpret, **extra)
    return call(*tiled, *whole)


def chain_fwd(shared: bool, p: dict, c: dict, *, block_rows: int = BLOCK_ROWS, interpret: bool | None = None,
              num_warps: int | None = None, num_stages: int | None = None):
    """`consistency._chain_fwd`'s contract, the k steps in one kernel: -> ((h_re [W, H], h_im [W, H], s_k [W, O]),
    residuals).

    Before the kernel, in XLA as `_chain_fwd`: the real rows' GRU inputs gi_re = x_re W_i + b_i and the actions'
    share of the first layer. The kernel reads per row tile s0, gi_re (per gate), that share, and the padded weights
    and statistics; it writes per step the states s_0..s_k, the model's normalised inputs x_0..x_k, the encoder's
    of the imagined states x_1..x_k (unless `shared`), every hidden layer's output, the imagined rows' GRU inputs
    and both kinds' recurrent products (per gate) and hidden states h_0..h_k: what the backward reads.
    """
    layers, w_i, w_h = p["layers"], p["w_i"], p["w_h"]
    s0, actions, x_re = p["s0"], p["actions"], p["x_re"]
    k, (W, O), H = actions.shape[0], s0.shape, w_h.shape[0]
    assert len(layers) >= 2 and x_re.shape[-1] == w_i.shape[0] == O, (len(layers), x_re.shape, w_i.shape, O)
    w_1, b_1 = layers[0]
    gi_re = x_re @ w_i + p["b_i"]  # [k, W, 3H]
    z1_actions = actions @ w_1[O:] + b_1  # [k, W, N1]
    rows, lanes, h_lanes = -(-W // block_rows) * block_rows, _lanes(O), _lanes(H)
    widths = [_lanes(kernel.shape[1]) for kernel, _ in layers[:-1]]
    wt, stats = _weights(p, O, H, lanes, h_lanes, widths), _statistics(c, lanes)
    gi_re = _gate_major(gi_re, rows, h_lanes)
    tiled = [_pad(s0, (rows, lanes)), gi_re, _pad(z1_actions, (k, rows, widths[0]))]
    whole = [stats, wt["w1x"], *[x for layer in wt["mid"] for x in layer], wt["w_out"], wt["b_out"], wt["w_i"],
             wt["b_i"], wt["w_h"], wt["b_hn"]]
    out_shapes = ([(k + 1, rows, lanes)] * 2 + ([] if shared else [(k, rows, lanes)]) + [(k, rows, n) for n in widths]
                  + [(k, 3, rows, h_lanes), (k, 2, 3, rows, h_lanes), (k + 1, 2, rows, h_lanes)])
    outs = _over_row_tiles(functools.partial(_forward_kernel, len(layers) - 2, shared, k), tiled, whole, out_shapes,
                           block_rows, interpret, num_warps, num_stages)
    states, xm = outs[:2]
    xe = None if shared else outs[2]
    outs = outs[2 if shared else 3:]
    hidden, (gi_im, gh, hs) = outs[:len(widths)], outs[len(widths):]
    residuals = dict(p=p, c=c, weights=wt, stats=stats, gi_re=gi_re, states=states, xm=xm, xe=xe, hidden=hidden,
                     gi_im=gi_im, gh=gh, hs=hs)
    return (hs[k, 0, :W, :H], hs[k, 1, :W, :H], states[k, :W, :O]), residuals


def chain_bwd(shared: bool, residuals: dict, cotangents: tuple, *, block_rows: int = BLOCK_ROWS,
              interpret: bool | None = None, num_warps: int | None = None, num_stages: int | None = None):
    """`consistency._chain_bwd`'s contract: the per-step loop in one kernel, reversed over k, then `_chain_bwd`'s
    products after its loop (the same expressions, in XLA).

    The kernel reads per row tile the cotangents (dh_re, dh_im, ds) and the forward's residuals; it writes per step
    the cotangents of the GRU's input and recurrent parts (per kind and gate) and of every layer's output, and the
    cotangent of s_0.
    """
    r = residuals
    p, c, wt = r["p"], r["c"], r["weights"]
    layers = p["layers"]
    dh_re, dh_im, ds = cotangents
    k, (W, O), H = p["actions"].shape[0], p["s0"].shape, p["w_h"].shape[0]
    rows, lanes, h_lanes = r["states"].shape[1], r["states"].shape[2], r["hs"].shape[-1]
    tiled = [_pad(jnp.stack([dh_re, dh_im]), (2, rows, h_lanes)), _pad(ds, (rows, lanes)), r["states"], *r["hidden"],
             r["gi_re"], r["gi_im"], r["gh"], r["hs"]]
    whole = [r["stats"], wt["w1x"], *[kernel for kernel, _ in wt["mid"]], wt["w_out"], wt["w_i"], wt["w_h"],
             wt["b_hn"]]
    out_shapes = ([(k, 2, 3, rows, h_lanes)] * 2 + [(k, rows, u.shape[-1]) for u in r["hidden"]]
                  + [(k, rows, lanes), (rows, lanes)])
    dgi, dhh, *dz, ds0 = _over_row_tiles(functools.partial(_backward_kernel, len(layers) - 2, shared, k), tiled,
                                         whole, out_shapes, block_rows, interpret, num_warps, num_stages)

    # after the loop: `_chain_bwd`'s products over all steps and rows, on the padding sliced away
    dgi, dhh = _gates_last(dgi, W, H), _gates_last(dhh, W, H)  # [k, 2, W, 3H]
    return cc.chain_gradients(p, c, r["xm"][:k, :W, :O],
                              [u[:, :W, :kernel.shape[1]] for u, (kernel, _) in zip(r["hidden"], layers)],
                              [d[:, :W, :kernel.shape[1]] for d, (kernel, _) in zip(dz, layers)],
                              (r["xm"][1:] if shared else r["xe"])[:, :W, :O], dgi, r["hs"][:k, :, :W, :H], dhh,
                              ds0[:W, :O])


def make_chain(block_rows: int = BLOCK_ROWS, interpret: bool | None = None, num_warps: int | None = NUM_WARPS,
               num_stages: int | None = NUM_STAGES):
    """The chain with these kernels: a function (shared, p, c) -> (h_re, h_im, s_k) with `consistency._chain`'s
    contract and gradient, for `fused_chain(..., chain=)`. block_rows: rows per program (a power of two >= 16);
    interpret: Pallas' interpret mode (None: off a GPU); num_warps, num_stages: Triton's warps per program and
    software-pipelining stages of its loops (None: Triton's defaults)."""
    assert block_rows >= MIN_LANES and block_rows & (block_rows - 1) == 0, block_rows
    options = dict(block_rows=block_rows, interpret=interpret, num_warps=num_warps, num_stages=num_stages)

    @functools.partial(jax.custom_vjp, nondiff_argnums=(0,))
    def chain(shared, p, c):
        return chain_fwd(shared, p, c, **options)[0]

    chain.defvjp(functools.partial(chain_fwd, **options), functools.partial(chain_bwd, **options))
    return chain


pallas_chain = make_chain()


# ---------------------------------------------------------------------------------------------------
# On a GPU: the kernels against the XLA chain, then both timed


def random_inputs(key: jax.Array, rows: int, obs: int, act: int, hidden: tuple, encoder_dim: int, horizon: int,
                  shared: bool) -> tuple:
    """Random arguments of `consistency.fused_chain` at these sizes: (model, gru, s0, actions, x_re, enc_obs), the
    weights at the scale of an initialised network, states spread as normalised ones."""
    keys = iter(jax.random.split(key, 16))
    sizes = (obs + act,) + tuple(hidden) + (obs,)
    layers = tuple((jax.random.normal(next(keys), (a, b)) / np.sqrt(a), 0.1 * jax.random.normal(next(keys), (b,)))
                   for a, b in zip(sizes[:-1], sizes[1:]))

    def stats(scale):
        return nz.update(nz.RunningStats.create(obs), scale * jax.random.normal(next(keys), (256, obs)))

    model = cc.MLPModel(layers=layers, obs=stats(1.0), delta=stats(0.1))
    H = encoder_dim
    gru = (jax.random.normal(next(keys), (obs, 3 * H)) / np.sqrt(obs), 0.1 * jax.random.normal(next(keys), (3 * H,)),
           jax.random.normal(next(keys), (H, 3 * H)) / np.sqrt(H), 0.1 * jax.random.normal(next(keys), (H,)))
    s0 = jax.random.normal(next(keys), (rows, obs))
    actions = jax.random.uniform(next(keys), (horizon, rows, act), minval=-1.0, maxval=1.0)
    x_re = jax.random.normal(next(keys), (horizon, rows, obs))
    return model, gru, s0, actions, x_re, model.obs if shared else stats(1.0)


def _loss_and_grads(chain, inputs: tuple, shared: bool, scales: tuple):
    """jit(value_and_grad) of a fixed linear function of the chain's outputs, with the outputs as aux."""
    model, gru, s0, actions, x_re, enc_obs = inputs
    W, O, H = s0.shape[0], s0.shape[1], gru[2].shape[0]
    keys = jax.random.split(jax.random.key(99), 3)
    weights = [jax.random.normal(key, shape) for key, shape in zip(keys, ((W, H), (W, H), (W, O)))]

    def loss(*args):
        out = cc.fused_chain(*args, enc_obs, scales, shared, chain=chain)
        return sum(jnp.sum(x * w) for x, w in zip(out, weights)), out

    return jax.jit(jax.value_and_grad(loss, argnums=(0, 1, 2, 3, 4), has_aux=True)), (model, gru, s0, actions, x_re)


def differences(chain, inputs: tuple, shared: bool, scales: tuple = (1.0, 1.0)) -> dict:
    """{name: (max abs difference, max relative difference)} of `chain`'s outputs and gradients against the XLA
    chain's on `inputs` (`random_inputs`); relative to the XLA value's largest magnitude in that array."""
    fx, args = _loss_and_grads(None, inputs, shared, scales)
    fp, _ = _loss_and_grads(chain, inputs, shared, scales)
    (_, out_x), grads_x = fx(*args)
    (_, out_p), grads_p = fp(*args)
    found = {}
    named = [(f"out/{name}", a, b) for name, a, b in zip(("h_re", "h_im", "s_k"), out_x, out_p)]
    names = ("model", "gru", "s0", "actions", "x_re")
    grads_x, grads_p = dict(zip(names, grads_x)), dict(zip(names, grads_p))
    named += [(f"grad{jax.tree_util.keystr(path)}", a, b)
              for (path, a), b in zip(jax.tree_util.tree_leaves_with_path(grads_x), jax.tree.leaves(grads_p))]
    for name, a, b in named:
        a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
        if a.size == 0 or not np.any(a):
            continue  # the statistics' zero gradients
        err = float(np.abs(a - b).max())
        found[name] = (err, err / float(np.abs(a).max()))
    return found


def time_chain(chain, inputs: tuple, shared: bool, repeats: int = 50) -> float:
    """Median seconds of one forward and backward of the chain (jitted, synchronised after each call)."""
    f, args = _loss_and_grads(chain, inputs, shared, (1.0, 1.0))
    for _ in range(3):
        jax.block_until_ready(f(*args))
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(f(*args))
        times.append(time.perf_counter() - start)
    return float(np.median(times))


def _tiling(text: str) -> dict:
    """'ROWS:WARPS:STAGES' (e.g. 16:4:1) -> make_chain's block_rows, num_warps, num_stages."""
    rows, warps, stages = (int(x) for x in text.split(":"))
    return dict(block_rows=rows, num_warps=warps, num_stages=stages)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m cdjax.kernels.chain", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--rows", type=int, default=512, help="windows per minibatch (compare suite: 512 of ant)")
    p.add_argument("--obs", type=int, default=27, help="O, the observation size")
    p.add_argument("--act", type=int, default=8, help="A, the action size")
    p.add_argument("--hidden", type=int, nargs="+", default=[500], help="the model's hidden widths")
    p.add_argument("--encoder-dim", type=int, default=128, help="H")
    p.add_argument("--horizon", type=int, default=20, help="k")
    p.add_argument("--tilings", nargs="+", default=[f"{BLOCK_ROWS}:{NUM_WARPS}:{NUM_STAGES}", "32:4:1", "16:8:1",
                                                     "16:4:3"],
                   help="ROWS:WARPS:STAGES per program to time (the first is also checked; default: pallas_chain's "
                        "first); one that fails to compile is reported and skipped")
    p.add_argument("--repeats", type=int, default=50, help="timed calls per implementation")
    p.add_argument("--no-time", action="store_true", help="the differences only")
    args = p.parse_args(argv)
    print(f"backend {jax.default_backend()}, devices {jax.devices()}, jax {jax.__version__}", flush=True)
    sizes = dict(rows=args.rows, obs=args.obs, act=args.act, hidden=tuple(args.hidden), encoder_dim=args.encoder_dim,
                 horizon=args.horizon)
    print(f"sizes {sizes}; checked with rows:warps:stages {args.tilings[0]}", flush=True)
    worst = 0.0
    for shared in (True, False):
        inputs = random_inputs(jax.random.key(0), shared=shared, **sizes)
        for precision in ("default", "highest"):
            with jax.default_matmul_precision(None if precision == "default" else precision):
                found = differences(make_chain(**_tiling(args.tilings[0])), inputs, shared, (1.0, 0.5))
            largest, (err, rel) = max(found.items(), key=lambda item: item[1][1])
            print(f"shared={shared} precision={precision}: largest relative difference {rel:.2e} "
                  f"(abs {err:.2e}) in {largest}", flush=True)
            for name, (e, r) in found.items():
                print(f"    {name:36s} abs {e:.2e} rel {r:.2e}")
            if precision == "highest":
                worst = max(worst, rel)
    if not args.no_time:
        inputs = random_inputs(jax.random.key(0), shared=True, **sizes)
        base = time_chain(None, inputs, True, args.repeats)
        print(f"xla chain: {base * 1e3:.3f} ms per forward+backward", flush=True)
        for tiling in args.tilings:
            try:
                t = time_chain(make_chain(**_tiling(tiling)), inputs, True, args.repeats)
            except Exception as e:  # noqa: BLE001 - e.g. Triton out of shared memory: the others still run
                print(f"pallas chain, rows:warps:stages {tiling}: failed: {type(e).__name__}: {str(e)[:300]}",
                      flush=True)
                continue
            print(f"pallas chain, rows:warps:stages {tiling}: {t * 1e3:.3f} ms per forward+backward "
                  f"({t / base:.2f}x the xla chain's)", flush=True)
    print(f"worst relative difference at precision highest: {worst:.2e}")
    return 0 if worst < 1e-4 else 1


if __name__ == "__main__":
    raise SystemExit(main())
