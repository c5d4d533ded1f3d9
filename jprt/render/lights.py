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
one-hot texel lights exactly the direction ``equirect_directions`` names (tested).

The parameter array Mitsuba exposes (``mi.traverse(scene)['<id>.data']``) has one halo column on
each side (last column first, first column last): ``mitsuba_envmap_data`` writes that layout.
"""

from __future__ import annotations

from typing import NamedTuple, Union

import numpy as np

__all__ = [
    "PointLights",
    "SpotLights",
    "DirectionalLights",
    "EnvMap",
    "Lighting",
    "equirect_directions",
    "direction_to_equirect",
    "to_mitsuba_envmap",
    "from_mitsuba_envmap",
    "mitsuba_envmap_data",
    "validate_envmap",
    "validate_lighting",
    "lighting_description",
]


class PointLights(NamedTuple):
    """K isotropic point lights.

    Fields:
      position:  (K, 3) float32 world positions.
      intensity: (K, 3) float32 RGB radiant intensity (W/sr per channel).
    """

    position: np.ndarray
    intensity: np.ndarray

    @classmethod
    def create(cls, position, intensity) -> "PointLights":
        """Validated constructor: accepts one light ((3,) arrays) or K lights ((K, 3))."""
        position = np.atleast_2d(np.asarray(position, np.float32))
        intensity = np.atleast_2d(np.asarray(intensity, np.float32))
        if intensity.shape[0] == 1 and position.shape[0] > 1:
            intensity = np.repeat(intensity, position.shape[0], axis=0)
        if position.ndim != 2 or position.shape[1] != 3 or intensity.shape != position.shape:
            raise ValueError(
                f"point lights need position (K, 3) and intensity (K, 3); got {position.shape} and {intensity.shape}"
            )
        if not (np.isfinite(position).all() and np.isfinite(intensity).all()):
            raise ValueError("point light position or intensity contains NaN or inf")
        return cls(position, intensity)

    @property
    def count(self) -> int:
        return int(self.position.shape[0])


def _rows(name: str, value, k: int | None, width: int | None) -> np.ndarray:
    """``value`` as a float32 (K, width) (or (K,) when width is None) array; one row broadcasts to K."""
    a = np.asarray(value, np.float32)
    a = np.atleast_2d(a) if width is not None else np.atleast_1d(a)
    if k is not None and a.shape[0] == 1 and k > 1:
        a = np.repeat(a, k, axis=0)
    if (width is not None and (a.ndim != 2 or a.shape[1] != width)) or (k is not None and a.shape[0] != k):
        want = f"({k if k is not None else 'K'}{', ' + str(width) if width is not None else ''})"
        raise ValueError(f"{name} must have shape {want}, got {np.shape(value)}")
    if not np.isfinite(a).all():
        raise ValueError(f"{name} contains NaN or inf")
    return a


class SpotLights(NamedTuple):
    """K spot lights (Mitsuba's ``spot`` emitter: full intensity inside ``beam_deg``, falling
    off linearly in angle to zero at ``cutoff_deg``).

    Fields:
      position:   (K, 3) float32 world positions.
      target:     (K, 3) float32 points the spot axes aim at.
      intensity:  (K, 3) float32 RGB radiant intensity on the axis (W/sr per channel).
      cutoff_deg: (K,) float32 half-angle of the cone, in degrees, in (0, 90].
      beam_deg:   (K,) float32 half-angle of the fully lit core, in degrees, <= cutoff_deg.
    """

    position: np.ndarray
    target: np.ndarray
    intensity: np.ndarray
    cutoff_deg: np.ndarray
    beam_deg: np.ndarray

    @classmethod
    def create(cls, position, target, intensity, cutoff_deg=30.0, beam_deg=None) -> "SpotLights":
        """Validated constructor; one light may be given as (3,) arrays. ``beam_deg`` defaults to
        three quarters of ``cutoff_deg``."""
        position = _rows("spot position", position, None, 3)
        k = position.shape[0]
        target = _rows("spot target", target, k, 3)
        intensity = _rows("spot intensity", intensity, k, 3)
        cutoff = _rows("spot cutoff_deg", cutoff_deg, k, None)
        beam = _rows("spot beam_deg", 0.75 * cutoff if beam_deg is None else beam_deg, k, None)
        if np.any(np.linalg.norm(target - position, axis=1) < 1e-6):
            raise ValueError("spot light target coincides with its position (no axis direction)")
        if np.any((cutoff <= 0) | (cutoff > 90)) or np.any((beam <= 0) | (beam > cutoff)):
            raise ValueError(f"spot angles need 0 < beam_deg <= cutoff_deg <= 90, got beam {beam} and cutoff {cutoff}")
        return cls(position, target, intensity, cutoff, beam)

    @property
    def count(self) -> int:
        return int(self.position.shape[0])


class DirectionalLights(NamedTuple):
    """K distant (directional) lights.

    Fields:
      direction:  (K, 3) float32 unit directions the light *travels* (from the light to the scene).
      irradiance: (K, 3) float32 RGB irradiance on a surface facing the light (W/m^2 per channel).
    """

    direction: np.ndarray
    irradiance: np.ndarray

    @classmethod
    def create(cls, direction, irradiance) -> "DirectionalLights":
        """Validated constructor; one light may be given as (3,) arrays; directions are normalised."""
        direction = _rows("directional light direction", direction, None, 3)
        norm = np.linalg.norm(direction, axis=1, keepdims=True)
        if np.any(norm < 1e-12):
            raise ValueError("directional light direction has zero length")
        irradiance = _rows("directional light irradiance", irradiance, direction.shape[0], 3)
        return cls((direction / norm).astype(np.float32), irradiance)

    @property
    def count(self) -> int:
        return int(self.direction.shape[0])


class EnvMap(NamedTuple):
    """An environment map in jprt's equirect layout (see the module docstring).

    Fields:
      radiance: (H, W, 3) float32 linear RGB radiance.
    """

    radiance: np.ndarray

    @classmethod
    def create(cls, radiance) -> "EnvMap":
        """Validated constructor (finite values, (H, W, 3) with H, W >= 2)."""
        return cls(validate_envmap(radiance))

    @classmethod
    def from_file(cls, path: str) -> "EnvMap":
        """Load an HDR/EXR equirect map (Radiance .hdr through Mitsuba's Bitmap, .exr through jprt.io)."""
        import os

        if not os.path.exists(path):
            raise FileNotFoundError(f"environment map not found: {path}")
        if path.lower().endswith(".exr"):
            from jprt import io

            return cls.create(io.read_exr(path, channels="RGB"))
        from jprt.render.setup import mitsuba

        mi = mitsuba()
        bitmap = mi.Bitmap(path).convert(mi.Bitmap.PixelFormat.RGB, mi.Struct.Type.Float32, srgb_gamma=False)
        return cls.create(np.array(bitmap))


Lighting = Union[PointLights, SpotLights, DirectionalLights, EnvMap, None]


def validate_envmap(radiance) -> np.ndarray:
    """Return ``radiance`` as a float32 (H, W, 3) array, or raise a one-line ValueError."""
    radiance = np.asarray(radiance, dtype=np.float32)
    if radiance.ndim != 3 or radiance.shape[2] != 3 or radiance.shape[0] < 2 or radiance.shape[1] < 2:
        raise ValueError(f"environment map must be (H, W, 3) with H, W >= 2, got shape {radiance.shape}")
    bad = ~np.isfinite(radiance)
    if bad.any():
        i, j, _ = np.argwhere(bad)[0]
        raise ValueError(
            f"environment map contains {int(bad.any(axis=2).sum())} non-finite texels (first at row {i}, column {j})"
        )
    return radiance


def validate_lighting(lighting: Lighting) -> Lighting:
    """Return ``lighting`` re-validated (finite values, right shapes), or raise ValueError."""
    if lighting is None:
        return None
    if isinstance(lighting, PointLights):
        return PointLights.create(lighting.position, lighting.intensity)
    if isinstance(lighting, SpotLights):
        return SpotLights.create(*lighting)
    if isinstance(lighting, DirectionalLights):
        return DirectionalLights.create(*lighting)
    if isinstance(lighting, EnvMap):
        return EnvMap.create(lighting.radiance)
    raise TypeError(f"unknown lighting type {type(lighting).__name__}")


def equirect_directions(height: int, width: int) -> np.ndarray:
    """Unit directions (H, W, 3) of jprt equirect texel centres."""
    theta = np.pi * (np.arange(height) + 0.5) / height
    phi = 2.0 * np.pi * (np.arange(width) + 0.5) / width
    st, ct = np.sin(theta)[:, None], np.cos(theta)[:, None]
    sp, cp = np.sin(phi)[None, :], np.cos(phi)[None, :]
    return np.stack(np.broadcast_arrays(sp * st, ct + 0 * sp, -cp * st), axis=-1)


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
    from jprt.config import array_digest

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
