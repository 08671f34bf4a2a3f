"""The off-policy learner: one jitted update collects `steps_per_update` batched env steps into a replay buffer held
in the TrainState and takes `grad_steps` SGD steps on sequences sampled from it.

What a checkpoint keeps (`saved_leaves`): parameters, target parameters, optimiser moments, observation statistics,
the running episode returns, the PRNG key, the replay buffer, which is most of it (buffer_steps x num_envs
transitions), and of the environments' state the leaves a later step reads (`cdjax.envs.resume.needed_leaves`: an
MJX state is mostly derived physics data), not each env's reset target, which init gives again from the same key. A
run resumed from it continues with the same numbers as one that was never stopped (exact on a CPU;
`tests/test_offpolicy_host.py`).
"""

from __future__ import annotations

import functools
import warnings
from typing import Callable

import jax
import jax.numpy as jnp
import optax
from flax import struct

from cdjax import envs
from cdjax import normalize as nz
from cdjax.agents.offpolicy.config import HP_RANGES, Config, HParams
from cdjax.agents.offpolicy.losses import REACHES, loss_terms, total_loss
from cdjax.agents.offpolicy.networks import Nets
from cdjax.checks import check_type
from cdjax.envs import EnvState, EpisodeStats
from cdjax.envs.resume import needed_leaves
from cdjax.optim import skip_if_not_finite
from cdjax.protocol import Trainer, scanned_train
from cdjax.replay import RingBuffer, sample_sequences
from cdjax.consistency import window_indices, window_mask
from cdjax.consistency.selfpredictive import latent_rollout, polyak
from cdjax.numerics import masked_mean

LR_OF = {"actor": "lr_actor", "critic": "lr_critic", "encoder": "lr_critic", "log_alpha": "lr_alpha",
         "model": "lr_model", "cc_encoder": "lr_model"}  # parameter group -> its learning rate's HParams field


@struct.dataclass
class TrainState:
    params: dict  # parameter groups (networks.Nets.init)
    target: dict  # {"critic", "encoder"}: Polyak averages of the online ones
    opt_state: optax.OptState
    norm: nz.RunningStats  # observation statistics (every observation the envs gave)
    buffer: RingBuffer  # items: one batched env step {obs, action, reward, next_obs, terminated, ended, valid} [E, ...]
    env_state: EnvState
    episodes: EpisodeStats
    last_return: jax.Array  # [] mean return of the last finished episodes (NaN before any)
    last_disc_return: jax.Array
    key: jax.Array
    step: jax.Array  # [] int32 updates done
    heldout: dict  # Config.diagnostics: {"env_state", "window": the newest horizon steps of the held-out envs}; else {}


def optimiser(hp: HParams, groups) -> optax.GradientTransformation:
    """Adam per parameter group (its own learning rate, the gradient's norm clipped per group), a step skipped
    whole when any gradient is not finite."""
    txs = {g: optax.chain(optax.clip_by_global_norm(hp.max_grad_norm), optax.adam(getattr(hp, LR_OF[g])))
           for g in groups}

    def init(params):
        return {g: txs[g].init(params[g]) for g in txs}

    def update(grads, state, params=None):
        out = {g: txs[g].update(grads[g], state[g], None if params is None else params[g]) for g in txs}
        return {g: o[0] for g, o in out.items()}, {g: o[1] for g, o in out.items()}

    return skip_if_not_finite(optax.GradientTransformation(init, update))


