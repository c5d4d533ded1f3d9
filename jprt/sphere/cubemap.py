"""Cube maps: direction <-> (face, u, v), texel centres, exact texel solid angles, and
energy-preserving equirect <-> cubemap resampling.

The cube map is the domain of the Haar wavelet lighting basis of Ng et al. 2003, as used by
Raghavan et al. 2023 §4 ("Haar wavelets on cubemap faces"). Conventions (OpenGL):

* faces in order +X, -X, +Y, -Y, +Z, -Z; a cube map is an array (6, N, N, ...) indexed
  [face, row, column]; u grows with the column and v with the row, both in [0, 1];
* on face f with major axis value ma = |d_f|, the face coordinates are (sc / ma, tc / ma) with
      +X: (-z, -y)   -X: (z, -y)   +Y: (x, z)   -Y: (x, -z)   +Z: (x, -y)   -Z: (-x, -y)
  and u = (sc / ma + 1) / 2, v = (tc / ma + 1) / 2.
* texel (i, j) of an N x N face covers u in [j, j + 1] / N and v in [i, i + 1] / N.

The equirect convention is jprt's (``jprt.render.lights``): texel (i, j) centred at
theta = pi (i + 0.5) / H, phi = 2 pi (j + 0.5) / W, d = (sin phi sin theta, cos theta,
-cos phi sin theta). Resampling is area-weighted: each destination texel averages the source
over the source texels it overlaps, with overlap areas estimated from sub-samples of both grids
and balanced towards the exact texel solid angles, so constant maps stay constant and the total
energy sum(L * solid angle) is kept to within 1 % (tested on the HDR maps in ../shared/assets).
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

__all__ = [
    "FACE_NAMES",
    "face_uv_to_direction",
    "direction_to_face_uv",
    "texel_directions",
    "texel_solid_angles",
    "direction_to_texel",
    "equirect_directions",
    "equirect_solid_angles",
    "equirect_to_cubemap",
    "cubemap_to_equirect",
    "sample_cubemap_nearest",
    "sample_cubemap_bilinear",
    "rotate_cubemap_y",
    "turned_back_y",
    "sample_equirect_nearest",
]

FACE_NAMES = ("+X", "-X", "+Y", "-Y", "+Z", "-Z")

# For each face: direction = ma_axis * sign + sc * s_axis + tc * t_axis, with (sc, tc) in [-1, 1].
_MAJOR = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], np.float64)
_S_AXIS = np.array([[0, 0, -1], [0, 0, 1], [1, 0, 0], [1, 0, 0], [1, 0, 0], [-1, 0, 0]], np.float64)
_T_AXIS = np.array([[0, -1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1], [0, -1, 0], [0, -1, 0]], np.float64)


def face_uv_to_direction(face, u, v):
    """Unit direction (..., 3) of face coordinates u, v in [0, 1] on ``face`` (int array).

    Numerics:
        face: (32,) int in [0, 5]
        u: (32,) in [0, 1]
        v: (32,) in [0, 1]
        float32: value rtol 1e-6 atol 1e-7; grad rtol 1e-5 atol 1e-6
    """
    face = jnp.asarray(face)
    sc = 2.0 * jnp.asarray(u) - 1.0
    tc = 2.0 * jnp.asarray(v) - 1.0
    d = (jnp.asarray(_MAJOR, jnp.float32)[face] + sc[..., None] * jnp.asarray(_S_AXIS, jnp.float32)[face]
         + tc[..., None] * jnp.asarray(_T_AXIS, jnp.float32)[face])
    return d / jnp.linalg.norm(d, axis=-1, keepdims=True)


def direction_to_face_uv(d):
    """(face int32, u, v) of directions (..., 3); d need not be normalised (must be non-zero).

    Numerics:
        d: (32, 3) unit
        fd: off (the face changes where two components tie in magnitude, which axis-aligned and diagonal draws hit)
        float32: value rtol 1e-6 atol 1e-7; grad rtol 1e-5 atol 1e-6
    """
    d = jnp.asarray(d)
    x, y, z = d[..., 0], d[..., 1], d[..., 2]
    ax, ay, az = jnp.abs(x), jnp.abs(y), jnp.abs(z)
    is_x = (ax >= ay) & (ax >= az)
    is_y = ~is_x & (ay >= az)
    face = jnp.where(is_x, jnp.where(x >= 0, 0, 1), jnp.where(is_y, jnp.where(y >= 0, 2, 3), jnp.where(z >= 0, 4, 5)))
    face = face.astype(jnp.int32)
    ma = jnp.where(is_x, ax, jnp.where(is_y, ay, az))
    # Safe division: ma > 0 for any non-zero direction; the clamp keeps gradients finite at 0.
    ma = jnp.maximum(ma, 1e-30)
    s_axis = jnp.asarray(_S_AXIS, d.dtype)[face]
    t_axis = jnp.asarray(_T_AXIS, d.dtype)[face]
    sc = jnp.sum(d * s_axis, axis=-1) / ma
    tc = jnp.sum(d * t_axis, axis=-1) / ma
    return face, 0.5 * (sc + 1.0), 0.5 * (tc + 1.0)


def texel_directions(n: int):
    """Unit directions (6, n, n, 3) of the texel centres of an n x n cube map.

    Numerics: not differentiable (a function of the integer face size).
    """
    c = (jnp.arange(n) + 0.5) / n
    v, u = jnp.meshgrid(c, c, indexing="ij")
    faces = jnp.arange(6)[:, None, None]
    return face_uv_to_direction(jnp.broadcast_to(faces, (6, n, n)), u[None], v[None])


def _area_element(x, y):
    """Solid angle of the face rectangle [0, x] x [0, y] (face plane at distance 1)."""
    return np.arctan2(x * y, np.sqrt(x * x + y * y + 1.0))


def texel_solid_angles(n: int):
    """Exact solid angles (6, n, n) of the texels of an n x n cube map (they sum to 4 pi).

    Numerics: not differentiable (a function of the integer face size).
    """
    edges = np.linspace(-1.0, 1.0, n + 1)
    x0, x1 = edges[:-1][None, :], edges[1:][None, :]
    y0, y1 = edges[:-1][:, None], edges[1:][:, None]
    omega = _area_element(x1, y1) - _area_element(x0, y1) - _area_element(x1, y0) + _area_element(x0, y0)
    return jnp.asarray(np.broadcast_to(omega, (6, n, n)).copy(), jnp.float32)


def direction_to_texel(d, n: int):
    """(face, row, column) int32 indices of the texels containing directions d (..., 3).

    Numerics: not differentiable (integer texel indices).
    """
    face, u, v = direction_to_face_uv(d)
    col = jnp.clip(jnp.floor(u * n), 0, n - 1).astype(jnp.int32)
    row = jnp.clip(jnp.floor(v * n), 0, n - 1).astype(jnp.int32)
    return face, row, col


def equirect_directions(height: int, width: int):
    """Unit directions (H, W, 3) of jprt equirect texel centres (as ``jprt.render.lights``).

    Numerics: not differentiable (a function of the integer map size).
    """
    theta = jnp.pi * (jnp.arange(height) + 0.5) / height
    phi = 2.0 * jnp.pi * (jnp.arange(width) + 0.5) / width
    st, ct = jnp.sin(theta)[:, None], jnp.cos(theta)[:, None]
    return jnp.stack(jnp.broadcast_arrays(jnp.sin(phi)[None] * st, ct, -jnp.cos(phi)[None] * st), axis=-1)


def equirect_solid_angles(height: int, width: int):
    """Exact solid angles (H, W) of equirect texels: (2 pi / W) (cos theta_i - cos theta_{i+1}).

    Numerics: not differentiable (a function of the integer map size).
    """
    edges = np.pi * np.arange(height + 1) / height
    band = (np.cos(edges[:-1]) - np.cos(edges[1:])) * 2.0 * np.pi / width
    return jnp.asarray(np.repeat(band[:, None], width, axis=1), jnp.float32)


def _equirect_texel(d, height: int, width: int):
    d = jnp.asarray(d)
    theta = jnp.arccos(jnp.clip(d[..., 1] / jnp.linalg.norm(d, axis=-1), -1.0, 1.0))
    phi = jnp.mod(jnp.arctan2(d[..., 0], -d[..., 2]), 2.0 * jnp.pi)
    row = jnp.clip(jnp.floor(theta / jnp.pi * height), 0, height - 1).astype(jnp.int32)
    col = jnp.clip(jnp.floor(phi / (2.0 * jnp.pi) * width), 0, width - 1).astype(jnp.int32)
    return row, col


def sample_equirect_nearest(equirect, d):
    """Value of the equirect texel containing each direction d (..., 3).

    Numerics: not differentiable (a nearest-texel gather: exact in any precision, its gradient a scatter to the chosen texel; within float rounding of a texel boundary float32 and float64 may choose neighbours).
    """
    row, col = _equirect_texel(d, equirect.shape[0], equirect.shape[1])
    return jnp.asarray(equirect)[row, col]


def sample_cubemap_nearest(cubemap, d):
    """Value of the cube-map texel containing each direction d (..., 3).

    Numerics: not differentiable (a nearest-texel gather: exact in any precision, its gradient a scatter to the chosen texel; within float rounding of a texel boundary float32 and float64 may choose neighbours).
    """
    face, row, col = direction_to_texel(d, cubemap.shape[1])
    return jnp.asarray(cubemap)[face, row, col]


def _equirect_subsamples(height: int, width: int, s: int):
    """Sub-samples of equirect texels, s x s per texel, uniform in cos(theta) and phi:
    directions (H*s*W*s, 3), texel index (H*s*W*s,), equal solid angles (texel / s^2)."""
    o = (jnp.arange(s) + 0.5) / s
    theta_edges = jnp.pi * jnp.arange(height + 1) / height
    ct0, ct1 = jnp.cos(theta_edges[:-1]), jnp.cos(theta_edges[1:])
    ct = (ct0[:, None] + (ct1 - ct0)[:, None] * o[None, :]).reshape(-1)
    phi = (2.0 * jnp.pi * (jnp.arange(width)[:, None] + o[None, :]) / width).reshape(-1)
    st = jnp.sqrt(jnp.maximum(1.0 - ct * ct, 0.0))
    d = jnp.stack(jnp.broadcast_arrays(jnp.sin(phi)[None] * st[:, None], ct[:, None],
                                       -jnp.cos(phi)[None] * st[:, None]), axis=-1)
    rows = jnp.repeat(jnp.arange(height), s)[:, None]
    cols = jnp.repeat(jnp.arange(width), s)[None, :]
    index = jnp.broadcast_to(rows * width + cols, d.shape[:2])
    omega = jnp.repeat(jnp.repeat(equirect_solid_angles(height, width), s, axis=0), s, axis=1) / (s * s)
    return d.reshape(-1, 3), index.reshape(-1), omega.reshape(-1)


@jax.jit
def sample_cubemap_bilinear(cubemap, d):
    """Values (..., C) of a cube map (6, N, N, C) at directions d (..., 3), bilinear between the
    four nearest texel centres of the face the direction falls on (clamped at the face's edges:
    within half a texel of an edge the value is the edge texels', not a blend across the seam).
    Differentiable in the values and in d (the face coordinates move smoothly inside a face).

    Numerics:
        case: cube_bilinear (a (6, 4, 4, 3) map in [0, 1e5], directions kept 2 degrees off the face diagonals)
        fd: off (the bilinear weights have kinks at texel centres, which face-centre draws hit)
        float32: value rtol 1e-5 atol 1e-2; grad rtol 1e-4 atol 1e-1
        (weights to 1e-7 times values to 1e5: rounding is absolute, ~1e-2)
    """
    cube = jnp.asarray(cubemap)
    n = cube.shape[1]
    face, u, v = direction_to_face_uv(d)
    x = jnp.clip(u * n - 0.5, 0.0, n - 1.0)
    y = jnp.clip(v * n - 0.5, 0.0, n - 1.0)
    x0 = jnp.clip(jnp.floor(x), 0, n - 1).astype(jnp.int32)
    y0 = jnp.clip(jnp.floor(y), 0, n - 1).astype(jnp.int32)
    x1, y1 = jnp.minimum(x0 + 1, n - 1), jnp.minimum(y0 + 1, n - 1)
    fx, fy = (x - x0)[..., None], (y - y0)[..., None]
    top = cube[face, y0, x0] * (1.0 - fx) + cube[face, y0, x1] * fx
    bottom = cube[face, y1, x0] * (1.0 - fx) + cube[face, y1, x1] * fx
    return top * (1.0 - fy) + bottom * fy


@jax.jit
def rotate_cubemap_y(cubemap, angle):
    """The cube map (6, N, N, C) of the environment turned by ``angle`` radians about +Y (a
    direction d of the result sees what R(-angle) d saw), each texel centre bilinear in the
    original (``sample_cubemap_bilinear``). Differentiable in ``angle``: a lighting designer's
    environment rotation. A quarter turn maps texel centres onto texel centres (exact).

    Numerics:
        case: cube_rotate (a (6, 4, 4, 3) map in [0, 1e5], angles in [0.1, 1.4] rad off the quarter turns)
        fd: off (the bilinear weights have kinks where a rotated centre crosses a texel centre)
        float32: value rtol 1e-4 atol 1e-1; grad rtol 1e-3 atol 1e1
        (values to 1e5 times weights whose rounding is ~1e-6 after the rotation's trigonometry)
    """
    cube = jnp.asarray(cubemap)
    d = texel_directions(cube.shape[1]).astype(jnp.result_type(angle, jnp.float32))
    return sample_cubemap_bilinear(cube, turned_back_y(d, angle))


def turned_back_y(d, angle):
    """R(-angle) d: directions (..., 3) turned by -``angle`` radians about +Y, what a direction d
    of a map turned by ``angle`` (``rotate_cubemap_y``; SG environment's ``rotate_preconvolved_y``)
    reads of the map before the turn.

    Numerics:
        d: (8, 3) unit
        angle: () in [-7, 7]
        float32: value rtol 1e-5 atol 1e-6; grad rtol 1e-5 atol 1e-5
    """
    d = jnp.asarray(d)
    c, s = jnp.cos(angle), jnp.sin(angle)
    # x' = c x - s z, z' = s x + c z
    return jnp.stack([c * d[..., 0] - s * d[..., 2], d[..., 1], s * d[..., 0] + c * d[..., 2]], axis=-1)


def _cube_subsamples(n: int, s: int):
    """Sub-texels of an n x n cube map, s x s per texel: centre directions, texel index, exact solid angles."""
    d = texel_directions(n * s)
    fine = jnp.arange(n * s) // s
    index = (jnp.arange(6)[:, None, None] * n + fine[None, :, None]) * n + fine[None, None, :]
    return d.reshape(-1, 3), index.reshape(-1), texel_solid_angles(n * s).reshape(-1)


def _cube_index(d, n: int):
    face, row, col = direction_to_texel(d, n)
    return (face * n + row) * n + col


def _equirect_index(d, height: int, width: int):
    row, col = _equirect_texel(d, height, width)
    return row * width + col


def _overlap_resample(values, src, dst, src_lookup, dst_lookup, src_omega, dst_omega, iterations: int):
    """Area-weighted resampling through an estimated overlap matrix A (dst x src).

    A is estimated from sub-samples of both grids (each sub-sample adds its solid angle to the
    (dst, src) pair it falls in: source sub-samples make sure every source texel's energy lands
    somewhere, destination sub-samples that every destination texel is covered). ``iterations``
    rounds of proportional fitting pull its column sums towards the source texels' solid angles
    (energy conservation); a final row normalisation makes each output texel an exact weighted
    average (constant maps stay constant). out_d = sum_s A_ds L_s / sum_s A_ds.
    """
    src_dirs, src_idx, src_w = src
    dst_dirs, dst_idx, dst_w = dst
    d_of = jnp.concatenate([dst_lookup(src_dirs), dst_idx])
    s_of = jnp.concatenate([src_idx, src_lookup(dst_dirs)])
    area = 0.5 * jnp.concatenate([src_w, dst_w])
    n_dst, n_src = dst_omega.shape[0], src_omega.shape[0]

    def balance(_, a):
        rows = jax.ops.segment_sum(a, d_of, n_dst)
        a = a * (dst_omega / jnp.maximum(rows, 1e-30))[d_of]
        cols = jax.ops.segment_sum(a, s_of, n_src)
        return a * (src_omega / jnp.maximum(cols, 1e-30))[s_of]

    area = jax.lax.fori_loop(0, iterations, balance, area)
    rows = jax.ops.segment_sum(area, d_of, n_dst)
    flat = values.reshape((n_src, -1))
    return jax.ops.segment_sum(area[:, None] * flat[s_of], d_of, n_dst) / jnp.maximum(rows, 1e-30)[:, None]


def _auto_supersample(src_angle: float, dst_angle: float) -> int:
    # At least 4 x 4 per texel: with 2 x 2 on both grids the sampled overlap pattern can admit no
    # balanced solution (measured: 25 % row error at any iteration count for 16x32 <-> 6x8x8).
    return max(4, min(8, int(np.ceil(2.0 * src_angle / dst_angle))))


@partial(jax.jit, static_argnames=("n", "supersample", "iterations"))
def equirect_to_cubemap(equirect, n: int, supersample: int | None = None, iterations: int = 12):
    """Area-weighted, energy-conserving resampling of an (H, W, ...) equirect map to (6, n, n, ...).

    See ``_overlap_resample``: each cube texel is the overlap-area-weighted average of the
    equirect texels it covers (constant maps stay constant), and the total energy sum(L dω) is
    kept within 1 % on real HDR maps with a sun (tested).

    Numerics:
        equirect: (8, 16, 3) in [0, 1e5]
        n: = 4
        grad: equirect
        float32: value rtol 1e-5 atol 1e-2; grad rtol 1e-5 atol 1e-6
        (overlap-weighted averages of texels to 1e5)
    """
    equirect = jnp.asarray(equirect)
    h, w = equirect.shape[:2]
    s = supersample or _auto_supersample(np.pi / h, (np.pi / 2) / n)
    t = supersample or _auto_supersample((np.pi / 2) / n, np.pi / h)
    out = _overlap_resample(
        equirect, _equirect_subsamples(h, w, s), _cube_subsamples(n, t),
        lambda d: _equirect_index(d, h, w), lambda d: _cube_index(d, n),
        equirect_solid_angles(h, w).reshape(-1), texel_solid_angles(n).reshape(-1), iterations)
    return out.reshape((6, n, n) + equirect.shape[2:])


@partial(jax.jit, static_argnames=("height", "width", "supersample", "iterations"))
def cubemap_to_equirect(cube, height: int, width: int, supersample: int | None = None, iterations: int = 12):
    """Area-weighted, energy-conserving resampling of a (6, n, n, ...) cube map to (H, W, ...)
    (the inverse direction of ``equirect_to_cubemap``, same method).

    Numerics:
        cube: (6, 4, 4, 3) in [0, 1e5]
        height: = 8
        width: = 16
        grad: cube
        float32: value rtol 1e-5 atol 1e-2; grad rtol 1e-5 atol 1e-6
        (overlap-weighted averages of texels to 1e5)
    """
    cube = jnp.asarray(cube)
    n = cube.shape[1]
    s = supersample or _auto_supersample((np.pi / 2) / n, np.pi / height)
    t = supersample or _auto_supersample(np.pi / height, (np.pi / 2) / n)
    out = _overlap_resample(
        cube, _cube_subsamples(n, s), _equirect_subsamples(height, width, t),
        lambda d: _cube_index(d, n), lambda d: _equirect_index(d, height, width),
        texel_solid_angles(n).reshape(-1), equirect_solid_angles(height, width).reshape(-1), iterations)
    return out.reshape((height, width) + cube.shape[3:])
