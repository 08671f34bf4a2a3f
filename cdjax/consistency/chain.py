"""The k-step chain fused: an MLP model and a GRU encoder, forward and backward written out (`fused_chain`)."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
from flax import struct

from cdjax import normalize as nz


@struct.dataclass
class MLPModel:
    """A dynamics model the consistency term can run fused (`mlp_step` is its step): an MLP with relu between
    its layers on the normalised state and the action, predicting the normalised change of state,

        s' = s + denormalize(delta, MLP([normalize(obs, s), a])).
    """

    layers: tuple  # ((kernel [in, out], bias [out]), ...): the first takes O + A inputs (state first), the last gives O
    obs: nz.RunningStats  # statistics of the states (the model's input)
    delta: nz.RunningStats  # statistics of the change of state (the model's output)


def mlp_step(model: MLPModel, s: jax.Array, a: jax.Array) -> jax.Array:
    """One imagined step of an MLPModel: s [..., O], a [..., A] -> s' [..., O]."""
    x = jnp.concatenate([nz.normalize(model.obs, s), a], axis=-1)
    for kernel, bias in model.layers[:-1]:
        x = jax.nn.relu(x @ kernel + bias)
    kernel, bias = model.layers[-1]
    return s + nz.denormalize(model.delta, x @ kernel + bias)


def gru_weights(encoder_params) -> tuple | None:
    """(W_i [D, 3H], b_i [3H], W_h [H, 3H], b_hn [H]) of the flax GRUCell under encoder_params["params"]["cell"]
    (gates r, z, n side by side), or None for parameters of another shape."""
    try:
        c = encoder_params["params"]["cell"]
        w_i = jnp.concatenate([c["ir"]["kernel"], c["iz"]["kernel"], c["in"]["kernel"]], axis=1)
        b_i = jnp.concatenate([c["ir"]["bias"], c["iz"]["bias"], c["in"]["bias"]])
        w_h = jnp.concatenate([c["hr"]["kernel"], c["hz"]["kernel"], c["hn"]["kernel"]], axis=1)
        return w_i, b_i, w_h, c["hn"]["bias"]
    except (KeyError, TypeError, IndexError):
        return None


def gru_gates(gi: jax.Array, gh: jax.Array, h: jax.Array) -> jax.Array:
    """flax's GRUCell update from its input part gi = x W_i + b_i and its recurrent part gh = h W_h (+ b_hn on
    the n gate), both [..., 3H] in gate order r, z, n: the same expressions as flax.linen.GRUCell."""
    H = h.shape[-1]
    r = jax.nn.sigmoid(gi[..., :H] + gh[..., :H])
    z = jax.nn.sigmoid(gi[..., H:2 * H] + gh[..., H:2 * H])
    n = jnp.tanh(gi[..., 2 * H:] + r * gh[..., 2 * H:])
    return (1.0 - z) * n + z * h


def layer_grads(a: jax.Array, b: jax.Array) -> tuple[jax.Array, jax.Array]:
    """A layer's (kernel, bias) gradient summed over every leading axis (every step and row at once) from its
    inputs a [..., I] and its outputs' cotangents b [..., J]: one matrix product of [a, 1] and b.

    (One product, not the kernel's product and the bias's sum apart: the separate sum adds a reduction per step and
    was measured slower on a GPU; benchmarks/README.md, "What was tried".)
    """
    a = jnp.concatenate([a, jnp.ones(a.shape[:-1] + (1,), a.dtype)], axis=-1)
    g = a.reshape(-1, a.shape[-1]).T @ b.reshape(-1, b.shape[-1])
    return g[:-1], g[-1]


def _chain_inputs(c: dict, shared: bool, s: jax.Array) -> jax.Array:
    """The model's normalised input of states s [W, O], and unless `shared` the encoder's beside it: [W, O or 2O]."""
    x = nz.normalize(c["model_obs"], s)
    return x if shared else jnp.concatenate([x, nz.normalize(c["enc_obs"], s)], axis=-1)


def _gates(c: dict, gi_re, both_im, hh, h):
    """One GRU step of the real and imagined rows (h [2W, H]: the W real rows, then the W imagined ones) from the real
    rows' input part gi_re [W, 3H], the imagined rows' raw product both_im [W, 3H] (x W_i, no bias) and the raw
    recurrent product hh [2W, 3H].

    The two kinds of rows are stacked along the rows, not along a new leading axis: under vmap (seeds) a new leading
    axis put the seeds' axis second, and XLA then transposed the hidden states and gates back in every step
    (`test_the_fused_chain_under_vmap_moves_no_axis_in_its_steps` checks that it does not)."""
    gi = jnp.concatenate([gi_re, both_im + c["b_i"]])
    return gru_gates(gi, hh + c["gh_bias"], h)


def stack_steps(xs: list) -> jax.Array:
    """The per-step arrays xs (each [...]) stacked along a new leading axis [k, ...], as jnp.stack, but written as a
    concatenation of [1, ...] slices: under vmap jnp.stack puts the vmapped axis second ([k, seeds, ...]), and the
    weight gradients' products then need it moved back in front, a transpose of each stacked array in every SGD step;
    this form keeps the vmapped axis in front."""
    return jnp.concatenate([x[None] for x in xs])


