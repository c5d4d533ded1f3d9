"""Datasets: cache hits render nothing, interrupted renders resume, corrupt entries are re-rendered."""

import glob
import os

import numpy as np
import pytest

from jprt.render import cameras, images
from jprt.render.dataset import open_dataset, render_dataset
from jprt.render.lights import EnvMap, PointLights
from jprt.render.scenes import cornell_box

SCENE = cornell_box(area_light=False)
CAMERAS = [cameras.look_at((x, 0, 3.9), (0, 0, 0), width=8, height=8) for x in (-0.3, 0.3)]
LIGHTS = [PointLights.create([0, 0.7, 0], [3, 3, 3]), PointLights.create([0.4, 0.5, 0.2], [1, 2, 3])]


def _render(cache, **kw):
    return render_dataset(SCENE, CAMERAS, LIGHTS, spp=4, seed=7, cache_dir=str(cache), progress=False, **kw)


def test_second_call_renders_nothing(tmp_path, mi):
    first = _render(tmp_path)
    assert first.stats == {"rendered": 2 + 2 + 4, "cached": 0, "corrupt": 0}  # lightings, gbuffers, items
    before = dict(images.RENDER_STATS)
    second = _render(tmp_path)
    assert dict(images.RENDER_STATS) == before  # measured: no Mitsuba render call at all
    assert second.stats == {"rendered": 0, "cached": 8, "corrupt": 0}
    assert second.folder == first.folder
    np.testing.assert_array_equal(second.radiance(3)["indirect"], first.radiance(3)["indirect"])
    # A different setting is a different dataset.
    assert render_dataset(SCENE, CAMERAS[:1], LIGHTS[:1], spp=2, cache_dir=str(tmp_path),
                          progress=False).folder != first.folder


def test_contents(tmp_path, mi):
    ds = _render(tmp_path)
    assert len(ds) == 4 and ds.items[1] == (0, 1)
    rad = ds.radiance(1)
    assert rad["direct"].shape == rad["indirect"].shape == (8, 8, 3)
    assert ds.gbuffer(1).normal.shape == (8, 8, 3)
    lighting = ds.lighting(1)
    np.testing.assert_array_equal(lighting.position, LIGHTS[1].position)
    reopened = open_dataset(ds.folder)
    np.testing.assert_array_equal(reopened.stacked("direct"), ds.stacked("direct"))
    assert reopened.cameras == CAMERAS


def test_interrupted_render_resumes(tmp_path, mi):
    written = []

    def interrupt_after_three(name):
        written.append(name)
        if len(written) == 3:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        _render(tmp_path, on_entry=interrupt_after_three)
    folder = os.path.dirname(glob.glob(str(tmp_path / "datasets" / "*" / "spec.json"))[0])
    assert not glob.glob(os.path.join(folder, "*.tmp")) and not glob.glob(os.path.join(folder, ".*.tmp"))
    resumed = _render(tmp_path)
    assert resumed.stats == {"rendered": 5, "cached": 3, "corrupt": 0}
    fresh = _render(tmp_path / "fresh")
    np.testing.assert_array_equal(resumed.stacked("indirect"), fresh.stacked("indirect"))


@pytest.mark.parametrize("damage", ["truncate", "flip_byte", "delete_data"])
def test_corrupt_entry_is_detected_and_rerendered(tmp_path, mi, damage):
    ds = _render(tmp_path)
    reference = ds.radiance(2)["indirect"]
    path = os.path.join(ds.folder, "item_00001_00000.npz")
    data = open(path, "rb").read()
    if damage == "truncate":
        open(path, "wb").write(data[: len(data) // 2])
    elif damage == "flip_byte":
        open(path, "wb").write(data[:-20] + bytes([data[-20] ^ 0xFF]) + data[-19:])
    else:
        os.remove(path)
    with pytest.raises(ValueError, match="corrupt"):
        ds.radiance(2)  # never silently used
    with pytest.warns(UserWarning, match="failed its checksum"):
        repaired = _render(tmp_path)
    assert repaired.stats == {"rendered": 1, "cached": 7, "corrupt": 1}
    np.testing.assert_array_equal(repaired.radiance(2)["indirect"], reference)  # same seed, same pixels


def test_bad_input_writes_nothing(tmp_path, mi):
    cache = tmp_path / "cache"
    with pytest.raises(ValueError, match="spp must be a positive integer"):
        render_dataset(SCENE, CAMERAS, LIGHTS, spp=-4, cache_dir=str(cache), progress=False)
    with pytest.raises(FileNotFoundError, match="scene file not found"):
        render_dataset(str(tmp_path / "missing.xml"), CAMERAS, LIGHTS, spp=1, cache_dir=str(cache), progress=False)
    bad = np.ones((4, 8, 3), np.float32)
    bad[1, 2, 0] = np.nan
    with pytest.raises(ValueError, match="must be finite"):
        render_dataset(SCENE, CAMERAS, [EnvMap(bad)], spp=1, cache_dir=str(cache), progress=False)
    with pytest.raises(ValueError, match="zip"):
        render_dataset(SCENE, CAMERAS, LIGHTS[:1], spp=1, pairs="zip", cache_dir=str(cache), progress=False)
    assert not cache.exists()


def test_envmap_dataset(tmp_path, mi):
    sky = np.ones((4, 8, 3), np.float32)
    ds = render_dataset(SCENE, CAMERAS[:1], [EnvMap.create(sky)], spp=2, cache_dir=str(tmp_path), progress=False)
    np.testing.assert_array_equal(ds.lighting(0).radiance, sky)
    assert ds.radiance(0)["direct"].mean() > 0
