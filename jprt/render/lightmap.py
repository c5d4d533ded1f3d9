"""Texture-space (lightmap) layouts of scene objects, surface samples, and radiance at surface points.

A lightmap stores one outgoing radiance per texel of an *atlas*: a square R x R image in which
every chosen object owns one or more charts (Belcour et al. 2022, §4.1: "we evaluate indirect
illumination in textures using the UV-space of the asset, thus each row of I is a lightmap").

Charts:
  * an object whose own UV layout does not overlap itself (Spot, Mitsuba's rectangles) is one
    chart, its UVs scaled to world units;
  * an object whose UVs overlap but that has few face planes (Mitsuba's cube maps all six faces
    onto [0, 1]^2; stairs) is split into planar charts, one per face plane, each parameterised by
    two axes of its plane;
  * any other object (no UVs, UVs collapsed to a point, or overlapping UVs on a curved mesh that
    would make thousands of planar charts) is unwrapped by xatlas (the lightmap unwrapper engines
    use: charts cut and packed without overlap), its layout scaled to world units.
Zero-area triangles are dropped (counted in a warning; a ray never hits them). Charts are
packed on shelves at one common texel size (world units per texel), with a two-texel gutter, so
texel density is uniform over the atlas, except that an object too small for ``min_texels``
texels at that density is scaled up until it has them.

Every triangle t then has an affine map ``uv = A_t [p, 1]`` from world position to atlas UV
(exact inside the triangle, since the barycentric interpolation of its corner UVs is affine).
A G-buffer pixel's atlas UV is therefore a function of (object, primitive index, position),
which ``atlas_gbuffer`` evaluates for a camera. ``Atlas`` holds only NumPy arrays (no Mitsuba
objects), so methods take it as data.

Radiance at surface points (texel centres, measurement points) is traced as rays that start a
small distance ``eps`` above the point along its geometric normal and point back at it: for a
diffuse surface that returns the outgoing radiance at the point; ``images.radiance_rays`` does
the path tracing, so the direct / indirect split is the same as for images.
"""

from __future__ import annotations

from typing import NamedTuple, Sequence

import numpy as np

from jprt.render import images
from jprt.render.cameras import Camera, camera_rays
from jprt.render.gbuffer import GBuffer, gbuffer, gbuffer_rays, hit_objects
from jprt.render.lights import DirectionalLights, Lighting, PointLights, SpotLights
from jprt.render.scenes import SceneHandle

__all__ = [
    "Atlas",
    "SurfacePoints",
    "mesh_triangles",
    "build_atlas",
    "atlas_gbuffer",
    "surface_samples",
    "albedo_at_points",
    "radiance_at_points",
    "direct_at_points",
    "indirect_at_points",
    "points_pathtracer",
    "incident_delta_lights",
    "free_positions",
    "enclosing_objects",
    "sees_points",
]

_GUTTER = 2  # texels between charts


class Atlas(NamedTuple):
    """A lightmap layout over some objects of a scene (all NumPy).

    Fields:
      resolution:  R, the atlas is R x R texels.
      objects:     (O,) int32 object ids (indices into ``SceneHandle.object_names()``).
      tri_offset:  (O,) int32 first global triangle of each object.
      tri_affine:  (F, 2, 4) float64 world position -> atlas UV map of every triangle.
      texel_index: (T,) int32 flat index (row * R + column) of each covered texel.
      position:    (T, 3) float32 world position of each covered texel centre.
      normal:      (T, 3) float32 unit geometric normal there.
      texel_object:(T,) int32 object id of each texel.
      fill_index:  (R * R,) int32 texel (0..T-1) whose value each atlas pixel shows: itself where
                   covered, the nearest covered texel elsewhere (gutter dilation for bilinear lookup).
      texel_size:  world units per texel.
    """

    resolution: int
    objects: np.ndarray
    tri_offset: np.ndarray
    tri_affine: np.ndarray
    texel_index: np.ndarray
    position: np.ndarray
    normal: np.ndarray
    texel_object: np.ndarray
    fill_index: np.ndarray
    texel_size: float

    @property
    def count(self) -> int:
        """Number of covered texels T."""
        return int(self.texel_index.shape[0])


class SurfacePoints(NamedTuple):
    """Points on scene surfaces (measurement points of Belcour et al. 2022, §4.1).

    Fields:
      position: (S, 3) float32.  normal: (S, 3) float32 unit geometric normal.
      albedo:   (S, 3) float32 diffuse albedo.  object_id: (S,) int32.
      area:     total area of the sampled surfaces (for blue-noise radii).
    """

    position: np.ndarray
    normal: np.ndarray
    albedo: np.ndarray
    object_id: np.ndarray
    area: float


# --------------------------------------------------------------------------------------------
# Geometry of the objects


def _object_index(handle: SceneHandle, objects: Sequence[str | int] | None) -> list[int]:
    names = handle.object_names()
    if objects is None:
        return list(range(len(names)))
    out = []
    for o in objects:
        if isinstance(o, (int, np.integer)):
            if not 0 <= int(o) < len(names):
                raise ValueError(f"object id {o} out of range (the scene has {len(names)} objects)")
            out.append(int(o))
        elif o in names:
            out.append(names.index(o))
        else:
            raise ValueError(f"unknown object {o!r}; the scene's objects are {names}")
    if len(set(out)) != len(out):
        raise ValueError(f"objects listed twice: {objects}")
    return out


def mesh_triangles(handle: SceneHandle, object_id: int) -> tuple[np.ndarray, np.ndarray | None]:
    """Triangles of one object: world corners (F, 3, 3) and corner UVs (F, 3, 2) or None. Triangle
    f of a mesh is its primitive f; a rectangle is one primitive split into two triangles that
    share one planar UV map.

    A scene file's disks, spheres and cylinders are meshes already (``scenes.xml`` tessellates
    them, ``SceneHandle.tessellated``); their UVs are Mitsuba's polar / latitude-longitude ones,
    whose texel density varies across the shape, so they come without UVs here and atlases unwrap
    them (planar charts for a disk, xatlas for the curved ones). Anything else that is not a
    triangle mesh (the analytic sphere of ``glossy_cornell``, curves, SDF grids) is refused in one
    line: its hits carry no triangle index a lightmap could map."""
    mi = handle.mi
    shape = handle.shapes()[object_id]
    params = mi.traverse(shape)
    keys = set(params.keys())
    if "vertex_positions" in keys:
        v = np.array(params["vertex_positions"], np.float64).reshape(-1, 3)
        f = np.array(params["faces"], np.int64).reshape(-1, 3)
        uv = np.array(params["vertex_texcoords"], np.float64).reshape(-1, 2) if "vertex_texcoords" in keys else None
        if uv is not None and (uv.shape[0] != v.shape[0] or shape.id() in getattr(handle, "tessellated", ())):
            uv = None
        return v[f], (uv[f] if uv is not None else None)
    if "to_world" in keys and shape.class_name() == "Rectangle":
        m = np.array(params["to_world"].matrix, np.float64).reshape(4, 4)
        local = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], np.float64)
        world = local @ m[:3, :3].T + m[:3, 3]
        uv = (local[:, :2] + 1.0) / 2.0
        tri = np.array([[0, 1, 2], [0, 2, 3]])
        return world[tri], uv[tri]
    raise ValueError(f"object {handle.object_names()[object_id]!r} (Mitsuba {shape.class_name()}) is not a triangle "
                     "mesh or a rectangle, which lightmaps, surface samples and per-vertex data need (scene files' "
                     "disks, spheres, cylinders and instances become meshes; built-in analytic shapes do not)")


def _areas(tris: np.ndarray) -> np.ndarray:
    return 0.5 * np.linalg.norm(np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0]), axis=1)


def _geometric_normals(tris: np.ndarray) -> np.ndarray:
    n = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)


def _uv_overlaps(uv: np.ndarray, res: int = 256) -> float:
    """Fraction of covered texels of a UV layout that more than one triangle covers."""
    lo, hi = uv.reshape(-1, 2).min(0), uv.reshape(-1, 2).max(0)
    scaled = (uv - lo) / np.maximum(hi - lo, 1e-12) * res
    count = np.zeros((res, res), np.int32)
    for t in range(scaled.shape[0]):
        idx, _ = _raster_triangle(scaled[t], res)
        np.add.at(count.reshape(-1), idx, 1)
    covered = count > 0
    return float((count > 1).sum() / max(covered.sum(), 1))


