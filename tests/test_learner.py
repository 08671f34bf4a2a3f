"""The learner inside the update: path weights against Mb-Mf, gradient-norm metrics, warm statistics,
sequence minibatches, GAE with the current value net, time-outs in physics steps."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from cdjax import HParams
from cdjax.agents.obs.learner import TERM_GROUPS, make_agent, refresh_norms, term_weights, to_segments

from _shared import EXACT, POINT, compiled

HP = HParams(alpha=1.0)


@pytest.fixture(scope="module")
def point_batch():
    """A trained-a-little cd state on the point mass, a fresh rollout and its first minibatch [T, Bs]."""
    trainer, init, update = compiled(POINT)
    state = init(jax.random.key(0), HP)
    for _ in range(3):  # non-trivial statistics, a model not at init; the next rollout holds time-out 40
        state, _ = update(state, HP)
    _, _, traj, batch = jax.jit(trainer.collect)(state, HP, jax.random.key(7))
    mb = jax.tree.map(lambda x: x[:, : POINT.minibatch_seqs], batch)
    return trainer, state, traj, batch, mb


def _grads(trainer, params, norms, mb, hp):
    offsets = jnp.arange(POINT.num_windows)
    return jax.jit(jax.grad(trainer.loss, has_aux=True), compiler_options=EXACT)(params, norms, mb, offsets, hp)


def _assert_same(a, b):
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)):
        np.testing.assert_allclose(x, y, rtol=1e-6, atol=1e-9)


def _differ(a, b) -> bool:
    return any(not np.allclose(x, y, rtol=1e-4, atol=1e-7) for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)))


def test_each_path_weight_at_zero_leaves_that_group_with_mbmf_gradient(point_batch):
    trainer, state, _, _, mb = point_batch
    mbmf, _, _ = compiled(POINT.replace(arm="mbmf"))
    params = {name: p for name, p in state.params.items() if name != "encoder"}
    g_mbmf, _ = _grads(mbmf, params, state.norms, mb, HP.replace(alpha=0.0))
    no_policy, m = _grads(trainer, state.params, state.norms, mb, HP.replace(cc_policy=0.0))
    assert float(m["loss/consistency"]) > 0
    _assert_same(no_policy["policy"], g_mbmf["policy"])  # the policy sees PPO alone ...
    assert _differ(no_policy["model"], g_mbmf["model"])  # ... while the model still gets l_cc
    no_model, _ = _grads(trainer, state.params, state.norms, mb, HP.replace(cc_model=0.0))
    _assert_same(no_model["model"], g_mbmf["model"])  # the model sees its NLL alone ...
    assert _differ(no_model["policy"], g_mbmf["policy"])  # ... while the policy still gets l_cc
    both, _ = _grads(trainer, state.params, state.norms, mb, HP)
    _assert_same(both["value"], g_mbmf["value"])  # l_cc never reaches the value function


def test_gradient_norm_metrics_match_per_term_gradients(point_batch):
    trainer, state, _, _, mb = point_batch
    hp = HP.replace(alpha=0.7, cc_policy=0.3, enc_aux_coef=2.0, model_coef=0.5).as_float32()
    offsets = jnp.arange(POINT.num_windows)
    metrics = jax.jit(trainer.grad_norms)(state.params, state.norms, mb, offsets, hp)
    weights = term_weights(hp)
    expected = {}
    for name, groups in TERM_GROUPS.items():
        term = lambda p, name=name: weights[name] * trainer.loss_terms(p, state.norms, mb, offsets, hp)[0][name]  # noqa: E731
        grads = jax.jit(jax.grad(term))(state.params)
        for group in groups:
            leaves = jax.tree.leaves(grads[group])
            expected[f"grad/{name}/{group}"] = float(np.sqrt(sum(float((x ** 2).sum()) for x in leaves)))
    total = jax.jit(jax.grad(lambda p: trainer.loss(p, state.norms, mb, offsets, hp)[0]))(state.params)
    for group in state.params:
        expected[f"grad/total/{group}"] = float(optax.global_norm(total[group]))
    assert set(metrics) == set(expected)
    for name, value in expected.items():
        np.testing.assert_allclose(metrics[name], value, rtol=1e-4, err_msg=name)
    assert expected["grad/consistency/policy"] > 0 and expected["grad/encoder_aux/encoder"] > 0
    # the terms besides l_cc are differentiated together, so each group must be reached by one of them at most
    for group in state.params:
        assert sum(group in groups for name, groups in TERM_GROUPS.items() if name != "consistency") <= 1, group


def _first_update(config, seed: int):
    """One update of `config` from init, and what its SGD's first step saw: (trainer, state before, state after,
    metrics, the statistics with the first rollout joined, the first minibatch and its windows' offsets)."""
    trainer, init, update = compiled(config)
    state = init(jax.random.key(seed), HP)
    new, metrics = update(state, HP)
    _, key_roll, key_sgd = jax.random.split(state.key, 3)
    _, _, traj, batch = jax.jit(trainer.collect)(state, HP, key_roll)
    warm = refresh_norms(state.norms, traj.obs, traj.next_obs, traj.reward, traj.valid)
    _, key_epochs = jax.random.split(key_sgd)  # the SGD's first minibatch: the diagnostics are its step's
    segments = jax.tree.map(lambda x: to_segments(x, config.segment), batch)
    first, offsets = trainer.first_minibatch(segments, jax.random.split(key_epochs, config.num_epochs)[0])
    return trainer, state, new, metrics, warm, first, offsets


