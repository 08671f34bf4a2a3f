"""The off-policy setting's pieces on the point mass: the replay sampler, the n-step target, compile-once, vmap over
seeds, the consistency arms at alpha 0, the self-predictive target's gradient, and a short learning run."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cdjax.agents.offpolicy import Config, HParams, Learner, make_train
from cdjax.agents.offpolicy.losses import REACHES, loss_terms, n_step_target
from cdjax.protocol import ConfigError
from cdjax.replay import RingBuffer, sample_sequences

TINY = Config(env="point", num_envs=4, steps_per_update=2, buffer_steps=32, batch_size=8, learning_starts=16,
              num_updates=6, actor_hidden=(16,), critic_hidden=(16,), encoder_hidden=(16,), model_hidden=(16,),
              latent_dim=8, cc_dim=8, episode_length=20)


def test_the_ring_buffer_wraps_and_samples_whole_sequences_of_one_stream():
    # 5 slots of 2 streams; item t of stream e holds 10 t + e. After 7 items, slots hold items 5, 6, 2, 3, 4.
    buffer = RingBuffer.create(jnp.zeros((2,), jnp.int32), 5)
    for t in range(7):
        buffer = buffer.add((10 * t + jnp.arange(2, dtype=jnp.int32))[None])
    np.testing.assert_array_equal(np.asarray(buffer.data)[:, 0], [50, 60, 20, 30, 40])
    assert int(buffer.filled) == 5 and int(buffer.count) == 7
    seqs = np.asarray(sample_sequences(buffer, jax.random.key(0), 400, 3))  # [3, 400]
    assert seqs.shape == (3, 400)
    np.testing.assert_array_equal(np.diff(seqs, axis=0), 10)  # consecutive items of one stream, never across the
    starts = seqs[0] // 10  # write position (item 6 is followed by the oldest, item 2)
    assert set(starts.tolist()) == {2, 3, 4} and set((seqs[0] % 10).tolist()) == {0, 1}
    # before the buffer is full: only the items written (3 of them: one sequence of 3, from item 0)
    part = RingBuffer.create(jnp.zeros((2,), jnp.int32), 5)
    for t in range(3):
        part = part.add((10 * t + jnp.arange(2, dtype=jnp.int32))[None])
    seqs = np.asarray(sample_sequences(part, jax.random.key(1), 50, 3))
    np.testing.assert_array_equal(seqs[:, :] // 10, np.broadcast_to(np.arange(3)[:, None], (3, 50)))


def test_the_n_step_target_stops_at_episode_ends_and_bootstraps_time_outs():
    # 4 sequences of 3 steps, rewards 1, 2, 4; gamma 0.5, reward scale 2.
    f, t = False, True
    batch = {
        "reward": jnp.array([[1.0] * 4, [2.0] * 4, [4.0] * 4]),
        "ended": jnp.array([[f, t, f, f], [f, f, t, f], [f, f, f, f]]),
        "terminated": jnp.array([[f, t, f, f], [f, f, f, f], [f, f, f, f]]),  # seq 2: a time-out at step 1
        "valid": jnp.array([[t, t, t, t], [t, t, t, f], [t, t, t, t]]),
        "next_obs": jnp.arange(3 * 4, dtype=jnp.float32).reshape(3, 4, 1),
    }
    ret, boot, discount, usable = n_step_target(batch, 3, 0.5, 2.0)
    np.testing.assert_allclose(ret, 2 * np.array([1 + 1 + 1, 1, 1 + 1, 1 + 1 + 1]))  # 1 + 0.5*2 + 0.25*4 = 3
    np.testing.assert_allclose(boot[:, 0], [8, 1, 6, 11])  # next_obs at the last step inside the episode
    np.testing.assert_allclose(discount, [0.125, 0.0, 0.25, 0.125])  # a termination: 0; a time-out: gamma^2
    np.testing.assert_array_equal(usable, [t, t, t, f])  # seq 3: an invalid step inside its n steps


@pytest.fixture(scope="module")
def stepped():
    """The paper-cd arm's update (the largest: every loss term) jitted once and run 12 times from init, through the
    random-action phase into learning: (how often it was traced, the state, the last update's metrics). The suite's
    only run of the paper-cd update with its default grounded-GRU encoder (test_settings_face.py's uses l2)."""
    learner = Learner(TINY.replace(arm="paper-cd"))
    traced = []

    def update(state, hp):
        traced.append(1)
        return learner.update(state, hp)

    step = jax.jit(update)
    state = learner.init(jax.random.key(1), HParams())
    for _ in range(12):
        state, metrics = step(state, HParams().as_float32())
    return len(traced), state, metrics


def test_the_update_compiles_once(stepped):
    traced, state, metrics = stepped
    assert traced == 1
    assert np.isfinite(float(metrics["loss/critic"])) and int(state.buffer.count) == 24


@pytest.fixture(scope="module")
def runs():
    """The self-pred arm's train (10 updates) of two seeds under two alphas, vmapped and each alone: (config, keys,
    hps, vmapped (states, metrics), [(state, metrics) alone]). The diagnostics test compares its run with the first
    run alone (heldout_envs sizes only what diagnostics add: without them it is the plain program)."""
    config = TINY.replace(arm="self-pred", num_updates=10, heldout_envs=2)
    keys = jax.random.split(jax.random.key(3), 2)
    hps = [HParams(alpha=0.5), HParams(alpha=2.0)]
    stacked = jax.tree.map(lambda *v: jnp.asarray(v, jnp.float32), *hps)
    vmapped = jax.jit(jax.vmap(make_train(config)))(keys, stacked)
    train = jax.jit(make_train(config))
    return config, keys, hps, vmapped, [train(keys[i], hps[i]) for i in range(2)]


def test_vmap_over_seeds_equals_each_seed_alone(runs):
    _, _, _, (states, metrics), alone = runs
    for i, (state, single) in enumerate(alone):
        for name in single:
            np.testing.assert_allclose(metrics[name][i], single[name], rtol=2e-5, atol=1e-6, err_msg=name)
        for a, b in zip(jax.tree.leaves(states.params), jax.tree.leaves(state.params)):
            np.testing.assert_allclose(a[i], b, rtol=2e-5, atol=1e-6)
    assert not np.allclose(metrics["loss/critic"][0, -1], metrics["loss/critic"][1, -1])  # the runs differ


@pytest.fixture(scope="module")
def replayed(stepped):
    """A paper-cd state past learning_starts and a batch sampled from its buffer."""
    _, state, _ = stepped
    batch = sample_sequences(state.buffer, jax.random.key(2), 16, 3)
    return state, batch


@functools.cache
def _jacobian(config):
    """jit(the jacobian of loss_terms w.r.t. params and target) of a config: each term's gradient per parameter
    group. Every input is an argument (the HParams too: alpha 0 and alpha 1 are one program); built once per config
    and shared by the gradient tests (their sum over the terms is total_loss's gradient, total_loss being the terms'
    sum)."""
    nets = Learner(config).nets
    terms = lambda *args: loss_terms(*args, nets=nets, config=config)[0]  # noqa: E731
    return jax.jit(jax.jacrev(terms, argnums=(0, 1)))


def _params(arm, state):
    params = dict(state.params)  # the paper-cd state's: the other arms have no consistency encoder
    if arm != "paper-cd":
        params.pop("cc_encoder")
    return params


def _terms(arm, state, batch, hp):
    """Each term's gradient w.r.t. (params, target) at the replayed state and batch."""
    return _jacobian(TINY.replace(arm=arm))(_params(arm, state), state.target, state.norm, batch, hp.as_float32(),
                                            jax.random.key(4))


def _grads(arm, state, batch, hp):
    """total_loss's gradient w.r.t. params: the sum of its terms'."""
    return jax.tree.map(lambda *g: sum(g), *[params for params, _ in _terms(arm, state, batch, hp).values()])


@pytest.mark.parametrize("arm", ["paper-cd", "self-pred"])
def test_the_consistency_arms_at_alpha_0_take_the_model_arms_gradients(replayed, arm):
    state, batch = replayed
    model = _grads("model", state, batch, HParams())
    at_zero = _grads(arm, state, batch, HParams(alpha=0.0))
    at_one = _grads(arm, state, batch, HParams(alpha=1.0))
    for group in model:
        for a, b in zip(jax.tree.leaves(at_zero[group]), jax.tree.leaves(model[group])):
            np.testing.assert_allclose(a, b, rtol=2e-5, atol=1e-7, err_msg=group)  # another program: rounding only
    changed = [not np.allclose(a, b) for a, b in zip(jax.tree.leaves(at_one["model"]), jax.tree.leaves(model["model"]))]
    assert any(changed)  # the term does reach the model at alpha 1
    if arm == "paper-cd":  # and the actor, along the policy path
        assert any(not np.allclose(a, b) for a, b in zip(jax.tree.leaves(at_one["actor"]),
                                                         jax.tree.leaves(model["actor"])))


def test_the_self_predictive_target_receives_no_gradient(replayed):
    state, batch = replayed
    for term, (_, target) in _terms("self-pred", state, batch, HParams(alpha=1.0)).items():  # not one term's
        assert all(not np.asarray(g).any() for g in jax.tree.leaves(target)), term
    online = _grads("self-pred", state, batch, HParams(alpha=1.0))
    assert any(np.asarray(g).any() for g in jax.tree.leaves(online["encoder"]))  # the online encoder learns


@pytest.mark.parametrize("arm", ["paper-cd", "self-pred"])
def test_each_loss_term_reaches_only_the_groups_it_is_built_to_train(replayed, arm):
    """The stop_gradients route every term as REACHES says: any other group's gradient is exactly zero, and each
    group it names gets some gradient (the diagnostics' "grad/<term>/<group>" are those norms)."""
    state, batch = replayed
    jac = {term: params for term, (params, _) in _terms(arm, state, batch, HParams(alpha=1.0)).items()}
    expected = {"critic", "actor", "temperature", "model"} | ({"consistency", "encoder_aux"} if arm == "paper-cd"
                                                               else {"self_pred"})
    assert set(jac) == expected
    for term, grads in jac.items():
        for group, g in grads.items():
            reached = any(np.asarray(leaf).any() for leaf in jax.tree.leaves(g))
            assert reached == (group in REACHES[term]), (term, group)


def test_obs_plus_latent_inputs_put_the_observation_beside_the_latent_and_keep_the_routing(replayed):
    """inputs="obs+latent": the actor and critic read [normalised obs, latent]; the model and the self-predictive
    term still work on the latent alone; every term reaches what REACHES says. inputs="obs" has no encoder, which
    the model arms refuse."""
    state, batch = replayed
    config = TINY.replace(arm="self-pred", inputs="obs+latent")
    nets = Learner(config).nets
    params = nets.init(jax.random.key(5))
    target = {"critic": params["critic"], "encoder": params["encoder"]}
    obs = batch["obs"][0]
    z = nets.encode(params["encoder"], obs)
    assert z.shape == (obs.shape[0], config.latent_dim)
    np.testing.assert_array_equal(nets.features(params["encoder"], obs), jnp.concatenate([obs, z], axis=-1))
    assert params["actor"]["params"]["MLP_0"]["Dense_0"]["kernel"].shape[0] == obs.shape[-1] + config.latent_dim
    # obs+latent is the default inputs: the self-pred loss-reach test's program
    jac = _jacobian(config)(params, target, state.norm, batch, HParams(alpha=1.0).as_float32(), jax.random.key(4))
    jac = {term: of_params for term, (of_params, _) in jac.items()}
    assert set(jac) == {"critic", "actor", "temperature", "model", "self_pred"}
    for term, grads in jac.items():
        for group, g in grads.items():
            assert any(np.asarray(leaf).any() for leaf in jax.tree.leaves(g)) == (group in REACHES[term]), (term, group)
    assert Learner(TINY.replace(inputs="obs")).nets.encoder is None
    with pytest.raises(ConfigError, match="needs inputs latent or obs\\+latent"):
        TINY.replace(arm="model", inputs="obs")


def test_diagnostics_change_no_training_number_and_hold_their_envs_out_of_the_replay(runs):
    config, keys, hps, _, alone = runs
    plain_state, plain = alone[0]
    state, metrics = jax.jit(make_train(config.replace(diagnostics=True)))(keys[0], hps[0])
    for name in plain:
        np.testing.assert_allclose(metrics[name], plain[name], rtol=2e-5, atol=1e-6, err_msg=name)
    for a, b in zip(jax.tree.leaves(state.params), jax.tree.leaves(plain_state.params)):
        np.testing.assert_allclose(a, b, rtol=2e-5, atol=1e-6)
    learning = np.asarray(plain["loss/critic"])
    assert np.isnan(learning[0]) and np.isfinite(learning[-1])  # the last updates learn, the first do not
    for name in ("grad/critic/encoder", "grad/model/model", "grad/self_pred/encoder", "latent/spread",
                 "heldout/open_loop_mse_1", f"heldout/open_loop_mse_{config.horizon}"):
        values = np.asarray(metrics[name])
        assert np.isnan(values[0]) and np.isfinite(values[-1]) and values[-1] > 0, name
    assert float(metrics["heldout/windows"][-1]) > 0
    # the held-out envs' observations are nowhere in the replay buffer
    replayed = np.asarray(state.buffer.data["obs"]).reshape(-1, np.asarray(state.buffer.data["obs"]).shape[-1])
    held = np.asarray(state.heldout["window"]["obs"]).reshape(-1, replayed.shape[-1])
    assert not (np.abs(replayed[:, None, :] - held[None]).max(-1) == 0).any()


def test_sac_learns_to_hold_the_point_mass_at_the_origin():
    """Random actions for the first 256 env steps, then 2 gradient steps per batched env step: within 9600 env steps
    the return of 30-step episodes (at most 30: reward 1 - |x|^2) rises well above the early policy's."""
    config = Config(env="point", num_envs=8, steps_per_update=8, updates_per_step=2, buffer_steps=512, batch_size=64,
                    learning_starts=256, num_updates=150, episode_length=30, actor_hidden=(32, 32),
                    critic_hidden=(32, 32), encoder_hidden=(32,), latent_dim=16)
    hp = HParams(gamma=0.9, lr_actor=1e-3, lr_critic=1e-3, lr_alpha=1e-3, init_alpha=0.1)
    _, metrics = jax.jit(make_train(config))(jax.random.key(0), hp)
    returns = np.asarray(metrics["episode/return"])
    early, late = np.nanmean(returns[4:30]), np.nanmean(returns[-30:])
    assert late > early + 5.0 and late > 15.0, (early, late)
