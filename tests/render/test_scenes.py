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
