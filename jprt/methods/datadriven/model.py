"""Data-driven precomputed radiance transfer (Belcour, Deliot, Barbier, Soler 2022).

Indirect light of an asset is predicted from a few measurements of *direct* light:

* **Measurement points** (§4.1): a blue-noise subset of a dense uniform set of surface samples,
  chosen by weighted sample elimination (Yuksel 2015, ``sample_elimination``). Direct light is
  measured at ``count * supersample`` points and averaged over the points nearest to each of the
  ``count`` coarse points (§5.1 "direct illumination downscaling", ``select_points``).
* **Dataset** (§4.1): N random lighting configurations of one lighting scenario (spot lights by
  default); column k of D is the direct vector x_k at the measurement points, column k of I the
  indirect lightmap of the asset (texels of ``jprt.render.lightmap.Atlas``).
* **Basis** (§3.2, §4.2): every column is divided by the norm of its direct vector (so the
  method works at any light intensity), the mean m is subtracted, and the SVD of the
  mean-subtracted indirect matrix is computed through its N x N Gram matrix (Turk and Pentland
  1991; ``gram_svd``). "n basis elements" means the mean plus n - 1 singular vectors U_n.
* **Transfer** (§3.1-3.2, Eq. 6, 10, 13, 14): M_n = C_n (D^T D + lambda I)^(-1) D^T, with
  C_n = U_n^T (I - m 1^T) the coefficients of the (normalised) dataset. Erratum (papers/README):
  Eq. 13-14 print the P x P Gram matrix D D^T between C_n (n x N) and D^T (N x P), which does not
  type-check with examples as columns; the push-through identity
  (D^T D + lambda I_N)^(-1) D^T = D^T (D D^T + lambda I_P)^(-1) makes both orientations equal for
  lambda > 0, and both tend to the Moore-Penrose pseudo-inverse D^+ as lambda -> 0 (Eq. 13).
  ``ridge_pinv`` computes it from the SVD of D (filter factors s / (s^2 + lambda)), so an
  ill-conditioned D gives a warning with its condition number and a finite result.
* **Runtime** (§4.3): lights -> direct at the fine measurement points (rendered outside JAX,
  e.g. ``jprt.render.lightmap.radiance_at_points``) -> average to x -> u = M_n x ->
  lightmap = m |x| + U_n u -> bilinear lookup through the G-buffer's atlas UV. One jit-compiled
  function (``evaluator``).
* **Mean** (``basis.mean``): the paper scales the stored mean by |x| at run time (``"norm"``).
  That makes the model y = m |x| + U_n M_n x non-linear in x, and a linear M_n must then also
  absorb the constant -U_n^T m of the normalised coefficients, which costs accuracy (measured:
  docs/methods/datadriven.md). ``"linear"`` (the default; not in the paper) keeps the mean as one more
  basis vector whose coefficient is regressed like the others, so y = B_n M_n x is exactly linear.
* **Colour** (§5.2): ``channels="mono"`` treats R, G, B as separate examples of one basis with
  one transfer matrix per channel; ``"multi"`` interleaves the channels in one vector.
* **Gamma space** (§5.3): with ``gamma > 0`` the dataset, the runtime direct vector and the
  reconstruction are mapped by g(v) = sign(v) |v|^(1/gamma) and the lightmap is mapped back.

Contract (``jprt.methods.base``): ``data.make_dataset(scene, config)`` -> ``DDData`` (rendered
once, cached by ``jprt.cache``), ``fit(data, config)`` -> ``FitResult(params, info)``,
``evaluator(params, config)`` -> ``evaluate(gbuffer, PointRadiance)``. This module is the paper's
math in pure JAX/NumPy and imports no Mitsuba; rendering lives in ``data.py``.
"""

from __future__ import annotations

import functools
import heapq
import math
import time
import warnings
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jprt.config import merge
from jprt.inputs import PointRadiance
from jprt.methods.base import FitResult, resolve
from jprt.methods.lightmap_lookup import atlas_inputs, lightmap_shader, modulation_params

__all__ = [
    "DEFAULT_CONFIG",
    "IllConditionedWarning",
    "MeasurementPoints",
    "DDData",
    "sample_elimination",
    "select_points",
    "coarse_direct",
    "gamma_encode",
    "gamma_decode",
    "gram_svd",
    "ridge_pinv",
    "lightmap",
    "reconstruct",
    "transfer_coefficients",
    "measurement_points",
    "example",
    "fit",
    "fit_arrays",
    "cross_validate_lambda",
    "evaluator",
    "project",
    "lightmap_rmse",
    "model_bytes",
]

