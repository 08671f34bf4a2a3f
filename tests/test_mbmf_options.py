"""The Mb-Mf phase's options closer to Nagabandi et al. (cdjax/agents/obs/mbmf/): elite-mean MPC actions, the task's
true reward for scoring candidates, an on-policy share of every model minibatch, deterministic DAgger rollouts,
and the label checks that say whether the distilled policy learnt the controller. Point mass; one compiled phase."""

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from cdjax import ConfigError, HParams
from cdjax.agents.obs import mpc
from cdjax.agents.obs.mbmf import MbMfPhase, make_mbmf_phase, make_mpc_controller, validate_phase
from cdjax.agents.obs.mbmf.phase import MbMfProgram
from cdjax.envs import rewards
from cdjax.replay import RingBuffer, fit

from _shared import POINT, compiled

CONFIG = POINT.replace(activation="tanh")  # as tests/test_mbmf.py: the programs of `compiled(CONFIG)` are shared
PHASE = MbMfPhase(num_envs=16, random_steps=25, aggregation_iters=2, mpc_steps_per_iter=20, model_epochs=60,
                  model_minibatch=32, mpc_horizon=5, mpc_candidates=128, distill_iters=2, distill_steps_per_iter=20,
                  distill_epochs=100, distill_minibatch=64, value_epochs=2, mpc_reward="true", mpc_elites=8,
                  onpolicy_fraction=0.5, dagger_deterministic=True, handover_steps=10)


def test_elite_mean_against_hand_worked_numbers():
    actions = jnp.array([[[0.1], [9.0]], [[0.5], [9.0]], [[-0.3], [9.0]], [[0.9], [9.0]]])  # [N=4, H=2, A=1]
    returns = jnp.array([1.0, 4.0, 3.0, jnp.nan])
    action, info = mpc.select_elite_mean(actions, returns, 2)
    np.testing.assert_allclose(action, [(0.5 - 0.3) / 2])  # the two best finite returns: candidates 1 and 2
    assert float(info["best_return"]) == 4.0
    best, _ = mpc.select_best(actions, returns)
    np.testing.assert_array_equal(mpc.select_elite_mean(actions, returns, 1)[0], best)
    # an elite without a finite return is left out of the mean; none finite: the zero action
    np.testing.assert_allclose(mpc.select_elite_mean(actions, returns, 4)[0], [(0.1 + 0.5 - 0.3) / 3], rtol=1e-6)
    np.testing.assert_array_equal(mpc.select_elite_mean(actions, jnp.full(4, jnp.nan), 3)[0], [0.0])
    with pytest.raises(ValueError, match="more than the 4 candidates"):
        mpc.select_elite_mean(actions, returns, 5)


def test_fit_draws_its_share_of_every_minibatch_from_the_new_part():
    """Slots [0, 10) old (x = 0), [10, 16) new (x = 1): with fraction 0.5 every minibatch of 4 is half new."""
    item = dict(x=jnp.zeros(()), valid=jnp.zeros((), bool))
    buf = RingBuffer.create(item, 16).add(dict(x=jnp.zeros(10), valid=jnp.ones(10, bool)))
    loss = lambda p, b: (jnp.mean((p - b["x"]) ** 2), {"seen": jnp.mean(b["x"]), "low": jnp.min(b["x"]),  # noqa: E731
                                                       "high": jnp.max(b["x"])})
    tx = optax.sgd(0.0)
    run = jax.jit(functools.partial(fit, loss, tx=tx, epochs=3, minibatch=4), static_argnames=("split", "fraction"))
    p = jnp.zeros(())
    # before there is new data, everything comes from the old part
    _, _, m = run(p, tx.init(p), buffer=buf, key=jax.random.key(0), split=10, fraction=0.5)
    assert float(m["high"]) == 0.0
    buf = buf.add(dict(x=jnp.ones(6), valid=jnp.ones(6, bool)))
    _, _, m = run(p, tx.init(p), buffer=buf, key=jax.random.key(0), split=10, fraction=0.5)
    assert float(m["seen"]) == 0.5  # every step's batch: 2 old, 2 new
    _, _, m = run(p, tx.init(p), buffer=buf, key=jax.random.key(0), split=10, fraction=0.0)
    assert float(m["seen"]) == pytest.approx(6 / 16)  # one shuffled pass over all 16 slots per epoch


