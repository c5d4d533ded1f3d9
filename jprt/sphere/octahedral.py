"""Octahedral maps (Praun and Hoppe 2003; Cigolle et al. 2014): the sphere unfolded onto a square.

A unit direction d is projected onto the octahedron |x| + |y| + |z| = 1; the upper half (z >= 0)
maps to the diamond |u| + |v| <= 1 of [-1, 1]^2 and the lower half is folded out to the corners.
An N x N map indexes texel (i, j) by v (rows) and u (columns), texel centres at
u = -1 + 2 (j + 0.5) / N. Used for per-texel directional data where a cube map's six faces are
awkward (light-field textures; Currius et al. 2020 store their SG lobes per texel instead).

Per-texel solid angles are exact: inside each quadrant the map is affine on either side of the
fold |u| + |v| = 1, which passes through texel corners when N is even, so each texel is two
triangles whose images are spherical triangles (area by Van Oosterom and Strackee 1983).
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

__all__ = ["encode", "decode", "texel_centers", "texel_directions", "texel_solid_angles", "hemisphere_mask",
           "hemisphere_solid_angles", "direction_to_texel"]


def _sign(x):
    return jnp.where(x >= 0, 1.0, -1.0)


def encode(d):
    """Unit directions (..., 3) -> octahedral coordinates (..., 2) in [-1, 1]^2.

    Numerics:
        d: (32, 3) unit
        fd: off (the lower hemisphere folds at z = 0 and the fold's signs flip at x, y = 0, which axis-aligned draws hit)
        float32: value rtol 1e-6 atol 1e-7; grad rtol 1e-5 atol 1e-6
    """
    d = jnp.asarray(d)
    # |x| + |y| + |z| >= 1 for unit vectors, so the clamp only guards d = 0.
    n = d / jnp.maximum(jnp.sum(jnp.abs(d), axis=-1, keepdims=True), 1e-30)
    u, v, z = n[..., 0], n[..., 1], n[..., 2]
    fu = (1.0 - jnp.abs(v)) * _sign(u)
    fv = (1.0 - jnp.abs(u)) * _sign(v)
    return jnp.stack([jnp.where(z >= 0, u, fu), jnp.where(z >= 0, v, fv)], axis=-1)


def decode(uv):
    """Octahedral coordinates (..., 2) in [-1, 1]^2 -> unit directions (..., 3).

    Numerics:
        uv: (32, 2) in [-1, 1]
        fd: off (the fold |u| + |v| = 1 and the axes u, v = 0 are kinks, and the domain's ends lie on them)
        float32: value rtol 1e-6 atol 1e-7; grad rtol 1e-5 atol 1e-6
    """
    uv = jnp.asarray(uv)
    u, v = uv[..., 0], uv[..., 1]
    z = 1.0 - jnp.abs(u) - jnp.abs(v)
    x = jnp.where(z >= 0, u, (1.0 - jnp.abs(v)) * _sign(u))
    y = jnp.where(z >= 0, v, (1.0 - jnp.abs(u)) * _sign(v))
    d = jnp.stack([x, y, z], axis=-1)
    return d / jnp.linalg.norm(d, axis=-1, keepdims=True)


def texel_centers(n: int):
    """Octahedral coordinates (n, n, 2) of texel centres, [..., 0] = u (column), [..., 1] = v (row).

    Numerics: not differentiable (a function of the integer map size).
    """
    c = -1.0 + 2.0 * (jnp.arange(n) + 0.5) / n
    v, u = jnp.meshgrid(c, c, indexing="ij")
    return jnp.stack([u, v], axis=-1)


def texel_directions(n: int):
    """Unit directions (n, n, 3) of texel centres.

    Numerics: not differentiable (a function of the integer map size).
    """
    return decode(texel_centers(n))


def direction_to_texel(d, n: int):
    """(row, column) int32 of the texels containing directions d (..., 3).

    Numerics: not differentiable (integer texel indices).
    """
    uv = encode(d)
    col = jnp.clip(jnp.floor((uv[..., 0] + 1.0) * 0.5 * n), 0, n - 1).astype(jnp.int32)
    row = jnp.clip(jnp.floor((uv[..., 1] + 1.0) * 0.5 * n), 0, n - 1).astype(jnp.int32)
    return row, col


def _decode_np(u, v):
    z = 1.0 - np.abs(u) - np.abs(v)
    x = np.where(z >= 0, u, (1.0 - np.abs(v)) * np.where(u >= 0, 1.0, -1.0))
    y = np.where(z >= 0, v, (1.0 - np.abs(u)) * np.where(v >= 0, 1.0, -1.0))
    d = np.stack([x, y, z], axis=-1)
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def _triangle_solid_angle(a, b, c):
    """Solid angle of spherical triangles with unit vertices (Van Oosterom and Strackee 1983)."""
    num = np.abs(np.einsum("...i,...i", a, np.cross(b, c)))
    den = 1.0 + np.einsum("...i,...i", a, b) + np.einsum("...i,...i", b, c) + np.einsum("...i,...i", c, a)
    return 2.0 * np.arctan2(num, den)


def _texel_triangles(n: int):
    """Per texel, its two triangles as (uv centroids (2, n, n, 2), solid angles (2, n, n))."""
    if n % 2:
        raise ValueError(f"octahedral solid angles need an even size (the fold must meet texel corners), got {n}")
    e = np.linspace(-1.0, 1.0, n + 1)
    u0, v0 = np.meshgrid(e[:-1], e[:-1], indexing="xy")
    u1, v1 = np.meshgrid(e[1:], e[1:], indexing="xy")
    corners = {(a, b): (np.where(a, u1, u0), np.where(b, v1, v0)) for a in (0, 1) for b in (0, 1)}
    # The fold |u| + |v| = 1 is the anti-diagonal of a texel where sign(u) == sign(v), else the
    # main diagonal: split along it so each triangle lies in one affine piece of the map.
    same = ((u0 + u1) * (v0 + v1)) > 0
    tri_anti = (((0, 0), (1, 0), (0, 1)), ((1, 1), (0, 1), (1, 0)))
    tri_main = (((0, 0), (1, 0), (1, 1)), ((0, 0), (1, 1), (0, 1)))
    centroids, angles = [], []
    for k in range(2):
        per_split = []
        for tri in (tri_anti[k], tri_main[k]):
            uvs = [corners[c] for c in tri]
            pts = [_decode_np(u, v) for u, v in uvs]
            cu = sum(u for u, _ in uvs) / 3.0
            cv = sum(v for _, v in uvs) / 3.0
            per_split.append((np.stack([cu, cv], -1), _triangle_solid_angle(*pts)))
        centroids.append(np.where(same[..., None], per_split[0][0], per_split[1][0]))
        angles.append(np.where(same, per_split[0][1], per_split[1][1]))
    return np.stack(centroids), np.stack(angles)


def texel_solid_angles(n: int):
    """Exact solid angles (n, n) of an n x n octahedral map's texels (n even; they sum to 4 pi).

    Numerics: not differentiable (a function of the integer map size).
    """
    _, angles = _texel_triangles(n)
    return jnp.asarray(angles.sum(axis=0), jnp.float32)


def hemisphere_solid_angles(n: int):
    """Exact solid angle (n, n) of each texel's part in the upper hemisphere z >= 0 (sums to 2 pi);
    texels cut by the fold |u| + |v| = 1 count half-triangles exactly.

    Numerics: not differentiable (a function of the integer map size).
    """
    centroids, angles = _texel_triangles(n)
    upper = (np.abs(centroids[..., 0]) + np.abs(centroids[..., 1])) < 1.0
    return jnp.asarray(np.sum(angles * upper, axis=0), jnp.float32)


def hemisphere_mask(n: int):
    """(n, n) bool: texels with any part in the upper hemisphere z >= 0 (centre in the diamond
    |u| + |v| <= 1; texels on the fold are half in, see ``hemisphere_solid_angles``).

    Numerics: not differentiable (a boolean mask).
    """
    c = texel_centers(n)
    return jnp.abs(c[..., 0]) + jnp.abs(c[..., 1]) <= 1.0
