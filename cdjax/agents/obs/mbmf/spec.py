"""The Mb-Mf phase's static sizes (`MbMfPhase`), the env steps it takes, and its validation."""

from __future__ import annotations

import dataclasses
from typing import Literal

from cdjax.agents.obs.config import Config
from cdjax.protocol import ConfigError

ModelObjective = Literal["mse", "nll"]
HANDOVER_CHECKS = 4  # rollouts of `handover_steps`: distilled and untrained policy, each sampled and with its mean action
MpcReward = Literal["model", "true"]


@dataclasses.dataclass(frozen=True)
class MbMfPhase:
    """Static sizes of the model-based phase; defaults follow Nagabandi et al.'s Half-Cheetah settings.

    With the defaults the phase takes 10 x (1000 + 7 x 1000 + 3 x 200) = 86,000 env steps (x action_repeat);
    it is latency-bound on a GPU: ~8,600 sequential MPC steps and ~150,000 small Adam steps.
    """

    num_envs: int = 10  # environments stepped in parallel by the phase (its own BatchedEnv); 0 = config.num_envs
    random_steps: int = 1000  # uniform-random steps per env before the first model (Nagabandi: 10 rollouts x 1000)
    aggregation_iters: int = 7  # rounds of MPC data collection + model retraining (Nagabandi, cheetah: 7)
    mpc_steps_per_iter: int = 1000  # MPC steps per env per round (Nagabandi: 10 rollouts x 1000)
    model_epochs: int = 60  # shuffled epochs over the model buffer at each (re)training (Nagabandi: 60)
    model_minibatch: int = 512  # transitions per model gradient step (Nagabandi: 512)
    buffer_size: int = 0  # model dataset capacity (ring buffer, oldest overwritten); 0 = all the phase collects
    model_objective: ModelObjective = "mse"  # mse: mean by MSE (Nagabandi), log_std by NLL; nll: losses.model_loss
    mpc_horizon: int = 20  # random-shooting planning horizon (Nagabandi, cheetah: 20; ant: 5)
    mpc_candidates: int = 1000  # action sequences sampled per state (Nagabandi, cheetah: 1000; ant: 15000)
    mpc_discount: float = 1.0  # predicted reward t weighted by discount**t (Nagabandi: 1, undiscounted)
    mpc_reward: MpcReward = "model"  # candidates scored by the model's reward, or "true": the task's reward of predicted obs
    mpc_elites: int = 1  # the MPC acts with the mean first action of its best mpc_elites candidates (1: Nagabandi's)
    onpolicy_fraction: float = 0.0  # share of model minibatches from the MPC data (Nagabandi's fraction_use_new); 0: uniform
    distill_iters: int = 3  # DAgger rounds after the first behaviour cloning (Nagabandi, cheetah: 3)
    distill_steps_per_iter: int = 200  # policy steps per env per DAgger round (Nagabandi, cheetah: 2 x 1000 in all)
    dagger_deterministic: bool = False  # DAgger rollouts act with the policy's mean action tanh(mu), not a sample
    distill_epochs: int = 200  # shuffled epochs over the distillation buffer per (re)training (Nagabandi: 70-300)
    distill_minibatch: int = 512  # (state, MPC action) pairs per policy gradient step; also the value's (Nagabandi: 512)
    distill_buffer_size: int = 0  # distillation dataset capacity (ring buffer); 0 = every labelled state
    relabel: bool = True  # re-plan the aggregation states with the final model before cloning (no env steps)
    relabel_chunk: int = 1024  # states planned for at once when relabelling (memory: chunk x candidates x width)
    value_epochs: int = 10  # epochs fitting the value to TD(lambda) returns of the DAgger rollouts; 0 = untouched
    hand_policy: bool = True  # PPO starts from the distilled policy; False: the initial one (ablation: model, norms, value)
    handover_steps: int = 0  # steps per env of 4 checks of the policy PPO gets against an untrained one; 0 = none

    def envs(self, config: Config) -> int:
        return self.num_envs or config.num_envs

    def steps_per_env(self) -> int:
        return self.random_steps + self.aggregation_iters * self.mpc_steps_per_iter + \
            self.distill_iters * self.distill_steps_per_iter + HANDOVER_CHECKS * self.handover_steps

    def model_capacity(self, config: Config) -> int:
        """Transitions the model buffer holds."""
        collected = self.envs(config) * (self.random_steps + self.aggregation_iters * self.mpc_steps_per_iter)
        return self.buffer_size or collected

    def distill_capacity(self, config: Config) -> int:
        """(state, MPC action) pairs the distillation buffer holds."""
        labelled = self.envs(config) * (self.aggregation_iters * self.mpc_steps_per_iter
                                        + self.distill_iters * self.distill_steps_per_iter)
        return self.distill_buffer_size or max(labelled, 1)


