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
"""

from __future__ import annotations

import numpy as np

from jprt.sphere import sh

__all__ = ["bake", "delta_light_coefficients", "lightmap", "order_to_degree"]


def order_to_degree(order: int) -> int:
    """Sloan's SH order (number of bands) -> maximal degree l."""
    if int(order) < 1:
        raise ValueError(f"SH order must be >= 1, got {order}")
    return int(order) - 1


def bake(handle, atlas, degree: int, *, spp: int, env_height: int = 32, seed: int = 0,
         progress: bool = True) -> np.ndarray:
    """Transfer vectors (T, (degree + 1)^2, 3) of the atlas texels: the indirect radiance at
    each texel under white distant lighting Y_i, for every SH function i."""
    from tqdm.auto import tqdm

    from jprt.render import lightmap
    from jprt.render.lights import EnvMap, equirect_directions

    h, w = int(env_height), 2 * int(env_height)
    basis = np.asarray(sh.evaluate(equirect_directions(h, w).astype(np.float32), int(degree)), np.float32)
    n = basis.shape[-1]
    out = np.zeros((len(atlas["position"]) if isinstance(atlas, dict) else atlas.count, n, 3), np.float32)
    position = atlas["position"] if isinstance(atlas, dict) else atlas.position
    normal = atlas["normal"] if isinstance(atlas, dict) else atlas.normal
    for i in tqdm(range(n), desc=f"SH PRT bake (degree {degree})", disable=not progress):
        for sign in (1.0, -1.0):
            part = np.maximum(sign * basis[..., i], 0.0)
            if part.max() <= 0:
                continue
            handle.set_lighting(EnvMap.create(np.repeat(part[..., None], 3, axis=-1)))
            out[:, i] += sign * lightmap.indirect_at_points(handle, position, normal, spp=spp,
                                                            seed=seed * 7919 + 2 * i + (sign < 0))
    return out


def delta_light_coefficients(directions, irradiance, degree: int) -> np.ndarray:
    """SH coefficients ((degree + 1)^2, 3) of deltas of RGB irradiance ``irradiance`` (K, 3)
    from unit ``directions`` (K, 3): l_i = sum_k E_k Y_i(w_k)."""
    d = np.asarray(directions, np.float32).reshape(-1, 3)
    e = np.asarray(irradiance, np.float64).reshape(-1, 3)
    if d.shape[0] != e.shape[0]:
        raise ValueError(f"{d.shape[0]} directions but {e.shape[0]} irradiances")
    y = np.asarray(sh.evaluate(d, int(degree)), np.float64)  # (K, n)
    return y.T @ e


def lightmap(transfer, coefficients) -> np.ndarray:
    """Indirect texels (T, 3) = sum_i l_i t_i per channel; ``transfer`` may hold more SH
    functions than ``coefficients`` (a degree-4 bake evaluates degree-2 lighting)."""
    transfer = np.asarray(transfer, np.float64)
    c = np.asarray(coefficients, np.float64)
    if c.shape[0] > transfer.shape[1]:
        raise ValueError(f"{c.shape[0]} SH coefficients but the transfer holds {transfer.shape[1]}")
    return np.einsum("tic,ic->tc", transfer[:, :c.shape[0]], c)
