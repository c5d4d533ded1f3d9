"""Multiresolution hash encoding (Müller et al. 2022) to the tiny-cuda-nn specification.

Level l (0-based) of L levels has

    scale_l = 2^(l log2 b) N_min - 1,    res_l = ceil(scale_l) + 1

and min(next_multiple(res_l^3, 8), T) table entries of F features each (tiny-cuda-nn
``encodings/grid.h``). A point x in [0, 1]^3 sits at pos = x scale_l + 0.5; the 8 corners of its
cell are looked up densely (index = i + j res + k res^2) while res_l^3 fits in the table and by
the spatial hash (i * 1) xor (j * 2654435761) xor (k * 805459861) (uint32) otherwise, both modulo
the table size, and blended trilinearly. Tables start uniform in [-1e-4, 1e-4].
The output is the concatenation of the L levels' F features.
"""

from __future__ import annotations

import math
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["HashGrid", "hashgrid", "level_scales", "level_resolutions", "level_table_sizes", "PRIMES"]

PRIMES = (1, 2654435761, 805459861)


class HashGrid(NamedTuple):
    """``init(key) -> params`` ({"tables": [(entries_l, F), ...]}), ``apply(params, x) -> (..., L F)``."""

    init: Callable
    apply: Callable
    n_outputs: int
    table_sizes: tuple[int, ...]


def level_scales(n_levels: int, base_resolution: int, per_level_scale: float) -> list[float]:
    """scale_l = 2^(l log2 b) N_min - 1 (float32 arithmetic, as tiny-cuda-nn).

    Numerics: not differentiable (a configuration table).
    """
    log2b = np.float32(math.log2(per_level_scale))
    return [float(np.float32(np.exp2(np.float32(l) * log2b) * np.float32(base_resolution) - np.float32(1.0)))
            for l in range(n_levels)]


def level_resolutions(n_levels: int, base_resolution: int, per_level_scale: float) -> list[int]:
    """res_l = ceil(scale_l) + 1.

    Numerics: not differentiable (a configuration table).
    """
    return [int(math.ceil(s)) + 1 for s in level_scales(n_levels, base_resolution, per_level_scale)]


def level_table_sizes(n_levels: int, log2_table_size: int, base_resolution: int, per_level_scale: float,
                      dims: int = 3) -> list[int]:
    """Entries per level: min(next_multiple(res^dims, 8), 2^log2_table_size).

    Numerics: not differentiable (a configuration table).
    """
    max_params = (2**32 - 1) // 2
    sizes = []
    for res in level_resolutions(n_levels, base_resolution, per_level_scale):
        dense = res**dims if float(res) ** dims <= max_params else max_params
        dense = (dense + 7) // 8 * 8
        sizes.append(min(dense, 2**log2_table_size))
    return sizes


def hashgrid(*, n_levels: int = 16, n_features: int = 2, log2_table_size: int = 19, base_resolution: int = 16,
             per_level_scale: float = 1.5, dtype=jnp.float32) -> HashGrid:
    """A 3D multiresolution hash encoding (defaults: the instant-ngp configuration).

    Numerics:
        case: hashgrid (4 levels, tables of 2^8 entries as ``init`` draws them, points in [0, 1]^3;
          gradients w.r.t. the tables and the points)
        fd: off (trilinear interpolation has kinks on cell faces, and the domain's ends lie on them)
        float32: value rtol 1e-5 atol 1e-10; grad rtol 1e-5 atol 1e-6
    """
    if n_levels < 1 or n_features < 1 or base_resolution < 1 or per_level_scale < 1.0:
        raise ValueError("hash grid needs n_levels, n_features, base_resolution >= 1 and per_level_scale >= 1")
    scales = level_scales(n_levels, base_resolution, per_level_scale)
    resolutions = level_resolutions(n_levels, base_resolution, per_level_scale)
    table_sizes = tuple(level_table_sizes(n_levels, log2_table_size, base_resolution, per_level_scale))
    corners = np.array([[(c >> d) & 1 for d in range(3)] for c in range(8)], np.uint32)  # (8, 3)

    def init(key):
        keys = jax.random.split(key, n_levels)
        return {"tables": [jax.random.uniform(k, (size, n_features), dtype, -1e-4, 1e-4)
                           for k, size in zip(keys, table_sizes)]}

    def level_index(grid, res: int, size: int):
        """grid (..., 3) uint32 corner coordinates -> table index (...,) uint32."""
        if res**3 <= size:  # dense: the whole grid fits in the table
            index = grid[..., 0] + grid[..., 1] * np.uint32(res) + grid[..., 2] * np.uint32(res * res)
        else:
            index = (grid[..., 0] * np.uint32(PRIMES[0])) ^ (grid[..., 1] * np.uint32(PRIMES[1])) \
                ^ (grid[..., 2] * np.uint32(PRIMES[2]))
        return index % np.uint32(size)

    def apply(params, x):
        x = jnp.asarray(x)
        if x.shape[-1] != 3:
            raise ValueError(f"hash grid expects 3D points, got shape {x.shape}")
        batch = x.shape[:-1]
        x = x.reshape(-1, 3)
        outputs = []
        for table, scale, res, size in zip(params["tables"], scales, resolutions, table_sizes):
            pos = x * jnp.asarray(scale, x.dtype) + 0.5
            floor = jnp.floor(pos)
            frac = pos - floor
            base = floor.astype(jnp.int32).astype(jnp.uint32)  # x in [0, 1] keeps these >= 0
            feats = jnp.zeros((x.shape[0], n_features), table.dtype)
            for corner in corners:
                grid = base + jnp.asarray(corner)[None, :]
                weight = jnp.prod(jnp.where(jnp.asarray(corner)[None, :] == 1, frac, 1.0 - frac), axis=-1)
                feats = feats + weight[:, None] * table[level_index(grid, res, size)]
            outputs.append(feats)
        return jnp.concatenate(outputs, axis=-1).reshape(batch + (n_levels * n_features,))

    return HashGrid(init, apply, n_levels * n_features, table_sizes)