def total_env_steps(config: Config, phase: MbMfPhase) -> int:
    """Environment steps the phase takes (physics steps: x action_repeat), computed statically."""
    return phase.envs(config) * phase.steps_per_env() * config.action_repeat


def validate_phase(config: Config, phase: MbMfPhase) -> None:
    """Raise ConfigError (one sentence) for a phase that cannot run; compiles nothing."""
    if not config.use_model:
        raise ConfigError(f"The Mb-Mf phase needs a dynamics model, but arm={config.arm!r} builds none.")
    positive = ("random_steps", "model_epochs", "model_minibatch", "mpc_horizon", "mpc_candidates", "mpc_elites",
                "distill_epochs", "distill_minibatch", "relabel_chunk")
    non_negative = ("num_envs", "aggregation_iters", "mpc_steps_per_iter", "distill_iters",
                    "distill_steps_per_iter", "buffer_size", "distill_buffer_size", "value_epochs", "handover_steps")
    for name in positive + non_negative:
        value = getattr(phase, name)
        low = 1 if name in positive else 0
        if not isinstance(value, int) or isinstance(value, bool) or value < low:
            kind = "a positive" if low else "a non-negative"
            raise ConfigError(f"MbMfPhase.{name} must be {kind} integer, got {value!r}.")
    if not 0.0 < phase.mpc_discount <= 1.0:
        raise ConfigError(f"MbMfPhase.mpc_discount must lie in (0, 1], got {phase.mpc_discount!r}.")
    if phase.model_objective not in ("mse", "nll"):
        raise ConfigError(f"Unknown MbMfPhase.model_objective {phase.model_objective!r}; choose mse or nll.")
    if phase.mpc_reward not in ("model", "true"):
        raise ConfigError(f"Unknown MbMfPhase.mpc_reward {phase.mpc_reward!r}; choose model or true.")
    if phase.mpc_reward == "true":
        from cdjax.envs import rewards  # local: the env layer imports brax

        if rewards.reward_fn(config.env) is None:
            raise ConfigError(f"MbMfPhase.mpc_reward='true' needs the task's reward as a function of observations, and "
                              f"{config.env} has none: {rewards.why_not(config.env)}; use mpc_reward='model'.")
        if rewards.needs_action_repeat_one(config.env) and config.action_repeat != 1:
            raise ConfigError(f"MbMfPhase.mpc_reward='true' on {config.env} needs action_repeat = 1.")
    if phase.mpc_elites > phase.mpc_candidates:
        raise ConfigError(f"MbMfPhase.mpc_elites={phase.mpc_elites} is more than its {phase.mpc_candidates} candidates.")
    if not (isinstance(phase.onpolicy_fraction, (int, float)) and not isinstance(phase.onpolicy_fraction, bool)
            and 0.0 <= phase.onpolicy_fraction < 1.0):
        raise ConfigError(f"MbMfPhase.onpolicy_fraction must lie in [0, 1), got {phase.onpolicy_fraction!r}.")
    if phase.onpolicy_fraction > 0 and phase.buffer_size:
        raise ConfigError("MbMfPhase.onpolicy_fraction > 0 needs buffer_size = 0 (every transition kept: the random "
                          "data stays at the front of the model's buffer).")
    for name in ("relabel", "dagger_deterministic", "hand_policy"):
        if not isinstance(getattr(phase, name), bool):
            raise ConfigError(f"MbMfPhase.{name} must be true or false, got {getattr(phase, name)!r}.")
    B = phase.envs(config)
    biggest = B * max(phase.random_steps, phase.mpc_steps_per_iter)
    if phase.model_capacity(config) < biggest:
        raise ConfigError(f"MbMfPhase.buffer_size={phase.buffer_size} cannot hold one stage's {biggest} transitions.")
    biggest = B * max(phase.mpc_steps_per_iter, phase.distill_steps_per_iter)
    if phase.distill_capacity(config) < biggest:
        raise ConfigError(
            f"MbMfPhase.distill_buffer_size={phase.distill_buffer_size} cannot hold one stage's {biggest} labelled states.")
