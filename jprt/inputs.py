"""The plain array types evaluators take: G-buffers, lights, environment maps and cameras.

Importable without Mitsuba (DESIGN.md, "Contracts"): a trained model's evaluator runs wherever JAX
runs, so its inputs are NamedTuples of arrays (pytrees: they jit, vmap and export). The Mitsuba
conversions (scene dicts, sensors, emitters) stay in ``jprt.render``, which re-exports these
names where they were defined before.

* ``GBuffer``: per-pixel first-hit attributes (``jprt.render.gbuffer`` fills it from exact
  pixel-centre rays).
* ``PointLights``, ``SpotLights``, ``DirectionalLights``, ``EnvMap`` (jprt's equirect layout, see
  ``jprt.render.lights``), ``CubeMap`` ((6, n, n, 3), ``jprt.sphere.cubemap`` layout),
  ``SHLighting`` (real SH coefficients), ``PointRadiance`` (direct radiance measured at points),
  ``LightScale`` (a bake's lighting scaled), ``PreconvolvedEnvironment`` (an environment convolved
  with GGX lobes): the lighting pytrees of the methods (``Method.lighting`` names one of them).
* ``Camera``: a pinhole camera of floats (hashable, serialisable).
"""

from __future__ import annotations

from typing import NamedTuple, Union

import numpy as np

from jprt.sphere.envmap import check_equirect

__all__ = ["GBuffer", "Camera", "PointLights", "SpotLights", "DirectionalLights", "EnvMap", "CubeMap",
           "SHLighting", "PointRadiance", "LightScale", "PreconvolvedEnvironment", "Lighting", "validate_envmap",
           "validate_lighting",
           "validate_gbuffer", "LIGHTING_TYPES", "vec3"]


def vec3(v, name: str = "vector") -> tuple[float, float, float]:
    """A finite 3-vector as a tuple of floats, or a one-line ValueError naming ``name``."""
    a = np.asarray(v, dtype=np.float64).reshape(-1)
    if a.shape != (3,) or not np.isfinite(a).all():
        raise ValueError(f"{name} must be a finite 3-vector, got {_given(v)}")
    return (float(a[0]), float(a[1]), float(a[2]))


def _given(value) -> str:
    """A short description of what was given: its shape and, when small, its values."""
    a = np.asarray(value)
    if a.size <= 4:
        return repr(a.tolist())
    return f"an array of shape {a.shape}"


def _nonfinite(name: str, a: np.ndarray) -> None:
    """One-line ValueError naming ``name`` and the first non-finite entry."""
    bad = ~np.isfinite(a)
    if bad.any():
        where = tuple(int(i) for i in np.argwhere(bad)[0])
        raise ValueError(f"{name} must be finite, got {int(bad.sum())} NaN/inf entries (first at {where}: "
                         f"{a[where]})")


