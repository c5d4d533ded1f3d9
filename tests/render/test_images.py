"""Direct / indirect split: indirect >= -3 sigma, direct + indirect = full within noise, ray batches."""

import numpy as np
import pytest

from jprt.render import cameras, images
from jprt.render.lights import PointLights
from jprt.render.scenes import CORNELL_CAMERA, SceneHandle, cornell_box, glossy_cornell

SEEDS = (11, 12, 13, 14)


# Relative tolerance on image means per scene: the glossy scene's caustic (a near-mirror sphere
# lit by a point light) makes its estimates far noisier at test spp.
MEAN_RTOL = {"cornell_box": 0.04, "glossy_cornell": 0.15}


@pytest.fixture(scope="module", params=["cornell_box", "glossy_cornell"])
def split(request, mi):
    scene = cornell_box(area_light=False) if request.param == "cornell_box" else glossy_cornell()
    handle = SceneHandle(scene, PointLights.create([0.1, 0.7, 0.2], [4.0, 4.0, 4.0]))
    camera = cameras.look_at((0, 0, 3.9), (0, 0, 0), width=16, height=16)
    renders = [images.direct_indirect(handle, camera, spp=16, seed=s) for s in SEEDS]
    independent = [images.render(handle, camera, spp=16, seed=100 + s) for s in SEEDS]
    return request.param, handle, camera, renders, independent


def test_indirect_nonnegative_within_noise(split):
    _, _, _, renders, _ = split
    indirect = np.stack([r.indirect for r in renders])
    sigma = indirect.std(axis=0, ddof=1)  # per-pixel noise of one render, from 4 seeds
    assert (indirect >= -3.0 * sigma[None] - 1e-6).all()
    assert indirect.mean() > 0.0


def test_direct_plus_indirect_equals_full_within_noise(split):
    """Against independently seeded full renders (the same-seed identity would prove nothing)."""
    _, _, _, renders, independent = split
    ours = np.stack([r.direct + r.indirect for r in renders])
    theirs = np.stack(independent)
    diff = ours.mean(axis=0) - theirs.mean(axis=0)
    se = np.sqrt((ours.var(axis=0, ddof=1) + theirs.var(axis=0, ddof=1)) / len(SEEDS))
    z = diff / np.maximum(se, 1e-6)
    # Image-level: mean difference is within 3 standard errors of the image mean.
    se_mean = np.sqrt(np.sum(se**2)) / se.size
    assert abs(diff.mean()) <= 3.0 * se_mean + 1e-6
    # Pixel-level: few |z| > 4 (t-distribution with 3 dof has heavy tails, so allow 3 %).
    assert np.mean(np.abs(z) > 4.0) < 0.03


def test_ray_batches_match_the_image_estimate(split):
    """Rays jittered uniformly inside each pixel estimate the same box-filtered pixel values as
    the image renders (pixel centres alone would not: edges and partly covered pixels differ)."""
    name, handle, camera, renders, _ = split
    rng = np.random.default_rng(0)
    bundles = [cameras.camera_rays(camera, rng.random((camera.height, camera.width, 2))) for _ in range(8)]
    origins = np.concatenate([o.reshape(-1, 3) for o, _ in bundles])
    directions = np.concatenate([d.reshape(-1, 3) for _, d in bundles])
    rays = images.indirect_rays(handle, origins, directions, spp=8, seed=5)
    assert (rays.indirect >= -1e-6).all()  # same-seed cancellation holds per ray too
    np.testing.assert_allclose(rays.direct + rays.indirect, rays.full, rtol=1e-6, atol=1e-6)
    for field in ("direct", "indirect"):
        image_mean = np.mean([getattr(r, field).mean() for r in renders])
        assert getattr(rays, field).mean() == pytest.approx(image_mean, rel=MEAN_RTOL[name]), field


def test_bad_spp_and_rays(mi):
    handle = SceneHandle(cornell_box(area_light=False), PointLights.create([0, 0.7, 0], [1, 1, 1]))
    camera = cameras.look_at((0, 0, 3.9), (0, 0, 0), width=4, height=4)
    for spp in (-1, 0, 2.5, True):
        with pytest.raises(ValueError, match="spp must be a positive integer"):
            images.render(handle, camera, spp=spp)
    with pytest.raises(ValueError, match="non-zero"):
        images.radiance_rays(handle, np.zeros((2, 3)), np.zeros((2, 3)), spp=1)


def test_builtin_cornell_box_with_its_own_area_light(mi):
    """The embedded default scene, lit by its own emitter (lighting=None): the light is visible to
    the camera in the direct image and the indirect is positive."""
    handle = SceneHandle(cornell_box(), None)
    origin, target, fov = CORNELL_CAMERA
    camera = cameras.look_at(origin, target, fov=fov, width=16, height=16)
    r = images.direct_indirect(handle, camera, spp=8, seed=0)
    assert r.direct.max() > 5.0  # the area light itself (radiance ~18 in red)
    assert r.indirect.mean() > 0.01 and (r.indirect >= -1e-6).all()
