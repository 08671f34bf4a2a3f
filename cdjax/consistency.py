"""The consistency term of Sodhani et al. (2019), independent of the setting that uses it.

A k-step window starts at a real state s_0 of a time-major batch. The real (closed-loop) pathway is
the sequence the environment produced, s_1..s_k; the imagined (open-loop) pathway applies the learned
model step k times from s_0 under the same actions. One shared encoder maps each sequence to a vector
and l_cc is the L2 distance between the two vectors, averaged over the windows that stay inside one
episode:

    l_cc = mean_w || enc(s_1..s_k) - enc(s^I_1..s^I_k) ||_2

Its gradient has two paths, weighted apart (`PathWeights`): into the model and the encoder
(`model`), and into the policy through the actions (`policy`); the paper's CD sets both to alpha.
The weights act on gradients only (`scale_gradient`), so the loss value is the same for any weights.

Encoders (`KINDS`):
- `grounded-gru` (the default): l_cc is the root-mean-square difference of the two GRU encodings
  (the L2 norm divided by sqrt(features)), and the encoder is also trained on the real encodings by
  an auxiliary loss (`encoder_aux`, trains the encoder only, weight `enc_aux_coef` in the caller):
  reconstruct the window it read (a linear decoder, mean squared error of the normalised states),
  plus a hinge that keeps every feature's spread across windows at least SPREAD_FLOOR,
  mean_j max(0, SPREAD_FLOOR - std_j). l_cc alone lets a trainable encoder shrink every encoding to
  one point (measured on ant: spread 1e-5 within ~20 updates), which makes l_cc vanish without a
  consistent model; the hinge makes shrinking cost, and the reconstruction makes ignoring the input
  cost. The reconstruction alone does not suffice, even with the encodings normalised per window: on ant
  that encoder's spread fell from 0.97 to 0.04 in 3 updates (experiments/consistency_weights).
- `gru`: the paper's GRU, trained by l_cc alone (it may collapse; its output spread is logged).
- `frozen-gru`: a random GRU that is never trained.
- `l2`: no encoder, the per-step L2 distance in normalised state space averaged over the k steps
  (what the authors' code effectively compares).

The model step, the state normalisation and the actions are passed in, so any setting (observation
space, latent states of a pixel model, a CNN's features) can use the same term.
"""

from __future__ import annotations

import functools
import warnings
from typing import Any, Callable, Mapping

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from cdjax import normalize as nz
from cdjax.numerics import masked_mean

KINDS = ("grounded-gru", "gru", "frozen-gru", "l2")
SPREAD_FLOOR = 0.5  # grounded-gru: the spread across windows below which each encoding feature is penalised
SPREAD = "encoder/spread_real"  # the metric of the real encodings' spread that `collapse_warning` reads
# Below this output spread (std of the encodings across windows, averaged over features) a trainable GRU maps
# every window to nearly one point: l_cc then vanishes without the model becoming consistent. A fresh GRU
# spreads ~0.1-1; the collapsed ant runs of experiments/paper_obs_space ended at 5e-5 to 3e-4.
COLLAPSE_SPREAD = 1e-3
TRAINED_ENCODERS = ("gru", "grounded-gru")


@struct.dataclass
class PathWeights:
    """Multipliers of the consistency gradient on each of its two paths (traced floats), and of the model path's
    share that trains the encoder."""

    model: Any  # into the model's and the encoder's parameters
    policy: Any  # into the actions, hence the policy's parameters
    encoder: Any = 1.0  # times `model` on the encoder's parameters alone (`path_weights`: 1 / alpha)

    @property
    def to_encoder(self) -> Any:
        """The multiplier of l_cc's gradient into the encoder's parameters (before the caller's alpha)."""
        return self.model * self.encoder


