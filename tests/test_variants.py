"""benchmarks.variants: a profiling variant changes what it names and nothing else, and is undone after."""

from __future__ import annotations

import contextlib

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from benchmarks import variants
from cdjax.agents.obs import losses
from _shared import benchmark_refuses


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


def test_scalar_loss_metrics_logs_the_same_means_with_the_same_gradient():
    """The SGD under `scalar-loss-metrics` (its loss values reduced in every step, as before they were shares): the
    loss functions give those values as scalars even when asked for shares, and the SGD, traced anew, reaches the same
    parameters and logged means as without it, up to the rounding of a sum's order; undone after the block."""
    from _shared import POINT

    from cdjax import HParams
    from cdjax.agents.obs import agent

    trainer = agent.make_agent(POINT.replace(arm="mbmf"))
    hp = HParams(alpha=0.0).as_float32()
    state = jax.jit(trainer.init)(jax.random.key(0), hp)
    _, _, _, batch = jax.jit(trainer.collect)(state, hp, jax.random.key(1))

    def sgd():  # a new function each call, so that jit traces it again
        return jax.jit(lambda s, b: trainer.sgd(s.params, s.opt_state, s.norms, b, hp, jax.random.key(2)))(state, batch)

    def step_metrics():  # one minibatch's loss metrics, asked for shares as the SGD asks
        mb = jax.tree.map(lambda x: agent.to_segments(x, trainer.L)[:, :POINT.minibatch_seqs], batch)
        return trainer.loss_terms(state.params, state.norms, mb, jnp.arange(POINT.num_windows), hp, shares=True)[1]

    (params, _), metrics = sgd()
    shared = set(trainer.share_metrics())
    assert {"loss/policy", "loss/value", "loss/entropy", "loss/ppo", "loss/model_nll", "loss/total"} <= shared
    assert step_metrics()["loss/policy"].ndim == 2
    with variants.applied("scalar-loss-metrics"):
        assert not {"loss/policy", "loss/model_nll", "loss/ppo"} & set(trainer.share_metrics())
        assert "loss/total" in trainer.share_metrics() and agent.SHARED_TERMS == {}
        inside = step_metrics()
        assert inside["loss/policy"].ndim == inside["loss/model_nll"].ndim == 0
        assert inside["ppo/approx_kl"].ndim == 2  # the diagnostics stay shares
        (params_v, _), metrics_v = sgd()
    assert set(trainer.share_metrics()) == shared and agent.SHARED_TERMS  # undone
    assert set(metrics_v) == set(metrics)
    for name in metrics:
        np.testing.assert_allclose(metrics_v[name], metrics[name], rtol=1e-5, atol=1e-6, err_msg=name)
    for a, b in zip(jax.tree.leaves(params), jax.tree.leaves(params_v)):
        assert jnp.array_equal(a, b)


def test_outer_dense_keeps_the_parameters_and_gives_the_same_gradients():
    """`outer-dense`: the agent's MLPs with the one-product backward have the same parameter tree and outputs, and
    the agent's loss the same gradient up to the rounding of a sum's order (it must reach every layer: policy, value,
    model); undone after the block."""
    from _shared import POINT

    from cdjax import HParams
    from cdjax.agents.obs import agent, networks

    mlp = networks.MLP((8, 8), 3)
    x = jax.random.normal(jax.random.PRNGKey(0), (2, 5, 4))
    params = mlp.init(jax.random.PRNGKey(1), x)
    with variants.applied("outer-dense"):
        assert networks.Dense is not flax_dense()
        params_v = mlp.init(jax.random.PRNGKey(1), x)
        out_v = mlp.apply(params, x)
    assert networks.Dense is flax_dense()
    assert jax.tree.structure(params_v) == jax.tree.structure(params)
    for a, b in zip(jax.tree.leaves(params), jax.tree.leaves(params_v)):
        assert jnp.array_equal(a, b)
    np.testing.assert_array_equal(out_v, mlp.apply(params, x))

    trainer = agent.make_agent(POINT.replace(arm="mbmf"))
    hp = HParams(alpha=0.0).as_float32()
    state = jax.jit(trainer.init)(jax.random.key(0), hp)
    _, _, _, batch = jax.jit(trainer.collect)(state, hp, jax.random.key(1))
    mb = jax.tree.map(lambda x: agent.to_segments(x, trainer.L)[:, :POINT.minibatch_seqs], batch)

    def loss(p):
        terms = trainer.loss_terms(p, state.norms, mb, jnp.arange(POINT.num_windows), hp)[0]
        return sum(terms.values())

    def grad():  # a new function each call, so that jit traces it again
        return jax.jit(jax.grad(lambda p: loss(p)))(state.params)

    def custom_layers():  # the layers whose backward is the variant's, in the loss as traced now
        return str(jax.make_jaxpr(lambda p: loss(p))(state.params)).count("custom_vjp_call")

    plain = grad()
    assert custom_layers() == 0
    with variants.applied("outer-dense"):
        outer = grad()
        assert custom_layers() == 7  # policy and value: 2 layers each; model: 1 and its two heads
    assert jax.tree.structure(outer) == jax.tree.structure(plain)
    nonzero = 0
    for (path, a), b in zip(jax.tree_util.tree_leaves_with_path(plain), jax.tree.leaves(outer)):
        np.testing.assert_allclose(b, a, rtol=2e-5, atol=1e-6, err_msg=jax.tree_util.keystr(path))
        nonzero += bool(jnp.any(a != 0))
    assert nonzero >= 10  # policy, value and model layers all have gradients


def flax_dense():
    import flax.linen as nn

    return nn.Dense


def test_grad_chunks_switches_the_chain_to_chunked_weight_gradients_only_inside_its_block():
    """`grad-chunks` sets consistency.GRAD_CHUNK (whose gradients test_consistency checks against the plain loop)
    inside its block only."""
    from cdjax import consistency

    assert consistency.GRAD_CHUNK is None
    with variants.applied("grad-chunks"):
        assert consistency.GRAD_CHUNK == 5
    assert consistency.GRAD_CHUNK is None


def test_bad_arguments_are_refused_in_one_sentence_before_the_variant_is_applied(tmp_path, capsys, monkeypatch):
    """An unknown variant (argparse's usage block before), BENCHMARK-ARGS that benchmarks.run refuses (in its name) and
    --merge (it builds no program for a variant to change): one sentence, exit status 2, nothing applied or run."""
    from benchmarks import run

    monkeypatch.setattr(variants, "applied", lambda variant: pytest.fail("a variant was applied"))
    afile = tmp_path / "afile"
    afile.write_text("")

    def refused(argv, prog, said):
        benchmark_refuses(capsys, variants.main, argv, prog, said, quiet=True)

    refused(["no-such", "--", "--tiny"], "variants", "argument variant: invalid choice: 'no-such'")
    refused(["bias-sum", "--", "--tiny", "--updates", "0"], "run", "argument --updates: '0' is not")
    refused(["bias-sum", "--", "--tiny", "--trace", str(afile)], "run", f"--trace: {afile} is a file")
    refused(["none", "--merge", str(tmp_path)], "variants", "--merge builds none")
    with monkeypatch.context() as patch:  # the same, asked rightly, applies it around benchmarks.run
        patch.setattr(variants, "applied", lambda variant: contextlib.nullcontext(seen.append(variant)))
        patch.setattr(run, "main", lambda argv: {"argv": argv})
        seen = []
        assert variants.main(["bias-sum", "--", "--tiny", "--dry-run"]) == {"argv": ["--tiny", "--dry-run"]}
        assert seen == ["bias-sum"]
