"""Real spherical harmonics: evaluation to any degree, projection, irradiance, network encodings,
and the quadratic-to-hemispherical-linear mapping (OHLSH) of Loos et al. 2011, Appendix B.

Convention: real SH without the Condon-Shortley phase (as in Sloan's "Stupid SH tricks"), polar
axis +Z of the direction vector, flat index k = l^2 + l + m:

    Y_l^0  = K_l^0 P_l^0(z)
    Y_l^m  = sqrt(2) K_l^m P_l^m(z) cos(m phi)      m > 0
    Y_l^-m = sqrt(2) K_l^m P_l^m(z) sin(m phi)      m > 0

Evaluation uses the fully normalised associated-Legendre recurrences (stable to high degree; no
factorials) on the polynomial form: sin^m(theta) cos(m phi) = Re((x + i y)^m), so there is no
atan2 and gradients stay finite at the poles.
"""

from __future__ import annotations

import math
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from jprt.sphere import cubemap as _cubemap

__all__ = [
    "num_coeffs",
    "index",
    "evaluate",
    "project",
    "project_cubemap",
    "project_equirect",
    "reconstruct",
    "clamped_cosine_coeffs",
    "irradiance",
    "encode",
    "ohlsh",
    "OHLSH_C1",
    "OHLSH_C2",
    "OHLSH_C3",
]


def num_coeffs(degree: int) -> int:
    """Number of real SH functions of degree <= ``degree``: (degree + 1)^2.

    Numerics: not differentiable (an integer count).
    """
    return (degree + 1) ** 2


def index(l: int, m: int) -> int:
    """Flat index l^2 + l + m.

    Numerics: not differentiable (an integer index).
    """
    return l * l + l + m


def _recurrence_tables(degree: int):
    """Per (l, m) constants of the normalised recurrences, as (L + 1, L + 1) NumPy arrays."""
    size = degree + 1
    diag = np.zeros(size)
    diag[0] = 1.0 / math.sqrt(4.0 * math.pi)
    for m in range(1, size):
        diag[m] = math.sqrt((2.0 * m + 1.0) / (2.0 * m)) * diag[m - 1]
    a = np.zeros((size, size))
    b = np.zeros((size, size))
    for l in range(size):
        for m in range(l - 1):  # m <= l - 2
            a[l, m] = math.sqrt((4.0 * l * l - 1.0) / (l * l - m * m))
            b[l, m] = math.sqrt(((l - 1.0) ** 2 - m * m) / (4.0 * (l - 1.0) ** 2 - 1.0))
    return diag, a, b


@partial(jax.jit, static_argnames=("degree",))
def evaluate(d, degree: int):
    """Real SH Y_k(d), k < (degree + 1)^2, of unit directions d (..., 3) -> (..., (degree + 1)^2).

    Numerics:
        d: (32, 3) unit
        degree: = 4
        float32: value rtol 1e-5 atol 1e-6; grad rtol 1e-4 atol 1e-5
    """
    if degree < 0:
        raise ValueError(f"degree must be >= 0, got {degree}")
    d = jnp.asarray(d)
    if d.shape[-1] != 3:
        raise ValueError(f"directions must have a last axis of 3, got shape {d.shape}")
    x, y, z = d[..., 0:1], d[..., 1:2], d[..., 2:3]
    size = degree + 1
    diag, a, b = _recurrence_tables(degree)
    ms = np.arange(size)
    # Row l of Q = K_l^m P_l^m(z) / sin^m(theta) for all m at once (0 where m > l):
    #   Q[m, m] = diag[m];  Q[m + 1, m] = sqrt(2m + 3) z Q[m, m];
    #   Q[l, m] = a_lm (z Q[l - 1, m] - b_lm Q[l - 2, m])  for m <= l - 2.
    zeros = jnp.zeros(z.shape[:-1] + (size,), d.dtype)

    def per_m(table):  # an (L + 1,) table over m, explicitly broadcast against the batch
        return jnp.broadcast_to(jnp.asarray(table, d.dtype), zeros.shape)

    rows = []
    prev2, prev1 = zeros, zeros
    for l in range(size):
        row = per_m(a[l]) * (z * prev1 - per_m(b[l]) * prev2)
        row = jnp.where(per_m(ms == l) > 0, per_m(diag), row)
        if l >= 1:
            row = jnp.where(per_m(ms == l - 1) > 0, per_m(np.sqrt(2.0 * ms + 3.0) * diag) * z, row)
        rows.append(row)
        prev2, prev1 = prev1, row
    q = jnp.stack(rows, axis=-2)  # (..., L + 1 [l], L + 1 [m])
    # cos(m phi) sin^m(theta) = Re((x + i y)^m), sin(m phi) sin^m(theta) = Im((x + i y)^m).
    cos_m, sin_m = [jnp.ones_like(x)], [jnp.zeros_like(x)]
    for _ in range(degree):
        c, s = cos_m[-1], sin_m[-1]
        cos_m.append(c * x - s * y)
        sin_m.append(c * y + s * x)
    # Y_lm = scale_m Q[l, |m|] (cos or sin)(|m| phi) sin^|m|(theta), in k = l^2 + l + m order, band
    # by band from static slices (an index array would compile to gathers, slow on a CPU; one
    # column at a time, to a program that grows as the degree squared)
    cos_all, sin_all = jnp.concatenate(cos_m, axis=-1), jnp.concatenate(sin_m, axis=-1)  # (..., L + 1)
    root2 = jnp.asarray(math.sqrt(2.0), d.dtype)
    bands = []
    for l in range(size):
        row = q[..., l, :]
        if l:
            bands.append(jnp.flip(row[..., 1:l + 1] * sin_all[..., 1:l + 1], axis=-1) * root2)  # m = -l .. -1
        bands.append(row[..., :1] * cos_all[..., :1])  # m = 0
        if l:
            bands.append(row[..., 1:l + 1] * cos_all[..., 1:l + 1] * root2)  # m = 1 .. l
    return jnp.concatenate(bands, axis=-1)


