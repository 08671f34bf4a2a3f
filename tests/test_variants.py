"""benchmarks.variants: a profiling variant changes what it names and nothing else, and is undone after."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from benchmarks import variants
from cdjax.agents.obs import losses


def _losses(pred_mean, pred_log_std, policy_mean, value, data):
    """The two loss functions as the agent calls them (through the module), summed."""
    model, model_metrics = losses.model_loss(pred_mean, pred_log_std, data["target"], data["mask"])
    hp = type("HP", (), {"clip_eps": 0.2, "vf_coef": 0.5, "ent_coef": 0.01})()
    ppo, ppo_metrics = losses.ppo_loss(policy_mean[..., None], jnp.ones_like(policy_mean)[..., None], value,
                                       data["raw_action"], data["log_prob_old"], data["adv"], data["returns"],
                                       data["mask"], hp)
    return model + ppo, {**model_metrics, **ppo_metrics}


def test_no_loss_metrics_zeroes_the_diagnostics_only_and_keeps_the_gradients():
    keys = iter(jax.random.split(jax.random.PRNGKey(3), 10))
    T, B, O = 5, 4, 3
    data = {"target": jax.random.normal(next(keys), (T, B, O + 1)),
            "mask": jax.random.bernoulli(next(keys), 0.8, (T, B)),
            "raw_action": jax.random.normal(next(keys), (T, B, 1)),
            "log_prob_old": jax.random.normal(next(keys), (T, B)),
            "adv": jax.random.normal(next(keys), (T, B)), "returns": jax.random.normal(next(keys), (T, B))}
    params = (jax.random.normal(next(keys), (T, B, O + 1)), 0.1 * jax.random.normal(next(keys), (T, B, O + 1)),
              jax.random.normal(next(keys), (T, B)), jax.random.normal(next(keys), (T, B)))
    grad = lambda: jax.jit(jax.value_and_grad(lambda p: _losses(*p, data), has_aux=True))(params)  # noqa: E731
    (loss, metrics), g = grad()
    with variants.applied("no-loss-metrics"):
        (loss_v, metrics_v), g_v = grad()
    zeroed = {m for names in variants.LOSS_METRICS.values() for m in names}
    assert zeroed <= set(metrics) and all(float(metrics[m]) != 0.0 for m in zeroed)
    assert all(float(metrics_v[m]) == 0.0 for m in zeroed)
    assert {k: float(v) for k, v in metrics_v.items() if k not in zeroed} == {
        k: float(v) for k, v in metrics.items() if k not in zeroed}
    assert float(loss_v) == float(loss)
    for a, b in zip(jax.tree.leaves(g), jax.tree.leaves(g_v)):
        assert jnp.array_equal(a, b)
    # undone after the block, and refused when unknown
    (_, metrics_after), _ = grad()
    assert all(float(metrics_after[m]) == float(metrics[m]) for m in zeroed)
    with pytest.raises(ValueError, match="unknown variant"):
        with variants.applied("no-such"):
            pass


def test_bias_sum_gives_the_same_weight_gradients_as_the_one_product():
    """`_outer` (one product of [a, 1] and b) against the variant's kernel product and bias sum: both the sums over
    every leading axis, equal up to rounding; the variant in place only inside its block."""
    from cdjax import consistency

    a = jax.random.normal(jax.random.PRNGKey(0), (6, 2, 5, 7))
    b = jax.random.normal(jax.random.PRNGKey(1), (6, 2, 5, 3))
    kernel, bias = consistency._outer(a, b)
    assert kernel.shape == (7, 3) and bias.shape == (3,)
    assert jnp.allclose(kernel, jnp.einsum("...i,...j->ij", a, b), atol=1e-5)
    assert jnp.allclose(bias, b.sum((0, 1, 2)), atol=1e-5)
    one_product = consistency._outer
    with variants.applied("bias-sum"):
        assert consistency._outer is not one_product
        split_kernel, split_bias = consistency._outer(a, b)
    assert consistency._outer is one_product
    assert jnp.allclose(split_kernel, kernel, atol=1e-5) and jnp.allclose(split_bias, bias, atol=1e-5)


def _chain_problem(shared: bool):
    """A small fused chain (k = 4 steps of a one-hidden-layer model, a GRU of 6 units, 9 windows) and a function
    giving its value and its gradients with respect to every input, traced (and jitted) when called."""
    from cdjax import consistency
    from cdjax import normalize as nz

    O, A, N, H, k, w = 5, 3, 7, 6, 4, 9
    keys = iter(jax.random.split(jax.random.key(2), 20))
    stats = lambda: nz.update(nz.RunningStats.create(O), 2.0 * jax.random.normal(next(keys), (64, O)))  # noqa: E731
    model = consistency.MLPModel(
        layers=((0.4 * jax.random.normal(next(keys), (O + A, N)), 0.1 * jax.random.normal(next(keys), (N,))),
                (0.4 * jax.random.normal(next(keys), (N, O)), 0.1 * jax.random.normal(next(keys), (O,)))),
        obs=stats(), delta=stats())
    gru = tuple(0.4 * jax.random.normal(next(keys), s) for s in ((O, 3 * H), (3 * H,), (H, 3 * H), (H,)))
    args = (model, gru, 2.0 * jax.random.normal(next(keys), (w, O)), jax.random.normal(next(keys), (k, w, A)),
            jax.random.normal(next(keys), (k, w, O)))
    enc_obs = model.obs if shared else stats()
    cotangents = [jax.random.normal(next(keys), s) for s in ((w, H), (w, H), (w, O))]

    def loss(*a):
        return sum(jnp.sum(x * c) for x, c in zip(consistency.fused_chain(*a, enc_obs, (0.5, 1.0), shared), cotangents))

    def grad():
        return jax.jit(jax.value_and_grad(loss, argnums=(0, 1, 2, 3, 4)))(*args)

    return dict(O=O, N=N, H=H, args=args, loss=loss, grad=grad)


def _assert_same_gradients(g, g_r):
    for (path, a), b in zip(jax.tree_util.tree_leaves_with_path(g), jax.tree.leaves(g_r)):  # float32 rounding of
        # sums in another order: relative to each leaf's largest entry (the first layer's reach 170 here)
        np.testing.assert_allclose(b, a, rtol=1e-5, atol=2e-6 * float(jnp.abs(a).max()),
                                   err_msg=jax.tree_util.keystr(path))
    assert float(jnp.abs(g[0].layers[-1][0]).max()) > 0 and float(jnp.abs(g[2]).max()) > 0


@pytest.mark.parametrize("shared", [True, False])
def test_chain_stream_puts_the_chains_forward_and_backward_on_a_stream_and_keeps_the_function(shared):
    """`chain-stream`: the lowered gradient holds the chain's forward and backward as calls annotated with the second
    stream (and the plain chain none); values and gradients as the plain chain's, also vmapped over a leading axis
    of runs; the plain chain back after the block."""
    from cdjax import consistency

    case = _chain_problem(shared)
    plain_chain = consistency._chain
    text = lambda: jax.jit(jax.grad(case["loss"], argnums=(0, 2))).lower(*case["args"]).as_text()  # noqa: E731
    v, g = case["grad"]()
    assert "_xla_stream_annotation" not in text()
    batched = lambda: jax.vmap(lambda s0: jax.grad(case["loss"], argnums=2)(  # noqa: E731
        *case["args"][:2], s0, *case["args"][3:]))(jnp.stack([case["args"][2], -case["args"][2]]))
    b = jax.jit(batched)()
    with variants.applied("chain-stream"):
        assert consistency._chain is not plain_chain
        annotated = text()
        v_r, g_r = case["grad"]()
        b_r = jax.jit(batched)()
    assert consistency._chain is plain_chain
    stream = variants.CHAIN_STREAM.split(":")[1]
    calls = [line for line in annotated.splitlines() if " call @" in line]
    on_stream = [line for line in calls if f'_xla_stream_annotation = "{stream}"' in line]
    assert len(on_stream) == 2, "one call for the forward, one for the backward"
    assert annotated.count("_xla_stream_annotation") == 2  # the ops inside the calls carry no annotation
    assert "annotate_device_placement" not in annotated  # no placement calls between the chain and its users
    np.testing.assert_allclose(v_r, v, rtol=1e-6)
    _assert_same_gradients(g, g_r)
    np.testing.assert_allclose(b_r, b, rtol=1e-5, atol=1e-6 * float(jnp.abs(b).max()))
    assert not np.allclose(b[0], b[1])  # the two runs differ, so the vmapped check sees each


def test_chain_stream_without_xla_metadata_call_annotates_through_compute_on(monkeypatch):
    """Where jax lacks `xla_metadata_call`, `chain-stream` falls back to a jitted call under `compute_on`: the chain's
    calls are still annotated with the stream, and the gradients are still the plain chain's."""
    import sys

    monkeypatch.setitem(sys.modules, "jax.experimental.scheduling_groups", None)  # its import now fails
    case = _chain_problem(False)
    v, g = case["grad"]()
    with variants.applied("chain-stream"):
        text = jax.jit(jax.grad(case["loss"], argnums=(0, 2))).lower(*case["args"]).as_text()
        v_r, g_r = case["grad"]()
    stream = variants.CHAIN_STREAM.split(":")[1]
    assert any(" call @" in line and f'_xla_stream_annotation = "{stream}"' in line and "_chain_" in line
               for line in text.splitlines())
    assert "xla_metadata_call" not in text
    np.testing.assert_allclose(v_r, v, rtol=1e-6)
    _assert_same_gradients(g, g_r)
