"""Cube maps: solid angles, direction <-> texel, energy-preserving resampling on real HDR maps."""

import glob
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from jprt.sphere import cubemap


@pytest.mark.parametrize("n", [1, 2, 7, 64])
def test_solid_angles_sum_to_4pi(n):
    omega = np.asarray(cubemap.texel_solid_angles(n), np.float64)
    assert omega.shape == (6, n, n) and (omega > 0).all()
    assert omega.sum() == pytest.approx(4 * np.pi, rel=1e-5)


def test_solid_angles_match_fine_quadrature(x64):
    """Exact texel solid angles against a 64x64 sub-sampled dA cos / r^2 quadrature."""
    n, s = 4, 64
    fine = (np.arange(n * s) + 0.5) / (n * s) * 2 - 1
    x, y = np.meshgrid(fine, fine, indexing="ij")
    da = (2.0 / (n * s)) ** 2 / (1 + x * x + y * y) ** 1.5
    approx = da.reshape(n, s, n, s).sum(axis=(1, 3))
    np.testing.assert_allclose(np.asarray(cubemap.texel_solid_angles(n))[0], approx, rtol=1e-4)


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n=st.sampled_from([1, 4, 16, 33]))
def test_direction_texel_direction_stays_in_the_texel(seed, n):
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(200, 3)).astype(np.float32)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    face, row, col = cubemap.direction_to_texel(jnp.asarray(d), n)
    face2, u, v = cubemap.direction_to_face_uv(jnp.asarray(d))
    np.testing.assert_array_equal(face, face2)
    assert ((u >= -1e-6) & (u <= 1 + 1e-6) & (v >= -1e-6) & (v <= 1 + 1e-6)).all()
    back = cubemap.face_uv_to_direction(face, u, v)
    np.testing.assert_allclose(back, d, atol=2e-6)
    centre = cubemap.texel_directions(n)[face, row, col]
    f3, r3, c3 = cubemap.direction_to_texel(centre, n)
    np.testing.assert_array_equal(np.stack([f3, r3, c3]), np.stack([face, row, col]))


def test_texel_centres_round_trip():
    f, r, c = cubemap.direction_to_texel(cubemap.texel_directions(8), 8)
    np.testing.assert_array_equal(f, np.broadcast_to(np.arange(6)[:, None, None], (6, 8, 8)))
    np.testing.assert_array_equal(r, np.broadcast_to(np.arange(8)[None, :, None], (6, 8, 8)))
    np.testing.assert_array_equal(c, np.broadcast_to(np.arange(8)[None, None, :], (6, 8, 8)))


