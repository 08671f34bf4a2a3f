"""The pixel setting's flax modules: the convolutional frame encoder and decoder, the model's core (prior, posterior,
LSTM transition) and the imitation policy. `model.LtqModel` puts them together."""

from __future__ import annotations

import flax.linen as nn
import jax
import jax.numpy as jnp

from cdjax.agents.pixel.convs import conv_kwargs, dense_kwargs


class ConvEncoder(nn.Module):
    """Convolutions of 4x4, stride 2, ReLU, then a dense layer. compute_dtype, conv_impl and output_grad:
    PixelConfig's (convs.py); the output is float32 in any compute dtype."""

    layers: int
    channels: int
    features: int
    compute_dtype: str = "float32"
    conv_impl: str = "grouped"
    output_grad: str = "float32"

    @nn.compact
    def __call__(self, x):  # [N, S, S, C] -> [N, features]
        for _ in range(self.layers):
            conv = nn.Conv(self.channels, (4, 4), strides=(2, 2), padding="SAME",
                           **conv_kwargs(self.conv_impl, self.compute_dtype, channels=(x.shape[-1], self.channels)))
            x = nn.relu(conv(x))
        dense = nn.Dense(self.features, **dense_kwargs(self.compute_dtype, True, self.output_grad))
        return dense(x.reshape(x.shape[0], -1))


def depth_to_space(y: jax.Array, factor: int = 2) -> jax.Array:
    """[N, H, W, f*f*C] -> [N, f*H, f*W, C]: each pixel's channels become an f x f block of pixels."""
    n, h, w, c = y.shape
    y = y.reshape(n, h, w, factor, factor, c // factor ** 2)
    return y.transpose(0, 1, 3, 2, 4, 5).reshape(n, h * factor, w * factor, c // factor ** 2)


class ConvDecoder(nn.Module):
    """Mirror of the encoder: each layer doubles the resolution.

    upsample "transpose": 4x4 transposed convolutions of stride 2. "subpixel": a 3x3 convolution of stride 1 to
    four times the channels, then each pixel's channels become a 2x2 block (depth_to_space). A 4x4 stride-2
    transposed convolution computes each output pixel from a 2x2 neighbourhood of its input, which a 3x3 window
    contains, so "subpixel" can represent every "transpose" layer; it avoids the input-dilated convolutions
    (three zeros in four inputs) that a transposed convolution is lowered to.

    compute_dtype, conv_impl and output_grad: PixelConfig's (convs.py, "subpixel" only); the means and scales
    are float32."""

    size: int
    layers: int
    channels: int
    min_std: float
    upsample: str = "subpixel"  # PixelConfig.upsample's default
    compute_dtype: str = "float32"
    conv_impl: str = "grouped"
    output_grad: str = "float32"

    def _up(self, y, features, output=False):
        if self.upsample == "subpixel":
            conv = nn.Conv(4 * features, (3, 3), padding="SAME",
                           **conv_kwargs(self.conv_impl, self.compute_dtype, output, (y.shape[-1], 4 * features),
                                         self.output_grad))
            return depth_to_space(conv(y))
        return nn.ConvTranspose(features, (4, 4), strides=(2, 2), padding="SAME")(y)

    @nn.compact
    def __call__(self, x):  # [N, D] -> (mean, std) [N, S, S, 3]
        start = self.size // 2 ** self.layers
        dense = nn.Dense(start * start * self.channels, **dense_kwargs(self.compute_dtype))
        y = nn.relu(dense(x)).reshape(-1, start, start, self.channels)
        for _ in range(self.layers - 1):
            y = nn.relu(self._up(y, self.channels))
        y = self._up(y, 6, output=True)
        return y[..., :3], nn.softplus(y[..., 3:]) + self.min_std


class Core(nn.Module):
    """Prior, posterior and the LSTM transition."""

    hidden: int
    latent: int
    mlp: int
    min_std: float

    def setup(self):
        self.prior_hidden, self.prior_out = nn.Dense(self.mlp), nn.Dense(2 * self.latent)
        self.post_hidden, self.post_out = nn.Dense(self.mlp), nn.Dense(2 * self.latent)
        self.cell = nn.OptimizedLSTMCell(self.hidden)

    def _gaussian(self, out):
        mean, raw = jnp.split(out, 2, axis=-1)
        return mean, nn.softplus(raw) + self.min_std

    def prior(self, h, a):
        return self._gaussian(self.prior_out(nn.relu(self.prior_hidden(jnp.concatenate([h, a], -1)))))

    def posterior(self, e, h, a):
        return self._gaussian(self.post_out(nn.relu(self.post_hidden(jnp.concatenate([e, h, a], -1)))))

    def transition(self, h, c, z, a):
        (c, h), _ = self.cell((c, h), jnp.concatenate([z, a], -1))
        return h, c

    def __call__(self, e, h, c, a):  # touches every part (for init)
        mean, std = self.posterior(e, h, a)
        self.prior(h, a)
        return self.transition(h, c, mean, a)


class Policy(nn.Module):
    hidden: tuple[int, ...]
    actions: int

    @nn.compact
    def __call__(self, h):
        for width in self.hidden:
            h = nn.relu(nn.Dense(width)(h))
        return jnp.tanh(nn.Dense(self.actions)(h))
