"""Sampling designs for training data: Latin hypercube samples in boxes, and the boxes a scene
suggests (``scene_regions``: where lights and views go when a config does not say).

Ren et al. 2013, Appendix A: "we uniformly subdivide the light range into N_l strata and randomly
sample the light position in each stratum" (Latin hypercube sampling, McKay et al.): along every
dimension the n samples fall one per stratum [k/n, (k+1)/n), with the strata of different
dimensions paired by independent random permutations.
"""

from __future__ import annotations

import warnings

import numpy as np

__all__ = ["latin_hypercube", "check_box", "scene_regions", "view_region_points", "free_lights", "even_lights",
           "uniform_free_lights", "NoFreeSpace", "centroidal_points", "EVEN_POOL", "EVEN_RULE", "view_points",
           "lit_fraction", "serves_view", "REGION_KEYS", "CORNELL_REGIONS", "MIN_LIT_FRACTION", "LIGHT_RULE"]


def check_box(lo, hi, name: str = "box") -> tuple[np.ndarray, np.ndarray]:
    """``(lo, hi)`` as float64 arrays of equal shape with lo <= hi, or a one-line ValueError."""
    lo = np.asarray(lo, np.float64).reshape(-1)
    hi = np.asarray(hi, np.float64).reshape(-1)
    if lo.shape != hi.shape or lo.size == 0:
        raise ValueError(f"{name}: corners {lo.tolist()} and {hi.tolist()} need the same non-zero length")
    if not (np.isfinite(lo).all() and np.isfinite(hi).all()) or np.any(hi < lo):
        raise ValueError(f"{name}: need finite corners with lo <= hi, got lo={lo.tolist()} hi={hi.tolist()}")
    return lo, hi


def latin_hypercube(rng: np.random.Generator, n: int, lo, hi) -> np.ndarray:
    """``n`` Latin-hypercube samples (n, D) in the box [lo, hi] (D = len(lo)).

    Each coordinate has exactly one sample in each of its n equal strata; degenerate dimensions
    (lo == hi) are constant.
    """
    lo, hi = check_box(lo, hi)
    n = int(n)
    if n <= 0:
        raise ValueError(f"need at least one sample, got n={n}")
    d = lo.size
    strata = np.stack([rng.permutation(n) for _ in range(d)], axis=1)
    u = (strata + rng.random((n, d))) / n
    return lo + (hi - lo) * u


#: The sampling regions ``scene_regions`` chooses when the config leaves them None.
REGION_KEYS = ("light_lo", "light_hi", "view_lo", "view_hi", "view_target", "fov")

#: The built-in Cornell boxes' regions (tuned for them; the numbers of benchmarks/results/rrf_*).
CORNELL_REGIONS = {"light_lo": [-0.6, 0.3, -0.6], "light_hi": [0.6, 0.9, 0.6], "view_lo": [-0.6, -0.4, 2.8],
                   "view_hi": [0.6, 0.4, 3.9], "view_target": [0.0, 0.0, 0.0], "fov": 39.3077}


