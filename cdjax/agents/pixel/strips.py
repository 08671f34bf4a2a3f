"""Image strips (PNG) of the pixel model next to the real frames: for each held-out sequence, three rows of the
newest frame of each step: the real frames, the closed loop's reconstructions (posterior latents, decoder
means) and the open loop's predictions (prior latents, from `context` filtered steps on; the context columns
repeat the reconstructions, framed in grey).

    from cdjax.agents.pixel.strips import write_strips
    write_strips(learner, state.params, state.heldout, key, "strip.png", sequences=2)   # one run's state
"""

from __future__ import annotations

import pathlib

import jax
import jax.numpy as jnp
import numpy as np

from cdjax.agents.pixel.model import newest_frames


def strip_images(learner, params, frames, actions, key) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(real, reconstructed, open-loop) [T, B, S, S, 3] in [0, 1] of time-major held-out sequences
    frames [T+F-1, B, S, S, 3] uint8, actions [T, B, A]."""
    model, C = learner.model, learner.config.context
    _, predicted, _, filtered = model.openloop_loglik(params, frames, actions, key, C)
    recon, _ = model.decode(params, filtered.h, filtered.z)
    real = newest_frames(frames, learner.config.frame_stack)
    imagined = jnp.concatenate([recon[:C], predicted])
    return tuple(jnp.clip(x, 0.0, 1.0) for x in (real, recon, imagined))


def _row(images: np.ndarray, context: int, pad: int = 1) -> np.ndarray:
    """[T, S, S, 3] -> [S + 2 pad, T (S + 2 pad), 3]: frames side by side; the first `context` framed grey."""
    T, S = images.shape[:2]
    out = np.ones((S + 2 * pad, T * (S + 2 * pad), 3), np.float32)
    for t in range(T):
        x0 = t * (S + 2 * pad)
        if t < context:
            out[:, x0:x0 + S + 2 * pad] = 0.5
        out[pad:pad + S, x0 + pad:x0 + pad + S] = images[t]
    return out


def write_strips(learner, params, heldout, key, path, sequences: int = 2) -> pathlib.Path:
    """PNG of `sequences` held-out sequences of one run (params and heldout without a run axis)."""
    import imageio.v3 as iio

    n = min(sequences, heldout.actions.shape[0])
    frames = jnp.swapaxes(heldout.frames[:n], 0, 1)
    actions = jnp.swapaxes(heldout.actions[:n], 0, 1)
    images = jax.jit(lambda p, f, a, k: strip_images(learner, p, f, a, k))(params, frames, actions, key)
    real, recon, imagined = (np.asarray(x) for x in images)
    C = learner.config.context
    rows = []
    for b in range(n):
        rows += [_row(real[:, b], 0), _row(recon[:, b], 0), _row(imagined[:, b], C)]
    image = (np.concatenate(rows, 0) * 255).round().astype(np.uint8)
    path = pathlib.Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    iio.imwrite(path, image)
    return path