DEFAULT_CONFIG: dict[str, Any] = {
    # the built-in Cornell box lit by spot lights inside it; lightmap over every object
    "scene": {"name": "cornell_box", "area_light": False},
    "objects": [],  # object names of the asset; [] = every object of the scene
    "lightmap": {"resolution": 64},  # the lightmap atlas's size in texels per side
    "points": {
        "candidates": 4096,  # dense uniform surface samples (also the sample-elimination input)
        # measurement points P (length of the direct vector per channel); direct measured at
        # count * supersample points, averaged to count (§5.1). 1024 x 2 was chosen by held-out
        # error against the projection floor on both benchmark scenes (docs/methods/datadriven.md)
        "count": 1024,
        "supersample": 2,
        "objects": [],  # objects carrying measurement points; [] = the lightmap's objects. An asset lit
        # mostly by bounce light from its surroundings needs points there too (Spot in a room)
        "seed": 0,  # seed of the candidates and the sample elimination
    },
    "lights": {  # the lighting scenario (§4.1): one light per configuration
        "kind": "spot",  # "spot" (the paper's) or "point" (target and cutoff unused)
        # light positions and spot targets uniform in these world-space boxes [x, y, z]
        "position_lo": [-0.8, -0.7, -0.7],
        "position_hi": [0.8, 0.9, 0.9],
        "target_lo": [-0.9, -1.0, -0.9],
        "target_hi": [0.9, 0.3, 0.3],
        "cutoff_deg": [20.0, 50.0],  # the spot's cutoff angle, uniform in this range (degrees)
        "intensity": [1.0, 6.0],  # W/sr on the axis, times a random colour of max channel 1
        "saturation": 0.6,  # 0 = white lights, 1 = fully random colours
        "clearance": 0.3,  # positions inside objects or this close to a surface are redrawn
    },
    "data": {
        "n_train": 256,  # training lighting configurations (one light each)
        "n_test": 32,  # held-out lighting configurations
        "spp": 64,  # path-traced samples per texel of a training lightmap
        "test_spp": 256,  # samples per texel of a held-out reference lightmap
        "seed": 0,  # seed of the lights and the renders
    },
    "basis": {
        "n": 16,  # basis vectors kept (the reduced lightmap space's size)
        "channels": "mono",  # "mono": R, G, B as examples of one basis (§5.2); "multi": one vector of all three
        "gamma": 0.0,  # g(v) = sign(v) |v|^(1 / gamma) applied to the data (§5.3); <= 0: none
        "center": True,  # subtract the mean lightmap before the SVD
        # "norm" = the paper's mean scaled by |x| at run time (§4.2); "linear" (the default) = the
        # mean is one more basis vector with a regressed coefficient, exactly linear in x like the
        # light transport itself (not in the paper; both measured: docs/methods/datadriven.md)
        "mean": "linear",
    },
    # demodulate: the lightmap is fitted to Lambertian texels' light over their texture, and a
    # Lambertian pixel shades the lookup with its own (``lightmap_lookup.remodulated_lookup``): a
    # texture finer than a texel comes from the pixel's material, as engines shade baked lightmaps
    # (the paper's lightmaps sit at the asset's texture resolution); glossy texels keep their light
    "shading": {"demodulate": True},
    "transfer": {
        "lam": 0.1,  # Tikhonov lambda of Eq. 14 on unit-norm direct vectors
        # lambda candidates chosen among by cv_folds-fold cross-validation over the training
        # configurations; [] uses lam
        "lam_cv": [1e-3, 3e-3, 1e-2, 3e-2, 0.1, 0.3, 1.0, 3.0],
        "cv_folds": 4,
        "rcond": 1e-12,  # singular values of the direct vectors below rcond x the largest are dropped
        "warn_condition": 1e7,  # warn when the direct vectors' condition number s_max / s_min exceeds this
    },
}


def _cfg(config: dict | None) -> dict:
    """``DEFAULT_CONFIG`` merged strictly with ``config`` (an unknown key raises ConfigError)."""
    return resolve(DEFAULT_CONFIG, config)


class IllConditionedWarning(RuntimeWarning):
    """The direct matrix D is (numerically) rank deficient; the transfer falls back on the
    regularised pseudo-inverse."""


# --------------------------------------------------------------------------------------------
# Measurement points (§4.1, §5.1)


def sample_elimination(points, n: int, *, area: float | None = None, alpha: float = 8.0, beta: float = 0.65,
                       gamma: float = 1.5) -> np.ndarray:
    """Indices of ``n`` of ``points`` (M, d) with a blue-noise distribution: weighted sample
    elimination (Yuksel 2015, §3-4).

    Every sample i has weight w_i = sum_j (1 - d_ij / (2 r_max))^alpha over neighbours closer than
    2 r_max, with distances below 2 r_min clamped to 2 r_min (weight limiting, §4), where
    r_max = sqrt(A / (2 sqrt(3) n)) is the maximal Poisson-disk radius of n samples on a surface
    of area A (d = 3 points on surfaces; in the plane A is the domain area) and
    r_min = r_max (1 - (n / M)^gamma) beta. The heaviest sample is removed and its neighbours'
    weights updated until n remain. ``area`` defaults to the area of the points' bounding box
    (right for samples of a planar domain, too large for curved surfaces: pass it).

    Numerics: not differentiable (selects point indices).
    """
    from scipy.spatial import cKDTree

    pts = np.asarray(points, np.float64)
    if pts.ndim != 2:
        raise ValueError(f"points must be (M, d), got shape {pts.shape}")
    m = pts.shape[0]
    n = int(n)
    if not 1 <= n <= m:
        raise ValueError(f"cannot keep {n} of {m} samples")
    if n == m:
        return np.arange(m)
    if area is None:
        ext = np.sort(pts.max(0) - pts.min(0))[::-1]
        area = float(ext[0] * ext[1]) if pts.shape[1] >= 2 else float(ext[0])
    if not area > 0:
        raise ValueError(f"area must be positive, got {area}")
    r_max = math.sqrt(area / (2.0 * math.sqrt(3.0) * n))
    r_min = r_max * (1.0 - (n / m) ** gamma) * beta
    tree = cKDTree(pts)
    pairs = tree.query_pairs(2.0 * r_max, output_type="ndarray")
    d = np.linalg.norm(pts[pairs[:, 0]] - pts[pairs[:, 1]], axis=1)
    w = (1.0 - np.maximum(d, 2.0 * r_min) / (2.0 * r_max)) ** alpha
    weight = np.zeros(m)
    np.add.at(weight, pairs[:, 0], w)
    np.add.at(weight, pairs[:, 1], w)
    order = np.argsort(np.concatenate([pairs[:, 0], pairs[:, 1]]), kind="stable")
    nbr = np.concatenate([pairs[:, 1], pairs[:, 0]])[order]
    nbr_w = np.concatenate([w, w])[order]
    start = np.searchsorted(np.concatenate([pairs[:, 0], pairs[:, 1]])[order], np.arange(m + 1))
    alive = np.ones(m, bool)
    heap = [(-weight[i], i) for i in range(m)]
    heapq.heapify(heap)
    remaining = m
    while remaining > n:
        negw, i = heapq.heappop(heap)
        if not alive[i] or -negw != weight[i]:
            continue  # stale entry
        alive[i] = False
        remaining -= 1
        for j, wij in zip(nbr[start[i]:start[i + 1]], nbr_w[start[i]:start[i + 1]]):
            if alive[j]:
                weight[j] -= wij
                heapq.heappush(heap, (-weight[j], int(j)))
    return np.nonzero(alive)[0]