def _texel_barycentrics(corners: np.ndarray, res: int, margin: float):
    """The texels (flat indices) of a triangle given in texel units, its bounding box grown by
    ``margin`` texels, with their centres (n, 2) and the centres' barycentric coordinates (n, 3);
    None for a box outside the atlas or a degenerate triangle."""
    lo = np.maximum(np.floor(corners.min(0) - margin).astype(int), 0)
    hi = np.minimum(np.ceil(corners.max(0) + margin).astype(int), res - 1)
    if np.any(hi < lo):
        return None
    a, b, c = corners
    m = np.array([b - a, c - a]).T
    if abs(np.linalg.det(m)) < 1e-14:
        return None
    xs, ys = np.meshgrid(np.arange(lo[0], hi[0] + 1), np.arange(lo[1], hi[1] + 1))
    p = np.stack([xs.ravel() + 0.5, ys.ravel() + 0.5], axis=1)
    l12 = np.linalg.solve(m, (p - a).T).T
    return ys.ravel() * res + xs.ravel(), p, np.column_stack([1.0 - l12.sum(1), l12])


def _raster_triangle(corners: np.ndarray, res: int, eps: float = 1e-9):
    """Texel centres (flat indices) inside a triangle given in texel units, and their
    barycentric coordinates (n, 3)."""
    grid = _texel_barycentrics(corners, res, 0.5)
    if grid is None:
        return np.zeros(0, np.int64), np.zeros((0, 3))
    flat, _, bary = grid
    inside = np.all(bary >= -eps, axis=1)
    return flat[inside], bary[inside]


def _raster_triangles(corners: np.ndarray, res: int, eps: float = 1e-9):
    """``_raster_triangle`` of many triangles (K, 3, 2) in texel units at once, with the same
    arithmetic (so the same bits): (flat texel indices, position k of the covering triangle,
    barycentric coordinates (n, 3)) of every covered texel centre. Triangles are batched by the
    size of their texel box, so each batch is one stacked solve."""
    empty = (np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 3)))
    if corners.shape[0] == 0:
        return empty
    lo = np.maximum(np.floor(corners.min(axis=1) - 0.5).astype(int), 0)
    hi = np.minimum(np.ceil(corners.max(axis=1) + 0.5).astype(int), res - 1)
    a = corners[:, 0]
    m = np.stack([corners[:, 1] - a, corners[:, 2] - a], axis=2)  # columns b - a, c - a
    ok = np.all(hi >= lo, axis=1)
    ok[ok] = np.abs(np.linalg.det(m[ok])) >= 1e-14
    size = hi - lo + 1
    flats, whichs, barys = [], [], []
    keys, group = np.unique(size[ok], axis=0, return_inverse=True)
    for g, (w, h) in enumerate(keys):
        sel = np.flatnonzero(ok)[group.ravel() == g]
        gx, gy = np.meshgrid(np.arange(w), np.arange(h))
        xs, ys = lo[sel, 0:1] + gx.ravel()[None], lo[sel, 1:2] + gy.ravel()[None]  # (K, n)
        p = np.stack([xs + 0.5, ys + 0.5], axis=2)
        l12 = np.linalg.solve(m[sel], (p - a[sel, None, :]).transpose(0, 2, 1)).transpose(0, 2, 1)
        bary = np.concatenate([1.0 - l12.sum(axis=2, keepdims=True), l12], axis=2)
        inside = np.all(bary >= -eps, axis=2)
        flats.append((ys * res + xs)[inside])
        whichs.append(np.broadcast_to(sel[:, None], inside.shape)[inside])
        barys.append(bary[inside])
    if not flats:
        return empty
    return np.concatenate(flats).astype(np.int64), np.concatenate(whichs).astype(np.int64), np.concatenate(barys)


#: Version of ``build_atlas``'s layout: caches of data baked on an atlas (their spec names it)
#: are rebuilt when it changes. 2: conservative rasterisation (charts thinner than a texel);
#: 3: raised objects bounded (RAISED_SPAN), growth to the asked density (DENSITY_SLACK);
#: 4: layouts far wider than their area shrunk (LAYOUT_SLACK), texels that do not see the
#: scene's views not shown (``build_atlas``'s ``seen_from``); 5: a two-sided surface's texels
#: face the side that sees the views where only one side does (``_orient``'s ``seen_from``).
ATLAS_FORMAT = 5

#: At most this many planar charts per object (a box has 6); an object with more face planes is unwrapped by xatlas.
MAX_PLANAR_CHARTS = 16


def _closest_on_triangles(corners: np.ndarray, res: int, reach: float):
    """For triangles (K, 3, 2) given in texel units: the texels (flat indices) whose centres lie
    within ``reach`` (texel units) of a triangle, the position k of that triangle, the distance,
    and the barycentric coordinates (n, 3) of the triangle's point nearest each centre, moved a
    little inwards (below): the conservative rasterisation's candidates. Batched like
    ``_raster_triangles`` (one triangle at a time gives the same bits)."""
    empty = (np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0), np.zeros((0, 3)))
    if corners.shape[0] == 0:
        return empty
    lo = np.maximum(np.floor(corners.min(axis=1) - reach).astype(int), 0)
    hi = np.minimum(np.ceil(corners.max(axis=1) + reach).astype(int), res - 1)
    a = corners[:, 0]
    m = np.stack([corners[:, 1] - a, corners[:, 2] - a], axis=2)  # columns b - a, c - a
    ok = np.all(hi >= lo, axis=1)
    ok[ok] = np.abs(np.linalg.det(m[ok])) >= 1e-14
    size = hi - lo + 1
    out = []
    keys, group = np.unique(size[ok], axis=0, return_inverse=True)
    for g, (w, h) in enumerate(keys):
        sel = np.flatnonzero(ok)[group.ravel() == g]
        c = corners[sel]
        gx, gy = np.meshgrid(np.arange(w), np.arange(h))
        xs, ys = lo[sel, 0:1] + gx.ravel()[None], lo[sel, 1:2] + gy.ravel()[None]  # (K, n)
        p = np.stack([xs + 0.5, ys + 0.5], axis=2)
        l12 = np.linalg.solve(m[sel], (p - a[sel, None, :]).transpose(0, 2, 1)).transpose(0, 2, 1)
        bary = np.concatenate([1.0 - l12.sum(axis=2, keepdims=True), l12], axis=2)
        best_d = np.where(np.all(bary >= 0.0, axis=2), 0.0, np.inf)
        best = bary.copy()
        for i, j in ((0, 1), (1, 2), (2, 0)):  # the nearest point of each edge
            e = c[:, j] - c[:, i]
            ee = np.maximum((e[:, None, :] @ e[:, :, None])[:, 0, 0], 1e-300)
            t = np.clip((p - c[:, None, i]) @ e[:, :, None] / ee[:, None, None], 0.0, 1.0)  # (K, n, 1)
            d = np.linalg.norm(c[:, None, i] + t * e[:, None, :] - p, axis=2)
            closer = d < best_d
            wgt = np.zeros(bary.shape)
            wgt[..., i], wgt[..., j] = 1.0 - t[..., 0], t[..., 0]
            best_d, best = np.where(closer, d, best_d), np.where(closer[..., None], wgt, best)
        near = best_d <= reach
        best, best_d = best[near], best_d[near]
        # a point on an edge is where the triangle meets its neighbours (a crease, a wall's foot):
        # move it towards the centroid by half the way or a quarter texel, whichever is less, so it
        # lies inside its own surface, not on a seam that an offset ray could slip through
        owner = np.broadcast_to(np.arange(len(sel))[:, None], near.shape)[near]
        to_centre = np.linalg.norm(((best - 1.0 / 3.0)[:, None, :] @ c[owner])[:, 0, :], axis=1)
        step = np.where(best_d > 0, np.minimum(0.5, 0.25 / np.maximum(to_centre, 1e-12)), 0.0)[:, None]
        out.append(((ys * res + xs)[near], sel[owner], best_d, (1.0 - step) * best + step / 3.0))
    if not out:
        return empty
    return tuple(np.concatenate(x) for x in zip(*out))


def _uv_area(uv: np.ndarray) -> np.ndarray:
    e1, e2 = uv[:, 1] - uv[:, 0], uv[:, 2] - uv[:, 0]
    return 0.5 * np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])


