"""Scenes: descriptions, validation, XML scenes from the shared assets, default cameras."""

import os

import numpy as np
import pytest

from jprt.render import images, scenes
from jprt.render.gbuffer import gbuffer
from jprt.render.scenes import SceneHandle


def test_descriptions_validate():
    with pytest.raises(ValueError, match="unknown Cornell box objects"):
        scenes.cornell_box(materials={"roof": {"type": "diffuse", "albedo": [1, 1, 1]}})
    with pytest.raises(ValueError, match="roughness"):
        scenes.glossy_cornell(floor_roughness=0.0)
    with pytest.raises(ValueError, match="unknown type"):
        scenes.cornell_box(materials={"floor": {"type": "velvet"}})
    with pytest.raises(FileNotFoundError, match="scene file not found"):
        scenes.xml("/no/such/scene.xml")
    with pytest.raises(ValueError, match="unknown scene"):
        scenes.describe("sponza")
    desc = scenes.glossy_cornell()
    assert scenes.describe(desc) == desc  # full descriptions pass through unchanged


def test_bitterli_xml_scene(assets, mi):
    path = os.path.join(assets, "scenes", "cornell_box_picture", "scene_picture.xml")
    handle = SceneHandle(scenes.xml(path))
    camera = handle.default_camera(24, 24)
    assert camera.fov == pytest.approx(19.5, rel=1e-3)
    r = images.direct_indirect(handle, camera, spp=8)
    assert r.direct.mean() > 0 and r.indirect.mean() > 0 and (r.indirect >= -1e-6).all()
    gb = gbuffer(handle, camera)
    assert gb.valid.mean() > 0.9
    assert len(set(handle.object_names())) == len(handle.object_names())
    np.testing.assert_allclose(np.linalg.norm(gb.normal[gb.valid], axis=-1), 1.0, atol=1e-5)


def test_open_top_glossy_cornell(mi):
    """open_top drops the ceiling (and is only recorded when set, so older cache hashes hold)."""
    assert "open_top" not in scenes.glossy_cornell()
    desc = scenes.glossy_cornell(open_top=True)
    assert scenes.describe(desc) == desc and desc["open_top"] is True
    with pytest.raises(ValueError, match="open_top"):
        scenes.glossy_cornell(open_top=True, area_light=True)
    names = SceneHandle(desc).object_names()
    assert "ceiling" not in names and "floor" in names
    assert "ceiling" in SceneHandle(scenes.glossy_cornell()).object_names()


def _xml(tmp_path, body: str, integrator: str = "path") -> str:
    path = tmp_path / "room.xml"
    path.write_text(f"""<scene version="3.0.0">
  <integrator type="{integrator}"/>
  <sensor type="perspective"><float name="fov" value="50"/>
    <transform name="to_world"><lookat origin="0, 0, 4" target="0, 0, 0" up="0, 1, 0"/></transform>
    <film type="hdrfilm"><integer name="width" value="32"/><integer name="height" value="24"/></film></sensor>
  <shape type="rectangle" id="floor"><bsdf type="diffuse"/></shape>
  {body}
</scene>""")
    return str(path)


@pytest.mark.mitsuba
def test_a_scene_file_with_a_non_radiance_integrator_is_refused_in_one_line(mi, tmp_path):
    """A glass's interior medium is accepted (volpath renders it: tests/render/test_media.py); an
    integrator that does not estimate radiance is refused in one line."""
    from jprt.render.scenes import SceneHandle

    glass = _xml(tmp_path, """<shape type="sphere" id="glass"><bsdf type="dielectric"/>
      <medium type="homogeneous" name="interior"><rgb name="albedo" value="0.5"/></medium></shape>""")
    assert SceneHandle({"name": "xml", "path": glass}).has_media
    depth = _xml(tmp_path, "", integrator="depth")
    with pytest.raises(ValueError, match="integrator 'depth' does not estimate"):
        SceneHandle({"name": "xml", "path": depth})
    SceneHandle({"name": "xml", "path": _xml(tmp_path, "", integrator="volpath")})  # same radiance: accepted


@pytest.mark.mitsuba
def test_the_file_camera_is_the_scene_files_sensor(mi, tmp_path):
    from jprt.render.dataset import DEFAULT_DATASET_CONFIG, cameras_from_config
    from jprt.render.scenes import SceneHandle

    path = _xml(tmp_path, "")
    (camera,) = cameras_from_config({**DEFAULT_DATASET_CONFIG["cameras"], "kind": "file", "width": 32, "height": 24},
                                    {"name": "xml", "path": path})
    assert camera == SceneHandle({"name": "xml", "path": path}).default_camera(32, 24)
    np.testing.assert_allclose(camera.origin, [0, 0, 4], atol=1e-5)
    np.testing.assert_allclose(camera.target, [0, 0, 3], atol=1e-5)
    with pytest.raises(ValueError, match="needs the scene"):
        cameras_from_config({**DEFAULT_DATASET_CONFIG["cameras"], "kind": "file"})


@pytest.mark.mitsuba
def test_the_ceiling_opening_cuts_only_the_top_of_a_room(mi, tmp_path):
    """opening="ceiling" removes a mesh's up/down-facing triangles in the top slab (a box room loses
    its top two of 12, keeping its BSDF), drops shapes lying wholly in the slab, keeps the rest, and
    is only recorded when set."""
    path = _xml(tmp_path, """
      <shape type="cube" id="room"><transform name="to_world"><scale value="2"/></transform>
        <bsdf type="twosided"><bsdf type="diffuse"><rgb name="reflectance" value="0.3"/></bsdf></bsdf></shape>
      <shape type="rectangle" id="lamp"><bsdf type="diffuse"/><transform name="to_world">
        <rotate x="1" angle="90"/><scale value="0.2"/><translate y="1.95"/></transform></shape>""")
    assert "opening" not in scenes.xml(path)  # older descriptions (and cache hashes) unchanged
    with pytest.raises(ValueError, match="unknown scene opening 'window'"):
        scenes.xml(path, opening="window")
    desc = scenes.xml(path, opening="ceiling")
    assert scenes.describe({"name": "xml", "path": path, "opening": "ceiling"}) == desc
    closed, opened = SceneHandle(scenes.xml(path)), SceneHandle(desc)
    assert closed.object_names() == ["floor", "room", "lamp"] and opened.object_names() == ["floor", "room"]
    room = {s.id(): s for s in opened.shapes()}["room"]
    assert room.face_count() == 10
    np.testing.assert_allclose(np.ravel(mi.traverse(room.bsdf())["brdf_0.reflectance.value"]), 0.3)

    def hits(handle, direction):
        ray = mi.Ray3f(mi.Point3f(0.5, 0.0, 0.5), mi.Vector3f(*direction))
        return bool(np.ravel(handle.scene.ray_intersect(ray).is_valid())[0])

    assert hits(closed, [0, 1, 0]) and not hits(opened, [0, 1, 0])  # the sky through the ceiling
    for direction in ([0, -1, 0], [1, 0, 0], [0, 0, -1]):  # floor and walls stay
        assert hits(opened, direction)
