"""The model-based phase of the hybrid Mb-Mf (Nagabandi et al., 2017), as one pure function.

`make_mbmf_phase(config, phase) -> run(state, hp) -> (state, info)`; the caller jits `run` (it compiles
once; it also vmaps over seeds). In the phase's own `phase.num_envs` environments:

1. random data: `random_steps` steps per env of uniform actions in [-1, 1];
2. model: params["model"] (Gaussian over the normalised delta-s and reward) trained with Adam(hp.lr_model),
   `model_epochs` shuffled epochs of minibatches over a ring buffer of real transitions (objective:
   `model_objective` below); the running statistics (state.norms) are updated from the new data first;
3. aggregation, `aggregation_iters` times: random-shooting MPC (cdjax.mpc) on the learned model acts for
   `mpc_steps_per_iter` steps, its transitions are appended to the buffer, the model is retrained;
4. distillation: the aggregation states are re-planned with the final model (`relabel`), the policy's
   deterministic action tanh(mu(s)) is regressed (MSE) on those MPC actions, then `distill_iters` DAgger
   rounds: the (stochastic) policy acts, MPC labels the states it visits, the pairs are aggregated, the
   policy is retrained;
5. the value is fitted to TD(lambda) returns of the DAgger rollouts (`value_epochs`, optional), the
   PPO environments are reset, and the TrainState goes back ready for `trainer.update`, with PPO's
   optimiser state untouched (fresh Adam moments) and `info["env_steps"]` counting every env step taken.

Why MSE on tanh(mu) rather than the Gaussian likelihood of atanh(action): random-shooting actions are
uniform samples, often near the box edge where atanh is ill-conditioned (a 0.999 label is 3.8 in
pre-squash space and dominates the loss), and the likelihood would also fit log_std to the scatter of
the controller's noisy labels. The MSE fits the action the policy executes at zero noise (as in
Nagabandi et al.'s code) and leaves log_std at hp.init_log_std for PPO's exploration.

Normalisation: the statistics are updated from the random and MPC data only (each time before the model
is retrained), and frozen during distillation, so that the model the MPC labels come from and the
policy being distilled see the same normalisation as at the end of the phase.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any, Callable, Literal

import jax
import jax.numpy as jnp
import optax
from flax import struct

from cdjax import losses, mpc, networks
from cdjax import normalize as nz
from cdjax.config import Config, ConfigError, HParams
from cdjax.envs import BatchedEnv, make_single_env
from cdjax.rollout import EpisodeStats
from cdjax.envs import strong_types
from cdjax.train import TrainState, Trainer, make_trainer


ModelObjective = Literal["mse", "nll"]


@dataclasses.dataclass(frozen=True)
class MbMfPhase:
    """Static sizes of the model-based phase; defaults follow Nagabandi et al.'s Half-Cheetah settings.

    With the defaults the phase takes 10 x (1000 + 7 x 1000 + 3 x 200) = 86,000 env steps (x action_repeat);
    on one H200, halfcheetah, one seed: 43 s to compile, 132 s to run (latency-bound: ~8,600 sequential
    MPC steps and ~150,000 small Adam steps).
    """

    num_envs: int = 10  # environments stepped in parallel by the phase (its own BatchedEnv); 0 = config.num_envs
    random_steps: int = 1000  # uniform-random steps per env before the first model (Nagabandi: 10 rollouts x 1000)
    aggregation_iters: int = 7  # rounds of MPC data collection + model retraining (Nagabandi, cheetah: 7)
    mpc_steps_per_iter: int = 1000  # MPC steps per env per round (Nagabandi: 10 rollouts x 1000)
    model_epochs: int = 60  # shuffled epochs over the model buffer at each (re)training (Nagabandi: 60)
    model_minibatch: int = 512  # transitions per model gradient step (Nagabandi: 512)
    buffer_size: int = 0  # model dataset capacity (ring buffer, oldest overwritten); 0 = all the phase collects
    model_objective: ModelObjective = "mse"  # mse: mean by MSE (Nagabandi), log_std by NLL; nll: losses.model_loss
    mpc_horizon: int = 20  # random-shooting planning horizon (Nagabandi, cheetah: 20; ant: 5)
    mpc_candidates: int = 1000  # action sequences sampled per state (Nagabandi, cheetah: 1000; ant: 15000)
    mpc_discount: float = 1.0  # predicted reward t weighted by discount**t (Nagabandi: 1, undiscounted)
    distill_iters: int = 3  # DAgger rounds after the first behaviour cloning (Nagabandi, cheetah: 3)
    distill_steps_per_iter: int = 200  # policy steps per env per DAgger round (Nagabandi, cheetah: 2 x 1000 in all)
    distill_epochs: int = 200  # shuffled epochs over the distillation buffer per (re)training (Nagabandi: 70-300)
    distill_minibatch: int = 512  # (state, MPC action) pairs per policy gradient step; also the value's (Nagabandi: 512)
    distill_buffer_size: int = 0  # distillation dataset capacity (ring buffer); 0 = every labelled state
    relabel: bool = True  # re-plan the aggregation states with the final model before cloning (no env steps)
    relabel_chunk: int = 1024  # states planned for at once when relabelling (memory: chunk x candidates x width)
    value_epochs: int = 10  # epochs fitting the value to TD(lambda) returns of the DAgger rollouts; 0 = untouched

    def envs(self, config: Config) -> int:
        return self.num_envs or config.num_envs

    def steps_per_env(self) -> int:
        return self.random_steps + self.aggregation_iters * self.mpc_steps_per_iter + \
            self.distill_iters * self.distill_steps_per_iter

    def model_capacity(self, config: Config) -> int:
        """Transitions the model buffer holds."""
        collected = self.envs(config) * (self.random_steps + self.aggregation_iters * self.mpc_steps_per_iter)
        return self.buffer_size or collected

    def distill_capacity(self, config: Config) -> int:
        """(state, MPC action) pairs the distillation buffer holds."""
        labelled = self.envs(config) * (self.aggregation_iters * self.mpc_steps_per_iter
                                        + self.distill_iters * self.distill_steps_per_iter)
        return self.distill_buffer_size or max(labelled, 1)


def total_env_steps(config: Config, phase: MbMfPhase) -> int:
    """Environment steps the phase takes (physics steps: x action_repeat), computed statically."""
    return phase.envs(config) * phase.steps_per_env() * config.action_repeat


def validate_phase(config: Config, phase: MbMfPhase) -> None:
    """Raise ConfigError (one sentence) for a phase that cannot run; compiles nothing."""
    if not config.use_model:
        raise ConfigError(f"The Mb-Mf phase needs a dynamics model, but arm={config.arm!r} builds none.")
    positive = ("random_steps", "model_epochs", "model_minibatch", "mpc_horizon", "mpc_candidates",
                "distill_epochs", "distill_minibatch", "relabel_chunk")
    non_negative = ("num_envs", "aggregation_iters", "mpc_steps_per_iter", "distill_iters",
                    "distill_steps_per_iter", "buffer_size", "distill_buffer_size", "value_epochs")
    for name in positive + non_negative:
        value = getattr(phase, name)
        low = 1 if name in positive else 0
        if not isinstance(value, int) or isinstance(value, bool) or value < low:
            kind = "a positive" if low else "a non-negative"
            raise ConfigError(f"MbMfPhase.{name} must be {kind} integer, got {value!r}.")
    if not 0.0 < phase.mpc_discount <= 1.0:
        raise ConfigError(f"MbMfPhase.mpc_discount must lie in (0, 1], got {phase.mpc_discount!r}.")
    if phase.model_objective not in ("mse", "nll"):
        raise ConfigError(f"Unknown MbMfPhase.model_objective {phase.model_objective!r}; choose mse or nll.")
    B = phase.envs(config)
    biggest = B * max(phase.random_steps, phase.mpc_steps_per_iter)
    if phase.model_capacity(config) < biggest:
        raise ConfigError(f"MbMfPhase.buffer_size={phase.buffer_size} cannot hold one stage's {biggest} transitions.")
    biggest = B * max(phase.mpc_steps_per_iter, phase.distill_steps_per_iter)
    if phase.distill_capacity(config) < biggest:
        raise ConfigError(
            f"MbMfPhase.distill_buffer_size={phase.distill_buffer_size} cannot hold one stage's {biggest} labelled states.")


# ----------------------------------------------------------------------------------------------------
# Data.
# ----------------------------------------------------------------------------------------------------


@struct.dataclass
class Rollout:
    """One stage of acting in the phase's environments; leaves time-major [L, B, ...]."""

    obs: jax.Array  # [L, B, O] observation acted on
    action: jax.Array  # [L, B, A] executed action
    label: jax.Array  # [L, B, A] the MPC's action at obs (distillation target; = action when MPC acts)
    next_obs: jax.Array  # [L, B, O] true observation after the action (before any reset)
    reward: jax.Array  # [L, B]
    terminated: jax.Array  # [L, B] bool
    ended: jax.Array  # [L, B] bool: terminated, timed out or invalid
    valid: jax.Array  # [L, B] bool


