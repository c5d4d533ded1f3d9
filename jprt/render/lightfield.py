"""Light-field capture (Currius et al. 2020 §3): for every texel of a lightmap atlas, the radiance
arriving over the whole sphere of directions, as a world-space octahedral map
(``jprt.sphere.octahedral``), path traced by Mitsuba from just above the surface.

For texel t at position x_t with normal n_t and octahedral texel direction w_k (its centre), the
capture is the mean of ``spp`` path samples of L_i(x_t + eps n_t, w_k): the radiance of a ray
leaving x_t + eps n_t along w_k (``jprt.render.images.radiance_rays``). Two maps are kept, both from
the same seeds:

* ``full``: every path (``max_depth=-1``), directly seen emitters and environment included;
* ``indirect``: only paths that have bounced before arriving: ``full`` minus the emitted radiance
  seen directly along w_k (``max_depth=1``, the same seed: the difference cancels exactly in
  Mitsuba 3, MITSUBA_NOTES.md). This is what a texel's lobes fit when the emitters are shaded
  separately.

Directions below the texel's surface (w_k . n_t <= 0) are not traced: ``below`` masks them (the
paper's hemisphere mask of the fitting loss) and their values are 0.

Texels are checked before capture (``jprt.render.lightmap.free_positions``): a capture point inside
other geometry (a box standing on the floor covers floor texels) is pushed out along its normal by
doubling offsets up to ``max_push`` x the texel size; what stays inside is flagged ``INSIDE`` and
left at 0, never averaged into a neighbour. ``flags`` says which texels were pushed (``PUSHED``).

``capture_lightfield`` caches the result through ``jprt.cache`` (content hash of scene, lighting,
atlas and settings; checksummed, atomic) and renders in blocks of texels with a progress bar; an
interrupted capture resumes from its finished blocks (each block is its own cache entry).

``capture_visibility`` captures, from the same points, what the environment terms of §5 need:
the fraction of each octahedral pixel's directions along which a ray escapes the scene (sees the
distant environment), ``samples`` jittered rays per pixel; geometry only, so one capture serves
every environment map.
"""

from __future__ import annotations

import time
from typing import NamedTuple, Sequence

import numpy as np

from jprt import cache
from jprt.render.lightmap import Atlas, ray_offset, intersect, build_atlas, free_positions
from jprt.render.scenes import SceneHandle, describe

__all__ = ["LightField", "Visibility", "OK", "PUSHED", "INSIDE", "capture_points", "capture_block", "capture_lightfield",
           "visibility_block", "capture_visibility"]

#: ``LightField.flags`` values.
OK, PUSHED, INSIDE = 0, 1, 2


class LightField(NamedTuple):
    """Captured incident radiance of the texels of an atlas.

    Fields:
      atlas: the ``jprt.render.lightmap.Atlas`` (as a dict of arrays).
      size: n, the octahedral maps are n x n.
      position: (T, 3) capture points (texel centre plus the offset used).
      normal: (T, 3) unit shading normals of the texels.
      full: (T, n, n, 3) float32 incident radiance, every path.
      indirect: (T, n, n, 3) float32 incident radiance of paths that bounced (full minus the
        directly seen emission).
      below: (T, n, n) bool, directions at or below the texel's surface (not traced, 0).
      flags: (T,) int8: OK, PUSHED (captured from further out) or INSIDE (not captured, 0).
      meta: {"spp", "seed", "jitter", "capture_s", "pushed", "inside"}.
    """

    atlas: dict
    size: int
    position: np.ndarray
    normal: np.ndarray
    full: np.ndarray
    indirect: np.ndarray
    below: np.ndarray
    flags: np.ndarray
    meta: dict


def atlas_digest(*arrays) -> str:
    """SHA-256 of arrays' float32 bytes (the atlas part of a capture's cache key)."""
    import hashlib

    h = hashlib.sha256()
    for x in arrays:
        h.update(np.ascontiguousarray(np.asarray(x, np.float32)).tobytes())
    return h.hexdigest()


def _directions(size: int) -> np.ndarray:
    from jprt.sphere import octahedral

    if int(size) < 2 or int(size) % 2:
        raise ValueError(f"octahedral map size must be even and >= 2, got {size}")
    return np.asarray(octahedral.texel_directions(int(size)), np.float64).reshape(-1, 3)


