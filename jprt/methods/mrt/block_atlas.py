"""The padded lightmap atlas of a block layout (Loos et al. 2011, §6.2, §7.2, §7.3 step 6).

Every face of every block is a t x t tile of texels; the atlas lays the tiles out in rows, each
with a one-texel gutter that repeats its edge, so a bilinear lookup never reads across tiles
(``atlas_layout``). A scene that is not itself a block layout reaches the atlas through a coarse
block proxy (§7.2): ``proxy_uv`` maps its surface points to a block face and a point on it.
``atlas_gbuffer_inputs`` is the atlas seen as an image (every texel at its own centre).

Per-texel arrays are (B, 6 t^2, ...): blocks, then the six faces' texels (``texels_of``).
"""

from __future__ import annotations

import numpy as np

from jprt import layouts
from jprt.inputs import GBuffer
from jprt.methods.lightmap_lookup import atlas_inputs

__all__ = ["texels_of", "atlas_layout", "proxy_uv", "atlas_gbuffer_inputs"]


def texels_of(albedo: np.ndarray) -> tuple[int, int]:
    """(blocks B, texels per face side n) of a per-texel array (B, 6 n^2, ...).

    Numerics: not differentiable (integer sizes).
    """
    b, n = albedo.shape[:2]
    return b, int(round(np.sqrt(n // 6)))


def atlas_layout(n_blocks: int, t: int) -> tuple[int, np.ndarray, np.ndarray]:
    """The padded lightmap atlas (§6.2, §7.3 step 6): each block face a (t + 2)^2 tile whose
    one-texel gutter repeats its edge. Returns (resolution R, texel_index (B n,) atlas pixel of
    each texel, fill_index (R^2,) texel each pixel shows).

    Numerics: not differentiable (integer atlas layout).
    """
    tiles = n_blocks * 6
    per_row = int(np.ceil(np.sqrt(tiles)))
    tile = t + 2
    res = per_row * tile
    fill = np.zeros((res, res), np.int64)
    texel_index = np.zeros(tiles * t * t, np.int64)
    jj, ii = np.meshgrid(np.arange(tile), np.arange(tile), indexing="ij")
    src = np.clip(jj - 1, 0, t - 1) * t + np.clip(ii - 1, 0, t - 1)
    for k in range(tiles):
        r0, c0 = (k // per_row) * tile, (k % per_row) * tile
        fill[r0:r0 + tile, c0:c0 + tile] = k * t * t + src
        inner = np.arange(t * t)
        texel_index[k * t * t + inner] = (r0 + 1 + inner // t) * res + c0 + 1 + inner % t
    return res, texel_index, fill.reshape(-1)


def proxy_uv(position, normal, layout, origin, size: float, t: int) -> tuple[np.ndarray, np.ndarray]:
    """Lightmap-atlas UVs (..., 2) and validity (...) of surface points of a scene mapped to its
    block proxy (§7.2): the cell that holds the point (nudged along its normal into the room),
    the face of that block whose inward normal is closest to the point's normal (so a box top is
    lit like a floor, a box side like the wall facing the same way; the paper picks the face by
    the direction from the block's centre), and the point's orthographic projection onto it.

    Numerics: not differentiable (atlas coordinates of scene points in NumPy).
    """
    lay = layouts.layout_from_dict(layout)
    p = np.asarray(position, np.float64)
    n = np.asarray(normal, np.float64)
    q = (p - np.asarray(origin, np.float64)) / float(size) + 1e-4 * n
    ci, cj = np.floor(q[..., 0]).astype(int), np.floor(q[..., 2]).astype(int)
    index = {c: k for k, c in enumerate(lay.cells)}
    if len(lay.cells) == 1:  # one block: everything maps to it (clamped)
        ci, cj = np.full_like(ci, lay.cells[0][0]), np.full_like(cj, lay.cells[0][1])
    block = np.vectorize(lambda i, j: index.get((int(i), int(j)), -1), otypes=[int])(ci, cj) if ci.size else ci
    local = np.clip(q - np.stack([ci, np.zeros_like(ci), cj], -1), 0.0, 1.0)
    face = np.argmax(n @ layouts.FACE_NORMALS.T, axis=-1)
    rel = local - layouts.FACE_ORIGINS[face]
    u = np.clip(np.sum(rel * layouts.FACE_U[face], -1), 0.0, 1.0)
    v = np.clip(np.sum(rel * layouts.FACE_V[face], -1), 0.0, 1.0)
    res, _, _ = atlas_layout(len(lay.cells), t)
    per_row = res // (t + 2)
    tile = np.maximum(block, 0) * 6 + face
    uv = np.stack([((tile % per_row) * (t + 2) + 1 + u * t) / res, ((tile // per_row) * (t + 2) + 1 + v * t) / res], -1)
    present = np.stack([np.asarray(b) for b in _present_faces(lay)])[np.maximum(block, 0), face]
    return uv.astype(np.float32), (block >= 0) & present


def _present_faces(lay: layouts.Layout) -> list:
    """Per block, whether each of its six faces exists (floor, ceiling, then the four sides:
    a side open to a neighbour or the exterior has no face)."""
    return [[True, True] + [k not in b.open_sides for k in range(4)] for b in lay.blocks]


def atlas_gbuffer_inputs(albedo) -> GBuffer:
    """The G-buffer of the padded atlas: every texel's own centre, with its albedo; gutters and
    missing faces invalid. The evaluator given it returns the texels as an (R, R, 3) image.

    Numerics: not differentiable (builds a G-buffer).
    """
    alb = np.asarray(albedo, np.float32)
    b, t = texels_of(alb)
    res, texel_index, _ = atlas_layout(b, t)
    g = atlas_inputs(res, texel_index)
    img = np.zeros((res * res, 3), np.float32)
    img[texel_index] = alb.reshape(-1, 3)
    present = np.zeros(res * res, bool)
    present[texel_index] = np.any(alb.reshape(-1, 3) > 0, axis=-1)
    return g._replace(diffuse_albedo=img.reshape(res, res, 3), valid=present.reshape(res, res))
