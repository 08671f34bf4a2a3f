"""The pixel consistency term's k imagined steps with both GRU encodings, unrolled, with a backward written out
(`PixelConfig.core_impl` fused; the observation setting's counterpart is `cdjax.consistency.fused_chain`).

The same function as `consistency_loss`'s scan over `LtqModel.prior_step` (with the policy acting on the imagined
h, or the expert's actions) and the encoder's GRU on the real and imagined h: per step one product of the new h with
the policy's first layer, the prior's hidden layer, the LSTM's recurrent kernels and the GRU's input kernel side by
side (the next step's three and this step's imagined GRU input at once), the policy's output layer, one product of
the action with the prior's and the LSTM's action rows, the prior's output layer, z's product and one GRU product of
both row kinds. The backward keeps per step only the cotangents of h, c and the GRU's hidden states; every weight's
gradient comes afterwards, one product over all k steps each.

Gradient paths are those of `consistency_loss`: the caller scales the core's and the policy's parameters; the GRU's
gradient from the real rows is scaled by scales[0] and from the imagined rows by scales[1].

What it shares with `cdjax.consistency.chain` (the same math): the GRU step (`gru_gates`) and its backward by the
same vjp, every layer's (kernel, bias) gradient as one product over all steps (`layer_grads`), and the per-step
arrays stacked so that a vmapped runs' axis stays in front (`stack_steps`). Why the loops are its own: the model
step is another function (the LSTM core with a latent sampled from the prior, z = mean + std * eps, and optionally
the policy acting on the imagined h, not an MLP on normalised states), so its forward products, its per-step
cotangents (through the LSTM cell, the softplus scale and the tanh policy) and the residuals they need differ;
and the GRU reads the model's own hidden state, with no normalisation statistics and no clip.
"""

from __future__ import annotations

import functools

import flax.linen as nn
import jax
import jax.numpy as jnp

from cdjax.agents.pixel.model import lstm_cell
from cdjax.consistency.chain import gru_gates, layer_grads, stack_steps


def _flat(x: jax.Array) -> jax.Array:
    return x.reshape(-1, x.shape[-1])


def _outer(xs: list, ds: list) -> jax.Array:
    """sum_t xs[t]^T ds[t]: one product over every step and row (a layer without bias)."""
    return _flat(stack_steps(xs)).T @ _flat(stack_steps(ds))


@functools.partial(jax.custom_vjp, nondiff_argnums=(0, 1))
def _chain(use_policy: bool, min_std: float, p: dict, scales: jax.Array):
    return _chain_fwd(use_policy, min_std, p, scales)[0]


def _chain_fwd(use_policy: bool, min_std: float, p: dict, scales: jax.Array):
    G, M = p["w_gh"].shape[0], p["wp_h"].shape[1]
    Np = p["pw1"].shape[1] if use_policy else 0
    k = p["eps"].shape[0]
    w_hall = jnp.concatenate(([p["pw1"]] if use_policy else []) + [p["wp_h"], p["w_hl"], p["w_i"]], axis=1)
    w_a = jnp.concatenate([p["wp_a"], p["w_xa"]], axis=1)  # [A, M + 4H]
    gi_re = p["x_re"] @ p["w_i"] + p["b_i"]  # [k, W, 3G]: the real rows' GRU inputs, all steps before the loop
    gh_bias = jnp.concatenate([jnp.zeros((2 * G,), p["b_hn"].dtype), p["b_hn"]])
    h, c = p["h0"], p["c0"]
    P = h @ w_hall[:, :-3 * G]
    hs = jnp.zeros((2,) + h.shape[:1] + (G,), h.dtype)
    res = dict(h=[h], c=[c], u1=[], a=[], gp=[], raw=[], std=[], z=[], gates=[], gi=[], gh=[], hs=[hs])
    for t in range(k):
        if use_policy:
            u1 = nn.relu(P[:, :Np] + p["pb1"])
            a = jnp.tanh(u1 @ p["pw2"] + p["pb2"])
            res["u1"].append(u1)
        else:
            a = p["actions"][t]
        Q = a @ w_a
        gp = P[:, Np:Np + M] + Q[:, :M] + p["bp"]
        mean, raw = jnp.split(nn.relu(gp) @ p["wo"] + p["bo"], 2, axis=-1)
        std = nn.softplus(raw) + min_std
        z = mean + std * p["eps"][t]
        gates = P[:, Np + M:] + Q[:, M:] + p["b_l"] + z @ p["w_z"]
        h, c = lstm_cell(gates, c)
        both = h @ w_hall  # the next step's policy, prior and LSTM parts | this step's imagined GRU input
        P = both[:, :-3 * G]
        gi = jnp.stack([gi_re[t], both[:, -3 * G:] + p["b_i"]])
        gh = hs @ p["w_gh"] + gh_bias
        hs = gru_gates(gi, gh, hs)
        for name, value in (("a", a), ("gp", gp), ("raw", raw), ("std", std), ("z", z), ("gates", gates),
                            ("gi", gi), ("gh", gh), ("h", h), ("c", c), ("hs", hs)):
            res[name].append(value)
    out = (hs[0], hs[1], jnp.concatenate([h, c], axis=-1))
    return out, (p, scales, w_hall, w_a, res)


