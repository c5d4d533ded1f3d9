"""G-buffers from exact pixel-centre primary rays.

Mitsuba's ``aov`` integrator averages over each pixel's footprint, which blurs edges and makes
integer quantities (object ids) meaningless at partially covered pixels. Here every pixel gets
one primary ray through its centre (``sensor.sample_ray`` at film position ((x + 0.5) / W,
(y + 0.5) / H)), intersected with ``scene.ray_intersect``.

Conventions: ``view`` points from the surface to the camera; the shading ``normal`` is flipped to
the viewer's side (n . v >= 0) so back-facing hits behave like two-sided surfaces, and
``reflected = reflect(-view, normal) = 2 (n . v) n - v``. Invalid pixels (the ray escapes) are
zero with ``object_id = -1``.

BRDF parameters per pixel: ``diffuse_albedo`` from the BSDF itself (textures included, through
``eval_diffuse_reflectance``); ``specular_albedo`` and ``roughness`` (GGX alpha) per object,
read from the BSDF's parameters (diffuse objects: specular 0, roughness 1).
"""

from __future__ import annotations

import numpy as np

from jprt.inputs import GBuffer

from jprt.render.cameras import Camera, check_rays, to_sensor_dict
from jprt.render.scenes import SceneHandle

__all__ = ["GBuffer", "gbuffer", "gbuffer_rays", "object_materials"]


def _first_value(params, suffixes) -> np.ndarray | None:
    for key in params.keys():
        if any(key == s or key.endswith("." + s) for s in suffixes):
            value = np.asarray(params[key], np.float32).reshape(-1)
            if value.size:
                return value
    return None


# BSDFs without a diffuse lobe. Mitsuba's default eval_diffuse_reflectance evaluates the whole
# BSDF at normal incidence, which is not zero for them.
_NO_DIFFUSE = ("Conductor", "Dielectric")


def object_materials(handle: SceneHandle) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per shape of the scene, from its BSDF: (specular_albedo (S, 3), roughness (S,),
    has_diffuse (S,) bool)."""
    mi = handle.mi
    specular, roughness, has_diffuse = [], [], []
    for shape in handle.shapes():
        bsdf = shape.bsdf()
        has_diffuse.append(not any(kind in bsdf.class_name() for kind in _NO_DIFFUSE))
        params = mi.traverse(bsdf)
        spec = _first_value(params, ("specular_reflectance.value",))
        alpha = _first_value(params, ("alpha", "alpha.value", "alpha_u", "alpha_u.value"))
        is_specular = alpha is not None or spec is not None
        spec = np.broadcast_to(spec if spec is not None else (1.0 if is_specular else 0.0), (3,))
        specular.append(np.asarray(spec, np.float32))
        roughness.append(float(alpha[0]) if alpha is not None else (0.0 if is_specular else 1.0))
    return np.stack(specular).astype(np.float32), np.asarray(roughness, np.float32), np.asarray(has_diffuse)


def _hits(handle: SceneHandle, ray, n: int) -> dict:
    """Flat (n, ...) first-hit attributes of a Dr.Jit ray batch (see ``GBuffer`` for the fields)."""
    mi = handle.mi
    import drjit as dr

    si = handle.scene.ray_intersect(ray)
    valid = si.is_valid()
    nrm = si.sh_frame.n
    v = -ray.d
    flip = dr.select(dr.dot(nrm, v) < 0, -1.0, 1.0)
    nrm = nrm * flip
    ndotv = dr.dot(nrm, v)
    r = 2.0 * ndotv * nrm - v
    albedo = si.bsdf(ray).eval_diffuse_reflectance(si, valid)
    object_id = dr.full(mi.Int32, -1, n)
    for k, shape in enumerate(handle.shapes()):
        object_id = dr.select(valid & (si.shape == mi.ShapePtr(shape)), k, object_id)

    def arr(value, c):
        a = np.array(value, dtype=np.float32)
        a = a.T if a.ndim == 2 else a
        return a.reshape(n, c) if c > 1 else a.reshape(n)

    valid_np = np.array(valid, dtype=bool).reshape(n)
    mask = valid_np[:, None]
    object_np = np.array(object_id, dtype=np.int32).reshape(n)
    specular_table, roughness_table, diffuse_table = object_materials(handle)
    safe_ids = np.maximum(object_np, 0)
    has_diffuse = (valid_np & diffuse_table[safe_ids])[:, None]

    def unit(a):
        norm = np.linalg.norm(a, axis=-1, keepdims=True)
        return np.where(mask, a / np.maximum(norm, 1e-12), 0.0).astype(np.float32)

    return dict(
        position=np.where(mask, arr(si.p, 3), 0.0).astype(np.float32),
        normal=unit(arr(nrm, 3)),
        view=unit(arr(v, 3)),
        reflected=unit(arr(r, 3)),
        uv=np.where(mask, arr(si.uv, 2), 0.0).astype(np.float32),
        diffuse_albedo=np.where(has_diffuse, arr(albedo, 3), 0.0).astype(np.float32),
        specular_albedo=np.where(mask, specular_table[safe_ids], 0.0).astype(np.float32),
        roughness=np.where(valid_np, roughness_table[safe_ids], 0.0).astype(np.float32),
        object_id=object_np,
        valid=valid_np,
    )


def gbuffer(handle: SceneHandle, camera: Camera) -> GBuffer:
    """Exact pixel-centre G-buffer of ``camera`` in the scene of ``handle``."""
    mi = handle.mi
    import drjit as dr

    sensor = mi.load_dict(to_sensor_dict(camera, 1, mi))
    w, h = camera.width, camera.height
    idx = dr.arange(mi.UInt32, w * h)
    x = mi.Float(idx % w) + 0.5
    y = mi.Float(idx // w) + 0.5
    film_pos = mi.Point2f(x / w, y / h)
    ray, _ = sensor.sample_ray(mi.Float(0.0), mi.Float(0.5), film_pos, mi.Point2f(0.5, 0.5))
    flat = _hits(handle, ray, w * h)
    return GBuffer(**{k: v.reshape((h, w) + v.shape[1:]) for k, v in flat.items()})


def gbuffer_rays(handle: SceneHandle, origins, directions) -> GBuffer:
    """First-hit attributes of arbitrary rays: a ``GBuffer`` whose fields are (N, ...) instead of
    (H, W, ...) (training samples of Ren et al. 2013, Appendix A: attributes at the first
    intersection of random viewing rays). ``view`` is minus the ray direction."""
    mi = handle.mi
    o, d = check_rays(origins, directions)
    ray = mi.Ray3f(mi.Point3f(o[:, 0], o[:, 1], o[:, 2]), mi.Vector3f(d[:, 0], d[:, 1], d[:, 2]))
    return GBuffer(**_hits(handle, ray, o.shape[0]))
