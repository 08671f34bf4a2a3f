"""The "Learning to Query" stochastic state-space model (Buesing et al. 2018) as Sodhani et al. describe it.

Time indexing. A sequence holds frames f_0..f_{L+F-2} (uint8 [S, S, 3]) and actions a_0..a_{L-1}; the
observation o_t is the stack of the F frames f_t..f_{t+F-1} (F = 4), and a_t is what the expert did after
seeing o_t. With s_{-1} = 0 and a_{-1} = 0 (s = the LSTM state (h, c)):

    prior      p(z_t | s_{t-1}, a_{t-1})          diagonal Gaussian (an MLP on [h_{t-1}, a_{t-1}])
    posterior  q(z_t | e(o_t), s_{t-1}, a_{t-1})  diagonal Gaussian (an MLP on [e(o_t), h_{t-1}, a_{t-1}])
    transition s_t = LSTM([z_t, a_{t-1}], s_{t-1})
    decoder    p(f_{t+F-1} | h_t, z_t)            diagonal Gaussian over the newest frame's pixels in [0, 1]
    policy     a_t ~= pi(h_t)                     tanh MLP, trained by imitation (mean squared error)

e: 4 convolutions (4x4, stride 2, 64 channels, ReLU) and a dense layer to 256; the decoder mirrors it (3x3
convolutions and depth_to_space, or transposed convolutions). How the convolutions are computed (their operands'
dtype, and the arrangement a sweep's vmapped runs meet) is convs.py's. The closed loop (`filter`) samples z
from the posterior (it reads the frames); the open loop (`imagine`) samples z from the prior and never reads a
frame. The ELBO is summed over the pixels, the latent dimensions and the time steps (not averaged per element,
the authors' bug), in nats.
Every standard deviation is softplus(raw) + min_std, from its own output (not from the mean, another bug).
"""

from __future__ import annotations

import functools
from typing import Callable, NamedTuple

import flax.linen as nn
import jax
import jax.numpy as jnp

from cdjax.agents.pixel.losses import gaussian_kl, gaussian_log_prob
from cdjax.agents.pixel.networks import ConvDecoder, ConvEncoder, Core, Policy
from cdjax.consistency import SequenceEncoder, init_encoder



def stack_frames(frames: jax.Array, stack: int) -> jax.Array:
    """frames [T+F-1, B, S, S, 3] uint8 -> observations [T, B, S, S, 3F] float32 in [0, 1] (oldest first)."""
    T = frames.shape[0] - stack + 1
    x = jnp.concatenate([frames[i:i + T] for i in range(stack)], axis=-1)
    return x.astype(jnp.float32) / 255.0


def newest_frames(frames: jax.Array, stack: int) -> jax.Array:
    """frames [T+F-1, B, S, S, 3] uint8 -> the newest frame of each observation [T, B, S, S, 3] in [0, 1]."""
    return frames[stack - 1:].astype(jnp.float32) / 255.0


LSTM_GATES = "ifgo"  # flax's LSTM cells' gate order (kernels "ii".."io" on the input, "hi".."ho" on h)


def _dense(layer: dict) -> tuple[jax.Array, jax.Array]:
    return layer["kernel"], layer["bias"]


def lstm_cell(gates: jax.Array, c: jax.Array) -> tuple[jax.Array, jax.Array]:
    """flax's LSTM update from the summed pre-activations [..., 4H] (gates i, f, g, o) and c -> (h', c')."""
    i, f, g, o = jnp.split(gates, 4, axis=-1)
    c = nn.sigmoid(f) * c + nn.sigmoid(i) * jnp.tanh(g)
    return nn.sigmoid(o) * jnp.tanh(c), c


def core_weights(core_params, hidden: int, latent: int) -> dict:
    """Core's parameters as the fused steps use them: the LSTM's four input and four recurrent kernels side by side
    (w_x [Z + A, 4H], w_h [H, 4H], b [4H]), the prior's and the posterior's layers as they are."""
    p = core_params["params"]
    cell = p["cell"]
    return dict(prior_hidden=_dense(p["prior_hidden"]), prior_out=_dense(p["prior_out"]),
                post_hidden=_dense(p["post_hidden"]), post_out=_dense(p["post_out"]),
                w_x=jnp.concatenate([cell[f"i{g}"]["kernel"] for g in LSTM_GATES], axis=1),
                w_h=jnp.concatenate([cell[f"h{g}"]["kernel"] for g in LSTM_GATES], axis=1),
                b=jnp.concatenate([cell[f"h{g}"]["bias"] for g in LSTM_GATES]), H=hidden, Z=latent)


