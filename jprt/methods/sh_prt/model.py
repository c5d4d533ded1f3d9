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

Local lights are what classic PRT cannot represent: a point or spot light becomes a delta of
irradiance E from its direction w_l as seen from one reference point (the asset centre),
projected as l_i = E Y_i(w_l) (``delta_light_coefficients``). The band limit blurs it and the
distant-light assumption ignores where the light is (Belcour et al. Fig. 12).

Contract (``jprt.methods.base``): ``data.make_dataset(scene, config)`` bakes the transfer vectors
of a lightmap atlas (cached by ``jprt.cache``); ``fit`` only packs them (the bake is the fit);
``evaluator(params, config)`` -> ``evaluate(gbuffer, SHLighting)``. This module imports no Mitsuba.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jprt.inputs import SHLighting
from jprt.methods.base import FitResult, resolve
from jprt.methods.lightmap_lookup import atlas_image, atlas_inputs, atlas_lookup
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
        # held-out procedural environment maps whose indirect light at every texel is rendered at
        # `spp` for the self-check (data.self_check; one render each, against the bake's
        # 2 (degree + 1)^2 - 1; 0: none). Not part of the bake's cache key
        "check_maps": 1,
    },
}


class SHData(NamedTuple):
    """A baked SH PRT asset.

    Fields:
      atlas: ``jprt.render.lightmap.Atlas`` arrays as a dict.
      transfer: (T, (degree + 1)^2, 3) transfer vectors of the atlas texels.
      meta: {"bake_s": seconds, "degree": int}.
    """

    atlas: dict
    transfer: np.ndarray
    meta: dict


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
    """Pack the baked transfer and the atlas layout as params (the bake is SH PRT's fit).

    Numerics: not differentiable (a fitting or training procedure).
    """
    resolve(DEFAULT_CONFIG, config)
    params = {"transfer": np.asarray(data.transfer, np.float32),
              "texel_index": np.asarray(data.atlas["texel_index"], np.int32),
              "fill_index": np.asarray(data.atlas["fill_index"], np.int32)}
    return FitResult(params, {"degree": int(data.meta["degree"]), "bake_s": float(data.meta["bake_s"])})


def evaluator(params, config: dict | None = None):
    """``evaluate(inputs, lighting) -> (H, W, 3)``: the lightmap sum_i l_i t_i (Eq. 5) looked up
    bilinearly through the G-buffer's atlas ``uv``; invalid pixels 0. ``lighting`` is an
    ``SHLighting`` with at most (degree + 1)^2 coefficients (fewer evaluate a lower order).

    Numerics: not differentiable (builds the float32 run-time program: a lightmap product, linear in the light).
    """
    resolve(DEFAULT_CONFIG, config)
    transfer = jnp.asarray(params["transfer"])
    fill = jnp.asarray(params["fill_index"])

    @jax.jit
    def evaluate(inputs, lighting):
        c = jnp.asarray(lighting.coefficients, jnp.float32)
        if c.shape[0] > transfer.shape[1]:
            raise ValueError(f"{c.shape[0]} SH coefficients but the transfer holds {transfer.shape[1]}")
        texels = jnp.einsum("tic,ic->tc", transfer[:, :c.shape[0]], c)
        image = atlas_lookup(atlas_image(texels, fill), jnp.asarray(inputs.uv, jnp.float32))
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
