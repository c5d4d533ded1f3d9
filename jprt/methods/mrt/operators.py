"""The geometric operators of the canonical block (Loos et al. 2011, §4 and §5.1), pure NumPy:
everything MRT precomputes by "ray tracing" the dictionary is computed here in closed form or by
deterministic quadrature over the unit block of ``jprt.layouts``.

* ``form_factors``: the one-bounce gather operator F of Eq. 1 for the closed cube. The paper
  casts gather rays; a cube is convex, so there is no occlusion and F is exact form factors:
  Lambert's contour integral from a point to a texel's rectangle, averaged over a
  ``q x q`` Gauss-Legendre rule on the receiving texel. One closed-cube F serves every
  dictionary element: a missing face only removes rows and columns (light reaching it leaves).
* ``point_light_direct``: the direct light of a point light at every texel, inside the block or
  outside it (seen only through the block's missing sides): the samples of the light prior (§4).
* Interface lightfields (§5.1): ``lightfield_rays`` samples the lightfield leaving side 0 (space
  ``s_s^2`` cells x direction ``s_d^2`` cells; directions by Shirley and Chiu's concentric map to
  a cosine-weighted hemisphere, ``concentric``/``concentric_inverse``), ``exit_resampling`` reads
  a block's surface radiance into it, ``entry_response`` deposits an entering lightfield on the
  block's texels, ``propagation`` carries it straight through the empty block to the left,
  opposite or right side.
* ``hemisphere_sh``/``volume_sh``: quadratic SH of the radiance a texel or a point in the block
  sees (§6.4, §6.5).

Quantities on texels are radiance; the gather returns E / pi, the mean incident radiance over the
cosine-weighted hemisphere, so outgoing radiance is albedo x (F l) (the albedo is applied per
texel at run time, ``model``).
"""

from __future__ import annotations

import numpy as np
from scipy import sparse

from jprt import layouts

__all__ = ["form_factors", "point_light_direct", "prior_lights", "concentric", "concentric_inverse",
           "lightfield_rays", "entry_rays", "exit_resampling", "entry_response", "propagation", "face_mask",
           "hemisphere_sh", "volume_sh", "volume_lightfield_sh"]


def face_mask(t: int, missing: tuple[int, ...]) -> np.ndarray:
    """(n,) bool: the texels that exist in a block with the given missing sides."""
    face = layouts.texel_centres(t)[2]
    return ~np.isin(face, [2 + s for s in missing])


def _texel_corners(t: int) -> np.ndarray:
    """(n, 4, 3) corners of every texel rectangle, counter-clockwise seen from inside."""
    pos, _, face = layouts.texel_centres(t)
    u, v = layouts.FACE_U[face] / (2 * t), layouts.FACE_V[face] / (2 * t)
    return np.stack([pos - u - v, pos + u - v, pos + u + v, pos - u + v], axis=1)


def _point_to_polygons(p, n, corners) -> np.ndarray:
    """Form factor from points p (P, 3) with normals n (P, 3) to polygons (Q, V, 3): Lambert's
    formula 1/(2 pi) |sum_e gamma_e n . (R_e x R_e+1) / |R_e x R_e+1||, (P, Q). Exact for
    polygons wholly above each point's tangent plane (true inside a convex block)."""
    r = corners[None] - p[:, None, None]  # (P, Q, V, 3)
    r = r / np.linalg.norm(r, axis=-1, keepdims=True)
    r1 = np.roll(r, -1, axis=2)
    c = np.cross(r, r1)
    cn = np.linalg.norm(c, axis=-1)
    gamma = np.arccos(np.clip(np.sum(r * r1, -1), -1.0, 1.0))
    with np.errstate(invalid="ignore", divide="ignore"):
        term = np.where(cn > 1e-15, gamma * np.einsum("pqvk,pk->pqv", c, n) / cn, 0.0)
    return np.abs(term.sum(-1)) / (2 * np.pi)