def _chain_bwd(use_policy: bool, min_std: float, residuals, cotangents):
    p, scales, w_hall, w_a, r = residuals
    dh_re, dh_im, ds = cotangents
    H, G = p["w_hl"].shape[0], p["w_gh"].shape[0]
    M = p["wp_h"].shape[1]
    Np = p["pw1"].shape[1] if use_policy else 0
    k = p["eps"].shape[0]
    dhs, dh, dc = jnp.stack([dh_re, dh_im]), ds[:, :H], ds[:, H:]
    dP = None  # the cotangent of the next step's policy, prior and LSTM parts of `both`
    d = {name: [None] * k for name in ("gi", "gh", "P", "dpre2", "Q", "out", "gates", "eps", "actions")}
    for t in reversed(range(k)):
        _, gru_vjp = jax.vjp(gru_gates, r["gi"][t], r["gh"][t], r["hs"][t])
        dgi, dgh, dhs_direct = gru_vjp(dhs)
        dhs = dhs_direct + dgh @ p["w_gh"].T
        d["gi"][t], d["gh"][t] = dgi, dgh
        dboth = dgi[1] if dP is None else jnp.concatenate([dP, dgi[1]], axis=-1)
        dh = dh + dboth @ (w_hall[:, -3 * G:] if dP is None else w_hall).T
        _, lstm_vjp = jax.vjp(lstm_cell, r["gates"][t], r["c"][t])
        dgates, dc = lstm_vjp((dh, dc))
        dz = dgates @ p["w_z"].T
        d["eps"][t] = dz * r["std"][t]
        dout = jnp.concatenate([dz, dz * p["eps"][t] * nn.sigmoid(r["raw"][t])], axis=-1)
        dgp = jnp.where(r["gp"][t] > 0, dout @ p["wo"].T, 0.0)
        dQ = jnp.concatenate([dgp, dgates], axis=-1)
        da = dQ @ w_a.T
        d["out"][t], d["gates"][t], d["Q"][t] = dout, dgates, dQ
        if use_policy:
            dpre2 = da * (1.0 - r["a"][t] ** 2)
            dpol = jnp.where(r["u1"][t] > 0, dpre2 @ p["pw2"].T, 0.0)
            d["dpre2"][t] = dpre2
            dP = jnp.concatenate([dpol, dgp, dgates], axis=-1)
        else:
            d["actions"][t] = da
            dP = jnp.concatenate([dgp, dgates], axis=-1)
        d["P"][t] = dP
        dh = jnp.zeros_like(dh)  # h_t reaches nothing but `both` of step t - 1 (added there)
    dh0 = dP @ w_hall[:, :-3 * G].T
    dc0 = dc

    # every weight's gradient, one product over all steps: `both` of step t (from h_{t+1}) carries the cotangents of
    # step t + 1's parts and of step t's imagined GRU input, the latter scaled as the imagined rows' GRU gradient
    zeros_P = jnp.zeros_like(d["P"][0])
    dgi = jnp.stack(d["gi"])  # [k, 2, W, 3G]
    dgi_scaled = dgi * scales[None, :, None, None]
    d_hall_parts = [jnp.concatenate([d["P"][t + 1] if t + 1 < k else zeros_P, dgi_scaled[t, 1]], axis=-1)
                    for t in range(k)]
    dw_hall = _outer(r["h"][1:], d_hall_parts)
    dw_hall = dw_hall.at[:, :-3 * G].add(_flat(r["h"][0]).T @ _flat(d["P"][0]))
    col = 0
    grads = {}
    if use_policy:
        grads["pw1"], col = dw_hall[:, :Np], Np
        grads["pb1"] = jnp.stack([dP_t[:, :Np] for dP_t in d["P"]]).sum((0, 1))
        grads["pw2"], grads["pb2"] = layer_grads(stack_steps(r["u1"]), stack_steps(d["dpre2"]))
    grads["wp_h"], grads["w_hl"], grads["w_i"] = (dw_hall[:, col:col + M], dw_hall[:, col + M:col + M + 4 * H],
                                                  dw_hall[:, -3 * G:])
    # the action's rows of the prior's hidden layer and of the LSTM, with their biases (bp, b_l): Q's cotangents
    dw_a, db_a = layer_grads(stack_steps(r["a"]), stack_steps(d["Q"]))
    grads["wp_a"], grads["w_xa"], grads["bp"], grads["b_l"] = dw_a[:, :M], dw_a[:, M:], db_a[:M], db_a[M:]
    grads["wo"], grads["bo"] = layer_grads(stack_steps([nn.relu(gp) for gp in r["gp"]]), stack_steps(d["out"]))
    grads["w_z"] = _outer(r["z"], d["gates"])
    # the GRU: the real rows' input products happened outside the loop (gi_re), the imagined rows' inside `both`
    grads["w_i"] = grads["w_i"] + _flat(p["x_re"]).T @ _flat(dgi_scaled[:, 0])
    grads["b_i"] = dgi_scaled.sum((0, 1, 2))
    dgh_scaled = jnp.stack(d["gh"]) * scales[None, :, None, None]
    grads["w_gh"] = _flat(jnp.stack(r["hs"][:-1])).T @ _flat(dgh_scaled)
    grads["b_hn"] = dgh_scaled[..., 2 * G:].sum((0, 1, 2))
    grads["x_re"] = dgi[:, 0] @ p["w_i"].T
    grads["h0"], grads["c0"] = dh0, dc0
    grads["eps"] = jnp.stack(d["eps"])
    if not use_policy:
        grads["actions"] = jnp.stack(d["actions"])
    return {name: grads[name] for name in p}, jnp.zeros_like(scales)


