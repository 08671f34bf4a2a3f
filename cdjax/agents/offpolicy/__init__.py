"""The off-policy setting: a sample-efficient actor-critic with a latent model and either consistency term.

    from cdjax.agents.offpolicy import Config, HParams, make_train

Why the SAC family: the sample-efficient agents whose consistency losses the question is about (TD-MPC2, MR.Q,
SPR-style and BBF-style critics, MAD-TD) learn a stochastic or entropy-regularised policy beside clipped or
ensembled critics, and Brax ships SAC for the same MJX tasks, which makes a parity check in one process possible.
The learner: an ensemble of Q functions with LayerNorm (the target takes the minimum: clipped double Q at 2),
n-step returns, an auto-tuned entropy temperature, Polyak targets, running observation statistics, num_envs envs
feeding a replay buffer in the TrainState, `updates_per_step` gradient steps per batched env step (the
update-to-data ratio), uniform random actions until `learning_starts` env steps, time-outs bootstrapped and
terminations not, non-finite env states reset and their transitions masked (`cdjax.envs`).

Arms (Config.arm), the same code with switches:
- `model-free`: SAC. With inputs="obs+latent" (the default) or "latent" the actor and critic read an encoder's latent
  (beside the normalised observation for "obs+latent") that only the critic's loss trains, so that the other arms
  differ from it by their losses alone; inputs="obs" has no encoder (Brax's SAC reads observations so). Why this
  default: docs/settings/offpolicy.md (the parity with Brax's SAC).
- `model`: a latent model (encoder, latent transition, reward head, observation decoder) trained by one-step
  prediction of the next observation and the reward; no consistency term.
- `paper-cd`: the model arm plus the paper's term (`cdjax.consistency.consistency_loss`): a GRU encoding of the real
  k-step window of observations against one of the window the model imagines from its first state. The model path
  reaches the encoder and the model (alpha x cc_model); the policy path (alpha x cc_policy) is defined off-policy by
  a straight-through action (`cdjax.consistency.selfpredictive.policy_path`): the window keeps the replayed actions' values,
  older policies' choices, and their gradient goes to the current actor's deterministic action at the same states.
- `self-pred`: the model arm plus the self-predictive term (`cdjax.consistency.selfpredictive`): the latent transition rolled out
  k steps from enc(s_0) under the replayed actions against an EMA target encoder's latents, weight alpha.
Every arm with a model has the actor and critic read the encoder's latent beside the observation (as OFENet does;
with inputs="latent" the latent alone, as TD-MPC2 and MR.Q do), the critic's gradient and the model's losses shaping it
and the actor reading it under stop_gradient, so that the representation is what the auxiliary losses change. At
alpha 0 both consistency arms take the model arm's gradients.

The modules: `config` (Config, HParams), `learner` (the jitted update; make_train, make_trainer, what a checkpoint
keeps), `networks`, `losses`, `presets`. This module adapts them to `cdjax.protocol` (SETTING).
"""

from __future__ import annotations

from cdjax.agents.offpolicy.config import ARMS, HP_RANGES, Config, HParams
from cdjax.agents.offpolicy.learner import Learner, TrainState, make_train, make_trainer
from cdjax.agents.offpolicy.presets import PRESETS
from cdjax.protocol import ConfigError, Metrics, Setting

RETURN = "episode/return"
DISC_RETURN = "episode/discounted_return"
MODEL_ONLY = ("lr_model", "model_coef")
CONSISTENCY_ONLY = ("alpha", "cc_model", "cc_policy", "enc_aux_coef", "rho")
UNUSED = {"model-free": MODEL_ONLY + CONSISTENCY_ONLY, "model": CONSISTENCY_ONLY,
          "paper-cd": ("rho",), "self-pred": ("cc_model", "cc_policy", "enc_aux_coef")}
FIXED = {"alpha": 0.0}


def arm_config(name: str, base: Config) -> Config:
    if name not in ARMS:
        raise ConfigError(f"Unknown arm {name!r}; choose from: {', '.join(ARMS)}.")
    try:
        return base.replace(arm=name)
    except ConfigError as err:
        raise ConfigError(f"Arm {name!r}: {err}") from None


def preset_of_env(given) -> str | None:
    env = given.get("env", Config.env)
    return {"inverted_pendulum": "pendulum"}.get(env, env) if env in PRESETS or env == "inverted_pendulum" else None


SETTING = Setting(
    name="offpolicy", about="an off-policy SAC-family learner with a latent model and either consistency term",
    config_type=Config, hparams_type=HParams, make_train=make_train, make_trainer=make_trainer, arm_config=arm_config,
    arm_fields=("arm",),
    arms_help=", ".join(ARMS), default_arms=ARMS,
    unused_hparams=lambda config, phase: {name: FIXED.get(name) for name in UNUSED[config.arm]},
    shown_hparams=lambda config: ("alpha",) if config.use_consistency else (),
    check_hparam=HP_RANGES.check_one,
    metrics=Metrics(ret=RETURN, discounted_ret=DISC_RETURN, skipped="train/skipped_steps", panels=(
        ("loss/critic", "critic loss", True), ("train/temperature", "entropy temperature", True),
        ("loss/model", "model loss (one step)", True), ("loss/self_predictive", "self-predictive loss", True),
        ("loss/consistency", "paper's consistency loss", True))),
    presets=PRESETS, default_preset=preset_of_env)

__all__ = ["ARMS", "Config", "HParams", "Learner", "PRESETS", "SETTING", "TrainState", "make_train", "make_trainer"]
