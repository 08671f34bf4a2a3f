"""The consistency module alone, on hand-made batches: windows, l_cc, encoders, the two gradient paths."""

import functools
import json
import types

import jax
import jax.extend
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from cdjax import consistency as cc
from cdjax import normalize as nz
from cdjax.envs.point import PointMass

K, W = 6, 10
ONE = cc.PathWeights(model=1.0, policy=1.0)
IRREDUCIBLE = 0.1  # amplitude of the tiny-task model's error that training cannot remove
INITIAL_ERROR = 0.05  # scale of its initial, learnable error


def _real_windows(seed=0, w=W):
    """w real k-step point-mass sequences under random actions (the 'closed loop')."""
    key_s, key_a = jax.random.split(jax.random.key(seed))
    s0 = jnp.concatenate([jax.random.uniform(key_s, (w, 2), minval=-1, maxval=1), jnp.zeros((w, 2))], -1)
    actions = jax.random.uniform(key_a, (K, w, 2), minval=-1, maxval=1)

    def step(s, a):
        s = PointMass.dynamics(s, a)
        return s, s

    _, real = jax.lax.scan(step, s0, actions)
    return s0, actions, real


def _stats():
    return nz.update(nz.RunningStats.create(4), jax.random.normal(jax.random.key(2), (64, 4)))


def _encoder(kind, obs=4):
    if kind == "l2":
        return {}
    module = cc.SequenceEncoder(8, K * obs if kind == "grounded-gru" else 0)
    return dict(encoder=module, encoder_params=cc.init_encoder(module, jax.random.key(1), obs))


def _model(scale):
    """A 'learned model' with one parameter: the point mass's step scaled by `scale` (1 = exact)."""
    return lambda p, s, a: PointMass.dynamics(s, a) * p["scale"], {"scale": jnp.asarray(scale, jnp.float32)}


def _loss(kind, scale=1.0, weights=ONE, mask=None, real=None, **enc):
    s0, actions, real_ = _real_windows()
    step, params = _model(scale)
    norm = lambda x: nz.normalize(_stats(), x)  # noqa: E731
    mask = jnp.ones((W,), bool) if mask is None else mask
    return cc.consistency_loss(step, params, s0, actions, real_ if real is None else real, mask, kind=kind,
                               normalize=norm, weights=weights, **(enc or _encoder(kind)))


@pytest.mark.parametrize("kind", cc.KINDS)
def test_zero_for_exact_model_positive_otherwise(kind):
    terms, m = _loss(kind, 1.0)
    assert float(terms["consistency"]) == 0.0
    assert float(m["consistency/final_mse"]) == 0.0
    wrong, _ = _loss(kind, 1.05)
    assert float(wrong["consistency"]) > 1e-4
    assert ("encoder_aux" in terms) == (kind == "grounded-gru")


@pytest.mark.parametrize("kind", ["gru", "grounded-gru"])
def test_masked_windows_contribute_nothing(kind):
    _, _, real = _real_windows()
    mask = jnp.arange(W) % 3 != 0
    enc = _encoder(kind)
    base, m = _loss(kind, 1.05, mask=mask, **enc)
    garbage = jnp.where(mask[None, :, None], real, 1e6)
    same, _ = _loss(kind, 1.05, mask=mask, real=garbage, **enc)
    for name in base:
        assert float(same[name]) == float(base[name]), name
    np.testing.assert_allclose(m["consistency/masked_fraction"], 4 / W)