class MeasurementPoints(NamedTuple):
    """Measurement points chosen among candidate surface samples.

    Fields:
      fine_index: (S,) indices into the candidates where direct light is measured.
      group:      (S,) index 0..P-1 of the coarse point each fine point is averaged into.
      counts:     (P,) number of fine points per coarse point (>= 1).
      coarse_index: (P,) candidate index of each coarse point (itself one of the fine points).
    """

    fine_index: np.ndarray
    group: np.ndarray
    counts: np.ndarray
    coarse_index: np.ndarray


def select_points(position, count: int, *, supersample: int = 1, area: float | None = None) -> MeasurementPoints:
    """Blue-noise measurement points and their §5.1 downscaling groups.

    ``count * supersample`` fine points are eliminated from the candidates, ``count`` coarse
    points from the fine ones, and every fine point is averaged into its nearest coarse point
    ("averaging neighboring direct samples when the measurement points are geometrically close").

    Numerics: not differentiable (selects points).
    """
    from scipy.spatial import cKDTree

    position = np.asarray(position, np.float64)
    count, supersample = int(count), int(supersample)
    if count < 1 or supersample < 1:
        raise ValueError(f"points.count and points.supersample must be >= 1, got {count} and {supersample}")
    if count * supersample > position.shape[0]:
        raise ValueError(f"{count} x {supersample} measurement points need at least that many candidates, "
                         f"got {position.shape[0]} (raise points.candidates)")
    fine = sample_elimination(position, count * supersample, area=area)
    coarse_local = sample_elimination(position[fine], count, area=area) if supersample > 1 else np.arange(count)
    _, group = cKDTree(position[fine][coarse_local]).query(position[fine])
    group[coarse_local] = np.arange(count)  # a coarse point always belongs to its own group
    counts = np.bincount(group, minlength=count)
    return MeasurementPoints(fine.astype(np.int32), group.astype(np.int32), counts.astype(np.int32),
                             fine[coarse_local].astype(np.int32))


# --------------------------------------------------------------------------------------------
# Linear algebra (§3, §4.2, §5.3)


def gamma_encode(v, gamma: float):
    """g(v) = sign(v) |v|^(1 / gamma) (§5.3; sign-extended so noisy negative indirect values and
    negative reconstructions survive the round trip). ``gamma <= 0`` is the identity.

    Numerics:
        v: (32,) in [-1e5, 1e5]
        gamma: = 2.2
        fd: off (the slope is infinite at v = 0 for gamma > 1, an end always drawn)
        float32: value rtol 5e-6 atol 0; grad rtol 1e-5 atol 0
        (|v|^(1/gamma) is exp(log|v| / gamma): float32's relative error grows with |log v|, 2.4e-6 at
          float32's smallest normal, 1.2e-38)
    """
    if gamma <= 0:
        return v
    if isinstance(v, jax.Array):
        return _gamma_encode(v, float(gamma))
    return np.sign(v) * np.abs(v) ** (1.0 / gamma)


@functools.partial(jax.custom_jvp, nondiff_argnums=(1,))
def _gamma_encode(v, gamma):
    return jnp.sign(v) * jnp.abs(v) ** (1.0 / gamma)


@_gamma_encode.defjvp
def _gamma_encode_jvp(gamma, primals, tangents):
    # the slope |v|^(1/gamma - 1) / gamma, infinite at v = 0 for gamma > 1: autodiff's
    # sign'(v) |v|^(1/gamma) + sign(v) d|v|^(1/gamma) gave 0 x inf = NaN there; here it is taken at
    # |v| = 1e-30 (1e16 for gamma 2.2: finite, and the same in float32 and float64)
    (v,), (dv,) = primals, tangents
    slope = jnp.maximum(jnp.abs(v), 1e-30) ** (1.0 / gamma - 1.0) / gamma
    return _gamma_encode(v, gamma), slope * dv


def gamma_decode(v, gamma: float):
    """Inverse of ``gamma_encode``: sign(v) |v|^gamma.

    Numerics:
        v: (32,) in [-1e3, 1e3]
        gamma: = 2.2
        float32: value rtol 5e-6 atol 1e-37; grad rtol 1e-5 atol 1e-37
        (as ``gamma_encode``; results below float32's smallest normal, 1.2e-38, flush to 0)
    """
    if gamma <= 0:
        return v
    xp = jnp if isinstance(v, jax.Array) else np
    return xp.sign(v) * xp.abs(v) ** gamma