def scene_regions(scene) -> dict:
    """Light and view sampling regions of ``scene`` (``REGION_KEYS`` and ``source``), what the
    config's None means:

    * the built-in Cornell boxes: ``CORNELL_REGIONS`` (source "cornell");
    * any other scene (source "scene bounds"), from its bounding box B (extent e): lights in the
      upper part of the room, x and z within B shrunk by 0.2 e, y from 0.55 to 0.85 of its height
      (light samples inside geometry or within 0.02 e of a surface are drawn again:
      ``free_lights``); views from the scene file's own camera when it has one (a box of 0.1 e
      about its position, its field of view, looking where it looks: the target is the point of
      its view ray nearest B's centre), else from inside B (shrunk by 0.3 e, at 0.35-0.65 of its
      height) towards B's centre with a 60 degree field of view. Views therefore look at the
      room as the file's author framed it."""
    from jprt.render.scenes import SceneHandle, describe

    desc = describe(scene)
    if desc["name"] in ("cornell_box", "glossy_cornell"):
        return {**{k: (list(v) if isinstance(v, list) else v) for k, v in CORNELL_REGIONS.items()}, "source": "cornell"}
    handle = SceneHandle(desc)
    box = handle.scene.bbox()
    lo, hi = np.asarray(box.min, np.float64), np.asarray(box.max, np.float64)
    ext = hi - lo
    size = float(ext.max())
    light_lo = lo + 0.2 * ext
    light_hi = hi - 0.2 * ext
    light_lo[1], light_hi[1] = lo[1] + 0.55 * ext[1], lo[1] + 0.85 * ext[1]
    centre = 0.5 * (lo + hi)
    sensors = handle.scene.sensors()
    if desc["name"] == "xml" and sensors:
        cam = handle.default_camera(64, 64)
        origin = np.asarray(cam.origin, np.float64)
        forward = np.asarray(cam.target, np.float64) - origin
        forward /= max(np.linalg.norm(forward), 1e-12)
        view_lo, view_hi = origin - 0.05 * size, origin + 0.05 * size
        target = origin + max(float(np.dot(centre - origin, forward)), 0.1 * size) * forward
        fov = float(cam.fov)
    else:
        view_lo, view_hi = lo + 0.3 * ext, hi - 0.3 * ext
        view_lo[1], view_hi[1] = lo[1] + 0.35 * ext[1], lo[1] + 0.65 * ext[1]
        target, fov = centre, 60.0
    return {"light_lo": light_lo.tolist(), "light_hi": light_hi.tolist(), "view_lo": view_lo.tolist(),
            "view_hi": view_hi.tolist(), "view_target": target.tolist(), "fov": fov, "source": "scene bounds"}


def view_region_points(handle, n: int = 3) -> np.ndarray:
    """(K, 3) points the scene is looked at from: an ``n`` x ``n`` x ``n`` grid over the corners
    and inside of its view region (``scene_regions``; about the file's own camera), less those
    inside geometry (``jprt.render.lightmap.free_positions``)."""
    from jprt.render.lightmap import free_positions

    regions = scene_regions(handle.description)
    lo, hi = np.asarray(regions["view_lo"], np.float64), np.asarray(regions["view_hi"], np.float64)
    t = np.linspace(0.0, 1.0, int(n))
    grid = np.stack(np.meshgrid(t, t, t, indexing="ij"), -1).reshape(-1, 3)
    points = lo + grid * (hi - lo)
    free = free_positions(handle, points)
    return points[free] if free.any() else points


#: A light drawn for a scene file must light directly at least this share of the points its own
#: camera sees (``lit_fraction``), else it is drawn again. Chosen on ``staircase``, whose light
#: box (the upper part of the file's bounds) is a third upstairs, out of the camera's hall: 8 of 24
#: lights there lit no point of the view, the others 11-62 %. On ``cornell_box_picture``,
#: ``veach-bidir`` and ``living-room`` every light of the box lit 68-97 %, so the rule leaves their
#: lights as they were (CHANGELOG.md, 2026-12-05).
MIN_LIT_FRACTION = 0.05
#: The version of the light-drawing rule, part of the cache keys of datasets whose lights it drew.
LIGHT_RULE = 2


def view_points(handle, size: int = 32) -> tuple[np.ndarray, np.ndarray] | None:
    """The points a scene file's own camera sees (a ``size`` x ``size`` G-buffer of its
    pixel-centre rays): (ray origins just off each surface, (N, 3); the surfaces' normals, facing
    the camera). None for a scene without a camera of its own (the built-in scenes), where there
    is no view to serve."""
    from jprt.render.gbuffer import gbuffer
    from jprt.render.lightmap import ray_offset

    if handle.description.get("name") != "xml" or not handle.scene.sensors():
        return None
    g = gbuffer(handle, handle.default_camera(size, size))
    valid = np.asarray(g.valid).reshape(-1)
    points = np.asarray(g.position, np.float64).reshape(-1, 3)[valid]
    normals = np.asarray(g.normal, np.float64).reshape(-1, 3)[valid]
    return points + ray_offset(handle) * normals, normals


