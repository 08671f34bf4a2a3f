"""The CUDA chain kernels' Python side on the CPU: when they are used, and that their wrappers give the XLA chain's
shapes (the kernels' values and gradients are checked on a GPU by `python -m benchmarks.chain_kernel`)."""

import jax
import jax.numpy as jnp
import pytest

from benchmarks import chain_kernel as ck
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
