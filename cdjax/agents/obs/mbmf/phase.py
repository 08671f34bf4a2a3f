"""The model-based phase of the hybrid Mb-Mf (Nagabandi et al., 2017), as one pure function.

`make_mbmf_phase(config, phase) -> run(state, hp) -> (state, info)`; the caller jits `run` (it compiles
once; it also vmaps over seeds). In the phase's own `phase.num_envs` environments:

1. random data: `random_steps` steps per env of uniform actions in [-1, 1];
2. model: params["model"] (Gaussian over the normalised delta-s and reward) trained with Adam(hp.lr_model),
   `model_epochs` shuffled epochs of minibatches over a ring buffer of real transitions (objective:
   `model_objective` below; with `onpolicy_fraction` > 0 that share of every minibatch comes from the MPC
   data once there is some, as Nagabandi et al.'s `fraction_use_new`); the running statistics
   (state.norms) are updated from the new data first;
3. aggregation, `aggregation_iters` times: random-shooting MPC (`mpc`) on the learned model acts for
   `mpc_steps_per_iter` steps, its transitions are appended to the buffer, the model is retrained. The
   candidates are scored by the model's reward or, `mpc_reward="true"`, by the task's reward of the predicted
   observations (cdjax.envs.rewards); the MPC acts with the best candidate's first action or the mean first
   action of its `mpc_elites` best;
4. distillation: the aggregation states are re-planned with the final model (`relabel`), the policy's
   deterministic action tanh(mu(s)) is regressed (MSE) on those MPC actions, then `distill_iters` DAgger
   rounds: the policy acts (sampling, or with its mean action: `dagger_deterministic`), MPC labels the
   states it visits, the pairs are aggregated, the policy is retrained; `label_checks` then measures on the
   policy's states how noisy the labels are and how close the policy came to their mean;
5. the value is fitted to TD(lambda) returns of the DAgger rollouts (`value_epochs`, optional), and the
   TrainState goes back ready for `agent.update`: with the distilled policy (or, `hand_policy=False`, the initial
   one: an ablation that keeps only the phase's model, normalisation and value), its PPO environments and their
   episode statistics as they were (the phase acts in its own), PPO's optimiser state untouched (fresh Adam
   moments) and `info["env_steps"]` counting every env step taken.

Why MSE on tanh(mu) rather than the Gaussian likelihood of atanh(action): random-shooting actions are
uniform samples, often near the box edge where atanh is ill-conditioned (a 0.999 label is 3.8 in
pre-squash space and dominates the loss), and the likelihood would also fit log_std to the scatter of
the controller's noisy labels. The MSE fits the action the policy executes at zero noise (as in
Nagabandi et al.'s code) and leaves log_std at hp.init_log_std for PPO's exploration.

Normalisation: the statistics are updated from the random and MPC data only (each time before the model
is retrained), and frozen during distillation, so that the model the MPC labels come from and the
policy being distilled see the same normalisation as at the end of the phase.

The program is a factory (`make_mbmf_phase`) whose closures are its stages; each stage is a function of
named state (`Acting`, `Fitted`, `ModelStage`, `PolicyStage`) and stays under ~80 lines.
"""

from __future__ import annotations

import functools
from typing import Any, Callable

import jax
import jax.numpy as jnp
import optax
from flax import struct

from cdjax import normalize as nz
from cdjax.agents.obs import losses, mpc, networks
from cdjax.agents.obs.learner import ObsAgent, TrainState, make_agent, model_target, refresh_norms
from cdjax.agents.obs.config import Config, HParams
from cdjax.agents.obs.mbmf.data import Labelled, Rollout, Transitions, model_objective
from cdjax.agents.obs.mbmf.spec import HANDOVER_CHECKS, MbMfPhase, validate_phase
from cdjax.agents.obs.rollout import env_step
from cdjax.envs import BatchedEnv, EnvState, EpisodeStats, batched, rewards, strong_types
from cdjax.numerics import masked_mean
from cdjax.optim import clipped_adam
from cdjax.replay import RingBuffer, fit


LABEL_CHECK_STATES = 64  # states of the distilled policy on which the labels' noise is measured (label_checks)
LABEL_DRAWS = 4  # independent MPC labels per such state


def _first_last(values: jax.Array) -> tuple[jax.Array, jax.Array]:
    """First and last entries of a per-round metric [R] (NaN when there were no rounds)."""
    if values.shape[0] == 0:
        nan = jnp.full((), jnp.nan, jnp.float32)
        return nan, nan
    return values[0], values[-1]


