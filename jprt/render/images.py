"""Direct and indirect radiance from Mitsuba: images for a camera, and batches of arbitrary rays.

The split (DESIGN.md, "Ground truth"): indirect = path tracing with ``max_depth=-1`` minus path
tracing with ``max_depth=2`` (emission + direct lighting), both with the *same sampler seed*.
The integrator is Mitsuba's ``path``, or ``volpath`` in a scene whose surfaces bound media
(``integrator_type``).
The two integrators consume the same random numbers for the shared prefix of every path, so
that prefix cancels exactly and the difference is >= 0 up to float rounding.

``RENDER_STATS`` counts every Mitsuba render call, so callers (and tests) can measure that a
cached dataset renders nothing.
"""

from __future__ import annotations

import collections
import time
from typing import NamedTuple

import numpy as np

from jprt.render.cameras import Camera, camera_rays, check_rays, to_sensor_dict
from jprt.render.scenes import SceneHandle

__all__ = ["Radiance", "RENDER_STATS", "check_spp", "integrator_type", "render", "direct_indirect", "centre_rays",
           "indirect_rays", "radiance_rays"]

#: Counters of Mitsuba work done by this process: "images", "ray_batches", "seconds".
RENDER_STATS: collections.Counter = collections.Counter()

_DIRECT_DEPTH = 2


class Radiance(NamedTuple):
    """Direct, indirect and full radiance, each (H, W, 3) float32 (or (N, 3) for ray batches)."""

    direct: np.ndarray
    indirect: np.ndarray
    full: np.ndarray


def vector_rows(values, m: int) -> np.ndarray:
    """A Dr.Jit 3-vector array of width m (Color3f, Vector3f; NumPy gives it as (3, m)) as an
    (m, 3) NumPy array; a width-1 literal broadcasts to m rows."""
    a = np.array(values, dtype=np.float32)
    if a.size == 3:
        return np.broadcast_to(a.reshape(1, 3), (m, 3))
    if a.ndim == 2 and a.shape[0] == 3 and a.shape[1] == m:
        a = a.T
    return a.reshape(m, 3)


def check_spp(spp) -> int:
    """Return ``spp`` as a positive int or raise a one-line ValueError."""
    if isinstance(spp, bool) or int(spp) != spp or int(spp) <= 0:
        raise ValueError(f"spp must be a positive integer, got {spp!r}")
    return int(spp)


def integrator_type(handle: SceneHandle) -> str:
    """The Mitsuba integrator jprt renders ``handle``'s scene with: ``volpath`` where a surface
    bounds a participating medium (a glass's interior medium; ``SceneHandle.has_media``),
    ``path`` otherwise (the two agree without media; ``path`` keeps earlier renders bit-stable).
    Both count ``max_depth`` alike (-1 unbounded, 2 emission + direct light), so the direct /
    indirect split with equal seeds holds for either."""
    return "volpath" if handle.has_media else "path"


def _integrator(handle: SceneHandle, max_depth: int):
    return handle.mi.load_dict({"type": integrator_type(handle), "max_depth": int(max_depth), "hide_emitters": False})


def render(handle: SceneHandle, camera: Camera, *, spp: int, max_depth: int = -1, seed: int = 0) -> np.ndarray:
    """Path-traced (H, W, 3) radiance of ``camera``; ``max_depth=-1`` is full global illumination."""
    spp = check_spp(spp)
    mi = handle.mi
    sensor = mi.load_dict(to_sensor_dict(camera, spp, mi))
    t0 = time.perf_counter()
    image = mi.render(handle.scene, sensor=sensor, integrator=_integrator(handle, max_depth), seed=int(seed), spp=spp)
    out = np.array(image, dtype=np.float32)
    RENDER_STATS["images"] += 1
    RENDER_STATS["seconds"] += time.perf_counter() - t0
    return out


def direct_indirect(handle: SceneHandle, camera: Camera, *, spp: int, seed: int = 0, max_depth: int = -1) -> Radiance:
    """Direct (``max_depth=2``) and indirect (full minus direct, same seed) images; ``max_depth``
    bounds the full render (-1: unbounded)."""
    full = render(handle, camera, spp=spp, max_depth=max_depth, seed=seed)
    direct = render(handle, camera, spp=spp, max_depth=_DIRECT_DEPTH, seed=seed)
    return Radiance(direct=direct, indirect=full - direct, full=full)


