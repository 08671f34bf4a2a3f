"""How the pixel model's convolutions are computed: the arrangement a sweep's vmap over runs meets, and the dtype
of their operands. `PixelConfig.conv_impl` and `PixelConfig.compute_dtype` choose; model.py asks `conv_kwargs` and
`dense_kwargs` for the keyword arguments of its flax layers.

A sweep vmaps its runs, each with its own weights. `jax.vmap` of a convolution whose input and kernel both carry the
run axis gives one grouped convolution (feature_group_count = runs; the kernel's gradient a grouped convolution
too), a shape GPU libraries often run below their dense speed. A kernel shared by the runs would let the runs fold
into the convolution's batch (that is what vmap does when only the input is batched), but every run here has its own
kernel, so the choice is how the per-run kernels meet:

    grouped   lax.conv_general_dilated as flax calls it (the default; float32 "grouped" is flax's own layer, bit for
              bit the model before these options): under the runs' vmap, grouped convolutions
    per-run   the same convolution, but the runs' vmap gives one ungrouped convolution per run (a custom batching
              rule, also for the input's and the kernel's gradients): R dense convolutions in one program
    auto      per layer: per-run where the layer's input or output has fewer than AUTO_MIN_CHANNELS channels per run
              (the encoder's first layer reads 3 x frame_stack, the decoder's last writes 24: a grouped convolution
              of so few channels per group runs far below its FLOPs: the decoder's last layer alone took most of
              the grouped bfloat16 update's kernel time in the profile of experiments/pixel/data/roofline-h200/),
              grouped elsewhere (wide layers, where the grouped kernels are efficient and per-run's
              slicing and stacking of every run's operands costs more)
    matmul    the convolution as one matrix product of patches (each output pixel's kernel window, gathered by
              strided slices) with the kernel reshaped to [kh*kw*C, O]: under the runs' vmap a batched matrix
              product (the runs its batch dimension). The patches are recomputed in the backward pass rather than
              kept (jax.checkpoint): they are kh*kw/stride^2 times the input (4x for the encoder, 9x for the decoder)

Mixed precision (`compute_dtype="bfloat16"`): the convolutions and the encoder's and decoder's dense layers take
bfloat16 operands (the parameters stay float32 and are cast where used, so their gradients, Adam's moments and
the updates are float32) and their hidden activations are bfloat16; the two layers whose outputs leave the
networks (the encoder's embedding and the decoder's pixel means and scales) accumulate and return float32, so the
ELBO's per-pixel log-densities and every sum over pixels, latents and steps are float32. The LSTM, the prior and
posterior, the policy and the consistency term stay float32 (small products, latency-bound, and recurrent).
"""

from __future__ import annotations

import functools
from typing import Callable

import jax
import jax.numpy as jnp
from jax import lax

NHWC = ("NHWC", "HWIO", "NHWC")


# --------------------------------------------------------------------------------------------- per-run

def per_run(fn: Callable) -> Callable:
    """fn(*arrays) whose vmap calls fn once per element of the mapped axis (a Python loop in the traced program,
    unbatched arguments broadcast) and stacks the results, instead of batching fn's operations."""
    looped = jax.custom_batching.custom_vmap(fn)

    @looped.def_vmap
    def rule(axis_size, in_batched, *args):
        args = [a if b else jnp.broadcast_to(a, (axis_size,) + a.shape) for a, b in zip(args, in_batched)]
        return jnp.stack([fn(*(a[r] for a in args)) for r in range(axis_size)]), True

    return looped


@functools.cache
def _per_run_conv(window_strides, padding, lhs_dilation, rhs_dilation, dimension_numbers, feature_group_count,
                  precision, preferred_element_type):
    """A convolution of fixed static arguments whose value and both gradients are `per_run`."""

    def conv(x, w):
        return lax.conv_general_dilated(x, w, window_strides, padding, lhs_dilation=lhs_dilation,
                                        rhs_dilation=rhs_dilation, dimension_numbers=dimension_numbers,
                                        feature_group_count=feature_group_count, precision=precision,
                                        preferred_element_type=preferred_element_type)

    def grad_x(x, w, g):
        return jax.vjp(lambda x: conv(x, w), x)[1](g)[0]

    def grad_w(x, w, g):
        return jax.vjp(lambda w: conv(x, w), w)[1](g)[0]

    forward, backward_x, backward_w = per_run(conv), per_run(grad_x), per_run(grad_w)

    @jax.custom_vjp
    def run_conv(x, w):
        return forward(x, w)

    def fwd(x, w):
        return forward(x, w), (x, w)

    def bwd(res, g):
        x, w = res
        return backward_x(x, w, g), backward_w(x, w, g)

    run_conv.defvjp(fwd, bwd)
    return run_conv


