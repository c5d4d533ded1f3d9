"""Latin hypercube sampling (Ren et al. 2013, Appendix A)."""

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from jprt.render.sampling import latin_hypercube


@settings(max_examples=30, deadline=None)
@given(n=st.integers(1, 50), d=st.integers(1, 5), seed=st.integers(0, 1000))
def test_one_sample_per_stratum(n, d, seed):
    rng = np.random.default_rng(seed)
    lo = rng.uniform(-2, 0, d)
    hi = lo + rng.uniform(0.1, 3, d)
    x = latin_hypercube(np.random.default_rng(seed), n, lo, hi)
    assert x.shape == (n, d)
    assert np.all((x >= lo) & (x <= hi))
    strata = np.floor((x - lo) / (hi - lo) * n).astype(int)
    for a in range(d):
        assert sorted(strata[:, a]) == list(range(n))


def test_degenerate_and_bad_boxes():
    x = latin_hypercube(np.random.default_rng(0), 4, [0, 1], [1, 1])
    assert np.all(x[:, 1] == 1)
    with pytest.raises(ValueError, match="lo <= hi"):
        latin_hypercube(np.random.default_rng(0), 4, [0, 1], [1, 0])
    with pytest.raises(ValueError, match="at least one"):
        latin_hypercube(np.random.default_rng(0), 0, [0], [1])


#: Two rooms side by side, a solid wall between them; the file's camera stands in the left one
#: and looks at its back wall. The scene's bounds (its light box) span both.
_TWO_ROOMS = """<scene version="3.0.0">
  <sensor type="perspective"><float name="fov" value="60"/>
    <transform name="to_world"><lookat origin="-2, 1, 1.8" target="-2, 1, -2" up="0, 1, 0"/></transform></sensor>
  <shape type="cube" id="left"><transform name="to_world"><scale x="1.9" y="1.5" z="2"/><translate x="-2" y="1.5"/>
    </transform><bsdf type="diffuse"/><boolean name="flip_normals" value="true"/></shape>
  <shape type="cube" id="right"><transform name="to_world"><scale x="1.9" y="1.5" z="2"/><translate x="2" y="1.5"/>
    </transform><bsdf type="diffuse"/><boolean name="flip_normals" value="true"/></shape>
</scene>"""


@pytest.mark.mitsuba
def test_lights_drawn_for_a_file_light_what_its_camera_sees(mi, tmp_path, monkeypatch):
    """In a file whose light box spans a room the camera does not see, every light free_lights
    draws lights at least MIN_LIT_FRACTION of the camera's view (none lands in the other room);
    with the rule off, the same draw puts lights there; the built-in scenes have no such view."""
    from jprt.render import sampling
    from jprt.render.scenes import SceneHandle

    path = tmp_path / "two_rooms.xml"
    path.write_text(_TWO_ROOMS)
    desc = {"name": "xml", "path": str(path), "keep_emitters": False}
    regions = sampling.scene_regions(desc)
    lo, hi = regions["light_lo"], regions["light_hi"]
    assert lo[0] < -1 and hi[0] > 1  # the box spans both rooms

    def draw():
        rng = np.random.default_rng(0)
        return sampling.free_lights(desc, sampling.latin_hypercube(rng, 12, lo, hi), lo, hi, rng)

    lights = draw()
    handle = SceneHandle(desc)
    lit = sampling.lit_fraction(handle, lights)
    assert np.all(lights[:, 0] < -0.1) and lit.min() >= sampling.MIN_LIT_FRACTION
    # lights share a ray batch: each one's share is what it scores alone
    np.testing.assert_array_equal(lit, [sampling.lit_fraction(handle, p[None])[0] for p in lights])
    assert sampling.lit_fraction(handle, [[2.0, 2.0, 0.0]])[0] == 0.0  # the right room lights none of it
    monkeypatch.setattr(sampling, "MIN_LIT_FRACTION", 0.0)
    assert np.any(draw()[:, 0] > 0.1)
    assert sampling.lit_fraction(SceneHandle({"name": "cornell_box", "area_light": False}), [[0, 1, 0]]) is None


def test_centroidal_points_cover_a_set_evenly_without_crowding_its_edges():
    """Picks of a uniform square's points: distinct members of the set; the largest distance from
    a point of the set to its nearest pick (the gap a held-out draw can fall in) well below that
    of as many random picks; no more of them near the edges than the edges' share of the area
    (a farthest-point draw puts most of its first picks there)."""
    from scipy.spatial import cKDTree

    from jprt.render.sampling import centroidal_points

    rng = np.random.default_rng(3)
    pool = rng.random((4000, 2))
    picks = centroidal_points(pool, 64, np.random.default_rng(0))
    assert picks.shape == (64, 2)
    members = cKDTree(pool).query(picks)[0]
    assert np.all(members == 0.0) and len(np.unique(picks, axis=0)) == 64
    gap = cKDTree(picks).query(pool)[0].max()
    random_gaps = [cKDTree(pool[np.random.default_rng(s).choice(4000, 64, replace=False)]).query(pool)[0].max()
                   for s in range(5)]
    assert gap < 0.75 * min(random_gaps)
    edge = 0.05
    near = np.mean(np.any((picks < edge) | (picks > 1 - edge), axis=1))
    assert near <= 1.0 - (1.0 - 2 * edge) ** 2  # 0.19, the edge band's share of the square
    with pytest.raises(ValueError, match="n <= 10"):
        centroidal_points(pool[:10], 11, rng)


@pytest.mark.mitsuba
def test_even_lights_fill_only_the_space_that_lights_the_view(mi, tmp_path):
    """even_lights in the two-room file: as many distinct lights as asked, every one in the room
    the camera sees, at free_lights' clearance from geometry, lighting at least MIN_LIT_FRACTION
    of the view; and 400 lights drawn as free_lights draws them (the held-out lights) are nearer
    to one of them, at the farthest, than to as many lights drawn that way."""
    from scipy.spatial import cKDTree

    from jprt.render import sampling
    from jprt.render.lightmap import free_positions
    from jprt.render.scenes import SceneHandle

    path = tmp_path / "two_rooms.xml"
    path.write_text(_TWO_ROOMS)
    desc = {"name": "xml", "path": str(path), "keep_emitters": False}
    regions = sampling.scene_regions(desc)
    lights = sampling.even_lights(desc, 12, regions["light_lo"], regions["light_hi"], np.random.default_rng(0))
    handle = SceneHandle(desc)
    assert lights.shape == (12, 3) and len(np.unique(lights, axis=0)) == 12
    assert np.all(lights[:, 0] < -0.1)
    assert sampling.lit_fraction(handle, lights).min() >= sampling.MIN_LIT_FRACTION
    box = handle.scene.bbox()
    clearance = 0.02 * float(np.max(np.asarray(box.max) - np.asarray(box.min)))
    assert free_positions(handle, lights, clearance=clearance).all()
    lo, hi = regions["light_lo"], regions["light_hi"]

    def drawn(n, seed):
        rng = np.random.default_rng(seed)
        return sampling.free_lights(desc, sampling.latin_hypercube(rng, n, lo, hi), lo, hi, rng)

    held_out = drawn(400, 5)
    assert cKDTree(lights).query(held_out)[0].max() < 0.85 * cKDTree(drawn(12, 0)).query(held_out)[0].max()