def test_true_reward_of_the_point_mass_is_the_simulators():
    from cdjax.envs.point import PointMass

    env = PointMass()
    keys = jax.random.split(jax.random.key(0), 64)
    state = jax.vmap(env.reset)(keys)
    action = jax.random.uniform(jax.random.key(1), (64, 2), minval=-1.5, maxval=1.5)
    after = jax.vmap(env.step)(state, action)
    np.testing.assert_allclose(rewards.reward_fn("point")(state.obs, action, after.obs), after.reward, rtol=1e-6)
    assert rewards.reward_fn("humanoid") is None and "centre of mass" in rewards.why_not("humanoid")


@pytest.mark.parametrize("task", ["halfcheetah", "ant", "swimmer"])
def test_true_rewards_of_mjx_tasks_on_their_kept_yardstick_trajectories(task):
    """The observation-based reward against the simulator's on the real random-action transitions kept in
    experiments/paper_obs_space/yardstick/ (no MJX program here): a planner needs their ranking to agree."""
    from cdjax.agents.obs import yardstick
    from experiments.paper_obs_space.yardstick import path_of

    y = yardstick.load(path_of(task))
    before = np.asarray([t or y.steps for t in y.meta["terminated_at"]])  # up to the episode's end
    keep = np.arange(y.steps)[None] < before[:, None]
    ours = np.asarray(rewards.reward_fn(task)(y.obs[:, :-1], y.action, y.obs[:, 1:]))[keep]
    real = y.reward[keep]
    corr = np.corrcoef(ours, real)[0, 1]
    print(f"{task}: correlation {corr:.4f}, mean abs difference {np.abs(ours - real).mean():.4f}, "
          f"reward std {real.std():.4f}")
    assert corr > 0.95


def test_the_controller_scores_candidates_with_the_true_reward():
    trainer, init, _ = compiled(CONFIG)
    state = init(jax.random.key(0), HParams())
    obs = jax.random.uniform(jax.random.key(2), (3, 4), minval=-1.0, maxval=1.0)
    phase = MbMfPhase(mpc_horizon=3, mpc_candidates=32, mpc_reward="true", mpc_elites=4)
    got = make_mpc_controller(trainer, phase)(state.params["model"], state.norms, obs, jax.random.key(5))

    def step_fn(s, a):
        next_s, _ = trainer.model_step(state.params["model"], state.norms, s, a)
        return next_s, rewards.reward_fn("point")(s, a, next_s)

    want, _ = mpc.batched_random_shooting(jax.random.key(5), step_fn, obs, horizon=3, num_candidates=32,
                                          action_size=2, num_elites=4)
    np.testing.assert_allclose(got, want, rtol=1e-6)
    model_scored = make_mpc_controller(trainer, MbMfPhase(mpc_horizon=3, mpc_candidates=32, mpc_elites=4))(
        state.params["model"], state.norms, obs, jax.random.key(5))
    assert not np.allclose(model_scored, want)  # the untrained model's reward ranks them otherwise


@pytest.fixture(scope="module")
def phase_run():
    trainer, init, _ = compiled(CONFIG)
    start = init(jax.random.key(0), HParams(alpha=1.0))
    state, info = jax.jit(make_mbmf_phase(CONFIG, PHASE, trainer))(start, HParams(alpha=1.0))
    return trainer, start, state, {k: float(v) for k, v in info.items()}


def test_deterministic_dagger_acts_with_the_mean_action():
    trainer, init, _ = compiled(CONFIG)
    state = init(jax.random.key(0), HParams())
    obs = jnp.ones((16, 4)) * 0.3
    for det in (True, False):
        program = MbMfProgram(CONFIG, PHASE.__class__(**{**PHASE.__dict__, "dagger_deterministic": det}), trainer)
        a, b = (program.dagger_action(state.params["policy"], state.norms, obs, jax.random.key(k)) for k in (1, 2))
        mean = trainer.act(state.params, state.norms, obs, None)
        assert np.allclose(a, mean) == det and np.allclose(a, b) == det


