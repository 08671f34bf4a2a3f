"""The Atari setting's pieces on the CPU: A2C's returns and losses against hand-worked numbers, the MinAtar
wrapper's ends and NaN guard, the arms as switches of one loss and the two consistency paths. Learning, vmap over
seeds, compile-once and resume run through the command line in test_atari_cli.py."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from cdjax.agents.atari import AtariConfig, AtariHParams, MinAtarEnv, make_trainer
from cdjax.agents.atari.learner import Batch
from cdjax.agents.atari.losses import a2c_loss, latent_model_loss, n_step_returns

# The cpu-minatar preset's sizes: MinAtar Breakout, 16 envs x 8 steps per update.
CONFIG = AtariConfig(env="breakout", arm="a2c", num_envs=16, rollout_len=8, horizon=4, conv_channels=8, latent=64,
                     model_hidden=64, encoder_dim=16, episode_length=500)
HP = AtariHParams(lr=3e-3)


def test_n_step_returns_by_hand():
    """gamma 0.5; column 0 runs through, column 1 terminates at t=1 and times out at t=2, column 2 has an
    invalid transition at t=2."""
    reward = jnp.array([[1.0, 1.0, 1.0], [2.0, 2.0, 2.0], [3.0, 3.0, 0.0], [4.0, 4.0, 4.0]])
    next_value = jnp.array([[10.0, 10.0, 10.0], [20.0, 20.0, 20.0], [30.0, 30.0, 0.0], [40.0, 40.0, 40.0]])
    terminated = jnp.zeros((4, 3), bool).at[1, 1].set(True)
    valid = jnp.ones((4, 3), bool).at[2, 2].set(False)
    ended = terminated | jnp.zeros((4, 3), bool).at[2, 1].set(True) | ~valid
    got = n_step_returns(reward, next_value, terminated, ended, valid, 0.5)
    expected = np.array([
        # 0: R3 = 4 + .5*40, R2 = 3 + .5*R3, R1 = 2 + .5*R2, R0 = 1 + .5*R1 (bootstrapped at the rollout's end)
        [1 + .5 * (2 + .5 * (3 + .5 * (4 + .5 * 40))), 2 + .5 * (3 + .5 * (4 + .5 * 40)), 3 + .5 * (4 + .5 * 40),
         4 + .5 * 40],
        # 1: R1 = 2 (terminated: no bootstrap), R0 = 1 + .5*2; R2 = 3 + .5*30 (time-out: V of the cut state)
        [1 + .5 * 2, 2, 3 + .5 * 30, 4 + .5 * 40],
        # 2: R2 = 0 (invalid); R1 bootstraps from V(s'_1) = 20 instead of reading R2
        [1 + .5 * (2 + .5 * 20), 2 + .5 * 20, 0, 4 + .5 * 40],
    ]).T
    np.testing.assert_allclose(got, expected, rtol=1e-6)


def test_a2c_and_model_losses_by_hand():
    """Two counted transitions and one masked one, two actions; gradients reach V only through the value loss."""
    hp = AtariHParams(value_coef=0.5, ent_coef=0.01)
    logits = jnp.array([[[0.0, 0.0], [np.log(3.0), 0.0], [5.0, -5.0]]])  # probs (.5, .5), (.75, .25)
    values, returns = jnp.array([[1.0, 2.0, 7.0]]), jnp.array([[3.0, 1.0, -9.0]])
    actions, mask = jnp.array([[0, 0, 1]]), jnp.array([[True, True, False]])
    (loss, metrics), grad_v = jax.value_and_grad(lambda v: a2c_loss(logits, v, actions, returns, mask, hp),
                                                 has_aux=True)(values)
    policy = -(2.0 * np.log(0.5) + -1.0 * np.log(0.75)) / 2  # advantages 3-1 = 2 and 1-2 = -1
    value = ((3 - 1) ** 2 + (1 - 2) ** 2) / 2
    ent = (np.log(2) - (0.75 * np.log(0.75) + 0.25 * np.log(0.25))) / 2
    np.testing.assert_allclose(metrics["loss/policy"], policy, rtol=1e-6)
    np.testing.assert_allclose(metrics["loss/value"], value, rtol=1e-6)
    np.testing.assert_allclose(metrics["policy/entropy"], ent, rtol=1e-6)
    np.testing.assert_allclose(loss, policy + 0.5 * value - 0.01 * ent, rtol=1e-6)
    np.testing.assert_allclose(grad_v, [[0.5 * (1 - 3), 0.5 * (2 - 1), 0.0]], rtol=1e-6)  # value_coef * (V - R)

    pred_z, target_z = jnp.array([[1.0, 2.0], [9.0, 9.0]]), jnp.array([[0.0, 0.0], [0.0, 0.0]])
    pred_r, reward, keep = jnp.array([1.0, 5.0]), jnp.array([3.0, 0.0]), jnp.array([True, False])
    (model, parts), grad_target = jax.value_and_grad(
        lambda t: latent_model_loss(pred_z, pred_r, t, reward, keep), has_aux=True)(target_z)
    np.testing.assert_allclose(parts["model/latent_mse"], (1 + 4) / 2, rtol=1e-6)
    np.testing.assert_allclose(parts["model/reward_mse"], (1 - 3) ** 2, rtol=1e-6)
    np.testing.assert_allclose(model, 2.5 + 4.0, rtol=1e-6)
    assert not np.asarray(grad_target).any()  # the target is a stop-gradient


class NaNOnAction2:
    """A MinAtar game whose reward is NaN whenever action 2 is executed (to exercise the guard)."""

    def __init__(self, game):
        self.game = game

    def __getattr__(self, name):
        return getattr(self.game, name)

    def step_env(self, key, state, action, params):
        obs, state, reward, done, info = self.game.step_env(key, state, action, params)
        return obs, state, jnp.where(action == 2, jnp.nan, reward), done, info


def test_minatar_ends_are_kept_apart_and_a_nan_is_contained():
    env = MinAtarEnv("breakout", 6, episode_length=8, sticky_prob=0.0)
    env.env = NaNOnAction2(env.env)  # random actions 0 and 1 first, then action 2 to exercise the guard
    step = jax.jit(env.step)
    state = env.reset(jax.random.key(1))
    fresh = env.reset(jax.random.key(2)).obs
    ends = {"terminated": 0, "truncated": 0}
    for t in range(40):
        action = jax.random.randint(jax.random.key(t), (6,), 0, 2)
        before = np.asarray(state.t)
        state, out = step(state, action)
        term, trunc = np.asarray(out.terminated), np.asarray(out.truncated)
        np.testing.assert_array_equal(trunc, (before + 1 == 8) & ~term)  # time-outs at the limit, games end earlier
        ended = term | trunc
        np.testing.assert_array_equal(np.asarray(state.t), np.where(ended, 0, before + 1))
        np.testing.assert_array_equal(np.asarray(state.last_action), np.where(ended, 0, action))  # no sticky
        # after an end the policy sees a first frame (bricks full, ball in row 3), next_obs the last one
        np.testing.assert_array_equal(np.asarray(state.obs)[ended][..., 3], np.asarray(fresh)[: ended.sum()][..., 3])
        assert (np.asarray(state.obs)[ended][:, 3, :, 1].sum(-1) == 1).all()
        ends["terminated"] += term.sum()
        ends["truncated"] += trunc.sum()
    assert ends["terminated"] > 0 and ends["truncated"] > 0

    state, out = step(env.reset(jax.random.key(0)), jnp.array([0, 2, 1, 0, 2, 1]))
    np.testing.assert_array_equal(out.valid, [True, False, True, True, False, True])
    assert np.isfinite(np.asarray(out.reward)).all() and not np.asarray(out.next_obs)[[1, 4]].any()
    np.testing.assert_array_equal(state.t, [1, 0, 1, 1, 0, 1])  # the invalid ones were reset
    assert not np.asarray(out.terminated | out.truncated)[[1, 4]].any()


def test_the_arms_are_switches_and_each_consistency_path_reaches_only_its_own_parameters():
    """On one rollout: the model's own loss never reaches the agent (a2c-model's agent gradient is a2c's); with
    cc_policy = 0 the consistency term adds nothing to the agent's gradient, with cc_policy > 0 it does (through
    the straight-through actions); with cc_model = 0 it adds nothing to the model's."""
    configs = {arm: CONFIG.replace(arm=arm) for arm in ("a2c-model", "a2c-cd")}
    learners = {arm: make_trainer(c).inner for arm, c in configs.items()}
    params = jax.jit(learners["a2c-cd"].init_params)(jax.random.key(3))
    # a batch of random frames, actions and ends (what the gradients reach does not depend on the data)
    key_obs, key_next, key_act, key_reward, key_end = jax.random.split(jax.random.key(4), 5)
    T, B, shape = CONFIG.rollout_len, CONFIG.num_envs, (10, 10, 4)
    ended = jax.random.uniform(key_end, (T, B)) < 0.1
    batch = Batch(obs=jax.random.bernoulli(key_obs, 0.2, (T, B) + shape).astype(jnp.float32),
                  action=jax.random.randint(key_act, (T, B), 0, 3),
                  reward=jax.random.bernoulli(key_reward, 0.2, (T, B)).astype(jnp.float32),
                  next_obs=jax.random.bernoulli(key_next, 0.2, (T, B) + shape).astype(jnp.float32),
                  terminated=ended, ended=ended, valid=jnp.ones((T, B), bool))
    offsets = jnp.arange(CONFIG.rollout_len - CONFIG.horizon + 1)

    def grads(arm, hp):
        mine = {k: v for k, v in params.items() if k in jax.eval_shape(learners[arm].init_params, jax.random.key(0))}
        return jax.jit(jax.grad(learners[arm].loss, has_aux=True))(mine, batch, offsets, hp)[0]

    base = grads("a2c-cd", HP.replace(alpha=0.0))  # the a2c-model baseline inside the a2c-cd program
    no_policy = grads("a2c-cd", HP.replace(cc_policy=0.0, cc_model=1.0))
    no_model = grads("a2c-cd", HP.replace(cc_policy=1.0, cc_model=0.0))
    for a, b in zip(jax.tree.leaves(grads("a2c-model", HP)), jax.tree.leaves({"agent": base["agent"],
                                                                             "model": base["model"]})):
        np.testing.assert_allclose(a, b, rtol=2e-5, atol=1e-7)  # another program: rounding only
    for a, b in zip(jax.tree.leaves(no_policy["agent"]), jax.tree.leaves(base["agent"])):
        np.testing.assert_array_equal(a, b)
    for a, b in zip(jax.tree.leaves(no_model["model"]), jax.tree.leaves(base["model"])):
        np.testing.assert_array_equal(a, b)
    for path, group in ((no_model, "agent"), (no_policy, "model")):
        moved = [np.abs(np.asarray(a) - np.asarray(b)).max() for a, b in
                 zip(jax.tree.leaves(path[group]), jax.tree.leaves(base[group]))]
        assert max(moved) > 1e-6, group  # the other path is there