def test_windows_and_mask_by_hand():
    """A [T=5, B=2] batch: windows of k=3 at offsets (0, 2) as rows (window-major), and their mask."""
    T, B, k = 5, 2, 3
    obs = jnp.arange(T * B, dtype=jnp.float32).reshape(T, B, 1)  # obs[t, b] = 2t + b
    next_obs = obs + 100.0
    actions = -obs
    ended = jnp.zeros((T, B), bool).at[0, 1].set(True)  # env 1's episode ends after step 0
    valid = jnp.ones((T, B), bool).at[4, 0].set(False)  # env 0's step 4 is not finite
    s0, a, real, mask = cc.windows(obs, next_obs, actions, ended, valid, jnp.array([0, 2]), k)
    np.testing.assert_array_equal(s0[:, 0], [0, 1, 4, 5])  # rows: (o=0, b=0), (0, 1), (2, 0), (2, 1)
    np.testing.assert_array_equal(a[:, :, 0], -np.array([[0, 1, 4, 5], [2, 3, 6, 7], [4, 5, 8, 9]]))
    np.testing.assert_array_equal(real[:, 2, 0], [104, 106, 108])  # window at 2 of env 0: next_obs[2..4]
    # (0, 1) crosses env 1's end after step 0; (2, 0) holds env 0's invalid step 4
    np.testing.assert_array_equal(mask, [True, False, False, True])


def test_window_mask_ends_on_the_last_step_are_fine():
    T, k = 6, 3
    ended = jnp.zeros((T, 1), bool).at[2, 0].set(True)
    valid = jnp.ones((T, 1), bool)
    idx = cc.window_indices(jnp.arange(T - k + 1), k)
    # an end after step 2 breaks windows whose first k-1 steps include 2 (starts 1 and 2); the window
    # starting at 0 ends exactly at the episode's last step, which is fine
    np.testing.assert_array_equal(cc.window_mask(ended, valid, idx)[:, 0], [True, False, False, True])


def test_window_offsets_all_or_distinct_sorted():
    np.testing.assert_array_equal(cc.window_offsets(jax.random.key(0), 8, 3, 6), np.arange(6))
    some = np.asarray(cc.window_offsets(jax.random.key(0), 8, 3, 3))
    assert len(set(some)) == 3 and list(some) == sorted(some) and some.max() <= 5


def test_scale_gradient_identity_forward_scaled_backward():
    x = jnp.array([1.0, -2.0])
    np.testing.assert_array_equal(cc.scale_gradient(x, 0.3), x)
    g = jax.grad(lambda x: (cc.scale_gradient(x, 0.3) ** 2).sum())(x)
    np.testing.assert_allclose(g, 0.3 * 2 * x, rtol=1e-6)
    g0 = jax.grad(lambda x: jnp.sqrt(cc.scale_gradient(x - x, 0.0)).sum())(x)  # d sqrt(u) / du at 0 is inf
    np.testing.assert_array_equal(g0, 0.0)  # a zero weight gives exactly zero, whatever flows back


def test_safe_norm_value_and_gradient_at_zero():
    x = jnp.zeros((3,))
    assert cc.safe_norm(x) == 0.0
    assert jnp.all(jax.grad(cc.safe_norm)(x) == 0.0)
    y = jnp.array([3.0, 4.0])
    np.testing.assert_allclose(cc.safe_norm(y), 5.0)
    np.testing.assert_allclose(jax.grad(cc.safe_norm)(y), [0.6, 0.8], rtol=1e-6)


