"""Staggered resets (Config.stagger_resets, BatchedEnv(stagger=True)): each env starts at its own random point of
the time limit, its episodes end spread out, and the shortened first episode never reaches the logged returns."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cdjax import ConfigError
from cdjax.envs import BatchedEnv, EpisodeStats
from cdjax.envs.point import PointMass

from _shared import POINT

LENGTH, STEPS, B = 20, 70, 32  # time limit, steps played, envs


def _play(env: BatchedEnv, key) -> tuple:
    """STEPS steps of zero actions from env.reset(key): (t at reset [B], truncated [T, B], stats at the end).

    With zero actions the point mass never terminates and, with cached resets, every full episode of an env
    replays the same trajectory from the same start: its return is a known number per env.
    """
    state = env.reset(key)
    stats = EpisodeStats.create(env.num_envs, skip=state.t > 0)

    def step(carry, _):
        state, stats = carry
        state, out = env.step(state, jnp.zeros((env.num_envs, env.action_size)))
        stats = stats.record(out.reward, out.terminated | out.truncated, out.terminated | out.truncated, 1.0)
        return (state, stats), out.truncated

    (_, stats), truncated = jax.lax.scan(step, (state, stats), None, length=STEPS)
    return state.t, truncated, stats


@pytest.fixture(scope="module")
def played():
    key = jax.random.key(3)
    staggered = jax.jit(lambda k: _play(BatchedEnv(PointMass(), B, LENGTH, stagger=True), k))(key)
    aligned = jax.jit(lambda k: _play(BatchedEnv(PointMass(), B, LENGTH), k))(key)
    # the return of one whole episode of each env: its first episode when unstaggered (same start states)
    whole = jax.jit(lambda k: _whole_returns(BatchedEnv(PointMass(), B, LENGTH), k))(key)
    return staggered, aligned, np.asarray(whole)


def _whole_returns(env, key):
    state = env.reset(key)

    def step(state, _):
        state, out = env.step(state, jnp.zeros((env.num_envs, env.action_size)))
        return state, out.reward

    return jax.lax.scan(step, state, None, length=LENGTH)[1].sum(0)


def test_staggered_envs_start_spread_over_the_time_limit_and_end_spread_out(played):
    (t0, truncated, _), (t0_aligned, truncated_aligned, _), _ = played
    t0, truncated = np.asarray(t0), np.asarray(truncated)
    assert np.all(np.asarray(t0_aligned) == 0)
    assert t0.min() >= 0 and t0.max() < LENGTH and len(np.unique(t0)) > B // 3  # own points of the time limit
    # env i times out first after LENGTH - t0[i] steps, then every LENGTH steps
    for i in range(B):
        ends = np.flatnonzero(truncated[:, i]) + 1
        expected = np.arange(LENGTH - t0[i], STEPS + 1, LENGTH)
        np.testing.assert_array_equal(ends, expected)
    assert truncated.sum(0).min() >= STEPS // LENGTH  # every env finishes several episodes (3 here)
    # unstaggered, all B envs end on the same steps; staggered, the ends are spread over many steps
    assert len(np.flatnonzero(np.asarray(truncated_aligned).any(1))) == STEPS // LENGTH
    assert len(np.flatnonzero(truncated.any(1))) > 3 * (STEPS // LENGTH)


def test_the_shortened_first_episode_is_not_counted(played):
    (t0, _, stats), (_, _, stats_aligned), whole = played
    t0 = np.asarray(t0)
    # per env: the first episode is counted only when it started at t = 0; then the whole ones that ended
    first_end = LENGTH - t0
    whole_after_first = (STEPS - first_end) // LENGTH
    counted = whole_after_first + (t0 == 0)
    assert float(stats.done_count) == counted.sum()
    np.testing.assert_allclose(float(stats.done_ret), (counted * whole).sum(), rtol=1e-5)
    # so the mean logged return is that of whole episodes, as without staggering (here: the same numbers)
    mean = float(stats.done_ret / stats.done_count)
    mean_aligned = float(stats_aligned.done_ret / stats_aligned.done_count)
    assert mean == pytest.approx((counted * whole).sum() / counted.sum(), rel=1e-5)
    assert mean_aligned == pytest.approx(whole.mean(), rel=1e-5)
    assert not np.asarray(stats.skip).any()  # every env's first episode has ended: nothing is skipped any more


def test_action_repeat_staggers_in_whole_agent_steps():
    env = BatchedEnv(PointMass(), 64, 9, action_repeat=2, stagger=True)  # 5 agent steps per episode
    t0 = np.asarray(jax.jit(env.reset)(jax.random.key(0)).t)
    assert set(np.unique(t0)) <= {0, 2, 4, 6, 8} and len(np.unique(t0)) == 5


def test_the_agent_marks_staggered_first_episodes_and_validates_the_option():
    from cdjax import make_agent

    agent = make_agent(POINT.replace(stagger_resets=True))
    assert agent.env.stagger
    state = jax.jit(agent.init)(jax.random.key(0), __import__("cdjax").HParams())
    np.testing.assert_array_equal(state.episodes.skip, state.env_state.t > 0)
    assert np.asarray(state.env_state.t).max() > 0
    assert not make_agent(POINT).env.stagger  # off by default
    with pytest.raises(ConfigError, match="stagger_resets must be true or false"):
        POINT.replace(stagger_resets=1)