def project(values, directions, weights, degree: int):
    """SH coefficients ((degree + 1)^2, ...) of samples by quadrature sum_i w_i f(d_i) Y(d_i).

    values (N, ...), directions (N, 3), weights (N,) (solid angles of the samples).

    Numerics:
        values: (32, 3) in [-1e5, 1e5]
        directions: (32, 3) unit
        weights: (32,) in [0, 1]
        degree: = 4
        float32: value rtol 1e-5 atol 2; grad rtol 1e-5 atol 1e-2
        (a quadrature sum of 32 terms up to 1e5 in size: float32 rounding is absolute, ~1e-7 of the
          sum of |terms| <= 3.2e6, so near-zero coefficients get the absolute bound)
    """
    y = evaluate(directions, degree) * jnp.asarray(weights)[:, None]
    return jnp.tensordot(y, jnp.asarray(values), axes=([0], [0]))


def project_cubemap(cube, degree: int):
    """SH coefficients of a (6, n, n, ...) cube map with exact texel solid angles.

    Numerics:
        cube: (6, 2, 2, 3) in [-1e5, 1e5]
        degree: = 2
        float32: value rtol 1e-5 atol 2; grad rtol 1e-5 atol 1e-6
        (a sum of 24 terms up to 1e5 x 0.5: absolute rounding, as ``project``)
    """
    cube = jnp.asarray(cube)
    n = cube.shape[1]
    d = _cubemap.texel_directions(n).reshape(-1, 3)
    w = _cubemap.texel_solid_angles(n).reshape(-1)
    return project(cube.reshape((6 * n * n,) + cube.shape[3:]), d, w, degree)


def project_equirect(equirect, degree: int):
    """SH coefficients of an (H, W, ...) jprt equirect map with exact texel solid angles.

    Note the polar axis of the SH is +Z while the equirect's is +Y: the map is projected as the
    function of direction it is, in one world frame.

    Numerics:
        equirect: (4, 8, 3) in [-1e5, 1e5]
        degree: = 2
        float32: value rtol 1e-5 atol 2; grad rtol 1e-5 atol 1e-6
        (a sum of 32 terms up to 1e5 x 0.5: absolute rounding, as ``project``)
    """
    equirect = jnp.asarray(equirect)
    h, w = equirect.shape[:2]
    d = _cubemap.equirect_directions(h, w).reshape(-1, 3)
    sa = _cubemap.equirect_solid_angles(h, w).reshape(-1)
    return project(equirect.reshape((h * w,) + equirect.shape[2:]), d, sa, degree)


def reconstruct(coeffs, d):
    """Evaluate sum_k c_k Y_k(d) for coefficients ((degree + 1)^2, ...) at directions (..., 3).

    Numerics:
        coeffs: (25, 3) in [-1e3, 1e3]
        d: (32, 3) unit
        float32: value rtol 1e-5 atol 2e-2; grad rtol 1e-4 atol 2e-1
        (a sum of 25 terms up to 1e3 x 1.5: absolute rounding near zero)
    """
    coeffs = jnp.asarray(coeffs)
    degree = int(round(math.sqrt(coeffs.shape[0]))) - 1
    if num_coeffs(degree) != coeffs.shape[0]:
        raise ValueError(f"{coeffs.shape[0]} is not a square number of SH coefficients")
    return jnp.tensordot(evaluate(d, degree), coeffs, axes=([-1], [0]))


