"""Watching a sweep: whether a trained encoder has collapsed (its output spread near zero)."""

from __future__ import annotations

import warnings
from typing import Any, Mapping

import numpy as np

from cdjax.consistency.term import SPREAD

# Below this output spread (std of the encodings across windows, averaged over features) a trainable GRU maps
# every window to nearly one point: l_cc then vanishes without the model becoming consistent. A fresh GRU
# spreads ~0.1-1; the collapsed ant runs of experiments/paper_obs_space ended at 5e-5 to 3e-4.
COLLAPSE_SPREAD = 1e-3
TRAINED_ENCODERS = ("gru", "grounded-gru")


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
