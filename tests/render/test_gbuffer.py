"""G-buffer: exact pixel-centre hits, unit normals, reflect(-v, n), materials, and AOV agreement."""

import numpy as np
import pytest

from jprt.render import cameras
from jprt.render.gbuffer import gbuffer
from jprt.render.lights import PointLights
from jprt.render.scenes import SceneHandle, cornell_box, glossy_cornell

LIGHT = PointLights.create([0, 0.7, 0], [1, 1, 1])


@pytest.fixture(scope="module")
def cornell(mi):
    handle = SceneHandle(cornell_box(area_light=False), LIGHT)
    camera = cameras.look_at((0.3, 0.2, 3.5), (0, 0, 0), width=32, height=24)
    return handle, camera, gbuffer(handle, camera)


def test_geometry_invariants(cornell):
    _, camera, gb = cornell
    v = gb.valid
    assert 0.5 < v.mean() < 1.0  # the open front of the box lets some rays escape
    np.testing.assert_allclose(np.linalg.norm(gb.normal[v], axis=-1), 1.0, atol=1e-5)
    np.testing.assert_allclose(np.linalg.norm(gb.view[v], axis=-1), 1.0, atol=1e-5)
    ndotv = np.sum(gb.normal * gb.view, axis=-1)
    assert (ndotv[v] >= -1e-6).all()
    expected = 2.0 * ndotv[..., None] * gb.normal - gb.view  # reflect(-v, n)
    np.testing.assert_allclose(gb.reflected[v], expected[v], atol=1e-5)
    # The view direction is minus the pixel-centre ray of an independent NumPy camera model,
    # and the hit lies on that ray.
    origins, directions = cameras.camera_rays(camera)
    np.testing.assert_allclose(-gb.view[v], directions[v], atol=1e-4)
    to_hit = gb.position - origins
    t = np.sum(to_hit * directions, axis=-1, keepdims=True)
    np.testing.assert_allclose(to_hit[v], (t * directions)[v], atol=1e-4)
    for field in ("position", "normal", "view", "reflected", "uv", "diffuse_albedo", "specular_albedo"):
        assert (getattr(gb, field)[~v] == 0).all(), field
    assert (gb.object_id[~v] == -1).all()


def test_objects_and_materials(cornell):
    handle, _, gb = cornell
    names = handle.object_names()
    floor = names.index("floor")
    on_floor = gb.object_id == floor
    assert on_floor.any()
    np.testing.assert_allclose(gb.normal[on_floor], np.broadcast_to([0, 1, 0], gb.normal[on_floor].shape), atol=1e-5)
    np.testing.assert_allclose(gb.diffuse_albedo[on_floor][0], [0.885809, 0.698859, 0.666422], rtol=1e-5)
    red = gb.object_id == names.index("red-wall")
    np.testing.assert_allclose(gb.diffuse_albedo[red][0], [0.570068, 0.0430135, 0.0443706], rtol=1e-5)
    assert (gb.roughness[gb.valid] == 1.0).all() and (gb.specular_albedo == 0).all()


def test_glossy_materials(mi):
    handle = SceneHandle(glossy_cornell(floor_roughness=0.3, sphere_roughness=0.05), LIGHT)
    gb = gbuffer(handle, cameras.look_at((0, 0, 3.9), (0, 0, 0), width=32, height=32))
    names = handle.object_names()
    sphere = gb.object_id == names.index("large-box")
    floor = gb.object_id == names.index("floor")
    assert sphere.any() and floor.any()
    np.testing.assert_allclose(gb.roughness[sphere], 0.05, rtol=1e-6)
    np.testing.assert_allclose(gb.roughness[floor], 0.3, rtol=1e-6)
    np.testing.assert_allclose(gb.specular_albedo[sphere][0], [0.95, 0.93, 0.88], rtol=1e-6)
    assert (gb.diffuse_albedo[sphere] == 0).all()  # a conductor has no diffuse lobe
    back = gb.object_id == names.index("back")
    assert len(np.unique(gb.diffuse_albedo[back][:, 2].round(4))) == 2  # the checker texture


