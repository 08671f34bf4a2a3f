"""The observation-space learner: make_agent(config) -> ObsAgent (init, update, ...); make_train(config) ->
train(key, hp); make_trainer(config) -> the protocol's Trainer.

One call of `update` is the whole consistent-dynamics step, compiled once: closed-loop rollout (scan over T steps
of B environments), GAE, then epochs x minibatches (scans) of PPO + model_coef * model NLL + alpha * consistency,
where the consistency term imagines k-step open-loop windows with the learned model from real start states, under
actions re-derived differentiably from the stored noise (so its gradient reaches the policy), encodes real and
imagined windows with one shared encoder, and averages the L2 distance over the windows inside one episode. Arms are switches of the same code: `model-free` builds no
model, `mbmf` trains the model without the consistency term, `cd` builds the consistency term with
weight `alpha` (alpha = 0 there still logs l_cc, without gradient).

The library never jits or vmaps a whole run: callers compose, e.g.
`jax.jit(jax.vmap(make_train(cfg), in_axes=(0, None)))(keys, hp)`.
"""

from __future__ import annotations

import functools
from typing import Callable

import jax
import jax.numpy as jnp
import optax
from jax.flatten_util import ravel_pytree

from cdjax import consistency, envs
from cdjax import normalize as nz
from cdjax.agents.obs import losses, networks, yardstick
from cdjax.agents.obs.config import HP_RANGES, Config, HParams
from cdjax.agents.obs.optim import make_optimizer
from cdjax.agents.obs.losses import SHARED_TERMS, TERM_GROUPS, model_target, term_weights
from cdjax.agents.obs.rollout import closed_loop, open_loop
from cdjax.agents.obs.state import Batch, History, TrainState, refresh_norms, saved_leaves, to_segments
from cdjax.checks import check_type
from cdjax.envs import EnvState, EpisodeStats, make_env, strong_types
from cdjax.numerics import masked_mean, masked_share
from cdjax.protocol import Trainer, scanned_train


def _norm(tree) -> jax.Array:
    """The global norm of a tree, taken on its leaves raveled into one vector (as the optimiser holds them)."""
    return optax.global_norm(ravel_pytree(tree)[0])


