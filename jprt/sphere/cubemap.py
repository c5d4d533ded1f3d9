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
over its own solid angle (by ``supersample^2`` solid-angle-weighted sub-samples taking the value of
the source texel they fall in), so the total energy sum(L * solid angle) is preserved up to the
quadrature of the overlaps.
"""

from __future__ import annotations

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
    "sample_equirect_nearest",
]

FACE_NAMES = ("+X", "-X", "+Y", "-Y", "+Z", "-Z")

# For each face: direction = ma_axis * sign + sc * s_axis + tc * t_axis, with (sc, tc) in [-1, 1].
_MAJOR = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], np.float64)
_S_AXIS = np.array([[0, 0, -1], [0, 0, 1], [1, 0, 0], [1, 0, 0], [1, 0, 0], [-1, 0, 0]], np.float64)
_T_AXIS = np.array([[0, -1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1], [0, -1, 0], [0, -1, 0]], np.float64)


def face_uv_to_direction(face, u, v):
    """Unit direction (..., 3) of face coordinates u, v in [0, 1] on ``face`` (int array)."""
    face = jnp.asarray(face)
    sc = 2.0 * jnp.asarray(u) - 1.0
    tc = 2.0 * jnp.asarray(v) - 1.0
    d = (jnp.asarray(_MAJOR, jnp.float32)[face] + sc[..., None] * jnp.asarray(_S_AXIS, jnp.float32)[face]
         + tc[..., None] * jnp.asarray(_T_AXIS, jnp.float32)[face])
    return d / jnp.linalg.norm(d, axis=-1, keepdims=True)


def direction_to_face_uv(d):
    """(face int32, u, v) of directions (..., 3); d need not be normalised (must be non-zero)."""
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
    """Unit directions (6, n, n, 3) of the texel centres of an n x n cube map."""
    c = (jnp.arange(n) + 0.5) / n
    v, u = jnp.meshgrid(c, c, indexing="ij")
    faces = jnp.arange(6)[:, None, None]
    return face_uv_to_direction(jnp.broadcast_to(faces, (6, n, n)), u[None], v[None])


def _area_element(x, y):
    """Solid angle of the face rectangle [0, x] x [0, y] (face plane at distance 1)."""
    return np.arctan2(x * y, np.sqrt(x * x + y * y + 1.0))


def texel_solid_angles(n: int):
    """Exact solid angles (6, n, n) of the texels of an n x n cube map (they sum to 4 pi)."""
    edges = np.linspace(-1.0, 1.0, n + 1)
    x0, x1 = edges[:-1][None, :], edges[1:][None, :]
    y0, y1 = edges[:-1][:, None], edges[1:][:, None]
    omega = _area_element(x1, y1) - _area_element(x0, y1) - _area_element(x1, y0) + _area_element(x0, y0)
    return jnp.asarray(np.broadcast_to(omega, (6, n, n)).copy(), jnp.float32)


def direction_to_texel(d, n: int):
    """(face, row, column) int32 indices of the texels containing directions d (..., 3)."""
    face, u, v = direction_to_face_uv(d)
    col = jnp.clip(jnp.floor(u * n), 0, n - 1).astype(jnp.int32)
    row = jnp.clip(jnp.floor(v * n), 0, n - 1).astype(jnp.int32)
    return face, row, col


def equirect_directions(height: int, width: int):
    """Unit directions (H, W, 3) of jprt equirect texel centres (as ``jprt.render.lights``)."""
    theta = jnp.pi * (jnp.arange(height) + 0.5) / height
    phi = 2.0 * jnp.pi * (jnp.arange(width) + 0.5) / width
    st, ct = jnp.sin(theta)[:, None], jnp.cos(theta)[:, None]
    return jnp.stack(jnp.broadcast_arrays(jnp.sin(phi)[None] * st, ct, -jnp.cos(phi)[None] * st), axis=-1)


def equirect_solid_angles(height: int, width: int):
    """Exact solid angles (H, W) of equirect texels: (2 pi / W) (cos theta_i - cos theta_{i+1})."""
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
    """Value of the equirect texel containing each direction d (..., 3)."""
    row, col = _equirect_texel(d, equirect.shape[0], equirect.shape[1])
    return jnp.asarray(equirect)[row, col]


def sample_cubemap_nearest(cubemap, d):
    """Value of the cube-map texel containing each direction d (..., 3)."""
    face, row, col = direction_to_texel(d, cubemap.shape[1])
    return jnp.asarray(cubemap)[face, row, col]


def _sub_offsets(s: int):
    return (jnp.arange(s) + 0.5) / s


def equirect_to_cubemap(equirect, n: int, supersample: int = 4):
    """Area-weighted resampling of an (H, W, C) equirect map to a (6, n, n, C) cube map."""
    equirect = jnp.asarray(equirect)
    s = supersample
    o = _sub_offsets(s)
    # Sub-sample face coordinates: (n*s,) along each axis.
    coords = ((jnp.arange(n)[:, None] + o[None, :]) / n).reshape(-1)
    v, u = jnp.meshgrid(coords, coords, indexing="ij")
    faces = jnp.broadcast_to(jnp.arange(6)[:, None, None], (6, n * s, n * s))
    d = face_uv_to_direction(faces, u[None], v[None])  # (6, ns, ns, 3)
    # Solid-angle weight of each sub-sample: the exact sub-texel solid angle.
    w = texel_solid_angles(n * s)  # (6, ns, ns)
    values = sample_equirect_nearest(equirect, d)  # (6, ns, ns, C)
    num = (values * w[..., None]).reshape(6, n, s, n, s, -1).sum(axis=(2, 4))
    den = w.reshape(6, n, s, n, s).sum(axis=(2, 4))
    return num / den[..., None]


def cubemap_to_equirect(cubemap, height: int, width: int, supersample: int = 4):
    """Area-weighted resampling of a (6, n, n, C) cube map to an (H, W, C) equirect map."""
    cubemap = jnp.asarray(cubemap)
    s = supersample
    o = _sub_offsets(s)
    theta_edges = jnp.pi * jnp.arange(height + 1) / height
    # Sub-rows uniform in cos(theta) inside each row, so each sub-sample has equal solid angle.
    ct0, ct1 = jnp.cos(theta_edges[:-1]), jnp.cos(theta_edges[1:])
    ct = (ct0[:, None] + (ct1 - ct0)[:, None] * o[None, :]).reshape(-1)  # (H*s,)
    phi = (2.0 * jnp.pi * (jnp.arange(width)[:, None] + o[None, :]) / width).reshape(-1)  # (W*s,)
    st = jnp.sqrt(jnp.maximum(1.0 - ct * ct, 0.0))
    d = jnp.stack(jnp.broadcast_arrays(jnp.sin(phi)[None] * st[:, None], ct[:, None],
                                       -jnp.cos(phi)[None] * st[:, None]), axis=-1)
    values = sample_cubemap_nearest(cubemap, d)  # (H*s, W*s, C)
    return values.reshape(height, s, width, s, -1).mean(axis=(1, 3))