def form_factors(t: int, quadrature: int = 2, *, chunk: int = 64) -> np.ndarray:
    """(n, n) gather operator F of the closed unit cube (Eq. 1): F[i, j] is the form factor from
    texel i to texel j (the mean over texel i of the point-to-rectangle form factor), so
    (F l)_i is texel i's incident irradiance / pi for surface radiance l and rows sum to 1."""
    t = int(t)
    pos, normal, face = layouts.texel_centres(t)
    corners = _texel_corners(t)
    x, w = np.polynomial.legendre.leggauss(int(quadrature))
    x, w = x / 2, w / 2  # on [-1/2, 1/2], weights summing to 1
    offs = [(a, b, wa * wb) for a, wa in zip(x, w) for b, wb in zip(x, w)]
    out = np.zeros((len(pos), len(pos)))
    for s in range(0, len(pos), chunk):
        sl = slice(s, s + chunk)
        for a, b, wt in offs:
            p = pos[sl] + (a * layouts.FACE_U[face[sl]] + b * layouts.FACE_V[face[sl]]) / t
            ff = _point_to_polygons(p, normal[sl], corners)
            ff[face[sl][:, None] == face[None, :]] = 0.0  # coplanar texels see nothing of each other
            out[sl] += wt * ff
    return out


def _exit_through(origin_inside, target) -> np.ndarray:
    """Side (0-3), or -1 for floor/ceiling, through which the segment from a point in the block
    to a point outside it leaves."""
    d = target - origin_inside
    face, _ = layouts.exit_face(origin_inside, d)
    return np.where(face >= 2, face - 2, -1)


def point_light_direct(t: int, lights, missing: tuple[int, ...] = ()) -> np.ndarray:
    """(n, m) direct light (radiance of a white albedo-1 texel, I cos / (pi r^2)) of m unit point
    lights at ``lights`` (m, 3) on every texel of a block with ``missing`` sides. Lights outside
    the block reach a texel only when the segment leaves through a missing side (the block is
    convex, so nothing else occludes); texels of missing faces are 0."""
    pos, normal, _ = layouts.texel_centres(t)
    lights = np.asarray(lights, np.float64).reshape(-1, 3)
    d = lights[None] - pos[:, None]  # (n, m, 3)
    r2 = np.sum(d * d, -1)
    cos = np.maximum(np.einsum("nmk,nk->nm", d, normal) / np.sqrt(r2), 0.0)
    val = cos / (np.pi * r2)
    inside = np.all((lights >= 0) & (lights <= 1), axis=-1)
    if not np.all(inside):
        p = np.repeat(pos[:, None], len(lights), 1).reshape(-1, 3)
        q = np.repeat(lights[None], len(pos), 0).reshape(-1, 3)
        side = _exit_through(p, q).reshape(len(pos), len(lights))
        ok = np.isin(side, list(missing)) | inside[None]
        val = np.where(ok, val, 0.0)
    return val * face_mask(t, missing)[:, None]


def prior_lights(grid: int, missing: tuple[int, ...] = ()) -> np.ndarray:
    """Light positions of the prior (§4, §7.1): a ``grid^3`` lattice of cell centres in the block
    and the same lattice in the cube beyond each missing side (light arriving through it)."""
    g = (np.arange(grid) + 0.5) / grid
    lattice = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    out = [lattice]
    for s in missing:
        out.append(lattice + layouts.SIDE_NORMALS[s])
    return np.concatenate(out)


# --------------------------------------------------------------------------------------------
# Interface lightfields (§5.1)


def concentric(square) -> np.ndarray:
    """Shirley and Chiu's concentric map [0, 1]^2 -> unit disk (..., 2)."""
    s = 2.0 * np.asarray(square, np.float64) - 1.0
    x, y = s[..., 0], s[..., 1]
    big_x = np.abs(x) > np.abs(y)
    with np.errstate(divide="ignore", invalid="ignore"):
        r = np.where(big_x, x, y)
        phi = np.where(big_x, np.pi / 4 * y / x, np.pi / 2 - np.pi / 4 * x / y)
    phi = np.where(r == 0, 0.0, phi)
    return np.stack([r * np.cos(phi), r * np.sin(phi)], -1)


