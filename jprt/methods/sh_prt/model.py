"""Classic spherical-harmonic PRT for indirect light (Sloan, Kautz, Snyder 2002), as the
baseline of Belcour et al. 2022 §6.4.

Distant lighting L(w) ~ sum_i l_i Y_i(w) of order ``degree + 1`` (Sloan's "order n" = n bands,
n^2 coefficients: order 3 -> degree 2, order 5 -> degree 4). Every lightmap texel stores a
transfer vector t_i = indirect outgoing radiance there when the scene is lit by the distant
light Y_i (§4, "interreflected transfer", including the room's bounce light); at run time the
indirect lightmap is sum_i l_i t_i (Eq. 5, per colour channel).

Baking renders each Y_i as an environment map with Mitsuba, its positive and negative parts
separately (DESIGN.md: signed emitters are unbiased but much noisier), and gathers indirect light
at the texels (``jprt.render.lightmap.indirect_at_points``).

A texel of a view-dependent material (glossy or mirror-like, ``jprt.render.gbuffer.
view_dependent_objects``) also stores Sloan et al.'s glossy transfer (§5) in its exit form: a
matrix M_ji whose row j is the projection of its indirect outgoing radiance, as a function of the
view direction w_o, onto SH Y_j(w_o) of order ``sh.exit_order`` under each distant light Y_i, so
that L_o(w_o) = sum_j Y_j(w_o) sum_i M_ji l_i. The BRDF is in the bake (Mitsuba's), not a zonal
kernel as in Sloan's §5; the radiance along a texel's normal alone is what a diffuse texel stores,
and a glossy floor seen at grazing angles is far from it (it mirrors what lies along the view).

Local lights are what classic PRT cannot represent: a point or spot light becomes a delta of
irradiance E from its direction w_l as seen from one reference point (the asset centre),
projected as l_i = E Y_i(w_l) (``delta_light_coefficients``). The band limit blurs it and the
distant-light assumption ignores where the light is (Belcour et al. Fig. 12).

Contract (``jprt.methods.base``): ``data.make_dataset(scene, config)`` bakes the transfer vectors
of a lightmap atlas (cached by ``jprt.cache``); ``fit`` only packs them (the bake is the fit);
``evaluator(params, config)`` -> ``evaluate(gbuffer, SHLighting)``. This module imports no Mitsuba.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jprt.inputs import SHLighting
from jprt.methods.base import FitResult, resolve
from jprt.methods.lightmap_lookup import atlas_inputs, lightmap_shader, modulation_params, texel_lookup
from jprt.sphere import sh

__all__ = ["DEFAULT_CONFIG", "SHData", "delta_light_coefficients", "lightmap", "order_to_degree", "fit",
           "evaluator", "example"]

DEFAULT_CONFIG = {
    "scene": {"name": "cornell_box", "area_light": False},
    "objects": [],  # object names of the asset; [] = every object of the scene
    "lightmap": {"resolution": 64},  # the lightmap atlas's size in texels per side
    "sh": {
        # Sloan's order (bands); the bake renders every SH function's positive and negative parts
        "order": 3,
        "spp": 64,  # path-traced samples per texel of each bake render
        "env_height": 32,  # the height in pixels of the equirect map each SH function is rendered as
        "seed": 0,  # seed of the bake's renders
        # Sloan's order of the exit transfer in the view direction at texels of view-dependent
        # materials (glossy, mirror, glass); 0: every texel stores the radiance along its normal only
        "exit_order": 3,
        "exit_directions": 32,  # view directions per such texel (a hemisphere set about its normal)
        "exit_spp": 16,  # path-traced samples along each of those directions
        # held-out procedural environment maps whose indirect light at every texel is rendered at
        # `spp` for the self-check (data.self_check; one render each, against the bake's
        # 2 (degree + 1)^2 - 1; 0: none). Not part of the bake's cache key
        "check_maps": 1,
    },
    # demodulate: a Lambertian pixel shades the looked-up texels' light over their diffuse albedo
    # with its own (``lightmap_lookup.remodulated_lookup``): a texture finer than a texel comes
    # from the pixel's material, as engines shade baked lightmaps; glossy texels keep their light
    "shading": {"demodulate": True},
}


class SHData(NamedTuple):
    """A baked SH PRT asset.

    Fields:
      atlas: ``jprt.render.lightmap.Atlas`` arrays as a dict.
      transfer: (T, (degree + 1)^2, 3) transfer vectors of the atlas texels (radiance along
        each texel's normal).
      meta: {"bake_s": seconds, "degree": int, "exit_degree": int (-1: no exit transfer)}.
      exit_transfer: (G, (exit_degree + 1)^2, (degree + 1)^2, 3) exit transfer matrices of the
        view-dependent texels (G may be 0).
      exit_texel: (G,) their texel indices.
      modulation: ``lightmap_lookup.texel_modulation`` of the texels' materials (T, 3) and (K, 3),
        or None (no demodulation).
    """

    atlas: dict
    transfer: np.ndarray
    meta: dict
    exit_transfer: np.ndarray = np.zeros((0, 1, 1, 3), np.float32)
    exit_texel: np.ndarray = np.zeros(0, np.int32)
    modulation: tuple | None = None


def order_to_degree(order: int) -> int:
    """Sloan's SH order (number of bands) -> maximal degree l.

    Numerics: not differentiable (an integer).
    """
    if int(order) < 1:
        raise ValueError(f"SH order must be >= 1, got {order}")
    return int(order) - 1


def delta_light_coefficients(directions, irradiance, degree: int) -> np.ndarray:
    """SH coefficients ((degree + 1)^2, 3) of deltas of RGB irradiance ``irradiance`` (K, 3)
    from unit ``directions`` (K, 3): l_i = sum_k E_k Y_i(w_k).

    Numerics: not differentiable (float64 NumPy: the light's SH projection, built from ``jprt.sphere.sh.evaluate``, covered).
    """
    d = np.asarray(directions, np.float32).reshape(-1, 3)
    e = np.asarray(irradiance, np.float64).reshape(-1, 3)
    if d.shape[0] != e.shape[0]:
        raise ValueError(f"{d.shape[0]} directions but {e.shape[0]} irradiances")
    y = np.asarray(sh.evaluate(d, int(degree)), np.float64)  # (K, n)
    return y.T @ e


def lightmap(transfer, coefficients) -> np.ndarray:
    """Indirect texels (T, 3) = sum_i l_i t_i per channel; ``transfer`` may hold more SH
    functions than ``coefficients`` (a degree-4 bake evaluates degree-2 lighting).

    Numerics: not differentiable (float64 NumPy: a product of the bake and the light's coefficients).
    """
    transfer = np.asarray(transfer, np.float64)
    c = np.asarray(coefficients, np.float64)
    if c.shape[0] > transfer.shape[1]:
        raise ValueError(f"{c.shape[0]} SH coefficients but the transfer holds {transfer.shape[1]}")
    return np.einsum("tic,ic->tc", transfer[:, :c.shape[0]], c)


def fit(data: SHData, config: dict | None = None) -> FitResult:
    """Pack the baked transfer and the atlas layout as params (the bake is SH PRT's fit), with the
    data's ``modulation`` for a demodulated evaluator (``shading.demodulate``: ``texel_modulation``,
    ``object_albedo``).

    Numerics: not differentiable (a fitting or training procedure).
    """
    cfg = resolve(DEFAULT_CONFIG, config)
    exit_texel = np.asarray(data.exit_texel, np.int32)
    params = {"transfer": np.asarray(data.transfer, np.float32),
              "texel_index": np.asarray(data.atlas["texel_index"], np.int32),
              "fill_index": np.asarray(data.atlas["fill_index"], np.int32),
              "exit_transfer": np.asarray(data.exit_transfer, np.float32),
              "exit_texel": exit_texel,
              "exit_normal": np.asarray(data.atlas["normal"], np.float32)[exit_texel].reshape(-1, 3)}
    if cfg["shading"]["demodulate"] and data.modulation is not None:
        params.update(modulation_params(data.modulation))
    return FitResult(params, {"degree": int(data.meta["degree"]), "bake_s": float(data.meta["bake_s"]),
                              "exit_degree": int(data.meta.get("exit_degree", -1)),
                              "exit_texels": int(exit_texel.size)})


def evaluator(params, config: dict | None = None):
    """``evaluate(inputs, lighting) -> (H, W, 3)``: the lightmap sum_i l_i t_i (Eq. 5) looked up
    bilinearly through the G-buffer's atlas ``uv`` (with ``params["texel_modulation"]`` a
    Lambertian pixel's lookup of the demodulated texels times its own diffuse albedo,
    ``lightmap_lookup.remodulated_lookup``); invalid pixels 0. ``lighting`` is an
    ``SHLighting`` with at most (degree + 1)^2 coefficients (fewer evaluate a lower order).

    Where the bake holds exit transfer (``params["exit_transfer"]``, view-dependent texels), a
    pixel whose G-buffer ``view`` lies in front of the texels it reads shades them as
    sum_j Y_j(view) sum_i M_ji l_i (module docstring; the exit coefficients are looked up
    bilinearly like the texels, the diffuse texels' share beside them); a pixel without a view
    (``atlas_inputs``: view 0) or behind them reads the radiance along the texels' normals.

    Numerics: not differentiable (builds the float32 run-time program: a lightmap product, linear in the light).
    """
    resolve(DEFAULT_CONFIG, config)
    transfer = jnp.asarray(params["transfer"])
    fill = jnp.asarray(params["fill_index"])
    exit_transfer = jnp.asarray(params.get("exit_transfer", np.zeros((0, 1, 1, 3), np.float32)))
    exit_texel = jnp.asarray(params.get("exit_texel", np.zeros(0, np.int32)))
    exit_normal = jnp.asarray(params.get("exit_normal", np.zeros((0, 3), np.float32)))
    n_texels = transfer.shape[0]
    exit_degree = int(round(math.sqrt(exit_transfer.shape[1]))) - 1
    # the bake holds the texels' light: a demodulated evaluator divides their texture out first
    # (an evaluator without modulation skips the division rather than dividing by ones)
    modulation = params.get("texel_modulation")
    inverse_modulation = None if modulation is None else 1.0 / jnp.asarray(modulation, jnp.float32)

    def demodulated(texels):
        return texels if inverse_modulation is None else texels * inverse_modulation
    materials, shade = lightmap_shader(params, fill)

    @jax.jit
    def evaluate(inputs, lighting):
        c = jnp.asarray(lighting.coefficients, jnp.float32)
        if c.shape[0] > transfer.shape[1]:
            raise ValueError(f"{c.shape[0]} SH coefficients but the transfer holds {transfer.shape[1]}")
        uv = jnp.asarray(inputs.uv, jnp.float32)
        pixel_materials = materials(inputs)
        texels = jnp.einsum("tic,ic->tc", transfer[:, :c.shape[0]], c)
        image = shade(demodulated(texels), uv, pixel_materials)
        if exit_transfer.shape[0]:
            coeff = jnp.einsum("gjic,ic->gjc", exit_transfer[:, :, :c.shape[0]], c)  # (G, m, 3)
            m = coeff.shape[1]
            glossy = jnp.zeros(n_texels, jnp.float32).at[exit_texel].set(1.0)
            rows = jnp.zeros((n_texels, m * 3 + 3), jnp.float32)
            rows = rows.at[exit_texel].set(jnp.concatenate([coeff.reshape(-1, m * 3), exit_normal], axis=1))
            diffuse = shade(demodulated(texels * (1.0 - glossy)[:, None]), uv, pixel_materials)
            looked = texel_lookup(rows, fill, uv)
            view = jnp.asarray(inputs.view, jnp.float32)
            y = sh.evaluate(view, exit_degree)  # (H, W, m)
            exit_image = jnp.einsum("...jc,...j->...c", looked[..., :m * 3].reshape(uv.shape[:-1] + (m, 3)), y)
            front = jnp.sum(view * looked[..., m * 3:], axis=-1) > 0.0
            image = jnp.where(front[..., None], diffuse + exit_image, image)
        return jnp.where(jnp.asarray(inputs.valid, bool)[..., None], image, 0.0)

    return evaluate


def example(data: SHData, config: dict | None = None):
    """The atlas G-buffer and a held-out light: a white delta of irradiance 1 from above and a
    dimmer one from the side, projected to SH.

    Numerics: not differentiable (a held-out input and lighting from a dataset).
    """
    resolve(DEFAULT_CONFIG, config)
    coefficients = delta_light_coefficients([[0.0, 1.0, 0.0], [0.6, 0.0, 0.8]], [[1.0, 1.0, 1.0], [0.3, 0.2, 0.1]],
                                            int(data.meta["degree"]))
    return (atlas_inputs(int(data.atlas["resolution"]), data.atlas["texel_index"]),
            SHLighting(coefficients.astype(np.float32)))
