"""The light-field encoder CNN of Currius et al. 2020, §4 ("Encoder Network").

Four blocks of 3 x 3 convolution (same padding) -> 2 x 2 max pooling -> ReLU, with 32 channels
in the first block doubling to 256 in the fourth (a 128 x 128 input ends as 8 x 8 x 256), then
one fully connected layer without activation to N x M outputs: M raw parameters for each of N
spherical Gaussians (the caller maps them to axes, sharpnesses and amplitudes).
"""

from __future__ import annotations

from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp

__all__ = ["CNN", "sg_encoder"]


class CNN(NamedTuple):
    """``init(key)``, ``apply(params, images (B, H, W, C)) -> (B, n_lobes, params_per_lobe)``."""

    init: Callable
    apply: Callable
    output_shape: tuple[int, int]


def sg_encoder(*, image_size: int = 128, in_channels: int = 3, n_lobes: int = 16, params_per_lobe: int = 7,
               channels=(32, 64, 128, 256), dtype=jnp.float32) -> CNN:
    """The encoder for square ``image_size`` inputs (divisible by 2^len(channels)).

    Numerics:
        case: sg_encoder (16 x 16 images in [0, 12] (log(1 + radiance) of radiance to 1e5), channels
          (4, 8), as ``init`` draws the weights; gradients w.r.t. the weights and the images)
        fd: off (ReLU and max-pooling have kinks)
        float32: value rtol 1e-4 atol 1e-5; grad rtol 1e-4 atol 1e-5
    """
    blocks = len(channels)
    if image_size % (2**blocks):
        raise ValueError(f"image size {image_size} must be divisible by {2**blocks}")
    final = image_size // 2**blocks
    flat = final * final * channels[-1]
    n_out = n_lobes * params_per_lobe

    def init(key):
        keys = jax.random.split(key, blocks + 1)
        convs = []
        c_in = in_channels
        for k, c_out in zip(keys[:-1], channels):
            fan_in = 9 * c_in
            convs.append({"w": jax.random.normal(k, (3, 3, c_in, c_out), dtype) * (2.0 / fan_in) ** 0.5,
                          "b": jnp.zeros((c_out,), dtype)})
            c_in = c_out
        limit = (6.0 / (flat + n_out)) ** 0.5
        dense = {"w": jax.random.uniform(keys[-1], (flat, n_out), dtype, -limit, limit), "b": jnp.zeros((n_out,), dtype)}
        return {"convs": convs, "dense": dense}

    def apply(params, images):
        h = jnp.asarray(images)
        if h.ndim != 4 or h.shape[1:] != (image_size, image_size, in_channels):
            raise ValueError(f"encoder expects (B, {image_size}, {image_size}, {in_channels}), got {h.shape}")
        for conv in params["convs"]:
            h = jax.lax.conv_general_dilated(h, conv["w"], (1, 1), "SAME", dimension_numbers=("NHWC", "HWIO", "NHWC"))
            h = h + conv["b"][None, None, None, :]
            h = jax.lax.reduce_window(h, -jnp.inf, jax.lax.max, (1, 2, 2, 1), (1, 2, 2, 1), "VALID")
            h = jax.nn.relu(h)
        h = h.reshape(h.shape[0], -1)
        out = h @ params["dense"]["w"] + params["dense"]["b"][None, :]
        return out.reshape(h.shape[0], n_lobes, params_per_lobe)

    return CNN(init, apply, (n_lobes, params_per_lobe))