def capture_points(handle: SceneHandle, position, normal, texel_size: float, *,
                   max_push: float = 4.0) -> tuple[np.ndarray, np.ndarray]:
    """Capture points of texels: ``position + eps normal`` where that is in free space, else
    pushed along the normal by texel_size x 1/4, 1/2, 1, ... up to ``max_push``, never through a
    surface (a floor texel under a box is not moved onto the box's lid); returns the points
    (T, 3) and flags (T,) (OK, PUSHED, INSIDE)."""
    position = np.asarray(position, np.float64).reshape(-1, 3)
    normal = np.asarray(normal, np.float64).reshape(-1, 3)
    eps = ray_offset(handle)
    if not np.isfinite(eps) or eps <= 0:  # a scene without geometry has no scale
        eps = 1e-4
    points = position + eps * normal
    flags = np.full(len(points), INSIDE, np.int8)
    todo = np.arange(len(points))
    offsets = [eps] + [texel_size * f for f in (0.25, 0.5, 1.0, 2.0, 4.0, 8.0) if f <= max_push]
    room = _distance_along(handle, position + eps * normal, normal)  # a push never passes through a surface
    for k, offset in enumerate(offsets):
        if not len(todo):
            break
        trial = position[todo] + offset * normal[todo]
        free = free_positions(handle, trial) & (offset <= room[todo])
        points[todo[free]] = trial[free]
        flags[todo[free]] = OK if k == 0 else PUSHED
        todo = todo[~free]
    return points, flags


def _distance_along(handle: SceneHandle, origins, directions) -> np.ndarray:
    """Distance (K,) to the first surface along each ray (inf where none)."""
    si = intersect(handle, origins, directions)
    valid = np.array(si.is_valid(), bool).reshape(-1)
    return np.where(valid, np.array(si.t, np.float64).reshape(-1), np.inf)


def _jittered_directions(n: int, rng, pixels=None, lead: tuple = ()) -> np.ndarray:
    """Unit directions uniform over the octahedral squares of an n x n map's pixels (all of them,
    or the flat indices ``pixels``), ``lead + (pixels, 3)``: one draw of ``rng`` per call."""
    from jprt.sphere import octahedral

    centres = np.asarray(octahedral.texel_centers(n), np.float64).reshape(-1, 2)
    if pixels is not None:
        centres = centres[pixels]
    uv = np.clip(centres + rng.uniform(-1.0 / n, 1.0 / n, tuple(lead) + centres.shape), -1.0, 1.0)
    d = np.asarray(octahedral.decode(uv.reshape(-1, 2)), np.float64)
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    return d.reshape(uv.shape[:-1] + (3,))


def capture_block(handle: SceneHandle, points, normal, flags, size: int, *, spp: int,
                  seed: int = 0, jitter: bool = False) -> dict:
    """The maps of one block of texels (see the module docstring): {"full", "indirect", "below"}.

    ``jitter``: each of the ``spp`` paths of a pixel leaves along its own direction, uniform over
    the pixel's octahedral square (a path whose direction lies below the surface adds 0), so a
    pixel holds the radiance averaged over its footprint (box-filtered) rather than sampled at its
    centre; a light source much smaller than a pixel (a lamp seen through glass) then adds its
    share to every pixel it overlaps instead of all or nothing. Same number of paths."""
    from jprt.render.images import radiance_rays

    points = np.asarray(points, np.float64).reshape(-1, 3)
    normal = np.asarray(normal, np.float64).reshape(-1, 3)
    dirs = _directions(size)
    m = dirs.shape[0]
    below = (normal @ dirs.T) <= 0.0  # (B, m)
    traced = ~below & (np.asarray(flags) != INSIDE)[:, None]
    rows, cols = np.nonzero(traced)
    full = np.zeros((len(points), m, 3), np.float32)
    indirect = np.zeros((len(points), m, 3), np.float32)
    if len(rows) and jitter:  # (spp, rows) paths, one direction each
        rng = np.random.default_rng([int(seed), 17])
        d = _jittered_directions(int(size), rng, cols, lead=(int(spp),))
        o = np.broadcast_to(points[rows], d.shape)
        up = (np.einsum("srk,rk->sr", d, normal[rows]) > 0.0)[..., None]
        every = radiance_rays(handle, o.reshape(-1, 3), d.reshape(-1, 3), spp=1, seed=seed, max_depth=-1)
        seen = radiance_rays(handle, o.reshape(-1, 3), d.reshape(-1, 3), spp=1, seed=seed, max_depth=1)
        every, seen = (np.where(up, x.reshape(d.shape), 0.0) for x in (every, seen))
        full[rows, cols] = every.mean(0)
        indirect[rows, cols] = (every - seen).mean(0)
    elif len(rows):
        o, d = points[rows], dirs[cols]
        every = radiance_rays(handle, o, d, spp=spp, seed=seed, max_depth=-1)
        seen = radiance_rays(handle, o, d, spp=spp, seed=seed, max_depth=1)
        full[rows, cols] = every
        indirect[rows, cols] = every - seen
    shape = (len(points), int(size), int(size))
    return {"full": full.reshape(shape + (3,)), "indirect": indirect.reshape(shape + (3,)),
            "below": below.reshape(shape)}


