"""Spherical Gaussians: closed forms vs quadrature, stability at the extremes, SG x ASG
convolution accuracy, and mixture fitting by gradient descent and EM."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

from jprt.sphere import sg

from jprt.sphere.quadrature import integrate

LAMBDAS = np.logspace(-3, 4, 8)
# The polar grid of the quadratures of products of lobes (jprt.sphere.quadrature, dense at the
# pole): at 600 x 200 points every integral of this file is within 2.3e-6 of the 1500 x 400-500
# grid's (measured on all cases of the inner product and convolution tests; their tolerances are
# 1e-3 and 5 %), at a fifth of the cost.
GRID = {"n_theta": 600, "n_phi": 200}
ANGLES = [0.0, 0.3, 1.0, 2.0, np.pi]  # aligned ... antipodal


def _axis(angle):
    return np.array([np.sin(angle), 0.0, np.cos(angle)])


@pytest.mark.parametrize("lam", LAMBDAS)
def test_integral_matches_quadrature(x64, lam):
    u = np.array([0.0, 0.0, 1.0])
    closed = float(sg.integral(jnp.asarray(lam), 1.7))
    numeric = integrate(lambda v: sg.evaluate(jnp.asarray(v), jnp.asarray(u), lam, 1.7), u)
    assert closed == pytest.approx(numeric, rel=1e-3)


@pytest.mark.parametrize("lam1", LAMBDAS[::2])
@pytest.mark.parametrize("lam2", LAMBDAS[1::2])
@pytest.mark.parametrize("angle", ANGLES)
def test_inner_product_matches_quadrature(x64, lam1, lam2, angle):
    u1, u2 = np.array([0.0, 0.0, 1.0]), _axis(angle)
    closed = float(sg.inner_product(jnp.asarray(u1), jnp.asarray(lam1), 0.5, jnp.asarray(u2), jnp.asarray(lam2), 2.0))
    pole = u1 if lam1 >= lam2 else u2

    def product(v):
        v = jnp.asarray(v)
        return sg.evaluate(v, jnp.asarray(u1), lam1, 0.5) * sg.evaluate(v, jnp.asarray(u2), lam2, 2.0)

    numeric = integrate(product, pole, **GRID)
    if numeric < 1e-280:  # both underflow to 0 far apart at lambda = 1e4
        assert closed < 1e-280
    else:
        assert closed == pytest.approx(numeric, rel=1e-3)
    # The product SG integrates to the same value.
    p = sg.product(jnp.asarray(u1), jnp.asarray(lam1), 0.5, jnp.asarray(u2), jnp.asarray(lam2), 2.0)
    assert float(sg.integral(p.sharpness, p.amplitude)) == pytest.approx(closed, rel=1e-9, abs=1e-300)


def test_printed_currius_formula_is_wrong(x64):
    """Currius et al. Eq. 21-23 with the normalised mean axis disagrees with quadrature; ours agrees."""
    u1, u2, l1, l2 = np.array([0, 0, 1.0]), _axis(1.0), 10.0, 5.0
    um = (l1 * u1 + l2 * u2) / (l1 + l2)
    printed = 4 * np.pi * np.sinh(np.linalg.norm(um)) / (np.linalg.norm(um) * np.exp(l1 + l2))
    numeric = integrate(lambda v: np.exp(l1 * (v @ u1 - 1)) * np.exp(l2 * (v @ u2 - 1)), u1)
    assert abs(printed / numeric - 1) > 0.5
    ours = float(sg.inner_product(jnp.asarray(u1), jnp.asarray(l1), 1.0, jnp.asarray(u2), jnp.asarray(l2), 1.0))
    assert ours == pytest.approx(numeric, rel=1e-6)


@pytest.mark.parametrize("lam", [1e-6, 1e4])
@pytest.mark.parametrize("amp", [0.0, 1.0])
def test_finite_values_and_gradients_at_extremes(lam, amp):
    u = jnp.array([0.0, 0.0, 1.0])
    antipodal = -u
    v = jnp.array([0.6, 0.0, 0.8])
    fns = {
        "evaluate": lambda lam, a: sg.evaluate(v, u, lam, a),
        "integral": lambda lam, a: sg.integral(lam, a),
        "inner_aligned": lambda lam, a: sg.inner_product(u, lam, a, u, lam, a),
        "inner_antipodal": lambda lam, a: sg.inner_product(u, lam, a, antipodal, lam, a),
        "product": lambda lam, a: sg.product(u, lam, a, antipodal, lam, a).amplitude,
    }
    for name, fn in fns.items():
        value = fn(jnp.float32(lam), jnp.float32(amp))
        grads = jax.grad(fn, argnums=(0, 1))(jnp.float32(lam), jnp.float32(amp))
        assert np.isfinite(float(value)), name
        assert all(np.isfinite(float(g)) for g in grads), name


def test_gradients_check(x64):
    u1 = jnp.array([0.0, 0.6, 0.8])
    u2 = jnp.array([0.0, 0.0, 1.0])
    check_grads(jax.jit(lambda l1, l2, a: sg.inner_product(u1, l1, a, u2, l2, a)), (3.0, 7.0, 0.5), order=2)
    # jitted, each is one program (eagerly, about a hundred small ones compile)
    check_grads(jax.jit(lambda lam: sg.integral(lam, 2.0)), (0.01,), order=2)
    check_grads(jax.jit(lambda v: sg.evaluate(v, u1, 5.0, 1.0)), (jnp.array([0.3, 0.4, 0.866]),), order=1)


# --------------------------------------------------------------------------------------------
# SG x warped-GGX ASG convolution (Currius et al. 2020, Appendix B; Xu et al. 2013, Eq. 12)

# The closed form replaces the integral of the product by a Gaussian integral over the tangent
# plane. It is meant to hold when the product lobe is sharp, effective sharpness
# s = nu + min(lambda_x, lambda_y) >= 8 (nu = light sharpness / 2, an angular width under about
# 20 degrees), and the light axis is not in the far tail of the BRDF lobe: its offset from the
# reflected direction is <= 4 / sqrt(s). There it is within 5 % of quadrature.
# benchmarks/sphere.py writes the full table, including the cases outside this region (broad
# lobes: up to 100 %; far tails: about 7 %).
VALID_SHARPNESS = 8.0
MAX_OFFSET_WIDTHS = 4.0


@jax.jit
def _lobe_product(v, axis, light_sharpness, asg):
    """The quadrature's integrand, one compiled program for every case (eager, each of its ops was
    a pass over the 750k grid points)."""
    return sg.evaluate(v, axis, light_sharpness, 1.0) * sg.asg_evaluate(v, asg)


def convolution_case(roughness, light_sharpness, view_deg, offset_rad):
    """(closed form, quadrature, effective sharpness) for a light lobe near the reflected direction."""
    n = jnp.array([0.0, 0.0, 1.0], jnp.float64)
    t = np.radians(view_deg)
    view = jnp.array([np.sin(t), 0.0, np.cos(t)])
    asg = sg.warp_ndf_to_asg(n, view, jnp.asarray(roughness))
    z, y = np.asarray(asg.z), np.asarray(asg.y)
    axis = z * np.cos(offset_rad) + y * np.sin(offset_rad)
    closed = float(sg.convolve_sg_asg(jnp.asarray(axis), jnp.asarray(light_sharpness), 1.0, asg))
    pole = axis if light_sharpness > float(asg.sharpness_x) else z
    numeric = integrate(lambda v: _lobe_product(jnp.asarray(v), jnp.asarray(axis), jnp.asarray(light_sharpness), asg),
                        pole, **GRID)
    effective = 0.5 * light_sharpness + min(float(asg.sharpness_x), float(asg.sharpness_y))
    return closed, numeric, effective


@pytest.mark.parametrize("roughness", [0.05, 0.1, 0.25, 0.5, 1.0])
@pytest.mark.parametrize("light_sharpness", [1.0, 10.0, 100.0, 1000.0])
def test_sg_asg_convolution_in_its_region(x64, roughness, light_sharpness):
    checked = 0
    for view_deg in (0.0, 40.0, 80.0):
        for offset in (0.0, 0.1, 0.3):
            closed, numeric, effective = convolution_case(roughness, light_sharpness, view_deg, offset)
            assert np.isfinite(closed)
            if effective >= VALID_SHARPNESS and offset * np.sqrt(effective) <= MAX_OFFSET_WIDTHS:
                checked += 1
                assert abs(closed / numeric - 1) <= 0.05, (view_deg, offset, closed, numeric)
    if 0.5 * light_sharpness + 2.0 / roughness**2 / 8.0 >= VALID_SHARPNESS:
        assert checked >= 6  # at least the offsets 0 and 0.1 at every view angle


def test_warp_basis_is_orthonormal_and_degenerate_safe():
    n = jnp.array([0.0, 0.0, 1.0])
    for view in (jnp.array([0.0, 0.0, 1.0]), jnp.array([0.6, 0.0, 0.8]), jnp.array([0.0, -0.99, 0.141])):
        view = view / jnp.linalg.norm(view)
        asg = sg.warp_ndf_to_asg(n, view, jnp.asarray(0.3))
        frame = np.stack([np.asarray(asg.x), np.asarray(asg.y), np.asarray(asg.z)])
        np.testing.assert_allclose(frame @ frame.T, np.eye(3), atol=1e-5)
        np.testing.assert_allclose(np.asarray(asg.z), np.asarray(2 * jnp.dot(n, view) * n - view), atol=1e-6)


# --------------------------------------------------------------------------------------------
# Fitting

TRUE_AXES = np.array([[0.0, 0.0, 1.0], [0.8, 0.0, 0.6], [-0.6, 0.64, -0.48], [0.0, -0.8, -0.6]])
TRUE_SHARPNESS = np.array([20.0, 40.0, 10.0, 60.0])
TRUE_AMPLITUDES = np.array([[4.0, 3.0, 2.0], [2.0, 2.0, 5.0], [1.0, 3.0, 1.0], [6.0, 1.0, 1.0]])


@pytest.fixture(scope="module")
def mixture_image():
    from jprt.sphere import cubemap

    axes = TRUE_AXES / np.linalg.norm(TRUE_AXES, axis=1, keepdims=True)
    d = cubemap.texel_directions(32).reshape(-1, 3)
    w = cubemap.texel_solid_angles(32).reshape(-1)
    values = sg.mixture_evaluate(d, jnp.asarray(axes, jnp.float32), jnp.asarray(TRUE_SHARPNESS, jnp.float32),
                                 jnp.asarray(TRUE_AMPLITUDES, jnp.float32))
    return d, w, values, axes


def _matched_angles_deg(found, truth):
    found = np.asarray(found, np.float64)
    found = found / np.linalg.norm(found, axis=-1, keepdims=True)
    cos = np.clip(found @ truth.T, -1, 1)
    return np.degrees(np.arccos(cos.max(axis=0)))  # best match for each true lobe


def test_gd_recovers_a_known_four_lobe_mixture(mixture_image):
    d, w, values, axes = mixture_image
    init = sg.peak_axes(d, values, 4)
    fit = sg.fit_gd(d, w, values[None], init, steps=600, learning_rate=0.03)
    assert (_matched_angles_deg(fit.axes[0], axes) < 2.0).all()
    assert float(fit.loss) < 1e-4


def test_em_recovers_a_known_four_lobe_mixture(mixture_image):
    d, w, values, axes = mixture_image
    init = sg.peak_axes(d, values, 4)
    fit = sg.fit_em(d, w, values, init, iterations=200)
    assert (_matched_angles_deg(fit.axes, axes) < 2.0).all()
    order = np.argmax(np.asarray(fit.axes) @ axes.T, axis=0)
    np.testing.assert_allclose(np.asarray(fit.sharpness)[order], TRUE_SHARPNESS, rtol=0.15)


def test_em_on_a_black_image_is_black_not_nan(mixture_image):
    """A texel inside geometry has a black light field: no mass, every axis collapses; the fit
    must come back finite with zero amplitudes (it returned NaN: 0 / 0 and a singular Gram)."""
    d, w, values, _ = mixture_image
    fit = sg.fit_em(d, w, jnp.zeros_like(values), sg.peak_axes(d, values, 4), iterations=20)
    assert np.isfinite(np.asarray(fit.amplitudes)).all() and np.isfinite(float(fit.loss))
    np.testing.assert_array_equal(np.asarray(fit.amplitudes), 0.0)


def test_alignment_regulariser_pulls_neighbouring_lobes_together():
    """Two texels whose single lobes point 20 degrees apart: the regulariser brings them closer."""
    from jprt.sphere import cubemap

    d = cubemap.texel_directions(16).reshape(-1, 3)
    w = cubemap.texel_solid_angles(16).reshape(-1)
    a = np.array([[0.0, 0.0, 1.0]])
    b = np.array([[np.sin(0.35), 0.0, np.cos(0.35)]])
    images = jnp.stack([sg.mixture_evaluate(d, jnp.asarray(x, jnp.float32), jnp.array([30.0]), jnp.array([[2.0]]))
                        for x in (a, b)])
    init = jnp.stack([jnp.asarray(a, jnp.float32), jnp.asarray(b, jnp.float32)])
    neighbours = jnp.array([[1], [0]])
    free = sg.fit_gd(d, w, images, init, steps=300)
    tied = sg.fit_gd(d, w, images, init, steps=300, neighbours=neighbours, align_weight=1.0)

    def angle(fit):
        return np.degrees(np.arccos(np.clip(float(jnp.dot(fit.axes[0, 0], fit.axes[1, 0])), -1, 1)))

    assert angle(tied) < 0.5 * angle(free)


def _integral_and_slope_f64(lam: float) -> tuple[float, float]:
    """int_S2 G for a = 1 and its derivative in lambda, in float64 (Taylor series below 1e-3)."""
    if lam < 1e-3:
        return (2 * np.pi * (2 - 2 * lam + 4 / 3 * lam**2 - 2 / 3 * lam**3),
                2 * np.pi * (-2 + 8 / 3 * lam - 2 * lam**2 + 16 / 15 * lam**3))
    return (2 * np.pi * -np.expm1(-2 * lam) / lam,
            2 * np.pi * (2 * lam * np.exp(-2 * lam) + np.expm1(-2 * lam)) / lam**2)


@pytest.mark.parametrize("lam", [0.0, 1e-9, 1e-8, 1e-7, 1e-6, 1e-4, 0.0999, 0.1, 0.1001, 0.5, 3.0, 1e2, 1e4])
def test_integral_and_its_sharpness_gradient_match_float64_down_to_zero(lam):
    """float32 value and d/dlambda of sg.integral against float64 (issue 20: the quotient rule's
    cancellation made the gradient 4.5 % off at 1e-6, ten times off at 1e-8 and NaN at 0)."""
    value = float(sg.integral(jnp.float32(lam), 1.0))
    slope = float(jax.grad(lambda x: sg.integral(x, 1.0))(jnp.float32(lam)))
    want_value, want_slope = _integral_and_slope_f64(float(np.float32(lam)))
    assert value == pytest.approx(want_value, rel=1e-6)
    assert slope == pytest.approx(want_slope, rel=1e-5, abs=1e-30)


def test_inner_product_gradient_is_right_for_nearly_cancelling_antipodal_lobes():
    """Antipodal axes, sharpness 2.001 and 2: d = |l1 u1 + l2 u2| = 1e-3, where (1 - exp(-2 d)) / d
    comes from its series; the float32 gradient in lambda1 against a float64 central difference."""
    u = jnp.array([0.0, 0.0, 1.0])

    def f(l1, dtype):
        return sg.inner_product(u.astype(dtype), l1, 1.0, -u.astype(dtype), jnp.asarray(2.0, dtype), 1.0)

    g = float(jax.grad(lambda l1: f(l1, jnp.float32))(jnp.float32(2.001)))
    with jax.enable_x64(True):
        h = 1e-7
        want = float((f(jnp.float64(2.001 + h), jnp.float64) - f(jnp.float64(2.001 - h), jnp.float64)) / (2 * h))
    assert np.isfinite(g) and g == pytest.approx(want, rel=1e-4)
