"""Haar wavelets on cube maps: orthonormality, reconstruction, Parseval, indexing, top-K."""

import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from jprt.sphere import cubemap, haar


def test_basis_is_orthonormal_at_face_size_8():
    n = 8
    basis = jnp.stack([haar.basis_function(i, n).reshape(-1) for i in range(6 * n * n)])
    gram = np.asarray(basis @ basis.T)
    np.testing.assert_allclose(gram, np.eye(6 * n * n), atol=1e-6)


def test_reconstruction_at_face_size_64():
    rng = np.random.default_rng(0)
    cube = rng.lognormal(0.0, 2.0, size=(6, 64, 64, 3)).astype(np.float32)  # HDR-like dynamic range
    back = np.asarray(haar.inverse(haar.forward(jnp.asarray(cube))))
    assert np.linalg.norm(back - cube) / np.linalg.norm(cube) < 1e-5
    premult = haar.inverse(haar.forward(jnp.asarray(cube), premultiply=True), premultiplied=True)
    assert np.linalg.norm(np.asarray(premult) - cube) / np.linalg.norm(cube) < 1e-5


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n=st.sampled_from([1, 2, 4, 16]), channels=st.sampled_from([(), (1,), (3,)]))
def test_parseval_and_shapes(seed, n, channels):
    cube = np.random.default_rng(seed).normal(size=(6, n, n) + channels).astype(np.float32)
    c = haar.forward(jnp.asarray(cube))
    assert c.shape == cube.shape and c.dtype == jnp.float32
    # the energies summed by NumPy (in JAX each of the 12 shapes compiled its own sum)
    energy = float(np.sum(np.asarray(c, np.float64) ** 2))
    np.testing.assert_allclose(energy, float(np.sum(cube.astype(np.float64) ** 2)), rtol=1e-5)


def test_matches_pywavelets_per_face():
    pywt = pytest.importorskip("pywt", reason="PyWavelets is the reference 2D Haar (test extra)")
    face = np.random.default_rng(3).normal(size=(16, 16))
    ours = np.asarray(haar.forward(jnp.asarray(np.broadcast_to(face, (6, 16, 16)).astype(np.float32))))[0]
    approx, *details = pywt.wavedec2(face, "haar")
    assert ours[0, 0] == pytest.approx(approx[0, 0], rel=1e-5)
    for level, (ch, cv, cd) in enumerate(details):
        r = 2**level
        # pywt's (cH, cV, cD) are our (V, H, D) up to sign conventions: compare magnitudes.
        np.testing.assert_allclose(np.abs(ours[r:2 * r, :r]), np.abs(ch), rtol=1e-4, atol=1e-5)
        np.testing.assert_allclose(np.abs(ours[:r, r:2 * r]), np.abs(cv), rtol=1e-4, atol=1e-5)
        np.testing.assert_allclose(np.abs(ours[r:2 * r, r:2 * r]), np.abs(cd), rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("n", [1, 2, 8, 32])
def test_flat_index_round_trip(n):
    idx = jnp.arange(6 * n * n)
    w = haar.unflatten_index(idx, n)
    np.testing.assert_array_equal(haar.flat_index(*w, n), idx)
    w = type(w)(*map(np.asarray, w))  # counted by NumPy (in JAX each size compiled its own reductions)
    assert int(np.sum(w.band == haar.BAND_SCALING)) == 6
    # Each level l holds 3 * 4^l coefficients per face.
    for level in range(int(np.log2(n))):
        count = int(np.sum((w.level == level) & (w.band != haar.BAND_SCALING)))
        assert count == 6 * 3 * 4**level
    assert (w.i >= 0).all() and (w.i < np.left_shift(1, w.level)).all()


def test_basis_support_matches_level():
    n = 16
    for index in (0, 1, 37, 5 * 256 + 200):
        w = haar.unflatten_index(index, n)
        support = np.count_nonzero(np.asarray(haar.basis_function(index, n)))
        expected = n * n if int(w.band) == haar.BAND_SCALING else (n >> int(w.level)) ** 2
        assert support == expected
        assert float(haar.support_area(n)[w.face, *divmod(index % (n * n), n)]) == pytest.approx(expected / n**2)


def test_top_k_and_retained_energy():
    rng = np.random.default_rng(1)
    cube = rng.lognormal(size=(6, 16, 16, 3)).astype(np.float32)
    c = haar.forward(jnp.asarray(cube))
    energies = [float(haar.retained_energy(c, k)) for k in (1, 8, 64, 300, 6 * 256)]
    assert all(a <= b + 1e-7 for a, b in zip(energies, energies[1:]))
    assert energies[-1] == pytest.approx(1.0, abs=1e-6)
    idx, values = haar.top_k(c, 64)
    mags = np.linalg.norm(np.asarray(c).reshape(-1, 3), axis=1)
    assert set(np.asarray(idx).tolist()) == set(np.argsort(-mags)[:64].tolist())
    np.testing.assert_array_equal(values, np.asarray(c).reshape(-1, 3)[np.asarray(idx)])
    idx_area, _ = haar.top_k(c, 64, area_weighted=True)
    weighted = mags * np.asarray(haar.support_area(16)).reshape(-1)
    assert set(np.asarray(idx_area).tolist()) == set(np.argsort(-weighted)[:64].tolist())


def test_premultiplied_dot_product_is_quadrature():
    """With solid-angle premultiplied lighting, sum_k L_k T_k = sum_texels L T dω."""
    rng = np.random.default_rng(2)
    light = rng.random((6, 8, 8)).astype(np.float32)
    transport = rng.random((6, 8, 8)).astype(np.float32)
    lhs = float(jnp.sum(haar.forward(jnp.asarray(light), premultiply=True) * haar.forward(jnp.asarray(transport))))
    rhs = float(np.sum(light * transport * np.asarray(cubemap.texel_solid_angles(8))))
    assert lhs == pytest.approx(rhs, rel=1e-5)


def test_rejects_non_power_of_two():
    with pytest.raises(ValueError, match="power of two"):
        haar.forward(jnp.zeros((6, 6, 6)))
    with pytest.raises(ValueError, match="cube map"):
        haar.forward(jnp.zeros((5, 8, 8)))
