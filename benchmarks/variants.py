"""What-if variants of the observation-space agent, for finding what one part of a compiled update costs on a GPU.

    python -m benchmarks.variants VARIANT -- BENCHMARK-ARGS
    python -m benchmarks.variants no-loss-metrics -- --suite compare --cases mbmf --trace DIR --out DIR

A variant is a named change to the agent's loss functions or consistency chain, applied in this process only, before
`benchmarks.run` builds its programs with BENCHMARK-ARGS; set it beside the same benchmark without the variant
(`none`, or a plain `python -m benchmarks.run`) on the same machine. Training never uses a variant.

Variants:
  none             the agent unchanged.
  no-loss-metrics  the losses' logged diagnostics that are not loss terms (PPO's approx_kl and clip_fraction, the
                   model's one-step and reward MSE) are zeros, so XLA drops their computations; the gradients are
                   unchanged. What those diagnostics still cost. Before the SGD took them as per-sample shares
                   reduced once per update (`numerics.masked_share`), XLA fused the reward MSE's per-minibatch sum
                   with the losses' backward into a one-block kernel: 67 ms of an Mb-Mf update's 0.528 s, 0.461 s
                   with this variant (2026-11-25, H100); with the shares Mb-Mf ran 0.460 s.
  scalar-loss-metrics  the SGD's logged loss values (loss/total, loss/ppo, loss/policy, loss/value, loss/entropy,
                   loss/model_nll) as scalars in every step, as before 2026-11-27, instead of per-sample shares reduced
                   once per update (`agent.SHARED_TERMS`); the same gradients and logged means. What those per-step
                   reductions cost: under vmap XLA fused two of them with the losses' backward into a 3-block kernel
                   (benchmarks/results/2026-11-27-h100-hlo-seeds/).
  bias-sum         the fused consistency chain's weight gradients as the kernel's matrix product and the bias's
                   separate sum, instead of one product of [inputs, 1] with the cotangents (`consistency._outer`).
                   The same gradients up to rounding; on an H100 (2026-11-25) paper-CD's update took 0.839 s with
                   it against 0.805 s without.
  outer-dense      every dense layer of the agent's MLPs (policy, value, dynamics model; not Brax PPO's) with a
                   backward that gives its kernel's and bias's gradients as one product of [inputs, 1] with the
                   outputs' cotangents (`consistency._outer`, as the fused chain does), instead of XLA's product and a
                   two-stage bias sum. The same parameters and, up to rounding, the same gradients. On an H100
                   (2026-11-27, benchmarks/results/2026-11-27-h100-hlo-model-free/) about 35 of model-free's 104
                   kernels per SGD step were the dense layers' bias and split-K reductions.
  grad-chunks      the fused consistency chain's weight gradients as sums of one product per 5 steps
                   (`consistency.GRAD_CHUNK`), not one product over all k steps after the backward loop: each chunk's
                   products depend only on its own steps' arrays, so with the GPU's data-flow scheduling they may run
                   beside the rest of the backward, and no stack of all k steps' arrays waits at the end of each SGD
                   step (on an H100, 2026-11-27, two such concatenations took about 21 ms of paper-CD's 0.618 s
                   update, benchmarks/results/2026-11-27-h100-per-program/). The same gradients up to rounding.
  (inplace-stacks, the fused chain's large per-step arrays written into their slots of one buffer per kind as the
  steps ran (the hidden units' and states' buffers starting as ones, their bias column in place) instead of
  concatenated after the loops, was reverted after its A/B: at one seed paper-CD 0.6005 and 0.6009 s/update against
  0.5973 and 0.6147 concatenated (ABBA), at 10 seeds 0.6546 against 0.5823; one H100, 2026-11-28,
  benchmarks/results/2026-11-28-h100-stacks/, code in c09c318.)
  (split-chain, the fused chain in a split form: the model's k steps first, then the GRU's imagined inputs in one
  product and the GRU's k steps, backward the GRU's chain, the model's share of its cotangents in one product and the
  model's chain, the hidden widths zero-padded to a multiple of 32, was removed after its A/B: paper-CD 0.6595 s/update
  against 0.6070 merged (1.70x Mb-Mf against 1.53x, each in its process), 10 seeds 0.5789 against 0.5653; 469 kernels
  per SGD step against 471 (the pads' work went to add and select fusions); one H100, 2026-11-27,
  benchmarks/results/2026-11-27-h100-split/.)
  (autodiff-gates, the fused chain's GRU backward by autodiff of its gates against `consistency.gru_gates_vjp`, a
  written backward whose cotangents were one concatenation each, was removed with that function after its A/B: the
  written one launched 472 kernels per SGD step against 471, 10 vmapped seeds 0.5687 against 0.5693 s/update, one
  H100, 2026-11-27, benchmarks/results/2026-11-27-h100-gates/.)
  (pad-hidden, the fused chain's hidden widths zero-padded to a multiple of 128 once per minibatch, was removed
  after its A/B: paper-CD 0.7306 s/update with it against 0.7304 s without, one H100, 2026-11-25,
  benchmarks/results/2026-11-25-h100-probes/.)
  (pallas-chain, the chain as two Pallas kernels (cdjax.kernels.chain, commit 7cc54f8), was removed with them:
  paper-CD 0.982 s/update with it against 0.732 s with XLA's chain, and its gradients off by up to 3e-2 relative on
  the GPU, one H100, 2026-11-26, benchmarks/results/2026-11-26-h100-pallas/.)
  (narrow-highest and narrow-wide, the chain's two narrow per-step products (the model's output layer forward, the
  states' cotangent backward) at float32's highest precision and with the weights zero-padded to 128 output columns,
  were removed with the hook they swapped (`consistency._narrow`) after their A/B: paper-CD 0.7633 and 0.7399
  s/update against 0.7291 s with the plain products, one H100, 2026-11-26, benchmarks/results/2026-11-26-h100-narrow/.)
  (chain-stream, the fused chain's forward and backward each as a call annotated with a second GPU stream and not to
  be inlined (`jax.experimental.scheduling_groups.xla_metadata_call`), under
  XLA_FLAGS=--xla_gpu_experimental_stream_annotation=true, so that XLA might run the chain beside PPO's and the
  model's losses, was removed after its A/B: paper-CD 0.7687 s/update with it, 0.7675 s with the calls but without
  the flag, against 0.7335 s plain; 10 vmapped seeds 1.76x Mb-Mf; one H100, 2026-11-26,
  benchmarks/results/2026-11-26-h100-stream/.)
  (merged-products, the fused chain's per-step products of the next inputs (the normalised state times
  [W1_x | W_i], the hidden states times W_h) and the two of their cotangents each as one block-diagonal product, was
  removed after its A/B: paper-CD 0.7982 and 0.8031 s/update with it against 0.7338 and 0.7355 s without, one H100,
  2026-11-26, benchmarks/results/2026-11-26-h100-merged/.)
  (skinny-reduce, the chain's narrow per-step products (the model's output layer forward, the states' cotangent
  backward) as a fused multiply-and-sum instead of split-K dots, was tried and not kept: paper-CD 0.7601 s/update
  with it against 0.7304 s without, one H100, 2026-11-26, benchmarks/results/2026-11-26-h100-compare/.)
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import inspect
from typing import Callable, Iterator

import jax
import jax.numpy as jnp

import flax.linen as nn

from benchmarks.common import Parser, refuse
from cdjax import consistency
from cdjax.agents.obs import agent, losses, networks

# the diagnostics (not loss terms) each loss function returns, by function name
LOSS_METRICS = {"policy_terms": ("ppo/approx_kl", "ppo/clip_fraction"),
                "model_loss": ("model/onestep_mse", "model/reward_mse")}


def _zeroing(fn: Callable, names: tuple[str, ...]) -> Callable:
    """fn with the metrics `names` of its (loss, metrics) result replaced by zeros of their shapes."""

    @functools.wraps(fn)
    def wrapped(*args, **kwargs):
        loss, metrics = fn(*args, **kwargs)
        return loss, {k: jnp.zeros_like(v) if k in names else v for k, v in metrics.items()}

    return wrapped


def _outer_bias_sum(a: jax.Array, b: jax.Array) -> tuple[jax.Array, jax.Array]:
    """consistency._outer's (kernel, bias) gradient as the kernel's product a^T b and the bias's sum of b."""
    b = b.reshape(-1, b.shape[-1])
    return a.reshape(-1, a.shape[-1]).T @ b, b.sum(0)