def _unwrap(tris: np.ndarray, texel: float) -> np.ndarray:
    """xatlas charts of one object's triangles (F, 3, 3), packed without overlap with
    ``_GUTTER``-texel padding at about ``texel`` world units per texel: corner coordinates
    (F, 3, 2) in world units. Corners are welded by position first (xatlas cuts charts along the
    mesh's connectivity; unshared corners would make every triangle a chart)."""
    import xatlas

    corners = tris.reshape(-1, 3)
    scale = max(float(np.ptp(corners, axis=0).max()), 1e-30)
    key = np.round(corners / (scale * 1e-6)).astype(np.int64)
    _, first, faces = np.unique(key, axis=0, return_index=True, return_inverse=True)
    atlas = xatlas.Atlas()
    atlas.add_mesh(corners[first].astype(np.float32), faces.reshape(-1, 3).astype(np.uint32))
    pack = xatlas.PackOptions()
    pack.padding = _GUTTER
    pack.texels_per_unit = float(1.0 / texel)
    atlas.generate(pack_options=pack)
    _, indices, uvs = atlas[0] if hasattr(atlas, "__getitem__") else atlas.get_mesh(0)
    uv = np.asarray(uvs, np.float64)[np.asarray(indices, np.int64).reshape(-1, 3)]
    return uv * np.array([atlas.width, atlas.height], np.float64) * texel


def _charts(tris: np.ndarray, uv: np.ndarray | None, overlap_tol: float,
            texel: float) -> tuple[list[tuple[np.ndarray, np.ndarray]], str]:
    """Split one object's (non-degenerate) triangles into charts: ([(triangle indices, corner
    coords in world units)], how: "uv" | "planar" | "xatlas"); ``texel`` is the expected world
    size of a texel (xatlas pads its charts by ``_GUTTER`` of them)."""
    area3 = _areas(tris)
    if uv is not None:
        uv_area = _uv_area(uv)
        if uv_area.sum() > 0 and _uv_overlaps(uv) <= overlap_tol:
            scale = np.sqrt(area3.sum() / uv_area.sum())
            return [(np.arange(tris.shape[0]), uv * scale)], "uv"
    # planar charts: group triangles by (normal, plane offset)
    n = _geometric_normals(tris)
    offset = np.einsum("fi,fi->f", n, tris[:, 0])
    key = np.round(np.column_stack([n * 1e3, offset[:, None] * 1e3])).astype(np.int64)
    _, group = np.unique(key, axis=0, return_inverse=True)
    group = group.ravel()
    if group.max() + 1 > MAX_PLANAR_CHARTS:
        return [(np.arange(tris.shape[0]), _unwrap(tris, texel))], "xatlas"
    charts = []
    for g in range(group.max() + 1):
        idx = np.nonzero(group == g)[0]
        normal = n[idx[0]]
        a = np.cross(normal, [0.0, 1.0, 0.0] if abs(normal[1]) < 0.9 else [1.0, 0.0, 0.0])
        a /= np.linalg.norm(a)
        b = np.cross(normal, a)
        charts.append((idx, np.stack([tris[idx] @ a, tris[idx] @ b], axis=-1)))
    return charts, "planar"


def _pack(sizes: np.ndarray, res: int, texel: float) -> np.ndarray | None:
    """Shelf packing of chart rectangles (world units) at ``texel`` world units per texel;
    returns the lower-left texel of each chart, or None if they do not fit in res x res."""
    ext = np.ceil(sizes / texel).astype(int) + 2 * _GUTTER
    order = np.argsort(-ext[:, 1], kind="stable")
    origin = np.zeros((len(sizes), 2), int)
    x = y = shelf = 0
    for i in order:
        w, h = ext[i]
        if x + w > res:
            x, y, shelf = 0, y + shelf, 0
        if w > res or y + h > res:
            return None
        origin[i] = (x + _GUTTER, y + _GUTTER)
        x += w
        shelf = max(shelf, h)
    return origin


def _affine_maps(tris: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """(F, 2, 4) matrices A with A [p, 1] = the barycentric interpolation of ``uv`` at the
    projection of p onto each triangle's plane; a zero-area triangle maps every point to its
    first corner's UV."""
    e1, e2 = tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0]
    n = np.cross(e1, e2)
    flat = np.linalg.norm(n, axis=1) <= 1e-12 * max(float(np.linalg.norm(n, axis=1).max(initial=0.0)), 1e-300)
    if flat.any():
        out = np.zeros((tris.shape[0], 2, 4))
        out[flat, :, 3] = uv[flat, 0]
        if (~flat).any():
            out[~flat] = _affine_maps(tris[~flat], uv[~flat])
        return out
    # world->barycentric: solve [e1 e2 n] (l1, l2, h) = p - v0
    basis = np.stack([e1, e2, n], axis=2)  # (F, 3, 3) columns
    inv = np.linalg.inv(basis)[:, :2, :]  # rows giving l1, l2
    du = np.stack([uv[:, 1] - uv[:, 0], uv[:, 2] - uv[:, 0]], axis=2)  # (F, 2, 2): uv = uv0 + du (l1, l2)
    lin = du @ inv  # (F, 2, 3)
    const = uv[:, 0] - np.einsum("fij,fj->fi", lin, tris[:, 0])
    return np.concatenate([lin, const[:, :, None]], axis=2)


def _fit_texel(sizes: np.ndarray, res: int, start: float, n_charts: int) -> float:
    """The smallest common texel size (bisection) at which chart rectangles ``sizes`` pack."""
    low = high = start
    while _pack(sizes, res, high) is None:
        high *= 1.5
        if high > 1e6 * low:
            raise ValueError(f"{n_charts} lightmap charts (with {_GUTTER}-texel gutters) do not fit a "
                             f"{res} x {res} atlas; raise the resolution")
    for _ in range(30):
        mid = 0.5 * (low + high)
        low, high = (low, mid) if _pack(sizes, res, mid) is not None else (mid, high)
    return high


#: An atlas whose charts do not fit its resolution doubles up to this factor (then it raises).
ATLAS_GROWTH = 8
#: An object whose area gives it too few texels has its texel density raised, but its layout grows
#: to span at most this many times the side of a square of its texels (2 min_texels of them).
RAISED_SPAN = 2.0


#: An object's layout (the bounding boxes of its charts) covers at most this many times its surface
#: area; a layout that covers more (xatlas charts far smaller than a texel, each padded by gutters:
#: curtains, foliage) is scaled down to it, so that it does not coarsen every other object's texels.
LAYOUT_SLACK = 4.0


#: The asked resolution promises a texel density: an atlas whose packing (gutters of many small
#: charts) leaves texels more than this factor larger than a gutter-free packing of the same area
#: would have at the asked resolution doubles (up to ``ATLAS_GROWTH``).
DENSITY_SLACK = 4.0


def _fit_texel_growing(sizes: np.ndarray, res: int, start: float, n_charts: int, asked: int,
                       ideal: float | None = None) -> tuple[float, int]:
    """(texel size, resolution): ``_fit_texel`` at ``res``, doubling the resolution while the
    charts' gutters alone overfill it, or while the texel size exceeds ``DENSITY_SLACK`` x
    ``ideal`` (the texel of a gutter-free packing at the asked resolution), up to
    ``ATLAS_GROWTH`` x the ``asked`` one."""
    while True:
        try:
            texel = _fit_texel(sizes, res, start, n_charts)
        except ValueError:
            if 2 * res > ATLAS_GROWTH * int(asked):
                raise
            res *= 2
            continue
        if ideal is None or texel <= DENSITY_SLACK * ideal or 2 * res > ATLAS_GROWTH * int(asked):
            return texel, res
        res *= 2


