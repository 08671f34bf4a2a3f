"""make_trainer(config) -> Trainer(init, update); make_train(config) -> train(key, hp).

One call of `update` is the whole consistent-dynamics step, compiled once: closed-loop rollout
(scan over T steps of B environments), GAE, then epochs x minibatches (scans) of

    PPO + model_coef * model NLL + alpha * consistency,

where the consistency term imagines k-step open-loop windows with the learned model from real start
states, under actions re-derived differentiably from the stored noise (so its gradient reaches the
policy), encodes real and imagined windows with one shared encoder, and averages the L2 distance over
the windows that stay inside one episode. Arms are switches of the same code: `model-free` builds no
model, `mbmf` trains the model without the consistency term, `cd` builds the consistency term with
weight `alpha` (alpha = 0 there still logs l_cc, without gradient).

The library never jits or vmaps a whole run: callers compose, e.g.
`jax.jit(jax.vmap(make_train(cfg), in_axes=(0, None)))(keys, hp)`.
"""

from __future__ import annotations

import functools
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import optax
from flax import struct

from cdjax import losses, networks
from cdjax import normalize as nz
from cdjax.config import Config, HParams
from cdjax.envs import EnvState, make_env, strong_types
from cdjax.rollout import EpisodeStats, Transition, closed_loop, open_loop


@struct.dataclass
class History:
    """The last H transitions of the first `eval_envs` environments (for open-loop error at k and 50)."""

    obs: jax.Array  # [H, E, O]
    next_obs: jax.Array  # [H, E, O]
    action: jax.Array  # [H, E, A]
    ended: jax.Array  # [H, E] bool
    valid: jax.Array  # [H, E] bool
    filled: jax.Array  # [] int32 how many of the H slots hold real data

    @classmethod
    def create(cls, length: int, envs: int, obs_size: int, action_size: int) -> "History":
        z = lambda *s: jnp.zeros(s, jnp.float32)  # noqa: E731
        return cls(z(length, envs, obs_size), z(length, envs, obs_size), z(length, envs, action_size),
                   jnp.zeros((length, envs), bool), jnp.zeros((length, envs), bool), jnp.zeros((), jnp.int32))

    def push(self, traj: Transition) -> "History":
        H, E = self.ended.shape
        cat = lambda old, new: jnp.concatenate([old, new[:, :E]], axis=0)[-H:]  # noqa: E731
        return History(cat(self.obs, traj.obs), cat(self.next_obs, traj.next_obs), cat(self.action, traj.action),
                       cat(self.ended, traj.ended), cat(self.valid, traj.valid),
                       jnp.minimum(self.filled + traj.obs.shape[0], H).astype(jnp.int32))


@struct.dataclass
class TrainState:
    params: dict  # {"policy", "value"[, "model"][, "encoder"]} flax variable dicts
    opt_state: Any  # optax state
    norms: nz.Norms  # running statistics of observations, deltas and rewards
    env_state: EnvState  # batched environment state
    episodes: EpisodeStats  # running returns per environment
    history: History  # recent transitions of a few environments (model diagnostics)
    last_return: jax.Array  # [] mean return of the latest finished episodes (NaN before any)
    last_disc_return: jax.Array  # [] same, discounted
    key: jax.Array  # PRNG key
    update_step: jax.Array  # [] int32 updates done


class Trainer(NamedTuple):
    config: Config
    init: Callable[[jax.Array, HParams], TrainState]  # (key, hp) -> state
    update: Callable[[TrainState, HParams], tuple[TrainState, dict]]  # (state, hp) -> (state, metrics)
    collect: Callable  # (state, hp) -> (env_state, episodes, traj, batch): rollout + GAE, no learning
    loss: Callable  # (params, norms, batch [T, Bm, ...], offsets [n], hp) -> (total, metrics)
    act: Callable  # (params, norms, obs [B, O], key or None) -> action [B, A]; None: deterministic
    model_step: Callable  # (model_params, norms, obs [..., O], action [..., A]) -> (next_obs, reward)
    env: Any  # the BatchedEnv


