"""The off-policy setting's losses on a batch of replayed sequences (time-major, leaves [L, B, ...]).

`loss_terms` returns every weighted term of an arm, `total_loss` their sum; each term reaches only the parameter
groups it trains (REACHES), by where its inputs are cut (stop_gradient), so one gradient of the sum updates every
group:

- critic (the critics and the encoder): n-step clipped double-Q regression on the first step of each sequence;
- actor (the actor): alpha log pi - min Q at the critic's inputs (Config.inputs; the encoder is not trained by the
  actor: stop_gradient);
- temperature (log alpha): -log alpha (log pi + target entropy);
- model, every arm but model-free (encoder, transition, reward head, decoder): the decoded predicted next
  observation against the normalised real one, and the predicted reward, one step, weight model_coef;
- self-pred (encoder, transition): `cdjax.consistency.selfpredictive.self_predictive_loss`, k steps against the target encoder,
  weight alpha;
- paper-cd (the model and its encoder at alpha x cc_model, the actor at alpha x cc_policy, the GRU encoder):
  `cdjax.consistency.consistency_loss` on the k-step window of observations, the imagined one made by the model as
  an observation-space step s' = decode(transition(encode(s), a)); the policy path is `selfpredictive.policy_path`.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp

from cdjax import consistency
from cdjax import normalize as nz
from cdjax.consistency import selfpredictive as sp
from cdjax.numerics import masked_mean


def n_step_target(batch: dict, n: int, gamma, reward_scale) -> tuple[jax.Array, jax.Array, jax.Array, jax.Array]:
    """The n-step return of each sequence's first step: (summed discounted rewards [B], the observation to bootstrap
    from [B, O], its discount [B] (0 after a termination), whether the sample is usable [B]).

    The sum stops at the first episode end within n steps: a termination bootstraps nothing, a time-out (a
    truncation) bootstraps from the true final observation. A non-finite (invalid) transition on the way makes the
    sample unusable."""
    ended, terminated, valid = batch["ended"][:n], batch["terminated"][:n], batch["valid"][:n]
    alive = jnp.cumprod(jnp.concatenate([jnp.ones_like(ended[:1]), ~ended[:-1]]).astype(jnp.float32), axis=0)
    discounts = jnp.asarray(gamma, jnp.float32) ** jnp.arange(n, dtype=jnp.float32)
    ret = (discounts[:, None] * alive * batch["reward"][:n]).sum(0) * reward_scale
    last = (alive.sum(0) - 1).astype(jnp.int32)  # [B] the last step inside the episode
    pick = lambda x: jnp.take_along_axis(x, last.reshape((1, -1) + (1,) * (x.ndim - 2)), axis=0)[0]  # noqa: E731
    discount = jnp.asarray(gamma, jnp.float32) ** (last + 1).astype(jnp.float32) * (1.0 - pick(terminated))
    usable = ((alive > 0) <= valid).all(0)
    return ret, pick(batch["next_obs"][:n]), discount, usable


def total_loss(params: dict, target: dict, norm: nz.RunningStats, batch: dict, hp, key: jax.Array, *, nets: Any,
               config: Any) -> tuple[jax.Array, dict]:
    """The sum of the arm's terms and their metrics (scalars). `target` holds the target critics and encoder."""
    terms, metrics = loss_terms(params, target, norm, batch, hp, key, nets=nets, config=config)
    return sum(terms.values()), metrics


# The parameter groups each term is built to reach (its other gradients are zero by its stop_gradients):
# what the gradient diagnostics report, and what tests/test_offpolicy.py checks of the routing.
REACHES = {"critic": ("critic", "encoder"), "actor": ("actor",), "temperature": ("log_alpha",),
           "model": ("encoder", "model"), "self_pred": ("encoder", "model"),
           "consistency": ("encoder", "model", "actor", "cc_encoder"), "encoder_aux": ("cc_encoder",)}