def _static(value):
    """A hashable form of a convolution argument (tuples for lists and padding pairs)."""
    if isinstance(value, (list, tuple)):
        return tuple(_static(v) for v in value)
    return value


def per_run_conv(lhs, rhs, window_strides, padding, lhs_dilation=None, rhs_dilation=None, dimension_numbers=None,
                 feature_group_count=1, batch_group_count=1, precision=None, preferred_element_type=None):
    """lax.conv_general_dilated's signature and value; under vmap, one ungrouped convolution per run."""
    if batch_group_count != 1:
        raise NotImplementedError("per_run_conv: batch_group_count != 1")
    if dimension_numbers is not None and not isinstance(dimension_numbers, lax.ConvDimensionNumbers):
        dimension_numbers = lax.conv_dimension_numbers(lhs.shape, rhs.shape, dimension_numbers)
    fn = _per_run_conv(_static(window_strides), _static(padding), _static(lhs_dilation), _static(rhs_dilation),
                       dimension_numbers, feature_group_count, precision, preferred_element_type)
    return fn(lhs, rhs)


# ---------------------------------------------------------------------------------------------- matmul

def patches(x: jax.Array, window: tuple[int, int], strides, padding) -> jax.Array:
    """x [N, H, W, C] -> [N, H', W', kh*kw*C]: each output pixel's kernel window, in the order of a HWIO kernel
    reshaped to [kh*kw*C, O] ((i * kw + j) * C + c). Strided slices of the padded input, concatenated."""
    N, H, W, C = x.shape
    (kh, kw), (sh, sw) = window, strides
    pads = lax.padtype_to_pads((H, W), (kh, kw), (sh, sw), padding) if isinstance(padding, str) else padding
    x = jnp.pad(x, ((0, 0), tuple(pads[0]), tuple(pads[1]), (0, 0)))
    oh = (x.shape[1] - kh) // sh + 1
    ow = (x.shape[2] - kw) // sw + 1
    cols = [lax.slice(x, (0, i, j, 0), (N, i + sh * (oh - 1) + 1, j + sw * (ow - 1) + 1, C), (1, sh, sw, 1))
            for i in range(kh) for j in range(kw)]
    return jnp.concatenate(cols, axis=-1)


def matmul_conv(lhs, rhs, window_strides, padding, lhs_dilation=None, rhs_dilation=None, dimension_numbers=None,
                feature_group_count=1, batch_group_count=1, precision=None, preferred_element_type=None):
    """lax.conv_general_dilated's signature and value (NHWC input, HWIO kernel, no dilation, one group) as patches
    times the kernel; under vmap, a batched matrix product. The patches are recomputed for the backward pass."""
    nhwc = lax.conv_dimension_numbers(lhs.shape, rhs.shape, NHWC)
    given = (dimension_numbers if dimension_numbers is None or isinstance(dimension_numbers, lax.ConvDimensionNumbers)
             else lax.conv_dimension_numbers(lhs.shape, rhs.shape, dimension_numbers))
    if given not in (None, nhwc) or feature_group_count != 1 or batch_group_count != 1 or any(
            d not in (None, 1) and tuple(d) != (1, 1) for d in (lhs_dilation, rhs_dilation)):
        raise NotImplementedError("matmul_conv: NHWC/HWIO, no dilation, one group")
    kh, kw, c, o = rhs.shape
    strides = tuple(window_strides)

    @jax.checkpoint
    def product(x, w):
        cols = patches(x, (kh, kw), strides, padding)
        return lax.dot_general(cols, w.reshape(kh * kw * c, o), (((cols.ndim - 1,), (0,)), ((), ())),
                               precision=precision, preferred_element_type=preferred_element_type)

    return product(lhs, rhs)


