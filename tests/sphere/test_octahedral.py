"""Octahedral maps: round trips, exact texel solid angles, hemisphere."""

import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from jprt.sphere import octahedral


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**31 - 1))
def test_encode_decode_round_trip(seed):
    d = np.random.default_rng(seed).normal(size=(300, 3)).astype(np.float32)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    uv = octahedral.encode(jnp.asarray(d))
    assert (jnp.abs(uv) <= 1.0 + 1e-6).all()
    np.testing.assert_allclose(octahedral.decode(uv), d, atol=2e-6)
    # Upper hemisphere <-> inner diamond.
    inner = np.asarray(jnp.abs(uv[:, 0]) + jnp.abs(uv[:, 1]) <= 1.0 + 1e-6)
    assert (inner == (d[:, 2] >= -1e-6)).all() or np.all(np.abs(d[inner != (d[:, 2] >= 0), 2]) < 1e-5)


@pytest.mark.parametrize("n", [2, 4, 16, 64])
def test_solid_angles_are_exact(n):
    omega = np.asarray(octahedral.texel_solid_angles(n), np.float64)
    assert (omega > 0).all()
    assert omega.sum() == pytest.approx(4 * np.pi, rel=1e-6)
    upper = np.asarray(octahedral.hemisphere_solid_angles(n), np.float64)
    assert upper.sum() == pytest.approx(2 * np.pi, rel=1e-6)
    assert ((upper > 0) == np.asarray(octahedral.hemisphere_mask(n))).all()


def test_solid_angles_match_monte_carlo():
    rng = np.random.default_rng(0)
    d = rng.normal(size=(2_000_000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    row, col = octahedral.direction_to_texel(jnp.asarray(d, jnp.float32), 8)
    counts = np.bincount(np.asarray(row) * 8 + np.asarray(col), minlength=64).reshape(8, 8)
    expected = np.asarray(octahedral.texel_solid_angles(8)) / (4 * np.pi) * len(d)
    assert np.abs(counts - expected).max() < 5 * np.sqrt(expected.max())


def test_texel_centres_round_trip_and_odd_size_error():
    row, col = octahedral.direction_to_texel(octahedral.texel_directions(16), 16)
    np.testing.assert_array_equal(row, np.broadcast_to(np.arange(16)[:, None], (16, 16)))
    np.testing.assert_array_equal(col, np.broadcast_to(np.arange(16)[None, :], (16, 16)))
    with pytest.raises(ValueError, match="even size"):
        octahedral.texel_solid_angles(5)