def _setup(scene, lighting, objects, resolution: int, atlas):
    """The scene, its handle, the atlas (built when not given) and the texels' capture points."""
    desc = describe(scene)
    handle = SceneHandle(desc, lighting)
    if atlas is None:
        atlas = build_atlas(handle, list(objects) if objects else None, resolution=int(resolution))
    a = atlas._asdict() if isinstance(atlas, Atlas) else dict(atlas)
    points, flags = capture_points(handle, a["position"], a["normal"], float(a["texel_size"]))
    return desc, handle, a, points, flags


def _cached_blocks(namespace: str, base: dict, count: int, block: int, build, label: str, progress: bool | None,
                   cache_dir: str | None):
    """Texels in blocks of ``block``, each block ``build(start, stop, index)``'s arrays cached as
    its own entry (``base`` + the block's range: a killed capture resumes), with a progress bar;
    returns ``key -> the blocks' arrays concatenated`` (an empty array for no texels)."""
    from jprt.progress import bar as progress_bar

    parts = []
    starts = list(range(0, int(count), int(block)))
    for b, start in enumerate(progress_bar(starts, progress=progress, desc=label, unit="block")):
        stop = min(int(count), start + int(block))
        arrays, _ = cache.cached(namespace, {**base, "block": [start, stop]},
                                 lambda start=start, stop=stop, b=b: build(start, stop, b), cache_dir=cache_dir)
        parts.append(arrays)
    return lambda k: np.concatenate([p[k] for p in parts]) if parts else np.zeros((0,))


def capture_lightfield(scene, lighting=None, *, objects: Sequence[str] | None = None, resolution: int = 64,
                       size: int = 32, spp: int = 64, seed: int = 0, block: int = 256,
                       atlas: Atlas | dict | None = None, cache_dir: str | None = None,
                       progress: bool | None = None, jitter: bool = False) -> LightField:
    """Capture the light field of every texel of ``atlas`` (default: ``build_atlas`` of ``objects``
    at ``resolution``) in ``scene`` under ``lighting`` (``None``: the scene's own emitters):
    ``size`` x ``size`` octahedral maps, ``spp`` paths per direction (at the pixel centre, or
    with ``jitter`` each over the pixel's footprint: ``capture_block``). Blocks of ``block`` texels
    are cache entries of their own (an interrupted capture resumes); the assembled light field is
    returned (not stored twice)."""
    from jprt.render.lights import lighting_description

    desc, handle, a, points, flags = _setup(scene, lighting, objects, resolution, atlas)
    base = {"format": 1, "scene": desc, "lighting": lighting_description(lighting) if lighting is not None else None,
            "atlas": atlas_digest(a["position"], a["normal"]),
            "size": int(size), "spp": int(spp), "seed": int(seed), **({"jitter": True} if jitter else {})}
    t0 = time.perf_counter()

    def build(start, stop, b):
        return capture_block(handle, points[start:stop], np.asarray(a["normal"])[start:stop], flags[start:stop],
                             int(size), spp=int(spp), seed=int(seed) * 1000003 + b, jitter=bool(jitter))

    cat = _cached_blocks("lightfield", base, len(points), block, build, "light-field capture", progress, cache_dir)
    return LightField(a, int(size), points.astype(np.float32), np.asarray(a["normal"], np.float32), cat("full"),
                      cat("indirect"), cat("below").astype(bool), flags,
                      {"spp": int(spp), "seed": int(seed), "jitter": bool(jitter), "capture_s": time.perf_counter() - t0,
                       "pushed": int((flags == PUSHED).sum()), "inside": int((flags == INSIDE).sum())})


