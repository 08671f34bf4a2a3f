"""The consistency term: zero for an exact model, gradient paths, alpha = 0, masking."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cdjax import HParams, losses, networks
from cdjax import normalize as nz
from cdjax.envs.point import PointMass

from _shared import POINT, compiled

K, W = 6, 10


def _real_windows(seed=0):
    """W real k-step point-mass sequences under random actions (the 'closed loop')."""
    key_s, key_a = jax.random.split(jax.random.key(seed))
    s0 = jnp.concatenate([jax.random.uniform(key_s, (W, 2), minval=-1, maxval=1), jnp.zeros((W, 2))], -1)
    actions = jax.random.uniform(key_a, (K, W, 2), minval=-1, maxval=1)

    def step(s, a):
        s = PointMass.dynamics(s, a)
        return s, s

    _, real = jax.lax.scan(step, s0, actions)
    return s0, actions, real


def _encoder(variant):
    if variant == "l2":
        return {}
    module = networks.Encoder(8)
    params = module.init(jax.random.key(1), jnp.zeros((1, 8)), jnp.zeros((1, 4)))
    return dict(encode_step=lambda h, x: module.apply(params, h, x), h0=jnp.zeros((W, 8)))


def _stats():
    return nz.update(nz.RunningStats.create(4), jax.random.normal(jax.random.key(2), (64, 4)))


@pytest.mark.parametrize("variant", ["gru", "frozen-gru", "l2"])
def test_zero_for_exact_model_positive_otherwise(variant):
    s0, actions, real = _real_windows()
    norm = lambda x: nz.normalize(_stats(), x)  # noqa: E731
    mask = jnp.ones((W,), bool)
    exact, m = losses.consistency_loss(PointMass.dynamics, norm, s0, actions, real, mask, encoder=variant,
                                       **_encoder(variant))
    assert float(exact) == 0.0
    assert float(m["consistency/final_mse"]) == 0.0
    biased = lambda s, a: PointMass.dynamics(s, a) + 0.01  # noqa: E731
    wrong, _ = losses.consistency_loss(biased, norm, s0, actions, real, mask, encoder=variant, **_encoder(variant))
    assert float(wrong) > 1e-4


def test_masked_windows_contribute_nothing():
    s0, actions, real = _real_windows()
    norm = lambda x: nz.normalize(_stats(), x)  # noqa: E731
    biased = lambda s, a: PointMass.dynamics(s, a) * 1.05  # noqa: E731
    mask = jnp.arange(W) % 3 != 0
    base, m = losses.consistency_loss(biased, norm, s0, actions, real, mask, encoder="gru", **_encoder("gru"))
    garbage = jnp.where(mask[None, :, None], real, 1e6)
    same, _ = losses.consistency_loss(biased, norm, s0, actions, garbage, mask, encoder="gru", **_encoder("gru"))
    assert float(same) == float(base)
    np.testing.assert_allclose(m["consistency/masked_fraction"], 4 / W)
    kept = np.asarray(mask)
    enc = _encoder("gru")
    enc["h0"] = enc["h0"][kept]
    alone, _ = losses.consistency_loss(biased, norm, s0[kept], actions[:, kept], real[:, kept],
                                       jnp.ones((kept.sum(),), bool), encoder="gru", **enc)
    np.testing.assert_allclose(alone, base, rtol=1e-6)


@pytest.fixture(scope="module")
def point_batch():
    trainer, init, update = compiled(POINT)
    hp = HParams(alpha=1.0)
    state = init(jax.random.key(0), hp)
    for _ in range(2):  # non-trivial normalisation statistics and a model that is not at init
        state, _ = update(state, hp)
    _, _, _, batch = jax.jit(trainer.collect)(state, hp)
    mb = jax.tree.map(lambda x: x[:, : POINT.minibatch_envs], batch)
    return trainer, state, mb


def _grads(trainer, params, norms, mb, alpha):
    offsets = jnp.arange(POINT.num_windows)
    fn = jax.jit(jax.grad(trainer.loss, has_aux=True))
    return fn(params, norms, mb, offsets, HParams(alpha=alpha))


def _norm(tree):
    return float(jnp.sqrt(sum(jnp.sum(x**2) for x in jax.tree.leaves(tree))))


def test_gradient_reaches_model_and_policy_not_value(point_batch):
    trainer, state, mb = point_batch
    g1, m1 = _grads(trainer, state.params, state.norms, mb, 1.0)
    g0, m0 = _grads(trainer, state.params, state.norms, mb, 0.0)
    diff = jax.tree.map(lambda a, b: a - b, g1, g0)  # the gradient of l_cc alone
    assert float(m1["loss/consistency"]) > 0
    assert _norm(diff["model"]) > 1e-6
    assert _norm(diff["policy"]) > 1e-6  # through the re-derived actions
    assert _norm(diff["encoder"]) > 1e-6
    assert _norm(diff["value"]) == 0.0
    # alpha = 0: the encoder gets nothing, and the other groups match the mbmf arm exactly
    assert _norm(g0["encoder"]) == 0.0
    mbmf, _, _ = compiled(POINT.replace(arm="mbmf"))
    params = {name: p for name, p in state.params.items() if name != "encoder"}
    g_mbmf, m_mbmf = _grads(mbmf, params, state.norms, mb, 0.0)
    for name in g_mbmf:
        for a, b in zip(jax.tree.leaves(g0[name]), jax.tree.leaves(g_mbmf[name])):
            np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(m0["loss/total"], m_mbmf["loss/total"], rtol=1e-6)


def test_rederived_actions_equal_executed_actions(point_batch):
    """Before any parameter change, squash(mean + std * noise) is numerically the executed action."""
    trainer, state, _ = point_batch
    hp = HParams(alpha=1.0)
    _, _, traj, _ = jax.jit(trainer.collect)(state, hp)
    policy = networks.Policy(2, POINT.policy_hidden)
    mean, log_std = policy.apply(state.params["policy"], nz.normalize(state.norms.obs, traj.obs))
    np.testing.assert_allclose(networks.act_from_noise(mean, log_std, traj.noise), traj.action, atol=1e-6)


def test_windows_crossing_a_reset_are_masked_in_the_update(point_batch):
    trainer, state, mb = point_batch
    offsets = jnp.arange(POINT.num_windows)
    loss = jax.jit(trainer.loss)
    _, m = loss(state.params, state.norms, mb.replace(ended=jnp.zeros_like(mb.ended)), offsets, HParams())
    assert float(m["consistency/masked_fraction"]) == 0.0
    # an episode end after step 5 in every env breaks the windows starting at 3..5 (k = 4): 3 of 9
    ended = jnp.zeros_like(mb.ended).at[5].set(True)
    _, m = loss(state.params, state.norms, mb.replace(ended=ended), offsets, HParams())
    np.testing.assert_allclose(m["consistency/masked_fraction"], 3 / 9, rtol=1e-6)
    # garbage after the reset in those windows changes nothing but what the kept windows see
    garbage = mb.next_obs.at[6].set(1e3)  # used only by windows starting at 3..6; 6 is kept
    _, m_garbage = loss(state.params, state.norms, mb.replace(ended=ended.at[6].set(True), next_obs=garbage),
                        offsets, HParams())
    _, m_clean = loss(state.params, state.norms, mb.replace(ended=ended.at[6].set(True)), offsets, HParams())
    # with ends after 5 and 6, windows 3..6 are masked: no kept window reads next_obs[6]
    np.testing.assert_allclose(m_garbage["loss/consistency"], m_clean["loss/consistency"], rtol=1e-6)
