"""The paper's second setting as a `Setting`: a "Learning to Query" state-space model of 64x64x3 frames of expert
trajectories, a policy trained by imitation from the model's state, with (ltq-cd) and without (ltq) the
consistency term between the open and the closed loop.

    cdjax sweep --setting pixel --preset pixel-halfcheetah --expert experts/halfcheetah.msgpack --out runs/px

Arms `ltq` and `ltq-cd` are one code path with a switch (`PixelConfig.arm`); `ltq-cdK` sets the horizon
(e.g. ltq-cd5). Pieces: `config` (PixelConfig, PixelHParams), `model` (the state-space model), `data` (expert
trajectories rendered in jit, the evaluation env), `expert` (the model-free expert's file), `learner` (the
update), `strips` (PNG image strips). The sweep's "env steps" are training frames (batch x sequence length per
update). The host's "return" metric is the held-out open-loop log-likelihood at k (nats per frame) and its
"discounted return" the same at `eval_horizon` steps: both higher is better. Evaluation episodes play the
imitation policy from pixels in the task (eval/return is the task's return).
"""

from __future__ import annotations

import re

from cdjax.agents.pixel.config import HP_RANGES, PixelConfig, PixelHParams
from cdjax.agents.pixel.learner import PixelLearner
from cdjax.consistency import collapse_warning
from cdjax.protocol import ConfigError, Metrics, Preset, Setting, Trainer

ARMS = ("ltq", "ltq-cd")
CONSISTENCY_ONLY = ("alpha", "cc_model", "cc_policy", "enc_aux_coef")


def arm_config(name: str, base: PixelConfig) -> PixelConfig:
    """An arm name -> its Config: "ltq", "ltq-cd", or "ltq-cdK" (ltq-cd with horizon K, e.g. ltq-cd5)."""
    match = re.fullmatch(r"(ltq|ltq-cd)(\d+)?", name)
    if match is None:
        raise ConfigError(f"Unknown arm {name!r}; choose ltq or ltq-cd (ltq-cd optionally with a horizon, e.g. "
                          "ltq-cd5).")
    arm, k = match.groups()
    if k is not None and arm == "ltq":
        raise ConfigError(f"Arm {name!r}: only ltq-cd takes a horizon in its name (e.g. ltq-cd5); ltq's k (of its "
                          "\"at k\" likelihood) is --horizon.")
    try:
        return base.replace(arm=arm, **({"horizon": int(k)} if k else {}))
    except ConfigError as err:
        raise ConfigError(f"Arm {name!r}: {err}") from None


check_hparam = HP_RANGES.check_one


def make_trainer(config: PixelConfig) -> Trainer:
    return trainer_of(PixelLearner(config))


def trainer_of(learner: PixelLearner) -> Trainer:
    """The protocol's view of a learner (e.g. one built on another world than the rendered task)."""
    # runs_split "local": under the partitioner the runs' vmapped convolutions (per-run weights) were all-gathered
    # across devices (102 all-gathers in the chunk, 4 H200s slower than one); each device now runs its own runs
    return Trainer(config=learner.config, init=learner.init, update=learner.update, policy=learner.policy,
                   act=learner.act, eval_env=learner.world.eval_env, saved_leaves=learner.saved_leaves, inner=learner,
                   runs_split="local")


# alpha: the ELBO is summed over 12,288 pixel terms per frame and 50 steps, so at alpha = 1 l_cc's gradient on the
# transition was ~0.15% of the ELBO's (measured at init on the 64x64 model: global norms 0.12 vs 81 for 12 steps;
# gradient clipping by value 1.0 was active on 0.07% of the elements). The presets run alpha 100 (1000 did no better
# on the log-likelihoods and worse on imitation at 400 updates on halfcheetah) with l_cc's path into the policy on
# (cc_policy 1, the paper's CD) and off (0): with it on, the held-out imitation error was worse than LtQ's in two
# independent 10-seed runs on halfcheetah (0.354 and 0.357 against 0.320), with it off equal (0.322 and 0.321;
# experiments/pixel/RESULTS.md). One program, vmapped with the seeds; the paper gives no alpha for this setting.
ALPHAS = (100.0,)
CC_POLICY = (0.0, 1.0)
# The grounded encoder's own loss at 10 (enc_aux_coef; the observation and Atari presets keep 1): l_cc's gradient
# reaches the encoder at cc_model whatever alpha is (`consistency.path_weights`), and the encodings shrink while
# cc_model x l_cc / spread exceeds enc_aux_coef, which at the start of training is 1.8-2.5 here (pixel-tiny and
# halfcheetah's update 1: 1.5). On pixel-tiny (CPU, 3 seeds, alpha 100, 3,000 updates) the spread fell from 0.06 to
# 0.01 and recovered after ~1,500 updates at 1, and never fell below 0.04 at 10 (0.57 at the end). Before
# path_weights, alpha 100 also weighed the encoder's share and every encoder of halfcheetah's 20 cd runs shrank
# ~10,000x by 10,000 updates (experiments/pixel/RESULTS.md, "Fifth pass").
ENC_AUX = (10.0,)
# What the task presets run (issue 22, one H200, 2026-11-25, experiments/pixel/RESULTS.md):
# - bfloat16 operands with each run's convolutions as its own (per-run): 2.86x float32/grouped's frames/s in a
#   sweep (115,759 against 40,530; 133k in the roofline), and held-out ELBO, log-likelihoods and imitation error
#   matched float32's on all 15 metric x arm pairs (halfcheetah, 3 arms x 10 seeds, 300 updates).
# - the model's Adam rate stays 1e-4 (the authors'): of 3e-5, 1e-4, 3e-4 and 1e-3 it gave the best held-out ELBO
#   and log-likelihood at 50 after 500 updates (ltq, halfcheetah, 5 seeds); 3e-4 and 1e-3 were lower, 3e-5's
#   log-likelihood at 50 collapsed. The policy's own rate 1e-3 cut the held-out imitation error from 0.270
#   [0.262, 0.279] to 0.234 [0.224, 0.239] with the ELBO inside the other's interval (9,471 against 11,459).
# - core_impl fused (2026-11-26, one H200, experiments/pixel/data/core-h200/): the same function as flax (tested to
#   float32 rounding) at 1.18x the frames/s for 10 runs (151,254 against 128,152; 2,800 kernels per update against
#   8,274) and 1.08x for 30 (147,989 against 137,323). `--compute-dtype float32 --conv-impl grouped --core-impl
#   flax` is the model of before, bit for bit.
# - output_grad compute (2026-11-26, one H200, experiments/pixel/data/grad-dtype-h200/): the output layers'
#   gradients as bfloat16 products (their forward unchanged) at 1.12x the update's frames/s for 30 runs (164,654
#   against 147,145: the decoder's output layer's TF32 gradient convolutions were ~12 % of the kernel time), 1.11x as
#   a sweep (164,678 against 148,675 over 300 updates), and held-out ELBO, log-likelihoods and imitation error
#   matched output_grad float32's on all 15 metric x arm pairs (halfcheetah, 3 arms x 10 seeds, 300 updates).
#   `--compute-dtype float32` alone still gives full float32 (output_grad changes nothing there).
FAST = dict(compute_dtype="bfloat16", conv_impl="per-run", core_impl="fused", output_grad="compute")
LR_POLICY = (1e-3,)