@functools.partial(jax.custom_vjp, nondiff_argnums=(0,))
def _chain(shared: bool, p: dict, c: dict):
    return _chain_fwd(shared, p, c)[0]


def _chain_fwd(shared: bool, p: dict, c: dict):
    """The k imagined steps and both encodings, unrolled: -> ((h_re [W, H], h_im [W, H], s_k [W, O]), residuals).

    Per step, three matrix products: the model's hidden layer(s) and output, then one product of the new
    state's normalised input with [first layer's state rows | W_i] (the next step's first layer and this step's
    imagined GRU input at once), and one of [h_re; h_im] with W_h. The real rows' GRU inputs and the actions'
    share of the first layer do not depend on the chain: one product each, before it. The residuals are the
    per-step arrays as they are (a list per kind), never written into stacked buffers step by step.
    """
    layers, w_i, w_h = p["layers"], p["w_i"], p["w_h"]
    s0, actions, x_re = p["s0"], p["actions"], p["x_re"]
    k, (W, O) = actions.shape[0], s0.shape
    (w_1, b_1), (w_out, b_out) = layers[0], layers[-1]
    N1 = w_1.shape[1]
    w_in = _input_weights(w_1, w_i, O, shared)
    c = dict(c, b_i=p["b_i"], gh_bias=jnp.concatenate([jnp.zeros((2 * w_h.shape[0],), p["b_hn"].dtype), p["b_hn"]]))
    gi_re = x_re @ w_i + p["b_i"]  # [k, W, 3H]
    z1_actions = actions @ w_1[O:] + b_1  # [k, W, N1]
    states, xin = [s0], [_chain_inputs(c, shared, s0)]
    p1 = xin[0] @ w_in[:, :N1]
    hs = [jnp.zeros((2 * W, w_h.shape[0]), s0.dtype)]  # real rows, then imagined rows
    hidden, both_im, hh = [], [], []
    for t in range(k):
        u = jax.nn.relu(p1 + z1_actions[t])
        us = [u]
        for kernel_t, bias in layers[1:-1]:
            u = jax.nn.relu(u @ kernel_t + bias)
            us.append(u)
        states.append(states[-1] + nz.denormalize(c["delta"], u @ w_out + b_out))
        xin.append(_chain_inputs(c, shared, states[-1]))
        both = xin[-1] @ w_in  # [W, N1 + 3H]: the next step's first layer (state part) | this step's GRU input
        p1 = both[:, :N1]
        hidden.append(us)
        both_im.append(both[:, N1:])
        hh.append(hs[-1] @ w_h)
        hs.append(_gates(c, gi_re[t], both_im[-1], hh[-1], hs[-1]))
    residuals = (p, c, w_in, gi_re, states, xin, hidden, both_im, hh, hs)
    return (hs[-1][:W], hs[-1][W:], states[-1]), residuals


def _input_weights(w_1: jax.Array, w_i: jax.Array, O: int, shared: bool) -> jax.Array:
    """[layer 1's state rows | W_i] for one normalised input (shared), else the block-diagonal [[W1_x, 0], [0, W_i]]
    for [model input | encoder input]: [X, N1 + 3H]."""
    if shared:
        return jnp.concatenate([w_1[:O], w_i], axis=1)
    N1 = w_1.shape[1]
    return jnp.zeros((2 * O, N1 + w_i.shape[1]), w_1.dtype).at[:O, :N1].set(w_1[:O]).at[O:, N1:].set(w_i)


def _chain_bwd(shared: bool, residuals, cotangents):
    """The chain's backward, unrolled: per step only the cotangents of the states and hidden states (three
    matrix products); every weight's gradient afterwards, one product over all k steps and both row kinds each
    (the bias as the product's last row)."""
    dh_re, dh_im, ds = cotangents
    p, c, w_in, gi_re, states, xin, hidden, both_im, hh, hs = residuals
    layers, w_h = p["layers"], p["w_h"]
    k = len(hidden)
    N1 = layers[0][0].shape[1]
    delta_std = c["delta"].std  # d denormalize(delta, z) / dz
    dh, dp1 = jnp.concatenate([dh_re, dh_im]), None  # cotangents of h_{t+1} and of the next step's first layer
    dgi, dhh, dzs = [None] * k, [None] * k, [None] * k
    for t in reversed(range(k)):
        _, gates_vjp = jax.vjp(functools.partial(_gates, c), gi_re[t], both_im[t], hh[t], hs[t])
        dgi_re, dgi_im, dhh[t], dh_direct = gates_vjp(dh)
        dgi[t] = jnp.concatenate([dgi_re, dgi_im])
        dh = dh_direct + dhh[t] @ w_h.T
        dboth = dgi_im if dp1 is None else jnp.concatenate([dp1, dgi_im], axis=-1)
        dxin = dboth @ (w_in[:, N1:] if dp1 is None else w_in).T
        _, inputs_vjp = jax.vjp(functools.partial(_chain_inputs, c, shared), states[t + 1])
        ds = ds + inputs_vjp(dxin)[0]  # every path into s_{t+1}
        dz = ds * delta_std  # the output layer's
        dzs[t] = [dz]
        for (kernel_t, _), u in zip(layers[:0:-1], hidden[t][::-1]):
            dz = jnp.where(u > 0, dz @ kernel_t.T, 0.0)
            dzs[t].append(dz)
        dzs[t] = dzs[t][::-1]
        dp1 = dz
    _, inputs_vjp = jax.vjp(functools.partial(_chain_inputs, c, shared), states[0])
    ds0 = ds + inputs_vjp(dp1 @ w_in[:, :N1].T)[0]

    stack = stack_steps  # [k, ...]: one copy per kind
    return _chain_weight_grads(p, c, stack(xin[:-1]), stack(xin[1:]), [stack(list(u)) for u in zip(*hidden)],
                               [stack(list(dz)) for dz in zip(*dzs)], stack(dgi), stack(dhh), stack(hs[:-1]), ds0)


