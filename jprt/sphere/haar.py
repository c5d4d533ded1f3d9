"""2D non-standard Haar wavelets on cube-map faces (Ng, Ramamoorthi and Hanrahan 2003, as used
for lighting and transport by Raghavan et al. 2023 §4 and §5).

Each N x N face (N a power of two) is decomposed independently by the *non-standard* 2D Haar
transform: every step replaces each 2 x 2 block (a b / c d) of the current average image by its
orthonormal average (a + b + c + d) / 2 and three details

    H = (a - b + c - d) / 2    (varies along columns)
    V = (a + b - c - d) / 2    (varies along rows)
    D = (a - b - c + d) / 2

and recurses on the averages until one scaling coefficient is left. The basis is orthonormal in
the Euclidean inner product over texels (Gram matrix = I, Parseval holds). Coefficients are
stored per face in the Mallat layout: the scaling coefficient at (0, 0) and, for level l
(detail resolution r = 2^l, l = 0 coarsest ... log2(N) - 1 finest), band H at rows [0, r) x
columns [r, 2r), V at [r, 2r) x [0, r), D at [r, 2r) x [r, 2r). That 2D position is the
"wavelet index as a 2D vector on a cubemap" of Raghavan et al. §4, and one flat index over the
whole cube map is ``face * N^2 + row * N + column``.

Lighting with solid-angle premultiplication (``premultiply=True``) makes the wavelet dot product
sum_k L_k T_k equal the quadrature sum_texels L T dω; Raghavan et al. §5 train *without* it.
"""

from __future__ import annotations

from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jprt.sphere.cubemap import texel_solid_angles

__all__ = [
    "BAND_SCALING", "BAND_H", "BAND_V", "BAND_D",
    "forward",
    "inverse",
    "WaveletIndex",
    "flat_index",
    "unflatten_index",
    "support_area",
    "top_k",
    "retained_energy",
    "basis_function",
]

BAND_SCALING, BAND_H, BAND_V, BAND_D = 0, 1, 2, 3


def check_face_size(n: int) -> int:
    """The number of Haar levels log2(n) of a cube-map face size n; ValueError unless n is a power of two.

    Numerics: not differentiable (an integer check).
    """
    levels = int(np.log2(n))
    if n < 1 or 2**levels != n:
        raise ValueError(f"Haar face size must be a power of two, got {n}")
    return levels


def _to_face_last(x):
    """(6, N, N, *C) -> (*C, 6, N, N) so the transform works on the last two axes."""
    x = jnp.asarray(x)
    if x.ndim < 3 or x.shape[0] != 6 or x.shape[1] != x.shape[2]:
        raise ValueError(f"expected a cube map of shape (6, N, N, ...), got {x.shape}")
    return jnp.moveaxis(x, (0, 1, 2), (-3, -2, -1))


def _from_face_last(x):
    return jnp.moveaxis(x, (-3, -2, -1), (0, 1, 2))


@partial(jax.jit, static_argnames=("premultiply",))
def forward(cubemap, *, premultiply: bool = False):
    """Non-standard Haar transform of every face of a (6, N, N, ...) cube map (Mallat layout).

    With ``premultiply`` the map is multiplied by the texel solid angles first.

    Numerics:
        cubemap: (6, 4, 4, 3) in [-1e5, 1e5]
        float32: value rtol 1e-6 atol 1e-1; grad rtol 1e-6 atol 1e-6
        (sums of 16 terms to 1e5 of both signs: rounding is absolute near zero)
    """
    cubemap = jnp.asarray(cubemap)
    n = cubemap.shape[1]
    levels = check_face_size(n)
    if premultiply:
        cubemap = cubemap * texel_solid_angles(n).reshape((6, n, n) + (1,) * (cubemap.ndim - 3))
    a = _to_face_last(cubemap)
    out = jnp.zeros_like(a)
    size = n
    for _ in range(levels):
        x00, x01 = a[..., 0::2, 0::2], a[..., 0::2, 1::2]
        x10, x11 = a[..., 1::2, 0::2], a[..., 1::2, 1::2]
        r = size // 2
        out = out.at[..., :r, r:size].set(0.5 * (x00 - x01 + x10 - x11))
        out = out.at[..., r:size, :r].set(0.5 * (x00 + x01 - x10 - x11))
        out = out.at[..., r:size, r:size].set(0.5 * (x00 - x01 - x10 + x11))
        a = 0.5 * (x00 + x01 + x10 + x11)
        size = r
    out = out.at[..., :1, :1].set(a)
    return _from_face_last(out)


@partial(jax.jit, static_argnames=("premultiplied",))
def inverse(coeffs, *, premultiplied: bool = False):
    """Inverse of ``forward`` (divides by the texel solid angles if ``premultiplied``).

    Numerics:
        coeffs: (6, 4, 4, 3) in [-1e5, 1e5]
        float32: value rtol 1e-6 atol 1e-1; grad rtol 1e-6 atol 1e-6
        (sums of terms to 1e5 of both signs: rounding is absolute near zero)
    """
    coeffs = jnp.asarray(coeffs)
    n = coeffs.shape[1]
    levels = check_face_size(n)
    c = _to_face_last(coeffs)
    a = c[..., :1, :1]
    r = 1
    for _ in range(levels):
        h = c[..., :r, r:2 * r]
        v = c[..., r:2 * r, :r]
        d = c[..., r:2 * r, r:2 * r]
        x00 = 0.5 * (a + h + v + d)
        x01 = 0.5 * (a - h + v - d)
        x10 = 0.5 * (a + h - v - d)
        x11 = 0.5 * (a - h - v + d)
        top = jnp.stack([x00, x01], axis=-1).reshape(x00.shape[:-1] + (2 * r,))
        bottom = jnp.stack([x10, x11], axis=-1).reshape(x10.shape[:-1] + (2 * r,))
        a = jnp.stack([top, bottom], axis=-2).reshape(top.shape[:-2] + (2 * r, 2 * r))
        r *= 2
    out = _from_face_last(a)
    if premultiplied:
        out = out / texel_solid_angles(n).reshape((6, n, n) + (1,) * (out.ndim - 3))
    return out


