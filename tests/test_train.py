"""The jitted update as a whole: seeds under vmap, compile once, NaN guard, arms, learning on MJX."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cdjax import Config, ConfigError, HParams, make_agent, make_train, stack_hparams

from _shared import PENDULUM, PENDULUM_HP, POINT, compiled


def _programs(config):
    """compiled(config), with PENDULUM's update at OPTIMISED's level: test_learning_on_mjx_pendulum runs it 100 times,
    and the compile-once and NaN tests take that program too (one MJX compile for the three, not two)."""
    return compiled(config, optimised=config is PENDULUM)


def _finite(tree):
    return all(bool(jnp.isfinite(x).all()) for x in jax.tree.leaves(tree)
               if hasattr(x, "dtype") and jnp.issubdtype(x.dtype, jnp.floating))


def test_vmap_over_seeds_and_an_alpha_grid_equals_each_run_alone():
    """Seeds and HParams floats vmap together (one program): each run equals the same run alone, the seeds
    really differ, and alpha changes the result.

    6 updates and HParams of Python floats, as test_runner's sweep runs them alone: the single-run program is the
    one test_runner.py::test_arms_and_seeds_vmapped_equal_each_run_alone compiles (the compilation cache serves it)."""
    train = make_train(POINT.replace(num_updates=6))
    keys = jnp.concatenate([jax.random.split(jax.random.key(3), 2)] * 2)  # seeds (0, 1) under alpha 0 and 0.5
    alone = [HParams(alpha=0.0)] * 2 + [HParams(alpha=0.5)] * 2
    hps = stack_hparams(alone)
    state_v, metrics_v = jax.jit(jax.vmap(train))(keys, hps)
    single = jax.jit(train)
    for i in range(4):
        state_i, metrics_i = single(keys[i], alone[i])
        for name in ("loss/total", "loss/consistency", "loss/model_nll", "env/reward_mean"):
            np.testing.assert_allclose(metrics_v[name][i], metrics_i[name], rtol=2e-5, atol=1e-6, err_msg=name)
        for a, b in zip(jax.tree.leaves(state_v.params), jax.tree.leaves(state_i.params)):
            np.testing.assert_allclose(a[i], b, rtol=2e-5, atol=1e-6)
    assert not np.allclose(metrics_v["loss/total"][2], metrics_v["loss/total"][3])  # the seeds differ
    assert not np.allclose(metrics_v["loss/total"][1], metrics_v["loss/total"][3])  # alpha matters


@pytest.mark.parametrize("config", [POINT, PENDULUM], ids=["point", "mjx-pendulum"])
def test_update_compiles_once(config):
    trainer, init, update = _programs(config)
    hp = PENDULUM_HP if config is PENDULUM else HParams()
    state = init(jax.random.key(0), hp)  # (other tests may have called this shared `update` already)
    state, _ = update(state, hp)
    state, _ = update(state, hp)
    state, _ = update(state, hp.replace(alpha=0.3))  # new float values, same program
    assert update._cache_size() == 1  # one program, whatever the order of the calls


def test_arms_switch_the_same_code():
    free, init, update = compiled(POINT.replace(arm="model-free"))
    state = init(jax.random.key(0), HParams())
    assert set(state.params) == {"policy", "value"}
    state2, metrics = update(state, HParams())
    assert "loss/model_nll" not in metrics and "loss/consistency" not in metrics
    mbmf, init, update = compiled(POINT.replace(arm="mbmf"))
    state = init(jax.random.key(0), HParams())
    assert set(state.params) == {"policy", "value", "model"}
    _, metrics = update(state, HParams())
    assert "loss/model_nll" in metrics and "loss/consistency" not in metrics
    l2, init, update = compiled(POINT.replace(encoder="l2"))
    state = init(jax.random.key(0), HParams())
    assert "encoder" not in state.params
    _, metrics = update(state, HParams())
    assert float(metrics["loss/consistency"]) > 0


def test_frozen_encoder_stays_put_trainable_one_moves():
    for encoder, should_move in (("frozen-gru", False), ("grounded-gru", True)):  # gru: tests/test_consistency.py
        _, init, update = compiled(POINT.replace(encoder=encoder))
        state = init(jax.random.key(0), HParams(alpha=1.0))
        new, _ = update(state, HParams(alpha=1.0))
        moved = any(not np.array_equal(a, b) for a, b in
                    zip(jax.tree.leaves(state.params["encoder"]), jax.tree.leaves(new.params["encoder"])))
        assert moved == should_move, encoder


def test_nan_in_one_env_is_reset_and_masked():
    trainer, init, update = _programs(PENDULUM)
    state = init(jax.random.key(1), PENDULUM_HP)
    state, _ = update(state, PENDULUM_HP)
    physics = state.env_state.core.pipeline_state
    poisoned = physics.replace(qd=physics.qd.at[3].set(jnp.nan), qvel=physics.qvel.at[3].set(jnp.nan))
    state = state.replace(env_state=state.env_state.replace(core=state.env_state.core.replace(pipeline_state=poisoned)))
    new, metrics = update(state, PENDULUM_HP)
    assert float(metrics["env/invalid_fraction"]) > 0  # the poisoned step was caught ...
    assert float(metrics["env/invalid_fraction"]) <= 1.0 / (PENDULUM.num_envs * PENDULUM.rollout_len) + 1e-9
    assert _finite(new.params) and _finite(new.opt_state) and _finite(new.norms)  # ... and reached nothing
    assert float(metrics["opt/skipped_updates"]) == 0.0  # no update had to be thrown away
    for name, value in metrics.items():
        if name.startswith("loss/"):
            assert np.isfinite(value), name
    assert _finite(new.env_state.core.pipeline_state.qd) and _finite(new.env_state.obs)  # env 3 was reset


def test_learning_on_mjx_pendulum():
    """Mean return rises far above the untrained policy's, and the open-loop model error falls."""
    # 100 updates: execution costs more than compiling here, so the update is compiled at XLA's default optimisation
    # level, not conftest's 0 (tests/conftest.py; _programs)
    _, init, update = _programs(PENDULUM)
    state = init(jax.random.key(0), PENDULUM_HP)
    returns, errors = [], []
    for _ in range(100):
        state, metrics = update(state, PENDULUM_HP)
        returns.append(float(metrics["episode/return"]))
        errors.append(float(metrics["model/openloop_mse_k"]))
    untrained = np.nanmean(returns[:3])
    trained = np.mean(returns[-10:])
    assert trained > 4 * untrained and trained > 100, (untrained, trained)
    first_errors = [e for e in errors[:15] if np.isfinite(e)]
    assert first_errors, "no open-loop error measured early on"
    assert np.nanmean(errors[-10:]) < 0.2 * np.mean(first_errors[:3]), (first_errors[:3], errors[-10:])