# ------------------------------------------------------------------------------------------- precision

def operands_in(fn: Callable, dtype, grad_dtype=jnp.float32) -> Callable:
    """fn (lax.conv_general_dilated's or lax.dot_general's signature) with its two operands cast to `dtype`,
    accumulated and returned in float32. `grad_dtype`: the dtype the backward pass casts the result's cotangent to
    (float32: as the result, so the operands' gradients are float32 products, TF32 on a GPU; `dtype`: the gradients
    are products of `dtype` operands, as a hidden layer's are)."""

    def cast(lhs, rhs, *args, **kwargs):
        kwargs["preferred_element_type"] = jnp.float32
        product = fn if jnp.dtype(grad_dtype) == jnp.float32 else _cotangent_in(fn, jnp.dtype(grad_dtype), args, kwargs)
        return product(lhs.astype(dtype), rhs.astype(dtype), *args, **kwargs)

    return cast


def _cotangent_in(fn: Callable, dtype, args, kwargs) -> Callable:
    """fn(lhs, rhs, *args, **kwargs) whose backward pass casts the cotangent to `dtype` and differentiates fn
    without `preferred_element_type` (its result in the operands' dtype), so both gradients are `dtype` products."""
    low = {k: v for k, v in kwargs.items() if k != "preferred_element_type"}

    @jax.custom_vjp
    def product(lhs, rhs):
        return fn(lhs, rhs, *args, **kwargs)

    def forward(lhs, rhs):
        return fn(lhs, rhs, *args, **kwargs), (lhs, rhs)

    def backward(operands, cotangent):
        _, vjp = jax.vjp(lambda lhs, rhs: fn(lhs, rhs, *args, **low), *operands)
        return vjp(cotangent.astype(dtype))

    product.defvjp(forward, backward)
    return lambda lhs, rhs, *_, **__: product(lhs, rhs)  # called with fn's arguments, which it holds


_CONVS = {"grouped": None, "per-run": per_run_conv, "matmul": matmul_conv}
AUTO_MIN_CHANNELS = 32  # conv_impl "auto": layers with fewer input or output channels than this run per-run


def layer_impl(impl: str, channels: tuple[int, int] | None = None) -> str:
    """The arrangement of one layer of (input, output) `channels` per run: `impl`, or for "auto" per-run where
    either is below AUTO_MIN_CHANNELS and grouped elsewhere."""
    if impl != "auto":
        return impl
    if channels is None:
        raise ValueError("conv_impl 'auto' needs the layer's input and output channels")
    return "per-run" if min(channels) < AUTO_MIN_CHANNELS else "grouped"


def conv_kwargs(impl: str, compute_dtype: str, output: bool = False, channels: tuple[int, int] | None = None,
                output_grad: str = "float32") -> dict:
    """Keyword arguments of a flax nn.Conv layer for `impl` and `compute_dtype`; `output`: the layer whose result
    leaves the network (float32 in any compute dtype; `output_grad`: PixelConfig's, the operands of its gradients'
    products, float32 or "compute" (compute_dtype): `operands_in`); `channels`: the layer's (input, output) channels
    per run, which "auto" needs. Float32 "grouped" gives {}: flax's own layer."""
    fn = _CONVS[layer_impl(impl, channels)]
    if compute_dtype == "float32":
        return {} if fn is None else {"conv_general_dilated": fn}
    dtype = jnp.dtype(compute_dtype)
    if output:
        grad_dtype = dtype if output_grad == "compute" else jnp.float32
        return {"conv_general_dilated": operands_in(fn or lax.conv_general_dilated, dtype, grad_dtype)}
    return {"dtype": dtype} | ({} if fn is None else {"conv_general_dilated": fn})


def dense_kwargs(compute_dtype: str, output: bool = False, output_grad: str = "float32") -> dict:
    """Keyword arguments of a flax nn.Dense layer of the encoder or decoder (see conv_kwargs)."""
    if compute_dtype == "float32":
        return {}
    dtype = jnp.dtype(compute_dtype)
    if output:
        return {"dot_general": operands_in(lax.dot_general, dtype, dtype if output_grad == "compute" else jnp.float32)}
    return {"dtype": dtype}