@pytest.mark.parametrize("kind", ["gru", "grounded-gru", "l2"])
def test_path_weights_scale_each_path_alone(kind):
    """d l_cc / d model params scales with weights.model, d / d actions with weights.policy, the encoder's with
    weights.model; the reconstruction's gradient does not depend on the weights; the value never changes."""
    s0, actions, real = _real_windows()
    step, model_params = _model(1.05)
    norm = lambda x: nz.normalize(_stats(), x)  # noqa: E731
    enc = _encoder(kind)
    mask = jnp.ones((W,), bool)

    def grads(w_model, w_policy, term="consistency", w_encoder=1.0):
        def f(mp, acts, ep):
            e = dict(enc, encoder_params=ep) if enc else {}
            terms, _ = cc.consistency_loss(step, mp, s0, acts, real, mask, kind=kind, normalize=norm,
                                           weights=cc.PathWeights(w_model, w_policy, w_encoder), **e)
            return terms[term]
        return jax.value_and_grad(f, argnums=(0, 1, 2))(model_params, actions, enc.get("encoder_params", {}))

    v1, (gm1, ga1, ge1) = grads(1.0, 1.0)
    v2, (gm2, ga2, ge2) = grads(0.25, 3.0)
    assert float(v1) == float(v2)
    np.testing.assert_allclose(gm2["scale"], 0.25 * gm1["scale"], rtol=1e-5)
    np.testing.assert_allclose(ga2, 3.0 * ga1, rtol=1e-5, atol=1e-9)
    assert float(jnp.abs(ga1).max()) > 0 and float(jnp.abs(gm1["scale"])) > 0
    for a, b in zip(jax.tree.leaves(ge2), jax.tree.leaves(ge1)):
        np.testing.assert_allclose(a, 0.25 * b, rtol=1e-5, atol=1e-9)
    _, (gm0, ga0, _) = grads(0.0, 0.0)
    assert float(gm0["scale"]) == 0.0 and float(jnp.abs(ga0).max()) == 0.0
    # weights.encoder scales the encoder's share alone: the model's and the actions' gradients stay
    v3, (gm3, ga3, ge3) = grads(0.25, 3.0, w_encoder=0.1)
    assert float(v3) == float(v1)
    np.testing.assert_allclose(gm3["scale"], gm2["scale"], rtol=1e-6)
    np.testing.assert_allclose(ga3, ga2, rtol=1e-6, atol=1e-9)
    for a, b in zip(jax.tree.leaves(ge3), jax.tree.leaves(ge1)):
        np.testing.assert_allclose(a, 0.025 * b, rtol=1e-5, atol=1e-9)
    if kind == "grounded-gru":
        r1, (_, _, gr1) = grads(1.0, 1.0, "encoder_aux")
        r0, (_, _, gr0) = grads(0.0, 0.0, "encoder_aux")
        assert float(r1) == float(r0) > 0
        for a, b in zip(jax.tree.leaves(gr0), jax.tree.leaves(gr1)):
            np.testing.assert_array_equal(a, b)


def _train_encoder_and_model(kind, steps=1000, alpha=1.0, weights=ONE):
    """Train a small model (the point mass with an error, plus a learnable linear correction) and the encoder
    on alpha x l_cc (plus the auxiliary loss at weight 1 for grounded-gru) with these path weights: -> (l_cc,
    spread) at the start and at the end."""
    s0, actions, real = _real_windows(seed=3, w=64)
    stats = nz.update(nz.RunningStats.create(4), real.reshape(-1, 4))
    norm = lambda x: nz.normalize(stats, x)  # noqa: E731
    enc = _encoder(kind)
    mask = jnp.ones((64,), bool)

    def step(p, s, a):  # the sine is an error the linear correction cannot remove
        return PointMass.dynamics(s, a) + IRREDUCIBLE * jnp.sin(5 * s) + s @ p["w"] + p["b"]

    params = {"model": {"w": INITIAL_ERROR * jax.random.normal(jax.random.key(4), (4, 4)),
                        "b": jnp.full((4,), INITIAL_ERROR)},
              "encoder": enc["encoder_params"]}

    def loss(p):
        terms, m = cc.consistency_loss(step, p["model"], s0, actions, real, mask, kind=kind, normalize=norm,
                                       weights=weights, encoder=enc["encoder"], encoder_params=p["encoder"])
        total = alpha * terms["consistency"] + terms.get("encoder_aux", 0.0)
        return total, (terms["consistency"], m["encoder/spread_real"])

    tx = optax.adam(3e-3)

    @jax.jit
    def train(params):
        def body(carry, _):
            p, o = carry
            g, aux = jax.grad(loss, has_aux=True)(p)
            u, o = tx.update(g, o, p)
            return (optax.apply_updates(p, u), o), aux
        return jax.lax.scan(body, (params, tx.init(params)), None, length=steps)[1]

    l_cc, spread = train(params)
    return float(l_cc[0]), float(l_cc[-1]), float(spread[0]), float(spread[-1])


