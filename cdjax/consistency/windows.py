"""The sequence encoder of the consistency term and the k-step windows of a time-major batch."""

from __future__ import annotations

import flax.linen as nn
import jax
import jax.numpy as jnp


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