def path_weights(hp) -> PathWeights:
    """The path weights of hyper-parameters with alpha, cc_model and cc_policy: l_cc's gradient reaches the model at
    alpha x cc_model and the policy at alpha x cc_policy, the encoder at cc_model alone (alpha = 0: not at all).

    alpha weighs the term against the model's and the policy's other losses; the grounded encoder's balance is
    between l_cc and its own loss (`enc_aux_coef`), which alpha must not tip. With alpha on the encoder's share, at
    the pixel presets' alpha 100 every encoder of 20 halfcheetah runs shrank its output ~10,000x by 10,000 updates
    (spread 0.12 to 5e-5, the spread floor's hinge at its maximum, experiments/pixel/RESULTS.md), so l_cc vanished:
    l_cc and the active hinge are both linear in the encodings' scale, and shrinking wins whenever alpha x cc_model
    x l_cc / spread exceeds enc_aux_coef. At alpha 1 (the observation and Atari presets) this is the weighting of
    before."""
    alpha = jnp.asarray(hp.alpha, jnp.float32)
    return PathWeights(model=hp.cc_model, policy=hp.cc_policy,
                       encoder=jnp.where(alpha > 0, 1.0 / jnp.where(alpha > 0, alpha, 1.0), 0.0))


@jax.custom_vjp
def _scale(x, s):
    return x


def _scale_fwd(x, s):
    return x, s


def _scale_bwd(s, g):
    # where(s == 0): a weight of 0 gives exactly zero, even if g is not finite.
    return jnp.where(s == 0, jnp.zeros_like(g), g * s.astype(g.dtype)), jnp.zeros_like(s)


_scale.defvjp(_scale_fwd, _scale_bwd)


def scale_gradient(tree, scale):
    """Identity on the values of `tree`; multiplies the gradient flowing back through it by `scale`."""
    scale = jnp.asarray(scale, jnp.float32)
    return jax.tree.map(lambda x: _scale(x, scale), tree)


def safe_norm(x: jax.Array, axis: int = -1) -> jax.Array:
    """Euclidean norm whose value AND gradient are exactly 0 at x = 0 (plain norm: NaN gradient)."""
    sq = jnp.sum(x**2, axis=axis)
    positive = sq > 0
    return jnp.where(positive, jnp.sqrt(jnp.where(positive, sq, 1.0)), 0.0)


# ---------------------------------------------------------------------------------------------------
# The sequence encoder


class SequenceEncoder(nn.Module):
    """The consistency encoder: a GRU scanned by the caller, and a decoder of a whole window.

    `__call__(h [..., H], x [..., D]) -> h'` is one GRU step. `decode(h [..., H]) -> [..., k * D]` maps a
    final encoding back to the k inputs it read (used by the grounded encoder's reconstruction loss;
    built only when `window_size` > 0).
    """

    features: int
    window_size: int = 0  # k * D: the size of the flattened window the decoder reconstructs; 0 = no decoder

    def setup(self):
        self.cell = nn.GRUCell(self.features)
        if self.window_size:
            self.decoder = nn.Dense(self.window_size)

    def __call__(self, h, x):
        h, _ = self.cell(h, x)
        return h

    def decode(self, h):
        return self.decoder(h)


def init_encoder(module: SequenceEncoder, key: jax.Array, input_size: int) -> dict:
    """Parameters of the encoder's GRU (inputs of `input_size`) and, if it has one, of its decoder."""
    h = jnp.zeros((1, module.features), jnp.float32)
    x = jnp.zeros((1, input_size), jnp.float32)
    if module.window_size:
        return module.init(key, h, x, method=lambda m, h, x: m.decode(m(h, x)))
    return module.init(key, h, x)


# ---------------------------------------------------------------------------------------------------
# Windows of a time-major batch


def windows_per_sequence(length: int, horizon: int, asked: int) -> int:
    """How many k-step windows a sequence of `length` steps gives: `asked` of them, or all length - k + 1 when
    `asked` is 0 (or more than there are)."""
    available = length - horizon + 1
    return available if asked == 0 else min(asked, available)


def window_offsets(key: jax.Array, length: int, horizon: int, num: int) -> jax.Array:
    """Start times [num] of k-step windows in sequences of `length` steps: all of them in order when
    `num` is their count, else `num` distinct random ones (sorted)."""
    available = length - horizon + 1
    if num >= available:
        return jnp.arange(available)
    return jnp.sort(jax.random.choice(key, available, (num,), replace=False))


