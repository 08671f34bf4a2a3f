"""Losses and statistics against hand-worked numbers."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cdjax import HParams, numerics
from cdjax.protocol import ConfigError
from cdjax.agents.obs import losses, networks
from cdjax import normalize as nz


def _gae(ended, bootstrap):
    reward = jnp.array([[1.0], [2.0], [3.0]])
    value = jnp.array([[0.5], [1.0], [1.5]])
    next_value = jnp.array([[1.0], [1.5], [2.0]])
    return losses.gae(reward, value, next_value, jnp.array(bootstrap)[:, None], jnp.array(ended)[:, None], 0.5, 0.5)


def test_gae_no_episode_end():
    # delta = (1.0, 1.75, 2.5); A2 = 2.5, A1 = 1.75 + 0.25 * 2.5, A0 = 1 + 0.25 * A1
    adv, ret = _gae([False, False, False], [True, True, True])
    np.testing.assert_allclose(adv[:, 0], [1.59375, 2.375, 2.5], rtol=1e-6)
    np.testing.assert_allclose(ret[:, 0], [2.09375, 3.375, 4.0], rtol=1e-6)


def test_gae_truncation_bootstraps_but_cuts_the_recursion():
    adv, _ = _gae([False, True, False], [True, True, True])
    np.testing.assert_allclose(adv[:, 0], [1.4375, 1.75, 2.5], rtol=1e-6)


def test_gae_termination_does_not_bootstrap():
    # delta1 = 2 - 1 = 1 (no gamma * V(s')), A0 = 1 + 0.25 * 1
    adv, _ = _gae([False, True, False], [True, False, True])
    np.testing.assert_allclose(adv[:, 0], [1.25, 1.0, 2.5], rtol=1e-6)


def test_ppo_clipping_and_masking():
    hp = HParams(clip_eps=0.2, vf_coef=0.5, ent_coef=0.0).as_float32()
    log_old = jnp.zeros((3,))
    log_new = jnp.log(jnp.array([1.5, 0.5, 7.0]))  # ratios 1.5, 0.5 and a masked outlier
    adv = jnp.array([1.0, -1.0, 100.0])  # normalised over the unmasked samples: (1, -1)
    mask = jnp.array([True, True, False])
    value, returns = jnp.array([0.0, 1.0, 50.0]), jnp.array([1.0, 3.0, -50.0])
    loss, m = losses.policy_terms(log_new, jnp.zeros(3), value, log_old, adv, returns, mask, hp)
    # surrogates: min(1.5 * 1, 1.2 * 1) = 1.2 and min(0.5 * -1, 0.8 * -1) = -0.8
    np.testing.assert_allclose(m["loss/policy"], -(1.2 - 0.8) / 2, rtol=1e-5)
    np.testing.assert_allclose(m["loss/value"], 0.5 * (1.0 + 4.0) / 2, rtol=1e-6)
    np.testing.assert_allclose(loss, -0.2 + 0.5 * 1.25, rtol=1e-5)
    np.testing.assert_allclose(m["ppo/clip_fraction"], 1.0)


def test_ppo_loss_matches_gaussian_log_prob():
    hp = HParams().as_float32()
    mean, log_std = jnp.array([[0.3, -0.2]]), jnp.array([[0.1, -0.4]])
    raw = jnp.array([[0.5, 0.0]])
    std = jnp.exp(log_std)
    logp = (-0.5 * ((raw - mean) / std) ** 2 - log_std - 0.5 * jnp.log(2 * jnp.pi)).sum(-1)
    # log_prob_old = logp makes the ratio exactly 1; with advantages (1) normalised to 0 the loss is 0
    loss, m = losses.ppo_loss(mean, std, jnp.zeros(1), raw, logp, jnp.ones(1), jnp.zeros(1), jnp.ones(1, bool), hp)
    np.testing.assert_allclose(m["ppo/approx_kl"], 0.0, atol=1e-6)
    np.testing.assert_allclose(m["loss/policy"], 0.0, atol=1e-6)
    np.testing.assert_allclose(m["loss/entropy"], (0.5 + 0.5 * jnp.log(2 * jnp.pi) + log_std).sum(), rtol=1e-6)


def test_squashed_entropy_by_hand():
    """Gaussian entropy plus log(1 - tanh(u)^2) at u = mean + std * noise, per action dimension summed."""
    mean, std, noise = jnp.array([[0.3, -2.0]]), jnp.array([[0.5, 0.2]]), jnp.array([[1.0, -1.5]])
    u = np.array([0.3 + 0.5, -2.0 - 0.3])
    gaussian = (0.5 + 0.5 * np.log(2 * np.pi) + np.log([0.5, 0.2])).sum()
    expected = gaussian + np.log(1 - np.tanh(u) ** 2).sum()
    np.testing.assert_allclose(networks.squashed_entropy(mean, std, noise), [expected], rtol=1e-5)
    # a saturating mean lowers the estimate; the Gaussian entropy alone does not see it
    far = networks.squashed_entropy(mean + 5.0, std, noise)
    assert float(far[0]) < expected - 5
    # large |u| stays finite (tanh saturates to 1 in float32; the closed form does not)
    assert np.isfinite(networks.squashed_entropy(jnp.array([[40.0]]), jnp.array([[1.0]]), jnp.array([[0.0]]))).all()


def test_gae_ignores_invalid_steps():
    """A non-finite step (valid = 0) has zero TD error: nothing of -V(s) reaches the step before it."""
    reward = jnp.array([[1.0], [0.0], [1.0]])
    value = jnp.array([[0.5], [7.0], [0.2]])
    next_value = jnp.array([[7.0], [0.0], [0.3]])
    valid = jnp.array([[True], [False], [True]])
    ended = ~valid  # the invalid step ends (and resets) its episode
    adv, _ = losses.gae(reward, value, next_value, valid, ended, 0.9, 0.8, valid)
    np.testing.assert_allclose(adv[:, 0], [1.0 + 0.9 * 7.0 - 0.5, 0.0, 1.0 + 0.9 * 0.3 - 0.2], rtol=1e-6)


def test_model_nll_and_mask():
    target = jnp.array([[1.0, 2.0], [5.0, 5.0]])
    mean = jnp.array([[1.0, 0.0], [0.0, 0.0]])
    log_std = jnp.zeros((2, 2))
    loss, m = losses.model_loss(mean, log_std, target, jnp.array([True, False]))
    np.testing.assert_allclose(loss, 0.5 * 4.0 + jnp.log(2 * jnp.pi), rtol=1e-6)  # 2 dims x 0.5 log 2 pi
    np.testing.assert_allclose(m["model/onestep_mse"], 0.0)
    np.testing.assert_allclose(m["model/reward_mse"], 4.0)


def test_running_stats_match_numpy_with_mask():
    rng = np.random.default_rng(0)
    a, b = rng.normal(3.0, 2.0, (50, 3)), rng.normal(-1.0, 0.5, (30, 3))
    mask_b = np.arange(30) % 3 != 0
    b_with_nan = b.copy()
    b_with_nan[~mask_b] = np.nan  # masked rows may hold anything
    s = nz.update(nz.update(nz.RunningStats.create(3), jnp.asarray(a, jnp.float32)),
                  jnp.asarray(b_with_nan, jnp.float32), jnp.asarray(mask_b))
    ref = np.concatenate([a, b[mask_b]])
    assert float(s.count) == len(ref)
    np.testing.assert_allclose(s.mean, ref.mean(0), rtol=1e-5)
    np.testing.assert_allclose(s.std, ref.std(0), rtol=1e-4)
    z = nz.normalize(s, jnp.asarray(ref, jnp.float32))
    np.testing.assert_allclose(z.mean(0), 0.0, atol=1e-4)


@pytest.mark.parametrize("steps", [1, 5, 20, numerics.DENSE_MAX_STEPS, numerics.DENSE_MAX_STEPS + 1])
def test_backward_recurrence_equals_the_sequential_loop(steps):
    """Both solvers (closed form up to DENSE_MAX_STEPS, associative scan beyond) give x_t = b_t + a_t x_{t+1} as a
    step-by-step loop does, with cuts (a = 0) and batch axes; a non-finite b_s reaches no x_t of t > s."""
    key_a, key_b, key_cut = jax.random.split(jax.random.key(steps), 3)
    a = jax.random.uniform(key_a, (steps, 3, 2), minval=0.5, maxval=1.0)
    a = jnp.where(jax.random.bernoulli(key_cut, 0.15, a.shape), 0.0, a)
    b = jax.random.normal(key_b, (steps, 3, 2))
    x, expected = np.zeros((3, 2), np.float32), []
    for t in reversed(range(steps)):
        x = np.asarray(b[t]) + np.asarray(a[t]) * x
        expected.append(x)
    np.testing.assert_allclose(numerics.backward_linear_recurrence(a, b), np.stack(expected[::-1]), rtol=1e-5,
                               atol=1e-6)
    got = numerics.backward_linear_recurrence(a, b.at[0].set(jnp.nan))
    assert bool(jnp.isfinite(got[1:]).all()) and not bool(jnp.isfinite(got[0]).any())



def test_orthogonal_init_gives_flax_matrices_one_run_at_a_time_under_vmap():
    """cdjax.numerics.orthogonal under vmap, and under two nested vmaps, draws flax's orthogonal matrices bit for bit,
    each from its own key, by one QR per matrix: no batched QR (jaxlib's batched QR on a CPU waits inside XLA's
    thread pool, and two at once hung a 2-core machine's vmapped init)."""
    import re

    from flax import linen as nn

    shape = (12, 5)
    keys = jax.random.split(jax.random.key(3), 6).reshape(2, 3)
    ours = jax.jit(jax.vmap(jax.vmap(lambda key: numerics.orthogonal(1.5)(key, shape))))(keys)
    flax_one = jax.jit(lambda key: nn.initializers.orthogonal(1.5)(key, shape))
    for i, j in np.ndindex(2, 3):
        np.testing.assert_array_equal(ours[i, j], flax_one(keys[i, j]))
    same = jax.vmap(lambda _: numerics.orthogonal(1.5)(keys[0, 0], shape))(jnp.arange(3))  # one key: one matrix
    np.testing.assert_array_equal(same, np.broadcast_to(flax_one(keys[0, 0]), (3, *shape)))
    program = str(jax.make_jaxpr(jax.vmap(jax.vmap(lambda key: numerics.orthogonal(1.5)(key, shape))))(keys))
    factored = re.findall(r"f32\[([\d,]+)\] \S+:f32\[[\d,]+\] = qr\[", program)
    assert factored == ["12,5"], factored


def test_policy_head_scale_scales_only_the_policy_head():
    """policy_head_scale multiplies lecun-uniform's policy head (its last layer's initial weights) and changes nothing
    else (hidden layers, biases; the same key draws the same weights); orthogonal weights keep their own head (gain
    0.01), and Config refuses another scale with them."""
    from cdjax.agents.obs.config import Config, validate

    key, obs = jax.random.PRNGKey(3), jnp.zeros((1, 5))

    def mlp(**kw):
        return networks.Policy(2, (8, 8), **kw).init(key, obs)["params"]["MLP_0"]

    brax, small = mlp(weight_init="lecun", head_scale=1.0), mlp(weight_init="lecun", head_scale=0.1)
    for layer in ("Dense_0", "Dense_1"):
        np.testing.assert_array_equal(small[layer]["kernel"], brax[layer]["kernel"])
    np.testing.assert_allclose(small["Dense_2"]["kernel"], 0.1 * brax["Dense_2"]["kernel"], rtol=1e-5, atol=1e-9)
    np.testing.assert_array_equal(small["Dense_2"]["bias"], brax["Dense_2"]["bias"])
    # lecun-uniform's own head: columns of 8 entries of variance 1/8, norm about 1; orthogonal's: norm 0.01
    assert 0.5 < np.linalg.norm(brax["Dense_2"]["kernel"], axis=0).mean() < 1.5
    for scale in (1.0, 0.1):
        ortho = mlp(weight_init="orthogonal", head_scale=scale)["Dense_2"]["kernel"]
        np.testing.assert_allclose(np.linalg.norm(ortho, axis=0), 0.01, rtol=1e-4)
    # the Config field reaches the policy (the default is 0.1), and orthogonal takes no other scale
    assert networks.build(Config(env="point", arm="model-free"), 5, 2)["policy"].head_scale == 0.1
    assert networks.build(Config(env="point", arm="model-free", policy_head_scale=1.0), 5, 2)["policy"].head_scale == 1.0
    validate(Config(env="point", weight_init="orthogonal"))
    with pytest.raises(ConfigError, match="policy_head_scale"):
        validate(Config(env="point", weight_init="orthogonal", policy_head_scale=1.0))