class Visibility(NamedTuple):
    """Environment visibility of the texels of an atlas (``capture_visibility``).

    Fields:
      atlas: the atlas (dict of arrays).  size: n, the maps are n x n.
      position: (T, 3) capture points.  normal: (T, 3) unit texel normals.
      visible: (T, n, n) float32 in [0, 1]: the fraction of the pixel's jittered rays that leave
        the scene (0 below the surface and for INSIDE texels).
      below: (T, n, n) bool, pixels whose centre is at or below the texel's surface.
      flags: (T,) int8 as in ``LightField``.  meta: {"samples", "seed", "capture_s"}.
    """

    atlas: dict
    size: int
    position: np.ndarray
    normal: np.ndarray
    visible: np.ndarray
    below: np.ndarray
    flags: np.ndarray
    meta: dict


def visibility_block(handle: SceneHandle, points, normal, flags, size: int, *, samples: int = 4,
                     seed: int = 0) -> dict:
    """One block's maps (``Visibility``): {"visible", "below"}; a jittered ray that points below
    the surface counts as blocked."""
    points = np.asarray(points, np.float64).reshape(-1, 3)
    normal = np.asarray(normal, np.float64).reshape(-1, 3)
    n = int(size)
    rng = np.random.default_rng(int(seed))
    visible = np.zeros((len(points), n * n), np.float64)
    below = (normal @ _directions(n).T) <= 0.0
    active = np.asarray(flags) != INSIDE
    for _ in range(int(samples)):
        dirs = _jittered_directions(n, rng)
        above = ((normal @ dirs.T) > 0.0) & active[:, None]
        rows, cols = np.nonzero(above)
        if len(rows):
            si = intersect(handle, points[rows], dirs[cols])
            visible[rows, cols] += ~np.array(si.is_valid(), bool).reshape(-1)
    visible /= max(int(samples), 1)
    shape = (len(points), n, n)
    return {"visible": visible.astype(np.float32).reshape(shape), "below": below.reshape(shape)}


def capture_visibility(scene, *, objects: Sequence[str] | None = None, resolution: int = 64, size: int = 64,
                       samples: int = 4, seed: int = 0, block: int = 256, atlas: Atlas | dict | None = None,
                       cache_dir: str | None = None, progress: bool | None = None) -> Visibility:
    """The environment visibility of every texel of ``atlas`` (default: ``build_atlas`` of
    ``objects`` at ``resolution``) in ``scene``, from the capture points ``capture_lightfield``
    uses: ``size`` x ``size`` octahedral maps, ``samples`` jittered rays per pixel. Cached per
    block of texels like the light field (resumable)."""
    desc, handle, a, points, flags = _setup(scene, None, objects, resolution, atlas)
    base = {"format": 1, "kind": "visibility", "scene": desc, "atlas": atlas_digest(a["position"], a["normal"]),
            "size": int(size), "samples": int(samples), "seed": int(seed)}
    t0 = time.perf_counter()

    def build(start, stop, b):
        return visibility_block(handle, points[start:stop], np.asarray(a["normal"])[start:stop], flags[start:stop],
                                int(size), samples=int(samples), seed=int(seed) * 1000003 + b)

    cat = _cached_blocks("visibility", base, len(points), block, build, "visibility capture", progress, cache_dir)
    return Visibility(a, int(size), points.astype(np.float32), np.asarray(a["normal"], np.float32), cat("visible"),
                      cat("below").astype(bool), flags,
                      {"samples": int(samples), "seed": int(seed), "capture_s": time.perf_counter() - t0})