class WaveletIndex(NamedTuple):
    """A cube-map wavelet: face, level (0 coarsest), band (0 scaling, 1 H, 2 V, 3 D), position (i, j)
    inside the level's r x r block (r = 2^level)."""

    face: jax.Array
    level: jax.Array
    band: jax.Array
    i: jax.Array
    j: jax.Array


def flat_index(face, level, band, i, j, n: int):
    """Flat index over the whole cube map of (face, level, band, i, j) for face size ``n``.

    Numerics: not differentiable (integer indices).
    """
    check_face_size(n)
    face, level, band, i, j = (jnp.asarray(t, jnp.int32) for t in (face, level, band, i, j))
    r = jnp.left_shift(1, level)
    row = jnp.where(band == BAND_SCALING, 0, jnp.where(band == BAND_H, i, r + i))
    col = jnp.where(band == BAND_SCALING, 0, jnp.where(band == BAND_V, j, r + j))
    return face * n * n + row * n + col


def unflatten_index(index, n: int) -> WaveletIndex:
    """Inverse of ``flat_index``.

    Numerics: not differentiable (integer indices).
    """
    check_face_size(n)
    index = jnp.asarray(index, jnp.int32)
    face = index // (n * n)
    rem = index % (n * n)
    row, col = rem // n, rem % n
    m = jnp.maximum(row, col)
    # level = floor(log2(max(row, col))) via the bit length; exact for integers.
    level = jnp.where(m == 0, 0, 31 - jax.lax.clz(jnp.maximum(m, 1)).astype(jnp.int32))
    r = jnp.left_shift(1, level)
    band = jnp.where(m == 0, BAND_SCALING, jnp.where(row < r, BAND_H, jnp.where(col < r, BAND_V, BAND_D)))
    i = jnp.where(band == BAND_SCALING, 0, jnp.where(band == BAND_H, row, row - r))
    j = jnp.where(band == BAND_SCALING, 0, jnp.where(band == BAND_V, col, col - r))
    return WaveletIndex(face, level, band, i, j)


def support_area(n: int):
    """(6, n, n) support size, as a fraction of one face, of each coefficient in Mallat layout.

    Numerics: not differentiable (a function of the integer face size).
    """
    check_face_size(n)
    rows = np.arange(n)
    m = np.maximum(rows[:, None], rows[None, :])
    level = np.where(m == 0, 0, np.floor(np.log2(np.maximum(m, 1))).astype(int))
    area = 1.0 / 4.0**level  # a level-l wavelet covers a (n / 2^l)^2 block of the face
    return jnp.asarray(np.broadcast_to(area, (6, n, n)).copy(), jnp.float32)


def _magnitude(coeffs):
    """|c| per coefficient, the Euclidean norm over any channel axes: (6, N, N)."""
    c = jnp.asarray(coeffs)
    return jnp.sqrt(jnp.sum(jnp.square(c.reshape(c.shape[:3] + (-1,))), axis=-1))


@partial(jax.jit, static_argnames=("k", "area_weighted"))
def top_k(coeffs, k: int, *, area_weighted: bool = False):
    """The ``k`` most important coefficients of a (6, N, N, ...) coefficient cube map.

    Importance is |c| (Euclidean norm over channels), or with ``area_weighted`` |c| times the
    area of the wavelet's support (Ng et al. 2003's area-weighted selection, which resolves the
    low-frequency colour first; Raghavan et al. 2023, §6). Returns (flat indices (k,) int32,
    values (k, ...)), largest first.

    Numerics:
        coeffs: (6, 4, 4, 3) in [-1e5, 1e5]
        k: = 8
        fd: off (the selected set changes where magnitudes tie, and drawn coefficients often repeat)
        float32: value rtol 0 atol 0; grad rtol 0 atol 0
        (a selection: the values are gathered, exact, once float32 and float64 select the same set,
          which the drawn float32-exact inputs guarantee up to the norm's rounding)
    """
    c = jnp.asarray(coeffs)
    n = c.shape[1]
    importance = _magnitude(c)
    if area_weighted:
        importance = importance * support_area(n)
    _, idx = jax.lax.top_k(importance.reshape(-1), k)
    values = c.reshape((6 * n * n,) + c.shape[3:])[idx]
    return idx.astype(jnp.int32), values


def retained_energy(coeffs, k: int):
    """Fraction of sum(c^2) kept by the ``k`` largest-magnitude coefficients.

    Numerics:
        coeffs: (6, 4, 4, 3) in [-1e5, 1e5]
        k: = 8
        fd: off (the top-k set changes where magnitudes tie, and drawn coefficients often repeat)
        float32: value rtol 1e-5 atol 0; grad rtol 1e-5 atol 1e-12
        (gradient entries are 2 c (kept - E) / sum c^2: rounding near 0 is ~1e-7 of 2 |c| / sum c^2)
    """
    c = jnp.asarray(coeffs)
    _, values = top_k(c, k)
    return jnp.sum(jnp.square(values)) / jnp.sum(jnp.square(c))


def basis_function(index: int, n: int):
    """The (6, n, n) cube map of the basis function with flat index ``index``.

    Numerics: not differentiable (a function of integer indices).
    """
    onehot = jnp.zeros(6 * n * n, jnp.float32).at[index].set(1.0).reshape(6, n, n)
    return inverse(onehot)
