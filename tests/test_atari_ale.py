"""The ALE tier (optional extra `atari`): a real game stepped inside a jitted lax.scan through ale-py's XLA
interface gives the observations, rewards and ends of ale-py's own Python-side stepping for the same seeds and
actions; life losses end learning episodes only; more than one run per process is refused in one sentence."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

pytest.importorskip("ale_py", reason="ale-py is the optional extra `atari`: pip install -e \".[atari]\"")

from ale_py.vector_env import AtariVectorEnv  # noqa: E402

from cdjax.agents.atari import AtariConfig  # noqa: E402
from cdjax.agents.atari.ale import ONE_RUN, AleEnv, vector_env  # noqa: E402
from cdjax.protocol import ConfigError  # noqa: E402

CONFIG = AtariConfig(env="ale-breakout", num_envs=3, sticky_prob=0.25, episode_length=27000, latent=512)
STEPS = 300


def test_a_jitted_scan_steps_the_games_ale_py_steps():
    env = AleEnv(CONFIG, 3, episodic_life=True)
    actions = jnp.asarray(np.random.RandomState(0).randint(0, env.num_actions, (STEPS, 3)), jnp.int32)

    @jax.jit
    def play(key, actions):
        state = env.reset(key)

        def step(state, action):
            state, out = env.step(state, action)
            return state, (out.next_obs, out.reward, out.terminated, out.game_over, out.valid, state.lives)

        return state.obs, jax.lax.scan(step, state, actions)[1]

    key = jax.random.key(5)
    first, (obs, reward, terminated, game_over, valid, lives) = play(key, actions)
    seeds = np.asarray(jax.random.randint(jax.random.split(key)[0], (3,), 0, 2**31 - 1, jnp.int32))

    python = vector_env(AtariVectorEnv, CONFIG, 3)
    py_obs, _ = python.reset(seed=seeds)
    np.testing.assert_array_equal(np.moveaxis(py_obs, 1, -1), first)
    life_losses = 0
    for t in range(STEPS):
        py_obs, py_reward, py_term, py_trunc, info = python.step(np.asarray(actions[t]))
        np.testing.assert_array_equal(np.moveaxis(py_obs, 1, -1), obs[t], err_msg=f"step {t}")
        np.testing.assert_array_equal(np.where(valid[t], py_reward, 0), reward[t])
        np.testing.assert_array_equal(py_term & valid[t], game_over[t] & ~py_trunc)
        np.testing.assert_array_equal(info["lives"], lives[t])
        life_losses += int((terminated[t] & ~game_over[t]).sum())
    assert life_losses > 0 and np.asarray(obs).any()  # lives were lost without the games ending
    assert np.asarray(game_over).any() and not np.asarray(valid).all()  # games ended; ale-py reset them a step later
    assert np.asarray(reward).sum() > 0  # random play scores in Breakout


def test_more_than_one_run_per_process_is_refused():
    env = AleEnv(CONFIG, 2)
    with pytest.raises(ConfigError, match="one seed per process"):
        jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.key(0), 2))
    state = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.key(0), 1))  # one run: as unbatched
    assert state.obs.shape == (1, 2, 84, 84, 4) and ONE_RUN.endswith(".")
