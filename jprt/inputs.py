"""The plain array types evaluators take: G-buffers, lights, environment maps and cameras.

Importable without Mitsuba (DESIGN.md, "Contracts"): a trained model's evaluator runs wherever JAX
runs, so its inputs are NamedTuples of arrays (pytrees: they jit, vmap and export). The Mitsuba
conversions (scene dicts, sensors, emitters) stay in ``jprt.render``, which re-exports these
names where they were defined before.

* ``GBuffer``: per-pixel first-hit attributes (``jprt.render.gbuffer`` fills it from exact
  pixel-centre rays).
* ``PointLights``, ``SpotLights``, ``DirectionalLights``, ``EnvMap`` (jprt's equirect layout, see
  ``jprt.render.lights``), ``CubeMap`` ((6, n, n, 3), ``jprt.sphere.cubemap`` layout),
  ``SHLighting`` (real SH coefficients), ``PointRadiance`` (direct radiance measured at points):
  the lighting pytrees of the methods (``Method.lighting`` names one of them).
* ``Camera``: a pinhole camera of floats (hashable, serialisable).
"""

from __future__ import annotations

from typing import NamedTuple, Union

import numpy as np

__all__ = ["GBuffer", "Camera", "PointLights", "SpotLights", "DirectionalLights", "EnvMap", "CubeMap",
           "SHLighting", "PointRadiance", "LightScale", "Lighting", "validate_envmap", "validate_lighting", "vec3"]


def vec3(v) -> tuple[float, float, float]:
    """A finite 3-vector as a tuple of floats, or ValueError."""
    v = np.asarray(v, dtype=np.float64).reshape(-1)
    if v.shape != (3,) or not np.isfinite(v).all():
        raise ValueError(f"expected a finite 3-vector, got {v!r}")
    return (float(v[0]), float(v[1]), float(v[2]))


class GBuffer(NamedTuple):
    """Per-pixel surface attributes of the first hit, all (H, W, ...) NumPy arrays.

    Fields:
      position:        (H, W, 3) float32 world position.
      normal:          (H, W, 3) float32 unit shading normal, facing the viewer.
      view:            (H, W, 3) float32 unit direction from the surface to the camera.
      reflected:       (H, W, 3) float32 unit mirror direction reflect(-view, normal).
      uv:              (H, W, 2) float32 surface texture coordinates.
      diffuse_albedo:  (H, W, 3) float32.
      specular_albedo: (H, W, 3) float32.
      roughness:       (H, W)    float32 GGX alpha (1 for diffuse surfaces).
      object_id:       (H, W)    int32 index into the scene's shapes, -1 where invalid.
      valid:           (H, W)    bool, the primary ray hit a surface.
    """

    position: np.ndarray
    normal: np.ndarray
    view: np.ndarray
    reflected: np.ndarray
    uv: np.ndarray
    diffuse_albedo: np.ndarray
    specular_albedo: np.ndarray
    roughness: np.ndarray
    object_id: np.ndarray
    valid: np.ndarray


class Camera(NamedTuple):
    """A pinhole camera looking from ``origin`` at ``target``.

    ``fov`` is the field of view in degrees along the smaller image axis (Mitsuba's
    ``fov_axis='smaller'``).
    """

    origin: tuple[float, float, float]
    target: tuple[float, float, float]
    up: tuple[float, float, float] = (0.0, 1.0, 0.0)
    fov: float = 39.3077
    width: int = 256
    height: int = 256

    def describe(self) -> dict:
        """A JSON-able dict of the camera (tuples as lists), for content hashing."""
        return {k: (list(map(float, v)) if isinstance(v, tuple) else v) for k, v in self._asdict().items()}


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
        """The number K of lights."""
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
        """The number K of lights."""
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
        """The number K of lights."""
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


class CubeMap(NamedTuple):
    """An environment as a cube map (``jprt.sphere.cubemap`` layout).

    Fields:
      radiance: (6, n, n, 3) float32 linear RGB radiance per texel.
    """

    radiance: np.ndarray


class SHLighting(NamedTuple):
    """Distant lighting as real spherical-harmonic coefficients (``jprt.sphere.sh`` order).

    Fields:
      coefficients: ((degree + 1)^2, 3) float32 RGB coefficients.
    """

    coefficients: np.ndarray


class PointRadiance(NamedTuple):
    """Direct radiance measured at a method's measurement points (data-driven PRT's lighting:
    any light, seen only through what it does at the points, Belcour et al. 2022 §4.3).

    Fields:
      direct: (S, 3) float32 RGB radiance at the S points.
    """

    direct: np.ndarray


class LightScale(NamedTuple):
    """The lighting a method was baked with, scaled per channel (SG light-field textures: the
    light field is captured under the scene's own emitters, and light transport is linear in
    their power, so an RGB factor is the one relighting a baked texture allows).

    Fields:
      scale: (3,) float32 RGB factor (1 = as baked).
    """

    scale: np.ndarray


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




def _register_export_serialization() -> None:
    """Let ``jax.export`` serialise functions whose arguments are these NamedTuples."""
    import jax

    for t in (GBuffer, PointLights, SpotLights, DirectionalLights, EnvMap, CubeMap, SHLighting, PointRadiance,
              LightScale):
        jax.export.register_namedtuple_serialization(t, serialized_name=f"jprt.inputs.{t.__name__}")


_register_export_serialization()