def test_default_encoder_keeps_its_spread_while_l_cc_is_trained_down():
    """grounded-gru: l_cc falls (the model becomes consistent) and the encodings stay spread out (the floor holds
    them near SPREAD_FLOOR); the paper's gru, trained the same way, shrinks its encodings instead (what
    collapsed on ant)."""
    l0, l1, s0, s1 = _train_encoder_and_model("grounded-gru")
    assert l1 < 0.3 * l0, (l0, l1)
    assert s1 > 0.5 * s0 and s1 > 0.9 * cc.SPREAD_FLOOR, (s0, s1)
    g_l0, g_l1, g_s0, g_s1 = _train_encoder_and_model("gru")
    assert g_s1 < 0.5 * g_s0, (g_s0, g_s1)  # the same training collapses the ungrounded encoder


def test_alpha_weighs_the_model_not_the_encoders_balance():
    """`path_weights`: l_cc reaches the encoder at cc_model whatever alpha is. The gradient of alpha x l_cc +
    encoder_aux on the encoder's parameters is the same at alpha 1 and 100, on the model's it is 100 times larger;
    with alpha on the encoder's share too (the weighting before) it was not, and at the pixel presets' alpha 100
    every encoder of 20 halfcheetah runs shrank its output ~10,000x (experiments/pixel/RESULTS.md; on pixel-tiny
    the same within 500 updates, and enc_aux_coef = alpha held it). Trained at alpha 100, the encodings keep their
    spread."""
    hp = lambda alpha: types.SimpleNamespace(alpha=alpha, cc_model=0.5, cc_policy=2.0)  # noqa: E731
    w = cc.path_weights(hp(100.0))
    assert (float(w.model), float(w.policy), float(w.to_encoder)) == (0.5, 2.0, pytest.approx(0.005))
    assert float(cc.path_weights(hp(0.0)).to_encoder) == 0.0
    assert float(cc.path_weights(hp(1.0)).encoder) == 1.0  # the observation and Atari presets: as before

    s0, actions, real = _real_windows()
    step, model_params = _model(1.05)
    enc = _encoder("grounded-gru")
    mask = jnp.ones((W,), bool)

    def grads(alpha, weights):
        def total(mp, ep):
            terms, _ = cc.consistency_loss(step, mp, s0, actions, real, mask, kind="grounded-gru", normalize=_stats(),
                                           weights=weights, encoder=enc["encoder"], encoder_params=ep)
            return alpha * terms["consistency"] + terms["encoder_aux"]
        return jax.grad(total, argnums=(0, 1))(model_params, enc["encoder_params"])

    (m1, e1), (m100, e100) = grads(1.0, cc.path_weights(hp(1.0))), grads(100.0, cc.path_weights(hp(100.0)))
    np.testing.assert_allclose(m100["scale"], 100.0 * m1["scale"], rtol=1e-5)
    for a, b in zip(jax.tree.leaves(e100), jax.tree.leaves(e1)):
        np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-8)
    _, e_before = grads(100.0, cc.PathWeights(0.5, 2.0))
    assert max(float(jnp.abs(a - b).max()) for a, b in zip(jax.tree.leaves(e_before), jax.tree.leaves(e1))) > 1e-3

    _, l1, sp0, sp1 = _train_encoder_and_model("grounded-gru", alpha=100.0, weights=cc.path_weights(hp(100.0)))
    assert sp1 > 0.5 * sp0 and sp1 > 0.9 * cc.SPREAD_FLOOR, (sp0, sp1)


def _mlp_model(obs=4, act=2, hidden=(16,), seed=5):
    """An MLPModel with random weights and statistics (the obs-space agent's dynamics model in the fused form)."""
    keys = iter(jax.random.split(jax.random.key(seed), 16))
    sizes = (obs + act,) + hidden + (obs,)
    layers = tuple((0.5 * jax.random.normal(next(keys), (a, b)) / np.sqrt(a), 0.1 * jax.random.normal(next(keys), (b,)))
                   for a, b in zip(sizes[:-1], sizes[1:]))
    stats = lambda key, scale: nz.update(nz.RunningStats.create(obs), scale * jax.random.normal(key, (64, obs)))  # noqa: E731
    return cc.MLPModel(layers=layers, obs=stats(next(keys), 1.0), delta=stats(next(keys), 0.1))


@pytest.mark.parametrize("kind,hidden,unroll,shared", [("grounded-gru", (16,), 1, True), ("gru", (16, 12), K, False),
                                                       ("frozen-gru", (16,), 2, True)])