class Learner:
    """The setting's learner for one Config: init, update, act (pure functions of their arguments)."""

    def __init__(self, config: Config):
        check_type(config, Config)
        self.config = config
        self.env = envs.make_env(config)
        self.nets = Nets(config, self.env.observation_size, self.env.action_size)
        self.loss = functools.partial(total_loss, nets=self.nets, config=config)
        self.heldout_env = (envs.batched(config.env, config.heldout_envs, config.episode_length, config.action_repeat,
                                         config.reset_mode, physics_backend=config.physics_backend)
                            if config.diagnostics else None)

    def item(self, env_state: EnvState, action, out: envs.Step) -> dict:
        return {"obs": env_state.obs, "action": action, "reward": out.reward, "next_obs": out.next_obs,
                "terminated": out.terminated, "ended": out.terminated | out.truncated | ~out.valid, "valid": out.valid}

    def init(self, key: jax.Array, hp: HParams) -> TrainState:
        HP_RANGES.check(hp, one_run=True)
        hp = hp.as_float32()
        c = self.config
        key, key_params, key_env = jax.random.split(key, 3)
        params = self.nets.init(key_params)
        params["log_alpha"] = jnp.log(hp.init_alpha)
        env_state = self.env.reset(key_env)
        A, E = self.env.action_size, c.num_envs
        zero_step = envs.Step(next_obs=env_state.obs, reward=jnp.zeros((E,)), terminated=jnp.zeros((E,), bool),
                              truncated=jnp.zeros((E,), bool), valid=jnp.zeros((E,), bool))
        example = self.item(env_state, jnp.zeros((E, A), jnp.float32), zero_step)
        nan = jnp.full((), jnp.nan, jnp.float32)
        heldout = {}
        if self.heldout_env is not None:  # its own key: the training envs' and the learner's streams stay as they are
            env_h = self.heldout_env.reset(jax.random.fold_in(key_env, 1))
            H, k = c.heldout_envs, c.horizon
            step_h = envs.Step(next_obs=env_h.obs, reward=jnp.zeros((H,)), terminated=jnp.zeros((H,), bool),
                               truncated=jnp.zeros((H,), bool), valid=jnp.zeros((H,), bool))
            item = self.item(env_h, jnp.zeros((H, A), jnp.float32), step_h)
            heldout = {"env_state": env_h, "window": jax.tree.map(lambda x: jnp.stack([x] * k), item)}
        return TrainState(
            params=params, target={"critic": params["critic"], "encoder": params["encoder"]},
            opt_state=optimiser(hp, params).init(params), norm=nz.RunningStats.create(self.env.observation_size),
            buffer=RingBuffer.create(example, c.buffer_steps), env_state=env_state,
            episodes=EpisodeStats.create(E), last_return=nan, last_disc_return=nan, key=key,
            step=jnp.zeros((), jnp.int32), heldout=heldout)

    def act(self, policy: dict, obs: jax.Array, key: jax.Array | None) -> jax.Array:
        """policy: {"actor", "encoder", "norm"}; key None: the deterministic action tanh(mean)."""
        x = self.nets.features(policy["encoder"], nz.normalize(policy["norm"], obs))
        if key is None:
            return jnp.tanh(self.nets.actor.apply(policy["actor"], x)[0])
        return self.nets.sample(policy["actor"], x, key)[0]

    def _collect(self, state: TrainState, hp: HParams) -> TrainState:
        c = self.config

        def step(state, _):
            key, key_act, key_random = jax.random.split(state.key, 3)
            obs = state.env_state.obs
            norm = nz.update(state.norm, obs)
            policy = {"actor": state.params["actor"], "encoder": state.params["encoder"], "norm": norm}
            random = state.buffer.count < c.random_steps
            uniform = jax.random.uniform(key_random, (c.num_envs, self.env.action_size), minval=-1.0, maxval=1.0)
            action = jnp.where(random, uniform, self.act(policy, obs, key_act))
            env_state, out = self.env.step(state.env_state, action)
            episodes = state.episodes.record(out.reward, out.terminated | out.truncated | ~out.valid,
                                             out.terminated | out.truncated, hp.gamma)
            buffer = state.buffer.add(jax.tree.map(lambda x: x[None], self.item(state.env_state, action, out)))
            heldout = state.heldout
            if self.heldout_env is not None:  # the same policy on the held-out envs; nothing of theirs is replayed
                key_h, key_u = jax.random.split(jax.random.fold_in(key_act, 1))
                obs_h = heldout["env_state"].obs
                uniform_h = jax.random.uniform(key_u, obs_h.shape[:1] + (self.env.action_size,), minval=-1.0,
                                               maxval=1.0)
                action_h = jnp.where(random, uniform_h, self.act(policy, obs_h, key_h))
                env_h, out_h = self.heldout_env.step(heldout["env_state"], action_h)
                item = self.item(heldout["env_state"], action_h, out_h)
                heldout = {"env_state": env_h, "window": jax.tree.map(lambda w, x: jnp.concatenate([w[1:], x[None]]),
                                                                      heldout["window"], item)}
            return state.replace(key=key, norm=norm, env_state=env_state, episodes=episodes, buffer=buffer,
                                 heldout=heldout), None

        return jax.lax.scan(step, state, None, length=c.steps_per_update)[0]

    def _train(self, state: TrainState, hp: HParams) -> tuple[TrainState, dict]:
        c = self.config
        tx = optimiser(hp, state.params)
        started = state.buffer.count >= c.random_steps

        def sgd(carry, _):
            params, target, opt_state, key = carry
            key, key_batch, key_loss = jax.random.split(key, 3)
            batch = sample_sequences(state.buffer, key_batch, c.batch_size, c.seq_len)
            grads, metrics = jax.grad(self.loss, has_aux=True)(params, target, state.norm, batch, hp, key_loss)
            updates, new_opt = tx.update(grads, opt_state, params)
            new_params = optax.apply_updates(params, updates)
            online = {"critic": new_params["critic"], "encoder": new_params["encoder"]}
            new_target = polyak(target, online, hp.tau)
            keep = lambda new, old: jax.tree.map(lambda n, o: jnp.where(started, n, o), new, old)  # noqa: E731
            return (keep(new_params, params), keep(new_target, target), keep(new_opt, opt_state), key), metrics

        carry = (state.params, state.target, state.opt_state, state.key)
        (params, target, opt_state, key), metrics = jax.lax.scan(sgd, carry, None, length=c.grad_steps)
        metrics = jax.tree.map(lambda m: jnp.where(started, m.mean(), jnp.nan), metrics)
        if c.diagnostics:  # at the parameters the gradient steps started from
            metrics.update(jax.tree.map(lambda m: jnp.where(started, m, jnp.nan), self.diagnose(state, hp)))
        return state.replace(params=params, target=target, opt_state=opt_state, key=key), metrics

    def diagnose(self, state: TrainState, hp: HParams) -> dict:
        """Config.diagnostics' metrics (scalars) at state's parameters, on a batch of its own sampled with a key
        folded from the state's (the learner's stream is not advanced)."""
        c, nets = self.config, self.nets
        key_batch, key_loss = jax.random.split(jax.random.fold_in(state.key, 0xD1A6))
        batch = sample_sequences(state.buffer, key_batch, c.batch_size, c.seq_len)
        terms = lambda p: loss_terms(p, state.target, state.norm, batch, hp, key_loss, nets=nets, config=c)[0]  # noqa: E731
        out = {f"grad/{term}/{group}": optax.global_norm(grads[group])
               for term, grads in jax.jacrev(terms)(state.params).items()
               for group in REACHES[term] if jax.tree.leaves(grads.get(group, {}))}
        if nets.encoder is not None:
            obs = nz.normalize(state.norm, batch["obs"][0])
            out["latent/spread"] = nets.encode(state.params["encoder"], obs).std(0).mean()
            out["latent/target_spread"] = nets.encode(state.target["encoder"], obs).std(0).mean()
        if c.use_model:  # the model's k-step open-loop prediction, decoded, on the held-out envs' newest window
            w = state.heldout["window"]
            mask = window_mask(w["ended"], w["valid"], window_indices(jnp.zeros((1,), jnp.int32), c.horizon))[0]
            z0 = nets.encode(state.params["encoder"], nz.normalize(state.norm, w["obs"][0]))
            model = lambda z, *a, method: nets.model.apply(state.params["model"], z, *a, method=method)  # noqa: E731
            latents = latent_rollout(functools.partial(model, method="transition"), z0, w["action"])
            err = ((model(latents, method="decode") - nz.normalize(state.norm, w["next_obs"])) ** 2).mean(-1)
            for j in range(c.horizon):
                out[f"heldout/open_loop_mse_{j + 1}"] = jnp.where(mask.any(), masked_mean(err[j], mask), jnp.nan)
            out["heldout/windows"] = mask.sum().astype(jnp.float32)
        return out

    def update(self, state: TrainState, hp: HParams) -> tuple[TrainState, dict]:
        """One update: collect, then learn. Metrics are scalars (the losses: means over the SGD steps, NaN before
        learning starts)."""
        hp = hp.as_float32()
        state = self._collect(state.replace(episodes=state.episodes.start_rollout()), hp)
        skipped_before = state.opt_state.total_notfinite
        state, metrics = self._train(state, hp)
        last_return, _ = state.episodes.mean_returns(state.last_return)
        _, last_disc = state.episodes.mean_returns(state.last_disc_return)
        metrics.update({"episode/return": last_return, "episode/discounted_return": last_disc,
                        "episode/count": state.episodes.done_count,
                        "train/skipped_steps": (state.opt_state.total_notfinite - skipped_before).astype(jnp.float32),
                        "buffer/filled": state.buffer.filled.astype(jnp.float32) * self.config.num_envs})
        state = state.replace(last_return=last_return, last_disc_return=last_disc, step=state.step + 1)
        return state, metrics


