"""Lighting: the one envmap conversion (checked through Mitsuba), validation, swapping lights."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from jprt.render import cameras, images
from jprt.render.lights import (EnvMap, PointLights, direction_to_equirect, from_mitsuba_envmap,
                                mitsuba_envmap_data, to_mitsuba_envmap)
from jprt.render.scenes import SceneHandle, cornell_box, empty
from jprt.sphere.cubemap import equirect_directions


@settings(max_examples=25, deadline=None)
@given(h=st.integers(2, 12), w=st.integers(2, 12), seed=st.integers(0, 2**31 - 1))
def test_conversion_round_trip_and_halo(h, w, seed):
    radiance = np.random.default_rng(seed).random((h, w, 3), dtype=np.float32) * 10
    bitmap = to_mitsuba_envmap(radiance)
    assert bitmap.shape == (2 * h + 1, w, 3)
    np.testing.assert_array_equal(from_mitsuba_envmap(bitmap), radiance)
    data = mitsuba_envmap_data(radiance)
    assert data.shape == (2 * h + 1, w + 2, 3)
    np.testing.assert_array_equal(data[:, 0], bitmap[:, -1])  # halo: last column first
    np.testing.assert_array_equal(data[:, -1], bitmap[:, 0])  # ... first column last
    np.testing.assert_array_equal(data[:, 1:-1], bitmap)


def test_direction_texel_round_trip():
    import jax

    with jax.enable_x64(True):  # the one equirect formula (jprt.sphere), evaluated in float64
        d = np.asarray(equirect_directions(16, 32))
    assert d.dtype == np.float64
    np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1.0, atol=1e-12)
    rows, cols = direction_to_equirect(d, 16, 32)
    np.testing.assert_allclose(rows, np.arange(16)[:, None] + 0 * cols, atol=1e-9)
    np.testing.assert_allclose(cols, np.arange(32)[None, :] + 0 * rows, atol=1e-9)


@pytest.mark.parametrize("bad, message", [
    (np.full((4, 8, 3), np.nan, np.float32), "must be finite"),
    (np.ones((4, 8), np.float32), "(H, W, 3)"),
    (np.ones((1, 8, 3), np.float32), "(H, W, 3)"),
])
def test_envmap_validation(bad, message):
    with pytest.raises(ValueError, match=message.replace("(", r"\(").replace(")", r"\)")):
        EnvMap.create(bad)


def test_envmap_with_one_nan_names_the_texel():
    radiance = np.ones((4, 8, 3), np.float32)
    radiance[2, 5, 1] = np.nan
    with pytest.raises(ValueError, match="1 NaN/inf entries \\(first at \\(2, 5, 1\\)"):
        EnvMap.create(radiance)


def _probe(handle, directions):
    origins = np.zeros_like(directions)
    return images.radiance_rays(handle, origins, directions, spp=1, seed=0)


def test_one_hot_texel_lights_exactly_its_direction(mi):
    """Mitsuba sees a one-hot jprt texel with value 1 exactly at the direction jprt names, and
    nothing at any other texel centre."""
    h, w = 8, 16
    radiance = np.zeros((h, w, 3), np.float32)
    radiance[3, 5] = 1.0
    handle = SceneHandle(empty(), EnvMap.create(radiance))
    dirs = np.asarray(equirect_directions(h, w)).reshape(-1, 3)
    seen = _probe(handle, dirs).reshape(h, w, 3)
    np.testing.assert_allclose(seen[3, 5], 1.0, atol=1e-5)
    seen[3, 5] = 0.0
    assert np.abs(seen).max() < 1e-5


def _bilinear(radiance, directions):
    """Independent NumPy bilinear lookup between jprt texel centres (away from the poles)."""
    h, w, _ = radiance.shape
    r, c = direction_to_equirect(directions, h, w)
    r0 = np.floor(r).astype(int)
    c0 = np.floor(c).astype(int)
    fr, fc = (r - r0)[:, None], (c - c0)[:, None]
    c0w, c1w = c0 % w, (c0 + 1) % w
    top = (1 - fc) * radiance[r0, c0w] + fc * radiance[r0, c1w]
    bottom = (1 - fc) * radiance[r0 + 1, c0w] + fc * radiance[r0 + 1, c1w]
    return (1 - fr) * top + fr * bottom


def test_mitsuba_lookup_is_bilinear_between_texel_centres(mi):
    rng = np.random.default_rng(1)
    h, w = 8, 16
    radiance = rng.random((h, w, 3)).astype(np.float32)
    handle = SceneHandle(empty(), EnvMap.create(radiance))
    theta = rng.uniform(np.pi / h, np.pi - np.pi / h, 500)  # between the first and last centre rows
    phi = rng.uniform(0, 2 * np.pi, 500)
    d = np.stack([np.sin(phi) * np.sin(theta), np.cos(theta), -np.cos(phi) * np.sin(theta)], axis=1)
    np.testing.assert_allclose(_probe(handle, d), _bilinear(radiance, d), rtol=2e-4, atol=2e-5)


def test_swapping_lights_needs_no_rebuild_and_matches_a_fresh_scene(mi):
    camera = cameras.look_at((0, 0, 3.9), (0, 0, 0), width=8, height=8)
    a = PointLights.create([0.0, 0.8, 0.0], [4.0, 4.0, 4.0])
    b = PointLights.create([-0.5, 0.3, 0.4], [1.0, 2.0, 3.0])
    handle = SceneHandle(cornell_box(area_light=False), a)
    handle.set_lighting(b)
    assert handle.builds == 1
    swapped = images.render(handle, camera, spp=4, seed=3)
    fresh = images.render(SceneHandle(cornell_box(area_light=False), b), camera, spp=4, seed=3)
    np.testing.assert_allclose(swapped, fresh, rtol=1e-5, atol=1e-6)

    env1 = EnvMap.create(np.ones((4, 8, 3), np.float32))
    env2 = EnvMap.create(np.full((4, 8, 3), 3.0, np.float32))
    probe = SceneHandle(empty(), env1)
    probe.set_lighting(env2)
    assert probe.builds == 1
    np.testing.assert_allclose(_probe(probe, np.asarray(equirect_directions(4, 8)).reshape(-1, 3)), 3.0, rtol=1e-5)
    probe.set_lighting(EnvMap.create(np.ones((8, 16, 3), np.float32)))  # new shape: rebuild
    assert probe.builds == 2


def test_point_light_validation():
    with pytest.raises(ValueError, match="NaN"):
        PointLights.create([0.0, np.nan, 0.0], [1.0, 1.0, 1.0])
    with pytest.raises(ValueError, match="position"):
        PointLights.create([[0.0, 0.0]], [1.0, 1.0, 1.0])
    lights = PointLights.create([[0, 0, 0], [1, 1, 1]], [2, 2, 2])  # one colour for all
    assert lights.count == 2 and lights.intensity.shape == (2, 3)