def test_fused_chain_equals_the_scanned_term_values_and_gradients(kind, hidden, unroll, shared):
    """`mlp_step` with an MLPModel and a GRUCell encoder runs the fused chain: the same terms, metrics and gradients
    (model layers, encoder, actions, start states) as the scanned term, under path weights apart and a mask; with
    the encoder normalising by the model's own statistics (shared) or by others."""
    s0, actions, real = _real_windows(seed=1)
    model = _mlp_model(hidden=hidden)
    enc = _encoder(kind)
    stats = model.obs if shared else _stats()
    mask = jnp.arange(W) % 4 != 1
    weights = cc.PathWeights(model=0.7, policy=0.3, encoder=0.4)

    def loss(fused, model, params, acts, s0):
        terms, metrics = cc.consistency_loss(cc.mlp_step, model, s0, acts, real, mask, kind=kind, normalize=stats,
                                             weights=weights, encoder=enc["encoder"], encoder_params=params,
                                             unroll=unroll, fused=fused)
        return 1.3 * terms["consistency"] + 0.6 * terms.get("encoder_aux", 0.0), (terms, metrics)

    args = (model, enc["encoder_params"], actions, s0)
    (v_f, (t_f, m_f)), g_f = jax.jit(jax.value_and_grad(functools.partial(loss, True), argnums=(0, 1, 2, 3),
                                                        has_aux=True))(*args)
    (v_s, (t_s, m_s)), g_s = jax.jit(jax.value_and_grad(functools.partial(loss, False), argnums=(0, 1, 2, 3),
                                                        has_aux=True))(*args)
    np.testing.assert_allclose(v_f, v_s, rtol=1e-5)
    for name in m_s:
        np.testing.assert_allclose(m_f[name], m_s[name], rtol=1e-5, atol=1e-7, err_msg=name)
    assert float(v_f) > 0
    for (path, a), b in zip(jax.tree_util.tree_leaves_with_path(g_s), jax.tree.leaves(g_f)):
        np.testing.assert_allclose(b, a, rtol=2e-4, atol=1e-6, err_msg=jax.tree_util.keystr(path))
    model_grads, enc_grads, action_grads, _ = g_f
    assert float(jnp.abs(action_grads).max()) > 0 and float(jnp.abs(model_grads.layers[0][0]).max()) > 0
    moved = any(float(jnp.abs(x).max()) > 0 for x in jax.tree.leaves(enc_grads))
    assert moved == (kind != "frozen-gru")


@pytest.mark.parametrize("spread,beyond", [(40.0, True), (1.0, False)])
def test_final_beyond_clip_is_the_share_of_final_states_past_the_clip(spread, beyond):
    """consistency/final_beyond_clip: the share of the unmasked windows' final imagined features that normalise
    beyond +-CLIP before the clip; states that reach `spread` std of the encoder's statistics (here the model's own)
    give a large share when spread is far beyond CLIP and none inside it; fused and scanned agree."""
    s0, actions, real = _real_windows(seed=3)
    model = _mlp_model()
    model = model.replace(obs=nz.update(nz.RunningStats.create(4),
                                        (1.0 / spread) * jax.random.normal(jax.random.key(7), (64, 4))))
    enc = _encoder("grounded-gru")
    mask = jnp.arange(W) % 3 != 2
    shares = []
    for fused in (True, False):
        _, metrics = cc.consistency_loss(cc.mlp_step, model, s0, actions, real, mask, kind="grounded-gru",
                                         normalize=model.obs, weights=ONE, fused=fused, **enc)
        shares.append(float(metrics["consistency/final_beyond_clip"]))
    assert shares[0] == shares[1]
    assert (shares[0] > 0.1) if beyond else (shares[0] == 0.0)