def concentric_inverse(disk) -> np.ndarray:
    """The inverse map, unit disk -> [0, 1]^2."""
    d = np.asarray(disk, np.float64)
    r = np.hypot(d[..., 0], d[..., 1])
    th = np.arctan2(d[..., 1], d[..., 0])
    th = np.where(th < -np.pi / 4, th + 2 * np.pi, th)
    k = 4 / np.pi
    x = np.select([th < np.pi / 4, th < 3 * np.pi / 4, th < 5 * np.pi / 4],
                  [r, r * (np.pi / 2 - th) * k, -r], r * (th - 3 * np.pi / 2) * k)
    y = np.select([th < np.pi / 4, th < 3 * np.pi / 4, th < 5 * np.pi / 4],
                  [r * th * k, r, -r * (th - np.pi) * k], -r)
    return np.clip((np.stack([x, y], -1) + 1.0) / 2.0, 0.0, 1.0)


# The frame of side 0 (x = 1): tangent u = +z, tangent v = +y, outward normal +x.
_TU, _TV, _N0 = np.array([0.0, 0, 1]), np.array([0.0, 1, 0]), np.array([1.0, 0, 0])


def lightfield_rays(spatial: int, directional: int, spatial_ss: int = 1, directional_ss: int = 1):
    """Sub-rays of the lightfield leaving the block through side 0: origins (R, 3) on x = 1,
    outward unit directions (R, 3) and the cell (R,) each belongs to (cell = position cell *
    directional^2 + direction cell; position cells over (u = z, v = y), direction cells over the
    concentric square). Every cell has spatial_ss^2 x directional_ss^2 sub-rays on a regular
    sub-grid; each carries cos theta d omega = pi / (directional * directional_ss)^2."""
    ns, nd = int(spatial) * int(spatial_ss), int(directional) * int(directional_ss)
    gs, gd = (np.arange(ns) + 0.5) / ns, (np.arange(nd) + 0.5) / nd
    uu, vv = np.meshgrid(gs, gs, indexing="xy")
    sa, sb = np.meshgrid(gd, gd, indexing="xy")
    pos_cell = (np.floor(vv * spatial).astype(int) * spatial + np.floor(uu * spatial).astype(int)).reshape(-1)
    dir_cell = (np.floor(sb * directional).astype(int) * directional + np.floor(sa * directional).astype(int)).reshape(-1)
    disk = concentric(np.stack([sa, sb], -1).reshape(-1, 2))
    cz = np.sqrt(np.maximum(1.0 - np.sum(disk ** 2, -1), 0.0))
    dirs = cz[:, None] * _N0 + disk[:, :1] * _TU + disk[:, 1:] * _TV
    origins = _N0 + uu.reshape(-1, 1) * _TU + vv.reshape(-1, 1) * _TV
    o = np.repeat(origins, len(dirs), axis=0)
    d = np.tile(dirs, (len(origins), 1))
    cell = (pos_cell[:, None] * directional ** 2 + dir_cell[None, :]).reshape(-1)
    return o, d, cell


def _cell_of_exit(points, dirs, spatial: int, directional: int) -> np.ndarray:
    """Lightfield cell of rays leaving through side 0 (the inverse of ``lightfield_rays``)."""
    iu = np.clip(np.floor(points @ _TU * spatial), 0, spatial - 1).astype(int)
    iv = np.clip(np.floor(points @ _TV * spatial), 0, spatial - 1).astype(int)
    sq = concentric_inverse(np.stack([dirs @ _TU, dirs @ _TV], -1))
    ja = np.clip(np.floor(sq[:, 0] * directional), 0, directional - 1).astype(int)
    jb = np.clip(np.floor(sq[:, 1] * directional), 0, directional - 1).astype(int)
    return (iv * spatial + iu) * directional ** 2 + jb * directional + ja