def clamped_cosine_coeffs(degree: int) -> np.ndarray:
    """A_l of the clamped cosine max(cos theta, 0) convolution (Ramamoorthi and Hanrahan 2001,
    Eq. 8-9): E_lm = A_l L_lm with A_0 = pi, A_1 = 2 pi / 3, A_l = 0 for odd l > 1 and
    A_l = 2 pi (-1)^(l/2 - 1) / ((l + 2)(l - 1)) * l! / (2^l ((l/2)!)^2) for even l.

    Numerics: not differentiable (a constant table).
    """
    out = np.zeros(degree + 1)
    for l in range(degree + 1):
        if l == 0:
            out[l] = math.pi
        elif l == 1:
            out[l] = 2.0 * math.pi / 3.0
        elif l % 2 == 0:
            out[l] = (2.0 * math.pi * (-1) ** (l // 2 - 1) / ((l + 2) * (l - 1))
                      * math.factorial(l) / (2**l * math.factorial(l // 2) ** 2))
    return out


def irradiance(coeffs, normals):
    """Irradiance E(n) = sum_lm A_l L_lm Y_lm(n) of radiance SH coefficients at normals (..., 3).

    Numerics:
        coeffs: (9, 3) in [-1e3, 1e3]
        normals: (32, 3) unit
        float32: value rtol 1e-5 atol 2e-2; grad rtol 1e-4 atol 2e-1
        (a sum of 9 terms up to 1e3 x 3: absolute rounding near zero)
    """
    coeffs = jnp.asarray(coeffs)
    degree = int(round(math.sqrt(coeffs.shape[0]))) - 1
    a = clamped_cosine_coeffs(degree)
    per_k = np.concatenate([np.full(2 * l + 1, a[l]) for l in range(degree + 1)])
    scaled = coeffs * jnp.asarray(per_k, coeffs.dtype).reshape((-1,) + (1,) * (coeffs.ndim - 1))
    return reconstruct(scaled, normals)


def encode(d, bands: int = 4):
    """SH encoding of directions for network inputs: the first ``bands``^2 real SH (bands = 4
    gives degrees 0..3, 16 features: tiny-cuda-nn's "SphericalHarmonics, degree 4", the SH4(w_r)
    of Raghavan et al. 2023 §4). ``bands`` up to 5 (degree 4).

    Numerics:
        d: (32, 3) unit
        bands: = 4
        float32: value rtol 1e-5 atol 1e-6; grad rtol 1e-4 atol 1e-5
    """
    if not 1 <= bands <= 5:
        raise ValueError(f"SH encoding supports 1..5 bands, got {bands}")
    return evaluate(d, bands - 1)


# Loos et al. 2011, Appendix B.
OHLSH_C1 = 3.0 * math.sqrt(5.0) / 4.0
OHLSH_C2 = 3.0 * math.sqrt(5.0) / 8.0
OHLSH_C3 = math.sqrt(15.0) / 2.0


def ohlsh(b):
    """Optimal hemispherical linear SH (Loos et al. 2011, Appendix B): the 4 linear coefficients
    a minimising int_{z >= 0} (L2 - L1)^2 for quadratic coefficients b (9, ...):

        a = H1^-1 H2 b = (b1 - c1 b7, b2 + c2 b6, b3 + c3 b7, b4 + c2 b8)

    with 1-based indices in the order l = 0; l = 1 (m = -1, 0, 1); l = 2 (m = -2 .. 2), c1 =
    3 sqrt(5) / 4, c2 = 3 sqrt(5) / 8, c3 = sqrt(15) / 2, for the hemisphere about +Z.

    Numerics:
        b: (9, 8) in [-1e5, 1e5]
        float32: value rtol 1e-6 atol 5e-2; grad rtol 1e-6 atol 1e-6
        (a difference of two terms up to 1e5 x 3.4: rounding is absolute near zero)
    """
    b = jnp.asarray(b)
    if b.shape[0] != 9:
        raise ValueError(f"OHLSH maps 9 quadratic SH coefficients, got {b.shape[0]}")
    return jnp.stack([b[0] - OHLSH_C1 * b[6], b[1] + OHLSH_C2 * b[5], b[2] + OHLSH_C3 * b[6], b[3] + OHLSH_C2 * b[7]])