def window_indices(offsets: jax.Array, horizon: int) -> jax.Array:
    """Time indices [k, n] of n windows of length k starting at `offsets` [n]."""
    return offsets[None, :] + jnp.arange(horizon)[:, None]


def window_mask(ended: jax.Array, valid: jax.Array, idx: jax.Array) -> jax.Array:
    """[n, B] True for windows that stay inside one episode.

    A window starting at o uses obs[o], actions o..o+k-1 and next_obs[o..o+k-1]. It is broken if an
    episode ends after any of its first k-1 steps (auto-reset replaced the next state) or if any of
    its k transitions is invalid. An episode ending after the window's last step is fine: next_obs
    holds the true final observation.
    """
    crosses = ended[idx[:-1]].any(axis=0)
    invalid = (~valid[idx]).any(axis=0)
    return ~crosses & ~invalid


def _rows(x: jax.Array) -> jax.Array:
    """[..., n, B, D] -> [..., n*B, D]."""
    return x.reshape(x.shape[:-3] + (-1,) + x.shape[-1:])


def windows(obs, next_obs, actions, ended, valid, offsets, horizon: int):
    """The windows of a time-major batch as rows: (s0 [W, O], actions [k, W, A], real [k, W, O], mask [W]).

    obs, next_obs [T, B, O]; actions [T, B, A] (keep them differentiable to let the policy path
    through); ended, valid [T, B]; offsets [n] window starts. W = n * B, window-major.
    """
    idx = window_indices(offsets, horizon)
    s0 = _rows(obs[offsets][None])[0]
    mask = window_mask(ended, valid, idx).reshape(-1)
    return s0, _rows(actions[idx]), _rows(next_obs[idx]), mask


# ---------------------------------------------------------------------------------------------------
# The k-step chain fused: an MLP model and a GRU encoder, forward and backward written out


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


def _outer(a: jax.Array, b: jax.Array) -> tuple[jax.Array, jax.Array]:
    """A layer's (kernel, bias) gradient summed over every leading axis (every step and row at once) from its
    inputs a [..., I] and its outputs' cotangents b [..., J]: one matrix product of [a, 1] and b.

    (One product, not the kernel's product and the bias's sum apart: on an H100 the separate sum's per-step reduce
    kernels made paper-CD's update 0.839 s against 0.805 s, 2026-11-25, `benchmarks.variants bias-sum`.)
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
    axis put the seeds' axis second, and XLA then transposed the hidden states and gates back in every step (15
    transposes per SGD step at 10 seeds, one H100, 2026-11-27, benchmarks/results/2026-11-27-h100-hlo-seeds/)."""
    gi = jnp.concatenate([gi_re, both_im + c["b_i"]])
    return gru_gates(gi, hh + c["gh_bias"], h)


def _stack_steps(xs: list) -> jax.Array:
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

    stack = _stack_steps  # [k, ...]: one copy per kind
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
    dlayers = tuple(_outer(x, dz) for x, dz in zip([model_in] + list(hidden), dz_layers))
    dactions = dz_layers[0] @ layers[0][0][O:].T
    # the GRU's weights: real and imagined rows in one product, each kind's cotangent scaled as scale_gradient would
    scales = jnp.repeat(jnp.stack(c["scales"]), W)[None, :, None]  # [1, 2W, 1]: each row's kind's scale
    scaled = lambda g: jnp.where(scales == 0, jnp.zeros_like(g), g * scales)  # noqa: E731
    x_enc = jnp.concatenate([p["x_re"], xin_next[..., -p["x_re"].shape[-1]:]], axis=1)  # [k, 2W, D]
    dw_i, db_i = _outer(x_enc, scaled(dgi))
    dw_h, dgh_bias = _outer(hs_prev, scaled(dhh))
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


# ---------------------------------------------------------------------------------------------------
# The term