@pytest.mark.parametrize("hidden,shared", [((16,), True), ((16, 12), False)])
def test_the_fused_chain_is_autodiff_of_the_plain_loop_with_every_output(hidden, shared, monkeypatch):
    """`fused_chain` against JAX's own gradient of k plain `mlp_step`s and GRU steps, with a loss on all three
    outputs (h_re, h_im and the final state s_k, which the terms use only in a metric), the GRU's real and imagined
    rows' gradients scaled apart, on states far beyond CLIP (where the clip binds); and so with its weight gradients
    summed over chunks of steps (GRAD_CHUNK, the last chunk shorter)."""
    s0, actions, real = _real_windows(seed=4)
    model = _mlp_model(hidden=hidden)
    model = model.replace(obs=nz.update(nz.RunningStats.create(4), 0.025 * jax.random.normal(jax.random.key(7),
                                                                                               (64, 4))))
    enc_obs = model.obs if shared else _stats()
    gru = cc.gru_weights(_encoder("gru")["encoder_params"])
    x_re = nz.normalize(enc_obs, real)
    scales = (0.7, 0.4)
    weights = jax.random.normal(jax.random.key(9), (3, W, gru[2].shape[0]))

    def objective(h_re, h_im, s_k):
        return (weights[0] * h_re).sum() + (weights[1] * h_im).sum() + 0.3 * (s_k ** 2).sum()

    def fused(model, gru, s0, actions, x_re):
        return objective(*cc.fused_chain(model, gru, s0, actions, x_re, enc_obs, scales, shared))

    def plain(model, gru, s0, actions, x_re):
        def cell(g, h, x):
            w_i, b_i, w_h, b_hn = g
            gh = h @ w_h + jnp.concatenate([jnp.zeros((2 * w_h.shape[0],)), b_hn])
            return cc.gru_gates(x @ w_i + b_i, gh, h)

        g_re, g_im = cc.scale_gradient(gru, scales[0]), cc.scale_gradient(gru, scales[1])
        s, h_re, h_im = s0, jnp.zeros((W, gru[2].shape[0])), jnp.zeros((W, gru[2].shape[0]))
        for t in range(K):
            s = cc.mlp_step(model, s, actions[t])
            h_re, h_im = cell(g_re, h_re, x_re[t]), cell(g_im, h_im, nz.normalize(enc_obs, s))
        return objective(h_re, h_im, s)

    args = (model, gru, s0, actions, x_re)
    v_f, g_f = jax.jit(jax.value_and_grad(fused, argnums=(0, 1, 2, 3, 4)))(*args)
    v_p, g_p = jax.jit(jax.value_and_grad(plain, argnums=(0, 1, 2, 3, 4)))(*args)
    np.testing.assert_allclose(v_f, v_p, rtol=1e-5)
    for (path, a), b in zip(jax.tree_util.tree_leaves_with_path(g_p), jax.tree.leaves(g_f)):
        np.testing.assert_allclose(b, a, rtol=2e-4, atol=1e-6,
                                   err_msg=jax.tree_util.keystr(path))
    assert float(jnp.abs(g_f[2]).max()) > 0 and float(jnp.abs(g_f[0].layers[-1][0]).max()) > 0
    monkeypatch.setattr(cc, "GRAD_CHUNK", 4)  # K = 6 steps: chunks of 4 and 2
    g_c = jax.jit(jax.grad(lambda *a: fused(*a), argnums=(0, 1, 2, 3, 4)))(*args)  # a new function: traced again
    for (path, a), b, f in zip(jax.tree_util.tree_leaves_with_path(g_p), jax.tree.leaves(g_c), jax.tree.leaves(g_f)):
        np.testing.assert_allclose(b, a, rtol=2e-4, atol=1e-6, err_msg=jax.tree_util.keystr(path))
        np.testing.assert_allclose(b, f, rtol=1e-5, atol=1e-6, err_msg=jax.tree_util.keystr(path))
    s_k = cc.fused_chain(model, gru, s0, actions, x_re, enc_obs, scales, shared)[2]
    assert float(jnp.abs((s_k - model.obs.mean) / model.obs.std).max()) > nz.CLIP  # the states leave the clip's range


