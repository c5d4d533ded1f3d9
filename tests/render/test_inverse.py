"""``jprt.render.inverse.SphereLights``: Mitsuba's own gradient of an image objective in point
lights modelled as small emitting spheres (the peer of ``jprt design``)."""

import numpy as np
import pytest

pytestmark = pytest.mark.mitsuba


@pytest.fixture(scope="module")
def handle(mi):
    from jprt.render.scenes import SceneHandle, cornell_box

    return SceneHandle(cornell_box(area_light=False))


@pytest.fixture(scope="module")
def camera(handle):
    return handle.default_camera(12, 12)


@pytest.fixture(scope="module")
def target(handle, camera):
    """Mitsuba's image of a hidden point light at (0.2, 0.5, 0.1)."""
    from jprt.inputs import PointLights
    from jprt.render import images

    handle.set_lighting(PointLights.create(np.array([[0.2, 0.5, 0.1]]), np.ones((1, 3))))
    r = images.centre_rays(handle, camera, spp=16, seed=1)
    return np.asarray(r.direct) + np.asarray(r.indirect)


@pytest.fixture(scope="module")
def peer(handle, camera, target):
    from jprt.render.inverse import SphereLights

    return SphereLights(handle, camera, target, count=1, radius=0.02, spp=4)


def test_the_intensity_gradient_is_the_derivative_of_mitsubas_objective(peer, target):
    """A render is linear in the spheres' radiance, so with the primal drawn with seed s and the
    derivative pass with seed s', prb's gradient of sum((img_s - T)^2) / sum(T^2) in intensity
    channel c is exactly 2 sum((img_s - T)_c img_s',c) / (I_c sum(T^2)): both images from
    Mitsuba's own primal renders with those seeds."""
    position, intensity = np.array([[-0.1, 0.4, 0.0]]), np.array([[0.8, 0.6, 0.5]])
    value, d_pos, d_int = peer.loss_and_grad(position, intensity, seed=3, seed_grad=10)
    img3, img10 = peer.image(position, intensity, seed=3), peer.image(position, intensity, seed=10)
    norm = np.sum(target ** 2)
    assert value == pytest.approx(np.sum((img3 - target) ** 2) / norm, rel=1e-5)
    want = 2.0 * np.sum((img3 - target) * img10, axis=(0, 1)) / (intensity[0] * norm)
    np.testing.assert_allclose(d_int[0], want, rtol=1e-4)
    assert np.isfinite(d_pos).all()


def test_a_light_moved_away_is_pulled_back_towards_the_hidden_one(handle, camera, target):
    """The hidden light sits at x = 0.2; a light at x = -0.6 (same height and depth) lights the
    red wall too much and the green one too little: the position gradient's x part (projective
    sampling, noisy: a single 16-spp estimate has the wrong sign one time in four at this size)
    averaged over 16 seeds at 64 spp says move right, by several of its standard errors."""
    from jprt.render.inverse import SphereLights

    peer = SphereLights(handle, camera, target, count=1, radius=0.02, spp=64)
    gx = np.array([peer.loss_and_grad(np.array([[-0.6, 0.5, 0.1]]), np.ones((1, 3)), seed=s)[1][0, 0]
                   for s in range(16)])
    assert gx.mean() < -4.0 * gx.std() / np.sqrt(len(gx))


def test_bad_arguments_are_refused(handle):
    from jprt.render.inverse import SphereLights

    camera = handle.default_camera(4, 4)
    with pytest.raises(ValueError, match="frame"):
        SphereLights(handle, camera, np.zeros((5, 4, 3)), count=1, radius=0.01)
    with pytest.raises(ValueError, match="radius > 0"):
        SphereLights(handle, camera, np.zeros((4, 4, 3)), count=1, radius=0.0)


def test_a_scene_file_with_its_own_camera_renders_at_the_asked_one(mi, tmp_path):
    """A scene file keeps its own camera as the scene's first sensor; the peer's scene is built
    from ``scene_dict``, which leaves it out, so the image is the asked camera's (the file's
    1280 x 720 sensor took its place on the staircase)."""
    from jprt.inputs import Camera
    from jprt.render.inverse import SphereLights
    from jprt.render.scenes import SceneHandle

    path = tmp_path / "room.xml"
    path.write_text("""<scene version="3.0.0">
  <sensor type="perspective"><float name="fov" value="50"/>
    <transform name="to_world"><lookat origin="0, 0, 4" target="0, 0, 0" up="0, 1, 0"/></transform>
    <film type="hdrfilm"><integer name="width" value="32"/><integer name="height" value="24"/></film></sensor>
  <shape type="rectangle" id="floor"><bsdf type="diffuse"/></shape>
</scene>""")
    handle = SceneHandle({"name": "xml", "path": str(path), "keep_emitters": False})
    assert not any(isinstance(v, mi.Sensor) for v in handle.scene_dict().values())
    camera = Camera((0.0, 0.0, 3.0), (0.0, 0.0, 0.0), (0.0, 1.0, 0.0), 40.0, 6, 6)
    peer = SphereLights(handle, camera, np.ones((6, 6, 3), np.float32), count=1, radius=0.05, spp=2)
    image = peer.image(np.array([[0.0, 0.0, 0.5]]), np.ones((1, 3)))
    assert image.shape == (6, 6, 3) and np.abs(image).max() > 0