def _feature_std(x: jax.Array, mask: jax.Array) -> jax.Array:
    """[D]: the standard deviation of each feature of x [W, D] across the unmasked rows."""
    m = mask.astype(jnp.float32)[:, None]
    n = jnp.maximum(m.sum(), 1.0)
    mean = (x * m).sum(0) / n
    return jnp.sqrt((((x - mean) ** 2) * m).sum(0) / n + 1e-12)


def grounding_loss(encoder, encoder_params, h_re: jax.Array, real: jax.Array, mask: jax.Array) -> tuple:
    """The grounded encoder's auxiliary loss on the real encodings h_re [W, H] of the windows real [k, W, D]:
    the decoded window's mean squared error plus the spread floor's hinge -> (loss, metrics)."""
    W = h_re.shape[0]
    target = jnp.swapaxes(real, 0, 1).reshape(W, -1)  # [W, k*D], step-major per row
    decoded = encoder.apply(encoder_params, h_re, method="decode")
    reconstruction = masked_mean(((decoded - jax.lax.stop_gradient(target)) ** 2).mean(-1), mask)
    floor = jax.nn.relu(SPREAD_FLOOR - _feature_std(h_re, mask)).mean()
    return reconstruction + floor, {"loss/encoder_reconstruction": reconstruction, "loss/encoder_spread_floor": floor}


def grounding_term(encoder, encoder_params, real_next: jax.Array, mask: jax.Array, normalize: nz.RunningStats) -> tuple:
    """The grounded-gru encoder's auxiliary term alone, without the k-step chain: the encoder over the real windows
    real_next [k, W, O] (raw states, normalised with `normalize`) from zeros, then `grounding_loss`. The same
    function as `consistency_loss`'s "encoder_aux" (whose imagined rows do not reach it) -> (loss, metrics)."""
    x = nz.normalize(normalize, real_next)
    h0 = jnp.zeros((x.shape[1], encoder.features), jnp.float32)
    h_re, _ = jax.lax.scan(lambda h, x_t: (encoder.apply(encoder_params, h, x_t), None), h0, x)
    return grounding_loss(encoder, encoder_params, h_re, x, mask)


def _spread(x: jax.Array, mask: jax.Array) -> jax.Array:
    """Mean over features of the standard deviation across the unmasked rows of x [W, D]."""
    return _feature_std(x, mask).mean()


def consistency_loss(model_step: Callable, model_params, s0, actions, real_next, mask, *, kind: str,
                     normalize: Callable | nz.RunningStats, weights: PathWeights, encoder=None, encoder_params=None,
                     unroll: int = 1, fused: bool = True) -> tuple[dict, dict]:
    """The consistency terms of a batch of windows: ({name: loss}, metrics).

    model_step(model_params, s [W, O], a [W, A]) -> s' imagines in raw state space; s0 [W, O] real start
    states; actions [k, W, A]; real_next [k, W, O] the real states s_1..s_k; mask [W]; normalize maps raw
    states to the encoder's input space (a function, or the RunningStats that `normalize.normalize` applies).
    For the GRU kinds, `encoder` is a module with `apply(params, h, x) -> h'` (and, for grounded-gru,
    `apply(params, h, method="decode") -> [W, k*O]`). One scan computes the imagined states and both encodings.

    With `mlp_step` and an `MLPModel`, a GRU encoder whose parameters are a flax GRUCell's (`gru_weights`) and
    normalize given as RunningStats, that scan runs fused (`fused_chain`: the same function, its backward
    written out, a third of the kernels on a GPU) unless fused=False.

    Terms: "consistency" (l_cc, averaged over unmasked windows) and, for grounded-gru, "encoder_aux"
    (the reconstruction error of the real window plus the spread floor's hinge).
    """
    k, W = actions.shape[:2]
    assert kind in KINDS, kind
    assert s0.shape[0] == W and real_next.shape[:2] == (k, W) and mask.shape == (W,), (
        s0.shape, actions.shape, real_next.shape, mask.shape)
    enc_obs = normalize if isinstance(normalize, nz.RunningStats) else None
    if enc_obs is not None:
        normalize = functools.partial(nz.normalize, enc_obs)
    shared = isinstance(model_params, MLPModel) and model_params.obs is enc_obs  # the caller's own statistics object
    model_params = scale_gradient(model_params, weights.model)
    actions = scale_gradient(actions, weights.policy)
    use_gru = kind != "l2"
    recon = kind == "grounded-gru"
    if kind == "frozen-gru":
        encoder_params = jax.lax.stop_gradient(encoder_params)
    dim = encoder.features if use_gru else 1
    gru = gru_weights(encoder_params) if use_gru else None
    if fused and model_step is mlp_step and isinstance(model_params, MLPModel) and gru is not None and enc_obs is not None:
        # real rows: the encoder's own parameters for grounded-gru (l_cc's share is scaled on h_re in _terms), scaled
        # ones otherwise; imagined rows: scaled (as the scan's encoder calls)
        scales = (1.0 if recon else weights.to_encoder, weights.to_encoder)
        h_re, h_im, s_im = fused_chain(model_params, gru, s0, actions, normalize(real_next), enc_obs, scales, shared)
        acc = None
    else:
        h_re, h_im, s_im, acc = _scanned(model_step, model_params, s0, actions, real_next, normalize, kind, weights,
                                         encoder, encoder_params, unroll, dim)
    terms, metrics = _terms(kind, h_re, h_im, s_im, real_next, mask, normalize, weights, encoder, encoder_params, k,
                            dim, acc)
    if enc_obs is not None:
        metrics.update(_beyond_clip(enc_obs, s_im, mask))
    return terms, metrics