class ObsAgent:
    """The observation-space agent of one Config: its environments, networks and every piece of its update.

    Not a pytree (it holds modules and the env): close over its bound methods, which are pure functions of
    their arguments: `init(key, hp)`, `update(state, hp)`, `collect`, `loss`, `loss_terms`, `grad_norms`,
    `advantages`, `act(params, norms, obs, key)`, `model_step(model_params, norms, obs, action)`; `env` is
    its BatchedEnv.
    """

    def __init__(self, config: Config):
        check_type(config, Config)
        self.config = config
        self.env = make_env(config)
        self.O, self.A = self.env.observation_size, self.env.action_size
        self.T, self.L, self.k, self.M = config.rollout_len, config.segment, config.horizon, config.num_minibatches
        self.modules = networks.build(config, self.O, self.A)
        self.policy, self.value = self.modules["policy"], self.modules["value"]
        self.model = self.modules.get("model")
        self.encoder = self.modules.get("encoder")
        self.yardstick = None  # the windows of config.yardstick the model is scored on (cdjax/agents/obs/yardstick.py)
        if config.yardstick and self.model is not None:
            data = yardstick.load(config.yardstick)
            yardstick.check_matches(data, config.env, self.O, self.A, config.yardstick)
            self.yardstick = yardstick.Windows.of(data, self.k, config.eval_horizon)

    def model_step(self, model_params, norms, obs, action):
        mean, _ = self.model.apply(model_params, nz.normalize(norms.obs, obs), action)
        next_obs = obs + nz.denormalize(norms.delta, mean[..., :-1])
        reward = nz.denormalize(norms.reward, mean[..., -1:])[..., 0]
        return next_obs, reward

    def mlp_model(self, model_params, norms) -> consistency.MLPModel:
        """The dynamics model in the form the consistency term runs fused: its layers up to the mean head's
        state columns (`model_step`'s next state; the reward column and the log-std head are not used)."""
        p = model_params["params"]
        n = len(self.config.model_hidden)
        layers = [(p[f"Dense_{i}"]["kernel"], p[f"Dense_{i}"]["bias"]) for i in range(n)]
        layers.append((p[f"Dense_{n}"]["kernel"][:, :self.O], p[f"Dense_{n}"]["bias"][:self.O]))
        return consistency.MLPModel(layers=tuple(layers), obs=norms.obs, delta=norms.delta)

    def act(self, params, norms, obs, key):
        mean, std = self.policy.apply(params["policy"], nz.normalize(norms.obs, obs))
        if key is None:
            return networks.squash(mean)
        return networks.act_from_noise(mean, std, jax.random.normal(key, mean.shape))

    def init(self, key: jax.Array, hp: HParams) -> TrainState:
        return self.init_from(key, hp, self.reset(key))

    def reset(self, key: jax.Array) -> EnvState:
        """The environments of init(key, hp)'s state (they do not depend on hp)."""
        key_env, _, _ = jax.random.split(key, 3)
        return self.env.reset(key_env)

    def init_from(self, key: jax.Array, hp: HParams, env_state: EnvState) -> TrainState:
        """init(key, hp) given its environments, reset(key): a sweep compiles the physics of a reset once for all
        its arms that act in the same environments (`cdjax.protocol.Trainer.reset`)."""
        HP_RANGES.check(hp, one_run=True)  # concrete values (outside jit) get the command line's checks
        hp = hp.as_float32()
        _, key_params, key_train = jax.random.split(key, 3)
        params = networks.init_params(self.modules, key_params, self.O, self.A, hp.init_log_std)
        opt_state = make_optimizer(self.config, params, hp).init(params)
        nan = jnp.full((), jnp.nan, jnp.float32)
        state = TrainState(
            params=params, opt_state=opt_state, norms=nz.Norms.create(self.O), env_state=env_state,
            # a staggered env's first episode starts part-way into its time limit: its return is not logged
            episodes=EpisodeStats.create(self.config.num_envs, skip=env_state.t > 0),
            history=History.create(self.config.history_len - 1, self.config.eval_envs, self.O, self.A),
            last_return=nan, last_disc_return=nan, key=key_train, update_step=jnp.zeros((), jnp.int32))
        return strong_types(state)

    def advantages(self, params, norms, mb: "Batch", hp, values=None, v_last=None):
        """GAE of a minibatch of sequences [L, Bs] with the current value net (no gradient through it);
        `values` [L, Bs], `v_last` [Bs]: the value net's output on mb.obs and on mb.next_obs[-1] when the
        caller has them already.

        V(obs[t+1]) is the current value of the next row except where the episode ended after t: there
        the bootstrap target is V(next_obs[t]), the final observation, taken from the rollout (only
        time-outs use it). The last step bootstraps on the current value of next_obs[L-1].
        """
        if values is None:
            values = self.value.apply(params["value"], nz.normalize(norms.obs, mb.obs))
        if v_last is None:
            v_last = self.value.apply(params["value"], nz.normalize(norms.obs, mb.next_obs[-1]))
        v, v_last = jax.lax.stop_gradient(values), jax.lax.stop_gradient(v_last)
        v_next = jnp.concatenate([jnp.where(mb.ended[:-1], mb.next_value[:-1], v[1:]), v_last[None]])
        return losses.gae(mb.reward * hp.reward_scale, v, v_next, mb.valid & ~mb.terminated, mb.ended, hp.gamma,
                          hp.gae_lambda, mb.valid)

    def loss_terms(self, params, norms, mb: "Batch", offsets, hp, with_consistency: bool = True,
                   taps: dict | None = None, shares: bool = False):
        """The named loss terms of one minibatch mb (leaves [L, Bs, ...]) -> ({name: scalar}, metrics).

        taps (`zero_taps`): zeros added to what the consistency term alone takes of the other terms' inputs, the
        model's parameters and the policy's actions [L, Bs, A]: the same terms, whose gradient with respect to the
        taps is l_cc's share of the model's and the actions' gradient (`tapped_gradient`).
        shares: the diagnostics named in `share_metrics()` as per-sample shares [L, Bs] of their masked means
        (`numerics.masked_share`), which `sgd` adds up over its steps and reduces once; otherwise scalars."""
        obs_n = nz.normalize(norms.obs, mb.obs)
        mean, std = self.policy.apply(params["policy"], obs_n)
        if self.config.gae_in_loss:  # one value pass over the sequences and the row each bootstraps on
            rows = jnp.concatenate([obs_n, nz.normalize(norms.obs, mb.next_obs[-1:])])
            values_all = self.value.apply(params["value"], rows)
            values = values_all[:-1]
            adv, returns = self.advantages(params, norms, mb, hp, values, values_all[-1])
        else:
            values = self.value.apply(params["value"], obs_n)
            adv, returns = mb.advantages, mb.returns
        entropy_noise = mb.noise if self.config.entropy == "squashed" else None
        ppo, metrics = losses.ppo_loss(mean, std, values, mb.raw_action, mb.log_prob, adv, returns, mb.valid,
                                       hp, entropy_noise, shares)
        metrics["policy/std"] = (masked_share if shares else masked_mean)(std.mean(-1), mb.valid)
        terms = {"ppo": ppo}
        if self.model is not None:
            pred_mean, pred_log_std = self.model.apply(params["model"], obs_n, mb.action)
            target = model_target(norms, mb.obs, mb.next_obs, mb.reward)
            terms["model_nll"], model_metrics = losses.model_loss(pred_mean, pred_log_std, target, mb.valid, shares)
            metrics.update(model_metrics)
        if self.config.use_consistency and with_consistency:
            actions = networks.act_from_noise(mean, std, mb.noise)  # [L, Bs, A], carries d/dphi
            model_params = params["model"]
            if taps is not None:
                actions = actions + taps["actions"]
                model_params = jax.tree.map(jnp.add, model_params, taps["model"])
            s0, window_actions, real_next, mask = consistency.windows(mb.obs, mb.next_obs, actions, mb.ended,
                                                                      mb.valid, offsets, self.k)
            cc_terms, cc_metrics = consistency.consistency_loss(
                consistency.mlp_step, self.mlp_model(model_params, norms), s0, window_actions, real_next, mask,
                kind=self.config.encoder, normalize=norms.obs,
                weights=consistency.path_weights(hp), encoder=self.encoder,
                encoder_params=params.get("encoder"), unroll=self.config.cc_unroll)
            terms.update(cc_terms)
            metrics.update(cc_metrics)
        return terms, metrics

    def loss(self, params, norms, mb, offsets, hp, with_consistency: bool = True, taps: dict | None = None,
             shares: bool = False):
        """Total loss of one minibatch mb (leaves [L, Bs, ...]) -> (loss, metrics): the named terms times
        `term_weights(hp)`; `shares` as in `loss_terms`."""
        terms, metrics = self.loss_terms(params, norms, mb, offsets, hp, with_consistency, taps, shares)
        weights = term_weights(hp)
        total = sum(weights[name] * term for name, term in terms.items())
        if shares:  # the terms' shares where they have them; a scalar term spread evenly over the samples
            like = mb.valid.astype(jnp.float32)
            metrics["loss/total"] = sum(
                weights[name] * (metrics[SHARED_TERMS[name]] if name in SHARED_TERMS else
                                 jnp.full_like(like, term / like.size)) for name, term in terms.items())
        else:
            metrics["loss/total"] = total
        return total, metrics

    # The gradient diagnostics: metrics "grad/<term>/<group>", the norm of each weighted loss term's gradient on
    # each parameter group it reaches (TERM_GROUPS), and "grad/total/<group>", of their sum. They are taken on the
    # SGD's first minibatch of each update, at the update's starting parameters, from the SGD's own gradient
    # (`sgd`; `grad_norms` is the same on any one minibatch). No second copy of the loss is differentiated: l_cc's
    # share is tapped from the SGD's backward (`zero_taps`), and the other terms, which do not run the k-step
    # chain, are differentiated once apart (`rest_gradient`).

    def zero_taps(self, params, mb: "Batch") -> dict | None:
        """Zeros for `loss_terms`' taps (None without the consistency term): {"model": like params["model"],
        "actions": [L, Bs, A]}."""
        if not self.config.use_consistency:
            return None
        return {"model": jax.tree.map(jnp.zeros_like, params["model"]), "actions": jnp.zeros_like(mb.action)}

    def tapped_gradient(self, params, norms, mb, offsets, hp, with_consistency: bool = True, taps=None,
                        shares: bool = False):
        """jax.grad of `loss` -> (gradient, the taps' gradient or None, metrics): with taps (`zero_taps`), the
        same gradient and, on the taps, l_cc's share of the model's gradient and of the actions' cotangent.
        `shares` as in `loss_terms`."""
        if taps is None:
            grads, metrics = jax.grad(self.loss, has_aux=True)(params, norms, mb, offsets, hp, with_consistency,
                                                               None, shares)
            return grads, None, metrics
        loss = lambda p, t: self.loss(p, norms, mb, offsets, hp, with_consistency, t, shares)  # noqa: E731
        (grads, tapped), metrics = jax.grad(loss, argnums=(0, 1), has_aux=True)(params, taps)
        return grads, tapped, metrics

    def rest_terms(self, params, norms, mb: "Batch", offsets, hp) -> dict:
        """The loss terms other than l_cc, without its k-step chain: PPO, the model's NLL and, for grounded-gru,
        the encoder's auxiliary term alone (`consistency.grounding_term`)."""
        terms, _ = self.loss_terms(params, norms, mb, offsets, hp, with_consistency=False)
        if self.config.use_consistency and self.config.encoder == "grounded-gru":
            _, _, real_next, mask = consistency.windows(mb.obs, mb.next_obs, mb.action, mb.ended, mb.valid, offsets,
                                                        self.k)
            terms["encoder_aux"], _ = consistency.grounding_term(self.encoder, params["encoder"], real_next, mask,
                                                                 norms.obs)
        return terms

    def rest_gradient(self, params, norms, mb, offsets, hp) -> dict | None:
        """The gradient of the weighted terms other than l_cc on one minibatch (None without l_cc, when the SGD's
        gradient on each group is one term's). Each group is reached by at most one of them (TERM_GROUPS), so
        its part of this gradient is that term's."""
        if not self.config.use_consistency:
            return None
        weights = term_weights(hp)

        def rest(p):
            return sum(weights[n] * t for n, t in self.rest_terms(p, norms, mb, offsets, hp).items())

        return jax.grad(rest)(params)

    def step_grad_norms(self, grads, tapped, rest) -> dict:
        """The diagnostics that need a minibatch's own gradient (`tapped_gradient`; in the SGD, every step of its
        first scan computes them and the first step's are kept): the total's norm on each group and, without
        l_cc, each term's (the only one on its groups); with it, l_cc's on the model (its tap) and on the encoder.
        The encoder's is the one taken as a difference (the total less `rest`'s encoder_aux, whose real-row pass
        l_cc shares): its error is the rounding of the two gradients, about 1e-7 of encoder_aux's in float32 and
        more where a GPU multiplies in TF32; the policy's and the model's shares are computed, not subtracted."""
        out = {f"grad/total/{group}": _norm(g) for group, g in grads.items()}
        if tapped is None:
            for name in self.term_names():
                out.update({f"grad/{name}/{group}": _norm(grads[group]) for group in TERM_GROUPS[name]
                            if group in grads})
            return out
        out["grad/consistency/model"] = _norm(tapped["model"])
        if "encoder" in grads:
            out["grad/consistency/encoder"] = _norm(jax.tree.map(jnp.subtract, grads["encoder"], rest["encoder"]))
        return out

    def rest_grad_norms(self, params, norms, mb, rest, actions_cotangent) -> dict:
        """The diagnostics of the other terms (their gradient `rest`) and l_cc's on the policy: the policy's
        backward of its tapped cotangent on the actions of mb (empty without l_cc)."""
        if rest is None:
            return {}
        out = {f"grad/{name}/{group}": _norm(rest[group]) for name in self.term_names() if name != "consistency"
               for group in TERM_GROUPS[name] if group in rest}

        def actions(policy_params):
            mean, std = self.policy.apply(policy_params, nz.normalize(norms.obs, mb.obs))
            return networks.act_from_noise(mean, std, mb.noise)

        _, pullback = jax.vjp(actions, params["policy"])
        out["grad/consistency/policy"] = _norm(pullback(actions_cotangent)[0])
        return out

    def term_names(self) -> tuple[str, ...]:
        """The names of the terms `loss_terms` returns."""
        names = ("ppo",) + (("model_nll",) if self.model is not None else ())
        if self.config.use_consistency:
            names += ("consistency",) + (("encoder_aux",) if self.config.encoder == "grounded-gru" else ())
        return names

    def grad_norms(self, params, norms, mb, offsets, hp) -> dict:
        """The gradient diagnostics on one minibatch mb at params (see above): what `sgd` reports of its first
        minibatch, from the same pieces."""
        grads, tapped, _ = self.tapped_gradient(params, norms, mb, offsets, hp, taps=self.zero_taps(params, mb))
        rest = self.rest_gradient(params, norms, mb, offsets, hp)
        out = self.step_grad_norms(grads, tapped, rest)
        out.update(self.rest_grad_norms(params, norms, mb, rest, None if tapped is None else tapped["actions"]))
        return out

    def openloop_metrics(self, model_params, norms, history: History) -> dict:
        """Open-loop MSE (normalised space) of the model at k and at eval_horizon steps on real data."""
        step = lambda s, a: self.model_step(model_params, norms, s, a)[0]  # noqa: E731
        _, imagined = open_loop(step, history.obs[0], history.action)
        out = {}
        for name, j in (("k", self.k), ("50", self.config.eval_horizon)):
            ok = (history.filled >= j) & ~history.ended[: j - 1].any(0) & history.valid[:j].all(0)
            err = ((nz.normalize(norms.obs, imagined[j - 1]) - nz.normalize(norms.obs, history.next_obs[j - 1])) ** 2).mean(-1)
            n = ok.sum()
            out[f"model/openloop_mse_{name}"] = jnp.where(n > 0, masked_mean(err, ok), jnp.nan)
        return out

    def collect(self, state: TrainState, hp: HParams, key: jax.Array):
        """Closed-loop rollout with the current policy, then GAE. -> (env_state, episodes, traj, batch)."""
        hp = hp.as_float32()
        params, norms = state.params, state.norms

        def behaviour(obs, key):
            mean, std = self.policy.apply(params["policy"], nz.normalize(norms.obs, obs))
            noise = jax.random.normal(key, mean.shape)
            raw = mean + std * noise
            log_prob = networks.action_distribution(mean, std).log_prob(raw)
            return networks.squash(raw), raw, noise, log_prob

        def value_of(obs):
            return self.value.apply(params["value"], nz.normalize(norms.obs, obs))

        # GAE recomputed in each minibatch needs of acting time only the bootstrap values of time-outs
        in_loss = self.config.gae_in_loss
        (env_state, episodes), traj = closed_loop(self.env, behaviour, value_of, state.env_state, state.episodes,
                                                  key, self.T, hp.gamma, timeouts_only=in_loss)
        adv = returns = None
        if not in_loss:
            adv, returns = losses.gae(traj.reward * hp.reward_scale, traj.value, traj.next_value,
                                      traj.valid & ~traj.terminated, traj.ended, hp.gamma, hp.gae_lambda, traj.valid)
        batch = Batch(traj.obs, traj.next_obs, traj.action, traj.raw_action, traj.noise, traj.log_prob,
                      traj.reward, traj.terminated, traj.ended, traj.valid, traj.next_value, adv, returns)
        return env_state, episodes, traj, batch

    def sgd(self, params, opt_state, norms, data: "Batch", hp: HParams, key: jax.Array):
        """Epochs x minibatches of Adam steps on the loss; minibatches are shuffled sequences of L steps. The
        gradient diagnostics (`grad_norms`) are those of the first step: its minibatch, at params. The other
        metrics are means over the steps; those of `share_metrics()` are added up per sample over the steps and
        reduced once (`loss_terms`' shares), not reduced in every step."""
        tx = make_optimizer(self.config, params, hp)
        segments = jax.tree.map(lambda x: to_segments(x, self.L), data)  # [L, N, ...]
        Bs = self.config.minibatch_seqs
        cc = self.config.use_consistency

        names = {}  # with_consistency -> the metric names, in the order of the stacked vector (set when traced)
        _, key_epochs = jax.random.split(key)  # (the first key is unused: the epochs' keys stay those of before)
        epoch_keys = jax.random.split(key_epochs, self.config.num_epochs)
        first, rest = None, None
        if cc:
            first, first_offsets = self.first_minibatch(segments, epoch_keys[0])
            rest = self.rest_gradient(params, norms, first, first_offsets, hp)

        def minibatch(carry, inp, with_consistency):
            params, opt_state, tap, summed = carry
            mb, key = inp
            offsets = consistency.window_offsets(key, self.L, self.k, self.config.num_windows)
            taps = self.zero_taps(params, mb) if with_consistency else None
            grads, tapped, metrics = self.tapped_gradient(params, norms, mb, offsets, hp, with_consistency, taps,
                                                          shares=True)
            updates, opt_state = tx.update(grads, opt_state, params)
            summed = {name: total + metrics.pop(name) for name, total in summed.items()}
            unreduced = [name for name, value in metrics.items() if jnp.ndim(value)]
            assert not unreduced, f"per-sample metrics not in share_metrics(): {unreduced}"
            values = list(metrics.values())
            if with_consistency:  # the diagnostics of every step; the first one's are kept (and its actions' tap)
                diagnostics = self.step_grad_norms(grads, tapped, rest)
                values += list(diagnostics.values())
                names["diagnostics"] = list(diagnostics)
                if cc:
                    is_first, kept = tap
                    tap = (jnp.zeros((), bool), jnp.where(is_first, tapped["actions"], kept))
            # one stacked vector per minibatch, not one output per metric: on a GPU each scan output is a
            # small write of its own in every one of the epochs x minibatches steps
            names[with_consistency] = list(metrics)
            stacked = jnp.stack(values) if values else jnp.zeros((0,), jnp.float32)  # every metric may be a share
            return (optax.apply_updates(params, updates), opt_state, tap, summed), stacked

        def epoch(carry, key, with_consistency):
            perm, mb_keys = self.shuffle(key)
            split = lambda x: jnp.swapaxes(x[:, perm].reshape((self.L, self.M, Bs) + x.shape[2:]), 0, 1)  # noqa: E731
            step = functools.partial(minibatch, with_consistency=with_consistency)
            return jax.lax.scan(step, carry, (jax.tree.map(split, segments), mb_keys))

        # Epochs with the consistency term first, then (cc_epochs > 0) the rest without it.
        n_cc = self.config.num_epochs if self.config.cc_epochs == 0 else self.config.cc_epochs
        tap = (jnp.ones((), bool), jnp.zeros_like(first.action)) if cc else ()
        summed = {name: jnp.zeros((self.L, Bs)) for name in self.share_metrics()}
        (params_new, opt_state, tap, summed), stacked = jax.lax.scan(
            functools.partial(epoch, with_consistency=True), (params, opt_state, tap, summed), epoch_keys[:n_cc])
        n = len(names[True])
        metrics = dict(zip(names[True], stacked[..., :n].mean((0, 1))))
        metrics.update(zip(names["diagnostics"], stacked[0, 0, n:]))
        metrics.update(self.rest_grad_norms(params, norms, first, rest, tap[1] if cc else None))
        carry = (params_new, opt_state, tap, summed)
        if n_cc < self.config.num_epochs:  # a metric of both parts: the mean over all epochs
            carry, stacked = jax.lax.scan(functools.partial(epoch, with_consistency=False), carry, epoch_keys[n_cc:])
            n_rest = self.config.num_epochs - n_cc
            for name, value in zip(names[False], stacked.mean((0, 1))):
                metrics[name] = (n_cc * metrics[name] + n_rest * value) / self.config.num_epochs
        steps = self.config.num_epochs * self.M
        metrics.update({name: total.sum() / steps for name, total in carry[3].items()})
        return carry[:2], metrics

    def share_metrics(self) -> tuple[str, ...]:
        """The minibatch metrics that `loss_terms` gives as per-sample shares when asked (`sgd` asks): the loss values
        of the terms in SHARED_TERMS and their total, and the diagnostics."""
        names = ("loss/total", "loss/ppo", "loss/policy", "loss/value", "loss/entropy", "ppo/approx_kl",
                 "ppo/clip_fraction", "policy/std")
        return names + (("loss/model_nll", "model/onestep_mse", "model/reward_mse") if self.model is not None else ())

    def shuffle(self, key: jax.Array) -> tuple[jax.Array, jax.Array]:
        """One epoch's order: (the permutation of the N sequences [N], the keys of its M minibatches [M])."""
        key_perm, key_mb = jax.random.split(key)
        return jax.random.permutation(key_perm, self.config.num_segments), jax.random.split(key_mb, self.M)

    def first_minibatch(self, segments: "Batch", key: jax.Array) -> tuple["Batch", jax.Array]:
        """The first minibatch [L, Bs, ...] of the epoch with key `key` (`sgd`'s epochs; segments: leaves
        [L, N, ...]) and its windows' offsets: what the SGD's first step takes."""
        perm, mb_keys = self.shuffle(key)
        mb = jax.tree.map(lambda x: x[:, perm[:self.config.minibatch_seqs]], segments)
        return mb, consistency.window_offsets(mb_keys[0], self.L, self.k, self.config.num_windows)

    def update(self, state: TrainState, hp: HParams) -> tuple[TrainState, dict]:
        hp = hp.as_float32()
        key, key_roll, key_sgd = jax.random.split(state.key, 3)
        env_state, episodes, traj, data = self.collect(state, hp, key_roll)
        # The rollout joins the statistics before SGD: the first update already learns on normalised data.
        norms = refresh_norms(state.norms, traj.obs, traj.next_obs, traj.reward, traj.valid)
        (params, opt_state), metrics = self.sgd(state.params, state.opt_state, norms, data, hp, key_sgd)

        history = state.history.push(traj)
        if self.model is not None:  # the model of the last update with the statistics it was trained with
            metrics.update(self.openloop_metrics(state.params["model"], state.norms, history))
        if self.yardstick is not None:  # the same model on the common yardstick
            step = lambda s, a: self.model_step(state.params["model"], state.norms, s, a)[0]  # noqa: E731
            metrics.update(yardstick.errors(step, self.yardstick))
        last_return, _ = episodes.mean_returns(state.last_return)
        _, last_disc = episodes.mean_returns(state.last_disc_return)
        metrics.update({
            "episode/return": last_return,
            "episode/discounted_return": last_disc,
            "episode/count": episodes.done_count,
            "env/reward_mean": masked_mean(traj.reward, traj.valid),
            "env/invalid_fraction": (~traj.valid).astype(jnp.float32).mean(),
            "opt/skipped_updates": opt_state.total_notfinite.astype(jnp.float32),
            "train/skipped_steps": (opt_state.total_notfinite - state.opt_state.total_notfinite).astype(jnp.float32),
        })
        new_state = TrainState(
            params=params, opt_state=opt_state, norms=norms, env_state=env_state, episodes=episodes,
            history=history, last_return=last_return, last_disc_return=last_disc, key=key,
            update_step=state.update_step + 1)
        return strong_types(new_state), metrics


