"""Static configuration and traced hyper-parameters of the pixel setting (Learning to Query + imitation)."""

from __future__ import annotations

import dataclasses
from typing import Literal

from flax import struct

from cdjax.checks import POSITIVE, UNIT, Choice, Count, Fields, HParamRanges, Real, Text
from cdjax.consistency import KINDS
from cdjax.protocol import ConfigError

Arm = Literal["ltq", "ltq-cd"]
ImagineActions = Literal["policy", "expert"]
Upsample = Literal["transpose", "subpixel"]
ComputeDtype = Literal["float32", "bfloat16"]
ConvImpl = Literal["grouped", "per-run", "auto", "matmul"]
CoreImpl = Literal["flax", "fused"]
OutputGrad = Literal["float32", "compute"]
PIXEL_ENVS = ("halfcheetah", "reacher", "pusher")


@dataclasses.dataclass(frozen=True)
class PixelConfig:
    """Everything that fixes a shape, a loop length or the graph of the compiled update."""

    env: str = "halfcheetah"  # MJX task rendered to pixels: halfcheetah, reacher or pusher
    arm: Arm = "ltq-cd"  # ltq: the state-space model and imitation; ltq-cd: plus the consistency term
    expert: str = ""  # file written by cdjax.agents.experts.save_expert; "" = an untrained policy (tests)
    expert_sample: bool = True  # the expert samples its Gaussian policy in the data (False: acts by its mean)
    image_size: int = 64  # S: frames are S x S x 3 (a multiple of 2^conv_layers)
    frame_stack: int = 4  # frames per observation (the encoder's input has 3 x frame_stack channels)
    conv_layers: int = 4  # convolutions of the encoder (4x4 kernels, stride 2), mirrored by the decoder
    conv_channels: int = 64  # channels of every convolution
    upsample: Upsample = "subpixel"  # decoder layers: 4x4 stride-2 transposed convolutions ("transpose"), or (3x3
    # convolutions to 4x the channels, then depth_to_space; see model.ConvDecoder)
    compute_dtype: ComputeDtype = "float32"  # operands of the encoder's and decoder's convolutions and dense
    # layers: float32, or bfloat16 (parameters, optimiser state, the LSTM, the policy and the ELBO's sums stay
    # float32; see convs.py)
    conv_impl: ConvImpl = "grouped"  # how a sweep's vmapped runs meet the convolutions: grouped (XLA's grouped
    # convolution), per-run (one ungrouped convolution per run), auto (per layer: per-run for the narrow first and
    # last layers, grouped for the rest; convs.py) or matmul (patches x kernel, a batched product)
    output_grad: OutputGrad = "float32"  # operands of the output layers' gradient products: float32 or compute
    # (compute_dtype's). The encoder's and decoder's output layers return float32 in any compute dtype; their
    # backward pass takes that cotangent as it is (float32: their gradients are float32 products, TF32 on a GPU; the
    # model of before) or cast to compute_dtype (bfloat16 products, as the hidden layers' gradients are;
    # convs.operands_in). With compute_dtype float32 both are float32, bit for bit.
    core_impl: CoreImpl = "flax"  # how the filter's and the prior's steps compute: flax (the modules' calls: the
    # model of before, bit for bit) or fused (the same function to float32 rounding, in fewer kernels per step on a
    # GPU: the filter's products on h merged and the inputs' shares taken out of its loop, its backward written out,
    # the prior's step without concatenating its inputs (under given actions their share taken out of the loop), and
    # the consistency term's k steps with both encodings unrolled, its backward written out; model.py, chain.py)
    embed_dim: int = 256  # e(o): the encoder's output size
    hidden: int = 256  # LSTM state size (h and c each)
    latent: int = 100  # z: per-step latent size
    mlp: int = 256  # width of the prior's and the posterior's hidden layer
    policy_hidden: tuple[int, ...] = (256,)  # imitation policy MLP on the LSTM output h
    min_std: float = 0.01  # floor of every predicted standard deviation (latents and pixels)
    num_sequences: int = 512  # N: expert training sequences kept on the device per run
    heldout_sequences: int = 32  # M: held-out expert sequences (metrics and strips)
    seq_len: int = 50  # L: steps per training sequence
    batch_size: int = 16  # sequences per update
    burn_in: int = 50  # expert steps after a reset before a sequence starts (unrendered)
    context: int = 5  # held-out: filtered steps before the open-loop prediction starts
    eval_horizon: int = 50  # held-out: open-loop steps (the paper's long-horizon test: 50)
    horizon: int = 10  # k: open-loop length of the consistency windows and of the "at k" likelihood
    cc_windows: int = 4  # consistency windows per training sequence (random starts)
    encoder: str = "grounded-gru"  # consistency encoder: grounded-gru, gru, frozen-gru or l2 (cdjax.consistency)
    encoder_dim: int = 64  # GRU size of the consistency encoder
    imagine_actions: ImagineActions = "policy"  # actions of the consistency's open loop: the policy's on the
    # imagined states (the authors' code; the only way l_cc reaches the policy) or the expert's
    eval_episode_length: int = 1000  # agent steps of an evaluation episode (the imitation policy from pixels)
    num_updates: int = 1000  # updates of one run

    def __post_init__(self):
        FIELDS.check(self)  # every field's type and range (cdjax.checks); what follows relates fields
        if self.image_size % (2 ** self.conv_layers):
            raise ConfigError(f"image_size={self.image_size} must be a multiple of 2^conv_layers = "
                              f"{2 ** self.conv_layers}.")
        if not self.horizon < self.seq_len:
            raise ConfigError(f"horizon={self.horizon} must be below seq_len={self.seq_len}.")
        if self.cc_windows > self.seq_len - self.horizon:  # windows of k steps among a sequence's seq_len - 1 actions
            raise ConfigError(f"cc_windows={self.cc_windows} is more than the {self.seq_len - self.horizon} k-step "
                              f"windows a sequence of seq_len={self.seq_len} holds (k={self.horizon}).")
        if self.upsample == "transpose" and (self.compute_dtype, self.conv_impl) != ("float32", "grouped"):
            raise ConfigError(f"upsample='transpose' runs only with compute_dtype='float32' and conv_impl='grouped' "
                              f"(got {self.compute_dtype!r} and {self.conv_impl!r}); use upsample='subpixel'.")
        if not self.horizon <= self.eval_horizon:
            raise ConfigError(f"horizon={self.horizon} must not exceed eval_horizon={self.eval_horizon}.")

    @property
    def use_consistency(self) -> bool:
        return self.arm == "ltq-cd"

    @property
    def env_steps_per_update(self) -> int:
        """Frames an update trains on (the sweep's budget counts these)."""
        return self.batch_size * self.seq_len

    def replace(self, **kw) -> "PixelConfig":
        return dataclasses.replace(self, **kw)