def _scanned(model_step, model_params, s0, actions, real_next, normalize, kind, weights, encoder, encoder_params,
             unroll, dim) -> tuple:
    """`consistency_loss`'s k steps as a scan (model_step and normalize as it passes them, the path weights already
    on model_params and actions) -> (h_re, h_im [W, dim], s_k, acc: l2's summed per-step distances)."""
    W = s0.shape[0]
    use_gru, recon = kind != "l2", kind == "grounded-gru"
    zeros = jnp.zeros((W, dim), jnp.float32)
    if recon:
        # Real rows with the encoder's own parameters (the reconstruction trains them at full weight, and
        # l_cc's share is scaled on h_re in _terms); imagined rows with the model-path-scaled parameters.
        scaled_params = scale_gradient(encoder_params, weights.to_encoder)

        def encode(h_re, h_im, x_re, x_im):
            return encoder.apply(encoder_params, h_re, x_re), encoder.apply(scaled_params, h_im, x_im)
    elif use_gru:
        scaled_params = scale_gradient(encoder_params, weights.to_encoder)

        def encode(h_re, h_im, x_re, x_im):  # one call on real and imagined rows together
            h = encoder.apply(scaled_params, jnp.concatenate([h_re, h_im]), jnp.concatenate([x_re, x_im]))
            return h[:W], h[W:]

    def step(carry, inp):
        s_im, h_re, h_im, acc = carry
        a, s_re = inp
        s_im = model_step(model_params, s_im, a)
        x_re, x_im = normalize(s_re), normalize(s_im)
        if use_gru:
            h_re, h_im = encode(h_re, h_im, x_re, x_im)
        else:
            acc = acc + safe_norm(x_re - x_im)
        return (s_im, h_re, h_im, acc), None

    init = (s0, zeros, zeros, jnp.zeros((W,), jnp.float32))
    (s_im, h_re, h_im, acc), _ = jax.lax.scan(step, init, (actions, real_next), unroll=unroll)
    return h_re, h_im, s_im, acc


def _beyond_clip(stats: nz.RunningStats, s_im: jax.Array, mask: jax.Array) -> dict:
    """{"consistency/final_beyond_clip": the share of the final imagined states' features (unmasked windows) whose
    normalised value, before `normalize`'s clip, lies beyond +-CLIP}: how often the clip binds at the chain's end."""
    stats = jax.lax.stop_gradient(stats)
    out = jnp.abs((jax.lax.stop_gradient(s_im) - stats.mean) / stats.std) > nz.CLIP  # `normalize` without its clip
    return {"consistency/final_beyond_clip": masked_mean(out.astype(jnp.float32).mean(-1), mask)}