def test_faces_point_where_their_names_say():
    d = np.asarray(cubemap.face_uv_to_direction(jnp.arange(6), jnp.full(6, 0.5), jnp.full(6, 0.5)))
    np.testing.assert_allclose(d, [[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], atol=1e-7)


def _energy(equirect):
    h, w = equirect.shape[:2]
    return np.tensordot(np.asarray(cubemap.equirect_solid_angles(h, w), np.float64), np.asarray(equirect, np.float64),
                        axes=([0, 1], [0, 1]))


@pytest.mark.parametrize("subset", [pytest.param(slice(None), marks=pytest.mark.slow, id="all"),
                                    pytest.param(slice(0, 1), id="one")])
def test_resampling_preserves_energy_on_hdr_maps(assets, subset):
    """equirect -> cubemap -> equirect keeps the total energy sum(L dω) within 1 % per channel
    (one map in the default suite, all twelve in the slow one)."""
    from jprt.render.lights import EnvMap

    paths = sorted(glob.glob(os.path.join(assets, "envmaps", "*.hdr")))[subset]
    assert paths, "no .hdr maps in the shared assets"
    for path in paths:
        equirect = EnvMap.from_file(path).radiance
        cube = cubemap.equirect_to_cubemap(equirect, 128)
        cube_energy = np.tensordot(np.asarray(cubemap.texel_solid_angles(128), np.float64), np.asarray(cube, np.float64),
                                   axes=([0, 1, 2], [0, 1, 2]))
        back = cubemap.cubemap_to_equirect(cube, *equirect.shape[:2])
        e0 = _energy(equirect)
        np.testing.assert_allclose(cube_energy, e0, rtol=0.01, err_msg=os.path.basename(path))
        np.testing.assert_allclose(_energy(back), e0, rtol=0.01, err_msg=os.path.basename(path))


def test_resampling_constant_and_smooth_fields():
    const = jnp.full((16, 32, 2), 3.0)
    np.testing.assert_allclose(cubemap.equirect_to_cubemap(const, 8), 3.0, rtol=1e-5)
    np.testing.assert_allclose(cubemap.cubemap_to_equirect(jnp.full((6, 8, 8), 3.0), 16, 32), 3.0, rtol=1e-5)
    # f(d) = d_y: area averages over texels differ from centre values by O(texel size^2).
    cube = cubemap.texel_directions(32)[..., 1:2]
    eq = cubemap.cubemap_to_equirect(cube, 32, 64)
    expected = np.asarray(cubemap.equirect_directions(32, 64))[..., 1:2]
    np.testing.assert_allclose(eq, expected, atol=0.05)


def test_bilinear_sampling_reads_texel_centres_exactly_and_blends_between_them():
    rng = np.random.default_rng(0)
    cube = jnp.asarray(rng.uniform(0, 1, (6, 4, 4, 3)), jnp.float32)
    centres = cubemap.texel_directions(4)
    np.testing.assert_allclose(cubemap.sample_cubemap_bilinear(cube, centres), cube, rtol=1e-5, atol=1e-6)
    # half way between two centres of a row on +Z: the mean of the two texels
    d = cubemap.face_uv_to_direction(jnp.array(4), jnp.array(0.5), jnp.array(0.375))
    np.testing.assert_allclose(cubemap.sample_cubemap_bilinear(cube, d), 0.5 * (cube[4, 1, 1] + cube[4, 1, 2]),
                               rtol=1e-5)


def test_rotation_about_y_turns_the_environment():
    rng = np.random.default_rng(1)
    cube = jnp.asarray(rng.uniform(0, 1, (6, 8, 8, 3)), jnp.float32)
    # a quarter turn maps texel centres onto texel centres: a permutation of the texels (up to
    # float32's cos(pi / 2) = -4e-8, which moves each lookup by that fraction of a face)
    quarter = np.asarray(cubemap.rotate_cubemap_y(cube, np.pi / 2))
    np.testing.assert_allclose(np.sort(quarter.reshape(-1)), np.sort(np.asarray(cube).reshape(-1)), atol=1e-5)
    np.testing.assert_allclose(cubemap.rotate_cubemap_y(cube, 2 * np.pi), cube, atol=1e-5)  # the same rounding
    np.testing.assert_allclose(cubemap.rotate_cubemap_y(jnp.full((6, 8, 8, 1), 2.5), 0.7), 2.5, rtol=1e-6)
    # a smooth field f(d) = d_x turns into cos(a) d_x + sin(a) d_z ... seen at R(-a) d: f = c x - s z
    field = cubemap.texel_directions(32)[..., 0:1]
    a = 0.4
    turned = np.asarray(cubemap.rotate_cubemap_y(field, a))[..., 0]
    d = np.asarray(cubemap.texel_directions(32))
    # within a face, bilinear; within half a texel of an edge the clamp holds the edge texel's value,
    # off by at most the field's change over half a texel (pi / 4 / 32 rad, |grad f| <= 1): 0.025
    err = np.abs(turned - (np.cos(a) * d[..., 0] - np.sin(a) * d[..., 2]))
    assert err.max() <= 0.025 and np.sqrt(np.mean(err ** 2)) <= 2e-3, (err.max(), np.sqrt(np.mean(err ** 2)))
    # and its derivative in the angle, where a designer's gradient flows: the exact field's, but
    # for the edge bands (half a texel at each end of a 32-texel face axis: ~3 % of the lookups,
    # held at the edge texel's value) that carry no slope
    g = jax.grad(lambda t: jnp.sum(cubemap.rotate_cubemap_y(field, t)[..., 0] * jnp.asarray(d[..., 2])))(a)
    want = np.sum((-np.sin(a) * d[..., 0] - np.cos(a) * d[..., 2]) * d[..., 2])
    assert 0.94 * abs(want) <= abs(float(g)) <= abs(want) and np.sign(float(g)) == np.sign(want), (float(g), want)