def gram_svd(a, n: int) -> tuple[np.ndarray, np.ndarray]:
    """The ``n`` leading left singular vectors (rows, n) and singular values (n,) of ``a``
    (rows x N), through the N x N Gram matrix a^T a when rows > N (Turk and Pentland 1991,
    §4.2): a^T a = V S^2 V^T, U = a V S^-1. Singular values below 10 sqrt(eps * max(rows, N))
    s_max (rounding noise of the Gram matrix) are returned as 0 with zero columns (never NaN). With rows <= N it is the thin SVD of ``a`` itself.

    Numerics: not differentiable (a float64 NumPy precomputation).
    """
    a = np.asarray(a, np.float64)
    rows, cols = a.shape
    n = int(n)
    if not 0 <= n <= min(rows, cols):
        raise ValueError(f"cannot take {n} singular vectors of a {rows} x {cols} matrix")
    if rows <= cols:
        u, s, _ = np.linalg.svd(a, full_matrices=False)
        return u[:, :n], s[:n]
    evals, v = np.linalg.eigh(a.T @ a)
    order = np.argsort(evals)[::-1][:n]
    s = np.sqrt(np.maximum(evals[order], 0.0))
    # the Gram matrix squares the condition number: singular values below ~sqrt(eps) s_max are
    # rounding noise of a^T a and are returned as exact zeros (zero singular vectors)
    tol = 10.0 * np.sqrt(np.finfo(np.float64).eps * max(rows, cols)) * (s[0] if s.size else 0.0)
    keep = s > max(tol, 1e-300)
    s = np.where(keep, s, 0.0)
    u = np.zeros((rows, n))
    u[:, keep] = (a @ v[:, order[keep]]) / s[keep]
    # re-orthonormalise (eigh of the Gram matrix squares the condition number)
    if keep.any():
        q, r = np.linalg.qr(u[:, keep])
        u[:, keep] = q * np.sign(np.diag(r))
    return u, s


def ridge_pinv(d, lam: float, *, rcond: float = 1e-12, warn_condition: float = 1e7,
               name: str = "D") -> tuple[np.ndarray, dict]:
    """(D^T D + lam I)^(-1) D^T = D^T (D D^T + lam I)^(-1) for D (P x N), from the SVD of D:
    V diag(s / (s^2 + lam)) U^T (Eq. 14; lam = 0 gives the pseudo-inverse of Eq. 13, with
    singular values below ``rcond * s_max`` dropped). Returns (N x P matrix, info) with the
    condition number s_max / s_min and the numerical rank; warns (``IllConditionedWarning``)
    when the condition number exceeds ``warn_condition``. Always finite.

    Numerics: not differentiable (a float64 NumPy precomputation).
    """
    d = np.asarray(d, np.float64)
    if not np.isfinite(d).all():
        raise ValueError(f"{name} contains NaN or inf")
    return _ridge_from_svd(np.linalg.svd(d, full_matrices=False), float(lam), rcond, warn_condition, name, d.shape)


# --------------------------------------------------------------------------------------------
# Fitting (§3-5)