def _prior_kernels(w: dict) -> tuple[jax.Array, jax.Array, jax.Array]:
    """The prior's hidden layer and the LSTM side by side: h's kernel [H, M + 4H], the action's [A, M + 4H] and the
    biases [M + 4H] (the hidden layer's first, then the LSTM's gates)."""
    H, Z = w["H"], w["Z"]
    wp, bp = w["prior_hidden"]
    return (jnp.concatenate([wp[:H], w["w_h"]], axis=1), jnp.concatenate([wp[H:], w["w_x"][Z:]], axis=1),
            jnp.concatenate([bp, w["b"]]))


def _prior_rest(w: dict, min_std: float, g, c, eps):
    """From g = [the prior's hidden pre-activation | the LSTM's h and action shares]: z = prior mean + std * eps and
    the transition -> (h', c', z)."""
    (wp, _), (wo, bo) = w["prior_hidden"], w["prior_out"]
    M = wp.shape[1]
    mean, raw = jnp.split(nn.relu(g[..., :M]) @ wo + bo, 2, axis=-1)
    z = mean + (nn.softplus(raw) + min_std) * eps
    h, c = lstm_cell(g[..., M:] + z @ w["w_x"][:w["Z"]], c)
    return h, c, z


def fused_prior_step(w: dict, min_std: float, h, c, a, eps):
    """Core's prior and transition (`LtqModel.prior_step` with core_impl flax) with h's two products in one and
    a's in one: z = prior mean + std * eps -> (h', c', z)."""
    w_h, w_a, b = _prior_kernels(w)
    return _prior_rest(w, min_std, h @ w_h + a @ w_a + b, c, eps)


def fused_imagine(w: dict, min_std: float, h0, c0, actions, eps):
    """`LtqModel.imagine` under given actions [K, B, A] with core_impl fused: the actions' shares of the prior's
    hidden layer and of the LSTM for all K steps in one product before the loop; per step one product of h with
    both (their h rows side by side), the prior's output layer and z's product, one packed row stored.
    -> (h, c, z), each [K, B, ...]."""
    w_h, w_a, b = _prior_kernels(w)

    def step(carry, inp):
        pre, noise = inp
        h, c, z = _prior_rest(w, min_std, carry[0] @ w_h + pre, carry[1], noise)
        return (h, c), jnp.concatenate([h, c, z], axis=-1)

    packed = jax.lax.scan(step, (h0, c0), (actions @ w_a + b, eps))[1]
    H = w["H"]
    return packed[..., :H], packed[..., H:2 * H], packed[..., 2 * H:]


def fused_filter(w: dict, min_std: float, embeds, prev_actions, eps, h0, c0):
    """`LtqModel.filter` with core_impl fused: the frames' and actions' shares of every layer for all T steps in one
    product each before the scan; per step one product of h with [prior | posterior | LSTM] (their hidden layers'
    h rows and the recurrent kernels), one of both hidden layers with the block-diagonal [prior_out, post_out] and
    one of z with the LSTM's z rows. -> (h, c, z, q mean, q std, p mean, p std), each [T, B, ...]."""
    H, Z = w["H"], w["Z"]
    E = embeds.shape[-1]
    (wp, bp), (wpo, bpo) = w["prior_hidden"], w["prior_out"]
    (wq, bq), (wqo, bqo) = w["post_hidden"], w["post_out"]
    M = wp.shape[1]
    w_h = jnp.concatenate([wp[:H], wq[E:E + H], w["w_h"]], axis=1)  # [H, 2M + 4H]
    inputs = jnp.concatenate([prev_actions @ wp[H:] + bp, embeds @ wq[:E] + prev_actions @ wq[E + H:] + bq,
                              prev_actions @ w["w_x"][Z:] + w["b"]], axis=-1)  # [T, B, 2M + 4H]
    w_out = jnp.zeros((2 * M, 4 * Z), wpo.dtype).at[:M, :2 * Z].set(wpo).at[M:, 2 * Z:].set(wqo)
    b_out = jnp.concatenate([bpo, bqo])
    w_z = w["w_x"][:Z]
    return _filter_scan(min_std, w_h, w_out, b_out, w_z, inputs, eps, h0, c0)