def entry_rays(origins, directions):
    """The rays leaving a block through side 0, seen by the neighbour they enter, turned so that
    it is the neighbour's side 0 too: one step back across the side and two turns. An exit
    lightfield is therefore, sample for sample, the neighbour's entry lightfield."""
    return layouts.rotate_points(origins - _N0, 2), layouts.rotate_directions(directions, 2)


def _cells_total(spatial: int, directional: int) -> int:
    return int(spatial) ** 2 * int(directional) ** 2


def exit_resampling(t: int, rays, spatial: int, directional: int) -> sparse.csr_matrix:
    """(s, n) sparse: the lightfield leaving side 0 as the mean over each cell's sub-rays of the
    radiance of the texel each sub-ray comes from (traced backwards into the block)."""
    o, d, cell = rays
    face, hit = layouts.exit_face(o - 1e-9 * d, -d)
    texel = layouts.locate(hit, t, layouts.FACE_NORMALS[face])
    s = _cells_total(spatial, directional)
    per_cell = np.bincount(cell, minlength=s)
    m = sparse.coo_matrix((1.0 / per_cell[cell], (cell, texel)), shape=(s, layouts.texel_count(t)))
    return m.tocsr()


def entry_response(t: int, rays, spatial: int, directional: int, directional_ss: int, spatial_ss: int) -> sparse.csr_matrix:
    """(n, s) sparse F_rlf (§5.1): the E / pi each texel receives from a unit-radiance entering
    lightfield cell (sub-ray flux L dA pi / N_d over the texel's area 1 / t^2, divided by pi)."""
    o, d, cell = entry_rays(*rays[:2]) + (rays[2],)
    face, hit = layouts.exit_face(o, d)
    texel = layouts.locate(hit, t, layouts.FACE_NORMALS[face])
    n_sub_s = (int(spatial) * int(spatial_ss)) ** 2
    n_sub_d = (int(directional) * int(directional_ss)) ** 2
    w = np.full(len(cell), t * t / (n_sub_s * n_sub_d))
    m = sparse.coo_matrix((w, (texel, cell)), shape=(layouts.texel_count(t), _cells_total(spatial, directional)))
    return m.tocsr()


def propagation(rays, spatial: int, directional: int) -> dict[int, sparse.csr_matrix]:
    """(s, s) sparse R for each relative side 1 (left), 2 (opposite), 3 (right): the lightfield
    entering side 0 carried straight through the empty block to the lightfield leaving that side.
    Each leaving cell is the mean over its sub-rays, traced backwards, of the entering cell they
    came through; sub-rays that come from the floor, the ceiling or a wall add nothing (that is
    surface radiance, not the propagated lightfield)."""
    o, d, cell = rays
    s = _cells_total(spatial, directional)
    per_cell = np.bincount(cell, minlength=s).astype(np.float64)
    out = {}
    for k in (1, 2, 3):
        ok, dk = layouts.rotate_points(o, k), layouts.rotate_directions(d, k)
        face, hit = layouts.exit_face(ok - 1e-9 * dk, -dk)
        sel = face == 2  # came in through side 0
        src = _cell_of_exit(layouts.rotate_points(hit[sel], 2) + _N0, layouts.rotate_directions(dk[sel], 2),
                            spatial, directional)
        dst = cell[sel]
        out[k] = sparse.coo_matrix((1.0 / per_cell[dst], (dst, src)), shape=(s, s)).tocsr()
    return out

# --------------------------------------------------------------------------------------------
# Higher-order irradiance (§6.4) and irradiance volumes (§6.5)


def sh9(d) -> np.ndarray:
    """Real SH up to l = 2 (the order of ``jprt.sphere.sh``: l = 0; l = 1 m = -1, 0, 1; l = 2
    m = -2 .. 2) at unit directions (..., 3) -> (..., 9)."""
    from jprt.sphere import sh

    return np.asarray(sh.evaluate(np.asarray(d, np.float64), 2), np.float64)


