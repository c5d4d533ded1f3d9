"""Configs: typed overrides, deep merge, unknown keys named with the nearest valid key, stable hash."""

import json
import os
import subprocess
import sys

import pytest
from hypothesis import given
from hypothesis import strategies as st

from jprt.config import ConfigError, apply_overrides, config_hash, merge, parse_value, save_resolved

BASE = {
    "train": {"max_iters": 100, "lr": 1e-3, "schedule": "cosine", "use_lm": True, "sizes": [20, 10]},
    "dataset": {"scene": {"name": "cornell_box", "area_light": False}, "spp": 64, "tag": None},
}


@pytest.mark.parametrize("text, value", [
    ("3", 3), ("3.5", 3.5), ("1e-4", 1e-4), ("true", True), ("False", False), ("none", None), ("null", None),
    ("[1, 2]", [1, 2]), ("'quoted'", "quoted"), ("cosine", "cosine"), ('{"a": 1}', {"a": 1}),
])
def test_parse_value(text, value):
    assert parse_value(text) == value and type(parse_value(text)) is type(value)


def test_overrides_are_typed_and_deep_merged():
    out = apply_overrides(BASE, ["train.max_iters=50", "train.lr=1", "dataset.scene.area_light=true",
                                 "dataset.tag=run7", "train.sizes=[30, 30, 5]"])
    assert out["train"]["max_iters"] == 50
    assert out["train"]["lr"] == 1.0 and isinstance(out["train"]["lr"], float)  # int widened to float
    assert out["dataset"]["scene"] == {"name": "cornell_box", "area_light": True}
    assert out["dataset"]["tag"] == "run7" and out["train"]["sizes"] == [30, 30, 5]
    assert BASE["train"]["max_iters"] == 100  # the defaults are never mutated


def test_unknown_key_names_the_closest():
    with pytest.raises(ConfigError, match=r"unknown config key 'train.max_iter'; did you mean 'train.max_iters'\?"):
        apply_overrides(BASE, ["train.max_iter=5"])
    with pytest.raises(ConfigError, match="did you mean 'dataset.spp'"):
        merge(BASE, {"dataset": {"sppp": 3}})


def test_type_errors():
    with pytest.raises(ConfigError, match="expects int"):
        apply_overrides(BASE, ["train.max_iters=fast"])
    with pytest.raises(ConfigError, match="expects bool"):
        apply_overrides(BASE, ["train.use_lm=3"])
    with pytest.raises(ConfigError, match="not of the form"):
        apply_overrides(BASE, ["train.max_iters"])


def test_named_section_is_replaced_when_its_name_changes():
    out = merge(BASE, {"dataset": {"scene": {"name": "xml", "path": "/x.xml"}}})
    assert out["dataset"]["scene"] == {"name": "xml", "path": "/x.xml"}


json_values = st.recursive(st.none() | st.booleans() | st.integers() | st.text(max_size=5)
                           | st.floats(allow_nan=False), lambda c: st.lists(c, max_size=3) | st.dictionaries(
                               st.text(max_size=4), c, max_size=3), max_leaves=10)


@given(config=st.dictionaries(st.text(min_size=1, max_size=4), json_values, max_size=5))
def test_hash_stable_under_key_order_and_merge_identity(config):
    reordered = dict(reversed(list(config.items())))
    assert config_hash(config) == config_hash(reordered)
    assert merge(config, {}) == config


def test_hash_changes_with_values_and_is_stable_across_processes(tmp_path):
    changed = apply_overrides(BASE, ["dataset.spp=65"])
    assert config_hash(changed) != config_hash(BASE)
    code = f"from jprt.config import config_hash; print(config_hash({BASE!r}))"
    other = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    assert other == config_hash(BASE)
    digest = save_resolved(BASE, str(tmp_path))
    saved = json.load(open(os.path.join(tmp_path, "config.json")))
    assert saved == {"hash": digest, "config": BASE}


def test_a_scene_section_takes_a_file_or_switches_kind(tmp_path):
    """``--set dataset.scene=/abs/room.xml``, or ``scene.name=xml`` then ``scene.path=...``; a key
    of another kind of scene says how to switch."""
    from jprt.config import ConfigError, apply_overrides

    room = tmp_path / "room.xml"
    room.write_text("<scene version='3.0.0'/>")
    config = {"dataset": {"scene": {"name": "cornell_box", "area_light": False}, "spp": 4}}
    got = apply_overrides(config, [f"dataset.scene={room}"])
    assert got["dataset"]["scene"] == {"name": "xml", "path": str(room), "keep_emitters": True}
    got = apply_overrides(config, ["dataset.scene.name=xml", f"dataset.scene.path={room}",
                                   "dataset.scene.keep_emitters=false", "dataset.scene.opening=ceiling"])
    assert got["dataset"]["scene"] == {"name": "xml", "path": str(room), "keep_emitters": False, "opening": "ceiling"}
    assert got["dataset"]["spp"] == 4 and config["dataset"]["scene"]["name"] == "cornell_box"
    with pytest.raises(ConfigError, match=r"for a 'cornell_box' scene; switch the scene's kind first \(--set "
                                          r"dataset.scene.name=xml"):
        apply_overrides(config, [f"dataset.scene.path={room}"])
    with pytest.raises(ConfigError, match="scene file not found"):
        apply_overrides(config, ["dataset.scene=/no/such/room.xml"])
    with pytest.raises(ConfigError, match="unknown scene name 'attic'"):
        apply_overrides(config, ["dataset.scene.name=attic"])
    same = apply_overrides(config, ["dataset.scene.name=cornell_box"])  # the same kind keeps its keys
    assert same == config