def _flat(x: jax.Array) -> jax.Array:
    """[L, B, ...] -> [L * B, ...]."""
    return x.reshape((-1,) + x.shape[2:])


@struct.dataclass
class Transitions:
    """Model data; leaves [N, ...]."""

    obs: jax.Array
    action: jax.Array
    next_obs: jax.Array
    reward: jax.Array
    valid: jax.Array

    @classmethod
    def of(cls, traj: Rollout) -> "Transitions":
        return cls(*map(_flat, (traj.obs, traj.action, traj.next_obs, traj.reward, traj.valid)))


@struct.dataclass
class Labelled:
    """Distillation data: visited states and the MPC's action there; leaves [N, ...]."""

    obs: jax.Array
    action: jax.Array
    valid: jax.Array

    @classmethod
    def of(cls, traj: Rollout) -> "Labelled":
        return cls(*map(_flat, (traj.obs, traj.label, traj.valid)))


@struct.dataclass
class RingBuffer:
    """A fixed-size dataset (static shapes): `data` leaves [N, ...], the oldest items overwritten first.

    Slots never written hold zeros with valid=False (every item type here has a `valid` field).
    """

    data: Any  # pytree with leaves [N, ...]
    count: jax.Array  # [] int32 items ever added

    @classmethod
    def create(cls, example: Any, size: int) -> "RingBuffer":
        """`example`: one item (leaves without the leading axis) giving shapes and dtypes."""
        data = jax.tree.map(lambda x: jnp.zeros((size,) + jnp.shape(x), jnp.asarray(x).dtype), example)
        return cls(data, jnp.zeros((), jnp.int32))

    @property
    def size(self) -> int:
        return jax.tree.leaves(self.data)[0].shape[0]

    @property
    def filled(self) -> jax.Array:
        return jnp.minimum(self.count, self.size)

    def add(self, items: Any) -> "RingBuffer":
        n = jax.tree.leaves(items)[0].shape[0]
        assert n <= self.size, (n, self.size)
        idx = (self.count + jnp.arange(n)) % self.size
        data = jax.tree.map(lambda d, x: d.at[idx].set(x.astype(d.dtype)), self.data, items)
        return RingBuffer(data, self.count + n)


