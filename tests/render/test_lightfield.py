"""Light-field capture (jprt.render.lightfield, Currius et al. 2020 §3): what a texel sees, the
split into full and bounced light, the below-surface mask, texels inside geometry, the cache."""

import numpy as np
import pytest

from jprt.render import lightfield
from jprt.render.lights import EnvMap

pytestmark = pytest.mark.mitsuba


def test_open_sky_is_the_environment_and_nothing_bounces(mi, tmp_path):
    """Nothing in the way: the full map is the constant environment above each texel's surface,
    the bounced part is exactly 0 (same seeds), below the surface is masked and 0."""
    atlas = {"position": np.array([[0.0, 0.0, 0.0], [1.0, 2.0, 3.0]], np.float32),
             "normal": np.array([[0.0, 1.0, 0.0], [0.6, 0.0, 0.8]], np.float32), "texel_size": 0.1}
    env = EnvMap.create(np.full((8, 16, 3), [0.5, 1.0, 2.0], np.float32))
    lf = lightfield.capture_lightfield("empty", env, atlas=atlas, size=8, spp=2, cache_dir=str(tmp_path),
                                       progress=False)
    assert lf.full.shape == (2, 8, 8, 3) and lf.below.shape == (2, 8, 8)
    assert (lf.flags == lightfield.OK).all()
    above = ~lf.below
    np.testing.assert_allclose(lf.full[above], np.broadcast_to([0.5, 1.0, 2.0], lf.full[above].shape), rtol=1e-5)
    assert np.array_equal(lf.indirect, np.zeros_like(lf.indirect))
    assert np.array_equal(lf.full[lf.below], np.zeros_like(lf.full[lf.below]))
    # the mask is the hemisphere of each normal: about half of the directions
    assert 0.35 < lf.below.mean() < 0.65


def test_jittered_capture_averages_each_pixel_over_its_footprint(mi, tmp_path):
    """capture jitter: under a constant sky a pixel wholly above the surface holds the sky exactly,
    one the horizon cuts holds the sky times the share of its paths above (strictly between 0 and
    the sky somewhere), nothing bounces, and the irradiance quadrature comes out near pi L."""
    from jprt.methods.sg_lightfield.model import texel_irradiance
    from jprt.sphere import octahedral

    normal = np.array([0.3, 0.9, 0.3]) / np.linalg.norm([0.3, 0.9, 0.3])  # the horizon cuts through pixels
    atlas = {"position": np.array([[0.0, 0.0, 0.0]], np.float32), "normal": normal[None].astype(np.float32),
             "texel_size": 0.1}
    sky = np.array([0.5, 1.0, 2.0], np.float32)
    env = EnvMap.create(np.full((8, 16, 3), sky, np.float32))
    n = 8
    lf = lightfield.capture_lightfield("empty", env, atlas=atlas, size=n, spp=16, cache_dir=str(tmp_path),
                                       progress=False, jitter=True)
    assert lf.meta["jitter"] and np.array_equal(lf.indirect, np.zeros_like(lf.indirect))
    # pixels whose four corners are all above the surface: the sky to rounding
    c = np.asarray(octahedral.texel_centers(n), np.float64)
    corners = [np.asarray(octahedral.decode(np.clip(c + np.array(o) / n, -1, 1))) @ normal for o in
               [(-1, -1), (-1, 1), (1, -1), (1, 1)]]
    inside = np.all([y > 1e-6 for y in corners], axis=0)
    assert inside.sum() > 4
    np.testing.assert_allclose(lf.full[0][inside], np.broadcast_to(sky, lf.full[0][inside].shape), rtol=1e-5)
    share = lf.full[0, ..., 1] / sky[1]
    assert (share <= 1 + 1e-5).all() and ((share > 0.01) & (share < 0.99)).any()  # the horizon's pixels
    e = np.asarray(texel_irradiance(lf.full, lf.normal, n))[0]
    np.testing.assert_allclose(e, np.pi * sky, rtol=0.15)


def test_cornell_floor_texels_under_the_boxes_are_flagged_and_the_rest_see_the_light(mi, tmp_path, monkeypatch):
    scene = {"name": "cornell_box", "area_light": True}
    kwargs = dict(objects=["floor"], resolution=16, size=4, spp=4, block=64, cache_dir=str(tmp_path), progress=False)
    lf = lightfield.capture_lightfield(scene, None, **kwargs)
    inside = lf.flags == lightfield.INSIDE
    assert inside.any() and (~inside).sum() > inside.sum()  # the blocks cover part of the floor
    assert np.array_equal(lf.full[inside], np.zeros_like(lf.full[inside]))  # never filled in from neighbours
    ok = ~inside
    assert np.isfinite(lf.full).all() and np.isfinite(lf.indirect).all()
    # the ceiling light is seen directly from the open floor: full light exceeds the bounced part
    assert lf.full[ok].sum() > lf.indirect[ok].sum() > 0
    # every texel above the floor plane: the capture points are, too
    assert (lf.position[:, 1] > np.asarray(lf.atlas["position"])[:, 1]).all()

    def no_render(*args, **kwargs):
        raise AssertionError("a cached capture rendered again")

    monkeypatch.setattr(lightfield, "capture_block", no_render)
    again = lightfield.capture_lightfield(scene, None, **kwargs)
    assert np.array_equal(again.full, lf.full) and np.array_equal(again.flags, lf.flags)


def test_a_push_never_passes_through_a_surface(mi):
    """Floor texels under the Cornell blocks stay INSIDE however far a push may go: moving them
    onto a block's lid would capture the wrong light field."""
    from jprt.render import lightmap
    from jprt.render.scenes import SceneHandle

    handle = SceneHandle({"name": "cornell_box", "area_light": False})
    atlas = lightmap.build_atlas(handle, ["floor"], resolution=16)
    _, near = lightfield.capture_points(handle, atlas.position, atlas.normal, atlas.texel_size)
    _, far = lightfield.capture_points(handle, atlas.position, atlas.normal, atlas.texel_size, max_push=100.0)
    assert (near == lightfield.INSIDE).sum() > 0
    np.testing.assert_array_equal(far, near)