# ----------------------------------------------------------------------------------------------------
# The phase's state between stages.
# ----------------------------------------------------------------------------------------------------


@struct.dataclass
class Acting:
    """The phase's environments: their state, the running episode statistics, the env steps taken."""

    env_state: EnvState
    stats: EpisodeStats
    env_steps: jax.Array  # [] int32 (physics steps: x action_repeat)


@struct.dataclass
class Fitted:
    """A network being fitted: its parameters and its optimiser's state."""

    params: Any
    opt_state: Any


@struct.dataclass
class ModelStage:
    """What the aggregation rounds carry: acting, the model, the statistics and both datasets."""

    acting: Acting
    model: Fitted
    norms: nz.Norms
    transitions: RingBuffer  # of Transitions: the model's data
    labelled: RingBuffer  # of Labelled: (state, MPC action) pairs for the distillation
    fit_metrics: dict  # the last model fit's metrics


@struct.dataclass
class PolicyStage:
    """What the DAgger rounds carry: acting, the policy being distilled and its dataset."""

    acting: Acting
    policy: Fitted
    labelled: RingBuffer


# ----------------------------------------------------------------------------------------------------
# The phase.
# ----------------------------------------------------------------------------------------------------


def phase_env(config: Config, phase: MbMfPhase, agent: ObsAgent) -> BatchedEnv:
    """The environments the phase acts in: the agent's when the sizes agree, else a new BatchedEnv."""
    B = phase.envs(config)
    if B == config.num_envs and not agent.env.stagger:  # the phase's episode statistics count every episode
        return agent.env
    return batched(config.env, B, config.episode_length, config.action_repeat, config.reset_mode)


def make_mpc_controller(agent: ObsAgent, phase: MbMfPhase) -> Callable:
    """controller(model_params, norms, obs [B, O], key) -> MPC actions [B, A] on the learned model.

    Candidates are scored by the model's predicted reward (`mpc_reward="model"`) or by the task's reward of
    the predicted observations (`"true"`, cdjax.envs.rewards); the action is the best candidate's first one,
    or the mean first action of the `mpc_elites` best.
    """
    A = agent.env.action_size
    true_reward = rewards.reward_fn(agent.config.env) if phase.mpc_reward == "true" else None
    repeat = agent.config.action_repeat

    def controller(model_params, norms, obs, key):
        def step_fn(s, a):  # [O], [A] -> [O], []
            next_s, reward = agent.model_step(model_params, norms, s, a)
            if true_reward is not None:
                reward = true_reward(s, a, next_s, repeat)
            return next_s, reward

        actions, _ = mpc.batched_random_shooting(key, step_fn, obs, horizon=phase.mpc_horizon,
                                                 num_candidates=phase.mpc_candidates, action_size=A,
                                                 discount=phase.mpc_discount, num_elites=phase.mpc_elites)
        return actions

    return controller