def fit(loss_fn: Callable, params, opt_state, tx: optax.GradientTransformation, buffer: RingBuffer,
        epochs: int, minibatch: int, key: jax.Array):
    """`epochs` shuffled passes of minibatches over the filled part of `buffer`.

    loss_fn(params, batch) -> (loss, metrics); batch leaves [minibatch, ...]. An epoch is
    ceil(filled / minibatch) gradient steps (a traced trip count: the data grows between calls), the
    last minibatch wrapping around to the start of the permutation. Returns (params, opt_state, mean
    metrics of the last epoch).
    """
    size = buffer.size
    filled = buffer.filled
    n_steps = (filled + minibatch - 1) // minibatch
    take = lambda idx: jax.tree.map(lambda d: d[idx], buffer.data)  # noqa: E731
    shapes = jax.eval_shape(lambda p: loss_fn(p, take(jnp.arange(minibatch)))[1], params)
    zeros = jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype), shapes)

    def epoch(carry, key):
        params, opt_state = carry
        # A random permutation of the filled slots first, the empty slots after them.
        order = jnp.argsort(jnp.where(jnp.arange(size) < filled, jax.random.uniform(key, (size,)), 2.0))

        def step(i, inner):
            params, opt_state, acc = inner
            idx = order[(i * minibatch + jnp.arange(minibatch)) % jnp.maximum(filled, 1)]
            grads, metrics = jax.grad(loss_fn, has_aux=True)(params, take(idx))
            updates, opt_state = tx.update(grads, opt_state, params)
            return optax.apply_updates(params, updates), opt_state, jax.tree.map(jnp.add, acc, metrics)

        params, opt_state, acc = jax.lax.fori_loop(0, n_steps, step, (params, opt_state, zeros))
        mean = jax.tree.map(lambda a: a / jnp.maximum(n_steps, 1).astype(a.dtype), acc)
        return (params, opt_state), mean

    (params, opt_state), metrics = jax.lax.scan(epoch, (params, opt_state), jax.random.split(key, epochs))
    return params, opt_state, jax.tree.map(lambda m: m[-1], metrics)


