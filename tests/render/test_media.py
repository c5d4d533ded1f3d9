"""Participating media inside surfaces (issue 45): a scene file whose glass holds an interior
medium renders with Mitsuba's volpath instead of being refused; a medium around the camera is
refused in one line."""

import numpy as np
import pytest

from jprt.render import images, scenes
from jprt.render.gbuffer import gbuffer
from jprt.render.scenes import SceneHandle

pytestmark = pytest.mark.mitsuba

#: A purely absorbing medium (albedo 0), red passing most: sigma_t = 6 x (0.2, 0.5, 1) per unit.
MEDIUM = """<medium type="homogeneous" name="interior"><rgb name="albedo" value="0"/>
      <rgb name="sigma_t" value="0.2, 0.5, 1"/><float name="scale" value="6"/></medium>"""


def _scene(tmp_path, name: str, body: str, sensor_extra: str = "") -> str:
    path = tmp_path / f"{name}.xml"
    path.write_text(f"""<scene version="3.0.0">
  <bsdf type="diffuse" id="white"><rgb name="reflectance" value="0.7"/></bsdf>
  <shape type="rectangle" id="floor"><ref id="white"/>
    <transform name="to_world"><rotate x="1" angle="-90"/><scale value="3"/><translate y="-1"/></transform></shape>
  <shape type="rectangle" id="back"><ref id="white"/>
    <transform name="to_world"><scale value="3"/><translate z="-2"/></transform></shape>
  <shape type="rectangle" id="lamp">
    <transform name="to_world"><rotate x="1" angle="90"/><scale value="0.5"/><translate y="1.5"/></transform>
    <emitter type="area"><rgb name="radiance" value="10"/></emitter></shape>
  {body}
  <sensor type="perspective"><float name="fov" value="50"/>{sensor_extra}
    <transform name="to_world"><lookat origin="0, 0.3, 4" target="0, -0.2, 0" up="0, 1, 0"/></transform>
    <film type="hdrfilm"><integer name="width" value="32"/><integer name="height" value="32"/></film></sensor>
</scene>""")
    return str(path)


def _glass(name: str, centre, radius: float, medium: bool) -> str:
    x, y, z = centre
    return (f'<shape type="sphere" id="{name}"><point name="center" x="{x}" y="{y}" z="{z}"/>'
            f'<float name="radius" value="{radius}"/><bsdf type="dielectric"/>{MEDIUM if medium else ""}</shape>')


def test_a_visible_glass_with_an_absorbing_interior_renders_with_volpath(mi, tmp_path):
    with_medium = SceneHandle(scenes.xml(_scene(tmp_path, "tinted", _glass("ball", (-0.3, -0.5, 0.3), 0.5, True))))
    clear = SceneHandle(scenes.xml(_scene(tmp_path, "clear", _glass("ball", (-0.3, -0.5, 0.3), 0.5, False))))
    assert with_medium.has_media and images.integrator_type(with_medium) == "volpath"
    assert not clear.has_media and images.integrator_type(clear) == "path"
    # the description says so (a dataset's spec records volpath for it); a file without one is unchanged
    assert with_medium.description.get("media") is True and "media" not in clear.description
    camera = with_medium.default_camera()
    tinted, plain = (images.direct_indirect(h, camera, spp=64, seed=1) for h in (with_medium, clear))
    for r in (tinted, plain):
        assert all(np.isfinite(x).all() for x in r)
        # volpath's max_depth counts like path's: full - direct with one seed cancels the shared prefix
        assert r.indirect.min() >= -1e-5 and r.indirect.mean() > 0
    ball = gbuffer(with_medium, camera).object_id == with_medium.object_names().index("ball")
    assert ball.sum() > 30
    through, clear_through = tinted.full[ball].mean(axis=0), plain.full[ball].mean(axis=0)
    # the medium absorbs along the refracted paths, blue (sigma_t 6 per unit) far more than red (1.2)
    assert (through < 0.8 * clear_through).all() and through[2] < 0.5 * through[0]


def test_a_medium_no_path_reaches_changes_nothing(mi, tmp_path):
    """A glass with an interior medium shut inside an opaque box (one-sided diffuse: no light gets in
    or out) leaves the image as it is without the medium: volpath (with the medium) against path
    (without), same seed. Tolerances: the image means within 1 % (their Monte Carlo error at 64 spp
    over 1024 pixels is about 0.15 %, so that is 6 sigma or more), and the per-pixel mean absolute
    difference no larger than 1.25 x that between two independently seeded path renders (the two
    integrators' noise is partly correlated: measured 0.63 x)."""
    box = ('<shape type="cube" id="box"><ref id="white"/>'
           '<transform name="to_world"><scale value="0.4"/><translate x="0.9" y="-0.6"/></transform></shape>')
    hidden = SceneHandle(scenes.xml(_scene(tmp_path, "hidden", box + _glass("hidden", (0.9, -0.6, 0.0), 0.25, True))))
    empty = SceneHandle(scenes.xml(_scene(tmp_path, "empty", box + _glass("hidden", (0.9, -0.6, 0.0), 0.25, False))))
    assert hidden.has_media and not empty.has_media
    camera = hidden.default_camera()
    ours = images.render(hidden, camera, spp=64, seed=2)
    theirs = images.render(empty, camera, spp=64, seed=2)
    again = images.render(empty, camera, spp=64, seed=9)
    np.testing.assert_allclose(ours.mean(), theirs.mean(), rtol=0.01)
    assert np.abs(ours - theirs).mean() <= 1.25 * np.abs(again - theirs).mean()


def test_environment_transport_refuses_media(mi, tmp_path):
    from jprt.render.transport import environment_transport

    handle = SceneHandle(scenes.xml(_scene(tmp_path, "tinted", _glass("ball", (-0.3, -0.5, 0.3), 0.5, True))))
    with pytest.raises(ValueError, match="participating media") as e:
        environment_transport(handle, np.zeros((1, 3)), np.array([[0.0, 0.0, -1.0]]), face_size=2, spp=1)
    assert "\n" not in str(e.value)


def test_a_medium_around_the_camera_is_refused_in_one_line(mi, tmp_path):
    fog = _scene(tmp_path, "fog", '<medium type="homogeneous" id="fog"><rgb name="albedo" value="0.5"/></medium>',
                 sensor_extra='<ref id="fog"/>')
    with pytest.raises(ValueError, match=r"fog\.xml: media that fill the camera's space are not supported") as e:
        SceneHandle(scenes.xml(fog))
    assert "\n" not in str(e.value)


def test_a_dataset_of_a_file_with_a_medium_records_volpath(mi, tmp_path):
    import json

    from jprt.render import cameras
    from jprt.render.dataset import render_dataset

    path = _scene(tmp_path, "tinted", _glass("ball", (-0.3, -0.5, 0.3), 0.5, True))
    cam = cameras.look_at((0, 0.3, 4), (0, -0.2, 0), width=4, height=4)
    ds = render_dataset(path, [cam], [None], spp=1, cache_dir=str(tmp_path / "cache"), gbuffers=False, progress=False)
    with open(f"{ds.folder}/spec.json") as f:
        assert json.load(f)["render"]["integrator"] == "volpath"