@pytest.mark.parametrize("changes, words", [
    (dict(env="antt"), "Unknown env 'antt'"),
    (dict(horizon=40, rollout_len=32), "longer than the minibatch sequences"),
    (dict(horizon=12, rollout_len=32, segment_len=8), "longer than the minibatch sequences"),
    (dict(rollout_len=32, segment_len=12), "does not divide rollout_len=32"),
    (dict(rollout_len=32, horizon=20, cc_windows=20), "is more than the 13 k-step windows"),
    (dict(activation="swishh"), "Unknown activation"),
    (dict(activation="Dense"), "Unknown activation 'Dense'"),  # a module class of flax.linen, not an activation
    (dict(activation="one_hot"), "Unknown activation 'one_hot'"),  # a function that wants more than an array
    (dict(encoder="vae"), "Unknown encoder"),
    (dict(num_envs=0), "num_envs must be a positive integer"),
    (dict(num_minibatches=-2), "num_minibatches must be a positive integer"),
    (dict(num_envs=30, num_minibatches=4), "does not divide the 30 sequences"),
    (dict(policy_hidden=()), "policy_hidden must be a non-empty tuple"),
    (dict(arm="dreamer"), "Unknown arm"),
])
def test_invalid_configs_fail_before_compiling(changes, words):
    with pytest.raises(ConfigError, match=words) as info:
        Config(**{**dict(env="ant"), **changes})
    message = str(info.value)
    assert message.endswith(".") and message.count(". ") == 0  # one sentence


def test_batched_env_keeps_truncation_apart_and_final_obs():
    from cdjax.envs import BatchedEnv
    from cdjax.envs.point import PointMass

    env = BatchedEnv(PointMass(start_range=0.5), num_envs=3, episode_length=4)
    state = env.reset(jax.random.key(0))
    step = jax.jit(env.step)
    push = jnp.array([[1.0, 0.0], [0.0, 0.0], [-1.0, 1.0]])
    for t in range(4):
        prev = state
        state, out = step(state, push)
        np.testing.assert_allclose(out.next_obs, PointMass.dynamics(prev.obs, push), rtol=1e-6)
    assert bool(out.truncated.all()) and not bool(out.terminated.any())
    np.testing.assert_array_equal(state.t, 0)
    np.testing.assert_allclose(state.obs, env.reset(jax.random.key(0)).obs)  # cached reset: own first start
    assert not np.allclose(out.next_obs, state.obs)  # the final observation survives the reset
    # leaving the box terminates, which is not a truncation
    far = state.replace(obs=state.obs.at[0, 0].set(1.99).at[0, 2].set(1.0),
                        core=state.core.replace(obs=state.core.obs.at[0, 0].set(1.99).at[0, 2].set(1.0)))
    _, out = step(far, push)
    assert bool(out.terminated[0]) and not bool(out.truncated[0])