def model_objective(pred_mean, pred_log_std, target, mask, kind: ModelObjective):
    """The model's training loss on normalised (delta-s, reward) targets [..., O+1] -> (loss, metrics).

    nll: the Gaussian NLL of losses.model_loss. Its per-dimension weights are 1/sigma^2, so the model
         spends its capacity on the dimensions it already predicts well (the state deltas, whose sigma
         reaches the floor) and starves the reward, which the MPC needs most.
    mse: the mean by the squared error summed over dimensions (Nagabandi et al.: MSE), every dimension
         weighted alike; log_std by the NLL at the stopped mean, so it is calibrated for the NLL that
         the PPO phase goes on training with.
    """
    if kind == "nll":
        return losses.model_loss(pred_mean, pred_log_std, target, mask)
    nll, metrics = losses.model_loss(jax.lax.stop_gradient(pred_mean), pred_log_std, target, mask)
    mse = losses.masked_mean(((target - pred_mean) ** 2).sum(-1), mask)
    metrics["loss/model_mse"] = mse
    return mse + nll, metrics


def _first_last(values: jax.Array) -> tuple[jax.Array, jax.Array]:
    """First and last entries of a per-round metric [R] (NaN when there were no rounds)."""
    if values.shape[0] == 0:
        nan = jnp.full((), jnp.nan, jnp.float32)
        return nan, nan
    return values[0], values[-1]


def _episode_return(stats: EpisodeStats) -> jax.Array:
    """Mean return of the episodes finished during the last stage (NaN if none)."""
    return jnp.where(stats.done_count > 0, stats.done_ret / jnp.maximum(stats.done_count, 1.0), jnp.nan)


# ----------------------------------------------------------------------------------------------------
# The phase.
# ----------------------------------------------------------------------------------------------------


def phase_env(config: Config, phase: MbMfPhase, trainer: Trainer) -> BatchedEnv:
    """The environments the phase acts in: the trainer's when the sizes agree, else a new BatchedEnv."""
    B = phase.envs(config)
    if B == config.num_envs:
        return trainer.env
    return BatchedEnv(make_single_env(config.env), B, config.episode_length, config.action_repeat,
                      config.reset_mode)