def sphere_directions(k: int, hemisphere: bool):
    """k x k (hemisphere: about +z) or k x 2k (sphere) equal-solid-angle stratified directions
    and their weights."""
    nu, nv = k, (k if hemisphere else 2 * k)
    a = (np.arange(nu) + 0.5) / nu
    b = (np.arange(nv) + 0.5) / nv
    aa, bb = np.meshgrid(a, b, indexing="ij")
    z = (1.0 - aa) if hemisphere else (1.0 - 2.0 * aa)
    phi = 2 * np.pi * bb
    r = np.sqrt(np.maximum(1 - z * z, 0))
    d = np.stack([r * np.cos(phi), r * np.sin(phi), z], -1).reshape(-1, 3)
    w = np.full(len(d), (2 * np.pi if hemisphere else 4 * np.pi) / len(d))
    return d, w


def hemisphere_sh(t: int, directions: int = 16) -> np.ndarray:
    """(n, 9, n) linear operator: the quadratic SH coefficients, in each texel's local frame
    (tangent u, tangent v, normal = +z), of the radiance the texel sees over its hemisphere
    (zero below it) from surface radiance l on the block's texels."""
    pos, normal, face = layouts.texel_centres(t)
    d_loc, w = sphere_directions(int(directions), hemisphere=True)
    y = sh9(d_loc) * w[:, None]  # (D, 9)
    out = np.zeros((len(pos), 9, len(pos)))
    for i in range(len(pos)):
        frame = np.stack([layouts.FACE_U[face[i]], layouts.FACE_V[face[i]], normal[i]])  # rows
        dw = d_loc @ frame
        f, hit = layouts.exit_face(np.repeat(pos[i:i + 1], len(dw), 0) + 1e-9 * normal[i], dw)
        tex = layouts.locate(hit, t, layouts.FACE_NORMALS[f])
        np.add.at(out[i].T, tex, y)
    return out


def volume_sh(t: int, points, directions: int = 12) -> np.ndarray:
    """(P, 9, n) linear operator: quadratic SH (block frame) of the radiance arriving at points
    inside the block from surface radiance l on its texels (§6.5's probes)."""
    d, w = sphere_directions(int(directions), hemisphere=False)
    y = sh9(d) * w[:, None]
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    out = np.zeros((len(pts), 9, layouts.texel_count(t)))
    for i, p in enumerate(pts):
        f, hit = layouts.exit_face(np.repeat(p[None], len(d), 0), d)
        tex = layouts.locate(hit, t, layouts.FACE_NORMALS[f])
        np.add.at(out[i].T, tex, y)
    return out


def volume_lightfield_sh(points, directions: int, spatial: int, directional: int, side: int) -> np.ndarray:
    """(P, 9, s) linear operator: quadratic SH (block frame) at points inside the block of the
    radiance arriving through ``side`` from the lightfield entering there (in the parameters of
    a block turned so that ``side`` is its side 0, as ``propagation`` and ``entry_response``
    use): each direction whose ray leaves through that side reads the entering cell of the
    opposite ray."""
    d, w = sphere_directions(int(directions), hemisphere=False)
    y = sh9(d) * w[:, None]
    turn = (4 - int(side)) % 4
    pts = layouts.rotate_points(np.asarray(points, np.float64).reshape(-1, 3), turn)
    dc = layouts.rotate_directions(d, turn)
    out = np.zeros((len(pts), 9, _cells_total(spatial, directional)))
    for i, p in enumerate(pts):
        f, hit = layouts.exit_face(np.repeat(p[None], len(dc), 0), dc)
        sel = f == 2
        cell = _cell_of_exit(layouts.rotate_points(hit[sel], 2) + _N0, layouts.rotate_directions(-dc[sel], 2),
                             spatial, directional)
        np.add.at(out[i].T, cell, y[sel])
    return out
