"""The CUDA chain kernels' Python side on the CPU: when they are used, and that their wrappers give the XLA chain's
shapes (the kernels' values and gradients are checked on a GPU by `python -m benchmarks.chain_kernel`)."""

import re

import jax
import jax.numpy as jnp
import pytest

from benchmarks import chain_kernel as ck
from cdjax import consistency as cc
from cdjax.kernels import chain as chain_kernel
from cdjax.protocol import ConfigError

SIZES = dict(horizon=4, obs=5, act=2, hidden=12, enc=8)


def test_the_kernels_are_off_unless_switched_on_never_on_a_cpu_and_a_bad_switch_is_one_sentence(monkeypatch):
    monkeypatch.delenv(chain_kernel.SWITCH_ENV, raising=False)
    assert not chain_kernel.usable(2, 5, 10, 12, 8, jnp.float32)
    monkeypatch.setenv(chain_kernel.SWITCH_ENV, "1")
    assert jax.default_backend() == "cpu"
    assert not chain_kernel.usable(2, 5, 10, 12, 8, jnp.float32)  # no GPU: XLA's chain, no build attempted
    monkeypatch.setenv(chain_kernel.SWITCH_ENV, "yes")
    with pytest.raises(ConfigError, match="CDJAX_CHAIN_KERNEL is 'yes'"):
        chain_kernel.usable(2, 5, 10, 12, 8, jnp.float32)


@pytest.mark.parametrize("shared", [True, False])
def test_the_kernel_path_has_the_xla_chains_shapes_alone_and_under_vmap(shared):
    args, enc_obs, weights = ck._problem(6, 0, shared, SIZES)

    def grad(kernel):
        return jax.value_and_grad(ck._objective_fn(enc_obs, weights, (1.0, 0.5), shared, kernel),
                                  argnums=tuple(range(5)))

    shapes = lambda t: jax.tree.map(lambda x: (x.shape, x.dtype), t)  # noqa: E731
    assert shapes(jax.eval_shape(grad(True), *args)) == shapes(jax.eval_shape(grad(False), *args))
    batched = jax.tree.map(lambda *xs: jnp.stack(xs), *[ck._problem(6, s, shared, SIZES)[0] for s in range(3)])
    assert shapes(jax.eval_shape(jax.vmap(grad(True)), *batched)) == shapes(jax.eval_shape(jax.vmap(grad(False)),
                                                                                         *batched))
    lowered = jax.jit(grad(True)).lower(*args).as_text()
    assert lowered.count("cdjax_chain_fwd(") == 1 and lowered.count("cdjax_chain_bwd(") == 1
    with ck._mode("cluster"):  # the cluster kernels: their own targets
        lowered = jax.jit(grad(True)).lower(*args).as_text()
    assert lowered.count("cdjax_chain_fwd_cluster(") == 1 and lowered.count("cdjax_chain_bwd_cluster(") == 1


def test_the_benchmarks_kernel_inputs_are_what_the_chain_hands_the_kernels():
    """benchmarks.chain_kernel's --compare-modes calls the kernels on inputs it builds itself: they must have the
    shapes of those consistency._chain_fwd hands the forward kernel, and give the forward's shapes."""
    for shared in (True, False):
        args = ck.kernel_inputs(6, SIZES, shared)
        out = jax.eval_shape(lambda *a: chain_kernel.forward(10.0, *a), *args)
        k, W, O, H = SIZES["horizon"], 6, SIZES["obs"], SIZES["enc"]
        assert [x.shape for x in out] == [(k, W, SIZES["hidden"]), (k + 1, W, O), (k + 1, W, O * (1 if shared else 2)),
                                          (k, W, 3 * H), (k, 2 * W, 3 * H), (k + 1, 2 * W, H)]
        (model, gru, s0, actions, x_re), enc_obs, _ = ck._problem(6, 0, shared, SIZES)
        chain = lambda *a: cc.fused_chain(*a, enc_obs, (1.0, 0.5), shared, kernel=True)  # noqa: E731
        lowered = jax.jit(chain).lower(model, gru, s0, actions, x_re).as_text()
        call = [line for line in lowered.splitlines() if "cdjax_chain_fwd(" in line][0]
        types = call.rsplit(" : (", 1)[1].split(") -> ")[0]  # the operands' types, in order
        shapes = [tuple(int(n) for n in t.split("x")[:-1]) for t in re.findall(r"tensor<([0-9x]+xf32)>", types)]
        assert shapes == [tuple(a.shape) for a in args]