def lit_fraction(handle, positions, size: int = 32, view=None) -> np.ndarray | None:
    """(K,) the share of the points a scene file's own camera sees (``view_points``; ``view``:
    those points, computed once by a caller that asks many times) that a point light at each of
    ``positions`` lights directly: the surface faces it and nothing is in between. None for a
    scene without a camera of its own."""
    from jprt.render.lightmap import unoccluded

    view = view_points(handle, size) if view is None else view
    if view is None:
        return None
    origins, normals = view
    if not len(origins):
        return np.zeros(len(np.atleast_2d(positions)))
    lights = np.asarray(positions, np.float64).reshape(-1, 3)
    facing = np.einsum("lnk,nk->ln", lights[:, None] - origins[None], normals) > 0
    return (facing & unoccluded(handle, origins, lights, rel=1e-4)).mean(axis=1)


def serves_view(handle, positions, view) -> np.ndarray:
    """(K,) bool: a point light at each of ``positions`` lights at least ``MIN_LIT_FRACTION`` of
    ``view`` (``view_points`` of ``handle``; every light serves when it is None)."""
    positions = np.asarray(positions, np.float64).reshape(-1, 3)
    if view is None:
        return np.ones(len(positions), bool)
    return lit_fraction(handle, positions, view=view) >= MIN_LIT_FRACTION


def centroidal_points(points, n: int, rng: np.random.Generator, *, iters: int = 40) -> np.ndarray:
    """``n`` of ``points`` (M, D), M >= n, spread evenly over them: Lloyd's k-means (a centroidal
    Voronoi tessellation of the point set, ``iters`` rounds from ``n`` random points), each
    centroid then replaced by the nearest point not taken yet, so every pick is one of ``points``.

    From a uniform set (``even_lights``' candidates) the cells come out about equally large, so
    inside the region the picks are as dense everywhere (asymptotically, from a non-uniform set
    their density goes as the set's to the power D / (D + 2)); a band about half a spacing wide
    along the region's boundary holds fewer picks than a uniform draw would put there, where a
    farthest-point draw crowds it; and they leave fewer and smaller gaps than ``n`` independent
    draws from the set. In a non-convex set a centroid may fall outside it (behind a pillar):
    its pick is then the nearest member, which may lie across a thin wall from it."""
    from scipy.spatial import cKDTree

    points = np.asarray(points, np.float64)
    n = int(n)
    if n <= 0 or n > len(points):
        raise ValueError(f"need 1 <= n <= {len(points)} points to choose from, got n={n}")
    centres = points[rng.choice(len(points), n, replace=False)].copy()
    for _ in range(int(iters)):
        label = cKDTree(centres).query(points)[1]
        counts = np.bincount(label, minlength=n)
        sums = np.zeros_like(centres)
        np.add.at(sums, label, points)
        moved = counts > 0  # an empty cell keeps its centre
        new = centres.copy()
        new[moved] = sums[moved] / counts[moved, None]
        if np.allclose(new, centres):
            break
        centres = new
    taken = np.zeros(len(points), bool)
    out = np.empty_like(centres)
    tree = cKDTree(points)
    for k, c in enumerate(centres):
        near = tree.query(c, k=min(len(points), 16))[1]
        free = [i for i in np.atleast_1d(near) if not taken[i]]
        i = free[0] if free else int(np.flatnonzero(~taken)[np.argmin(
            np.sum((points[~taken] - c) ** 2, axis=1))])
        taken[i] = True
        out[k] = points[i]
    return out


#: Acceptable candidates ``even_lights`` spreads its lights over, per light.
EVEN_POOL = 16
#: The version of ``even_lights``' rule (pool size, k-means, picking), part of the cache keys of
#: datasets whose lights it drew.
EVEN_RULE = 1


class NoFreeSpace(ValueError):
    """A light box with too little space where a light may go (off geometry, lighting enough of
    the file's camera's view): ``free_lights``, ``even_lights``, ``uniform_free_lights``."""


def _no_free_space(lo, hi) -> NoFreeSpace:
    return NoFreeSpace(f"no free space for lights in the light box {np.asarray(lo).tolist()} / "
                       f"{np.asarray(hi).tolist()} (outside geometry, lighting at least {MIN_LIT_FRACTION:.0%} of "
                       "what the file's camera sees): set the light box")