def loss_terms(params: dict, target: dict, norm: nz.RunningStats, batch: dict, hp, key: jax.Array, *, nets: Any,
               config: Any) -> tuple[dict, dict]:
    """The arm's weighted terms {name in REACHES: scalar} (their sum is the loss) and the metrics."""
    key_next, key_pi = jax.random.split(key)
    A = batch["action"].shape[-1]
    alpha_t = jnp.exp(jax.lax.stop_gradient(params["log_alpha"]))
    obs0 = nz.normalize(norm, batch["obs"][0])

    # critic: n-step clipped double Q
    ret, boot_obs, discount, usable = n_step_target(batch, config.n_step, hp.gamma, hp.reward_scale)
    x_boot = nets.features(target["encoder"], nz.normalize(norm, boot_obs))
    a_next, logp_next = nets.sample(params["actor"], x_boot, key_next)
    q_next = nets.q(target["critic"], x_boot, a_next).min(0)
    y = jax.lax.stop_gradient(ret + discount * (q_next - alpha_t * logp_next))
    z0 = nets.encode(params["encoder"], obs0)  # None without an encoder
    x0 = nets.inputs(obs0, z0)
    q = nets.q(params["critic"], x0, batch["action"][0])  # [C, B]
    critic = masked_mean(0.5 * ((q - y) ** 2).sum(0), usable)

    # actor and temperature, at the inputs the critic was trained on (the encoder not shaped by the actor)
    x_pi = jax.lax.stop_gradient(x0)
    a_pi, logp = nets.sample(params["actor"], x_pi, key_pi)
    q_pi = nets.q(jax.lax.stop_gradient(params["critic"]), x_pi, a_pi).min(0)
    valid0 = batch["valid"][0]
    actor = masked_mean(alpha_t * logp - q_pi, valid0)
    target_entropy = -hp.target_entropy_scale * A
    temperature = masked_mean(-params["log_alpha"] * jax.lax.stop_gradient(logp + target_entropy), valid0)
    terms = {"critic": critic, "actor": actor, "temperature": temperature}
    metrics = {"loss/critic": critic, "loss/actor": actor, "loss/temperature": temperature, "train/temperature": alpha_t,
               "train/entropy": -masked_mean(jax.lax.stop_gradient(logp), valid0),
               "train/q": masked_mean(jax.lax.stop_gradient(q.mean(0)), usable),
               "train/usable_fraction": usable.astype(jnp.float32).mean()}
    if not config.use_model:
        return terms, metrics

    # the model's one-step prediction (every arm with a model)
    obs1 = nz.normalize(norm, batch["next_obs"][0])
    _, r_pred, obs1_pred = nets.model.apply(params["model"], z0, batch["action"][0])
    obs_err = masked_mean(((obs1_pred - obs1) ** 2).mean(-1), valid0)
    rew_err = masked_mean((r_pred - batch["reward"][0] * hp.reward_scale) ** 2, valid0)
    model = obs_err + rew_err
    terms["model"] = hp.model_coef * model
    metrics.update({"loss/model": model, "model/obs_mse": obs_err, "model/reward_mse": rew_err})

    k = config.horizon
    if config.use_consistency:
        idx = consistency.window_indices(jnp.zeros((1,), jnp.int32), k)
        mask = consistency.window_mask(batch["ended"][:k], batch["valid"][:k], idx).reshape(-1)
        metrics["consistency/masked_fraction"] = (~mask).astype(jnp.float32).mean()
    if config.arm == "self-pred":
        transition = lambda z, a: nets.model.apply(params["model"], z, a, method="transition")  # noqa: E731
        predicted = sp.latent_rollout(transition, z0, batch["action"][:k])
        targets = nets.encode(target["encoder"], nz.normalize(norm, batch["next_obs"][:k]))
        term, sp_metrics = sp.self_predictive_loss(predicted, targets, mask, hp.rho)
        terms["self_pred"] = hp.alpha * term
        metrics.update(sp_metrics)
    elif config.arm == "paper-cd":
        obs_k = nz.normalize(norm, batch["obs"][:k])
        mean_k, _ = nets.actor.apply(params["actor"], jax.lax.stop_gradient(nets.features(params["encoder"], obs_k)))
        actions = sp.policy_path(batch["action"][:k], jnp.tanh(mean_k))

        def model_step(p, s, a):  # normalised observation -> the next one, through the latent
            z = nets.encode(p["encoder"], s)
            return nets.model.apply(p["model"], nets.model.apply(p["model"], z, a, method="transition"),
                                    method="decode")

        cc_terms, cc_metrics = consistency.consistency_loss(
            model_step, {"encoder": params["encoder"], "model": params["model"]}, obs0, actions,
            nz.normalize(norm, batch["next_obs"][:k]), mask, kind=config.cc_encoder, normalize=lambda x: x,
            weights=consistency.path_weights(hp), encoder=nets.cc_encoder, encoder_params=params.get("cc_encoder"),
            fused=False)
        terms["consistency"] = hp.alpha * cc_terms["consistency"]
        if "encoder_aux" in cc_terms:
            terms["encoder_aux"] = hp.enc_aux_coef * cc_terms["encoder_aux"]
        metrics.update(cc_metrics)
    return terms, metrics