def make_train(config: Config) -> Callable[[jax.Array, HParams], tuple[TrainState, dict]]:
    """train(key, hp) -> (final state, metrics with leaves [num_updates]): pure, jit/vmap it yourself."""
    learner = Learner(config)
    return scanned_train(learner.init, learner.update, config.num_updates)


def make_trainer(config: Config) -> Trainer:
    """The learner of `config` as the host side runs it (`cdjax.protocol.Trainer`)."""
    learner = Learner(config)

    @functools.cache
    def saved_leaves():
        every = jax.tree.map(lambda _: True, jax.eval_shape(learner.init, jax.random.key(0), HParams()))
        try:
            env = needed_leaves(learner.env)
        except Exception as err:  # noqa: BLE001 - an optimisation of the checkpoint's size must not end a run
            warnings.warn(f"checkpoints keep the whole {config.env} state: the analysis of which leaves a resume "
                          f"needs failed ({type(err).__name__}: {err})", stacklevel=2)
            return every
        return every.replace(env_state=env.replace(first=jax.tree.map(lambda _: False, env.first)))

    def eval_env(num_envs: int) -> envs.BatchedEnv:
        return envs.batched(config.env, num_envs, config.episode_length, config.action_repeat, config.reset_mode,
                            physics_backend=config.physics_backend)

    return Trainer(config=config, init=learner.init, update=learner.update,
                   policy=lambda s: {"actor": s.params["actor"], "encoder": s.params["encoder"], "norm": s.norm},
                   act=learner.act, eval_env=eval_env, saved_leaves=saved_leaves, inner=learner)
