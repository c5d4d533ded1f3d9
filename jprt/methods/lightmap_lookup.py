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

__all__ = ["atlas_lookup", "atlas_image", "atlas_inputs", "modulation", "lambertian", "texel_modulation",
           "remodulated_lookup", "ALBEDO_FLOOR"]


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


#: The smallest diffuse albedo, per channel, a Lambertian surface's light is divided by or
#: multiplied with (``modulation``), so a black texel does not divide by zero.
ALBEDO_FLOOR = 0.02


def modulation(albedo):
    """max(albedo, ``ALBEDO_FLOOR``) per channel."""
    return jnp.maximum(albedo, ALBEDO_FLOOR)


def lambertian(diffuse_albedo, specular_albedo):
    """(...,) bool: a diffuse albedo and no specular one (a Lambertian material), whose light is
    its albedo times the irradiance over pi, exactly."""
    return jnp.any(diffuse_albedo > 0.0, axis=-1) & jnp.all(specular_albedo == 0.0, axis=-1)


def texel_modulation(diffuse_albedo, specular_albedo, texel_object) -> np.ndarray:
    """(T, 6) what a demodulated lightmap divides each texel's light by, and the albedo a pixel's is
    taken relative to: at a Lambertian texel (``lambertian``) its ``modulation`` over the mean
    modulation of its object's Lambertian texels (its texture, the object's mean divided out: an
    untextured object's texels keep their light), then that mean; elsewhere 1 (a glossy texel's
    light is not its diffuse albedo times anything: dividing by its texture would put the texture
    into its reflections) and 0."""
    d, s = np.asarray(diffuse_albedo, np.float32), np.asarray(specular_albedo, np.float32)
    obj = np.asarray(texel_object)
    lamb = np.asarray(lambertian(d, s))
    m = np.asarray(modulation(d), np.float64)
    mean = np.zeros_like(m)
    for o in np.unique(obj[lamb]):
        mine = lamb & (obj == o)
        mean[mine] = m[mine].mean(axis=0)
    rel = np.where(lamb[:, None], m / np.where(lamb[:, None], mean, 1.0), 1.0)
    return np.concatenate([rel, mean], axis=1).astype(np.float32)


def remodulated_lookup(image, modulation_image, uv, albedo, specular):
    """Shading with a demodulated lightmap (texels divided by ``texel_modulation``'s first three
    columns; ``modulation_image`` its (R, R, 6) atlas image): the bilinear lookup of ``image`` times
    the pixel's own ``modulation`` over its object's mean where the pixel is Lambertian (``albedo``
    and ``specular`` (..., 3) from its G-buffer), so the albedo detail finer than a texel (a
    texture) comes from the pixel, as engines shade lightmaps that hold illumination; elsewhere
    times the looked-up texel modulation (a glossy pixel, or an atlas G-buffer, ``atlas_inputs``,
    without albedos: at texel centres exactly the texels' light)."""
    looked = atlas_lookup(modulation_image, uv)
    own = modulation(albedo) / jnp.maximum(looked[..., 3:], ALBEDO_FLOOR)
    scale = jnp.where(lambertian(albedo, specular)[..., None] & (looked[..., 3:] > 0.0), own, looked[..., :3])
    return atlas_lookup(image, uv) * scale


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