# the loss values the SGD logs as per-sample shares since 2026-11-27 (`scalar-loss-metrics` undoes it), by function
SCALAR_LOSSES = {"policy_terms": ("loss/policy", "loss/value", "loss/entropy", "loss/ppo"),
                 "model_loss": ("loss/model_nll",)}


def _scalar_losses(fn: Callable, names: tuple[str, ...]) -> Callable:
    """fn whose metrics `names` are the masked means (scalars) even when it is asked for shares."""

    signature = inspect.signature(fn)

    @functools.wraps(fn)
    def wrapped(*args, **kwargs):
        loss, metrics = fn(*args, **kwargs)
        bound = signature.bind(*args, **kwargs)
        if bound.arguments.get("shares"):
            bound.arguments["shares"] = False
            _, scalars = fn(*bound.args, **bound.kwargs)  # the same computation but the means: XLA shares the rest
            metrics = {**metrics, **{k: scalars[k] for k in names}}
        return loss, metrics

    return wrapped


@jax.custom_vjp
def _affine(x: jax.Array, kernel: jax.Array, bias: jax.Array) -> jax.Array:
    return x @ kernel + bias


def _affine_fwd(x, kernel, bias):
    return x @ kernel + bias, (x, kernel)


def _affine_bwd(residuals, g):
    x, kernel = residuals
    dkernel, dbias = consistency._outer(x, g)  # summed over every leading axis, the bias as the product's last row
    return g @ kernel.T, dkernel, dbias


