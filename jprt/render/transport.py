"""Ground-truth environment-to-pixel light transport from Mitsuba.

The transport of pixel p to cube-map texel t is the fraction of the radiance of t that reaches p:

    B_p = sum_t T[p, t] L_t                                     (Raghavan et al. 2023, Eq. 1-3)

for an environment map L that is constant over each texel of a (6, n, n) cube map. It is
estimated by tracing BSDF-sampled paths from each pixel's primary ray and adding, whenever a
path escapes the scene, its throughput into the texel of the escape direction (the estimator
of MITSUBA_NOTES.md, "Environment->pixel transport in one pass"). Only BSDF sampling is used:
with the environment as the only emitter that is unbiased, and it needs no emitter at all, so
one pass gives the whole row T[p, :] for every environment at once.

``min_depth`` selects the path lengths: escapes after ``min_depth`` or more scattering events
count. ``min_depth=2`` is the *indirect* transport, the same split as ``jprt.render.images``
(Mitsuba's ``max_depth=2`` is emission plus direct lighting: escapes after 0 or 1 bounces), and
``max_depth`` matches Mitsuba's ``path`` integrator (escapes on segments 0 ... max_depth - 1).
"""

from __future__ import annotations

import time

import numpy as np

from jprt.render.cameras import check_rays
from jprt.render.images import RENDER_STATS, check_spp, vector_rows
from jprt.render.scenes import SceneHandle

__all__ = ["environment_transport"]


def _direction_to_texel(d: np.ndarray, n: int) -> np.ndarray:
    """Flat cube-map texel index face * n^2 + row * n + col of directions (M, 3) (jprt.sphere.cubemap
    conventions; NumPy so the render layer does not trace JAX)."""
    from jprt.sphere.cubemap import direction_to_texel

    face, row, col = (np.asarray(a) for a in direction_to_texel(d, n))
    return (face.astype(np.int64) * n + row) * n + col


def environment_transport(handle: SceneHandle, origins, directions, *, face_size: int, spp: int, seed: int = 0,
                          min_depth: int = 2, max_depth: int = 8, chunk_rays: int = 1 << 20) -> np.ndarray:
    """Transport T (N, 6, n, n, 3) from each cube-map texel to each of N rays (pixels).

    Args:
      handle: the scene (its lights are ignored: every escaping path is counted).
      origins, directions: N primary rays (e.g. ``jprt.render.cameras.camera_rays``).
      face_size: n, the cube map's face size.
      spp: paths per ray.
      min_depth, max_depth: escapes on path segments min_depth ... max_depth - 1 count
        (2, D: the indirect part of Mitsuba's ``path`` integrator with ``max_depth=D``).

    Returns:
      T with B = sum_t T[:, t] L_t for a texel-wise constant map L (6, n, n, 3); T already
      contains the texels' solid angles (it integrates over each texel).

    A scene with participating media (``SceneHandle.has_media``) is refused in one line: these
    paths would cross media without their attenuation.
    """
    spp = check_spp(spp)
    if handle.has_media:
        raise ValueError("environment_transport traces surfaces only (BSDF sampling, no medium attenuation or "
                         "scattering); this scene's surfaces bound participating media (render it with "
                         "jprt.render.images, which uses volpath)")
    if not 0 <= min_depth < max_depth:
        raise ValueError(f"need 0 <= min_depth < max_depth, got {min_depth}, {max_depth}")
    mi = handle.mi
    import drjit as dr

    origins, directions = check_rays(origins, directions)
    n_rays, n_texels = origins.shape[0], 6 * face_size * face_size
    out = np.zeros((n_rays * n_texels, 3), np.float64)
    ctx = mi.BSDFContext()
    per_chunk = max(1, chunk_rays // spp)
    t0 = time.perf_counter()
    for c, start in enumerate(range(0, n_rays, per_chunk)):
        stop = min(n_rays, start + per_chunk)
        m = (stop - start) * spp
        pixel = np.repeat(np.arange(start, stop, dtype=np.int64), spp)
        sampler = mi.load_dict({"type": "independent", "sample_count": spp})
        sampler.seed((int(seed) * 7919 + c) % (1 << 32), m)
        o = np.repeat(origins[start:stop], spp, axis=0)
        d = np.repeat(directions[start:stop], spp, axis=0)
        ray = mi.Ray3f(mi.Point3f(o[:, 0], o[:, 1], o[:, 2]), mi.Vector3f(d[:, 0], d[:, 1], d[:, 2]))
        throughput = mi.Color3f(1.0)
        active = mi.Bool(True)
        for depth in range(max_depth):
            si = handle.scene.ray_intersect(ray, active)
            valid = si.is_valid()
            if depth >= min_depth:
                escaped = np.array(active & ~valid, dtype=bool)
                if escaped.any():
                    w = vector_rows(throughput, m)[escaped]
                    dirs = vector_rows(ray.d, m)[escaped]
                    index = pixel[escaped] * n_texels + _direction_to_texel(dirs, face_size)
                    for ch in range(3):
                        out[:, ch] += np.bincount(index, weights=w[:, ch], minlength=out.shape[0])
            active = active & valid
            if depth == max_depth - 1 or not bool(dr.any(active)):
                break
            bsdf = si.bsdf(ray)
            bs, weight = bsdf.sample(ctx, si, sampler.next_1d(active), sampler.next_2d(active), active)
            throughput = dr.select(active, throughput * weight, 0.0)
            active = active & (bs.pdf > 0) & dr.any(weight != 0)
            ray = si.spawn_ray(si.to_world(bs.wo))
            sampler.schedule_state()
            dr.eval(ray, throughput, active)
    RENDER_STATS["ray_batches"] += 1
    RENDER_STATS["seconds"] += time.perf_counter() - t0
    return (out / spp).astype(np.float32).reshape(n_rays, 6, face_size, face_size, 3)