def build_atlas(handle: SceneHandle, objects: Sequence[str | int] | None = None, *, resolution: int = 64,
                overlap_tol: float = 0.01, eps: float | None = None, min_texels: int = 4,
                seen_from="scene") -> Atlas:
    """Lay out a lightmap atlas of ``objects`` (names or ids; None = all) at ``resolution``^2.

    Charts (module docstring: the mesh's own UVs, planar charts, or xatlas) are packed at the
    smallest common texel size (found by bisection) that fits the atlas; an object with fewer
    than ``min_texels`` texels at that size is scaled up (its texel density raised) and the
    packing redone. Texel centres covered by a triangle become lightmap texels (their position
    and geometric normal interpolated from the triangle), and so do texels a chart only overlaps
    (conservative rasterisation: just inside the nearest triangle, by its point nearest the
    centre, so a chart thinner than a texel still has texels of its own), and uncovered atlas
    pixels point at their nearest covered texel (``fill_index``) so a bilinear lookup never reads
    an empty texel.
    Zero-area triangles are left out of the charts, with a warning that counts them, and so are
    objects without area. An object raised to ``min_texels`` grows to a few texels at most
    (``RAISED_SPAN``). Where the charts' gutters overfill ``resolution`` or leave its texels more
    than ``DENSITY_SLACK`` x coarser than a gutter-free packing would (a file of many small
    meshes), the atlas doubles its resolution (up to ``ATLAS_GROWTH`` x, with a warning naming the
    size; ``Atlas.resolution`` is the one used).

    ``seen_from``: (K, 3) points the scene is looked at from, "scene" (``jprt.render.sampling.
    view_region_points``: its view region) or None. A texel that none of them sees (a wall's part
    behind a cornice or above the ceiling, the floor under a sofa, a face buried in another object)
    is still baked, but no atlas pixel shows it: ``fill_index`` points its pixels at the nearest
    texel of the same object that is seen, so a bilinear lookup beside it never blends in light
    from the other side of a surface (on ``living-room``, a sky-lit band above the cornice bled
    into the top of the walls: CHANGELOG.md, 2026-12-05). The same points orient two-sided
    surfaces (``_orient``): a texel faces the side that sees them where only one side does.
    """
    import warnings

    from scipy import ndimage

    if int(resolution) < 8:
        raise ValueError(f"atlas resolution must be >= 8, got {resolution}")
    res = int(resolution)
    ids = _object_index(handle, objects)
    names = handle.object_names()
    meshes = [mesh_triangles(handle, obj) for obj in ids]
    flat = [names[o] for o, (tris, _) in zip(ids, meshes) if not (_areas(tris) > 0).any()]
    if flat:  # no ray hits them, so no pixel reads them: they get no texels
        warnings.warn(f"lightmap atlas: {len(flat)} objects without area left out ({', '.join(flat)})", stacklevel=2)
        ids, meshes = zip(*[(o, m) for o, m in zip(ids, meshes) if names[o] not in flat]) if len(flat) < len(ids) \
            else ((), ())
        ids, meshes = list(ids), list(meshes)
    if not ids:
        raise ValueError("the atlas's objects have no area")
    per_object = [tris for tris, _ in meshes]
    total = sum(_areas(t).sum() for t in per_object)
    if not total > 0:
        raise ValueError("the atlas's objects have no area")
    guess = np.sqrt(total) / res * 1.3  # the texel size a well-packed atlas reaches
    charts, dropped = [], {}
    for oi, (tris, uv) in enumerate(meshes):
        area = _areas(tris)
        keep = np.flatnonzero(area > 1e-12 * max(float(area.max(initial=0.0)), 1e-300))
        if len(keep) < len(tris):
            dropped[names[ids[oi]]] = int(len(tris) - len(keep))
        if len(keep) == 0:
            raise ValueError(f"object {names[ids[oi]]!r} has no triangle of non-zero area")
        found, _ = _charts(tris[keep], None if uv is None else uv[keep], overlap_tol, guess)
        charts += [(oi, keep[idx], coords) for idx, coords in found]
    if dropped:
        warnings.warn(f"lightmap atlas: {sum(dropped.values())} zero-area triangles left out "
                      f"({', '.join(f'{k}: {v}' for k, v in sorted(dropped.items()))})", stacklevel=2)
    object_area = np.array([_areas(t).sum() for t in per_object])
    chart_object = np.array([c[0] for c in charts])
    extent = np.array([np.ptp(c[2].reshape(-1, 2), axis=0) for c in charts])  # (charts, 2) unscaled
    object_extent = np.array([extent[chart_object == oi].max() for oi in range(len(ids))])
    object_box = np.bincount(chart_object, weights=extent.prod(axis=1), minlength=len(ids))
    # a layout wider than LAYOUT_SLACK x its area shrinks to that (its charts then share texels:
    # the object's light is blurred over its own surface, at the texel density of the others)
    scale = np.minimum(1.0, np.sqrt(LAYOUT_SLACK * object_area / np.maximum(object_box, 1e-300)))
    texel0 = None
    for _ in range(4):  # raise the density of objects below min_texels until every one has them
        coords = [c[2] * scale[c[0]] for c in charts]
        lo = np.array([c.reshape(-1, 2).min(0) for c in coords])
        sizes = np.array([c.reshape(-1, 2).max(0) for c in coords]) - lo
        texel, res = _fit_texel_growing(sizes, res, guess * 0.4, len(charts), int(resolution),
                                        ideal=np.sqrt(total) / int(resolution))
        # texels the object gets: its area's, or what a shrunk layout covers (LAYOUT_SLACK x less
        # than its box: about its area's at the first packing; conservative rasterisation)
        texels = np.maximum(object_area, object_box / LAYOUT_SLACK) * scale ** 2 / texel ** 2
        short = texels < 2.0 * int(min_texels)  # rasterised texel centres fall short of the area's count
        # a raised object's layout spans at most RAISED_SPAN x the side of a square of 2 min_texels
        # texels of the first packing (a bound that followed the texel size would feed back): an
        # object of almost no area over a wide layout (many tiny charts with gutters, slivers) would
        # otherwise grow without bound, take the atlas over and leave every other object short;
        # spread that wide, its charts get texels of their own as they are (conservative rasterisation)
        texel0 = texel if texel0 is None else texel0
        span = RAISED_SPAN * np.sqrt(2.0 * int(min_texels))
        cap = np.maximum(span * texel0 / np.maximum(object_extent, 1e-300), scale)
        raised = np.minimum(scale * np.sqrt(2.0 * int(min_texels) / np.maximum(texels, 1e-12)), cap)
        short &= raised > scale * (1.0 + 1e-9)
        if not short.any():
            break
        scale[short] = raised[short]
    origin = _pack(sizes, res, texel)
    if res != int(resolution):
        warnings.warn(f"lightmap atlas: {len(charts)} charts (with {_GUTTER}-texel gutters) do not fit a "
                      f"{resolution} x {resolution} atlas at the texel density it asks; the atlas is "
                      f"{res} x {res}", stacklevel=2)

    n_tri = [t.shape[0] for t in per_object]
    tri_offset = np.concatenate([[0], np.cumsum(n_tri)[:-1]]).astype(np.int32)
    atlas_uv = np.full((sum(n_tri), 3, 2), -1.0)
    for ci, (oi, idx, _) in enumerate(charts):
        atlas_uv[tri_offset[oi] + idx] = ((coords[ci] - lo[ci]) / texel + origin[ci]) / res
    for oi in range(len(ids)):  # dropped triangles: a point of their object's first chart (never rasterised)
        block = atlas_uv[tri_offset[oi]:tri_offset[oi] + n_tri[oi]]
        missing = block[:, 0, 0] < 0
        block[missing] = block[~missing][0, 0]
    all_tris = np.concatenate(per_object)
    tri_object = np.concatenate([np.full(n, ids[oi], np.int32) for oi, n in enumerate(n_tri)])
    affine = _affine_maps(all_tris, atlas_uv)

    owner = np.full(res * res, -1, np.int64)
    bary_of = np.zeros((res * res, 3))
    live = np.flatnonzero(_areas(all_tris) > 0)
    # a texel centre covered by several triangles belongs to the first of them
    flat, which, bary = _raster_triangles(atlas_uv[live] * res, res)
    order = np.lexsort((which, flat))
    first = order[np.unique(flat[order], return_index=True)[1]]
    owner[flat[first]], bary_of[flat[first]] = live[which[first]], bary[first]
    # conservative rasterisation: a texel that no triangle covers at its centre but that some
    # triangle's chart overlaps (its centre within half a texel diagonal) belongs to the nearest
    # such triangle, at about the triangle's point nearest the centre. A chart thinner than a
    # texel (a table's edge) otherwise has no texel at all, and its pixels read the nearest
    # covered texel of the atlas, which can be another chart many texels away.
    centred = owner >= 0
    flat, which, dist, bary = _closest_on_triangles(atlas_uv[live] * res, res, 0.5 * np.sqrt(2.0))
    free = ~centred[flat]
    flat, which, dist, bary = flat[free], which[free], dist[free], bary[free]
    order = np.lexsort((which, dist, flat))  # per texel the nearest triangle, the first of equals
    first = order[np.unique(flat[order], return_index=True)[1]]
    owner[flat[first]], bary_of[flat[first]] = live[which[first]], bary[first]
    texel_index = np.nonzero(owner >= 0)[0].astype(np.int32)
    if texel_index.size == 0:
        raise ValueError("the atlas covers no texel centre; raise the resolution")
    t_of = owner[texel_index]
    position = np.einsum("ti,tij->tj", bary_of[texel_index], all_tris[t_of])
    points = None
    if seen_from is not None:
        from jprt.render.sampling import view_region_points

        points = view_region_points(handle) if isinstance(seen_from, str) else \
            np.asarray(seen_from, np.float64).reshape(-1, 3)
    normal = _orient(handle, tri_object[t_of], position, _geometric_normals(all_tris)[t_of], seen_from=points)
    _, nearest = ndimage.distance_transform_edt((owner < 0).reshape(res, res), return_indices=True)
    flat_nearest = (nearest[0] * res + nearest[1]).ravel()
    lookup = np.full(res * res, -1, np.int64)
    lookup[texel_index] = np.arange(texel_index.size)
    fill_index = lookup[flat_nearest].astype(np.int32)
    if points is not None:
        sees = sees_points(handle, position, normal, points)
        if (~sees).any():
            fill_index = _show_seeing(fill_index, texel_index, tri_object[t_of], sees, res)
    return Atlas(resolution=res, objects=np.asarray(ids, np.int32), tri_offset=tri_offset, tri_affine=affine,
                 texel_index=texel_index, position=position.astype(np.float32), normal=normal.astype(np.float32),
                 texel_object=tri_object[t_of], fill_index=fill_index, texel_size=float(texel))