def test_positions_agree_with_mitsuba_aov_on_planar_interiors(mi, cornell):
    """Where a pixel's 3x3 neighbourhood is one planar surface, Mitsuba's pixel-averaged AOV
    position lies within 10 % of the pixel's footprint on that surface of our pixel-centre hit
    (perspective makes the average differ slightly at grazing angles; a half-pixel shift would
    show as about 50 %)."""
    from numpy.lib.stride_tricks import sliding_window_view

    handle, camera, gb = cornell
    sensor = mi.load_dict(cameras.to_sensor_dict(camera, 256, mi))
    aov = np.array(mi.render(handle.scene, sensor=sensor, spp=256,
                             integrator=mi.load_dict({"type": "aov", "aovs": "p:position"})))[..., :3]
    ids = gb.object_id
    id_win = sliding_window_view(np.pad(ids, 1, constant_values=-2), (3, 3))
    n_win = sliding_window_view(np.pad(gb.normal, ((1, 1), (1, 1), (0, 0))), (3, 3), axis=(0, 1))
    planar = ((id_win == ids[..., None, None]).all(axis=(-1, -2)) & (ids >= 0)
              & (np.abs(n_win - gb.normal[..., None, None]).max(axis=(2, 3, 4)) < 1e-3))
    assert planar.sum() > 100
    distance = np.linalg.norm(gb.position - np.asarray(camera.origin), axis=-1)
    pixel_angle = 2.0 * np.tan(np.radians(camera.fov) / 2.0) / min(camera.width, camera.height)
    footprint = distance * pixel_angle / np.maximum(np.sum(gb.normal * gb.view, axis=-1), 1e-3)
    error = np.linalg.norm(aov - gb.position, axis=-1)
    assert (error[planar] <= 0.1 * footprint[planar]).all(), np.max(error[planar] / footprint[planar])


def test_gbuffer_rays_match_pixel_centres(cornell):
    """The ray-batch G-buffer (RRF training samples) sees what the image G-buffer sees when given
    the same pixel-centre rays (NumPy camera model == Mitsuba's sensor)."""
    from jprt.render.gbuffer import gbuffer_rays

    handle, camera, gb = cornell
    o, d = cameras.camera_rays(camera)
    rays = gbuffer_rays(handle, o.reshape(-1, 3), d.reshape(-1, 3))
    valid = rays.valid.reshape(gb.valid.shape)
    assert (valid == gb.valid).mean() > 0.99  # silhouette pixels may flip by rounding
    both = valid & gb.valid
    np.testing.assert_allclose(rays.position.reshape(gb.position.shape)[both], gb.position[both], atol=2e-3)
    same = both & (rays.object_id.reshape(gb.object_id.shape) == gb.object_id)
    assert same.sum() > 0.98 * both.sum()
    np.testing.assert_allclose(rays.normal.reshape(gb.normal.shape)[same], gb.normal[same], atol=1e-4)
    np.testing.assert_allclose(rays.diffuse_albedo.reshape(gb.diffuse_albedo.shape)[same], gb.diffuse_albedo[same],
                               atol=1e-5)
    with pytest.raises(ValueError, match="non-zero"):
        gbuffer_rays(handle, np.zeros((2, 3)), np.zeros((2, 3)))


def test_random_rays_inside_the_frustum():
    camera = cameras.look_at((0, 0, 3.9), (0, 0, 0), width=40, height=20, fov=30.0)
    o, d = cameras.random_rays(camera, 2000, np.random.default_rng(0))
    assert o.shape == d.shape == (2000, 3)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-12)
    # fov is along the smaller (vertical) axis: |y/z| <= tan(15 deg), |x/z| <= 2 tan(15 deg).
    t = np.tan(np.radians(15.0))
    assert np.all(np.abs(d[:, 1] / d[:, 2]) <= t + 1e-9) and np.abs(d[:, 1] / d[:, 2]).max() > 0.95 * t
    assert np.all(np.abs(d[:, 0] / d[:, 2]) <= 2 * t + 1e-9) and np.abs(d[:, 0] / d[:, 2]).max() > 1.9 * t
