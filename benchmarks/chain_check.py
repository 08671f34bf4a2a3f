"""How closely the fused consistency chain follows the plain loop on this device (issue 21).

    python -m benchmarks.chain_check [--out DIR] [--windows 512 --horizon 20 --obs 27 --act 8 --hidden 500 --enc 128]

At the ant's widths by default: the fused chain (`consistency.fused_chain`) at JAX's default matmul precision against
JAX's own gradient of k plain `mlp_step`s and GRU steps at the highest precision. A loss on all three outputs (the
encodings and the final state) reaches every input. On a GPU the default precision may round products to TF32: this
says what that costs the chain in accuracy. Two rows beside it tell the precision from the implementation: the plain
loop itself at the default precision (what any chain of these products costs at it) and the fused chain at the
highest (what is the fused chain's own). Each entry is max |g - g_ref| / max |g_ref| over an input's leaves. Prints a
table and writes DIR/results.json.
"""

from __future__ import annotations

import argparse
import json
import pathlib

import jax
import jax.numpy as jnp
import numpy as np

from benchmarks.common import Parser
from cdjax import consistency as cc
from cdjax import normalize as nz
from cdjax.options import positive

ARGS = ("model", "gru", "s0", "actions", "x_re")
# (row, chain, matmul precision); "default" is JAX's default (TF32 may be used for float32 products on a GPU)
ROWS = (("fused chain", "fused", "default"), ("plain loop", "plain", "default"), ("fused chain, highest", "fused",
                                                                                   "highest"))


def _problem(windows: int, horizon: int, obs: int, act: int, hidden: int, enc: int, seed: int) -> tuple:
    """(model, gru, s0, actions, x_re, enc_obs, output weights): random weights at initialisation-like scales,
    statistics of unit-scale states, real and start states inside +-3 std."""
    keys = iter(jax.random.split(jax.random.key(seed), 16))
    normal = lambda shape, scale: scale * jax.random.normal(next(keys), shape)  # noqa: E731
    layers = ((normal((obs + act, hidden), 1 / np.sqrt(obs + act)), normal((hidden,), 0.1)),
              (normal((hidden, obs), 0.3 / np.sqrt(hidden)), normal((obs,), 0.1)))
    stats = lambda scale: nz.update(nz.RunningStats.create(obs), normal((4096, obs), scale))  # noqa: E731
    model = cc.MLPModel(layers=layers, obs=stats(1.0), delta=stats(0.1))
    gru = (normal((obs, 3 * enc), 1 / np.sqrt(obs)), normal((3 * enc,), 0.1), normal((enc, 3 * enc), 1 / np.sqrt(enc)),
           normal((enc,), 0.1))
    s0 = jnp.clip(normal((windows, obs), 1.0), -3, 3)
    actions = jnp.tanh(normal((horizon, windows, act), 1.0))
    x_re = nz.normalize(model.obs, jnp.clip(normal((horizon, windows, obs), 1.0), -3, 3))
    return model, gru, s0, actions, x_re, model.obs, normal((3, windows, enc), 1.0)


def _objective(weights, h_re, h_im, s_k):
    return (weights[0] * h_re).sum() + (weights[1] * h_im).sum() + 0.1 * (weights[2, :, :1] * s_k).sum()


def _plain(enc_obs, weights, scales, model, gru, s0, actions, x_re):
    """The reference: k `mlp_step`s and GRU steps, the GRU's real and imagined rows' gradients scaled apart."""
    def cell(g, h, x):
        w_i, b_i, w_h, b_hn = g
        return cc.gru_gates(x @ w_i + b_i, h @ w_h + jnp.concatenate([jnp.zeros((2 * w_h.shape[0],)), b_hn]), h)

    g_re, g_im = cc.scale_gradient(gru, scales[0]), cc.scale_gradient(gru, scales[1])
    s = s0
    h_re = h_im = jnp.zeros((s0.shape[0], gru[2].shape[0]))
    for t in range(actions.shape[0]):
        s = cc.mlp_step(model, s, actions[t])
        h_re, h_im = cell(g_re, h_re, x_re[t]), cell(g_im, h_im, nz.normalize(enc_obs, s))
    return _objective(weights, h_re, h_im, s)


def _fused(enc_obs, weights, scales, *args):
    return _objective(weights, *cc.fused_chain(*args, enc_obs, scales, True))


def _errors(grads, reference) -> dict[str, float]:
    """Per input: max |g - g_ref| / max |g_ref| over its leaves."""
    out = {}
    for name, g, r in zip(ARGS, grads, reference):
        diff = max(float(jnp.abs(a - b).max()) for a, b in zip(jax.tree.leaves(g), jax.tree.leaves(r)))
        scale = max(float(jnp.abs(b).max()) for b in jax.tree.leaves(r))
        out[name] = diff / max(scale, 1e-30)
    return out


def check(windows=512, horizon=20, obs=27, act=8, hidden=500, enc=128, seed=0) -> dict:
    model, gru, s0, actions, x_re, enc_obs, weights = _problem(windows, horizon, obs, act, hidden, enc, seed)
    scales = (1.0, 0.5)
    args = (model, gru, s0, actions, x_re)
    grad = lambda f: jax.jit(jax.value_and_grad(f, argnums=tuple(range(5))))  # noqa: E731
    plain = lambda *a: _plain(enc_obs, weights, scales, *a)  # noqa: E731
    fused = lambda *a: _fused(enc_obs, weights, scales, *a)  # noqa: E731
    with jax.default_matmul_precision("highest"):
        v_ref, g_ref = grad(plain)(*args)
    rows = {}
    for name, f, precision in ROWS:
        with jax.default_matmul_precision(precision):
            v, g = grad({"fused": fused, "plain": plain}[f])(*args)
        rows[name] = {"value": abs(float(v) - float(v_ref)) / abs(float(v_ref)), **_errors(g, g_ref)}
    return {"device": str(jax.devices()[0].device_kind), "backend": jax.default_backend(),
            "sizes": dict(windows=windows, horizon=horizon, obs=obs, act=act, hidden=hidden, enc=enc, seed=seed),
            "relative_error": rows}


def main(argv=None) -> dict:
    p = Parser(prog="python -m benchmarks.chain_check", description=__doc__,
               formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", help="directory for results.json")
    for name, default in (("windows", 512), ("horizon", 20), ("obs", 27), ("act", 8), ("hidden", 500), ("enc", 128),
                          ("seed", 0)):
        p.add_argument(f"--{name}", type=int if name == "seed" else positive, default=default)
    a = p.parse_args(argv)
    result = check(a.windows, a.horizon, a.obs, a.act, a.hidden, a.enc, a.seed)
    print(f"{result['device']} ({result['backend']}), {result['sizes']}: relative error against the plain loop at "
          "the highest precision")
    print_errors(result["relative_error"])
    write_results(a.out, result)
    return result


def print_errors(rows: dict) -> None:
    """A markdown table of rows {name: {"value": e, input: e, ...}} (relative errors, as `check` gives them)."""
    print("| | value | " + " | ".join(ARGS) + " |")
    print("| --- | ---: | " + " | ".join("---:" for _ in ARGS) + " |")
    for name, row in rows.items():
        print(f"| {name} | {row['value']:.2e} | " + " | ".join(f"{row[k]:.2e}" for k in ARGS) + " |")


def write_results(directory: str | None, result: dict) -> None:
    """DIR/results.json, when a directory is given."""
    if directory:
        out = pathlib.Path(directory)
        out.mkdir(parents=True, exist_ok=True)
        (out / "results.json").write_text(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