def make_agent(config: Config) -> ObsAgent:
    """The observation-space agent of `config`: its pure pieces (`init`, `update`, `collect`, `loss`, `act`,
    `model_step`, ...) as bound methods; nothing is jitted here. `cdjax.agents.obs.make_trainer` hands the
    host side the protocol's `Trainer` of the same agent."""
    return ObsAgent(config)


def make_train(config: Config) -> Callable[[jax.Array, HParams], tuple[TrainState, dict]]:
    """train(key, hp) -> (final state, metrics with leaves [num_updates]): pure, jit/vmap it yourself."""
    agent = make_agent(config)
    return scanned_train(agent.init, agent.update, config.num_updates)


def make_trainer(config: Config) -> Trainer:
    """The observation-space agent of `config` as the host side runs it (`cdjax.protocol.Trainer`)."""
    agent = make_agent(config)

    def eval_env(num_envs: int) -> envs.BatchedEnv:
        return envs.BatchedEnv(agent.env.env, num_envs, config.episode_length, config.action_repeat,
                               config.reset_mode, observation_size=agent.env.observation_size)

    def fresh_policy(key: jax.Array) -> dict:
        """The policy network as its module initialises it, statistics at their initial values."""
        params = agent.policy.init(key, jnp.zeros((1, agent.O), jnp.float32))
        return {"params": {"policy": params}, "norms": nz.Norms.create(agent.O)}

    # everything cdjax.envs.make_env builds the environments from: arms equal in these share one reset program
    env_key = ("obs", config.env, config.num_envs, config.episode_length, config.action_repeat, config.reset_mode,
               bool(getattr(config, "stagger_resets", False)), config.physics_backend)
    return Trainer(
        config=config, init=agent.init, update=agent.update, reset=agent.reset, init_from=agent.init_from,
        env_key=env_key,
        policy=lambda state: {"params": {"policy": state.params["policy"]}, "norms": state.norms},
        act=lambda policy, obs, key: agent.act(policy["params"], policy["norms"], obs, key), eval_env=eval_env,
        saved_leaves=functools.cache(lambda: saved_leaves(config, agent.init, HParams())), fresh_policy=fresh_policy,
        inner=agent)
