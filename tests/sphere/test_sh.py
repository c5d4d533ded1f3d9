"""Spherical harmonics: orthonormality, scipy agreement, irradiance, OHLSH."""

import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from jprt.sphere import cubemap, sh
from jprt.sphere.quadrature import scipy_real_sh


def _gauss_grid(n_theta=40, n_phi=80):
    """Gauss-Legendre in cos(theta) x uniform phi: exact for SH products up to degree 2 n_theta - 1."""
    z, wz = np.polynomial.legendre.leggauss(n_theta)
    phi = 2 * np.pi * (np.arange(n_phi) + 0.5) / n_phi
    st_ = np.sqrt(1 - z**2)
    d = np.stack(np.broadcast_arrays(st_[:, None] * np.cos(phi), st_[:, None] * np.sin(phi), z[:, None]), -1)
    w = np.broadcast_to(wz[:, None] * (2 * np.pi / n_phi), d.shape[:2])
    return d.reshape(-1, 3), w.reshape(-1)


def test_orthonormal_by_quadrature(x64):
    d, w = _gauss_grid()
    y = np.asarray(sh.evaluate(jnp.asarray(d), 8))
    gram = (y * w[:, None]).T @ y
    np.testing.assert_allclose(gram, np.eye(81), atol=1e-4)
    # Also with the cube map's exact texel solid angles (midpoint rule).
    dc = cubemap.texel_directions(128).reshape(-1, 3)
    wc = np.asarray(cubemap.texel_solid_angles(128), np.float64).reshape(-1)
    yc = np.asarray(sh.evaluate(dc, 4), np.float64)
    np.testing.assert_allclose((yc * wc[:, None]).T @ yc, np.eye(25), atol=1e-4)


def test_matches_scipy_to_degree_8(x64):
    pytest.importorskip("scipy.special")
    rng = np.random.default_rng(0)
    d = rng.normal(size=(500, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    d[:3] = [[0, 0, 1], [0, 0, -1], [1, 0, 0]]  # poles and the equator
    np.testing.assert_allclose(np.asarray(sh.evaluate(jnp.asarray(d), 8)), scipy_real_sh(d, 8), atol=1e-10)


def test_high_degree_is_stable(x64):
    d, w = _gauss_grid(n_theta=64, n_phi=130)
    y = np.asarray(sh.evaluate(jnp.asarray(d), 30))
    assert np.isfinite(y).all()
    norms = np.sum(y * y * w[:, None], axis=0)
    np.testing.assert_allclose(norms, 1.0, atol=1e-8)


def test_projection_reconstructs_band_limited_functions(x64):
    rng = np.random.default_rng(1)
    coeffs = rng.normal(size=(16, 2))
    d, w = _gauss_grid()
    f = np.asarray(sh.reconstruct(jnp.asarray(coeffs), jnp.asarray(d)))
    np.testing.assert_allclose(np.asarray(sh.project(jnp.asarray(f), jnp.asarray(d), jnp.asarray(w), 3)), coeffs,
                               atol=1e-10)


def test_irradiance_of_constant_environment_is_pi_times_radiance():
    cube = jnp.full((6, 16, 16, 3), 2.5)
    coeffs = sh.project_cubemap(cube, 2)
    normals = jnp.asarray(np.random.default_rng(0).normal(size=(50, 3)))
    normals = normals / jnp.linalg.norm(normals, axis=1, keepdims=True)
    np.testing.assert_allclose(sh.irradiance(coeffs, normals), np.pi * 2.5, rtol=1e-4)
    eq = jnp.full((128, 256), 2.5)  # midpoint quadrature in theta: error O((pi / H)^2) on degree 4
    np.testing.assert_allclose(sh.irradiance(sh.project_equirect(eq, 4), normals), np.pi * 2.5, rtol=1e-4)


def test_irradiance_of_a_directional_cosine_lobe(x64):
    """For L(w) = max(w . z, 0), E(n = z) = int cos^2 = 2 pi / 3 (order-8 SH converge to it)."""
    d, w = _gauss_grid(n_theta=60, n_phi=120)
    radiance = np.maximum(d[:, 2], 0.0)
    coeffs = sh.project(jnp.asarray(radiance), jnp.asarray(d), jnp.asarray(w), 8)
    e = float(sh.irradiance(coeffs, jnp.asarray([[0.0, 0.0, 1.0]]))[0])
    assert e == pytest.approx(2 * np.pi / 3, rel=2e-3)


def test_ohlsh_equals_numerical_hemispherical_least_squares(x64):
    """Loos et al. 2011, Appendix B, against solving H1 a = H2 b by quadrature over z >= 0."""
    z, wz = np.polynomial.legendre.leggauss(64)
    z, wz = 0.5 * (z + 1), 0.5 * wz  # Gauss-Legendre on cos(theta) in [0, 1]
    phi = 2 * np.pi * (np.arange(128) + 0.5) / 128
    st_ = np.sqrt(1 - z**2)
    d = np.stack(np.broadcast_arrays(st_[:, None] * np.cos(phi), st_[:, None] * np.sin(phi), z[:, None]), -1).reshape(-1, 3)
    w = np.broadcast_to(wz[:, None] * (2 * np.pi / 128), (64, 128)).reshape(-1)
    y = np.asarray(sh.evaluate(jnp.asarray(d), 2))
    h1 = (y[:, :4] * w[:, None]).T @ y[:, :4]
    h2 = (y[:, :4] * w[:, None]).T @ y
    b = np.random.default_rng(2).normal(size=(9, 5))
    np.testing.assert_allclose(np.asarray(sh.ohlsh(jnp.asarray(b))), np.linalg.solve(h1, h2 @ b), atol=1e-10)


@settings(max_examples=10, deadline=None)
@given(bands=st.integers(1, 5), batch=st.tuples(st.integers(1, 4), st.integers(1, 3)))
def test_encoding_shapes(bands, batch):
    d = jnp.ones(batch + (3,)) / np.sqrt(3)
    out = sh.encode(d, bands)
    assert out.shape == batch + (bands * bands,) and out.dtype == jnp.float32


def test_bad_arguments():
    with pytest.raises(ValueError, match="1..5 bands"):
        sh.encode(jnp.ones((2, 3)), 6)
    with pytest.raises(ValueError, match="9 quadratic"):
        sh.ohlsh(jnp.ones(4))
    with pytest.raises(ValueError, match="square number"):
        sh.reconstruct(jnp.ones(5), jnp.ones((1, 3)))