# The kind and range of every Config field (cdjax.checks; the Literal, tuple and bool fields take theirs from
# their annotations), checked when a Config is built.
FIELDS = Fields(
    PixelConfig, env=Choice(PIXEL_ENVS), expert=Text(), image_size=Count(1), frame_stack=Count(1),
    conv_layers=Count(1, high=16), conv_channels=Count(1), embed_dim=Count(1), hidden=Count(1), latent=Count(1),
    mlp=Count(1), min_std=Real(POSITIVE), num_sequences=Count(1), heldout_sequences=Count(1), seq_len=Count(2),
    batch_size=Count(1), burn_in=Count(0), context=Count(1), eval_horizon=Count(1), horizon=Count(1),
    cc_windows=Count(1), encoder=Choice(KINDS), encoder_dim=Count(1), eval_episode_length=Count(1),
    num_updates=Count(1))


@struct.dataclass
class PixelHParams:
    """Traced float32 scalars (vmappable with the seeds)."""

    lr: float = 1e-4  # Adam step size (the authors' code: 1e-4)
    lr_policy: float = 0.0  # Adam step size of the imitation policy's parameters; 0: the same as lr
    clip: float = 1.0  # gradient clipping by value (the authors' code: 1.0)
    imitation_coef: float = 1.0  # weight of the imitation loss (mean squared error of the expert's actions)
    alpha: float = 1.0  # weight of l_cc (ltq-cd only)
    cc_model: float = 1.0  # multiplier of l_cc's gradient into the transition and the encoder (paper: 1)
    cc_policy: float = 1.0  # multiplier of l_cc's gradient into the policy through imagined actions (paper: 1)
    enc_aux_coef: float = 1.0  # weight of the grounded encoder's own loss (reconstruction + spread floor)
    gamma: float = 0.99  # discount of the evaluation's discounted return


# The range of every HParams field (the rest: not negative), checked on the command line's grid and by `init`.
HP_RANGES = HParamRanges(PixelHParams, lr=POSITIVE, clip=POSITIVE, gamma=UNIT)


Config, HParams = PixelConfig, PixelHParams  # the face every setting shares: cdjax.agents.<setting>.Config, HParams