class MbMfProgram:
    """The phase of one Config and MbMfPhase: its environments, networks, controller and stages.

    Not a pytree: close over its bound methods. `run(state, hp)` is the whole phase.
    """

    def __init__(self, config: Config, phase: MbMfPhase, agent: ObsAgent | None = None):
        validate_phase(config, phase)
        self.config, self.phase = config, phase
        self.agent = agent if agent is not None else make_agent(config)
        self.env = phase_env(config, phase, self.agent)
        self.B, self.O, self.A = self.env.num_envs, self.env.observation_size, self.env.action_size
        self.modules = networks.build(config, self.O, self.A)
        self.model, self.policy, self.value = self.modules["model"], self.modules["policy"], self.modules["value"]
        self.controller = make_mpc_controller(self.agent, phase)

    def rollout(self, acting: Acting, choose: Callable, key: jax.Array, length: int, gamma) -> tuple[Acting, Rollout]:
        """`length` steps of choose(obs [B, O], key) -> (action, label), both [B, A]: (acting, Rollout [L, B])."""

        def step(acting: Acting, step_key):
            obs = acting.env_state.obs
            action, label = choose(obs, step_key)
            env_state, stats, out = env_step(self.env, acting.env_state, acting.stats, action, gamma)
            tr = Rollout(obs=obs, action=action, label=label, next_obs=out.next_obs, reward=out.reward,
                         terminated=out.terminated, ended=out.terminated | out.truncated | ~out.valid, valid=out.valid)
            return Acting(env_state, stats, acting.env_steps + self.B * self.config.action_repeat), tr

        start = acting.replace(stats=acting.stats.start_rollout())
        return jax.lax.scan(step, start, jax.random.split(key, length))

    def dagger_action(self, policy_params, norms, obs: jax.Array, key: jax.Array) -> jax.Array:
        """The policy's action in a DAgger rollout [B, A]: its mean action tanh(mu) (`dagger_deterministic`) or a
        sample with its current noise."""
        return self.agent.act({"policy": policy_params}, norms, obs, None if self.phase.dagger_deterministic else key)

    def update_norms(self, norms: nz.Norms, data: Transitions) -> nz.Norms:
        return refresh_norms(norms, data.obs, data.next_obs, data.reward, data.valid)

    def model_batch_loss(self, model_params, batch: Transitions, norms):
        mean, log_std = self.model.apply(model_params, nz.normalize(norms.obs, batch.obs), batch.action)
        target = model_target(norms, batch.obs, batch.next_obs, batch.reward)
        return model_objective(mean, log_std, target, batch.valid, self.phase.model_objective)

    def distill_loss(self, policy_params, batch: Labelled, norms):
        mean, _ = self.policy.apply(policy_params, nz.normalize(norms.obs, batch.obs))
        err = networks.squash(mean) - batch.action
        mse = masked_mean((err**2).mean(-1), batch.valid)
        return mse, {"distill/mse": mse, "distill/abs_error": masked_mean(jnp.abs(err).mean(-1), batch.valid)}

    def buffer_abs_error(self, policy_params, norms, buffer: RingBuffer) -> jax.Array:
        """Mean |tanh(mu(s)) - a_MPC| over the filled, valid part of the distillation buffer."""
        data = buffer.data.replace(valid=buffer.data.valid & (jnp.arange(buffer.size) < buffer.filled))
        return self.distill_loss(policy_params, data, norms)[1]["distill/abs_error"]

    def fit_model(self, model_fit: Fitted, norms, data: RingBuffer, tx, key) -> tuple[Fitted, dict]:
        """Retrain the model on the buffer; with onpolicy_fraction > 0 that share of every minibatch comes from
        the MPC data, which follows the random data (its B x random_steps transitions) in the buffer."""
        loss = functools.partial(self.model_batch_loss, norms=norms)
        params, opt_state, metrics = fit(loss, model_fit.params, model_fit.opt_state, tx, data, self.phase.model_epochs,
                                         self.phase.model_minibatch, key, split=self.B * self.phase.random_steps,
                                         fraction=self.phase.onpolicy_fraction)
        return Fitted(params, opt_state), metrics

    def fit_policy(self, policy_fit: Fitted, norms, data: RingBuffer, tx, key) -> Fitted:
        loss = functools.partial(self.distill_loss, norms=norms)
        params, opt_state, _ = fit(loss, policy_fit.params, policy_fit.opt_state, tx, data, self.phase.distill_epochs,
                                   self.phase.distill_minibatch, key)
        return Fitted(params, opt_state)

    def relabel(self, model_params, norms, buffer: RingBuffer, key: jax.Array) -> RingBuffer:
        """Re-plan the actions of the aggregation states with the final model, `relabel_chunk` states at once.

        The MPC that acted during aggregation round i planned with the self.model of round i; relabelling makes
        every cloning target come from one self.controller, the one the DAgger rounds query.
        """
        n = min(buffer.size, self.B * self.phase.aggregation_iters * self.phase.mpc_steps_per_iter)  # the filled slots
        chunk = min(self.phase.relabel_chunk, n)
        n_chunks = -(-n // chunk)
        obs = jnp.zeros((n_chunks * chunk, self.O), jnp.float32).at[:n].set(buffer.data.obs[:n])
        keys = jax.random.split(key, n_chunks)
        plan = lambda inp: self.controller(model_params, norms, inp[0], inp[1])  # noqa: E731
        labels = jax.lax.map(plan, (obs.reshape(n_chunks, chunk, self.O), keys)).reshape(-1, self.A)[:n]
        return buffer.replace(data=buffer.data.replace(action=buffer.data.action.at[:n].set(labels)))

    def label_checks(self, policy_params, model_params, norms, states: jax.Array, key: jax.Array) -> dict:
        """How learnable the distillation targets are, on up to LABEL_CHECK_STATES of `states` [N, O].

        The MPC's label at a state is random (its candidates are), so a policy that regressed it perfectly
        would still differ from single labels. With LABEL_DRAWS independent labels per state:
        labels/self_error: |one label - the mean of the others|, what no policy can beat by much;
        labels/mean_abs: |mean label|, the size of what is there to learn;
        distill/abs_error_mean: |policy - mean label|, how close the policy came to it;
        distill/abs_error_zero: |0 - one label|, the error of the zero action (an untrained tanh policy's).
        All are means over states and action dimensions.
        """
        n = min(LABEL_CHECK_STATES, states.shape[0])
        obs = states[:: states.shape[0] // n][:n]  # spread over the rollout's steps and envs
        labels = jax.lax.map(lambda k: self.controller(model_params, norms, obs, k),
                             jax.random.split(key, LABEL_DRAWS))  # [D, n, A]
        mean = labels.mean(0)
        others = (labels.sum(0)[None] - labels) / (LABEL_DRAWS - 1)
        policy = self.agent.act({"policy": policy_params}, norms, obs, None)
        return {"labels/self_error": jnp.abs(labels - others).mean(),
                "labels/mean_abs": jnp.abs(mean).mean(),
                "distill/abs_error_mean": jnp.abs(policy - mean).mean(),
                "distill/abs_error_zero": jnp.abs(labels).mean()}

    def handover_checks(self, fresh_params, fresh_norms, policy_params, norms, hp: HParams, key: jax.Array):
        """What PPO starts from: the distilled policy against the untrained one (what the model-free arm starts
        from, with init's statistics), each sampling (as PPO's first rollout acts) and with its mean action,
        `handover_steps` steps from the same reset states and noise of the phase's environments -> (reward per step
        of each, env steps taken). The four rollouts are one scan, vmapped over them (one physics body to compile).
        """
        key_reset, key_act = jax.random.split(key)
        four = lambda a, b: jnp.stack([a, a, b, b])  # noqa: E731  distilled, distilled, untrained, untrained
        params = jax.tree.map(four, policy_params, fresh_params)
        stats_ = jax.tree.map(four, norms, fresh_norms)
        sample = jnp.array([True, False, True, False])

        def reward_per_step(params, stats_, sample):
            def act(obs, k):
                action = jnp.where(sample, self.agent.act({"policy": params}, stats_, obs, k),
                                   self.agent.act({"policy": params}, stats_, obs, None))
                return action, action

            acting = Acting(self.env.reset(key_reset), EpisodeStats.create(self.B), jnp.zeros((), jnp.int32))
            _, traj = self.rollout(acting, act, key_act, self.phase.handover_steps, hp.gamma)
            return masked_mean(traj.reward, traj.valid)

        rewards = jax.vmap(reward_per_step)(params, stats_, sample)
        names = ("handover/sampled", "handover/mean_action", "fresh/sampled", "fresh/mean_action")
        out = {f"{name}_reward_mean": rewards[i] for i, name in enumerate(names)}
        steps = HANDOVER_CHECKS * self.B * self.phase.handover_steps * self.config.action_repeat
        return out, jnp.asarray(steps, jnp.int32)

    def fit_value(self, value_params, norms, traj: Rollout, hp: HParams, key: jax.Array):
        """Regress V on TD(lambda) returns of traj [L, N] (recomputed with the current V every epoch)."""
        L, N = traj.reward.shape
        obs_n, next_n = nz.normalize(norms.obs, traj.obs), nz.normalize(norms.obs, traj.next_obs)
        mb = min(self.phase.distill_minibatch, L * N)
        n_mb = (L * N) // mb
        tx = clipped_adam(hp.lr_value, hp)
        flat = lambda x: x.reshape((L * N,) + x.shape[2:])  # noqa: E731

        def loss_fn(vp, batch):
            obs, target, valid = batch
            loss = 0.5 * masked_mean((self.value.apply(vp, obs) - target) ** 2, valid)
            return loss, loss

        def epoch(carry, key):
            vp, opt_state = carry
            v, v_next = self.value.apply(vp, obs_n), self.value.apply(vp, next_n)
            _, returns = losses.gae(traj.reward * hp.reward_scale, v, v_next,
                                    traj.valid & ~traj.terminated, traj.ended, hp.gamma, hp.gae_lambda, traj.valid)
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
                                               jax.random.split(key, self.phase.value_epochs))
        return value_params, loss[-1]

    def models_stage(self, state: TrainState, hp: HParams, model_tx, keys) -> tuple[ModelStage, dict]:
        """Steps 1-3: random data, the first model, then the MPC aggregation rounds."""
        key_reset, key_random, key_model, key_agg = keys
        info = {}

        def uniform(obs, key):
            action = jax.random.uniform(key, (self.B, self.A), minval=-1.0, maxval=1.0)
            return action, action

        acting = Acting(self.env.reset(key_reset), EpisodeStats.create(self.B), jnp.zeros((), jnp.int32))
        acting, traj = self.rollout(acting, uniform, key_random, self.phase.random_steps, hp.gamma)
        info["random/reward_mean"] = masked_mean(traj.reward, traj.valid)
        info["random/episode_return"] = acting.stats.mean_returns()[0]
        data = Transitions.of(traj)
        norms = self.update_norms(state.norms, data)
        capacity = self.phase.model_capacity(self.config)
        transitions = RingBuffer.create(jax.tree.map(lambda x: x[0], data), capacity).add(data)
        labelled = RingBuffer.create(
            Labelled(jnp.zeros((self.O,), jnp.float32), jnp.zeros((self.A,), jnp.float32), jnp.zeros((), bool)),
            self.phase.distill_capacity(self.config))
        model_params = state.params["model"]
        model_fit, fit_metrics = self.fit_model(Fitted(model_params, model_tx.init(model_params)), norms, transitions,
                                           model_tx, key_model)

        def aggregate(stage: ModelStage, key):
            key_roll, key_fit = jax.random.split(key)

            def plan(obs, key):
                action = self.controller(stage.model.params, stage.norms, obs, key)
                return action, action

            acting, traj = self.rollout(stage.acting, plan, key_roll, self.phase.mpc_steps_per_iter, hp.gamma)
            data = Transitions.of(traj)
            # fresh on-policy data, not trained on yet
            _, heldout = self.model_batch_loss(stage.model.params, data, stage.norms)
            norms = self.update_norms(stage.norms, data)
            transitions = stage.transitions.add(data)
            model_fit, fit_metrics = self.fit_model(stage.model, norms, transitions, model_tx, key_fit)
            metrics = {"reward_mean": masked_mean(traj.reward, traj.valid),
                       "episode_return": acting.stats.mean_returns()[0],
                       "heldout_mse": heldout["model/onestep_mse"],
                       "heldout_reward_mse": heldout["model/reward_mse"]}
            return ModelStage(acting, model_fit, norms, transitions, stage.labelled.add(Labelled.of(traj)),
                              fit_metrics), metrics

        stage = ModelStage(acting, model_fit, norms, transitions, labelled, fit_metrics)
        stage, agg = jax.lax.scan(aggregate, stage, jax.random.split(key_agg, self.phase.aggregation_iters))
        info["mpc/reward_mean_first"], info["mpc/reward_mean_last"] = _first_last(agg["reward_mean"])
        info["mpc/episode_return"] = _first_last(agg["episode_return"])[1]
        info["model/heldout_mse_first"], info["model/heldout_mse_last"] = _first_last(agg["heldout_mse"])
        info["model/heldout_reward_mse_last"] = _first_last(agg["heldout_reward_mse"])[1]
        info["model/train_mse"] = stage.fit_metrics["model/onestep_mse"]
        info["model/train_reward_mse"] = stage.fit_metrics["model/reward_mse"]
        info["model/train_nll"] = stage.fit_metrics["loss/model_nll"]
        return stage, info

    def policy_stage(self, state: TrainState, stage: ModelStage, hp: HParams, keys
                     ) -> tuple[PolicyStage, Rollout, dict]:
        """Step 4: behaviour cloning of the (relabelled) MPC actions, then the DAgger rounds."""
        key_relabel, key_distill, key_dagger, key_check = keys
        model_params, norms = stage.model.params, stage.norms
        policy_tx = clipped_adam(hp.lr_distill, hp)
        labelled = stage.labelled
        if self.phase.relabel and self.phase.aggregation_iters > 0:
            labelled = self.relabel(model_params, norms, labelled, key_relabel)
        info = {"distill/abs_error_before": self.buffer_abs_error(state.params["policy"], norms, labelled)}
        policy_params = state.params["policy"]
        policy_fit = self.fit_policy(Fitted(policy_params, policy_tx.init(policy_params)), norms, labelled, policy_tx,
                                key_distill)

        def dagger(stage: PolicyStage, key):
            key_roll, key_fit = jax.random.split(key)

            def act_and_label(obs, key):
                key_act, key_plan = jax.random.split(key)
                action = self.dagger_action(stage.policy.params, norms, obs, key_act)
                return action, self.controller(model_params, norms, obs, key_plan)

            acting, traj = self.rollout(stage.acting, act_and_label, key_roll, self.phase.distill_steps_per_iter,
                                        hp.gamma)
            new = Labelled.of(traj)
            _, new_error = self.distill_loss(stage.policy.params, new, norms)  # the policy's own states, untrained on
            labelled = stage.labelled.add(new)
            policy_fit = self.fit_policy(stage.policy, norms, labelled, policy_tx, key_fit)
            metrics = {"reward_mean": masked_mean(traj.reward, traj.valid),
                       "episode_return": acting.stats.mean_returns()[0],
                       "abs_error_new": new_error["distill/abs_error"]}
            return PolicyStage(acting, policy_fit, labelled), (metrics, traj)

        stage = PolicyStage(stage.acting, policy_fit, labelled)
        stage, (dag, trajs) = jax.lax.scan(dagger, stage, jax.random.split(key_dagger, self.phase.distill_iters))
        info["distill/abs_error"] = self.buffer_abs_error(stage.policy.params, norms, stage.labelled)
        # the states the distilled policy visits (last DAgger round), else the first labelled ones
        states = trajs.obs[-1].reshape(-1, self.O) if self.phase.distill_iters else stage.labelled.data.obs
        info.update(self.label_checks(stage.policy.params, model_params, norms, states, key_check))
        info["dagger/abs_error_new_first"], info["dagger/abs_error_new_last"] = _first_last(dag["abs_error_new"])
        info["dagger/reward_mean_first"], info["dagger/reward_mean_last"] = _first_last(dag["reward_mean"])
        info["dagger/episode_return"] = _first_last(dag["episode_return"])[1]
        return stage, trajs, info

    def run(self, state: TrainState, hp: HParams) -> tuple[TrainState, dict]:
        hp = hp.as_float32()
        (key, key_reset, key_random, key_model, key_agg, key_relabel, key_distill, key_dagger, key_value,
         key_check, key_handover) = jax.random.split(state.key, 11)
        model_tx = clipped_adam(hp.lr_model, hp)
        models, info = self.models_stage(state, hp, model_tx, (key_reset, key_random, key_model, key_agg))
        policies, trajs, policy_info = self.policy_stage(state, models, hp,
                                                         (key_relabel, key_distill, key_dagger, key_check))
        info.update(policy_info)

        # 5. The value on the DAgger rollouts ([R, L, B] -> [L, R*B]: each round a separate segment).
        value_params = state.params["value"]
        if self.phase.value_epochs > 0 and self.phase.distill_iters > 0:
            segments = jax.tree.map(lambda x: jnp.swapaxes(x, 0, 1).reshape((x.shape[1], -1) + x.shape[3:]), trajs)
            value_params, info["value/loss"] = self.fit_value(value_params, models.norms, segments, hp, key_value)
        else:
            info["value/loss"] = jnp.full((), jnp.nan, jnp.float32)

        info["env_steps"] = policies.acting.env_steps
        if self.phase.handover_steps:
            checks, steps = self.handover_checks(state.params["policy"], state.norms, policies.policy.params,
                                                 models.norms, hp, key_handover)
            info.update(checks)
            info["env_steps"] = info["env_steps"] + steps
        policy_params = policies.policy.params if self.phase.hand_policy else state.params["policy"]
        params = dict(state.params, model=models.model.params, policy=policy_params, value=value_params)
        # The PPO environments are as init left them (the phase acted in its own): each keeps the reset target
        # it was created with, which a checkpoint therefore need not store.
        new_state = state.replace(params=params, norms=models.norms, env_state=state.env_state,
                                  episodes=state.episodes, key=key)
        return strong_types(new_state), info


def make_mbmf_phase(config: Config, phase: MbMfPhase, agent: ObsAgent | None = None
                    ) -> Callable[[TrainState, HParams], tuple[TrainState, dict]]:
    """run(state, hp) -> (state ready for PPO, info dict of scalars); pure, jit (and vmap) it yourself.

    `state` is what agent.init returns (or any TrainState of `config`); params["model"] and
    params["policy"] come back trained, params["value"] fitted (value_epochs > 0), norms updated, the PPO
    environments, their episode statistics (init's: fresh, staggered first episodes marked) and opt_state
    untouched (the phase acts in environments of its own, never staggered), the encoder untouched.
    With handover_steps > 0, info also holds the reward per step of the distilled and of the untrained policy,
    sampled and with their mean action, from the same reset states (`handover_checks`).
    info["env_steps"] (int32) counts the env steps the phase took: charge them to the arm's budget.
    """
    return MbMfProgram(config, phase, agent).run
