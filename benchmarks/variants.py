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
  bias-sum         the fused consistency chain's weight gradients as the kernel's matrix product and the bias's
                   separate sum, instead of one product of [inputs, 1] with the cotangents (`consistency._outer`).
                   The same gradients up to rounding; on an H100 (2026-11-25) paper-CD's update took 0.839 s with
                   it against 0.805 s without.
  chain-stream     the fused chain's forward and backward each as a call on a second GPU stream
                   (a call annotated with stream 1 and not to be inlined, `_on_stream`), so that XLA may run the
                   chain's small sequential kernels beside the rest of the minibatch's gradient (PPO's and the model's
                   losses, which do not depend on the chain) rather than after it. XLA:GPU acts on the annotation only
                   with XLA_FLAGS=--xla_gpu_experimental_stream_annotation=true (set it beside the variant; without it
                   the calls run on the one stream). The same function. The term adds about 1.07 ms per minibatch
                   beside Mb-Mf's 0.64 ms (2026-11-26, H100), so overlap could hide up to about half of it.
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
  (skinny-reduce, the chain's narrow per-step products (the model's output layer forward, the states' cotangent
  backward) as a fused multiply-and-sum instead of split-K dots, was tried and not kept: paper-CD 0.7601 s/update
  with it against 0.7304 s without, one H100, 2026-11-26, benchmarks/results/2026-11-26-h100-compare/.)
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import os
from typing import Callable, Iterator

import jax
import jax.numpy as jnp

from cdjax import consistency
from cdjax.agents.obs import losses

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


VARIANTS = ("none", "no-loss-metrics", "bias-sum", "chain-stream")

CHAIN_STREAM = "gpu_stream:1"  # the compute type of the chain's calls under `chain-stream`


def _on_stream(fn: Callable) -> Callable:
    """fn (arrays in, a tree of arrays out) as one call XLA:GPU may put on the stream CHAIN_STREAM names: a call
    whose frontend attributes are the stream annotation and `inlineable = "false"`
    (`jax.experimental.scheduling_groups.xla_metadata_call`), the ops inside it unannotated. Where this jax lacks
    that, a jitted call traced under `compute_on(CHAIN_STREAM)`, which annotates every call inside it too."""
    try:
        from jax.experimental.scheduling_groups import xla_metadata_call
    except ImportError:
        from jax.experimental.compute_on import compute_on

        jitted = jax.jit(fn)

        def call(*args):
            with compute_on(CHAIN_STREAM):
                return jitted(*args)

        return call
    return xla_metadata_call(fn, _xla_stream_annotation=CHAIN_STREAM.split(":")[1], inlineable="false")


def _chain_on_stream() -> Callable:
    """consistency._chain with its forward and backward each run as a call on CHAIN_STREAM: the same custom_vjp,
    its rules wrapped."""

    @functools.partial(jax.custom_vjp, nondiff_argnums=(0,))
    def chain(shared, p, c):
        return _on_stream(lambda p, c: consistency._chain_fwd(shared, p, c)[0])(p, c)

    def fwd(shared, p, c):
        return _on_stream(functools.partial(consistency._chain_fwd, shared))(p, c)

    def bwd(shared, residuals, cotangents):
        return _on_stream(functools.partial(consistency._chain_bwd, shared))(residuals, cotangents)

    chain.defvjp(fwd, bwd)
    return chain


@contextlib.contextmanager
def applied(variant: str) -> Iterator[None]:
    """The agent with `variant` while the block runs (programs traced inside it keep it); restored after."""
    if variant not in VARIANTS:
        raise ValueError(f"unknown variant {variant!r}: one of {', '.join(VARIANTS)}")
    saved = {name: getattr(losses, name) for name in LOSS_METRICS}
    outer, chain = consistency._outer, consistency._chain
    if variant == "no-loss-metrics":
        for name, metrics in LOSS_METRICS.items():
            setattr(losses, name, _zeroing(saved[name], metrics))
    if variant == "bias-sum":
        consistency._outer = _outer_bias_sum
    if variant == "chain-stream":
        consistency._chain = _chain_on_stream()
    try:
        yield
    finally:
        for name, fn in saved.items():
            setattr(losses, name, fn)
        consistency._outer, consistency._chain = outer, chain


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(prog="python -m benchmarks.variants", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("variant", choices=VARIANTS)
    p.add_argument("benchmark_args", nargs=argparse.REMAINDER, help="after --: the arguments of benchmarks.run")
    args = p.parse_args(argv)
    rest = args.benchmark_args[1:] if args.benchmark_args[:1] == ["--"] else args.benchmark_args
    from benchmarks import run

    print(f"variant: {args.variant}", flush=True)
    if args.variant == "chain-stream":
        try:
            from jax.experimental.scheduling_groups import xla_metadata_call  # noqa: F401
            form = "xla_metadata_call (the chain's calls annotated, nothing inside them)"
        except ImportError:
            form = "compute_on (this jax has no xla_metadata_call: every call inside the chain's is annotated too)"
        print(f"the chain's calls on {CHAIN_STREAM} through {form}; XLA_FLAGS={os.environ.get('XLA_FLAGS', '')!r}",
              flush=True)
    with applied(args.variant):
        return run.main(rest)


if __name__ == "__main__":
    main()
