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

Modules: `weights` (the two paths' weights, `scale_gradient`), `windows` (the sequence encoder and the windows of a
batch), `chain` (the fused k-step chain of an MLP model and a GRU encoder), `term` (`consistency_loss` and the
grounded encoder's loss), `collapse` (the sweep's watch for a collapsed encoder), `selfpredictive` (the self-predictive
term of SPR/TD-MPC2/MR.Q beside the paper's, and what both share on replayed sequences). Every public name of the
first five is here too.
"""

from cdjax.consistency.chain import MLPModel, fused_chain, gru_gates, gru_weights, mlp_step
from cdjax.consistency.collapse import COLLAPSE_SPREAD, TRAINED_ENCODERS, collapse_warning
from cdjax.consistency.term import (KINDS, SPREAD, SPREAD_FLOOR, consistency_loss, encoded_terms, grounding_loss,
                                    grounding_term)
from cdjax.consistency.weights import PathWeights, path_weights, safe_norm, scale_gradient
from cdjax.consistency.windows import (SequenceEncoder, init_encoder, window_indices, window_mask, window_offsets,
                                       windows, windows_per_sequence)

__all__ = ["COLLAPSE_SPREAD", "KINDS", "SPREAD", "SPREAD_FLOOR", "TRAINED_ENCODERS", "MLPModel", "PathWeights",
           "SequenceEncoder", "collapse_warning", "consistency_loss", "encoded_terms", "fused_chain", "grounding_loss",
           "grounding_term", "gru_gates", "gru_weights", "init_encoder", "mlp_step", "path_weights", "safe_norm",
           "scale_gradient", "window_indices", "window_mask", "window_offsets", "windows", "windows_per_sequence"]