def radiance_rays(handle: SceneHandle, origins, directions, *, spp: int, seed: int = 0,
                  max_depth: int = -1, chunk_rays: int = 1 << 21) -> np.ndarray:
    """Mean radiance (N, 3) arriving along each of N rays, ``spp`` path samples per ray.

    Rays are traced through the ``path`` integrator (``volpath`` with media: ``integrator_type``)
    directly (``integrator.sample``), so any ray bundle works: pixels of any camera, hemispheres at
    surface points, probe directions. Every ray starts in vacuum (outside all media).
    Work is split into chunks of at most ``chunk_rays`` path samples to bound memory.
    """
    spp = check_spp(spp)
    mi = handle.mi
    import drjit as dr

    origins, directions = check_rays(origins, directions)
    integrator = _integrator(handle, max_depth)
    n = origins.shape[0]
    per_chunk = max(1, chunk_rays // spp)
    out = np.empty((n, 3), np.float32)
    t0 = time.perf_counter()
    for c, start in enumerate(range(0, n, per_chunk)):
        stop = min(n, start + per_chunk)
        m = stop - start
        sampler = mi.load_dict({"type": "independent", "sample_count": spp})
        sampler.seed((int(seed) * 7919 + c) % (1 << 32), m * spp)
        rep = lambda a: np.repeat(a[start:stop], spp, axis=0)  # noqa: E731
        o, d = rep(origins), rep(directions)
        ray = mi.RayDifferential3f(mi.Point3f(o[:, 0], o[:, 1], o[:, 2]), mi.Vector3f(d[:, 0], d[:, 1], d[:, 2]))
        spec, _, _ = integrator.sample(handle.scene, sampler, ray)
        out[start:stop] = vector_rows(spec, m * spp).reshape(m, spp, 3).mean(axis=1)
        dr.eval()
    RENDER_STATS["ray_batches"] += 1
    RENDER_STATS["seconds"] += time.perf_counter() - t0
    return out


def indirect_rays(handle: SceneHandle, origins, directions, *, spp: int, seed: int = 0,
                  chunk_rays: int = 1 << 21, max_depth: int = -1) -> Radiance:
    """Direct and indirect radiance (N, 3) along arbitrary rays (per-sample training data).

    Same split as the images: full (``max_depth``, default -1: unbounded) minus ``max_depth=2``
    with equal seeds.
    """
    full = radiance_rays(handle, origins, directions, spp=spp, seed=seed, max_depth=max_depth,
                         chunk_rays=chunk_rays)
    direct = radiance_rays(handle, origins, directions, spp=spp, seed=seed, max_depth=_DIRECT_DEPTH,
                           chunk_rays=chunk_rays)
    return Radiance(direct=direct, indirect=full - direct, full=full)


def centre_rays(handle: SceneHandle, camera: Camera, *, spp: int, seed: int = 0, max_depth: int = -1) -> Radiance:
    """Direct, indirect and full radiance (H, W, 3) along the camera's pixel-centre rays
    (``jprt.render.cameras.camera_rays``), the split of ``indirect_rays``.

    These are the rays the G-buffers trace (``jprt.render.gbuffer.gbuffer``,
    ``jprt.render.lightmap.atlas_gbuffer``), so each pixel is the radiance of the one surface point
    that a per-pixel prediction sees: the reference to score such predictions against. An image of
    ``render`` / ``direct_indirect`` is each pixel's average over its footprint (rays jittered
    over the pixel, box filter) instead: at every silhouette, and wherever a pixel spans several
    texels (a surface seen at grazing angles, an edge thinner than a pixel), it holds light that no
    per-pixel prediction can show (a caustic elsewhere in a pixel, the surface behind an edge;
    CHANGELOG.md has the measured case).
    """
    origins, directions = camera_rays(camera)
    rad = indirect_rays(handle, origins.reshape(-1, 3), directions.reshape(-1, 3), spp=spp, seed=seed,
                        max_depth=max_depth)
    shape = (camera.height, camera.width, 3)
    return Radiance(*(np.asarray(x).reshape(shape) for x in rad))