def _nonnegative(name: str, a: np.ndarray, signed: bool) -> None:
    """One-line ValueError naming ``name`` unless every entry is >= 0 (or ``signed`` is asked for)."""
    if not signed and (a < 0).any():
        where = tuple(int(i) for i in np.argwhere(a < 0)[0])
        raise ValueError(f"{name} must be >= 0 (pass signed=True for signed lighting), got "
                         f"{int((a < 0).sum())} negative entries (first at {where}: {a[where]})")


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
    def create(cls, position, intensity, *, signed: bool = False) -> "PointLights":
        """Validated constructor: accepts one light ((3,) arrays) or K lights ((K, 3)); finite
        values, intensities >= 0 unless ``signed`` (a signed basis light)."""
        position = _rows("point light position", position, None, 3)
        intensity = _rows("point light intensity", intensity, position.shape[0], 3)
        _nonnegative("point light intensity", intensity, signed)
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
    if (width is not None and (a.ndim != 2 or a.shape[1] != width)) or (k is not None and a.shape[0] != k) or \
            (width is None and a.ndim != 1):
        want = f"({k if k is not None else 'K'}{', ' + str(width) if width is not None else ''})"
        raise ValueError(f"{name} must have shape {want}, got shape {np.shape(value)}")
    _nonfinite(name, a)
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
    def create(cls, position, target, intensity, cutoff_deg=30.0, beam_deg=None, *, signed: bool = False) -> "SpotLights":
        """Validated constructor; one light may be given as (3,) arrays. ``beam_deg`` defaults to
        three quarters of ``cutoff_deg``; intensities >= 0 unless ``signed``."""
        position = _rows("spot position", position, None, 3)
        k = position.shape[0]
        target = _rows("spot target", target, k, 3)
        intensity = _rows("spot intensity", intensity, k, 3)
        _nonnegative("spot intensity", intensity, signed)
        cutoff = _rows("spot cutoff_deg", cutoff_deg, k, None)
        beam = _rows("spot beam_deg", 0.75 * cutoff if beam_deg is None else beam_deg, k, None)
        if np.any(np.linalg.norm(target - position, axis=1) < 1e-6):
            raise ValueError("spot target must differ from its position (the axis direction), got the same point")
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
    def create(cls, direction, irradiance, *, signed: bool = False) -> "DirectionalLights":
        """Validated constructor; one light may be given as (3,) arrays; directions are normalised;
        irradiance >= 0 unless ``signed``."""
        direction = _rows("directional light direction", direction, None, 3)
        norm = np.linalg.norm(direction, axis=1, keepdims=True)
        if np.any(norm < 1e-12):
            raise ValueError("directional light direction must be non-zero, got a zero vector")
        irradiance = _rows("directional light irradiance", irradiance, direction.shape[0], 3)
        _nonnegative("directional light irradiance", irradiance, signed)
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
    def create(cls, radiance, *, signed: bool = False) -> "EnvMap":
        """Validated constructor (finite values, (H, W, 3) with H, W >= 2, >= 0 unless ``signed``)."""
        return cls(validate_envmap(radiance, signed=signed))

    @classmethod
    def from_file(cls, path: str) -> "EnvMap":
        """Load an equirect map from a Radiance .hdr (``jprt.io.read_hdr``, equal to Mitsuba's
        Bitmap bit for bit) or an .exr file (``jprt.io.read_exr``); no Mitsuba needed."""
        import os

        from jprt import io

        if not os.path.exists(path):
            raise FileNotFoundError(f"environment map not found: {path}")
        if path.lower().endswith(".exr"):
            return cls.create(io.read_exr(path, channels="RGB"))
        if path.lower().endswith((".hdr", ".rgbe", ".pic")):
            return cls.create(io.read_hdr(path))
        raise ValueError(f"environment map {path}: read .hdr (Radiance RGBE) or .exr files")


class CubeMap(NamedTuple):
    """An environment as a cube map (``jprt.sphere.cubemap`` layout).

    Fields:
      radiance: (6, n, n, 3) float32 linear RGB radiance per texel.
    """

    radiance: np.ndarray

    @classmethod
    def create(cls, radiance, *, signed: bool = False) -> "CubeMap":
        """Validated constructor: (6, n, n, 3), finite, >= 0 unless ``signed``."""
        a = np.asarray(radiance, np.float32)
        if a.ndim != 4 or a.shape[0] != 6 or a.shape[1] != a.shape[2] or a.shape[1] < 1 or a.shape[3] != 3:
            raise ValueError(f"cube map radiance must have shape (6, n, n, 3), got shape {a.shape}")
        _nonfinite("cube map radiance", a)
        _nonnegative("cube map radiance", a, signed)
        return cls(a)


class SHLighting(NamedTuple):
    """Distant lighting as real spherical-harmonic coefficients (``jprt.sphere.sh`` order).

    Fields:
      coefficients: ((degree + 1)^2, 3) float32 RGB coefficients.
    """

    coefficients: np.ndarray

    @classmethod
    def create(cls, coefficients) -> "SHLighting":
        """Validated constructor: ((degree + 1)^2, 3), finite (SH coefficients are signed)."""
        a = np.asarray(coefficients, np.float32)
        n = a.shape[0] if a.ndim == 2 else 0
        if a.ndim != 2 or a.shape[1] != 3 or n < 1 or int(round(np.sqrt(n))) ** 2 != n:
            raise ValueError(f"SH lighting coefficients must have shape ((degree + 1)^2, 3), got shape {a.shape}")
        _nonfinite("SH lighting coefficients", a)
        return cls(a)


