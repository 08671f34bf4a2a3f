"""The common yardstick (cdjax/agents/obs/yardstick.py, experiments/paper_obs_space/yardstick.py): held-out real
trajectories collected once, every model scored on the same windows in the same units, logged every update."""

import json

import jax
import numpy as np
import pytest

from cdjax import ConfigError, HParams, make_agent
from cdjax.agents.obs import yardstick
from cdjax.envs.point import PointMass
from experiments.paper_obs_space import yardstick as collector

from _shared import POINT


@pytest.fixture(scope="module")
def point_file(tmp_path_factory):
    obs, action, length, reward, meta = collector.collect("point", trajectories=4, steps=30, seed=0)
    path = yardstick.save(tmp_path_factory.mktemp("ys") / "point.npz", obs, action, length, meta, reward=reward)
    return path, obs, action


def test_collected_once_kept_and_loaded(point_file):
    path, obs, action = point_file
    y = yardstick.load(path)
    assert y.obs.shape == (4, 31, 4) and y.action.shape == (4, 30, 2) and list(y.length) == [30] * 4
    np.testing.assert_array_equal(y.obs, obs)
    assert y.meta["env"] == "point" and "random" in y.meta["policy"]
    # real trajectories: each observation follows from the previous one and the action by the true dynamics
    np.testing.assert_allclose(PointMass.dynamics(y.obs[:, :-1], y.action), y.obs[:, 1:], atol=1e-6)
    assert y.reward.shape == (4, 30)  # the simulator's rewards, kept
    assert np.all(np.abs(y.action) <= 1) and y.action.std() > 0.4  # uniform random actions
    # the same seed gives the same file's data (collected once; a re-collection is reproducible on one machine)
    again = collector.collect("point", trajectories=4, steps=30, seed=0)[0]
    np.testing.assert_array_equal(again, obs)
    assert path.stat().st_size < 20_000


def test_windows_and_errors_against_hand_computed_numbers(point_file):
    path, obs, action = point_file
    w = yardstick.Windows.of(yardstick.load(path), k=4, long=10, stride=10)
    assert w.start.shape == (4 * 3, 4) and w.action.shape == (12, 10, 2)  # starts 0, 10, 20 of 30 steps
    np.testing.assert_array_equal(w.start[1], obs[0, 10])
    np.testing.assert_array_equal(w.target_k[1], obs[0, 14])
    np.testing.assert_array_equal(w.target_long[1], obs[0, 20])
    exact = jax.jit(lambda: yardstick.errors(PointMass.dynamics, w))()
    assert float(exact["model/yardstick_mse_k"]) < 1e-10 and float(exact["model/yardstick_mse_50"]) < 1e-10
    frozen = yardstick.errors(lambda s, a: s, w)  # a model that predicts no change
    scale = w.scale
    hand_k = np.mean(((w.start - w.target_k) / scale) ** 2)
    hand_long = np.mean(((w.start - w.target_long) / scale) ** 2)
    np.testing.assert_allclose(float(frozen["model/yardstick_mse_k"]), hand_k, rtol=1e-5)
    np.testing.assert_allclose(float(frozen["model/yardstick_mse_50"]), hand_long, rtol=1e-5)
    assert hand_k > 0 and hand_long > 0
    # a dimension that does not move on the yardstick is left out (its scale sits at the floor)
    still = yardstick.Windows(w.start, w.action, w.target_k + np.array([0, 0, 0, 5.0], np.float32), w.target_long,
                              np.array([*w.scale[:3], yardstick.SCALE_FLOOR], np.float32), w.k, w.long)
    exact_still = yardstick.errors(PointMass.dynamics, still)
    assert float(exact_still["model/yardstick_mse_k"]) < 1e-10


def test_every_update_logs_the_yardstick_and_a_wrong_file_fails_in_one_sentence(point_file, tmp_path):
    path = str(point_file[0])
    config = POINT.replace(yardstick=path, num_updates=2)
    agent = make_agent(config)
    state = jax.jit(agent.init)(jax.random.key(0), HParams())
    # the update logs both numbers (traced, not compiled: the numbers come from the same function below)
    _, metrics = jax.eval_shape(agent.update, state, HParams())
    assert metrics["model/yardstick_mse_k"].shape == () and metrics["model/yardstick_mse_50"].shape == ()
    numbers = jax.jit(lambda p, n: yardstick.errors(lambda s, a: agent.model_step(p, n, s, a)[0], agent.yardstick))(
        state.params["model"], state.norms)
    assert agent.yardstick.k == 4 and agent.yardstick.long == 10
    assert np.isfinite(numbers["model/yardstick_mse_k"]) and np.isfinite(numbers["model/yardstick_mse_50"])
    assert make_agent(config.replace(arm="model-free")).yardstick is None  # no model, nothing to score
    missing = POINT.replace(yardstick=str(tmp_path / "missing.npz"))  # a run.json read elsewhere still loads
    with pytest.raises(ConfigError, match="does not exist"):
        make_agent(missing)
    with pytest.raises(ConfigError, match="yardstick must be a string, got 3"):
        POINT.replace(yardstick=3)
    y = yardstick.load(path)
    other = yardstick.save(tmp_path / "ant.npz", y.obs, y.action, y.length, {**y.meta, "env": "ant"})
    with pytest.raises(ConfigError, match="was collected on 'ant'"):
        make_agent(POINT.replace(yardstick=str(other)))
    short = yardstick.save(tmp_path / "short.npz", y.obs[:, :6], y.action[:, :5], np.minimum(y.length, 5), y.meta)
    with pytest.raises(ConfigError, match="fewer than the 10"):
        make_agent(POINT.replace(yardstick=str(short)))
    assert json.loads(str(np.load(path)["meta"]))["trajectories"] == 4