_affine.defvjp(_affine_fwd, _affine_bwd)


class _OuterDense(nn.Dense):
    """flax's Dense (the same parameters, initialisers and outputs) whose kernel and bias gradients are one product."""

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        kernel = self.param("kernel", self.kernel_init, (jnp.shape(x)[-1], self.features), self.param_dtype)
        bias = self.param("bias", self.bias_init, (self.features,), self.param_dtype)
        return _affine(x, kernel, bias)


_OuterDense.__name__ = "Dense"  # flax names a submodule by its class: Dense_0, ... as with flax's own


VARIANTS = ("none", "no-loss-metrics", "scalar-loss-metrics", "bias-sum", "outer-dense", "grad-chunks")


@contextlib.contextmanager
def applied(variant: str) -> Iterator[None]:
    """The agent with `variant` while the block runs (programs traced inside it keep it); restored after."""
    if variant not in VARIANTS:
        raise ValueError(f"unknown variant {variant!r}: one of {', '.join(VARIANTS)}")
    saved = {name: getattr(losses, name) for name in LOSS_METRICS}
    outer, shared_terms, share_metrics = consistency._outer, dict(agent.SHARED_TERMS), agent.ObsAgent.share_metrics
    dense, grad_chunk = networks.Dense, consistency.GRAD_CHUNK
    if variant == "no-loss-metrics":
        for name, metrics in LOSS_METRICS.items():
            setattr(losses, name, _zeroing(saved[name], metrics))
    if variant == "scalar-loss-metrics":
        for name, metrics in SCALAR_LOSSES.items():
            setattr(losses, name, _scalar_losses(saved[name], metrics))
        agent.SHARED_TERMS.clear()  # loss/total: the scalar terms' total spread over the samples
        scalars = {m for names in SCALAR_LOSSES.values() for m in names}
        agent.ObsAgent.share_metrics = lambda self: tuple(n for n in share_metrics(self) if n not in scalars)
    if variant == "bias-sum":
        consistency._outer = _outer_bias_sum
    if variant == "outer-dense":
        networks.Dense = _OuterDense
    if variant == "grad-chunks":
        consistency.GRAD_CHUNK = 5
    try:
        yield
    finally:
        for name, fn in saved.items():
            setattr(losses, name, fn)
        consistency._outer = outer
        networks.Dense = dense
        consistency.GRAD_CHUNK = grad_chunk
        agent.SHARED_TERMS.clear()
        agent.SHARED_TERMS.update(shared_terms)
        agent.ObsAgent.share_metrics = share_metrics


def main(argv=None) -> dict:
    """Bad input (an unknown variant, BENCHMARK-ARGS that `benchmarks.run` refuses, --merge, which builds no program)
    ends in one sentence with exit status 2 before the variant is applied or anything runs."""
    from benchmarks import run

    p = Parser(prog="python -m benchmarks.variants", description=__doc__,
               formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("variant", choices=VARIANTS)
    p.add_argument("benchmark_args", nargs=argparse.REMAINDER, help="after --: the arguments of benchmarks.run")
    args = p.parse_args(argv)
    rest = args.benchmark_args[1:] if args.benchmark_args[:1] == ["--"] else args.benchmark_args
    if run.parse(list(rest)).merge:  # (run's own refusals, in its name, first)
        refuse(p.prog, "a variant applies to the programs benchmarks.run builds, and --merge builds none: merge with "
                       "`python -m benchmarks.run --merge` alone")
    print(f"variant: {args.variant}", flush=True)
    with applied(args.variant):
        return run.main(rest)


if __name__ == "__main__":
    main()