def test_grounding_term_alone_is_the_terms_encoder_aux_with_its_gradient():
    """The grounded encoder's auxiliary term without the k-step chain (what the gradient diagnostics differentiate
    apart) equals the fused term's encoder_aux, in value and in its gradient on the encoder."""
    s0, actions, real = _real_windows(seed=1)
    model = _mlp_model(hidden=(16,))
    enc = _encoder("grounded-gru")
    mask = jnp.arange(W) % 4 != 1

    def whole(params):
        terms, _ = cc.consistency_loss(cc.mlp_step, model, s0, actions, real, mask, kind="grounded-gru",
                                       normalize=model.obs, weights=ONE, encoder=enc["encoder"], encoder_params=params)
        return terms["encoder_aux"]

    alone = lambda params: cc.grounding_term(enc["encoder"], params, real, mask, model.obs)[0]  # noqa: E731
    (v_w, g_w), (v_a, g_a) = (jax.jit(jax.value_and_grad(f))(enc["encoder_params"]) for f in (whole, alone))
    np.testing.assert_allclose(v_a, v_w, rtol=1e-5)
    assert float(v_a) > 0
    for a, b in zip(jax.tree.leaves(g_a), jax.tree.leaves(g_w)):
        np.testing.assert_allclose(a, b, rtol=2e-4, atol=1e-7)


def test_mlp_step_is_the_agents_model_step():
    """The obs-space agent's model in the fused form (`ObsAgent.mlp_model`) steps exactly as its model_step."""
    from cdjax.agents.obs import networks
    from cdjax.agents.obs.agent import ObsAgent

    from _shared import POINT

    agent = ObsAgent(POINT.replace(model_hidden=(16, 8)))
    params = networks.init_params(agent.modules, jax.random.key(0), agent.O, agent.A, -0.5)
    norms = nz.Norms(obs=_stats(), delta=nz.update(nz.RunningStats.create(4), 0.1 * jax.random.normal(
        jax.random.key(3), (64, 4))), reward=nz.RunningStats.create(1))
    s = jax.random.normal(jax.random.key(4), (7, agent.O))
    a = jax.random.uniform(jax.random.key(5), (7, agent.A), minval=-1, maxval=1)
    np.testing.assert_allclose(cc.mlp_step(agent.mlp_model(params["model"], norms), s, a),
                               agent.model_step(params["model"], norms, s, a)[0], rtol=1e-6, atol=1e-6)


def _transposes(jaxpr) -> int:
    """How many transpose operations a jaxpr holds, its sub-jaxprs' included."""
    return sum(e.primitive.name == "transpose" for e in jaxpr.eqns) + sum(
        _transposes(sub) for e in jaxpr.eqns for sub in jax.extend.core.jaxprs_in_params(e.params))


@pytest.mark.parametrize("shared", [True, False])
def test_the_fused_chain_under_vmap_moves_no_axis_in_its_steps(shared):
    """The fused chain's gradient vmapped over runs (as a sweep's seeds are) holds the unbatched gradient's transposes
    (its products' weights, which XLA folds into the products) and two more, not some in every step: its real and
    imagined rows and its per-step arrays are stacked so that the runs' axis stays in front (a stack along a new
    leading axis put it second, and XLA transposed it back in every step on a GPU)."""
    s0, actions, real = _real_windows(seed=4)
    model = _mlp_model()
    enc_obs = model.obs if shared else _stats()
    gru = cc.gru_weights(_encoder("gru")["encoder_params"])

    def loss(model, gru, s0, actions, x_re):
        h_re, h_im, s_k = cc.fused_chain(model, gru, s0, actions, x_re, enc_obs, (0.7, 0.4), shared)
        return (h_re * h_im).sum() + (s_k ** 2).sum()

    grad = jax.grad(loss, argnums=(0, 1, 2, 3, 4))
    args = (model, gru, s0, actions, nz.normalize(enc_obs, real))
    runs = jax.tree.map(lambda x: jnp.stack([x, x + 0.1]), args)
    alone = _transposes(jax.make_jaxpr(grad)(*args).jaxpr)
    assert alone >= K  # the products' transposed weights, at least one per step
    assert _transposes(jax.make_jaxpr(jax.vmap(grad))(*runs).jaxpr) <= alone + 2