def encoded_terms(kind: str, h_re, h_im, s_im, real_next, mask, normalize, weights: PathWeights, encoder,
                  encoder_params) -> tuple[dict, dict]:
    """`consistency_loss`'s terms and metrics from a GRU kind's final encodings h_re, h_im [W, H] and final imagined
    state s_im, for a caller that ran the k steps its own way (e.g. `cdjax.agents.pixel.chain`); the other
    arguments as `consistency_loss`'s (normalize a function)."""
    assert kind in KINDS and kind != "l2", kind
    return _terms(kind, h_re, h_im, s_im, real_next, mask, normalize, weights, encoder, encoder_params,
                  real_next.shape[0], h_re.shape[-1])


def _terms(kind, h_re, h_im, s_im, real_next, mask, normalize, weights, encoder, encoder_params, k, dim, acc=None):
    """The terms and metrics of `consistency_loss` from the final encodings (or, for l2, acc) and state."""
    use_gru, recon = kind != "l2", kind == "grounded-gru"
    terms = {}
    if recon:
        per_window = safe_norm(scale_gradient(h_re, weights.to_encoder) - h_im) / jnp.sqrt(float(dim))
    elif use_gru:
        per_window = safe_norm(h_re - h_im)
    else:
        per_window = acc / k
    terms["consistency"] = masked_mean(per_window, mask)
    aux_metrics = {}
    if recon:
        terms["encoder_aux"], aux_metrics = grounding_loss(encoder, encoder_params, h_re, normalize(real_next), mask)
    e_re, e_im = (h_re, h_im) if use_gru else (normalize(real_next[-1]), normalize(s_im))
    final_err = ((normalize(real_next[-1]) - normalize(s_im)) ** 2).mean(-1)
    metrics = {
        "loss/consistency": terms["consistency"],
        "encoder/spread_real": _spread(e_re, mask),
        "encoder/spread_imagined": _spread(e_im, mask),
        "consistency/masked_fraction": (~mask).astype(jnp.float32).mean(),
        "consistency/final_mse": masked_mean(final_err, mask),
    }
    metrics.update(aux_metrics)
    return terms, metrics


# ---------------------------------------------------------------------------------------------------
# Watching a sweep


def collapse_warning(arm_name: str, config: Any, metrics: Mapping) -> tuple[int, str] | None:
    """(how many runs, a sentence) when the trained encoder of some runs has collapsed, else None: when a run's
    median spread over the second half of the chunk is below COLLAPSE_SPREAD.

    metrics: {name: [R, n]} on the host (one chunk). One update's spread is a noisy sample: it is measured on the
    windows of one rollout, and when they look alike (e.g. many Atari games restarting on the same screen) it dips
    by orders of magnitude for that update alone (ALE Breakout: 2e-4 between values of 0.5-0.9). A collapse
    stays, so the median over the chunk's later updates tells the two apart. Only the trained encoders (gru,
    grounded-gru) are checked: `frozen-gru` does not train and `l2` has no encoder.
    """
    if config.encoder not in TRAINED_ENCODERS or SPREAD not in metrics:
        return None
    spread = np.asarray(metrics[SPREAD], float)
    later = spread[:, spread.shape[1] // 2:]
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # a run with no finite value: NaN, not low
        typical = np.nanmedian(later, axis=1)
    low = np.isfinite(typical) & (typical < COLLAPSE_SPREAD)
    if not low.any():
        return None
    n = int(low.sum())
    return n, (f"Arm {arm_name}: the {config.encoder} encoder's output spread stayed below {COLLAPSE_SPREAD:g} over "
               f"the last {later.shape[1]} updates in {n} of {typical.size} runs (median {np.median(typical[low]):.1e}); "
               "the encoder may have collapsed, which makes l_cc vanish without making the model consistent. The "
               "frozen-gru and l2 encoders (--encoder) cannot collapse.")