def test_the_phase_with_every_option_hands_over_a_policy_that_beats_random_actions(phase_run):
    trainer, start, state, info = phase_run
    print({k: round(v, 4) for k, v in info.items()})
    # the distilled policy acting (deterministically) in the DAgger rounds earns more per step than random actions
    assert info["dagger/reward_mean_last"] > info["random/reward_mean"] + 0.1
    assert info["mpc/reward_mean_last"] > info["random/reward_mean"] + 0.1
    # and it learnt the controller: far closer to the mean MPC label than the zero action is to single labels,
    # and within reach of what a single label is from the others' mean
    assert info["distill/abs_error_mean"] < 0.5 * info["distill/abs_error_zero"]
    assert info["labels/mean_abs"] > 0.1 and info["labels/self_error"] < info["distill/abs_error_zero"]
    # PPO's start: the distilled policy earns more per step than the untrained one (the model-free arm's start),
    # sampling as PPO's first rollout does and with the mean action, from the same reset states
    assert info["handover/sampled_reward_mean"] > info["fresh/sampled_reward_mean"] + 0.05
    assert info["handover/mean_action_reward_mean"] > info["fresh/mean_action_reward_mean"] + 0.05
    assert int(info["env_steps"]) == 16 * (25 + 2 * 20 + 2 * 20 + 4 * 10)


def test_invalid_options_fail_in_one_sentence():
    with pytest.raises(ConfigError, match="humanoid has none"):
        validate_phase(CONFIG.replace(env="humanoid"), MbMfPhase(mpc_reward="true"))
    with pytest.raises(ConfigError, match="onpolicy_fraction must lie in"):
        validate_phase(CONFIG, MbMfPhase(onpolicy_fraction=1.0))
    with pytest.raises(ConfigError, match="needs buffer_size = 0"):
        validate_phase(CONFIG, MbMfPhase(num_envs=4, onpolicy_fraction=0.5, buffer_size=100_000))
    with pytest.raises(ConfigError, match="mpc_elites=9 is more than its 8 candidates"):
        validate_phase(CONFIG, MbMfPhase(mpc_candidates=8, mpc_elites=9))
    with pytest.raises(ConfigError, match="dagger_deterministic must be true or false"):
        validate_phase(CONFIG, MbMfPhase(dagger_deterministic="yes"))


def test_hand_policy_false_keeps_the_initial_policy_and_everything_else_the_phase_trains():
    """The ablation `hand_policy=False`: the same phase (same key, same env steps), PPO gets the initial policy
    back while the model, the normalisation and the value are the phase's, exactly as with the distilled hand-over."""
    tiny = MbMfPhase(num_envs=4, random_steps=6, aggregation_iters=1, mpc_steps_per_iter=4, model_epochs=2,
                     model_minibatch=8, mpc_horizon=2, mpc_candidates=8, distill_iters=1, distill_steps_per_iter=4,
                     distill_epochs=2, distill_minibatch=8, value_epochs=1)
    trainer, init, _ = compiled(CONFIG)
    start = init(jax.random.key(0), HParams())
    (handed, info_h), (kept, info_k) = (jax.jit(make_mbmf_phase(CONFIG, p, trainer))(start, HParams())
                                        for p in (tiny, dataclasses.replace(tiny, hand_policy=False)))
    same = lambda a, b: all(np.array_equal(x, y) for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)))  # noqa: E731
    assert same(kept.params["policy"], start.params["policy"]) and not same(handed.params["policy"], start.params["policy"])
    for name in ("model", "value", "encoder"):
        assert same(kept.params[name], handed.params[name]), name
    assert not same(kept.params["model"], start.params["model"]) and not same(kept.params["value"], start.params["value"])
    assert same(kept.norms, handed.norms) and int(info_k["env_steps"]) == int(info_h["env_steps"])
    with pytest.raises(ConfigError, match="hand_policy must be true or false"):
        validate_phase(CONFIG, MbMfPhase(hand_policy=1))