_chain.defvjp(_chain_fwd, _chain_bwd)


def pixel_chain(core_w: dict, policy_params, gru: tuple, h0, c0, actions, eps, x_re, scales, min_std: float,
                use_policy: bool) -> tuple[jax.Array, jax.Array, jax.Array]:
    """The k imagined steps from (h0, c0) [W, H] with the prior's noise eps [k, W, Z], acting by the policy on the
    imagined h (use_policy) or by actions [k, W, A], and the GRU encodings of the real h x_re [k, W, H] and of the
    imagined ones: (h_re, h_im [W, G], s_k [W, 2H]). core_w: `model.core_weights`; policy_params: the Policy
    module's (one hidden layer); gru: `consistency.gru_weights`'s (W_i, b_i, W_h, b_hn); scales [2]."""
    H, Z = core_w["H"], core_w["Z"]
    (wp, bp), (wo, bo) = core_w["prior_hidden"], core_w["prior_out"]
    w_i, b_i, w_gh, b_hn = gru
    p = dict(wp_h=wp[:H], wp_a=wp[H:], bp=bp, wo=wo, bo=bo, w_hl=core_w["w_h"], w_xa=core_w["w_x"][Z:],
             w_z=core_w["w_x"][:Z], b_l=core_w["b"], w_i=w_i, b_i=b_i, w_gh=w_gh, b_hn=b_hn, h0=h0, c0=c0, eps=eps,
             x_re=x_re)
    if use_policy:
        layers = policy_params["params"]
        if set(layers) != {"Dense_0", "Dense_1"}:
            raise ValueError(f"pixel_chain takes a policy of one hidden layer, got layers {sorted(layers)}")
        p.update(pw1=layers["Dense_0"]["kernel"], pb1=layers["Dense_0"]["bias"], pw2=layers["Dense_1"]["kernel"],
                 pb2=layers["Dense_1"]["bias"])
    else:
        p["actions"] = actions
    return _chain(use_policy, min_std, p, jnp.asarray(scales, jnp.float32))
