"""A2C with an optional latent dynamics model and the consistency term, as one jitted update.

One update (`A2C.update(state, hp)`, pure):
1. rollout: `rollout_len` steps of `num_envs` environments with the current policy (lax.scan), raw scores
   recorded for the reported returns;
2. the loss of that batch, as named terms times their weights (`term_weights`):
   - `a2c`: policy gradient with the n-step advantage, value loss, entropy bonus (cdjax.agents.atari.losses);
   - `model` (a2c-model, a2c-cd): the latent model's one-step loss: from z_t = torso(s_t) (stop-gradient)
     and the action, predict z_{t+1} = torso(s_{t+1}) (stop-gradient target) and the reward;
   - `consistency` (a2c-cd): `cdjax.consistency.consistency_loss` between the encoded real latent sequence
     z_1..z_k of each window and the sequence the model imagines from z_0 under the same actions, with the
     path weights cc_model and cc_policy; `encoder_aux` for the grounded-gru encoder;
3. one optimiser step: RMSprop on the agent (torso, actor, critic), as A2C (Mnih et al. 2016 and OpenAI
   baselines, whose A2C figures this arm is compared with), Adam on the model and the encoder, each group's
   gradient clipped at max_grad_norm; a step whose gradient is not finite is skipped.

The consistency gradient reaches the policy through the actions, as in the observation-space agent: the
imagined rollout is fed a straight-through one-hot of the executed action, onehot(a) + pi(.|s) -
stop_gradient(pi(.|s)), numerically the executed action, whose gradient flows into the policy's logits.
"""

from __future__ import annotations

import functools
from typing import Any, Callable

import jax
import jax.numpy as jnp
import optax
from flax import struct

from cdjax import consistency
from cdjax.agents.atari import losses
from cdjax.agents.atari.config import HP_RANGES, AtariConfig, AtariHParams
from cdjax.agents.atari.minatar import MinAtarEnv
from cdjax.agents.atari.networks import ActorCritic, LatentModel, torso_of
from cdjax.checks import check_type
from cdjax.envs import EpisodeStats
from cdjax.optim import skip_if_not_finite
from cdjax.protocol import Trainer, scanned_train

TERMS = ("a2c", "model", "consistency", "encoder_aux")


def term_weights(hp: AtariHParams) -> dict[str, jax.Array]:
    """The weight of each named loss term in the total."""
    return {"a2c": jnp.ones((), jnp.float32), "model": hp.model_coef, "consistency": hp.alpha,
            "encoder_aux": hp.enc_aux_coef}


def make_env(config: AtariConfig, num_envs: int, training: bool = True):
    """The batched env of `config`: a MinAtar game, or an ALE game (cdjax.agents.atari.ale; training=True
    ends an episode at every lost life for learning, the reported returns are whole games either way)."""
    if config.is_ale:
        from cdjax.agents.atari.ale import AleEnv

        return AleEnv(config, num_envs, episodic_life=training)
    return MinAtarEnv(config.env, num_envs, config.episode_length, config.sticky_prob)


@struct.dataclass
class Batch:
    """One rollout, time-major [T, B, ...]."""

    obs: jax.Array  # [T, B, H, W, C] what the policy acted on
    action: jax.Array  # [T, B] int32
    reward: jax.Array  # [T, B] raw reward
    next_obs: jax.Array  # [T, B, H, W, C] the observation after the action, before any reset
    terminated: jax.Array  # [T, B] bool: the episode ended by the game (no bootstrap)
    ended: jax.Array  # [T, B] bool: terminated, timed out, or reset after a non-finite step
    valid: jax.Array  # [T, B] bool: False for a non-finite transition


@struct.dataclass
class A2CState:
    params: dict  # {"agent"[, "model"[, "encoder"]]}
    opt_state: Any
    env_state: Any
    stats: EpisodeStats
    last_return: jax.Array  # [] the mean return of the latest rollout in which episodes ended (NaN before)
    last_disc_return: jax.Array  # [] the same, discounted
    key: jax.Array
    step: jax.Array  # [] int32 updates done


