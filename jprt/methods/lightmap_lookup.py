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

__all__ = ["atlas_lookup", "texel_lookup", "texel_taps", "atlas_image", "atlas_inputs", "shown_texels", "modulation",
           "lambertian", "texel_modulation", "remodulated_lookup", "modulation_params", "lightmap_shader", "ALBEDO_FLOOR"]


def atlas_lookup(image, uv):
    """Bilinear lookup of an (R, R, C) atlas at (..., 2) UVs (u -> column, v -> row; texel
    centres at (i + 0.5) / R), clamped to the atlas."""
    return _bilinear(lambda i, j: image[i, j], image.shape[0], uv)


def texel_lookup(texels, fill_index, uv):
    """``atlas_lookup(atlas_image(texels, fill_index), uv)`` without building the atlas image:
    each bilinear corner reads its texel through ``fill_index`` (the same values and arithmetic).
    Where the texels are computed per frame and wide (an exit-transfer row per texel), the image
    would be written and read back every frame; here only the looked-up rows are read."""
    r = int(round(math.sqrt(fill_index.shape[0])))
    return _bilinear(lambda i, j: texels[fill_index[i * r + j]], r, uv)


def _corners(r: int, uv):
    """The bilinear corners of (..., 2) UVs in an R x R atlas: rows r0, r1, columns c0, c1 (int32)
    and the fractions fc, fr towards c1 and r1, clamped to the atlas."""
    col = jnp.clip(uv[..., 0] * r - 0.5, 0.0, r - 1.0)
    row = jnp.clip(uv[..., 1] * r - 0.5, 0.0, r - 1.0)
    c0, r0 = jnp.floor(col).astype(jnp.int32), jnp.floor(row).astype(jnp.int32)
    c1, r1 = jnp.minimum(c0 + 1, r - 1), jnp.minimum(r0 + 1, r - 1)
    return r0, r1, c0, c1, col - c0, row - r0


def texel_taps(fill_index, uv):
    """(index, weight), each (..., 4): the texels (through ``fill_index``) and bilinear weights of
    ``texel_lookup``'s four corners at (..., 2) UVs, so that the lookup of texel values x is
    sum_k weight_k x[index_k]. A texel-space shader (``jprt.methods.sg_lightfield.model.evaluator``)
    uses them twice: to gather the G-buffer's pixels onto the texels they read, and to read back."""
    r = int(round(math.sqrt(fill_index.shape[0])))
    r0, r1, c0, c1, fc, fr = _corners(r, jnp.asarray(uv, jnp.float32))
    index = jnp.stack([fill_index[r0 * r + c0], fill_index[r0 * r + c1], fill_index[r1 * r + c0],
                       fill_index[r1 * r + c1]], axis=-1)
    weight = jnp.stack([(1 - fc) * (1 - fr), fc * (1 - fr), (1 - fc) * fr, fc * fr], axis=-1)
    return index, weight


def _bilinear(at, r: int, uv):
    """The bilinear lookup of an R x R atlas whose texel at (row i, column j) ``at(i, j)`` reads."""
    r0, r1, c0, c1, fc, fr = _corners(r, uv)
    fc, fr = fc[..., None], fr[..., None]
    top = at(r0, c0) * (1 - fc) + at(r0, c1) * fc
    bottom = at(r1, c0) * (1 - fc) + at(r1, c1) * fc
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


def texel_modulation(diffuse_albedo, specular_albedo, texel_object, hit_object, n_objects: int):
    """What a demodulated lightmap divides each texel's light by, and what a pixel's albedo is
    taken relative to: ((T, 3) float32, (n_objects, 3) float32). A Lambertian texel (``lambertian``,
    its material read on its own object: ``hit_object`` equal to ``texel_object``) is divided by
    its ``modulation`` over the mean modulation of its object's Lambertian texels (its texture, the
    object's mean divided out: an untextured object's texels keep their light), the second array
    holding that mean per object (0 for an object without Lambertian texels); every other texel
    by 1 (a glossy texel's light is not its diffuse albedo times anything: dividing by its texture
    would put the texture into its reflections)."""
    d, s = np.asarray(diffuse_albedo, np.float32), np.asarray(specular_albedo, np.float32)
    obj = np.asarray(texel_object)
    lamb = np.asarray(lambertian(d, s)) & (np.asarray(hit_object) == obj)
    m = np.asarray(modulation(d), np.float64)
    means = np.zeros((int(n_objects), 3))
    rel = np.ones_like(m)
    for o in np.unique(obj[lamb]):
        mine = lamb & (obj == o)
        means[o] = m[mine].mean(axis=0)
        rel[mine] = m[mine] / means[o]
    return rel.astype(np.float32), means.astype(np.float32)