def _light_rule(scene):
    """``acceptable(points) -> (K,) bool``: where a light may go in ``scene`` (``free_lights``'
    rule): outside geometry, at least 2 % of the scene's extent from any surface
    (``lightmap.free_positions``), and lighting at least ``MIN_LIT_FRACTION`` of what the file's
    camera sees (``serves_view``, asked only of the free points). The camera's view is traced
    once, here."""
    from jprt.render.lightmap import free_positions
    from jprt.render.scenes import SceneHandle

    handle = SceneHandle(scene)
    box = handle.scene.bbox()
    clearance = 0.02 * float(np.max(np.asarray(box.max) - np.asarray(box.min)))
    view = view_points(handle)

    def acceptable(points):
        ok = free_positions(handle, points, clearance=clearance)
        if ok.any():
            ok[ok] = serves_view(handle, points[ok], view)
        return ok

    return acceptable


def _acceptable_pool(scene, want: int, light_lo, light_hi, rng, tries: int) -> np.ndarray:
    """Up to ``want`` uniform points of the light box where ``free_lights`` would keep a light,
    drawn ``want`` at a time for at most ``tries`` rounds (fewer where the box has little such
    space), in the order drawn."""
    acceptable = _light_rule(scene)
    lo, hi = check_box(light_lo, light_hi, "light box")
    pool, have = [], 0
    for _ in range(int(tries)):
        cand = lo + (hi - lo) * rng.random((want, lo.size))
        ok = acceptable(cand)
        pool.append(cand[ok])
        have += int(ok.sum())
        if have >= want:
            break
    return np.concatenate(pool)[:want]


def even_lights(scene, n: int, light_lo, light_hi, rng, tries: int = 50) -> np.ndarray:
    """``n`` training lights spread evenly over the acceptable part of the light box: uniform
    candidates in the box, kept where ``free_lights`` would keep a light (off geometry, lighting
    enough of the file's camera's view), ``EVEN_POOL`` per light, then ``centroidal_points`` of
    them. Held-out lights drawn uniformly from the same space (``free_lights``) then fall nearer a
    training light, in distribution, than to ``n`` lights drawn as ``free_lights`` draws them
    (CHANGELOG.md, 2026-12-07 (afternoon), measured on the four interiors). ``NoFreeSpace`` when
    fewer than ``n`` acceptable candidates are found in ``tries`` rounds, a warning when fewer
    than ``EVEN_POOL`` a light are."""
    want = EVEN_POOL * int(n)
    pool = _acceptable_pool(scene, want, light_lo, light_hi, rng, tries)
    if len(pool) < int(n):
        raise _no_free_space(light_lo, light_hi)
    if len(pool) < want:
        warnings.warn(f"even_lights: {len(pool)} acceptable candidates for {int(n)} lights (of {tries * want} drawn; "
                      f"{EVEN_POOL} a light asked for): the lights are spread over fewer", stacklevel=2)
    return centroidal_points(pool, n, rng)


def uniform_free_lights(scene, n: int, light_lo, light_hi, rng, tries: int = 50) -> np.ndarray:
    """``n`` lights drawn independently and uniformly over the part of the light box where
    ``free_lights`` would keep a light, as ``even_lights`` draws its candidates (``EVEN_POOL`` x
    ``n`` a round, up to ``tries`` rounds): for a box where ``free_lights``, which redraws each
    refused light on its own, gives up first. ``NoFreeSpace`` when fewer than ``n`` are found."""
    pool = _acceptable_pool(scene, EVEN_POOL * int(n), light_lo, light_hi, rng, tries)
    if len(pool) < int(n):
        raise _no_free_space(light_lo, light_hi)
    return pool[:int(n)]


def free_lights(scene, lights: np.ndarray, light_lo, light_hi, rng, tries: int = 50) -> np.ndarray:
    """Light positions outside geometry, at least 2 % of the light box's scene extent from any
    surface (``lightmap.free_positions``) and, in a scene file with a camera, lighting at least
    ``MIN_LIT_FRACTION`` of what that camera sees (``lit_fraction``: a light in another room
    serves no view): each one that is not is drawn again, uniformly in the light box;
    ``NoFreeSpace`` (a ValueError) when one is still refused after ``tries`` rounds."""
    acceptable = _light_rule(scene)
    lo, hi = np.asarray(light_lo, np.float64), np.asarray(light_hi, np.float64)
    lights = np.array(lights, np.float64)
    for _ in range(tries):
        bad = ~acceptable(lights)
        if not bad.any():
            return lights
        lights[bad] = lo + (hi - lo) * rng.random((int(bad.sum()), 3))
    raise _no_free_space(lo, hi)