def _chain_weight_grads(p: dict, c: dict, xin_prev, xin_next, hidden: list, dz_layers: list, dgi, dhh, hs_prev, ds0):
    """Every weight's gradient from the chain's per-step arrays, stacked [k, ...]: one product over all k steps and
    both row kinds each (the bias as the product's last row), and the inputs' cotangents.

    xin_prev, xin_next [k, W, X]: the normalised inputs of steps 0..k-1 and 1..k; hidden: each hidden layer's
    outputs [k, W, N]; dz_layers: each layer's output cotangents; dgi, dhh [k, 2W, 3H]: the GRU's input and
    recurrent parts' cotangents; hs_prev [k, 2W, H]: the hidden states entering each step; ds0 [W, O]."""
    layers = p["layers"]
    O, W, H = ds0.shape[-1], ds0.shape[0], p["w_h"].shape[0]
    model_in = jnp.concatenate([xin_prev[..., :O], p["actions"]], axis=-1)  # layer 1's inputs, steps 0..k-1
    dlayers = tuple(layer_grads(x, dz) for x, dz in zip([model_in] + list(hidden), dz_layers))
    dactions = dz_layers[0] @ layers[0][0][O:].T
    # the GRU's weights: real and imagined rows in one product, each kind's cotangent scaled as scale_gradient would
    scales = jnp.repeat(jnp.stack(c["scales"]), W)[None, :, None]  # [1, 2W, 1]: each row's kind's scale
    scaled = lambda g: jnp.where(scales == 0, jnp.zeros_like(g), g * scales)  # noqa: E731
    x_enc = jnp.concatenate([p["x_re"], xin_next[..., -p["x_re"].shape[-1]:]], axis=1)  # [k, 2W, D]
    dw_i, db_i = layer_grads(x_enc, scaled(dgi))
    dw_h, dgh_bias = layer_grads(hs_prev, scaled(dhh))
    dp = dict(layers=dlayers, w_i=dw_i, b_i=db_i, w_h=dw_h, b_hn=dgh_bias[2 * H:], s0=ds0, actions=dactions,
              x_re=dgi[:, :W] @ p["w_i"].T)
    return dp, jax.tree.map(jnp.zeros_like, {name: c[name] for name in ("model_obs", "delta", "enc_obs", "scales")})


_chain.defvjp(_chain_fwd, _chain_bwd)


def fused_chain(model: MLPModel, gru: tuple, s0, actions, x_re, enc_obs: nz.RunningStats, scales: tuple,
                shared: bool = False) -> tuple[jax.Array, jax.Array, jax.Array]:
    """The k imagined steps of an MLPModel from s0 [W, O] under actions [k, W, A] and the GRU encodings of the real
    (normalised) states x_re [k, W, D] and of the imagined ones (normalised by enc_obs): (h_re, h_im [W, H], s_k).

    The same function as k steps of `mlp_step` and the GRU scanned (as `consistency_loss` does unfused), unrolled,
    with a backward written out: per step only the cotangents of states and hidden states, every weight's gradient
    afterwards in one product over all steps; the real and imagined rows share each GRU product. The GRU's
    gradient from the real rows is scaled by scales[0] and from the imagined rows by scales[1] (as
    `scale_gradient` would on the encoder's parameters of each); the running statistics are constants.
    `shared`: enc_obs is the model's own obs statistics (one normalised input serves both).
    """
    w_i, b_i, w_h, b_hn = gru
    layers = tuple(tuple(layer) for layer in model.layers)
    p = dict(layers=layers, w_i=w_i, b_i=b_i, w_h=w_h, b_hn=b_hn, s0=s0, actions=actions, x_re=x_re)
    c = jax.lax.stop_gradient(dict(model_obs=model.obs, delta=model.delta, enc_obs=enc_obs,
                                   scales=tuple(jnp.asarray(x, jnp.float32) for x in scales)))
    return _chain(shared, p, c)
