"""The Mb-Mf model-based phase (cdjax/agents/obs/mbmf/) on the point mass: model, MPC, distillation, hand-over to PPO.

One compiled phase (module fixture) and one compiled evaluation function serve every test.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cdjax import ConfigError, HParams
from cdjax.agents.obs.mbmf import MbMfPhase, make_mbmf_phase, make_mpc_controller, total_env_steps
from cdjax.replay import RingBuffer, fit

from _shared import POINT, compiled

HP = HParams(alpha=1.0)
# Nagabandi et al. distil the MPC into a tanh MLP policy (the first paper-* presets did too); with swish, the default of
# the PPO learner, this 16-unit policy clones the controller less closely (distillation error 0.36 vs 0.32).
CONFIG = POINT.replace(activation="tanh")
PHASE = MbMfPhase(num_envs=16, random_steps=25, aggregation_iters=2, mpc_steps_per_iter=20, model_epochs=100,
                  model_minibatch=32, mpc_horizon=5, mpc_candidates=256, distill_iters=2, distill_steps_per_iter=20,
                  distill_epochs=200, distill_minibatch=64, value_epochs=5)
EVAL_STEPS = 30  # steps per evaluation rollout (16 envs, from the same reset states for every controller)
RANDOM, MPC, POLICY, POLICY_DET = range(4)  # action sources of `evaluate`


@pytest.fixture(scope="module")
def setup():
    trainer, init, update = compiled(CONFIG)
    run = jax.jit(make_mbmf_phase(CONFIG, PHASE, trainer))
    start = init(jax.random.key(0), HP)
    state, info = run(start, HP)
    controller = make_mpc_controller(trainer, PHASE)
    env = trainer.env

    @jax.jit
    def evaluate(source, params, norms, key):
        """Roll one action source for EVAL_STEPS steps from fixed reset states -> transitions [T, B, ...]."""

        def step(env_state, k):
            obs = env_state.obs
            branches = [
                lambda: jax.random.uniform(k, obs.shape[:1] + (env.action_size,), minval=-1.0, maxval=1.0),
                lambda: controller(params["model"], norms, obs, k),
                lambda: trainer.act(params, norms, obs, k),
                lambda: trainer.act(params, norms, obs, None),
            ]
            action = jax.lax.switch(source, branches)
            env_state, out = env.step(env_state, action)
            return env_state, dict(obs=obs, action=action, next_obs=out.next_obs, reward=out.reward, valid=out.valid)

        return jax.lax.scan(step, env.reset(jax.random.key(123)), jax.random.split(key, EVAL_STEPS))[1]

    controllers = jax.jit(jax.vmap(controller, in_axes=(None, None, None, 0)))  # one call per key
    return dict(trainer=trainer, init=init, update=update, run=run, start=start, state=state, info=info,
                controllers=controllers, evaluate=evaluate)


def _total_reward(setup, source, state, seed=5):
    traj = setup["evaluate"](source, state.params, state.norms, jax.random.key(seed))
    return float(traj["reward"].sum(0).mean()), traj


def test_env_steps_and_hand_over(setup):
    state, info, start = setup["state"], setup["info"], setup["start"]
    assert int(info["env_steps"]) == total_env_steps(CONFIG, PHASE) == 16 * (25 + 2 * 20 + 2 * 20)
    for name, value in info.items():
        assert np.isfinite(value) or "episode_return" in name, name  # no episode ends in so few steps is fine
    moved = lambda a, b: any(not np.array_equal(x, y) for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)))  # noqa: E731
    assert moved(start.params["model"], state.params["model"]) and moved(start.params["policy"], state.params["policy"])
    assert moved(start.params["value"], state.params["value"])
    assert not moved(start.params["encoder"], state.params["encoder"])
    assert not moved(start.opt_state, state.opt_state)  # PPO starts with fresh Adam moments
    # exploration is left to hp.init_log_std: cloning fits the mean; the std head gets no gradient from it
    from cdjax.agents.obs import networks
    from cdjax import normalize as nz

    head = lambda p: p["params"]["MLP_0"][f"Dense_{len(CONFIG.policy_hidden)}"]  # noqa: E731
    np.testing.assert_array_equal(head(state.params["policy"])["kernel"][:, 2:], head(start.params["policy"])["kernel"][:, 2:])
    np.testing.assert_array_equal(head(state.params["policy"])["bias"][2:], head(start.params["policy"])["bias"][2:])
    # the std head's bias is the one init_log_std set: std = exp(init_log_std) where its weights read zero features
    np.testing.assert_allclose(jax.nn.softplus(head(state.params["policy"])["bias"][2:]) + networks.MIN_POLICY_STD,
                               np.exp(HParams().init_log_std), rtol=1e-5)
    # with small head weights (orthogonal init) the std is exp(init_log_std) in every state
    small = networks.Policy(2, CONFIG.policy_hidden, CONFIG.activation, CONFIG.policy_std, "orthogonal")
    params = networks.set_initial_std(small, small.init(jax.random.key(3), jnp.zeros((1, 4))), HParams().init_log_std)
    obs = jax.random.uniform(jax.random.key(9), (64, 4), minval=-1.0, maxval=1.0)
    _, std = small.apply(params, nz.normalize(state.norms.obs, obs))
    np.testing.assert_allclose(std, np.exp(HParams().init_log_std), rtol=0.05)
    assert float(state.norms.obs.count) == 16 * (25 + 2 * 20)  # random + MPC data, not the DAgger rollouts
    np.testing.assert_array_equal(state.env_state.t, 0)
    assert int(state.update_step) == 0 and float(state.episodes.done_count) == 0


def test_phase_compiles_once(setup):
    run = setup["run"]
    other = setup["init"](jax.random.key(1), HP)
    _, info = run(other, HP.replace(lr_model=3e-3, alpha=0.0))  # new floats and seed, same program
    assert run._cache_size() == 1
    assert int(info["env_steps"]) == total_env_steps(CONFIG, PHASE)


def test_model_one_step_error_on_held_out_transitions(setup):
    """Fresh transitions (random actions and the distilled policy, new keys): the phase's model predicts
    the next state far better than the untrained model and than 'nothing changes'."""
    trainer, start, state = setup["trainer"], setup["start"], setup["state"]
    _, rand = _total_reward(setup, RANDOM, state, seed=11)
    _, pol = _total_reward(setup, POLICY, state, seed=12)
    data = {k: jnp.concatenate([rand[k], pol[k]]) for k in rand}
    valid = np.asarray(data["valid"])

    def error(params, norms):
        pred, reward = trainer.model_step(params["model"], norms, data["obs"], data["action"])
        return (float(np.mean(np.asarray(((pred - data["next_obs"]) ** 2).mean(-1))[valid])),
                float(np.mean(np.asarray((reward - data["reward"]) ** 2)[valid])))

    trained, trained_r = error(state.params, state.norms)
    untrained, untrained_r = error(start.params, start.norms)
    no_change = float(np.mean(np.asarray(((data["obs"] - data["next_obs"]) ** 2).mean(-1))[valid]))
    print(f"one-step MSE: trained {trained:.2e}, untrained {untrained:.2e}, no-change {no_change:.2e}; "
          f"reward MSE: trained {trained_r:.2e}, untrained {untrained_r:.2e}")
    assert trained < 0.02 * untrained and trained < 0.1 * no_change
    assert trained_r < 0.1 * untrained_r
    info = setup["info"]  # and on each round's fresh MPC data, before training on it
    assert info["model/heldout_mse_last"] < info["model/heldout_mse_first"]


def test_mpc_on_learned_model_beats_random_actions(setup):
    state, info = setup["state"], setup["info"]
    random_return, _ = _total_reward(setup, RANDOM, state)
    mpc_return, _ = _total_reward(setup, MPC, state)
    print(f"{EVAL_STEPS}-step return: MPC {mpc_return:.2f}, random {random_return:.2f}")
    assert mpc_return > random_return + 5.0
    assert info["mpc/reward_mean_last"] > info["random/reward_mean"]  # the same inside the phase


def test_distillation_matches_controller_on_visited_states(setup):
    """On the states the distilled policy visits, its action is close to the controller's: to the mean of 64
    MPC calls (random shooting is noisy: each call draws new candidates; the mean's own noise is an eighth of
    one call's: with 16 calls, a quarter, it decided the first comparison on some hosts), much closer than the
    untrained policy is, and closer than a single MPC call is. The first steps from reset are where the controller's
    actions are far from zero; near the goal an untrained policy (action ~ 0) is already almost right."""
    trainer, start, state, info = (setup[k] for k in ("trainer", "start", "state", "info"))
    _, traj = _total_reward(setup, POLICY, state)
    figures = {}
    for name, steps in (("first 10 steps", slice(0, 10)), ("all steps", slice(None))):
        obs = traj["obs"][steps].reshape(-1, traj["obs"].shape[-1])
        labels = setup["controllers"](state.params["model"], state.norms, obs, jax.random.split(jax.random.key(21), 64))
        target = labels.mean(0)
        after = float(jnp.abs(trainer.act(state.params, state.norms, obs, None) - target).mean())
        before = float(jnp.abs(trainer.act(start.params, start.norms, obs, None) - target).mean())
        one_call = float(jnp.abs(labels - target).mean())
        figures[name] = (after, before, one_call)
        print(f"{name}: |policy - MPC mean| after {after:.3f}, before {before:.3f}; |one MPC call - MPC mean| {one_call:.3f}")
    print(f"in the phase (single labels): after {float(info['distill/abs_error']):.3f}, "
          f"before {float(info['distill/abs_error_before']):.3f}; DAgger rounds' new states: "
          f"{float(info['dagger/abs_error_new_first']):.3f} -> {float(info['dagger/abs_error_new_last']):.3f}")
    after, before, one_call = figures["first 10 steps"]
    assert after < 0.4 * before and after < 0.6 * one_call
    after, before, one_call = figures["all steps"]
    assert after < 0.6 * before and after < 0.75 * one_call
    assert info["distill/abs_error"] < 0.8 * info["distill/abs_error_before"]


def test_ppo_continues_from_the_phase(setup):
    """update compiles for the returned state without recompiling (same types as init's), losses are finite
    for Mb-Mf (alpha = 0) and CD (alpha > 0), and the policy starts far better than a fresh one."""
    update, start, state = setup["update"], setup["start"], setup["state"]
    update(start, HP)
    size = update._cache_size()
    for alpha in (0.0, 1.0):
        new, metrics = update(state, HP.replace(alpha=alpha))
        for name, value in metrics.items():
            if name.startswith("loss/"):
                assert np.isfinite(value), (alpha, name)
        assert all(bool(jnp.isfinite(x).all()) for x in jax.tree.leaves(new.params))
    assert update._cache_size() == size
    fresh_det, _ = _total_reward(setup, POLICY_DET, start)
    fresh, _ = _total_reward(setup, POLICY, start)
    after, _ = _total_reward(setup, POLICY, state)
    after_det, _ = _total_reward(setup, POLICY_DET, state)
    print(f"{EVAL_STEPS}-step return: policy after phase {after:.2f} (deterministic {after_det:.2f}), "
          f"fresh {fresh:.2f} (deterministic {fresh_det:.2f})")
    assert after > fresh + 5.0 and after_det > fresh_det + 5.0


def test_ring_buffer_and_fit_use_only_filled_slots():
    buf = RingBuffer.create(dict(x=jnp.zeros(()), valid=jnp.zeros((), bool)), 5)
    buf = buf.add(dict(x=jnp.arange(1.0, 4.0), valid=jnp.ones(3, bool)))
    assert int(buf.filled) == 3
    buf = buf.add(dict(x=jnp.arange(4.0, 8.0), valid=jnp.ones(4, bool)))  # 6 and 7 overwrite 1 and 2
    np.testing.assert_array_equal(buf.data["x"], [6.0, 7.0, 3.0, 4.0, 5.0])
    assert int(buf.count) == 7 and int(buf.filled) == 5
    # Fit a scalar to the mean of the filled part: the empty slots (zeros) must not pull it down.
    import optax

    part = RingBuffer.create(dict(x=jnp.zeros(()), valid=jnp.zeros((), bool)), 8).add(
        dict(x=jnp.full((3,), 4.0), valid=jnp.ones(3, bool)))
    loss = lambda p, b: (jnp.mean((p - b["x"]) ** 2), {"seen": jnp.mean(b["x"])})  # noqa: E731
    tx = optax.sgd(0.1)
    p, _, metrics = jax.jit(lambda p, buf, key: fit(loss, p, tx.init(p), tx, buf, 50, 2, key))(
        jnp.zeros(()), part, jax.random.key(0))
    np.testing.assert_allclose(p, 4.0, rtol=1e-4)
    np.testing.assert_allclose(metrics["seen"], 4.0)


@pytest.mark.parametrize("changes, words", [
    (dict(buffer_size=10), "cannot hold one stage's"),
    (dict(random_steps=0), "random_steps must be a positive integer"),
    (dict(model_objective="huber"), "Unknown MbMfPhase.model_objective"),
])
def test_invalid_phases_fail_before_compiling(changes, words):
    from cdjax.agents.obs.mbmf import validate_phase

    with pytest.raises(ConfigError, match=words):
        validate_phase(POINT, MbMfPhase(num_envs=4, **changes))
    with pytest.raises(ConfigError, match="needs a dynamics model"):
        validate_phase(POINT.replace(arm="model-free"), MbMfPhase())