def _filter_outputs(min_std: float, packed: jax.Array, H: int, Z: int) -> tuple:
    """The filter's outputs (h, c, z, q mean, q std, p mean, p std) from its packed per-step rows [..., H + H + Z +
    4Z + ...] (h', c', z, the output layer's [p mean, p raw, q mean, q raw], then anything else)."""
    h, c, z = packed[..., :H], packed[..., H:2 * H], packed[..., 2 * H:2 * H + Z]
    p_mean, p_raw, q_mean, q_raw = jnp.split(packed[..., 2 * H + Z:2 * H + 5 * Z], 4, axis=-1)
    return h, c, z, q_mean, nn.softplus(q_raw) + min_std, p_mean, nn.softplus(p_raw) + min_std


@functools.partial(jax.custom_vjp, nondiff_argnums=(0,))
def _filter_scan(min_std, w_h, w_out, b_out, w_z, inputs, eps, h0, c0):
    return _filter_scan_fwd(min_std, w_h, w_out, b_out, w_z, inputs, eps, h0, c0)[0]


def _filter_scan_fwd(min_std, w_h, w_out, b_out, w_z, inputs, eps, h0, c0):
    """The filter's loop: per step g = h W_h + inputs_t, the output layer on relu(g's hidden part), z, the LSTM;
    one packed row [h', c', z, output layer, g] written per step (one store, not one per output)."""
    M2 = w_out.shape[0]

    def step(carry, inp):
        h, c = carry
        pre, noise = inp
        g = h @ w_h + pre
        out = nn.relu(g[..., :M2]) @ w_out + b_out
        _, _, q_mean, q_raw = jnp.split(out, 4, axis=-1)
        z = q_mean + (nn.softplus(q_raw) + min_std) * noise
        h, c = lstm_cell(g[..., M2:] + z @ w_z, c)
        return (h, c), jnp.concatenate([h, c, z, out, g], axis=-1)

    packed = jax.lax.scan(step, (h0, c0), (inputs, eps))[1]
    H, Z = h0.shape[-1], w_z.shape[0]
    return _filter_outputs(min_std, packed, H, Z), (w_h, w_out, w_z, eps, h0, c0, packed)


def _filter_scan_bwd(min_std, residuals, cotangents):
    """The filter's backward: per step the LSTM's, the output layer's and h's cotangents (three products: with
    W_z, W_out and W_h transposed), one packed row of g's and the output layer's cotangents stored; every weight's
    gradient afterwards, one product over all steps and rows each."""
    w_h, w_out, w_z, eps, h0, c0, packed = residuals
    dh_out, dc_out, dz_out, dq_mean_out, dq_std_out, dp_mean, dp_std = cotangents
    H, Z, M2 = h0.shape[-1], w_z.shape[0], w_out.shape[0]
    h, c, z = packed[..., :H], packed[..., H:2 * H], packed[..., 2 * H:2 * H + Z]
    out, g = packed[..., 2 * H + Z:2 * H + 5 * Z], packed[..., 2 * H + 5 * Z:]
    _, p_raw, _, q_raw = jnp.split(out, 4, axis=-1)
    gates = g[..., M2:] + z @ w_z  # the LSTM's pre-activations, every step in one product
    c_prev = jnp.concatenate([c0[None], c[:-1]])
    dp_raw = dp_std * nn.sigmoid(p_raw)

    def step(carry, inp):
        dh, dc = carry  # from step t + 1
        dh_t, dc_t, dz_t, dq_mean_t, dq_std_t, dp_mean_t, dp_raw_t, q_raw_t, eps_t, g_t, gates_t, c_prev_t = inp
        _, lstm_vjp = jax.vjp(lstm_cell, gates_t, c_prev_t)
        dgates, dc_prev = lstm_vjp((dh + dh_t, dc + dc_t))
        dz = dz_t + dgates @ w_z.T
        dq_raw = (dq_std_t + dz * eps_t) * nn.sigmoid(q_raw_t)
        dout = jnp.concatenate([dp_mean_t, dp_raw_t, dq_mean_t + dz, dq_raw], axis=-1)
        dg = jnp.concatenate([jnp.where(g_t[..., :M2] > 0, dout @ w_out.T, 0.0), dgates], axis=-1)
        return (dg @ w_h.T, dc_prev), jnp.concatenate([dg, dout], axis=-1)

    zeros = jnp.zeros_like(h0)
    (dh0, dc0), grads = jax.lax.scan(step, (zeros, zeros), (dh_out, dc_out, dz_out, dq_mean_out, dq_std_out, dp_mean,
                                                            dp_raw, q_raw, eps, g, gates, c_prev), reverse=True)
    dg, dout = grads[..., :-4 * Z], grads[..., -4 * Z:]
    dgates = dg[..., M2:]
    flat = lambda x: x.reshape(-1, x.shape[-1])  # noqa: E731 - [T * B, ...]: one product over every step and row
    h_prev = jnp.concatenate([h0[None], h[:-1]])
    dz = dz_out + dgates @ w_z.T
    q_std = nn.softplus(q_raw) + min_std
    return (flat(h_prev).T @ flat(dg), flat(nn.relu(g[..., :M2])).T @ flat(dout), flat(dout).sum(0),
            flat(z).T @ flat(dgates), dg, dz * q_std, dh0, dc0)