def _preset(env: str, *, horizon: int, frames: int, about: str, **config) -> Preset:
    config = {**FAST, **config}
    return Preset(about=about, config=dict(env=env, horizon=horizon, **config),
                  hparams={"alpha": ALPHAS, "cc_policy": CC_POLICY, "enc_aux_coef": ENC_AUX, "lr_policy": LR_POLICY}, sweep=dict(arms=ARMS, seeds=10, total_env_steps=frames, chunk_updates=200, eval_episodes=4))


PRESETS = {
    "pixel-halfcheetah": _preset("halfcheetah", horizon=10, frames=8_000_000,
                                 about="paper, pixels: halfcheetah, ltq vs ltq-cd (k=10, alpha 100, cc_policy 0 and 1) x 10 seeds, 10k updates"),
    # reacher's expert acts every 4 physics steps (cdjax's reacher preset): its episodes are 250 agent steps
    "pixel-reacher": _preset("reacher", horizon=5, frames=8_000_000, eval_episode_length=250,
                             about="paper, pixels: reacher, ltq vs ltq-cd (k=5, alpha 100, cc_policy 0 and 1) x 10 seeds, 10k updates"),
    "pixel-pusher": _preset("pusher", horizon=5, frames=8_000_000,
                            about="paper, pixels: pusher (Fetch-Push stand-in), ltq vs ltq-cd (k=5, alpha 100, cc_policy 0 and 1) x 10 seeds"),
    # Tests and trying the command on a CPU: 16x16 frames, tiny networks, a few updates.
    "pixel-tiny": Preset(
        about="CPU plumbing: reacher at 16x16, tiny networks, 2 seeds, 6 updates",
        config=dict(env="reacher", image_size=16, conv_channels=4, embed_dim=16, hidden=16, latent=4, mlp=16,
                    policy_hidden=(16,), num_sequences=4, heldout_sequences=2, seq_len=6, batch_size=2, burn_in=2,
                    context=2, eval_horizon=3, horizon=2, cc_windows=2, encoder_dim=8, eval_episode_length=3),
        hparams={"lr": (1e-3,)},
        sweep=dict(arms=ARMS, seeds=2, total_env_steps=6 * 12, chunk_updates=3, eval_episodes=2)),
}


def preset_of_env(given) -> str | None:
    name = "pixel-" + given.get("env", PixelConfig.env)
    return name if name in PRESETS else None


SETTING = Setting(
    name="pixel", about="pixel state-space models (Learning to Query) with imitation (the paper's second setting)",
    config_type=PixelConfig, hparams_type=PixelHParams, make_trainer=make_trainer, arm_config=arm_config,
    arm_fields=("arm",), arms_help="ltq, ltq-cd, or ltq-cdN for ltq-cd with horizon N", default_arms=ARMS,
    unused_hparams=lambda config, phase: {} if config.use_consistency else {n: None for n in CONSISTENCY_ONLY},
    shown_hparams=lambda config: ("alpha",) if config.use_consistency else (),
    check_hparam=check_hparam,
    metrics=Metrics(ret="heldout/loglik_k", discounted_ret="heldout/loglik_50", skipped="train/skipped_steps",
                    ret_field="horizon", panels=(
        ("heldout/imitation", "held-out imitation loss", True),
        ("loss/imitation", "imitation loss", True),
        ("model/elbo_per_frame", "ELBO per frame (nats)", False),
        ("loss/consistency", "consistency loss", True),
        ("encoder/spread_real", "encoder spread (real)", False))),
    presets=PRESETS, default_preset=preset_of_env, watch=collapse_warning)

__all__ = ["ARMS", "PRESETS", "SETTING", "PixelConfig", "PixelHParams", "PixelLearner", "arm_config", "make_trainer",
           "trainer_of"]
