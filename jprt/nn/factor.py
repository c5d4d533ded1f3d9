"""The CP-factored feature field of Raghavan et al. 2023, Eq. 6-7.

    h_k(x) = sum_m S_m[x] W_m[k] U_m            (Eq. 7)

S is a 3D multiresolution hash grid with M outputs (M = levels x features per level), W a cube-map
grid of shape (6, R, R, M) indexed by the wavelet's 2D position k on the cube map after the
non-standard Haar decomposition (``jprt.sphere.haar``'s flat index face * R^2 + row * R + col),
and U an M x L matrix (a bias-free linear layer). The paper uses M = L = 64 and R = 64.

``apply(params, x, k)`` evaluates a batch of points x (B, 3) in [0, 1]^3 against a set of K
wavelet indices k (K,) and returns (B, K, L). The contraction is
h = (S[x] (B, M)) * (W[k] (K, M)) @ U, formed as one einsum over m, so nothing larger than
(B, K, max(M, L)) is materialised; ``chunk`` bounds it further by evaluating x in chunks.
"""

from __future__ import annotations

from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp

from jprt.nn.hashgrid import hashgrid

__all__ = ["FactorField", "factor_field"]


class FactorField(NamedTuple):
    """``init(key)``, ``apply(params, x (B, 3), k (K,)) -> (B, K, L)``, and ``parts(params, x, k)
    -> (S[x] (B, M), W[k] (K, M))``: the two factors before the contraction with U, for callers
    that fold U into what follows (h_k(x) A = (S[x] * W[k]) (U A) costs 2 M width per (x, k)
    instead of 2 M L + 2 L width)."""

    init: Callable
    apply: Callable
    n_components: int
    n_features: int
    face_size: int
    parts: Callable


def factor_field(*, face_size: int = 64, n_features: int = 64, n_levels: int = 32, features_per_level: int = 2,
                 log2_table_size: int = 19, base_resolution: int = 16, per_level_scale: float = 1.3,
                 chunk: int | None = None, w_init: float = 1.0, dtype=jnp.float32) -> FactorField:
    """Factored field with S = hash grid (n_levels x features_per_level = M components), W over a
    6 x face_size^2 cube map (initialised N(0, w_init^2)), U (M x n_features). Defaults are the
    paper's (§5).

    Numerics:
        case: factor_field (face size 4, 8 features, 4 x 2 hash-grid components, as ``init`` draws
          them, points in [0, 1]^3, every wavelet index; gradients w.r.t. S, W, U)
        fd: off (the hash grid's trilinear interpolation has kinks on cell faces)
        float32: value rtol 1e-4 atol 1e-9; grad rtol 1e-4 atol 1e-5
        (a table entry's gradient sums 96 wavelets x 16 points of both signs: its rounding is
          ~1e-7 of the sum of |terms|, ~1e2 here)
    """
    grid = hashgrid(n_levels=n_levels, n_features=features_per_level, log2_table_size=log2_table_size,
                    base_resolution=base_resolution, per_level_scale=per_level_scale, dtype=dtype)
    m = grid.n_outputs
    n_wavelets = 6 * face_size * face_size

    def init(key):
        ks, kw, ku = jax.random.split(key, 3)
        limit = (6.0 / (m + n_features)) ** 0.5
        return {
            "S": grid.init(ks),
            "W": w_init * jax.random.normal(kw, (n_wavelets, m), dtype),
            "U": jax.random.uniform(ku, (m, n_features), dtype, -limit, limit),
        }

    def parts(params, x, k):
        return grid.apply(params["S"], x), params["W"][jnp.asarray(k, jnp.int32)]  # (B, M), (K, M)

    def contract(params, x, k):
        s, w = parts(params, x, k)
        return jnp.einsum("bm,km,ml->bkl", s, w, params["U"])

    def apply(params, x, k):
        x = jnp.asarray(x)
        k = jnp.asarray(k, jnp.int32)
        if x.ndim != 2 or x.shape[-1] != 3 or k.ndim != 1:
            raise ValueError(f"factor field expects x (B, 3) and k (K,), got {x.shape} and {k.shape}")
        if chunk is None or x.shape[0] <= chunk:
            return contract(params, x, k)
        pad = (-x.shape[0]) % chunk
        xs = jnp.pad(x, ((0, pad), (0, 0))).reshape(-1, chunk, 3)
        out = jax.lax.map(lambda xc: contract(params, xc, k), xs)
        return out.reshape((-1,) + out.shape[2:])[: x.shape[0]]

    return FactorField(init, apply, m, n_features, face_size, parts)
