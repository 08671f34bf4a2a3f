"""The term: l_cc and the grounded encoder's auxiliary loss of a batch of windows (`consistency_loss`)."""

from __future__ import annotations

import functools
from typing import Callable

import jax
import jax.numpy as jnp

from cdjax import normalize as nz
from cdjax.consistency.chain import MLPModel, fused_chain, gru_weights, mlp_step
from cdjax.consistency.weights import PathWeights, safe_norm, scale_gradient
from cdjax.numerics import masked_mean

KINDS = ("grounded-gru", "gru", "frozen-gru", "l2")
SPREAD_FLOOR = 0.5  # grounded-gru: the spread across windows below which each encoding feature is penalised
SPREAD = "encoder/spread_real"  # the metric of the real encodings' spread that `collapse_warning` reads


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