def test_update_zero_normalises_with_the_first_rollout():
    """The first rollout joins the (empty) statistics before SGD: update 0's minibatches are normalised with
    them (its gradient diagnostics equal those computed with the first rollout's statistics, not the cold
    ones), and the state carries them."""
    trainer, state, new, metrics, warm, first, offsets = _first_update(POINT, 1)
    assert float(new.norms.obs.count) == POINT.rollout_len * POINT.num_envs
    _assert_same(new.norms, warm)
    diag = jax.jit(trainer.grad_norms)
    with_warm, with_cold = diag(state.params, warm, first, offsets, HP), diag(state.params, state.norms, first, offsets, HP)
    for name in with_warm:
        np.testing.assert_allclose(metrics[name], with_warm[name], rtol=1e-5, err_msg=name)
    assert not np.isclose(metrics["grad/model_nll/model"], with_cold["grad/model_nll/model"], rtol=1e-2)


@pytest.mark.parametrize("changes", [dict(arm="model-free"), dict(cc_epochs=1)], ids=["model-free", "cd-first-epoch"])
def test_the_sgds_gradient_diagnostics_are_its_first_steps(changes):
    """The SGD's gradient diagnostics are its first step's: they equal `grad_norms` of its first minibatch, for the
    model-free arm (no taps) and for CD with the term in the first epoch only (the later epoch's steps must not replace
    them)."""
    trainer, state, _, metrics, warm, first, offsets = _first_update(POINT.replace(**changes), 3)
    expected = jax.jit(trainer.grad_norms)(state.params, warm, first, offsets, HP)
    assert expected and all(name.startswith("grad/") for name in expected)
    for name in expected:
        np.testing.assert_allclose(metrics[name], expected[name], rtol=1e-5, err_msg=name)


def test_to_segments_by_hand():
    x = jnp.arange(6 * 2).reshape(6, 2)  # x[t, b] = 2t + b, T = 6, B = 2
    seg = to_segments(x, 3)  # 2 segments of 3 steps per env: columns (s=0, b=0), (0, 1), (1, 0), (1, 1)
    np.testing.assert_array_equal(seg, [[0, 1, 6, 7], [2, 3, 8, 9], [4, 5, 10, 11]])


def test_sequence_minibatches_update_runs_and_learns_the_model():
    """segment_len < T: minibatches of shuffled (env, segment) sequences; the windows stay inside them."""
    config = POINT.replace(segment_len=6, num_minibatches=4)
    _, init, update = compiled(config)
    state = init(jax.random.key(2), HP)
    nll = []
    for _ in range(6):
        state, m = update(state, HP)
        nll.append(float(m["loss/model_nll"]))
        assert float(m["consistency/masked_fraction"]) < 1.0
    assert nll[-1] < nll[1]


