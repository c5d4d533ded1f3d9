"""Spherical Gaussians (SGs), anisotropic SGs (ASGs) and SG-mixture fitting.

Isotropic SG (Currius et al. 2020, Eq. 1 / Eq. 16):   G(v; u, lambda, a) = a exp(lambda (v . u - 1)).

* integral:       int G = 2 pi a (1 - exp(-2 lambda)) / lambda, evaluated as -2 pi a expm1(-2 lambda) / lambda.
* product:        G1 G2 = G(v; u_m / |u_m|, |u_m|, a1 a2 exp(|u_m| - lambda1 - lambda2)), u_m = lambda1 u1 + lambda2 u2.
* inner product:  int G1 G2 = 4 pi a1 a2 sinh(d) / (d exp(lambda1 + lambda2)), d = |lambda1 u1 + lambda2 u2|.
  Currius et al. Eq. 21-23 normalise the mean axis (u_m / (lambda1 + lambda2)); that is wrong
  (see ../shared/papers/README.md). Here it is evaluated stably as
  2 pi a1 a2 exp(d - lambda1 - lambda2) (-expm1(-2 d)) / d, every exponent <= 0.

Anisotropic SG (Xu et al. 2013, Eq. 4): ASG(v; [x, y, z], [lx, ly], c) = c max(v . z, 0) exp(-lx (v . x)^2 - ly (v . y)^2)
(Currius et al. Eq. 20 prints the exponent without the squares).

GGX as SGs (Currius et al. 2020, Appendix B, after Pettineo 2016): the NDF as an SG in the
half-vector domain (Eq. 17), warped to an ASG about the reflected view direction (Eq. 18), and
convolved with an isotropic light SG by Xu et al. 2013, Eq. 12:

    int G(v; u, lambda, a) ASG(v) dv ~= pi a c / sqrt((nu + lx)(nu + ly)) ASG(u; [x, y, z], [nu lx / (nu + lx), nu ly / (nu + ly)], 1),

with nu = lambda / 2. Currius et al. Eq. 24 prints this with the ASG's own sharpnesses and
evaluated at v; the sharpnesses must be convolved and the ASG evaluated at the light lobe's axis
(as Pettineo's code does).

Fitting (Currius et al. 2020 §4 and its baselines): gradient descent on the log-L2 loss
(log(T + 1) - log(P + 1))^2 with an optional axis-alignment regulariser between neighbouring
texels, and EM on a von Mises-Fisher mixture (Banerjee et al. 2005).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

__all__ = [
    "SG", "ASG",
    "evaluate", "integral", "product", "inner_product",
    "mixture_evaluate", "mixture_integral",
    "asg_evaluate", "orthonormal_basis",
    "ggx_ndf_sg", "warp_ndf_to_asg", "convolve_sg_asg",
    "peak_axes", "log_l2", "fit_gd", "fit_em",
]

_TINY = 1e-20


class SG(NamedTuple):
    """An isotropic SG (or a batch): axis (..., 3) unit, sharpness (...), amplitude (...) or (..., C)."""

    axis: jax.Array
    sharpness: jax.Array
    amplitude: jax.Array


class ASG(NamedTuple):
    """An anisotropic SG: orthonormal frame (x, y, z) each (..., 3), sharpness_x/y (...), amplitude (...)."""

    x: jax.Array
    y: jax.Array
    z: jax.Array
    sharpness_x: jax.Array
    sharpness_y: jax.Array
    amplitude: jax.Array


def _dot(a, b):
    """Dot product over the last axis; batch axes broadcast explicitly (one axis vs many directions)."""
    a, b = jnp.broadcast_arrays(jnp.asarray(a), jnp.asarray(b))
    return jnp.sum(a * b, axis=-1)


def _safe_norm(v):
    # Clamped so the gradient is finite when v = 0 (equal and opposite lobes).
    return jnp.sqrt(jnp.maximum(jnp.sum(v * v, axis=-1), _TINY))


#: Below this |x|, (1 - exp(-2 x)) / x and its derivative come from their Taylor series: the
#: quotient rule's (2 x exp(-2 x) + expm1(-2 x)) / x^2 cancels catastrophically in float32 (its
#: derivative was 4.5 % off at 1e-6, ten times off at 1e-8, NaN at 0); the series through x^5
#: is below float32 rounding here (the first dropped term is 0.044 x^6).
_SERIES_BELOW = 0.1


@jax.custom_jvp
def _one_minus_exp_neg2_over(x):
    """(1 - exp(-2 x)) / x, stable for x -> 0 (limit 2) and x large, with a derivative that is
    too (sum_n (-1)^n 2^(n+1) x^n / (n+1)!, and its term-wise derivative, for |x| < 0.1)."""
    x = jnp.asarray(x)
    small = jnp.abs(x) < _SERIES_BELOW
    xs = jnp.where(small, x, 0.0)
    series = 2.0 + xs * (-2.0 + xs * (4.0 / 3.0 + xs * (-2.0 / 3.0 + xs * (4.0 / 15.0 + xs * (-4.0 / 45.0)))))
    xl = jnp.where(small, 1.0, x)
    return jnp.where(small, series, -jnp.expm1(-2.0 * xl) / xl)


@_one_minus_exp_neg2_over.defjvp
def _one_minus_exp_neg2_over_jvp(primals, tangents):
    (x,), (dx,) = primals, tangents
    x = jnp.asarray(x)
    small = jnp.abs(x) < _SERIES_BELOW
    xs = jnp.where(small, x, 0.0)
    series = -2.0 + xs * (8.0 / 3.0 + xs * (-2.0 + xs * (16.0 / 15.0 + xs * (-4.0 / 9.0 + xs * (16.0 / 105.0)))))
    xl = jnp.where(small, 1.0, x)
    exact = (2.0 * xl * jnp.exp(-2.0 * xl) + jnp.expm1(-2.0 * xl)) / (xl * xl)
    return _one_minus_exp_neg2_over(x), jnp.where(small, series, exact) * dx


def _cos_minus_one(v, u):
    """v . u - 1 for unit v, u, as -|v - u|^2 / 2: the same number, without the cancellation that
    leaves float32's v . u - 1 with an absolute error of ~1e-7 (a relative error of lambda x 1e-7
    in the lobe, 1e-3 at lambda = 1e4, where the difference form stays at rounding)."""
    v, u = jnp.broadcast_arrays(jnp.asarray(v), jnp.asarray(u))
    return -0.5 * jnp.sum(jnp.square(v - u), axis=-1)


@jax.custom_jvp
def _lobe_gap(axis1, sharpness1, axis2, sharpness2):
    """lambda_m - lambda1 - lambda2 (<= 0), lambda_m = |lambda1 u1 + lambda2 u2|, for unit axes.

    The value as -lambda1 lambda2 |u1 - u2|^2 / (lambda_m + lambda1 + lambda2): the printed
    difference of ~1e4-sized terms cancels for nearly aligned lobes (1e-3 of the amplitude lost
    in float32). The derivative explicitly, d/dlambda_i = u_i . u_m - 1 and d/du_i = lambda_i u_m,
    with u_i . u_m - 1 free of cancellation too: autodiff of the quotient cancels two terms of size
    1 / lambda for nearly opposite lobes (7 % off in float32 at lambda = 0.5 against 243), and
    1 - u_i . u_m from a rounded u_m lost 0.5 % for lobes 1e-3 rad apart."""
    gap = jnp.sum(jnp.square(axis1 - axis2), axis=-1)
    lm = _safe_norm(sharpness1[..., None] * axis1 + sharpness2[..., None] * axis2)
    return -sharpness1 * sharpness2 * gap / jnp.maximum(lm + sharpness1 + sharpness2, _TINY)


@_lobe_gap.defjvp
def _lobe_gap_jvp(primals, tangents):
    axis1, s1, axis2, s2 = primals
    da1, ds1, da2, ds2 = tangents
    um = s1[..., None] * axis1 + s2[..., None] * axis2
    lm = _safe_norm(um)
    axis = um / lm[..., None]
    gap = jnp.sum(jnp.square(axis1 - axis2), axis=-1)  # 2 (1 - c), c = u1 . u2
    c, sin2 = 1.0 - 0.5 * gap, 0.5 * gap * (2.0 - 0.5 * gap)  # 1 - c^2 without cancellation

    def one_minus_cos(a, b):
        # 1 - u_a . u_m = (lm - a - b c) / lm: for a + b c >= 0 as b^2 (1 - c^2) / (lm (lm + a + b c))
        # (u_m nearly u_a: the difference cancels), otherwise as printed (it is >= 1 there)
        num = a + b * c
        stable = b * b * sin2 / (lm * jnp.maximum(lm + num, _TINY))
        return jnp.where(num >= 0.0, stable, 1.0 - num / lm)

    tangent = (-one_minus_cos(s1, s2) * ds1 - one_minus_cos(s2, s1) * ds2
               + s1 * jnp.sum(axis * da1, axis=-1) + s2 * jnp.sum(axis * da2, axis=-1))
    return _lobe_gap(axis1, s1, axis2, s2), tangent


def _lobe_pair(axis1, sharpness1, axis2, sharpness2):
    """(u_m, lambda_m, lambda_m - lambda1 - lambda2) of two lobes, broadcast to a common shape."""
    shape = jnp.broadcast_shapes(jnp.shape(sharpness1), jnp.shape(sharpness2), jnp.shape(axis1)[:-1],
                                 jnp.shape(axis2)[:-1])
    sharpness1, sharpness2 = (jnp.broadcast_to(jnp.asarray(s), shape) for s in (sharpness1, sharpness2))
    axis1, axis2 = (jnp.broadcast_to(jnp.asarray(a), shape + (3,)) for a in (axis1, axis2))
    um = sharpness1[..., None] * axis1 + sharpness2[..., None] * axis2
    lm = _safe_norm(um)
    return um / lm[..., None], lm, _lobe_gap(axis1, sharpness1, axis2, sharpness2)


def evaluate(v, axis, sharpness, amplitude):
    """G(v; u, lambda, a) = a exp(lambda (v . u - 1)), with v . u - 1 = -|v - u|^2 / 2 (unit v, u).

    Numerics:
        v: (32, 3) unit
        axis: (32, 3) unit near v
        sharpness: (32,) in [0, 1e4]
        amplitude: (32,) in [0, 1e5]
        float32: value rtol 1e-5 atol 1e-30; grad rtol 1e-4 atol 1e-25
    """
    return amplitude * jnp.exp(sharpness * _cos_minus_one(v, axis))


def integral(sharpness, amplitude):
    """int_S2 G = 2 pi a (1 - exp(-2 lambda)) / lambda (-> 4 pi a as lambda -> 0).

    Numerics:
        sharpness: (32,) in [0, 1e6]
        amplitude: (32,) in [0, 1e5]
        float32: value rtol 1e-6 atol 0; grad rtol 1e-5 atol 1e-30
    """
    return 2.0 * jnp.pi * amplitude * _one_minus_exp_neg2_over(sharpness)


def product(axis1, sharpness1, amplitude1, axis2, sharpness2, amplitude2) -> SG:
    """The SG equal to G1(v) G2(v) (axis undefined, the zero vector, when the lobes cancel exactly).

    The amplitude's exponent lambda_m - lambda1 - lambda2 and its derivative are evaluated
    without cancellation (``_lobe_gap``; the same numbers for unit axes).

    Numerics:
        case: sg_product (axes unit, aligned and antipodal among them, sharpness in [0, 1e4],
          amplitude in [0, 1e5]; the axis is compared where lambda_m >= 1e-2 (lambda1 + lambda2):
          where the lobes cancel it is arbitrary, and the product lobe flat)
        fd: off (|lambda1 u1 + lambda2 u2| has a kink where opposite lobes of equal sharpness cancel, a point always drawn)
        float32: value rtol 1e-4 atol 1e-6; grad rtol 1e-4 atol 1e-6
        (the axis is a unit vector: 1e-6 absolute is a few float32 roundings of its components)
    """
    axis, lm, exponent = _lobe_pair(axis1, sharpness1, axis2, sharpness2)
    return SG(axis, lm, amplitude1 * amplitude2 * jnp.exp(exponent))


def inner_product(axis1, sharpness1, amplitude1, axis2, sharpness2, amplitude2):
    """int_S2 G1 G2 = 4 pi a1 a2 sinh(d) / (d exp(lambda1 + lambda2)), d = |lambda1 u1 + lambda2 u2|
    (d - lambda1 - lambda2 as in ``product``, without cancellation).

    Numerics:
        axis1: (32, 3) unit
        sharpness1: (32,) in [0, 1e4]
        amplitude1: (32,) in [0, 1e5]
        axis2: (32, 3) unit near axis1
        sharpness2: (32,) in [0, 1e4]
        amplitude2: (32,) in [0, 1e5]
        fd: off (d has a kink where opposite lobes of equal sharpness cancel, a point always drawn)
        float32: value rtol 1e-4 atol 1e-30; grad rtol 1e-4 atol 1e-20
    """
    _, d, exponent = _lobe_pair(axis1, sharpness1, axis2, sharpness2)
    # 4 pi sinh(d) exp(-l1 - l2) / d = 2 pi exp(d - l1 - l2) (1 - exp(-2 d)) / d
    return 2.0 * jnp.pi * amplitude1 * amplitude2 * jnp.exp(exponent) * _one_minus_exp_neg2_over(d)


def mixture_evaluate(v, axes, sharpness, amplitudes):
    """Sum of K SGs at directions v (..., 3): axes (K, 3), sharpness (K,), amplitudes (K, C) -> (..., C)
    (v . u - 1 as -|v - u|^2 / 2, see ``evaluate``).

    Numerics:
        v: (16, 3) unit
        axes: (4, 3) unit
        sharpness: (4,) in [0, 1e4]
        amplitudes: (4, 3) in [0, 1e5]
        float32: value rtol 1e-5 atol 1e-30; grad rtol 1e-4 atol 1e-25
    """
    cos = _cos_minus_one(jnp.asarray(v)[..., None, :], axes)  # (..., K)
    k = jnp.exp(jnp.broadcast_to(sharpness, cos.shape) * cos)
    return jnp.tensordot(k, amplitudes, axes=([-1], [0]))


def mixture_integral(sharpness, amplitudes):
    """int_S2 of a mixture: (C,) from sharpness (K,) and amplitudes (K, C).

    Numerics:
        sharpness: (8,) in [0, 1e6]
        amplitudes: (8, 3) in [0, 1e5]
        float32: value rtol 1e-5 atol 0; grad rtol 1e-5 atol 1e-30
    """
    return jnp.sum(integral(jnp.broadcast_to(sharpness[:, None], amplitudes.shape), amplitudes), axis=0)


def asg_evaluate(v, asg: ASG):
    """ASG(v) = c max(v . z, 0) exp(-lx (v . x)^2 - ly (v . y)^2) (Xu et al. 2013, Eq. 4), for unit
    v and an orthonormal frame.

    Numerics:
        case: asg (frames from ``orthonormal_basis`` of unit z, sharpness in [0, 1e4], amplitude
          in [0, 1e5], v unit)
        fd: off (max(v . z, 0) has a kink at v . z = 0, which axis-aligned draws hit)
        float32: value rtol 5e-4 atol 2e-2; grad rtol 5e-4 atol 2e-2
        (the exponent E = lx (v . x)^2 carries 2 sqrt(lx E) x 1.2e-7 of float32's rounding of
          v . x, 2.3e-4 at lx = 1e4 and E = 87, where exp(-E) reaches float32's smallest normal)
        (near v . z = 0 the error is absolute: c x float32's ~1.2e-7 in v . z, 1.2e-2 at c = 1e5)
    """
    # For unit v and an orthonormal frame, lx (v.x)^2 + ly (v.y)^2 = ly |v x z|^2 + (lx - ly) (v.x)^2:
    # the frame's x enters only through the anisotropy lx - ly. Nearly isotropic lobes (a view
    # near the normal in ``warp_ndf_to_asg``) have an x that is poorly defined, and autodiff of the
    # printed form cancels two terms of size ly / sin(theta) there (16 % off in float32 at
    # 0.07 degrees); |v x z|^2 keeps the peak's exponent at rounding, where 1 - (v.z)^2 would not.
    v = jnp.asarray(v)
    vx, vz = _dot(v, asg.x), _dot(v, asg.z)
    vxz = jnp.cross(*jnp.broadcast_arrays(v, jnp.asarray(asg.z)))
    exponent = asg.sharpness_y * jnp.sum(vxz * vxz, axis=-1) + (asg.sharpness_x - asg.sharpness_y) * vx * vx
    return asg.amplitude * jnp.maximum(vz, 0.0) * jnp.exp(-exponent)


def orthonormal_basis(z):
    """An orthonormal frame (x, y) around unit z, branch-free (Duff et al. 2017); it flips where
    z crosses the xy-plane (sign(z_z)), continuous elsewhere.

    Numerics:
        z: (32, 3) unit
        fd: off (the frame flips at z_z = 0, which axis-aligned draws hit)
        float32: value rtol 1e-5 atol 1e-6; grad rtol 1e-4 atol 1e-5
    """
    sign = jnp.where(z[..., 2] >= 0, 1.0, -1.0)
    a = -1.0 / (sign + z[..., 2])
    b = z[..., 0] * z[..., 1] * a
    x = jnp.stack([1.0 + sign * z[..., 0] ** 2 * a, sign * b, -sign * z[..., 0]], axis=-1)
    y = jnp.stack([b, sign + z[..., 1] ** 2 * a, -z[..., 1]], axis=-1)
    return x, y


def ggx_ndf_sg(roughness):
    """(sharpness, amplitude) of the SG approximating the NDF (Currius et al. 2020, Eq. 17):
    exp(-(arccos(h . n) / r)^2) ~= G(h; n, 2 / r^2, 1 / (pi r^2)).

    Numerics:
        roughness: (32,) in [1e-4, 1]
        float32: value rtol 1e-6 atol 0; grad rtol 1e-6 atol 0
    """
    r2 = jnp.square(roughness)
    return 2.0 / r2, 1.0 / (jnp.pi * r2)


def warp_ndf_to_asg(normal, view, roughness) -> ASG:
    """The NDF SG warped to an ASG about the reflected view direction (Currius et al. 2020,
    Eq. 18, after Pettineo 2016): z = reflect(-view, n), x perpendicular to the plane of
    incidence, lx = lambda_d / (8 max(n . view, 1e-4)^2), ly = lambda_d / 8, c = a_d.

    Numerics:
        case: warp_asg (the ASG's value at its axis and at unit directions near it, for unit
          normals, views to 89.9 degrees from them, roughness in [1e-2, 1]; the frame alone is
          arbitrary at normal incidence, where the lobe is isotropic)
        fd: off (the frame switches to a fallback at normal incidence, a point always drawn)
        float32: value rtol 1e-3 atol 1e-6; grad rtol 1e-3 atol 1e-4
    """
    lam, amp = ggx_ndf_sg(roughness)
    ndotv = _dot(normal, view)
    z = 2.0 * ndotv[..., None] * normal - view
    cross = jnp.cross(normal, z)
    cross2 = jnp.sum(cross * cross, axis=-1)
    fallback_x, _ = orthonormal_basis(z)
    # At normal incidence the plane of incidence is undefined and the lobe is isotropic. Below
    # sin(theta) = 1e-3 the lobe's anisotropy (lx / ly - 1 = tan^2 theta) moves its value by less
    # than 1e-5 of its peak wherever it is above exp(-10) of it, while float32's cross product,
    # of size sin(theta), has a direction set by rounding (and a derivative of size 1 / sin(theta)):
    # the fixed frame is used there.
    # (no square root of the unclamped |cross|^2: its slope at 0 is infinite, and where() passes
    # inf x 0 = NaN back from the branch it does not take)
    x = jnp.where((cross2 > 1e-6)[..., None], cross * jax.lax.rsqrt(jnp.maximum(cross2, 1e-6))[..., None], fallback_x)
    y = jnp.cross(z, x)
    c = jnp.maximum(ndotv, 1e-4)
    return ASG(x, y, z, lam / (8.0 * c * c), lam / 8.0 + 0.0 * c, amp + 0.0 * c)


def convolve_sg_asg(axis, sharpness, amplitude, asg: ASG):
    """int_S2 G(v; axis, sharpness, amplitude) ASG(v) dv by Xu et al. 2013, Eq. 12.

    Numerics:
        case: convolve (light lobes with unit axes, sharpness in [0, 1e4], amplitude in [0, 1e5],
          against ASGs on ``orthonormal_basis`` frames of unit z, sharpnesses in [0, 1e4],
          amplitude in [0, 1e5])
        fd: off (the ASG's max(v . z, 0) has a kink that axis-aligned draws hit)
        float32: value rtol 5e-4 atol 1e-2; grad rtol 1e-3 atol 1e-2
        (``asg_evaluate``'s rounding, the exponent's 2 sqrt(lx E) x 1.2e-7, and its absolute error
          near v . z = 0; the gradient's lx (v . x) factor adds v . x's relative rounding; chained through ``warp_ndf_to_asg`` the roughness cancels analytically in
          c / sqrt(lx ly), which autodiff does not see: a caller differentiating in the roughness
          writes the scale fused, as ``jprt.methods.sg_lightfield.model.shade`` does)
    """
    nu = 0.5 * sharpness
    sx = nu * asg.sharpness_x / (nu + asg.sharpness_x)
    sy = nu * asg.sharpness_y / (nu + asg.sharpness_y)
    scale = jnp.pi / jnp.sqrt((nu + asg.sharpness_x) * (nu + asg.sharpness_y))
    return amplitude * scale * asg_evaluate(axis, ASG(asg.x, asg.y, asg.z, sx, sy, asg.amplitude))


# --------------------------------------------------------------------------------------------
# Fitting


def peak_axes(directions, values, k: int, min_separation_deg: float = 5.0):
    """Initial lobe axes by greedy matching pursuit on the image's luminance.

    Repeatedly takes the brightest direction of the residual, estimates that lobe's sharpness
    from the samples above half its peak (ln(peak / value) = lambda (1 - cos theta) for an SG),
    and subtracts the lobe, so a bright lobe's shoulder is not mistaken for another lobe.
    NumPy (not traced): initialisation runs once per image. Returns (k, 3) float32.

    Numerics: not differentiable (a greedy NumPy selection of directions).
    """
    d = np.asarray(directions, np.float64)
    lum = np.asarray(values, np.float64)
    residual = (lum.mean(axis=-1) if lum.ndim == 2 else lum).copy()
    cos_sep = np.cos(np.radians(min_separation_deg))
    chosen: list[np.ndarray] = []
    for _ in range(k):
        candidates = np.argsort(-residual)
        i = next((int(c) for c in candidates if all(d[c] @ u < cos_sep for u in chosen)), int(candidates[0]))
        peak = max(residual[i], 1e-30)
        cos = d @ d[i]
        near = (residual > 0.5 * peak) & (cos > 0.5) & (cos < 1.0 - 1e-9)
        lam = np.median(np.log(peak / residual[near]) / (1.0 - cos[near])) if near.any() else 10.0
        # a direction taken for separation need not be its neighbourhood's peak: then the estimate
        # is negative (it overflowed exp below); a lobe's sharpness is positive
        lam = float(np.clip(lam, 0.1, 1e4))
        residual = np.maximum(residual - peak * np.exp(lam * (cos - 1.0)), 0.0)
        chosen.append(d[i])
    return np.asarray(chosen, np.float32)


class FitResult(NamedTuple):
    """A fitted mixture: axes (..., K, 3), sharpness (..., K), amplitudes (..., K, C), final loss."""

    axes: jax.Array
    sharpness: jax.Array
    amplitudes: jax.Array
    loss: jax.Array


def log_l2(pred, target, weights):
    """Weighted mean over samples of the log-L2 loss (Currius et al. §4, Eq. 9) summed over
    channels: (log(1 + P) - log(1 + T))^2, radiances clamped at 0; weights match pred[..., 0].

    Numerics:
        pred: (16, 3) in [-1e5, 1e5]
        target: (16, 3) in [0, 1e5]
        weights: (16,) in [0, 1]
        fd: off (max(P, 0) has a kink at P = 0, an end always drawn)
        float32: value rtol 1e-5 atol 1e-12; grad rtol 1e-5 atol 1e-12
    """
    # clamped by where, not maximum: at P = 0 (every lobe underflowed) maximum passes half the
    # gradient, where the one-sided slope of a mixture that cannot go below 0 is the whole of it
    err = jnp.square(jnp.log1p(jnp.where(pred >= 0.0, pred, 0.0)) - jnp.log1p(jnp.maximum(target, 0.0)))
    return jnp.sum(weights[..., None] * err) / jnp.maximum(jnp.sum(weights), 1e-20)


def fit_gd(directions, weights, values, init_axes, *, init_sharpness: float = 10.0, steps: int = 500,
           learning_rate: float = 0.05, neighbours=None, align_weight: float = 0.0) -> FitResult:
    """Fit K-lobe SG mixtures to spherical images by Adam on the log-L2 loss (Currius et al. §4).

    Args:
      directions: (N, 3) sample directions shared by all images; weights: (N,) solid angles.
      values: (B, N, C) images (B texels).
      init_axes: (B, K, 3) or (K, 3) initial lobe axes (e.g. from ``peak_axes``).
      neighbours: optional (B, M) int indices of each texel's neighbours; with ``align_weight``
        > 0, adds align_weight * mean(1 - u_bk . u_nk) over neighbour pairs and lobes k
        (the axis-alignment regulariser that keeps lobe k coherent across texels).

    Numerics: not differentiable (a fitting loop; its loss, ``log_l2`` of ``mixture_evaluate``, is covered).
    """
    import optax

    directions = jnp.asarray(directions, jnp.float32)
    weights = jnp.asarray(weights, jnp.float32)
    values = jnp.asarray(values, jnp.float32)
    b, _, c = values.shape
    init_axes = jnp.broadcast_to(jnp.asarray(init_axes, jnp.float32), (b,) + jnp.asarray(init_axes).shape[-2:])
    k = init_axes.shape[-2]
    mean_value = jnp.mean(values, axis=1)  # (B, C)
    params = {
        "axes": init_axes,
        "log_sharpness": jnp.full((b, k), math.log(init_sharpness), jnp.float32),
        "log_amplitude": jnp.log(jnp.maximum(jnp.broadcast_to(mean_value[:, None, :], (b, k, c)), 1e-3)),
    }

    def unpack(p):
        axes = p["axes"] / jnp.linalg.norm(p["axes"], axis=-1, keepdims=True)
        return axes, jnp.exp(p["log_sharpness"]), jnp.exp(p["log_amplitude"])

    def loss_fn(p):
        axes, lam, amp = unpack(p)
        pred = jax.vmap(lambda a, l, m: mixture_evaluate(directions, a, l, m))(axes, lam, amp)
        loss = log_l2(pred, values, jnp.broadcast_to(weights, values.shape[:2]))
        if neighbours is not None and align_weight > 0.0:
            nb = jnp.asarray(neighbours)
            align = jnp.sum(axes[:, None, :, :] * axes[nb], axis=-1)  # (B, M, K)
            loss = loss + align_weight * jnp.mean(1.0 - align)
        return loss

    opt = optax.adam(learning_rate)

    @jax.jit
    def run(p):
        def step(carry, _):
            p, state = carry
            loss, grads = jax.value_and_grad(loss_fn)(p)
            updates, state = opt.update(grads, state, p)
            return (optax.apply_updates(p, updates), state), loss

        (p, _), losses = jax.lax.scan(step, (p, opt.init(p)), None, length=steps)
        return p, losses[-1]

    params, last = run(params)
    axes, lam, amp = unpack(params)
    return FitResult(axes, lam, amp, loss_fn(params) if steps == 0 else last)


def _log_vmf_norm(kappa):
    """log of kappa / (2 pi (1 - exp(-2 kappa))), the vMF normaliser in the SG form exp(kappa (u.x - 1))."""
    return jnp.log(kappa) - jnp.log(2.0 * jnp.pi) - jnp.log(-jnp.expm1(-2.0 * kappa))


def fit_em(directions, weights, values, init_axes, *, iterations: int = 100, init_sharpness: float = 10.0,
           max_sharpness: float = 1e5) -> FitResult:
    """Fit a K-lobe SG mixture to one spherical image by EM on a von Mises-Fisher mixture.

    The image is treated as weighted samples (weight = luminance x solid angle); vMF lobes are
    SGs with amplitude = energy x mixing weight x kappa / (2 pi (1 - exp(-2 kappa))). Per-channel
    amplitudes are then refitted by weighted least squares with the axes and sharpnesses fixed
    (clipped at 0). directions (N, 3), weights (N,), values (N, C), init_axes (K, 3).

    Numerics: not differentiable (an EM fitting loop).
    """
    directions = jnp.asarray(directions, jnp.float32)
    weights = jnp.asarray(weights, jnp.float32)
    values = jnp.asarray(values, jnp.float32)
    lum = jnp.maximum(jnp.mean(values, axis=-1), 0.0)
    w = lum * weights
    total = jnp.maximum(jnp.sum(w), 1e-30)  # a black image (a texel inside geometry) has no mass: no 0 / 0
    axes = jnp.asarray(init_axes, jnp.float32)
    k = axes.shape[0]
    kappa = jnp.full((k,), init_sharpness, jnp.float32)
    pi = jnp.full((k,), 1.0 / k, jnp.float32)

    @jax.jit
    def em(axes, kappa, pi):
        def body(carry, _):
            axes, kappa, pi = carry
            log_prior = (jnp.log(pi) + _log_vmf_norm(kappa))[None, :]
            logp = log_prior + kappa[None, :] * (directions @ axes.T - 1.0)  # (N, K)
            r = jax.nn.softmax(logp, axis=-1) * w[:, None]
            mass = jnp.maximum(jnp.sum(r, axis=0), 1e-30)
            resultant = r.T @ directions  # (K, 3)
            length = jnp.linalg.norm(resultant, axis=-1)
            axes = resultant / jnp.maximum(length, 1e-30)[:, None]
            rbar = jnp.clip(length / mass, 1e-6, 1.0 - 1e-6)
            kappa = jnp.clip(rbar * (3.0 - rbar**2) / (1.0 - rbar**2), 1e-3, max_sharpness)
            return (axes, kappa, mass / total), None

        (axes, kappa, pi), _ = jax.lax.scan(body, (axes, kappa, pi), None, length=iterations)
        return axes, kappa, pi

    axes, kappa, pi = em(axes, kappa, pi)
    basis = jnp.exp(kappa[None, :] * (directions @ axes.T - 1.0))  # (N, K)
    gram = (basis * weights[:, None]).T @ basis
    # a ridge relative to the Gram's scale: coincident lobes (a black image collapses every axis)
    # make it singular in float32, where an absolute 1e-9 is below rounding
    gram = gram + (1e-6 * jnp.trace(gram) / k + 1e-30) * jnp.eye(k)
    rhs = (basis * weights[:, None]).T @ values
    amplitudes = jnp.maximum(jnp.linalg.solve(gram, rhs), 0.0)
    pred = basis @ amplitudes
    loss = log_l2(pred, values, weights)
    return FitResult(axes, kappa, amplitudes, loss)
