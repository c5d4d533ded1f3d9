"""Lighting descriptions and the one conversion from jprt's equirect maps to Mitsuba's envmap.

jprt's equirectangular convention (also used by ``jprt.sphere``): an (H, W, 3) array whose texel
(i, j) has its centre at

    theta = pi (i + 0.5) / H,   phi = 2 pi (j + 0.5) / W,
    d = (sin(phi) sin(theta), cos(theta), -cos(phi) sin(theta))      (Y up)

which is the usual layout of HDR files (Poly Haven and others).

Mitsuba 3's ``envmap`` emitter reads row i of an Hm x W bitmap at theta = pi i / (Hm - 1), so row 0
and row Hm - 1 sit exactly on the poles, and bilinearly interpolates between rows. Passing a
texel-centre map unchanged therefore shifts every row by up to half a texel. ``to_mitsuba_envmap``
instead builds a (2H + 1) x W bitmap whose odd rows are the jprt rows (at their exact centres),
whose even rows are the means of their two neighbours, and whose pole rows are the mean of the
first/last jprt row. Mitsuba's bilinear lookup of that bitmap is *exactly* the bilinear
interpolation of the jprt map between texel centres (with a single value at each pole), so a
one-hot texel lights exactly the direction ``jprt.sphere.cubemap.equirect_directions`` names (tested).

The parameter array Mitsuba exposes (``mi.traverse(scene)['<id>.data']``) has one halo column on
each side (last column first, first column last): ``mitsuba_envmap_data`` writes that layout.
"""

from __future__ import annotations

import numpy as np

from jprt.hashing import array_digest
from jprt.inputs import (DirectionalLights, EnvMap, Lighting, PointLights, SpotLights, validate_envmap,
                         validate_lighting)

__all__ = [
    "PointLights",
    "SpotLights",
    "DirectionalLights",
    "EnvMap",
    "Lighting",
    "direction_to_equirect",
    "to_mitsuba_envmap",
    "from_mitsuba_envmap",
    "mitsuba_envmap_data",
    "validate_envmap",
    "validate_lighting",
    "lighting_description",
]


def direction_to_equirect(directions, height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """Continuous texel coordinates (row, column) of unit directions; texel centres are integers."""
    d = np.asarray(directions, dtype=np.float64)
    theta = np.arccos(np.clip(d[..., 1], -1.0, 1.0))
    phi = np.mod(np.arctan2(d[..., 0], -d[..., 2]), 2.0 * np.pi)
    return theta / np.pi * height - 0.5, phi / (2.0 * np.pi) * width - 0.5


def to_mitsuba_envmap(radiance) -> np.ndarray:
    """jprt (H, W, 3) equirect -> the (2H + 1, W, 3) bitmap Mitsuba's envmap reproduces exactly."""
    radiance = validate_envmap(radiance)
    h, w, _ = radiance.shape
    out = np.empty((2 * h + 1, w, 3), np.float32)
    out[1::2] = radiance
    out[2:-1:2] = 0.5 * (radiance[:-1] + radiance[1:])
    out[0] = radiance[0].mean(axis=0)
    out[-1] = radiance[-1].mean(axis=0)
    return out


def from_mitsuba_envmap(bitmap) -> np.ndarray:
    """Inverse of ``to_mitsuba_envmap`` (also accepts the halo-padded parameter array)."""
    bitmap = np.asarray(bitmap, np.float32)
    if bitmap.shape[0] % 2 != 1:
        raise ValueError(f"not a jprt-converted Mitsuba envmap (even row count {bitmap.shape[0]})")
    return bitmap[1::2]


def mitsuba_envmap_data(radiance) -> np.ndarray:
    """The (2H + 1, W + 2, 3) array to write into ``mi.traverse(scene)['<id>.data']``.

    Mitsuba keeps one halo column on each side: the last column first and the first column last.
    """
    bitmap = to_mitsuba_envmap(radiance)
    return np.concatenate([bitmap[:, -1:], bitmap, bitmap[:, :1]], axis=1)


def lighting_description(lighting: Lighting) -> dict:
    """A JSON-able description of ``lighting`` for content hashing (arrays by their bytes)."""
    if lighting is None:
        return {"kind": "scene"}
    if isinstance(lighting, PointLights):
        return {
            "kind": "point",
            "position": np.asarray(lighting.position, np.float32).tolist(),
            "intensity": np.asarray(lighting.intensity, np.float32).tolist(),
        }
    if isinstance(lighting, (SpotLights, DirectionalLights)):
        kind = "spot" if isinstance(lighting, SpotLights) else "directional"
        return {"kind": kind, **{k: np.asarray(v, np.float32).tolist() for k, v in lighting._asdict().items()}}
    if isinstance(lighting, EnvMap):
        return {"kind": "envmap", "shape": list(lighting.radiance.shape), "digest": array_digest(lighting.radiance)}
    raise TypeError(f"unknown lighting type {type(lighting).__name__}")