def make_optimizer(config: Config, params: dict, hp: HParams) -> optax.GradientTransformation:
    """Adam per parameter group with its own learning rate and gradient clipping.

    The frozen-GRU encoder gets zero updates. A step whose gradients are not finite is skipped.
    """

    def group(lr):
        return optax.chain(optax.clip_by_global_norm(hp.max_grad_norm), optax.adam(lr, eps=1e-5))

    lrs = {"policy": hp.lr_policy, "value": hp.lr_value, "model": hp.lr_model, "encoder": hp.lr_model}
    transforms = {}
    for name in params:
        frozen = name == "encoder" and config.encoder == "frozen-gru"
        transforms[name] = optax.set_to_zero() if frozen else group(lrs[name])
    labels = lambda p: {name: jax.tree.map(lambda _: name, sub) for name, sub in p.items()}  # noqa: E731
    return optax.apply_if_finite(optax.multi_transform(transforms, labels), max_consecutive_errors=1_000_000)


def make_trainer(config: Config) -> Trainer:
    env = make_env(config)
    O, A = env.observation_size, env.action_size
    T, k, M, Bm = config.rollout_len, config.horizon, config.num_minibatches, config.minibatch_envs
    modules = networks.build(config, O, A)
    policy, value = modules["policy"], modules["value"]
    model = modules.get("model")
    encoder = modules.get("encoder")
    n_windows = config.num_windows
    all_offsets = config.num_windows == T - k + 1

    def model_step(model_params, norms, obs, action):
        mean, _ = model.apply(model_params, nz.normalize(norms.obs, obs), action)
        next_obs = obs + nz.denormalize(norms.delta, mean[..., :-1])
        reward = nz.denormalize(norms.reward, mean[..., -1:])[..., 0]
        return next_obs, reward

    def act(params, norms, obs, key):
        mean, log_std = policy.apply(params["policy"], nz.normalize(norms.obs, obs))
        if key is None:
            return networks.squash(mean)
        return networks.act_from_noise(mean, log_std, jax.random.normal(key, mean.shape))

    def init(key: jax.Array, hp: HParams) -> TrainState:
        hp = hp.as_float32()
        key_env, key_params, key_train = jax.random.split(key, 3)
        env_state = env.reset(key_env)
        params = networks.init_params(modules, key_params, O, A, hp.init_log_std)
        opt_state = make_optimizer(config, params, hp).init(params)
        nan = jnp.full((), jnp.nan, jnp.float32)
        state = TrainState(
            params=params, opt_state=opt_state, norms=nz.Norms.create(O), env_state=env_state,
            episodes=EpisodeStats.create(config.num_envs),
            history=History.create(config.history_len - 1, config.eval_envs, O, A),
            last_return=nan, last_disc_return=nan, key=key_train, update_step=jnp.zeros((), jnp.int32))
        return strong_types(state)

    def loss_fn(params, norms, mb, offsets, hp, with_consistency: bool = True):
        """Total loss of one minibatch mb (leaves [T, Bm, ...]) -> (loss, metrics)."""
        obs_n = nz.normalize(norms.obs, mb.obs)
        mean, log_std = policy.apply(params["policy"], obs_n)
        values = value.apply(params["value"], obs_n)
        total, metrics = losses.ppo_loss(mean, log_std, values, mb.raw_action, mb.log_prob, mb.advantages,
                                         mb.returns, mb.valid, hp)
        metrics["loss/ppo"] = total
        if model is not None:
            pred_mean, pred_log_std = model.apply(params["model"], obs_n, mb.action)
            target = jnp.concatenate([nz.normalize(norms.delta, mb.next_obs - mb.obs),
                                      nz.normalize(norms.reward, mb.reward[..., None])], axis=-1)
            nll, model_metrics = losses.model_loss(pred_mean, pred_log_std, target, mb.valid)
            metrics.update(model_metrics)
            total = total + hp.model_coef * nll
        if config.use_consistency and with_consistency:
            actions = networks.act_from_noise(mean, log_std, mb.noise)  # [T, Bm, A], carries d/dphi
            idx = losses.window_indices(offsets, k)  # [k, n]
            flat = lambda x: x.reshape(x.shape[:-3] + (-1,) + x.shape[-1:])  # noqa: E731  [.., n, Bm, D] -> [.., n*Bm, D]
            mask = losses.window_mask(mb.ended, mb.valid, idx).reshape(-1)
            if encoder is not None:
                enc_params = params["encoder"]
                if config.encoder == "frozen-gru":
                    enc_params = jax.lax.stop_gradient(enc_params)
                encode_step = functools.partial(encoder.apply, enc_params)
                h0 = jnp.zeros((mask.shape[0], config.encoder_dim), jnp.float32)
            else:
                encode_step, h0 = None, None
            step = lambda s, a: model_step(params["model"], norms, s, a)[0]  # noqa: E731
            cc, cc_metrics = losses.consistency_loss(
                step, functools.partial(nz.normalize, norms.obs), flat(mb.obs[offsets][None])[0],
                flat(actions[idx]), flat(mb.next_obs[idx]), mask, encoder=config.encoder,
                encode_step=encode_step, h0=h0, unroll=config.cc_unroll)
            metrics.update(cc_metrics)
            total = total + hp.alpha * cc
        metrics["loss/total"] = total
        return total, metrics

    def openloop_metrics(model_params, norms, history: History) -> dict:
        """Open-loop MSE (normalised space) of the model at k and at eval_horizon steps on real data."""
        step = lambda s, a: model_step(model_params, norms, s, a)[0]  # noqa: E731
        _, imagined = open_loop(step, history.obs[0], history.action)
        out = {}
        for name, j in (("k", k), ("50", config.eval_horizon)):
            ok = (history.filled >= j) & ~history.ended[: j - 1].any(0) & history.valid[:j].all(0)
            err = ((nz.normalize(norms.obs, imagined[j - 1]) - nz.normalize(norms.obs, history.next_obs[j - 1])) ** 2).mean(-1)
            n = ok.sum()
            out[f"model/openloop_mse_{name}"] = jnp.where(n > 0, losses.masked_mean(err, ok), jnp.nan)
        return out

    def collect(state: TrainState, hp: HParams):
        """Closed-loop rollout with the current policy, then GAE. -> (env_state, episodes, traj, batch)."""
        hp = hp.as_float32()
        params, norms = state.params, state.norms
        _, key_roll, _ = jax.random.split(state.key, 3)

        def behaviour(obs, key):
            mean, log_std = policy.apply(params["policy"], nz.normalize(norms.obs, obs))
            noise = jax.random.normal(key, mean.shape)
            raw = mean + jnp.exp(log_std) * noise
            log_prob = networks.action_distribution(mean, log_std).log_prob(raw)
            return networks.squash(raw), raw, noise, log_prob

        def value_of(obs):
            return value.apply(params["value"], nz.normalize(norms.obs, obs))

        (env_state, episodes), traj = closed_loop(env, behaviour, value_of, state.env_state, state.episodes,
                                                  key_roll, T, hp.gamma)
        advantages, returns = losses.gae(traj.reward * hp.reward_scale, traj.value, traj.next_value,
                                         traj.valid & ~traj.terminated, traj.ended, hp.gamma, hp.gae_lambda)
        batch = Batch(traj.obs, traj.next_obs, traj.action, traj.raw_action, traj.noise, traj.log_prob,
                      traj.reward, traj.ended, traj.valid, advantages, returns)
        return env_state, episodes, traj, batch

    def update(state: TrainState, hp: HParams) -> tuple[TrainState, dict]:
        env_state, episodes, traj, data = collect(state, hp)
        hp = hp.as_float32()
        tx = make_optimizer(config, state.params, hp)
        key, _, key_epochs = jax.random.split(state.key, 3)
        params, norms = state.params, state.norms

        def minibatch(carry, inp, with_consistency):
            params, opt_state = carry
            mb, key = inp
            if all_offsets:
                offsets = jnp.arange(n_windows)
            else:
                offsets = jnp.sort(jax.random.choice(key, T - k + 1, (n_windows,), replace=False))
            grads, metrics = jax.grad(loss_fn, has_aux=True)(params, norms, mb, offsets, hp, with_consistency)
            updates, opt_state = tx.update(grads, opt_state, params)
            params = optax.apply_updates(params, updates)
            return (params, opt_state), metrics

        def epoch(carry, key, with_consistency):
            key_perm, key_mb = jax.random.split(key)
            perm = jax.random.permutation(key_perm, config.num_envs)
            split = lambda x: jnp.swapaxes(x[:, perm].reshape((T, M, Bm) + x.shape[2:]), 0, 1)  # noqa: E731
            mbs = jax.tree.map(split, data)
            step = functools.partial(minibatch, with_consistency=with_consistency)
            return jax.lax.scan(step, carry, (mbs, jax.random.split(key_mb, M)))

        # Epochs with the consistency term first, then (cc_epochs > 0) the rest without it.
        epoch_keys = jax.random.split(key_epochs, config.num_epochs)
        n_cc = config.num_epochs if config.cc_epochs == 0 else config.cc_epochs
        carry, metrics = jax.lax.scan(functools.partial(epoch, with_consistency=True), (params, state.opt_state),
                                      epoch_keys[:n_cc])
        if n_cc < config.num_epochs:
            carry, rest = jax.lax.scan(functools.partial(epoch, with_consistency=False), carry, epoch_keys[n_cc:])
            metrics = {name: jnp.concatenate([value, rest[name]]) if name in rest else value
                       for name, value in metrics.items()}
        params, opt_state = carry
        metrics = jax.tree.map(jnp.mean, metrics)

        history = state.history.push(traj)
        if model is not None:
            metrics.update(openloop_metrics(state.params["model"], norms, history))
        new_norms = nz.Norms(
            obs=nz.update(norms.obs, traj.obs, traj.valid),
            delta=nz.update(norms.delta, traj.next_obs - traj.obs, traj.valid),
            reward=nz.update(norms.reward, traj.reward[..., None], traj.valid),
        )
        count = episodes.done_count
        last_return = jnp.where(count > 0, episodes.done_ret / jnp.maximum(count, 1.0), state.last_return)
        last_disc = jnp.where(count > 0, episodes.done_disc_ret / jnp.maximum(count, 1.0), state.last_disc_return)
        metrics.update({
            "episode/return": last_return,
            "episode/discounted_return": last_disc,
            "episode/count": count,
            "env/reward_mean": losses.masked_mean(traj.reward, traj.valid),
            "env/invalid_fraction": (~traj.valid).astype(jnp.float32).mean(),
            "opt/skipped_updates": opt_state.total_notfinite.astype(jnp.float32),
        })
        new_state = TrainState(
            params=params, opt_state=opt_state, norms=new_norms, env_state=env_state, episodes=episodes,
            history=history, last_return=last_return, last_disc_return=last_disc, key=key,
            update_step=state.update_step + 1)
        return strong_types(new_state), metrics

    return Trainer(config=config, init=init, update=update, collect=collect, loss=loss_fn, act=act,
                   model_step=model_step, env=env)


@struct.dataclass
class Batch:
    """What the SGD phase needs of a rollout; leaves [T, B, ...]."""

    obs: jax.Array
    next_obs: jax.Array
    action: jax.Array
    raw_action: jax.Array
    noise: jax.Array
    log_prob: jax.Array
    reward: jax.Array
    ended: jax.Array
    valid: jax.Array
    advantages: jax.Array
    returns: jax.Array


def make_train(config: Config) -> Callable[[jax.Array, HParams], tuple[TrainState, dict]]:
    """train(key, hp) -> (final state, metrics with leaves [num_updates]): pure, jit/vmap it yourself."""
    trainer = make_trainer(config)

    def train(key: jax.Array, hp: HParams):
        state = trainer.init(key, hp)
        return jax.lax.scan(lambda s, _: trainer.update(s, hp), state, None, length=config.num_updates)

    return train