class PointRadiance(NamedTuple):
    """Direct radiance measured at a method's measurement points (data-driven PRT's lighting:
    any light, seen only through what it does at the points, Belcour et al. 2022 §4.3).

    Fields:
      direct: (S, 3) float32 RGB radiance at the S points.
    """

    direct: np.ndarray

    @classmethod
    def create(cls, direct, *, signed: bool = False) -> "PointRadiance":
        """Validated constructor: (S, 3), finite, >= 0 unless ``signed``."""
        a = np.asarray(direct, np.float32)
        if a.ndim != 2 or a.shape[1] != 3 or a.shape[0] < 1:
            raise ValueError(f"point radiance direct must have shape (S, 3), got shape {a.shape}")
        _nonfinite("point radiance direct", a)
        _nonnegative("point radiance direct", a, signed)
        return cls(a)


class LightScale(NamedTuple):
    """The lighting a method was baked with, scaled per channel (SG light-field textures: the
    light field is captured under the scene's own emitters, and light transport is linear in
    their power, so an RGB factor is the one relighting a baked texture allows).

    Fields:
      scale: (3,) float32 RGB factor (1 = as baked).
    """

    scale: np.ndarray

    @classmethod
    def create(cls, scale) -> "LightScale":
        """Validated constructor: (3,), finite, >= 0."""
        a = np.asarray(scale, np.float32)
        if a.shape != (3,):
            raise ValueError(f"light scale must have shape (3,), got {_given(scale)}")
        _nonfinite("light scale", a)
        _nonnegative("light scale", a, False)
        return cls(a)


class PreconvolvedEnvironment(NamedTuple):
    """A distant environment pre-convolved with the GGX NDF at several roughnesses (Currius et
    al. 2020 Eq. 6; the split-sum lighting of real-time engines): what an environment map becomes
    once, when it changes, for SG environment visibility (``jprt.methods.sg_environment``, whose
    ``model.preconvolved`` makes it from a map).

    Fields:
      u: (A, n, n, 3) float32 octahedral maps (``jprt.sphere.octahedral`` layout) of U(r), one
        per GGX alpha.
      alphas: (A,) float32 GGX alphas of the maps, increasing.
    """

    u: np.ndarray
    alphas: np.ndarray

    @classmethod
    def create(cls, u, alphas) -> "PreconvolvedEnvironment":
        """Validated constructor: u (A, n, n, 3) finite and >= 0, alphas (A,) increasing in (0, 1]."""
        a = np.asarray(u, np.float32)
        al = np.asarray(alphas, np.float32)
        if a.ndim != 4 or a.shape[1] != a.shape[2] or a.shape[1] < 1 or a.shape[3] != 3:
            raise ValueError(f"pre-convolved environment u must have shape (A, n, n, 3), got shape {a.shape}")
        if al.shape != (a.shape[0],):
            raise ValueError(f"pre-convolved environment alphas must have shape ({a.shape[0]},) (one per map), "
                             f"got {_given(alphas)}")
        _nonfinite("pre-convolved environment u", a)
        _nonnegative("pre-convolved environment u", a, False)
        if not (np.isfinite(al).all() and (al > 0).all() and (al <= 1).all() and (np.diff(al) > 0).all()):
            raise ValueError(f"pre-convolved environment alphas must increase within (0, 1], got {_given(alphas)}")
        return cls(a, al)


Lighting = Union[PointLights, SpotLights, DirectionalLights, EnvMap, None]

#: Every lighting type ``validate_lighting`` checks (the ``Method.lighting`` of some method).
LIGHTING_TYPES = (PointLights, SpotLights, DirectionalLights, EnvMap, CubeMap, SHLighting, PointRadiance, LightScale,
                  PreconvolvedEnvironment)


def validate_envmap(radiance, *, signed: bool = False) -> np.ndarray:
    """Return ``radiance`` as a float32 (H, W, 3) array, or raise a one-line ValueError (shape,
    finite values, >= 0 unless ``signed``): ``jprt.sphere.envmap.check_equirect``, the one check
    of an equirect map."""
    return check_equirect(radiance, signed=signed)