def test_a_large_action_repeat_is_one_loop_with_the_unrolled_repeats_results(monkeypatch):
    """Past UNROLLED_REPEATS the repeats run as one loop: the program does not grow with them (1000 unrolled steps
    ran a 24 GB machine out of memory while compiling), and the step gives what the unrolled repeats give."""
    import cdjax.envs as envs
    from cdjax.envs import BatchedEnv
    from cdjax.envs.point import PointMass

    def run(repeat):
        env = BatchedEnv(PointMass(start_range=0.5), num_envs=3, episode_length=40, action_repeat=repeat)
        state = env.reset(jax.random.key(1))
        push = jnp.array([[0.3, -0.2], [0.0, 0.1], [-0.4, 0.4]])
        outs = []
        for _ in range(4):  # the last step ends the episodes at 40 physics steps
            state, out = jax.jit(env.step)(state, push)
            outs.append(out)
        size = len(jax.make_jaxpr(env.step)(state, push).eqns)
        return jax.tree.map(np.asarray, (state.obs, state.t, outs)), size

    looped, size_10 = run(10)
    _, size_20 = run(20)
    assert size_10 == size_20  # one loop, whatever the repeats
    monkeypatch.setattr(envs, "UNROLLED_REPEATS", 100)
    unrolled, size_unrolled = run(10)
    assert size_unrolled > size_10
    jax.tree.map(lambda a, b: np.testing.assert_allclose(a, b, rtol=1e-6), looped, unrolled)
    assert bool(looped[2][-1].truncated.all()) and looped[1].tolist() == [0, 0, 0]


@pytest.mark.parametrize("reset_mode", ["cached", "fresh"])
def test_rollout_values_are_values_of_obs_and_next_obs(reset_mode):
    """closed_loop values obs and next_obs after the scan (with cached resets it derives value(obs[t+1]) from
    value(next_obs[t]) and the restart obs): the result is the value network applied to each, across
    truncations, terminations and a non-finite step."""
    from cdjax.agents.obs import networks
    from cdjax import normalize as nz

    config = POINT.replace(arm="model-free", episode_length=5, reset_mode=reset_mode, gae_in_loss=False)
    trainer = make_agent(config)
    state = jax.jit(trainer.init)(jax.random.key(2), HParams())
    env_state = state.env_state
    core_obs = env_state.core.obs.at[0].set(jnp.nan).at[1, 0].set(1.99).at[1, 2].set(1.0)  # 0: NaN, 1: leaves the box
    state = state.replace(env_state=env_state.replace(core=env_state.core.replace(obs=core_obs),
                                                      obs=env_state.obs.at[1].set(core_obs[1])))
    _, _, traj, _ = jax.jit(trainer.collect)(state, HParams(), jax.random.key(5))
    assert bool(traj.terminated.any()) and bool(traj.truncated.any()) and not bool(traj.valid.all())
    value = lambda obs: networks.Value(config.value_hidden, config.activation).apply(  # noqa: E731
        state.params["value"], nz.normalize(state.norms.obs, obs))
    np.testing.assert_allclose(traj.value, value(traj.obs), rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(traj.next_value, value(traj.next_obs), rtol=1e-6, atol=1e-6)
    # GAE in the loss: only the time-outs' final observations are valued at acting time
    in_loss = make_agent(config.replace(gae_in_loss=True))
    assert in_loss.env.max_timeouts(config.rollout_len) == -(-config.rollout_len // 5) >= 2
    _, _, lean, batch = jax.jit(in_loss.collect)(state, HParams(), jax.random.key(5))
    assert lean.value is None and batch.advantages is None
    assert int(lean.truncated.sum(0).max()) >= 2  # some env timed out more than once
    np.testing.assert_array_equal(lean.truncated, traj.truncated)
    np.testing.assert_allclose(lean.next_value, np.where(traj.truncated, value(traj.next_obs), 0.0), rtol=1e-6,
                               atol=1e-6)


def test_the_arms_of_one_env_trace_its_physics_once(monkeypatch):
    """Agents of one env (the arms of a sweep) act in one env object through one jitted batched step
    (`envs.physics`): a second agent's rollout, here one with other options and under vmap over runs, reuses the
    first one's trace of the physics instead of tracing the env's step again (on an MJX task thousands of
    operations each time). Lowering only: nothing compiles."""
    from cdjax import envs
    from cdjax.envs.point import PointMass

    traced = []
    step = PointMass.step
    monkeypatch.setattr(PointMass, "step", lambda self, state, action: traced.append(1) or step(self, state, action))
    monkeypatch.setattr(envs, "_SHARED_ENVS", {})  # a fresh point env, made with the counting step
    monkeypatch.setattr(envs, "_PHYSICS", {})
    first, second = make_agent(POINT), make_agent(POINT.replace(horizon=3, num_epochs=1))
    assert first.env.env is second.env.env
    state = jax.eval_shape(first.env.reset, jax.random.key(0))
    action = jnp.zeros((POINT.num_envs, first.env.action_size))
    jax.jit(first.env.step).lower(state, action)
    assert len(traced) == 1
    jax.jit(jax.vmap(lambda s, a: second.env.step(s, a)[1].reward)).lower(
        jax.tree.map(lambda x: jnp.zeros((2,) + x.shape, x.dtype), state), jnp.stack([action] * 2))
    assert len(traced) == 1  # the second agent's env, under vmap over 2 runs: the same trace, batched
    jax.jit(lambda s, a: envs.BatchedEnv(PointMass(), POINT.num_envs, 10).step(s, a)).lower(state, action)
    assert len(traced) == 2  # another env object traces its own