def remodulated_lookup(image, relative_image, uv, albedo, specular, object_id, object_mean):
    """Shading with a demodulated lightmap (texels divided by ``texel_modulation``'s first array;
    ``relative_image`` its (R, R, 3) atlas image): the bilinear lookup of ``image`` times a
    Lambertian pixel's own ``modulation`` over its object's mean (``albedo``, ``specular`` (..., 3)
    and ``object_id`` (...) from its G-buffer; ``object_mean`` the second array), so the albedo
    detail finer than a texel (a texture) comes from the pixel, as engines shade lightmaps that
    hold illumination; any other pixel times the looked-up texel modulation (a glossy pixel, or an
    atlas G-buffer, ``atlas_inputs``, without albedos: at texel centres exactly the texels' light)."""
    mean = jnp.asarray(object_mean)[jnp.clip(object_id, 0, object_mean.shape[0] - 1)]
    own = lambertian(albedo, specular)[..., None] & (object_id >= 0)[..., None] & (mean > 0.0)
    scale = jnp.where(own, modulation(albedo) / jnp.maximum(mean, ALBEDO_FLOOR), atlas_lookup(relative_image, uv))
    return atlas_lookup(image, uv) * scale


def modulation_params(modulation) -> dict:
    """The params a demodulated lightmap's evaluator reads (``lightmap_shader``) from
    ``texel_modulation``'s pair: ``texel_modulation`` (T, 3) and ``object_albedo`` (K, 3)."""
    return {"texel_modulation": np.asarray(modulation[0], np.float32),
            "object_albedo": np.asarray(modulation[1], np.float32)}


def lightmap_shader(params: dict, fill_index):
    """How a lightmap method's evaluator shades pixels with its texels: ``(materials, shade)``.
    ``materials(inputs)``: the G-buffer fields ``shade`` reads (diffuse and specular albedo and
    object id; None where the params carry no ``texel_modulation``). ``shade(texels, uv,
    materials)``: texels (T, 3) looked up at ``uv`` (``remodulated_lookup``, else
    ``atlas_lookup``); where the params carry ``texel_modulation`` the texels must already be the
    light over their texture (data-driven PRT fits them so; SH PRT divides its bake first)."""
    fill = jnp.asarray(fill_index)
    if "texel_modulation" not in params:
        return (lambda inputs: None), (lambda texels, uv, materials: atlas_lookup(atlas_image(texels, fill), uv))
    relative = atlas_image(jnp.asarray(params["texel_modulation"], jnp.float32), fill)
    means = jnp.asarray(params["object_albedo"], jnp.float32)

    def materials(inputs):
        return (jnp.asarray(inputs.diffuse_albedo, jnp.float32), jnp.asarray(inputs.specular_albedo, jnp.float32),
                jnp.asarray(inputs.object_id, jnp.int32))

    def shade(texels, uv, materials):
        return remodulated_lookup(atlas_image(texels, fill), relative, uv, *materials, means)

    return materials, shade


def atlas_image(texels, fill_index):
    """Lightmap texels (T, C) -> the (R, R, C) atlas image through ``fill_index``."""
    res = int(round(math.sqrt(fill_index.shape[0])))
    return texels[fill_index].reshape(res, res, texels.shape[-1])


def shown_texels(texel_index, fill_index) -> np.ndarray:
    """(T,) bool: the texels whose own atlas pixel shows them. A texel no view sees has its pixel
    pointed at a seen neighbour's (``fill_index``; ``jprt.render.lightmap.build_atlas``'
    ``seen_from``), so no image of the atlas shows its value."""
    texel_index = np.asarray(texel_index)
    return np.asarray(fill_index)[texel_index] == np.arange(texel_index.size)


def atlas_inputs(resolution: int, texel_index, fill_index=None) -> GBuffer:
    """A G-buffer of the atlas itself, (R, R): every pixel looks up its own texel centre; valid
    where a texel is covered. A lightmap evaluator given it returns the lightmap as an (R, R, 3)
    image (exactly the texel values: the lookups land on texel centres), so lightmap errors are
    image errors over the valid pixels. Given the atlas's ``fill_index``, a texel whose pixel shows
    another texel (one no view sees: ``jprt.render.lightmap.build_atlas``' ``seen_from``) is not
    valid: no image shows its value, and its pixel's value is its neighbour's."""
    res = int(resolution)
    centres = (np.arange(res, dtype=np.float32) + 0.5) / res
    uv = np.stack(np.meshgrid(centres, centres, indexing="xy"), axis=-1)
    valid = np.zeros(res * res, bool)
    texel_index = np.asarray(texel_index)
    shows_itself = np.ones(texel_index.size, bool) if fill_index is None else shown_texels(texel_index, fill_index)
    valid[texel_index[shows_itself]] = True
    zeros3 = np.zeros((res, res, 3), np.float32)
    return GBuffer(position=zeros3, normal=zeros3, view=zeros3, reflected=zeros3, uv=uv,
                   diffuse_albedo=zeros3, specular_albedo=zeros3, roughness=np.zeros((res, res), np.float32),
                   object_id=np.where(valid, 0, -1).astype(np.int32).reshape(res, res), valid=valid.reshape(res, res))