def test_gae_in_the_loss_equals_the_rollout_gae_with_the_same_value_net(point_batch):
    """With the rollout's own parameters and statistics, recomputing GAE inside a minibatch of whole-rollout
    sequences (from a rollout that valued only the time-outs' final observations) gives the advantages that
    GAE once per rollout computes at acting time (time-outs bootstrap on the final observation)."""
    trainer, state, traj, batch, _ = point_batch
    assert bool(traj.truncated.any()) and batch.advantages is None
    once = make_agent(POINT.replace(gae_in_loss=False))
    _, _, _, full = jax.jit(once.collect)(state, HP, jax.random.key(7))  # the same rollout
    adv, ret = jax.jit(trainer.advantages)(state.params, state.norms, batch, HP)
    np.testing.assert_allclose(adv, full.advantages, rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(ret, full.returns, rtol=1e-4, atol=1e-5)


def test_time_out_counts_physics_steps_with_action_repeat():
    from cdjax.envs import BatchedEnv
    from cdjax.envs.point import PointMass

    env = BatchedEnv(PointMass(start_range=0.2), num_envs=2, episode_length=6, action_repeat=2)
    state = env.reset(jax.random.key(0))
    step = jax.jit(env.step)
    truncated = []
    for _ in range(4):
        state, out = step(state, jnp.zeros((2, 2)))
        truncated.append(bool(out.truncated.all()))
    assert truncated == [False, False, True, False]  # 3 agent steps x 2 physics steps = 6


def test_skip_if_not_finite_equals_optax_apply_if_finite():
    """The select-based skip gives optax.apply_if_finite's updates and state over finite and non-finite steps."""
    from cdjax.optim import skip_if_not_finite

    params = {"w": jnp.arange(3.0), "b": jnp.ones((2, 2))}
    inner = optax.chain(optax.clip_by_global_norm(1.0), optax.adam(0.1))
    ours, ref = skip_if_not_finite(inner), optax.apply_if_finite(inner, max_consecutive_errors=1_000_000)
    s_ours, s_ref = ours.init(params), ref.init(params)
    grads = [{"w": jnp.array([1.0, -2.0, 0.5]), "b": jnp.full((2, 2), 0.3)},
             {"w": jnp.array([jnp.nan, 1.0, 0.0]), "b": jnp.ones((2, 2))},
             {"w": jnp.array([0.1, 0.2, jnp.inf]), "b": jnp.ones((2, 2))},
             {"w": jnp.array([-1.0, 0.5, 2.0]), "b": jnp.full((2, 2), -0.7)}]
    for g in grads:
        (u_ours, s_ours), (u_ref, s_ref) = (jax.jit(ours.update, compiler_options=EXACT)(g, s_ours, params),
                                            ref.update(g, s_ref, params))
        for a, b in zip(jax.tree.leaves((u_ours, s_ours)), jax.tree.leaves((u_ref, s_ref))):
            np.testing.assert_array_equal(a, b)
    assert int(s_ours.total_notfinite) == 2 and int(s_ours.notfinite_count) == 0
    assert jax.tree.structure(s_ours) == jax.tree.structure(s_ref)


def test_per_group_vectors_gives_the_tree_optimizers_steps():
    """Adam with clipping per group on one raveled vector per group takes the steps it takes on the trees, and
    a non-finite step is still skipped."""
    from cdjax.optim import per_group_vectors, skip_if_not_finite

    params = {"policy": {"w": jnp.arange(6.0).reshape(2, 3), "b": jnp.ones(3)},
              "value": {"w": jnp.full((3, 1), 0.5), "b": jnp.zeros(1)}}
    groups = lambda p: {name: jax.tree.map(lambda _: name, sub) for name, sub in p.items()}  # noqa: E731
    chains = {"policy": optax.chain(optax.clip_by_global_norm(1.0), optax.adam(0.1)),
              "value": optax.chain(optax.clip_by_global_norm(0.5), optax.adam(0.03))}
    on_trees = skip_if_not_finite(optax.multi_transform(chains, groups))
    on_vectors = per_group_vectors(skip_if_not_finite(optax.multi_transform(chains, lambda p: {n: n for n in p})))
    s_tree, s_vec = on_trees.init(params), on_vectors.init(params)
    key = jax.random.key(3)
    for i in range(4):
        key, sub = jax.random.split(key)
        grads = jax.tree.map(lambda x: 3.0 * jax.random.normal(sub, x.shape), params)
        if i == 2:
            grads["value"]["b"] = jnp.array([jnp.nan])
        u_tree, s_tree = on_trees.update(grads, s_tree, params)
        u_vec, s_vec = jax.jit(on_vectors.update)(grads, s_vec, params)
        assert jax.tree.structure(u_vec) == jax.tree.structure(u_tree)
        for a, b in zip(jax.tree.leaves(u_vec), jax.tree.leaves(u_tree)):
            np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-7)
        params = optax.apply_updates(params, u_tree)
    assert int(s_vec.total_notfinite) == 1 == int(s_tree.total_notfinite)
    assert s_vec.inner_state.inner_states["value"].inner_state[1][0].mu["value"].shape == (4,)  # one vector per group