class A2C:
    """The learner of one Config; pure methods, jit/vmap them at the entry point."""

    def __init__(self, config: AtariConfig):
        check_type(config, AtariConfig)
        self.config = config
        self.env = make_env(config, config.num_envs)
        self.num_actions = self.env.num_actions
        self.agent = ActorCritic(self.num_actions, torso_of(config))
        self.model = LatentModel(config.latent, (config.model_hidden,) * 2) if config.use_model else None
        self.encoder = None
        if config.use_consistency and config.encoder != "l2":
            window = config.horizon * config.latent if config.encoder == "grounded-gru" else 0
            self.encoder = consistency.SequenceEncoder(config.encoder_dim, window)

    # --- parameters and optimiser

    def init_params(self, key: jax.Array) -> dict:
        key_agent, key_model, key_encoder = jax.random.split(key, 3)
        obs = jnp.zeros((1,) + tuple(self.env.obs_shape), jnp.float32)
        params = {"agent": self.agent.init(key_agent, obs)}
        if self.model is not None:
            z, a = jnp.zeros((1, self.config.latent)), jnp.zeros((1, self.num_actions))
            params["model"] = self.model.init(key_model, z, a)
        if self.encoder is not None:
            params["encoder"] = consistency.init_encoder(self.encoder, key_encoder, self.config.latent)
        return params

    def optimizer(self, hp: AtariHParams) -> optax.GradientTransformation:
        def clipped(tx):
            return optax.chain(optax.clip_by_global_norm(hp.max_grad_norm), tx)

        groups = {"agent": clipped(optax.rmsprop(hp.lr, decay=hp.rms_decay, eps=hp.rms_eps)),
                  "model": clipped(optax.adam(hp.lr_model)),
                  "encoder": (optax.set_to_zero() if self.config.encoder == "frozen-gru"
                              else clipped(optax.adam(hp.lr_model)))}
        labels = lambda params: {name: jax.tree.map(lambda _: name, sub) for name, sub in params.items()}  # noqa: E731
        return skip_if_not_finite(optax.multi_transform(groups, labels))

    def init(self, key: jax.Array, hp: AtariHParams) -> A2CState:
        HP_RANGES.check(hp, one_run=True)  # concrete values (outside jit) get the command line's checks
        key_params, key_env, key_next = jax.random.split(key, 3)
        params = self.init_params(key_params)
        nan = jnp.full((), jnp.nan, jnp.float32)
        return A2CState(params=params, opt_state=self.optimizer(hp).init(params),
                        env_state=self.env.reset(key_env), stats=EpisodeStats.create(self.config.num_envs),
                        last_return=nan, last_disc_return=nan, key=key_next, step=jnp.zeros((), jnp.int32))

    # --- acting

    def act(self, agent_params, obs: jax.Array, key: jax.Array | None) -> jax.Array:
        """Actions [B] int32 for obs [B, ...]: sampled from the policy, or its most likely action (key None)."""
        logits, _, _ = self.agent.apply(agent_params, obs)
        if key is None:
            return jnp.argmax(logits, axis=-1).astype(jnp.int32)
        return jax.random.categorical(key, logits).astype(jnp.int32)

    def collect(self, agent_params, env_state, stats: EpisodeStats, key: jax.Array, gamma):
        """`rollout_len` steps of every environment: (env_state, stats, Batch [T, B])."""

        def step(carry, key_t):
            env_state, stats = carry
            action = self.act(agent_params, env_state.obs, key_t)
            new_state, out = self.env.step(env_state, action)
            ended = out.terminated | out.truncated | ~out.valid
            game_over = getattr(out, "game_over", ended)  # ALE's episodic life: a lost life ends only the learning episode
            stats = stats.record(out.reward, game_over | ~out.valid, game_over & out.valid, gamma)
            batch = Batch(obs=env_state.obs, action=action, reward=out.reward, next_obs=out.next_obs,
                          terminated=out.terminated, ended=ended, valid=out.valid)
            return (new_state, stats), batch

        keys = jax.random.split(key, self.config.rollout_len)
        (env_state, stats), batch = jax.lax.scan(step, (env_state, stats), keys)
        return env_state, stats, batch

    # --- the loss

    def loss_terms(self, params: dict, batch: Batch, offsets: jax.Array, hp: AtariHParams) -> tuple[dict, dict]:
        """The named loss terms of one rollout -> ({name: scalar}, metrics)."""
        T = batch.action.shape[0]
        both = jnp.concatenate([batch.obs, batch.next_obs])  # one torso pass over s_t and s'_t
        logits, values, z = self.agent.apply(params["agent"], both)
        next_value, z_next = jax.lax.stop_gradient(values[T:]), jax.lax.stop_gradient(z[T:])
        logits, values, z = logits[:T], values[:T], z[:T]
        reward = jnp.sign(batch.reward) if self.config.clip_rewards else batch.reward
        returns = losses.n_step_returns(reward, next_value, batch.terminated, batch.ended, batch.valid, hp.gamma)
        a2c, metrics = losses.a2c_loss(logits, values, batch.action, returns, batch.valid, hp)
        terms = {"a2c": a2c}
        onehot = jax.nn.one_hot(batch.action, self.num_actions)
        if self.model is not None:
            pred_z, pred_r = self.model.apply(params["model"], jax.lax.stop_gradient(z), onehot)
            terms["model"], model_metrics = losses.latent_model_loss(pred_z, pred_r, z_next, reward, batch.valid)
            metrics.update(model_metrics)
        if self.config.use_consistency:
            probs = jax.nn.softmax(logits)
            actions = onehot + probs - jax.lax.stop_gradient(probs)  # the executed action; d/d(policy) flows
            s0, window_actions, real_next, mask = consistency.windows(
                jax.lax.stop_gradient(z), z_next, actions, batch.ended, batch.valid, offsets, self.config.horizon)
            cc_terms, cc_metrics = consistency.consistency_loss(
                lambda p, s, a: self.model.apply(p, s, a)[0], params["model"], s0, window_actions, real_next, mask,
                kind=self.config.encoder, normalize=lambda x: x,
                weights=consistency.path_weights(hp), encoder=self.encoder,
                encoder_params=params.get("encoder"), unroll=self.config.cc_unroll)
            terms.update(cc_terms)
            metrics.update(cc_metrics)
        return terms, metrics

    def loss(self, params: dict, batch: Batch, offsets: jax.Array, hp: AtariHParams) -> tuple[jax.Array, dict]:
        terms, metrics = self.loss_terms(params, batch, offsets, hp)
        weights = term_weights(hp)
        total = sum(weights[name] * term for name, term in terms.items())
        metrics["loss/total"] = total
        return total, metrics

    # --- one update

    def update(self, state: A2CState, hp: AtariHParams) -> tuple[A2CState, dict]:
        key, key_rollout, key_windows = jax.random.split(state.key, 3)
        env_state, stats, batch = self.collect(state.params["agent"], state.env_state, state.stats.start_rollout(),
                                               key_rollout, hp.gamma)
        offsets = consistency.window_offsets(key_windows, self.config.rollout_len, self.config.horizon,
                                             self.config.num_windows)
        grads, metrics = jax.grad(self.loss, has_aux=True)(state.params, batch, offsets, hp)
        updates, opt_state = self.optimizer(hp).update(grads, state.opt_state, state.params)
        params = optax.apply_updates(state.params, updates)
        ret = stats.mean_returns(state.last_return)[0]
        disc_ret = stats.mean_returns(state.last_disc_return)[1]
        metrics.update({f"grad/{name}": optax.global_norm(g) for name, g in grads.items()})
        metrics.update({
            "episode/return": ret, "episode/discounted_return": disc_ret, "episode/count": stats.done_count,
            "train/reward": batch.reward.mean(), "env/invalid_fraction": 1.0 - batch.valid.astype(jnp.float32).mean(),
            "train/skipped_step": (opt_state.total_notfinite - state.opt_state.total_notfinite).astype(jnp.float32)})
        new = state.replace(params=params, opt_state=opt_state, env_state=env_state, stats=stats, last_return=ret,
                            last_disc_return=disc_ret, key=key, step=state.step + 1)
        return new, metrics