def _examples(direct: np.ndarray, indirect: np.ndarray, channels: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Columns of D and I: mono -> (P, 3N) and (T, 3N) with channel labels; multi -> (3P, N)
    and (3T, N) with the channels interleaved per point / texel (§5.2)."""
    n = direct.shape[0]
    if channels == "mono":
        x = np.transpose(direct, (1, 2, 0)).reshape(direct.shape[1], 3 * n)  # column c * N + k
        y = np.transpose(indirect, (1, 2, 0)).reshape(indirect.shape[1], 3 * n)
        label = np.repeat(np.arange(3), n)
        return x, y, label
    if channels == "multi":
        return direct.reshape(n, -1).T, indirect.reshape(n, -1).T, np.zeros(n, np.int64)
    raise ValueError(f"basis.channels must be 'mono' or 'multi', got {channels!r}")


def coarse_direct(direct, group, counts):
    """Average fine direct measurements (..., S, 3) into their coarse points (..., P, 3) (§5.1).

    NumPy input is averaged in float64 on the host (fitting, projection); JAX input (the
    evaluator, traced or not) with ``jax.ops.segment_sum`` in its own dtype.

    Numerics:
        case: coarse_direct (16 fine points in 4 groups, direct radiance in [0, 1e5])
        float32: value rtol 1e-6 atol 0; grad rtol 1e-6 atol 0
    """
    if isinstance(direct, jax.Array):
        p = counts.shape[0]
        summed = jax.ops.segment_sum(jnp.moveaxis(direct, -2, 0), group, num_segments=p)
        return jnp.moveaxis(summed, 0, -2) / jnp.expand_dims(counts[:, None].astype(direct.dtype),
                                                             tuple(range(direct.ndim - 2)))
    direct = np.asarray(direct, np.float64)
    out = np.zeros(direct.shape[:-2] + (len(counts), 3))
    np.add.at(out, (Ellipsis, np.asarray(group), slice(None)), direct)
    return out / np.asarray(counts)[:, None]


class _Stage(NamedTuple):
    """Normalised examples and their basis (everything of a fit that does not depend on lambda)."""

    xn: np.ndarray  # (P or 3P, examples) unit direct vectors
    label: np.ndarray  # (examples,) colour channel (mono) or 0 (multi)
    mean: np.ndarray  # stored mean (zeros when the mean is a regressed basis vector)
    basis: np.ndarray  # (rows, n)
    coeffs: np.ndarray  # (n, examples) regression targets
    singular_values: np.ndarray
    energy: float
    points: int
    counts: np.ndarray
    examples: int


def _stage(direct, indirect, group, cfg: dict) -> _Stage:
    bcfg = cfg["basis"]
    direct = np.asarray(direct, np.float64)
    indirect = np.asarray(indirect, np.float64)
    group = np.asarray(group, np.int64)
    if direct.ndim != 3 or direct.shape[2] != 3 or indirect.ndim != 3 or indirect.shape[2] != 3:
        raise ValueError(f"direct must be (N, S, 3) and indirect (N, T, 3), got {direct.shape} and {indirect.shape}")
    if direct.shape[0] != indirect.shape[0]:
        raise ValueError(f"direct has {direct.shape[0]} examples, indirect {indirect.shape[0]}")
    if group.shape != (direct.shape[1],) or group.min() < 0:
        raise ValueError(f"group must be (S,) = ({direct.shape[1]},) non-negative indices, got {group.shape}")
    if not (np.isfinite(direct).all() and np.isfinite(indirect).all()):
        raise ValueError("direct or indirect data contain NaN or inf")
    if bcfg["mean"] not in ("norm", "linear"):
        raise ValueError(f"basis.mean must be 'norm' (Belcour et al. §4.2) or 'linear', got {bcfg['mean']!r}")
    p = int(group.max()) + 1
    counts = np.bincount(group, minlength=p)
    if np.any(counts == 0):
        raise ValueError(f"coarse points {np.nonzero(counts == 0)[0][:5]} have no fine point")
    coarse = coarse_direct(direct, group, counts)
    gamma = float(bcfg["gamma"])
    x, y, label = _examples(gamma_encode(coarse, gamma), gamma_encode(indirect, gamma), bcfg["channels"])
    norms = np.linalg.norm(x, axis=0)
    usable = norms > 1e-12 * max(float(norms.max()), 1e-300)
    if not usable.any():
        raise ValueError("every example has a zero direct vector: no light reaches any measurement point")
    if not usable.all():
        warnings.warn(f"{int((~usable).sum())} of {usable.size} examples have a zero direct vector (the light "
                      "reaches no measurement point); they carry no information for the transfer and are skipped",
                      IllConditionedWarning, stacklevel=3)
    x, y, label, norms = x[:, usable], y[:, usable], label[usable], norms[usable]
    xn, yn = x / norms, y / norms
    center = bool(bcfg["center"])
    n_total = int(bcfg["n"])
    if n_total < 1:
        raise ValueError(f"basis.n must be >= 1, got {bcfg['n']}")
    mean = yn.mean(axis=1) if center else np.zeros(yn.shape[0])
    a = yn - mean[:, None]
    n_basis = min(n_total - (1 if center else 0), min(a.shape))
    u, sv = gram_svd(a, n_basis)
    total = float(np.sum(a ** 2))
    energy = float(np.sum(sv ** 2) / total) if total > 0 else 1.0
    if center and bcfg["mean"] == "linear":
        # the mean is one more basis vector whose coefficient is regressed like the others, so the
        # model stays exactly linear in x (no |x| factor)
        q, r = np.linalg.qr(np.column_stack([mean, u]))
        u = q * np.where(np.abs(np.diag(r)) > 1e-12 * max(np.abs(np.diag(r)).max(), 1e-300), 1.0, 0.0)
        return _Stage(xn, label, np.zeros_like(mean), u, u.T @ yn, sv, energy, p, counts, int(usable.sum()))
    return _Stage(xn, label, mean, u, u.T @ a, sv, energy, p, counts, int(usable.sum()))


class _Solver:
    """SVDs of the direct matrices of a stage (per channel for mono), reused for every lambda."""

    def __init__(self, stage: _Stage, channels: str):
        self.stage = stage
        self.channels = channels
        self.parts = []
        for ch in (range(3) if channels == "mono" else [0]):
            sel = stage.label == ch
            if sel.any():
                self.parts.append((ch, sel, np.linalg.svd(stage.xn[:, sel], full_matrices=False)))

    def transfer(self, lam: float, rcond: float, warn: float | None) -> tuple[np.ndarray, list]:
        st = self.stage
        n = st.basis.shape[1]
        transfer = np.zeros((3, n, st.points)) if self.channels == "mono" else np.zeros((n, st.xn.shape[0]))
        info = []
        for ch, sel, svd in self.parts:
            name = f"D (channel {'RGB'[ch]})" if self.channels == "mono" else "D"
            pinv, inf = _ridge_from_svd(svd, lam, rcond, warn, name, st.xn[:, sel].shape)
            if self.channels == "mono":
                transfer[ch] = st.coeffs[:, sel] @ pinv
            else:
                transfer = st.coeffs @ pinv
            info.append(inf)
        return transfer, info


def _ridge_from_svd(svd, lam: float, rcond: float, warn: float | None, name: str, shape) -> tuple[np.ndarray, dict]:
    if lam < 0:
        raise ValueError(f"lambda must be >= 0, got {lam}")
    u, s, vt = svd
    s_max = float(s[0]) if s.size else 0.0
    keep = s > rcond * s_max if s_max > 0 else np.zeros_like(s, bool)
    filt = np.where(keep, s / np.where(keep, s * s + lam, 1.0), 0.0)
    s_min = float(s[-1]) if s.size else 0.0
    cond = s_max / s_min if s_min > 0 else math.inf
    info = {"condition": cond, "rank": int(keep.sum()), "shape": list(shape), "s_max": s_max, "s_min": s_min}
    if warn is not None and cond > warn:
        warnings.warn(f"{name} ({shape[0]} x {shape[1]}) is ill-conditioned: condition number {cond:.3g}, "
                      f"numerical rank {info['rank']} of {min(shape)} (duplicate measurement points, or lights "
                      f"that reach none); the transfer uses the regularised pseudo-inverse (lambda = {lam:g})",
                      IllConditionedWarning, stacklevel=4)
    return (vt.T * filt) @ u.T, info


def fit_arrays(direct, indirect, group, config: dict | None = None) -> FitResult:
    """Basis and transfer matrices from N examples.

    Args:
      direct: (N, S, 3) direct radiance at the S fine measurement points of each configuration.
      indirect: (N, T, 3) indirect lightmap texels of each configuration.
      group: (S,) coarse point index of each fine point (``MeasurementPoints.group``).
      config: ``basis`` and ``transfer`` sections (``DEFAULT_CONFIG`` layout); ``transfer.lam_cv``
        is not used here (see ``fit`` and ``cross_validate_lambda``).

    Returns ``FitResult(params, info)``: params {mean, basis, transfer, group, counts,
    singular_values} (arrays, read by ``lightmap``), info {n, lam, points, texels, examples,
    conditioning, energy_kept}.

    Numerics: not differentiable (a fitting or training procedure).
    """
    cfg = _cfg(config)
    bcfg, tcfg = cfg["basis"], cfg["transfer"]
    stage = _stage(direct, indirect, group, cfg)
    lam = float(tcfg["lam"])
    transfer, info = _Solver(stage, bcfg["channels"]).transfer(lam, float(tcfg["rcond"]), float(tcfg["warn_condition"]))
    params = {
        "mean": stage.mean.astype(np.float32),
        "basis": stage.basis.astype(np.float32),
        "transfer": transfer.astype(np.float32),
        "group": np.asarray(group, np.int32),
        "counts": stage.counts.astype(np.int32),
        "singular_values": stage.singular_values.astype(np.float32),
    }
    return FitResult(params, {"n": int(bcfg["n"]), "lam": lam, "points": stage.points,
                              "texels": int(np.shape(indirect)[1]), "examples": stage.examples,
                              "conditioning": info, "energy_kept": stage.energy})


# --------------------------------------------------------------------------------------------
# Evaluation (§4.3): the one lightmap function


def reconstruct(mean, basis, coeffs, norms, channels: str):
    """The lightmap from basis coefficients (§4.2-4.3): m |x| + U_n u, per channel for "mono".

    Args:
      mean, basis: (T,) and (T, n) ("mono"), (3T,) and (3T, n) ("multi"), in transfer space.
      coeffs: u, (..., n, 3) ("mono") or (..., n) ("multi").
      norms: |x| of the direct vectors, (..., 3) ("mono") or (...) ("multi").
    Returns (..., T, 3) in transfer space (still gamma-mapped). NumPy in (float64 projection),
    NumPy out; JAX in (the evaluator), JAX out.

    Numerics:
        case: dd_reconstruct (T = 8 texels, n = 4 basis vectors of a ``fit_arrays`` fit, coefficients
          in [-1e5, 1e5], norms in [0, 1e5], "mono")
        float32: value rtol 1e-5 atol 1e-1; grad rtol 1e-5 atol 1e-6
        (a sum of 5 terms up to 1e5 of both signs: rounding is absolute near zero)
    """
    xp = jnp if isinstance(coeffs, jax.Array) else np
    if channels == "mono":
        lead = tuple(range(norms.ndim - 1))
        return xp.expand_dims(mean[:, None], lead) * norms[..., None, :] + xp.einsum("tn,...nc->...tc", basis, coeffs)
    out = xp.expand_dims(mean, tuple(range(norms.ndim))) * norms[..., None] + xp.einsum("tn,...n->...t", basis, coeffs)
    return out.reshape(out.shape[:-1] + (-1, 3))


def _safe_norm(x, axis: int):
    """|x| with the slope 0 at x = 0 (jnp.linalg.norm's is NaN there: a black light)."""
    sq = jnp.sum(x * x, axis=axis)
    nonzero = sq > 0.0
    return jnp.where(nonzero, jnp.sqrt(jnp.where(nonzero, sq, 1.0)), 0.0)


@functools.partial(jax.jit, static_argnames=("channels", "gamma"))
def _lightmap(params: dict, direct, *, channels: str, gamma: float):
    x = gamma_encode(coarse_direct(direct, params["group"], params["counts"]), gamma)  # (..., P, 3)
    if channels == "mono":
        u = jnp.einsum("cnp,...pc->...nc", params["transfer"], x)  # (..., n, 3): u_c = M_c x_c
        norms = _safe_norm(x, axis=-2)  # (..., 3)
    else:
        xv = x.reshape(x.shape[:-2] + (-1,))
        u = jnp.einsum("np,...p->...n", params["transfer"], xv)
        norms = _safe_norm(xv, axis=-1)
    return gamma_decode(reconstruct(params["mean"], params["basis"], u, norms, channels), gamma)


def lightmap(params: dict, direct, config: dict | None = None):
    """Fine direct (..., S, 3) -> lightmap texels (..., T, 3) (§4.3): average to the coarse points
    (§5.1), gamma map (§5.3), u = M_n x, m |x| + U_n u (or B_n u with ``basis.mean="linear"``),
    map back; a demodulated fit's times ``params["texel_modulation"]`` (the texels' texture).
    Jitted, batched over leading axes; the evaluator, cross-validation and the
    experiments all go through it. Only the arrays named in ``fit_arrays`` are read.

    Numerics:
        case: dd_lightmap (a ``fit_arrays`` fit to 24 random configurations of 16 fine points in 8
          groups and 12 texels, n = 4; direct radiance in [0, 1e5]; gamma 0 and 2.2)
        fd: off (gamma encoding has an infinite slope at 0 and |x| a kink at x = 0, both drawn)
        float32: value rtol 1e-4 atol 1e-1; grad rtol 1e-4 atol 1e-5
        (a fitted linear map of inputs to 1e5 with both signs: rounding is absolute near zero)
    """
    cfg = _cfg(config)
    arrays = {k: jnp.asarray(params[k]) for k in ("mean", "basis", "transfer", "group", "counts")}
    # in the params' precision: float32 from ``fit``, float64 where a test enables x64
    out = _lightmap(arrays, jnp.asarray(direct, arrays["transfer"].dtype), channels=cfg["basis"]["channels"],
                    gamma=float(cfg["basis"]["gamma"]))
    if "texel_modulation" in params:  # a demodulated fit: its texture back on, the texels' light
        mod = jnp.asarray(params["texel_modulation"], out.dtype)  # (T, 3), over the leading axes
        out = out * mod.reshape((1,) * (out.ndim - mod.ndim) + mod.shape)
    return out


def transfer_coefficients(params: dict, x, config: dict | None = None):
    """u = M_n g(x) for a coarse direct vector x (P, 3) (the transfer product alone, for timing).

    Numerics:
        case: dd_transfer (the ``dd_lightmap`` fit; coarse direct radiance in [0, 1e5])
        float32: value rtol 1e-5 atol 1e-1; grad rtol 1e-5 atol 1e-6
        (sums of 8 terms to 1e5 of both signs: rounding is absolute near zero)
    """
    cfg = _cfg(config)
    transfer = jnp.asarray(params["transfer"])
    xg = gamma_encode(jnp.asarray(x, transfer.dtype), float(cfg["basis"]["gamma"]))
    if cfg["basis"]["channels"] == "mono":
        return jnp.einsum("cnp,pc->nc", transfer, xg)
    return transfer @ xg.reshape(-1)


def evaluator(params: dict, config: dict | None = None):
    """``evaluate(inputs, lighting) -> (H, W, 3)`` indirect radiance (§4.3).

    ``inputs`` is a G-buffer with ``uv`` in atlas coordinates and ``valid``
    (``jprt.render.lightmap.atlas_gbuffer``; ``jprt.methods.lightmap_lookup.atlas_inputs`` for the atlas
    itself, which makes the output the lightmap as an (R, R, 3) image);
    ``lighting`` a ``PointRadiance``: the direct radiance (S, 3) at the fine measurement points
    (the method's lighting input, §4.3 "fake G-buffer"). Pure and jitted: the lightmap
    (``lightmap``) then a bilinear atlas lookup per pixel; for a demodulated fit
    (``params["texel_modulation"]``) the lookup of the texels' light over their texture, times a
    Lambertian pixel's own
    (``inputs.diffuse_albedo``, ``specular_albedo`` and ``object_id``,
    ``lightmap_lookup.remodulated_lookup``);
    invalid pixels are 0.

    Numerics: not differentiable (builds the float32 run-time program; its arithmetic is ``lightmap``'s, covered).
    """
    cfg = _cfg(config)
    for key in ("texel_index", "fill_index", "fine_index"):
        if key not in params:
            raise ValueError(f"params have no {key!r} (fit_arrays output): use fit(data, config), which adds the "
                             "lightmap layout")
    arrays = {k: jnp.asarray(params[k]) for k in ("mean", "basis", "transfer", "group", "counts")}
    n_fine = int(params["group"].shape[0])
    channels, gamma = cfg["basis"]["channels"], float(cfg["basis"]["gamma"])
    materials, shade = lightmap_shader(params, params["fill_index"])

    @jax.jit
    def image(uv, valid, pixel_materials, direct):
        texels = _lightmap(arrays, direct, channels=channels, gamma=gamma)  # demodulated for a demodulated fit
        return jnp.where(valid[..., None], shade(texels, uv, pixel_materials), 0.0)

    def evaluate(inputs, lighting):
        uv = jnp.asarray(inputs.uv, jnp.float32)
        valid = jnp.asarray(inputs.valid, bool)
        direct = jnp.asarray(lighting.direct, jnp.float32)
        if uv.shape[:-1] != valid.shape or uv.shape[-1] != 2:
            raise ValueError(f"inputs.uv must be (H, W, 2) matching valid (H, W), got {uv.shape} and {valid.shape}")
        if direct.shape != (n_fine, 3):
            raise ValueError(f"lighting.direct must be ({n_fine}, 3) radiance at the fine measurement points, "
                             f"got {direct.shape}")
        return image(uv, valid, materials(inputs), direct)

    return evaluate


def project(params: dict, direct, indirect, config: dict | None = None) -> np.ndarray:
    """The best reconstruction of reference lightmaps in the fitted basis (Fig. 14 dashed):
    s (m + U_n U_n^T (y / s - m)) in the transfer space (gamma-mapped, s = |x| of the example's
    own direct vector), mapped back. direct (N, S, 3), indirect (N, T, 3) -> (N, T, 3).

    Numerics: not differentiable (a float64 NumPy precomputation).
    """
    cfg = _cfg(config)
    gamma, channels = float(cfg["basis"]["gamma"]), cfg["basis"]["channels"]
    direct = np.asarray(direct, np.float64)
    indirect = np.asarray(indirect, np.float64)
    coarse = gamma_encode(coarse_direct(direct, params["group"], params["counts"]), gamma)  # (N, P, 3)
    n, t = indirect.shape[0], indirect.shape[1]
    mean = np.asarray(params["mean"], np.float64)
    u = np.asarray(params["basis"], np.float64)
    y = gamma_encode(indirect, gamma)
    if channels == "mono":
        norms = np.maximum(np.linalg.norm(coarse, axis=1), 1e-30)  # (N, 3)
        coeffs = np.einsum("tn,ktc->knc", u, y - mean[None, :, None] * norms[:, None, :])  # s U^T (y / s - m)
    else:
        norms = np.maximum(np.linalg.norm(coarse.reshape(n, -1), axis=1), 1e-30)  # (N,)
        coeffs = (y.reshape(n, -1) - mean[None, :] * norms[:, None]) @ u  # (N, n): s U^T (y / s - m)
    return gamma_decode(reconstruct(mean, u, coeffs, norms, channels), gamma).reshape(n, t, 3)


def cross_validate_lambda(direct, indirect, group, config: dict | None, lambdas, *, folds: int = 4,
                          seed: int = 0) -> dict:
    """Choose the ridge lambda (Eq. 14) by k-fold cross-validation over lighting configurations:
    for every candidate, fit on k - 1 folds and measure the lightmap RMSE (``lightmap``) on the
    held-out fold (the basis and the SVDs of each fold are shared by all candidates).
    Returns {"best": lambda, "lambdas": [...], "rmse": [...]} (never looks at test data).

    Numerics: not differentiable (a fitting or training procedure).
    """
    direct, indirect = np.asarray(direct), np.asarray(indirect)
    n = direct.shape[0]
    folds = int(folds)
    if folds < 2 or folds > n:
        raise ValueError(f"cv_folds must be in [2, {n}], got {folds}")
    if not len(lambdas):
        raise ValueError("no lambda candidates")
    order = np.random.default_rng(seed).permutation(n)
    cfg = _cfg(config)
    sq = np.zeros(len(lambdas))
    count = 0
    for part in np.array_split(order, folds):
        train = np.setdiff1d(order, part)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", IllConditionedWarning)
            stage = _stage(direct[train], indirect[train], group, cfg)
        solver = _Solver(stage, cfg["basis"]["channels"])
        params = {"mean": stage.mean, "basis": stage.basis, "group": np.asarray(group), "counts": stage.counts}
        for j, lam in enumerate(lambdas):
            params["transfer"], _ = solver.transfer(float(lam), float(cfg["transfer"]["rcond"]), None)
            err = np.asarray(lightmap(params, direct[part], cfg), np.float64) - indirect[part]
            sq[j] += float(np.sum(err ** 2))
        count += indirect[part].size
    scores = np.sqrt(sq / count)
    return {"best": float(lambdas[int(np.argmin(scores))]), "lambdas": [float(l) for l in lambdas],
            "rmse": [float(v) for v in scores]}


def lightmap_rmse(predictions, references) -> float:
    """RMSE over all texels, channels and configurations of (N, T, 3) lightmaps.

    Numerics: not differentiable (an error statistic in NumPy).
    """
    p, r = np.asarray(predictions, np.float64), np.asarray(references, np.float64)
    if p.shape != r.shape:
        raise ValueError(f"predictions {p.shape} and references {r.shape} differ")
    return float(np.sqrt(np.mean((p - r) ** 2)))


def model_bytes(params: dict) -> int:
    """Bytes of the runtime data (float32 basis, mean and transfer matrices, point groups).

    Numerics: not differentiable (an integer size).
    """
    return int(sum(np.asarray(params[k]).nbytes for k in ("mean", "basis", "transfer", "group", "counts")))


class DDData(NamedTuple):
    """Rendered examples of one lighting scenario.

    Fields:
      atlas: ``jprt.render.lightmap.Atlas`` arrays as a dict (NumPy only).
      candidates: dict of candidate surface samples (position, normal, albedo, object_id, area).
      direct / indirect: (N, S, 3) direct at every candidate and (N, T, 3) indirect lightmaps
        (training configurations, ``data.spp`` samples per texel).
      direct_test / indirect_test: held-out configurations (``data.test_spp``).
      lights / lights_test: dicts of the stacked fields of the lights (``SpotLights`` or ``PointLights``).
      meta: scene description, object names, render seconds, cache path.
      modulation: ``lightmap_lookup.texel_modulation`` of the texels' materials (a Lambertian
        texel's albedo over its object's mean (T, 3), the means per object (K, 3)), or None.
    """

    atlas: dict
    candidates: dict
    direct: np.ndarray
    indirect: np.ndarray
    direct_test: np.ndarray
    indirect_test: np.ndarray
    lights: dict
    lights_test: dict
    meta: dict
    modulation: tuple | None = None


def fit(data: DDData, config: dict | None = None) -> FitResult:
    """Measurement points (§4.1, §5.1), basis and transfer (§4.2) from a ``DDData``; the params
    also carry the lightmap layout the evaluator needs (fine_index, texel_index, fill_index).
    With ``shading.demodulate`` the basis and transfer are fitted to the texels' light over their
    texture (the data's ``modulation``: a Lambertian texel's albedo over its object's mean), which
    the params keep (``texel_modulation``, ``object_albedo``) for ``lightmap`` and the evaluator.
    ``info`` adds ``lambda_cv`` (the cross-validation, or None), ``resolution`` and ``fit_s``.

    Numerics: not differentiable (a fitting or training procedure).
    """
    cfg = _cfg(config)
    t0 = time.perf_counter()
    points = measurement_points(data, cfg)
    direct = data.direct[:, points.fine_index]
    demodulate = cfg["shading"]["demodulate"] and data.modulation is not None
    indirect = data.indirect / np.asarray(data.modulation[0], np.float32) if demodulate else data.indirect
    cv = None
    if cfg["transfer"]["lam_cv"]:
        cv = cross_validate_lambda(direct, indirect, points.group, cfg, cfg["transfer"]["lam_cv"],
                                   folds=int(cfg["transfer"]["cv_folds"]))
        cfg = merge(cfg, {"transfer": {"lam": cv["best"]}})
    params, info = fit_arrays(direct, indirect, points.group, cfg)
    if demodulate:
        params.update(modulation_params(data.modulation))
    params["fine_index"] = points.fine_index
    params["texel_index"] = np.asarray(data.atlas["texel_index"], np.int32)
    params["fill_index"] = np.asarray(data.atlas["fill_index"], np.int32)
    info.update(lambda_cv=cv, resolution=int(data.atlas["resolution"]), fit_s=time.perf_counter() - t0,
                model_bytes=model_bytes(params))
    return FitResult(params, info)


def measurement_points(data: DDData, config: dict | None = None) -> MeasurementPoints:
    """The measurement points of ``config["points"]`` among ``data``'s candidates (§4.1, §5.1):
    what ``fit`` uses (deterministic, so ``example`` finds the same points).

    Numerics: not differentiable (selects points).
    """
    pcfg = _cfg(config)["points"]
    return select_points(data.candidates["position"], pcfg["count"], supersample=pcfg["supersample"],
                         area=float(data.candidates["area"]))


def example(data: DDData, config: dict | None = None):
    """A held-out (inputs, lighting) pair: the atlas G-buffer (``atlas_inputs``) and the direct
    radiance of the first held-out configuration at the fine measurement points.

    Numerics: not differentiable (a held-out input and lighting from a dataset).
    """
    fine = measurement_points(data, config).fine_index
    direct = data.direct_test[0] if len(data.direct_test) else data.direct[0]
    return (atlas_inputs(int(data.atlas["resolution"]), data.atlas["texel_index"]),
            PointRadiance(np.asarray(direct[fine], np.float32)))