_filter_scan.defvjp(_filter_scan_fwd, _filter_scan_bwd)


class Filtered(NamedTuple):
    """The closed loop over T steps of B sequences; leaves [T, B, ...]."""

    h: jax.Array
    c: jax.Array
    z: jax.Array
    post_mean: jax.Array
    post_std: jax.Array
    prior_mean: jax.Array
    prior_std: jax.Array


class LtqModel:
    """The modules of one Config and the pure functions of the two pathways."""

    def __init__(self, config, action_size: int):
        self.config, self.A = config, action_size
        c = config
        self.encoder = ConvEncoder(c.conv_layers, c.conv_channels, c.embed_dim, c.compute_dtype, c.conv_impl,
                                   c.output_grad)
        self.decoder = ConvDecoder(c.image_size, c.conv_layers, c.conv_channels, c.min_std, c.upsample,
                                   c.compute_dtype, c.conv_impl, c.output_grad)
        self.core = Core(c.hidden, c.latent, c.mlp, c.min_std)
        self.policy = Policy(tuple(c.policy_hidden), action_size)
        self.cc_encoder = None
        if c.use_consistency and c.encoder != "l2":
            self.cc_encoder = SequenceEncoder(c.encoder_dim, c.horizon * c.hidden if c.encoder == "grounded-gru" else 0)

    def init(self, key: jax.Array) -> dict:
        c = self.config
        k_enc, k_dec, k_core, k_pol, k_cc = jax.random.split(key, 5)
        h = jnp.zeros((1, c.hidden), jnp.float32)
        a = jnp.zeros((1, self.A), jnp.float32)
        params = {
            "encoder": self.encoder.init(k_enc, jnp.zeros((1, c.image_size, c.image_size, 3 * c.frame_stack))),
            "decoder": self.decoder.init(k_dec, jnp.zeros((1, c.hidden + c.latent))),
            "core": self.core.init(k_core, jnp.zeros((1, c.embed_dim)), h, h, a),
            "policy": self.policy.init(k_pol, h),
        }
        if self.cc_encoder is not None:
            params["cc_encoder"] = init_encoder(self.cc_encoder, k_cc, c.hidden)
        return params

    # --- pieces ------------------------------------------------------------------------------------
    def embed(self, params, obs):
        """obs [T, B, S, S, 3F] -> e(o) [T, B, E]."""
        flat = obs.reshape((-1,) + obs.shape[2:])
        return self.encoder.apply(params["encoder"], flat).reshape(obs.shape[:2] + (-1,))

    def decode(self, params, h, z):
        """h [..., H], z [..., Z] -> (mean, std) [..., S, S, 3] of the newest frame."""
        lead = h.shape[:-1]
        x = jnp.concatenate([h, z], -1).reshape(-1, h.shape[-1] + z.shape[-1])
        mean, std = self.decoder.apply(params["decoder"], x)
        return mean.reshape(lead + mean.shape[1:]), std.reshape(lead + std.shape[1:])

    def act(self, params, h):
        return self.policy.apply(params["policy"], h)

    def prior_step(self, core_params, h, c, a, eps):
        """One open-loop step: z = prior mean + std * eps, then the transition -> (h', c', z)."""
        cfg = self.config
        if cfg.core_impl == "fused":
            return fused_prior_step(core_weights(core_params, cfg.hidden, cfg.latent), cfg.min_std, h, c, a, eps)
        mean, std = self.core.apply(core_params, h, a, method="prior")
        z = mean + std * eps
        h, c = self.core.apply(core_params, h, c, z, a, method="transition")
        return h, c, z

    # --- the two pathways --------------------------------------------------------------------------
    def filter(self, params, embeds, prev_actions, eps, h0=None, c0=None) -> Filtered:
        """Closed loop: embeds [T, B, E] of the frames, prev_actions [T, B, A] (a_{t-1}), eps [T, B, Z]."""
        T, B = embeds.shape[:2]
        zeros = jnp.zeros((B, self.config.hidden), jnp.float32)
        h0 = zeros if h0 is None else h0
        c0 = zeros if c0 is None else c0
        core = params["core"]
        cfg = self.config
        if cfg.core_impl == "fused":
            w = core_weights(core, cfg.hidden, cfg.latent)
            return Filtered(*fused_filter(w, cfg.min_std, embeds, prev_actions, eps, h0, c0))

        def step(carry, inp):
            h, c = carry
            e, a, noise = inp
            p_mean, p_std = self.core.apply(core, h, a, method="prior")
            q_mean, q_std = self.core.apply(core, e, h, a, method="posterior")
            z = q_mean + q_std * noise
            h, c = self.core.apply(core, h, c, z, a, method="transition")
            return (h, c), Filtered(h, c, z, q_mean, q_std, p_mean, p_std)

        _, out = jax.lax.scan(step, (h0, c0), (embeds, prev_actions, eps))
        return out

    def imagine(self, params, h0, c0, actions, eps, policy: Callable | None = None):
        """Open loop from (h0, c0) [B, H] with latents from the prior: eps [K, B, Z]; actions [K, B, A] are
        a_{t-1} of each step, or None with `policy(h) -> a` acting on the imagined states.
        Returns (h, c, z) [K, B, ...]. Reads no frame."""

        cfg = self.config
        fused = core_weights(params["core"], cfg.hidden, cfg.latent) if cfg.core_impl == "fused" else None
        if fused is not None and policy is None and actions is not None:
            return fused_imagine(fused, cfg.min_std, h0, c0, actions, eps)

        def step(carry, inp):
            h, c = carry
            a, noise = inp
            a = policy(h) if policy is not None else a
            if fused is not None:
                h, c, z = fused_prior_step(fused, cfg.min_std, h, c, a, noise)
            else:
                h, c, z = self.prior_step(params["core"], h, c, a, noise)
            return (h, c), (h, c, z)

        if actions is None:
            actions = jnp.zeros(eps.shape[:2] + (self.A,), jnp.float32)
        _, out = jax.lax.scan(step, (h0, c0), (actions, eps))
        return out

    # --- the ELBO ----------------------------------------------------------------------------------
    def elbo(self, params, frames, actions, key) -> tuple[jax.Array, dict, Filtered]:
        """frames [T+F-1, B, S, S, 3] uint8, actions [T, B, A] -> (ELBO [B] summed over t and elements,
        {"nll": [T, B], "kl": [T, B]} per step, the filtered states)."""
        F = self.config.frame_stack
        T, B = actions.shape[:2]
        prev = jnp.concatenate([jnp.zeros_like(actions[:1]), actions[:-1]])
        eps = jax.random.normal(key, (T, B, self.config.latent))
        out = self.filter(params, self.embed(params, stack_frames(frames, F)), prev, eps)
        mean, std = self.decode(params, out.h, out.z)
        nll = -gaussian_log_prob(newest_frames(frames, F), mean, std).sum((-3, -2, -1))
        kl = gaussian_kl(out.post_mean, out.post_std, out.prior_mean, out.prior_std).sum(-1)
        return -(nll + kl).sum(0), {"nll": nll, "kl": kl}, out

    def openloop_loglik(self, params, frames, actions, key, context: int):
        """The open loop's log-likelihood of real frames after `context` filtered steps, and the closed loop
        over the same sequences: frames [C+K+F-1, B, ...], actions [C+K, B, A] ->
        (log p(f_t | open loop) [K, B] nats per frame, predicted means [K, B, S, S, 3], ELBO [B], filtered).

        The closed loop filters every step, but the open loop starts from its state after the C context
        observations (the filter is causal: that state has read frames f_0..f_{C+F-2} only) and imagines K
        steps with latents from the prior under the real actions. log p with z from the prior is a one-sample
        estimate of a lower bound of the open loop's marginal log-likelihood."""
        F, C = self.config.frame_stack, context
        K = actions.shape[0] - C
        key_filter, key_imagine = jax.random.split(key)
        elbo, _, out = self.elbo(params, frames, actions, key_filter)
        prev = jnp.concatenate([jnp.zeros_like(actions[:1]), actions[:-1]])
        eps = jax.random.normal(key_imagine, (K,) + out.z.shape[1:])
        h, _, z = self.imagine(params, out.h[C - 1], out.c[C - 1], prev[C:], eps)
        mean, std = self.decode(params, h, z)
        target = newest_frames(frames, F)[C:]
        return gaussian_log_prob(target, mean, std).sum((-3, -2, -1)), mean, elbo, out