@functools.lru_cache(maxsize=None)
def learner(config: AtariConfig) -> A2C:
    """One learner per Config (its env and modules are built once)."""
    return A2C(config)


TrainState = A2CState  # the face every setting shares: cdjax.agents.<setting>.TrainState


def make_train(config: AtariConfig) -> Callable[[jax.Array, AtariHParams], tuple[A2CState, dict]]:
    """train(key, hp) -> (final state, metrics with leaves [num_updates]): pure, jit/vmap it yourself (a MinAtar
    game; an ALE game's emulators live outside JAX and run under the host side's sweep)."""
    agent = learner(config)
    return scanned_train(agent.init, agent.update, config.num_updates)


def make_trainer(config: AtariConfig) -> Trainer:
    """The A2C learner of `config` as the host side runs it (`cdjax.protocol.Trainer`)."""
    agent = learner(config)

    @functools.cache
    def eval_env(num_envs: int):
        """The evaluation env of `num_envs` episodes, one per size: an ALE env's emulators are made once, not at every
        evaluation."""
        return make_env(config, num_envs, training=False)

    def saved_leaves():
        """MinAtar: every leaf. ALE: not the environments (the emulators live outside JAX; a resumed run starts
        fresh games from init's) nor the running returns of the episodes in flight."""
        every = jax.tree.map(lambda _: True, jax.eval_shape(agent.init, jax.random.key(0), AtariHParams()))
        if not config.is_ale:
            return every
        stats = every.stats.replace(ret=False, disc_ret=False, disc=False)
        return every.replace(env_state=jax.tree.map(lambda _: False, every.env_state), stats=stats)

    return Trainer(config=config, init=agent.init, update=agent.update, policy=lambda state: state.params["agent"],
                   act=agent.act, eval_env=eval_env,
                   saved_leaves=saved_leaves, inner=agent)