def make_mpc_controller(trainer: Trainer, phase: MbMfPhase) -> Callable:
    """controller(model_params, norms, obs [B, O], key) -> MPC actions [B, A] on the learned model."""
    A = trainer.env.action_size

    def controller(model_params, norms, obs, key):
        step_fn = lambda s, a: trainer.model_step(model_params, norms, s, a)  # noqa: E731  [O], [A] -> [O], []
        actions, _ = mpc.batched_random_shooting(key, step_fn, obs, horizon=phase.mpc_horizon,
                                                 num_candidates=phase.mpc_candidates, action_size=A,
                                                 discount=phase.mpc_discount)
        return actions

    return controller


def make_mbmf_phase(config: Config, phase: MbMfPhase, trainer: Trainer | None = None
                    ) -> Callable[[TrainState, HParams], tuple[TrainState, dict]]:
    """run(state, hp) -> (state ready for PPO, info dict of scalars); pure, jit (and vmap) it yourself.

    `state` is what trainer.init returns (or any TrainState of `config`); params["model"] and
    params["policy"] come back trained, params["value"] fitted (value_epochs > 0), norms updated, the PPO
    environments reset, episode statistics fresh, opt_state and the encoder untouched.
    info["env_steps"] (int32) counts the env steps the phase took: charge them to the arm's budget.
    """
    validate_phase(config, phase)
    trainer = trainer if trainer is not None else make_trainer(config)
    env = phase_env(config, phase, trainer)
    B, O, A = env.num_envs, env.observation_size, env.action_size
    modules = networks.build(config, O, A)
    model, policy, value = modules["model"], modules["policy"], modules["value"]
    controller = make_mpc_controller(trainer, phase)
    steps_per_call = B * config.action_repeat

    def rollout(carry, choose: Callable, key: jax.Array, length: int, gamma):
        """`length` steps of choose(obs [B, O], key) -> (action, label), both [B, A].

        carry: (env_state, episode stats, env-step counter). Returns (carry, Rollout [length, B, ...]).
        """
        env_state, stats, counter = carry

        def step(inner, step_key):
            env_state, stats, counter = inner
            obs = env_state.obs
            action, label = choose(obs, step_key)
            env_state, out = env.step(env_state, action)
            ended = out.terminated | out.truncated | ~out.valid
            stats = stats.record(out.reward, ended, out.terminated | out.truncated, gamma)
            tr = Rollout(obs=obs, action=action, label=label, next_obs=out.next_obs, reward=out.reward,
                         terminated=out.terminated, ended=ended, valid=out.valid)
            return (env_state, stats, counter + steps_per_call), tr

        return jax.lax.scan(step, (env_state, stats.start_rollout(), counter), jax.random.split(key, length))

    def update_norms(norms: nz.Norms, data: Transitions) -> nz.Norms:
        return nz.Norms(obs=nz.update(norms.obs, data.obs, data.valid),
                        delta=nz.update(norms.delta, data.next_obs - data.obs, data.valid),
                        reward=nz.update(norms.reward, data.reward[..., None], data.valid))

    def model_batch_loss(model_params, norms, batch: Transitions):
        mean, log_std = model.apply(model_params, nz.normalize(norms.obs, batch.obs), batch.action)
        target = jnp.concatenate([nz.normalize(norms.delta, batch.next_obs - batch.obs),
                                  nz.normalize(norms.reward, batch.reward[..., None])], axis=-1)
        return model_objective(mean, log_std, target, batch.valid, phase.model_objective)

    def distill_loss(policy_params, norms, batch: Labelled):
        mean, _ = policy.apply(policy_params, nz.normalize(norms.obs, batch.obs))
        err = networks.squash(mean) - batch.action
        mse = losses.masked_mean((err**2).mean(-1), batch.valid)
        return mse, {"distill/mse": mse, "distill/abs_error": losses.masked_mean(jnp.abs(err).mean(-1), batch.valid)}

    def buffer_abs_error(policy_params, norms, buffer: RingBuffer) -> jax.Array:
        """Mean |tanh(mu(s)) - a_MPC| over the filled, valid part of the distillation buffer."""
        data = buffer.data
        data = data.replace(valid=data.valid & (jnp.arange(buffer.size) < buffer.filled))
        return distill_loss(policy_params, norms, data)[1]["distill/abs_error"]

    def relabel(model_params, norms, buffer: RingBuffer, key: jax.Array) -> RingBuffer:
        """Re-plan the actions of the aggregation states with the final model, `relabel_chunk` states at once.

        The MPC that acted during aggregation round i planned with the model of round i; relabelling makes
        every cloning target come from one controller, the one the DAgger rounds query.
        """
        n = min(buffer.size, B * phase.aggregation_iters * phase.mpc_steps_per_iter)  # the filled slots
        chunk = min(phase.relabel_chunk, n)
        n_chunks = -(-n // chunk)
        obs = jnp.zeros((n_chunks * chunk, O), jnp.float32).at[:n].set(buffer.data.obs[:n])
        keys = jax.random.split(key, n_chunks)
        plan = lambda inp: controller(model_params, norms, inp[0], inp[1])  # noqa: E731
        labels = jax.lax.map(plan, (obs.reshape(n_chunks, chunk, O), keys)).reshape(-1, A)[:n]
        return buffer.replace(data=buffer.data.replace(action=buffer.data.action.at[:n].set(labels)))

    def fit_value(value_params, norms, traj: Rollout, hp: HParams, key: jax.Array):
        """Regress V on TD(lambda) returns of traj [L, N] (recomputed with the current V every epoch)."""
        L, N = traj.reward.shape
        obs_n, next_n = nz.normalize(norms.obs, traj.obs), nz.normalize(norms.obs, traj.next_obs)
        mb = min(phase.distill_minibatch, L * N)
        n_mb = (L * N) // mb
        tx = optax.chain(optax.clip_by_global_norm(hp.max_grad_norm), optax.adam(hp.lr_value, eps=1e-5))
        flat = lambda x: x.reshape((L * N,) + x.shape[2:])  # noqa: E731

        def loss_fn(vp, batch):
            obs, target, valid = batch
            loss = 0.5 * losses.masked_mean((value.apply(vp, obs) - target) ** 2, valid)
            return loss, loss

        def epoch(carry, key):
            vp, opt_state = carry
            _, returns = losses.gae(traj.reward * hp.reward_scale, value.apply(vp, obs_n), value.apply(vp, next_n),
                                    traj.valid & ~traj.terminated, traj.ended, hp.gamma, hp.gae_lambda)
            perm = jax.random.permutation(key, L * N)[: n_mb * mb].reshape(n_mb, mb)
            data = (flat(obs_n), flat(jax.lax.stop_gradient(returns)), flat(traj.valid))

            def step(inner, idx):
                vp, opt_state = inner
                grads, loss = jax.grad(loss_fn, has_aux=True)(vp, jax.tree.map(lambda d: d[idx], data))
                updates, opt_state = tx.update(grads, opt_state, vp)
                return (optax.apply_updates(vp, updates), opt_state), loss

            (vp, opt_state), loss = jax.lax.scan(step, (vp, opt_state), perm)
            return (vp, opt_state), loss.mean()

        (value_params, _), loss = jax.lax.scan(epoch, (value_params, tx.init(value_params)),
                                               jax.random.split(key, phase.value_epochs))
        return value_params, loss[-1]

    def run(state: TrainState, hp: HParams) -> tuple[TrainState, dict]:
        hp = hp.as_float32()
        (key, key_reset, key_random, key_model, key_agg, key_relabel, key_distill, key_dagger, key_value,
         key_final) = jax.random.split(state.key, 10)
        model_tx = optax.chain(optax.clip_by_global_norm(hp.max_grad_norm), optax.adam(hp.lr_model, eps=1e-5))
        policy_tx = optax.chain(optax.clip_by_global_norm(hp.max_grad_norm), optax.adam(hp.lr_distill, eps=1e-5))
        model_params, policy_params = state.params["model"], state.params["policy"]
        model_opt, policy_opt = model_tx.init(model_params), policy_tx.init(policy_params)
        carry = (env.reset(key_reset), EpisodeStats.create(B), jnp.zeros((), jnp.int32))
        info = {}

        # 1. Uniform random actions.
        def uniform(obs, key):
            action = jax.random.uniform(key, (B, A), minval=-1.0, maxval=1.0)
            return action, action

        carry, traj = rollout(carry, uniform, key_random, phase.random_steps, hp.gamma)
        info["random/reward_mean"] = losses.masked_mean(traj.reward, traj.valid)
        info["random/episode_return"] = _episode_return(carry[1])
        data = Transitions.of(traj)
        norms = update_norms(state.norms, data)
        model_buffer = RingBuffer.create(jax.tree.map(lambda x: x[0], data), phase.model_capacity(config)).add(data)
        distill_buffer = RingBuffer.create(
            Labelled(jnp.zeros((O,), jnp.float32), jnp.zeros((A,), jnp.float32), jnp.zeros((), bool)),
            phase.distill_capacity(config))

        # 2. The first model.
        model_loss = lambda p, batch, norms: model_batch_loss(p, norms, batch)  # noqa: E731
        model_params, model_opt, fit_metrics = fit(functools.partial(model_loss, norms=norms), model_params,
                                                   model_opt, model_tx, model_buffer, phase.model_epochs,
                                                   phase.model_minibatch, key_model)

        # 3. Aggregation: MPC on the model acts, its data is appended, the model retrained.
        def aggregate(agg_carry, key):
            carry, model_params, model_opt, norms, model_buffer, distill_buffer, fit_metrics = agg_carry
            key_roll, key_fit = jax.random.split(key)

            def plan(obs, key):
                action = controller(model_params, norms, obs, key)
                return action, action

            carry, traj = rollout(carry, plan, key_roll, phase.mpc_steps_per_iter, hp.gamma)
            data = Transitions.of(traj)
            _, heldout = model_batch_loss(model_params, norms, data)  # fresh on-policy data, not trained on yet
            norms = update_norms(norms, data)
            model_buffer = model_buffer.add(data)
            distill_buffer = distill_buffer.add(Labelled.of(traj))
            model_params, model_opt, fit_metrics = fit(functools.partial(model_loss, norms=norms), model_params,
                                                       model_opt, model_tx, model_buffer, phase.model_epochs,
                                                       phase.model_minibatch, key_fit)
            metrics = {"reward_mean": losses.masked_mean(traj.reward, traj.valid),
                       "episode_return": _episode_return(carry[1]),
                       "heldout_mse": heldout["model/onestep_mse"],
                       "heldout_reward_mse": heldout["model/reward_mse"]}
            return (carry, model_params, model_opt, norms, model_buffer, distill_buffer, fit_metrics), metrics

        agg_carry = (carry, model_params, model_opt, norms, model_buffer, distill_buffer, fit_metrics)
        agg_carry, agg = jax.lax.scan(aggregate, agg_carry, jax.random.split(key_agg, phase.aggregation_iters))
        carry, model_params, _, norms, _, distill_buffer, fit_metrics = agg_carry
        info["mpc/reward_mean_first"], info["mpc/reward_mean_last"] = _first_last(agg["reward_mean"])
        info["mpc/episode_return"] = _first_last(agg["episode_return"])[1]
        info["model/heldout_mse_first"], info["model/heldout_mse_last"] = _first_last(agg["heldout_mse"])
        info["model/heldout_reward_mse_last"] = _first_last(agg["heldout_reward_mse"])[1]
        info["model/train_mse"] = fit_metrics["model/onestep_mse"]
        info["model/train_reward_mse"] = fit_metrics["model/reward_mse"]
        info["model/train_nll"] = fit_metrics["loss/model_nll"]

        # 4. Distillation: behaviour cloning on the MPC's data, then DAgger rounds.
        if phase.relabel and phase.aggregation_iters > 0:
            distill_buffer = relabel(model_params, norms, distill_buffer, key_relabel)
        bc_loss = functools.partial(lambda p, batch, norms: distill_loss(p, norms, batch), norms=norms)
        info["distill/abs_error_before"] = buffer_abs_error(policy_params, norms, distill_buffer)
        policy_params, policy_opt, _ = fit(bc_loss, policy_params, policy_opt, policy_tx, distill_buffer,
                                           phase.distill_epochs, phase.distill_minibatch, key_distill)

        def dagger(dagger_carry, key):
            carry, policy_params, policy_opt, distill_buffer = dagger_carry
            key_roll, key_fit = jax.random.split(key)

            def act_and_label(obs, key):
                key_act, key_plan = jax.random.split(key)
                action = trainer.act({"policy": policy_params}, norms, obs, key_act)
                return action, controller(model_params, norms, obs, key_plan)

            carry, traj = rollout(carry, act_and_label, key_roll, phase.distill_steps_per_iter, hp.gamma)
            labelled = Labelled.of(traj)
            _, new_error = distill_loss(policy_params, norms, labelled)  # the policy's own states, before training
            distill_buffer = distill_buffer.add(labelled)
            policy_params, policy_opt, _ = fit(bc_loss, policy_params, policy_opt, policy_tx, distill_buffer,
                                               phase.distill_epochs, phase.distill_minibatch, key_fit)
            metrics = {"reward_mean": losses.masked_mean(traj.reward, traj.valid),
                       "episode_return": _episode_return(carry[1]),
                       "abs_error_new": new_error["distill/abs_error"]}
            return (carry, policy_params, policy_opt, distill_buffer), (metrics, traj)

        dagger_carry = (carry, policy_params, policy_opt, distill_buffer)
        dagger_carry, (dag, trajs) = jax.lax.scan(dagger, dagger_carry,
                                                  jax.random.split(key_dagger, phase.distill_iters))
        carry, policy_params, _, distill_buffer = dagger_carry
        info["distill/abs_error"] = buffer_abs_error(policy_params, norms, distill_buffer)
        info["dagger/abs_error_new_first"], info["dagger/abs_error_new_last"] = _first_last(dag["abs_error_new"])
        info["dagger/reward_mean_first"], info["dagger/reward_mean_last"] = _first_last(dag["reward_mean"])
        info["dagger/episode_return"] = _first_last(dag["episode_return"])[1]

        # 5. The value on the DAgger rollouts ([R, L, B] -> [L, R*B]: each round a separate segment).
        value_params = state.params["value"]
        if phase.value_epochs > 0 and phase.distill_iters > 0:
            segments = jax.tree.map(lambda x: jnp.swapaxes(x, 0, 1).reshape((x.shape[1], -1) + x.shape[3:]), trajs)
            value_params, info["value/loss"] = fit_value(value_params, norms, segments, hp, key_value)
        else:
            info["value/loss"] = jnp.full((), jnp.nan, jnp.float32)

        info["env_steps"] = carry[2]
        params = dict(state.params, model=model_params, policy=policy_params, value=value_params)
        new_state = state.replace(params=params, norms=norms, env_state=trainer.env.reset(key_final),
                                  episodes=EpisodeStats.create(config.num_envs), key=key)
        return strong_types(new_state), info

    return run


__all__ = ["MbMfPhase", "RingBuffer", "fit", "make_mbmf_phase", "make_mpc_controller", "total_env_steps",
           "validate_phase"]