def test_diagnostic_shares_sum_to_the_scalar_diagnostics_with_the_same_gradient(point_batch):
    """loss(shares=True): the diagnostics of share_metrics() per sample [L, Bs], summing to the scalar masked means
    of shares=False; every other metric and the gradient unchanged."""
    trainer, state, _, _, mb = point_batch
    offsets = jnp.arange(POINT.num_windows)
    grad = jax.jit(jax.grad(trainer.loss, has_aux=True), static_argnums=(5, 7), compiler_options=EXACT)
    g, scalar = grad(state.params, state.norms, mb, offsets, HP, True, None, False)
    g_shares, shared = grad(state.params, state.norms, mb, offsets, HP, True, None, True)
    assert set(shared) == set(scalar)
    for name in trainer.share_metrics():
        assert shared[name].shape == mb.valid.shape, name
        # a float32 sum's rounding scales with its terms' magnitudes, not with the sum: the policy loss's shares
        # (advantages normalised to mean zero) nearly cancel
        scale = float(jnp.abs(shared[name]).sum())
        np.testing.assert_allclose(shared[name].sum(), scalar[name], rtol=1e-5, atol=1e-8 + 1e-6 * scale,
                                   err_msg=name)
    assert float(scalar["model/reward_mse"]) > 0 and float(scalar["ppo/clip_fraction"]) >= 0
    for name in set(scalar) - set(trainer.share_metrics()):
        assert shared[name].shape == () and float(shared[name]) == float(scalar[name]), name
    for a, b in zip(jax.tree.leaves(g), jax.tree.leaves(g_shares)):
        assert jnp.array_equal(a, b)


@pytest.mark.parametrize("arm, cc_epochs", [("mbmf", 0), ("cd", 1)])
def test_sgd_diagnostics_are_the_mean_of_every_steps_masked_means(arm, cc_epochs):
    """sgd's metrics (its shares summed once after the loop, the others stacked per step) equal the mean over its
    epochs x minibatches of each step's scalar metrics, stepped here by hand in the same order; for cd with the
    consistency term in the first epoch only, across both of sgd's loops."""
    from cdjax import consistency
    from cdjax.agents.obs.optim import make_optimizer

    config = POINT.replace(arm=arm, cc_epochs=cc_epochs)
    trainer = make_agent(config)
    hp = HP.replace(alpha=0.0 if arm == "mbmf" else 1.0).as_float32()
    state = jax.jit(trainer.init)(jax.random.key(3), hp)
    _, _, _, batch = jax.jit(trainer.collect)(state, hp, jax.random.key(8))
    key = jax.random.key(9)
    (params, _), metrics = jax.jit(trainer.sgd)(state.params, state.opt_state, state.norms, batch, hp, key)

    tx = make_optimizer(config, state.params, hp)
    segments = jax.tree.map(lambda x: to_segments(x, trainer.L), batch)

    @functools.partial(jax.jit, static_argnums=4)
    def step(p, o, mb, offsets, with_consistency):
        g, m = jax.grad(trainer.loss, has_aux=True)(p, state.norms, mb, offsets, hp, with_consistency)
        updates, o = tx.update(g, o, p)
        return optax.apply_updates(p, updates), o, m

    p, o, seen = state.params, state.opt_state, []
    n_cc = cc_epochs or config.num_epochs
    for epoch, epoch_key in enumerate(jax.random.split(jax.random.split(key)[1], config.num_epochs)):
        perm, mb_keys = trainer.shuffle(epoch_key)
        for i in range(trainer.M):
            rows = perm[i * config.minibatch_seqs:(i + 1) * config.minibatch_seqs]
            offsets = consistency.window_offsets(mb_keys[i], trainer.L, trainer.k, config.num_windows)
            mb = jax.tree.map(lambda x, rows=rows: x[:, rows], segments)
            p, o, m = step(p, o, mb, offsets, arm == "cd" and epoch < n_cc)
            seen.append(m)
    assert len(seen) == config.num_epochs * trainer.M > 1
    for name in trainer.share_metrics() + ("loss/model_nll", "loss/policy"):
        expected = np.mean([float(m[name]) for m in seen])
        np.testing.assert_allclose(metrics[name], expected, rtol=1e-4, atol=1e-7, err_msg=name)
    assert np.std([float(m["model/reward_mse"]) for m in seen]) > 0  # a mean of different steps, not one step's
    for a, b in zip(jax.tree.leaves(params), jax.tree.leaves(p)):  # the same steps
        np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-6)
