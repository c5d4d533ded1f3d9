"""Looking up a lightmap on the evaluator side (pure JAX/NumPy): the bilinear texel lookup the
lightmap methods (data-driven PRT, SH PRT, MRT, the SG methods) shade pixels with, the atlas
image of a lightmap's texels, and the G-buffer of an atlas itself.

A lightmap lives in an (R, R) atlas (``jprt.render.lightmap.Atlas``): ``texel_index`` (T,) are the
flat atlas pixels covered by a surface, ``fill_index`` (R * R,) the texel each atlas pixel shows
(gutters repeat their nearest texel so bilinear lookups never read an empty pixel).
"""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np

from jprt.inputs import GBuffer

__all__ = ["atlas_lookup", "atlas_image", "atlas_inputs"]


def atlas_lookup(image, uv):
    """Bilinear lookup of an (R, R, C) atlas at (..., 2) UVs (u -> column, v -> row; texel
    centres at (i + 0.5) / R), clamped to the atlas."""
    r = image.shape[0]
    col = jnp.clip(uv[..., 0] * r - 0.5, 0.0, r - 1.0)
    row = jnp.clip(uv[..., 1] * r - 0.5, 0.0, r - 1.0)
    c0, r0 = jnp.floor(col).astype(jnp.int32), jnp.floor(row).astype(jnp.int32)
    c1, r1 = jnp.minimum(c0 + 1, r - 1), jnp.minimum(r0 + 1, r - 1)
    fc, fr = (col - c0)[..., None], (row - r0)[..., None]
    top = image[r0, c0] * (1 - fc) + image[r0, c1] * fc
    bottom = image[r1, c0] * (1 - fc) + image[r1, c1] * fc
    return top * (1 - fr) + bottom * fr


def atlas_image(texels, fill_index):
    """Lightmap texels (T, C) -> the (R, R, C) atlas image through ``fill_index``."""
    res = int(round(math.sqrt(fill_index.shape[0])))
    return texels[fill_index].reshape(res, res, texels.shape[-1])


def atlas_inputs(resolution: int, texel_index) -> GBuffer:
    """A G-buffer of the atlas itself, (R, R): every pixel looks up its own texel centre; valid
    where a texel is covered. A lightmap evaluator given it returns the lightmap as an (R, R, 3)
    image (exactly the texel values: the lookups land on texel centres), so lightmap errors are
    image errors over the valid pixels."""
    res = int(resolution)
    centres = (np.arange(res, dtype=np.float32) + 0.5) / res
    uv = np.stack(np.meshgrid(centres, centres, indexing="xy"), axis=-1)
    valid = np.zeros(res * res, bool)
    valid[np.asarray(texel_index)] = True
    zeros3 = np.zeros((res, res, 3), np.float32)
    return GBuffer(position=zeros3, normal=zeros3, view=zeros3, reflected=zeros3, uv=uv,
                   diffuse_albedo=zeros3, specular_albedo=zeros3, roughness=np.zeros((res, res), np.float32),
                   object_id=np.where(valid, 0, -1).astype(np.int32).reshape(res, res), valid=valid.reshape(res, res))