def _show_seeing(fill_index: np.ndarray, texel_index: np.ndarray, texel_object: np.ndarray, sees: np.ndarray,
                 res: int) -> np.ndarray:
    """``fill_index`` with every atlas pixel that shows a texel not seen (``sees`` False) pointed at
    the nearest texel of the same object that is (within the object's atlas box; an object none of
    whose texels is seen keeps its own)."""
    from scipy import ndimage

    fill = fill_index.astype(np.int64).copy()
    row, col = texel_index // res, texel_index % res
    pixel_object = texel_object[fill]
    for obj in np.unique(texel_object[~sees]):
        mine = texel_object == obj
        if not (mine & sees).any():
            continue
        shows = np.flatnonzero((pixel_object == obj) & ~sees[fill])
        r0, r1 = min(row[mine].min(), (shows // res).min()), max(row[mine].max(), (shows // res).max()) + 1
        c0, c1 = min(col[mine].min(), (shows % res).min()), max(col[mine].max(), (shows % res).max()) + 1
        box = np.ones((r1 - r0, c1 - c0), bool)  # True: not a seeing texel of this object
        good = np.flatnonzero(mine & sees)
        box[row[good] - r0, col[good] - c0] = False
        grid = np.full((r1 - r0, c1 - c0), -1, np.int64)
        grid[row[good] - r0, col[good] - c0] = good
        _, (nr, nc) = ndimage.distance_transform_edt(box, return_indices=True)
        fill[shows] = grid[nr[shows // res - r0, shows % res - c0], nc[shows // res - r0, shows % res - c0]]
    return fill.astype(np.int32)


def sees_points(handle: SceneHandle, position, normal, points, *, chunk: int = 1 << 20) -> np.ndarray:
    """(T,) bool: from each surface point (``position``, ``normal`` (T, 3)), at least one of
    ``points`` (K, 3) on its normal's side is visible (an unblocked segment from just off the
    surface). A lightmap texel holds the radiance leaving its normal's side: a view of its other
    side (a two-sided curtain seen from behind) is not served by it."""
    position = np.asarray(position, np.float64).reshape(-1, 3)
    normal = np.asarray(normal, np.float64).reshape(-1, 3)
    points = np.asarray(points, np.float64).reshape(-1, 3)
    eps = ray_offset(handle)
    out = np.zeros(len(position), bool)
    per = max(1, chunk // max(len(points), 1))
    for a in range(0, len(position), per):
        p, n = np.repeat(position[a:a + per], len(points), axis=0), np.repeat(normal[a:a + per], len(points), axis=0)
        q = np.tile(points, (min(per, len(position) - a), 1))
        o = p + eps * n
        d = q - o
        dist = np.linalg.norm(d, axis=1)
        d /= np.maximum(dist, 1e-300)[:, None]
        front = np.sum(d * n, axis=1) > 0.0
        si = intersect(handle, o, d)
        t = np.where(np.array(si.is_valid(), bool).reshape(-1), np.array(si.t, np.float64).reshape(-1), np.inf)
        out[a:a + per] = (front & (t >= dist - eps)).reshape(-1, len(points)).any(axis=1)
    return out


# --------------------------------------------------------------------------------------------
# Per-pixel atlas coordinates


def intersect(handle: SceneHandle, origins, directions):
    """Mitsuba's first intersections (``SurfaceInteraction3f``) of rays (N, 3) x (N, 3), in float32."""
    mi = handle.mi
    o, d = np.asarray(origins, np.float32), np.asarray(directions, np.float32)
    ray = mi.Ray3f(mi.Point3f(o[:, 0], o[:, 1], o[:, 2]), mi.Vector3f(d[:, 0], d[:, 1], d[:, 2]))
    return handle.scene.ray_intersect(ray)


def unoccluded(handle: SceneHandle, origins, lights, *, rel: float = 0.0, slack: float = 0.0) -> np.ndarray:
    """(L, N) bool: the segment from each of ``origins`` (N, 3) to each of ``lights`` (L, 3) meets
    no surface before the light (a first hit at t >= dist x (1 - ``rel``) - ``slack`` counts as
    the light's). The rays go to Mitsuba in batches of about a million: one call per light costs
    a kernel launch each, on a many-mesh scene 50x the batch's time."""
    origins = np.asarray(origins, np.float64).reshape(-1, 3)
    lights = np.asarray(lights, np.float64).reshape(-1, 3)
    out = np.zeros((len(lights), len(origins)), bool)
    if not len(origins) or not len(lights):
        return out
    step = max(1, (1 << 20) // len(origins))  # lights per batch
    for a in range(0, len(lights), step):
        to_light = lights[a:a + step, None] - origins[None]  # (L, N, 3)
        dist = np.linalg.norm(to_light, axis=2)
        d = to_light / np.maximum(dist, 1e-12)[..., None]
        si = intersect(handle, np.broadcast_to(origins, d.shape).reshape(-1, 3), d.reshape(-1, 3))
        t = np.where(np.array(si.is_valid(), bool).reshape(-1), np.array(si.t, np.float64).reshape(-1), np.inf)
        out[a:a + step] = t.reshape(dist.shape) >= dist * (1.0 - rel) - slack
    return out


def _primitive_hits(handle: SceneHandle, origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
    si = intersect(handle, origins, directions)
    prim = np.array(si.prim_index, np.int64).reshape(-1)
    return np.where(np.array(si.is_valid(), bool).reshape(-1), prim, -1)


def atlas_gbuffer(handle: SceneHandle, atlas: Atlas, camera: Camera) -> GBuffer:
    """The exact pixel-centre G-buffer of ``camera`` with ``uv`` replaced by atlas UVs and
    ``valid`` restricted to pixels that see an atlas object (the "fake G-buffer" lookup of
    Belcour et al. 2022, §4.3)."""
    gb = gbuffer(handle, camera)
    o, d = camera_rays(camera)
    prim = _primitive_hits(handle, o.reshape(-1, 3), d.reshape(-1, 3)).reshape(gb.object_id.shape)
    slot = np.full(max(int(gb.object_id.max()) + 1, int(atlas.objects.max()) + 1), -1)
    slot[atlas.objects] = np.arange(atlas.objects.size)
    obj = np.where(gb.object_id >= 0, gb.object_id, 0)
    in_atlas = gb.valid & (slot[obj] >= 0) & (prim >= 0)
    # a rectangle is one primitive: its triangles share one affine map, so any of them works
    tri = np.where(in_atlas, atlas.tri_offset[np.maximum(slot[obj], 0)] + np.maximum(prim, 0), 0)
    tri = np.minimum(tri, atlas.tri_affine.shape[0] - 1)
    p1 = np.concatenate([gb.position, np.ones(gb.position.shape[:-1] + (1,), np.float32)], axis=-1)
    uv = np.einsum("hwij,hwj->hwi", atlas.tri_affine[tri], p1.astype(np.float64))
    uv = np.where(in_atlas[..., None], uv, 0.0).astype(np.float32)
    return gb._replace(uv=uv, valid=in_atlas, object_id=np.where(in_atlas, gb.object_id, -1).astype(np.int32))


# --------------------------------------------------------------------------------------------
# Surface samples and radiance at surface points


def surface_samples(handle: SceneHandle, n: int, *, objects: Sequence[str | int] | None = None,
                    seed: int = 0) -> SurfacePoints:
    """``n`` uniform random points (area-weighted) on ``objects``, with geometric normals and the
    diffuse albedo there (read from the BSDF through a ray that hits the point)."""
    if int(n) < 1:
        raise ValueError(f"need at least one surface sample, got {n}")
    rng = np.random.default_rng(seed)
    ids = _object_index(handle, objects)
    tris = [mesh_triangles(handle, o)[0] for o in ids]
    all_tris = np.concatenate(tris)
    owner = np.concatenate([np.full(t.shape[0], o, np.int32) for o, t in zip(ids, tris)])
    area = _areas(all_tris)
    pick = rng.choice(area.size, size=int(n), p=area / area.sum())
    r1, r2 = rng.random(int(n)), rng.random(int(n))
    s = np.sqrt(r1)
    bary = np.column_stack([1 - s, s * (1 - r2), s * r2])
    position = np.einsum("ni,nij->nj", bary, all_tris[pick])
    normal = _orient(handle, owner[pick], position, _geometric_normals(all_tris)[pick])
    return SurfacePoints(position.astype(np.float32), normal.astype(np.float32),
                         albedo_at_points(handle, position, normal)[0], owner[pick], float(area.sum()))


def albedo_at_points(handle: SceneHandle, position, normal) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The BSDF's diffuse and specular albedo (S, 3) float32 each at surface points (``position``,
    ``normal`` (S, 3)), read through a ray that hits each point along its normal (textures
    included), and the object that ray hit (S,) (-1: none; another object where surfaces meet);
    a lightmap's texels' with ``atlas.position`` and ``atlas.normal``."""
    position, normal = np.asarray(position, np.float64), np.asarray(normal, np.float64)
    gb = gbuffer_rays(handle, position + ray_offset(handle) * normal, -normal)
    return (np.asarray(gb.diffuse_albedo, np.float32), np.asarray(gb.specular_albedo, np.float32),
            np.asarray(gb.object_id, np.int32))


def enclosing_objects(handle: SceneHandle) -> list[int]:
    """Object ids of the shapes that enclose the scene: a bounding box spanning 90 % of the
    scene's on every axis (a room modelled as one closed mesh)."""
    box = handle.scene.bbox()
    extent = np.asarray(box.max, np.float64) - np.asarray(box.min, np.float64)
    out = []
    for k, shape in enumerate(handle.shapes()):
        b = shape.bbox()
        if np.all(np.asarray(b.max, np.float64) - np.asarray(b.min, np.float64) >= 0.9 * extent):
            out.append(k)
    return out


def _hemisphere_directions(n: int = 16) -> np.ndarray:
    """``n`` fixed cosine-distributed unit directions about +z (a Fibonacci spiral)."""
    k = np.arange(n) + 0.5
    r = np.sqrt(k / n)
    phi = k * np.pi * (3.0 - np.sqrt(5.0))
    return np.stack([r * np.cos(phi), r * np.sin(phi), np.sqrt(1.0 - r * r)], axis=1)


def _two_sided(handle: SceneHandle, rooms) -> np.ndarray:
    """(S,) bool: shapes with a ``twosided`` BSDF that do not enclose the scene (``rooms``)."""
    return np.array([k not in rooms and shape.bsdf() is not None and shape.bsdf().class_name() == "TwoSidedBRDF"
                     for k, shape in enumerate(handle.shapes())], bool)


def _orient(handle: SceneHandle, object_id, position, normal, n_dirs: int = 16, seen_from=None) -> np.ndarray:
    """``normal`` (N, 3) turned towards the side of the surface that the rest of the scene is on,
    where that is ambiguous: on a shape that encloses the scene (``enclosing_objects``: a room
    modelled as one closed mesh) towards the scene's centre; on other two-sided surfaces (a
    ``twosided`` BSDF) towards the side that sees the views where only one side sees any of
    ``seen_from`` ((K, 3) view points, ``sees_points``; None: no such test), so a landing seen
    from below and closed off above serves its underside; else away from the authored side
    where fewer than half of ``n_dirs`` cosine-distributed rays from it hit *another* object
    farther than 2 % of the scene's size (it escapes the scene, as outside a room's wall) and
    the other side's rays do so at least 25 points more often; otherwise the geometric normal
    stays (a picture on a wall, whose back sees only the wall, keeps its front; the inside of a
    closed box sees only itself). A texel's radiance is gathered, and a measurement point's
    direct light measured, on the side its normal points to, so a wall whose face points
    outwards would otherwise read the dark outside. One-sided surfaces keep their normal:
    Mitsuba shades only that side."""
    rooms = enclosing_objects(handle)
    object_id = np.asarray(object_id)
    box = handle.scene.bbox()
    out = np.array(normal, np.float64, copy=True)
    if rooms:
        centre = 0.5 * (np.asarray(box.min, np.float64) + np.asarray(box.max, np.float64))
        outwards = np.isin(object_id, rooms) & (np.sum(out * (centre - np.asarray(position)), axis=1) < 0)
        out[outwards] *= -1.0
    sel = np.flatnonzero(np.isin(object_id, np.flatnonzero(_two_sided(handle, rooms))))
    if sel.size == 0:
        return out.astype(np.asarray(normal).dtype)
    size = float(np.max(np.asarray(box.max, np.float64) - np.asarray(box.min, np.float64)))
    local = _hemisphere_directions(n_dirs)
    p, nrm = np.asarray(position, np.float64)[sel], np.asarray(normal, np.float64)[sel]
    score = []
    for side in (1.0, -1.0):
        z = side * nrm
        helper = np.where(np.abs(z[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
        x = np.cross(helper, z)
        x /= np.linalg.norm(x, axis=1, keepdims=True)
        y = np.cross(z, x)
        d = local[None, :, 0:1] * x[:, None] + local[None, :, 1:2] * y[:, None] + local[None, :, 2:3] * z[:, None]
        o = np.repeat(p + ray_offset(handle) * z, n_dirs, axis=0)
        si = intersect(handle, o, d.reshape(-1, 3))
        t = np.where(np.array(si.is_valid(), bool).reshape(-1), np.array(si.t, np.float64).reshape(-1), np.inf)
        hit = hit_objects(handle, si)
        other = (hit >= 0) & (hit != np.repeat(object_id[sel], n_dirs))
        score.append(((t > 0.02 * size) & np.isfinite(t) & other).reshape(-1, n_dirs).mean(axis=1))
    # flip only where the authored side mostly sees nothing and the other side clearly more (a
    # picture on a wall sees the room through an opening on its front, the wall behind it on its
    # back: the front keeps)
    flip = (score[0] < 0.5) & (score[1] > score[0] + 0.25)
    if seen_from is not None and len(seen_from):
        # where exactly one side sees the views, that side serves them, whatever the rays above say
        front, back = sees_points(handle, p, nrm, seen_from), sees_points(handle, p, -nrm, seen_from)
        flip = np.where(front != back, back, flip)
    out[sel[flip]] *= -1.0
    return out.astype(np.asarray(normal).dtype)


def ray_offset(handle: SceneHandle) -> float:
    """How far along the normal a secondary ray starts off a surface point, so it does not hit
    the surface it leaves: 1e-4 of the diagonal of the scene's bounding box."""
    box = handle.scene.bbox()
    return 1e-4 * float(np.linalg.norm(np.array(box.max) - np.array(box.min)))


def radiance_at_points(handle: SceneHandle, position, normal, *, spp: int, seed: int = 0,
                       max_depth: int = 2) -> np.ndarray:
    """Outgoing radiance (S, 3) along the normal at surface points, path traced with
    ``max_depth`` (2 = direct lighting only, -1 = full global illumination).

    With one point, spot or directional light the direct part is deterministic (one shadow ray),
    so ``spp=1`` gives it exactly (the "deferred shading of measurement points" of §4.3). With
    several, Mitsuba's integrator picks one emitter per sample: use ``direct_at_points``.
    """
    position = np.asarray(position, np.float64)
    normal = np.asarray(normal, np.float64)
    eps = ray_offset(handle)
    return images.radiance_rays(handle, position + eps * normal, -normal, spp=spp, seed=seed, max_depth=max_depth)


def direct_at_points(handle: SceneHandle, lighting, position, normal) -> np.ndarray:
    """Direct radiance (S, 3) along the normal at surface points under ``lighting`` (point, spot or
    directional lights; set on ``handle`` when it returns), exact: each light alone at one sample
    (one shadow ray), summed. Rendered together, Mitsuba's integrator samples one of the K emitters
    per sample and weights it by K, a one-sample estimate (two lights at 1 spp: 70 % of the largest
    value off at some points of data-driven PRT's test scene, against 2e-7 for this sum). The
    scene's own emitters, if it keeps any, would be counted once per light: the callers' scenes
    have none. Several lights cost two scene rebuilds (K lights to one and back).
    """
    count = int(getattr(lighting, "count", 1) or 1)
    if count <= 1:
        handle.set_lighting(lighting)
        return radiance_at_points(handle, position, normal, spp=1, max_depth=2)
    total = 0.0
    for k in range(count):
        handle.set_lighting(type(lighting)(*(np.asarray(f)[k:k + 1] for f in lighting)))
        total = total + radiance_at_points(handle, position, normal, spp=1, max_depth=2)
    handle.set_lighting(lighting)
    return np.asarray(total, np.float32)


def indirect_at_points(handle: SceneHandle, position, normal, *, spp: int, seed: int = 0) -> np.ndarray:
    """Indirect outgoing radiance (S, 3) at surface points: full minus direct with equal seeds."""
    position = np.asarray(position, np.float64)
    normal = np.asarray(normal, np.float64)
    eps = ray_offset(handle)
    return images.indirect_rays(handle, position + eps * normal, -normal, spp=spp, seed=seed).indirect


def points_pathtracer(handle: SceneHandle, position, normal, lightings: Sequence, to_images, *, seed: int,
                      time_seed: int, warmup: bool = False, repeats: int = 1, note: str = ""):
    """Mitsuba as the equal-error peer of a lightmap method (a ``jprt.eval.PathTracer``): its
    ``render_at(spp)`` is the indirect light (``indirect_at_points``) at the points under each of
    ``lightings`` in turn (seed ``seed + k`` for the k-th), the list of (S, 3) arrays passed to
    ``to_images`` (-> the held-out images); its ``time_at(spp)`` renders the first lighting at
    ``time_seed``: one untimed call first when ``warmup`` (the kernel's compilation), then the
    median of ``repeats`` timed calls (ms)."""
    from jprt import eval as jeval

    def render_at(spp):
        texels = []
        for k, lighting in enumerate(lightings):
            handle.set_lighting(lighting)
            texels.append(indirect_at_points(handle, position, normal, spp=int(spp), seed=int(seed) + k))
        return to_images(texels)

    def time_at(spp):
        handle.set_lighting(lightings[0])
        if warmup:
            indirect_at_points(handle, position, normal, spp=int(spp), seed=int(time_seed))
        return jeval.time_call(lambda: indirect_at_points(handle, position, normal, spp=int(spp), seed=int(time_seed)),
                               repeats=int(repeats), warmup=0)["median_ms"]

    return jeval.PathTracer(render_at, time_at, note)


def incident_delta_lights(handle: SceneHandle, point, lighting: Lighting) -> tuple[np.ndarray, np.ndarray]:
    """Unoccluded incident light of delta lights at ``point``: unit directions towards each light
    (K, 3) and the RGB irradiance each delivers to a surface facing it (K, 3) (intensity times
    spot falloff over squared distance; a directional light's irradiance).

    This is what a distant-lighting method (classic SH PRT) sees of local lights: each light
    becomes a delta in the environment of ``point``.
    """
    mi = handle.mi
    point = np.asarray(point, np.float64).reshape(3)
    if isinstance(lighting, DirectionalLights):
        return -lighting.direction.astype(np.float64), lighting.irradiance.astype(np.float64)
    if not isinstance(lighting, (PointLights, SpotLights)):
        raise TypeError(f"incident_delta_lights takes point, spot or directional lights, not {type(lighting).__name__}")
    handle.set_lighting(lighting)
    directions, values = [], []
    it = mi.Interaction3f()
    it.p = mi.Point3f(*map(float, point))
    for emitter in handle.scene.emitters():
        ds, spec = emitter.sample_direction(it, mi.Point2f(0.5, 0.5), True)
        directions.append(np.array(ds.d, np.float64).reshape(3))
        values.append(np.array(spec, np.float64).reshape(3))
    return np.array(directions), np.array(values)


def free_positions(handle: SceneHandle, points, *, clearance: float = 0.0, n_dirs: int = 26) -> np.ndarray:
    """(K,) bool: the points lie in free space (not inside a closed object: fewer than half of
    ``n_dirs`` rays in all directions hit a surface from its back side) and no surface is closer
    than ``clearance`` along those rays. Used to reject random light positions inside the
    Cornell box's blocks, or touching a wall. A shape that encloses the scene (its bounding box
    spans 90 % of the scene's on every axis: a room modelled as one closed mesh, whose faces may
    well point outwards; ``enclosing_objects``) is a room, not an object a point can be inside of.
    Two-sided surfaces (a ``twosided`` BSDF: walls whose faces point outwards are common in scene
    files) have no back side: a point is inside one when at least 90 % of the rays hit it."""
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    g = np.stack(np.meshgrid(*[np.array([-1.0, 0.0, 1.0])] * 3, indexing="ij"), -1).reshape(-1, 3)
    dirs = g[np.any(g != 0, axis=1)][:n_dirs]
    dirs = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
    o = np.repeat(pts, len(dirs), axis=0)
    d = np.tile(dirs, (len(pts), 1))
    si = intersect(handle, o, d)
    valid = np.array(si.is_valid(), bool).reshape(-1)
    n = np.array(si.n, np.float64)
    n = (n.T if n.shape[0] == 3 and n.ndim == 2 else n).reshape(-1, 3)
    t = np.where(valid, np.array(si.t, np.float64).reshape(-1), np.inf)
    back = valid & (np.sum(n * d, axis=1) > 0)
    rooms = enclosing_objects(handle)
    hit = hit_objects(handle, si)
    twosided = _two_sided(handle, rooms)
    one_sided = np.append(~twosided & ~np.isin(np.arange(len(twosided)), rooms), False)  # [-1]: no hit
    # one-sided surfaces: seen from their back side; two-sided ones have no back, so a point is
    # inside one when (nearly) every ray hits that same object
    inside = (back & one_sided[hit]).reshape(len(pts), -1).mean(axis=1) >= 0.5
    per = hit.reshape(len(pts), -1)
    for k in np.flatnonzero(twosided):
        inside |= (per == k).mean(axis=1) >= 0.9
    near = t.reshape(len(pts), -1).min(axis=1) < clearance
    return ~inside & ~near


# --------------------------------------------------------------------------------------------
# Per-vertex interpolation on a subdivided scene mesh (the per-vertex feature baseline of
# Raghavan et al. 2023, Table 6)


def _sphere_frame(handle: SceneHandle, object_id: int) -> tuple[np.ndarray, float] | None:
    shape = handle.shapes()[object_id]
    if shape.class_name() != "Sphere":
        return None
    m = np.array(handle.mi.traverse(shape)["to_world"].matrix, np.float64).reshape(4, 4)
    return m[:3, 3], float(np.linalg.norm(m[:3, 0]))


def vertex_interpolation(handle: SceneHandle, positions, *, edge: float = 0.1,
                         chunk: int = 65536) -> tuple[np.ndarray, np.ndarray, int]:
    """Vertex indices and interpolation weights of surface points on a subdivided scene mesh.

    Every triangle of every object (``mesh_triangles``) is split regularly into N^2 triangles
    (N = 2^l, the smallest with edges <= ``edge``); vertices are shared along the edges inside
    an object. A point gets the three corners of the sub-triangle it lies in with their
    barycentric weights. Analytic spheres (the built-in scenes'; a scene file's spheres are
    meshes already) become a latitude-longitude vertex grid of about ``edge`` spacing with
    bilinear weights over four vertices.

    Args:
      positions: (..., 3) points on the scene's surfaces (e.g. G-buffer positions); points off
        every surface get the nearest surface's vertices.
      chunk: points per batch, fewer where the scene has many triangles (each batch holds
        (points x triangles) arrays: at most about 4M entries).
    Returns (index (..., 4) int32, weight (..., 4) float32 summing to 1, vertex positions (V, 3)).
    """
    pos = np.asarray(positions, np.float64)
    shape = pos.shape[:-1]
    p = pos.reshape(-1, 3)
    n_obj = len(handle.shapes())
    keys: dict = {}
    vertices: list = []

    def vid(obj: int, world: np.ndarray) -> np.ndarray:
        out = np.empty(len(world), np.int64)
        for i, w in enumerate(np.round(world / (1e-4 * edge)).astype(np.int64)):
            key = (obj, *w.tolist())
            if key not in keys:
                keys[key] = len(vertices)
                vertices.append(world[i])
            out[i] = keys[key]
        return out

    tris, owner, sphere_objs = [], [], []
    for obj in range(n_obj):
        frame = _sphere_frame(handle, obj)
        if frame is not None:
            sphere_objs.append((obj, frame))
            continue
        t, _ = mesh_triangles(handle, obj)
        tris.append(t)
        owner += [obj] * len(t)
    tris = np.concatenate(tris) if tris else np.zeros((0, 3, 3))
    lengths = np.linalg.norm(tris - np.roll(tris, 1, axis=1), axis=-1).max(axis=1) if len(tris) else np.zeros(0)
    levels = np.maximum(1, 2 ** np.ceil(np.log2(np.maximum(lengths / edge, 1.0)))).astype(np.int64)
    # vertex ids of every triangle's barycentric grid (i, j) -> corner0 + i/N (c1 - c0) + j/N (c2 - c0)
    grids = []
    for t, obj, n in zip(tris, owner, levels):
        i, j = np.meshgrid(np.arange(n + 1), np.arange(n + 1), indexing="ij")
        ok = i + j <= n
        world = t[0] + (i[ok, None] / n) * (t[1] - t[0]) + (j[ok, None] / n) * (t[2] - t[0])
        table = np.full((n + 1, n + 1), -1, np.int64)
        table[i[ok], j[ok]] = vid(obj, world)
        grids.append(table)
    grid = np.full((max(len(grids), 1), int(levels.max(initial=1)) + 1, int(levels.max(initial=1)) + 1), 0, np.int64)
    for g_i, table in enumerate(grids):
        grid[g_i, :table.shape[0], :table.shape[1]] = np.maximum(table, 0)
    spheres = []
    for obj, (center, radius) in sphere_objs:
        n_theta = max(2, int(np.ceil(np.pi * radius / edge)))
        n_phi = max(3, int(np.ceil(2 * np.pi * radius / edge)))
        base = len(vertices)
        th, ph = np.meshgrid(np.pi * np.arange(n_theta + 1) / n_theta, 2 * np.pi * np.arange(n_phi) / n_phi,
                             indexing="ij")  # ids: rows of theta, columns of phi (wrapping)
        vertices.extend(center + radius * np.stack([np.sin(th) * np.sin(ph), np.cos(th), np.sin(th) * np.cos(ph)],
                                                   -1).reshape(-1, 3))
        spheres.append((center, radius, n_theta, n_phi, base))

    index = np.zeros((len(p), 4), np.int64)
    weight = np.zeros((len(p), 4), np.float64)
    best = np.full(len(p), np.inf)
    chunk = max(1, min(int(chunk), (1 << 22) // max(len(tris), 1)))  # (points, triangles) arrays of ~100 MB at most
    for start in range(0, len(p), chunk):
        q = p[start:start + chunk]
        sl = slice(start, start + len(q))
        if len(tris):
            e1, e2 = tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0]
            nrm = np.cross(e1, e2)
            nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-30)
            rel = q[:, None, :] - tris[None, :, 0]  # (Q, F, 3)
            dist = np.abs(np.einsum("qfk,fk->qf", rel, nrm))
            # barycentric coordinates (b1, b2) of the projection, by the 2 x 2 normal equations
            d11, d12, d22 = (e1 * e1).sum(1), (e1 * e2).sum(1), (e2 * e2).sum(1)
            r1, r2 = np.einsum("qfk,fk->qf", rel, e1), np.einsum("qfk,fk->qf", rel, e2)
            det = np.maximum(d11 * d22 - d12 * d12, 1e-30)
            b1, b2 = (d22 * r1 - d12 * r2) / det, (d11 * r2 - d12 * r1) / det
            outside = np.maximum.reduce([-b1, -b2, b1 + b2 - 1.0, np.zeros_like(b1)])
            score = dist + outside * np.sqrt(np.maximum(d11, d22))[None, :]
            f = np.argmin(score, axis=1)
            s = score[np.arange(len(q)), f]
            take = s < best[sl]
            best[sl] = np.where(take, s, best[sl])
            a1, a2 = np.clip(b1[np.arange(len(q)), f], 0, 1), np.clip(b2[np.arange(len(q)), f], 0, 1)
            tot = a1 + a2
            scale = 1.0 / np.maximum(tot, 1.0)
            a1, a2 = a1 * scale, a2 * scale
            n = levels[f]
            u, v = a1 * n, a2 * n
            i = np.minimum(np.floor(u).astype(np.int64), n - 1)
            j = np.minimum(np.floor(v).astype(np.int64), n - 1 - i)
            fu, fv = u - i, v - j
            upper = (fu + fv > 1.0) & (i + j <= n - 2)
            ids = np.zeros((len(q), 4), np.int64)
            ws = np.zeros((len(q), 4))
            lower_ids = np.stack([grid[f, i, j], grid[f, i + 1, j], grid[f, i, j + 1]], 1)
            upper_ids = np.stack([grid[f, i + 1, j + 1], grid[f, i, j + 1], grid[f, i + 1, j]], 1)
            ids[:, :3] = np.where(upper[:, None], upper_ids, lower_ids)
            ws[:, :3] = np.where(upper[:, None], np.stack([fu + fv - 1.0, 1.0 - fu, 1.0 - fv], 1),
                                 np.stack([1.0 - fu - fv, fu, fv], 1))
            ws[:, :3] = np.clip(ws[:, :3], 0.0, 1.0)
            index[sl] = np.where(take[:, None], ids, index[sl])
            weight[sl] = np.where(take[:, None], ws, weight[sl])
        for center, radius, n_theta, n_phi, base in spheres:
            d = q - center
            r = np.linalg.norm(d, axis=1)
            s = np.abs(r - radius)
            take = s < best[sl]
            best[sl] = np.where(take, s, best[sl])
            d = d / np.maximum(r[:, None], 1e-30)
            t = np.arccos(np.clip(d[:, 1], -1, 1)) / np.pi * n_theta
            ph = np.mod(np.arctan2(d[:, 0], d[:, 2]), 2 * np.pi) / (2 * np.pi) * n_phi
            ti = np.minimum(np.floor(t).astype(np.int64), n_theta - 1)
            pj = np.floor(ph).astype(np.int64) % n_phi
            ft, fp = t - ti, ph - np.floor(ph)
            pk = (pj + 1) % n_phi
            ids = base + np.stack([ti * n_phi + pj, ti * n_phi + pk, (ti + 1) * n_phi + pj, (ti + 1) * n_phi + pk], 1)
            ws = np.stack([(1 - ft) * (1 - fp), (1 - ft) * fp, ft * (1 - fp), ft * fp], 1)
            index[sl] = np.where(take[:, None], ids, index[sl])
            weight[sl] = np.where(take[:, None], ws, weight[sl])
    weight /= np.maximum(weight.sum(axis=1, keepdims=True), 1e-30)
    return (index.reshape(shape + (4,)).astype(np.int32), weight.reshape(shape + (4,)).astype(np.float32),
            np.asarray(vertices, np.float32).reshape(-1, 3))