def validate_lighting(lighting, *, signed: bool = False, expected: type | None = None):
    """Return ``lighting`` re-validated (finite values, right shapes, non-negative unless
    ``signed``), or raise a one-line ValueError; TypeError when it is not of the ``expected``
    type (a method's ``Method.lighting``)."""
    if expected is not None and lighting is not None and not isinstance(lighting, expected):
        raise TypeError(f"lighting must be {expected.__name__}, got {type(lighting).__name__}")
    if lighting is None:
        return None
    if isinstance(lighting, PointLights):
        return PointLights.create(lighting.position, lighting.intensity, signed=signed)
    if isinstance(lighting, SpotLights):
        return SpotLights.create(*lighting, signed=signed)
    if isinstance(lighting, DirectionalLights):
        return DirectionalLights.create(*lighting, signed=signed)
    if isinstance(lighting, EnvMap):
        return EnvMap.create(lighting.radiance, signed=signed)
    if isinstance(lighting, CubeMap):
        return CubeMap.create(lighting.radiance, signed=signed)
    if isinstance(lighting, SHLighting):
        return SHLighting.create(lighting.coefficients)
    if isinstance(lighting, PointRadiance):
        return PointRadiance.create(lighting.direct, signed=signed)
    if isinstance(lighting, LightScale):
        return LightScale.create(lighting.scale)
    if isinstance(lighting, PreconvolvedEnvironment):
        return PreconvolvedEnvironment.create(lighting.u, lighting.alphas)
    raise TypeError(f"lighting must be one of jprt.inputs' lighting types, got {type(lighting).__name__}")


def validate_gbuffer(gbuffer: "GBuffer") -> "GBuffer":
    """Return ``gbuffer`` checked, or raise a one-line ValueError naming the field: every field
    (H, W, ...) with the same H, W and its documented trailing shape; at valid pixels positions,
    normals, views, albedos and roughness finite, normals and views unit (within 1e-3) or zero
    (a lightmap atlas's G-buffer has no directions), roughness in [0, 1], albedos >= 0."""
    if not isinstance(gbuffer, GBuffer):
        raise TypeError(f"inputs must be a GBuffer, got {type(gbuffer).__name__}")
    valid = np.asarray(gbuffer.valid)
    if valid.ndim != 2:
        raise ValueError(f"G-buffer valid must have shape (H, W), got shape {valid.shape}")
    h, w = valid.shape
    tails = {"position": (3,), "normal": (3,), "view": (3,), "reflected": (3,), "uv": (2,), "diffuse_albedo": (3,),
             "specular_albedo": (3,), "roughness": (), "object_id": ()}
    for name, tail in tails.items():
        shape = np.shape(getattr(gbuffer, name))
        if shape != (h, w) + tail:
            raise ValueError(f"G-buffer {name} must have shape {(h, w) + tail} (as valid), got shape {shape}")
    v = valid.astype(bool)
    for name in ("position", "normal", "view", "diffuse_albedo", "specular_albedo", "roughness"):
        _nonfinite(f"G-buffer {name} at valid pixels", np.asarray(getattr(gbuffer, name))[v])
    for name in ("normal", "view"):
        length = np.linalg.norm(np.asarray(getattr(gbuffer, name), np.float64)[v], axis=-1)
        length = length[length > 0]  # zero: a lightmap atlas's G-buffer carries no directions
        if length.size and np.max(np.abs(length - 1.0)) > 1e-3:
            raise ValueError(f"G-buffer {name} must be unit vectors at valid pixels, got lengths from "
                             f"{length.min():.6g} to {length.max():.6g}")
    rough = np.asarray(gbuffer.roughness)[v]
    if rough.size and (rough.min() < 0 or rough.max() > 1):
        raise ValueError(f"G-buffer roughness must be in [0, 1] at valid pixels, got {rough.min():.6g} to {rough.max():.6g}")
    for name in ("diffuse_albedo", "specular_albedo"):
        _nonnegative(f"G-buffer {name} at valid pixels", np.asarray(getattr(gbuffer, name))[v], False)
    return gbuffer




def _register_export_serialization() -> None:
    """Let ``jax.export`` serialise functions whose arguments are these NamedTuples."""
    import jax

    for t in (GBuffer, PointLights, SpotLights, DirectionalLights, EnvMap, CubeMap, SHLighting, PointRadiance,
              LightScale, PreconvolvedEnvironment):
        jax.export.register_namedtuple_serialization(t, serialized_name=f"jprt.inputs.{t.__name__}")


_register_export_serialization()
