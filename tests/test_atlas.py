"""The speed-accuracy atlas (jprt.atlas, experiments/atlas.py, ``jprt atlas``): its presets are
valid for every method they name, equal error is read off Mitsuba's curve correctly, the table and
figure are written; end to end at the ``test`` preset (slow), and on a scene file."""

import json
import os

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from jprt import atlas
from jprt.cli import main as cli_main
from jprt.config import apply_overrides, merge
from jprt.methods import REGISTRY
from jprt.experiment import load_experiment
from jprt.sweep import ROW_KEYS, parse_grid, point_config

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
EXPERIMENT = load_experiment(os.path.join(ROOT, "experiments", "atlas.py"))


def _resolves(task_name: str, task: dict, e: dict) -> set:
    """The methods that run on ``task``; each one with an entry under the task's methods (run or
    not): its config with the entry's ``set`` items and its grid's first and last points resolves
    strictly."""
    ran = set()
    for name in REGISTRY:
        if not atlas.applicability(task, name):
            ran.add(name)
        elif name not in task["methods"]:
            continue
        target = atlas.TaskExperiment(task_name, task, name, e, "/tmp/unused")
        grid = parse_grid(task["methods"][name]["grid"])
        for point in [dict()] + [{k: v[i] for k, v in grid.items()} for i in (0, -1)]:
            cfg = point_config(target.CONFIG, point)
            REGISTRY[name].resolve({k: cfg[k] for k in REGISTRY[name].default_config})
    return ran


@pytest.mark.parametrize("preset", sorted(atlas.PRESETS))
def test_presets_resolve_for_every_method(preset):
    """Every (task, method) of every preset: the method's config with the task's ``set`` items
    and each grid point resolves strictly (a typo fails here, not an hour into the run)."""
    config = merge(EXPERIMENT.CONFIG, EXPERIMENT.PRESETS[preset])
    ran = set()
    for task_name, task in config["tasks"].items():
        ran |= _resolves(task_name, task, config["eval"])
    relighting = {n for n in REGISTRY if REGISTRY[n].task_lightings}
    assert ran == relighting  # every registered method that relights is on some task


def test_methods_without_adapter_or_knob_are_skipped_with_reason():
    task = {**atlas.TASKS["local_lights"], "methods": {}}
    assert "no size knob" in atlas.applicability(task, "rrf")
    assert "takes environment" in atlas.applicability(atlas.TASKS["local_lights"], "wavelet_prt")


def test_dotted_items_round_trip():
    base = {"a": {"b": 1, "c": [1, 2]}, "d": "x"}
    items = atlas.dotted({"a": {"b": 3, "c": [4]}, "d": "y"})
    assert apply_overrides(base, items) == {"a": {"b": 3, "c": [4]}, "d": "y"}


_curves = st.lists(st.tuples(st.integers(1, 4096), st.floats(1e-4, 1.0), st.floats(0.1, 1e4)), min_size=1,
                   max_size=8, unique_by=lambda t: t[0])


@given(curve=_curves, rmse=st.floats(1e-5, 2.0), frame_ms=st.floats(0.01, 100.0))
@settings(max_examples=100, deadline=None)
def test_equal_error_matches_brute_force(curve, rmse, frame_ms):
    pts = [{"spp": s, "rmse": r, "ms": ms} for s, r, ms in curve]
    out = atlas.equal_error(pts, rmse, frame_ms)
    reached = [p for p in pts if p["rmse"] <= rmse]
    if reached:
        best = min(reached, key=lambda p: p["spp"])
        assert out["equal_error_spp"] == best["spp"] and out["equal_error_reached"]
        assert out["pathtrace_ms_equal_error"] == best["ms"]
    else:  # the largest spp's time, a lower bound
        assert out["equal_error_spp"] is None and out["equal_error_reached"] is False
        assert out["pathtrace_ms_equal_error"] == max(pts, key=lambda p: p["spp"])["ms"]
    assert out["speedup_equal_error"] == pytest.approx(out["pathtrace_ms_equal_error"] / frame_ms)
    assert atlas.equal_error(pts, None, frame_ms)["equal_error_spp"] is None


def _synthetic_record():
    row = {k: 1.0 for k in ROW_KEYS} | {"status": "done", "model.hidden": [8, 4], "equal_error_spp": 4,
                                        "equal_error_reached": True}
    slow = dict(row, frame_ms=3.0, indirect_rmse=2.0, **{"model.hidden": [2, 1]})
    curve = [{"spp": 1, "ms": 2.0, "rmse": 0.3}, {"spp": 4, "ms": 5.0, "rmse": 0.1}]
    return {"tasks": {"t": {"title": "a task", "n_images": 2, "resolution": 8, "reference_spp": 16,
                            "mitsuba_curve": curve, "methods": {
                                "rrf": {"status": "done", "knobs": ["model.hidden"], "points": [row, slow],
                                        "pareto": {"frame_ms": [0], "model_bytes": [0], "train_s": [0]}},
                                "sh_prt": {"status": "skipped", "reason": "not this task"}}}}}


def test_table_and_figure(tmp_path):
    record = _synthetic_record()
    text = atlas.table(record)
    rows = [line for line in text.splitlines() if line.startswith("| rrf |")]
    assert len(rows) == 1 and "hidden=[8,4]" in rows[0]  # the front (also the best); the dominated point not
    assert "Not run: sh_prt (not this task)" in text and "4 spp 0.1000 in 5 ms" in text
    path = str(tmp_path / "atlas_t.png")
    atlas.plot_task(path, record["tasks"]["t"])
    assert os.path.getsize(path) > 1000


@pytest.mark.slow  # ~40 s cold: both tasks, every method, Mitsuba's curve
@pytest.mark.mitsuba
def test_atlas_test_preset(mi, tmp_path):
    out = str(tmp_path / "atlas")
    args = ["run", "experiments/atlas.py", "--preset", "test", "--set", f"output.dir={out}", "--set",
            "eval.select=indirect_rel_rmse<=100"]  # every point meets it: the cheapest frame is chosen
    assert cli_main(args) == 0
    with open(os.path.join(out, "atlas.json")) as f:
        record = json.load(f)
    assert set(record["tasks"]) == {"local_lights", "environment"}
    for task_name, task in record["tasks"].items():
        curve = task["mitsuba_curve"]
        assert [c["spp"] for c in curve] == [1, 4, 16] and all(c["ms"] > 0 and c["rmse"] > 0 for c in curve)
        assert os.path.isfile(os.path.join(out, f"atlas_{task_name}.png"))
        done = {n for n, m in task["methods"].items() if m["status"] == "done"}
        assert done == ({"rrf", "datadriven", "sh_prt", "mrt"} if task_name == "local_lights"
                        else {"wavelet_prt", "sh_prt"})
        for name in done:
            m = task["methods"][name]
            assert m["counts"]["failed"] == 0
            for row in m["points"]:
                assert set(ROW_KEYS) <= set(row)
                assert np.isfinite(row["indirect_rmse"]) and row["frame_ms"] > 0
                assert row["pathtrace_ms_equal_error"] in [c["ms"] for c in curve]
            assert m["pareto"]["frame_ms"]
            ok = [r for r in m["points"] if r["status"] != "failed"]
            assert m["selected"]["frame_ms"] == min(r["frame_ms"] for r in ok)
        fastest = min((m["selected"]["frame_ms"], n) for n, m in task["methods"].items() if m["status"] == "done")
        assert task["selected"]["method"] == fastest[1]
    # the selected config runs exactly that method's point on that task, in its own folder
    path = record["tasks"]["local_lights"]["methods"]["sh_prt"]["selected"]["config"]
    assert cli_main(["run", "experiments/atlas.py", "--config", path]) == 0
    with open(os.path.join(out, "selected_local_lights_sh_prt", "atlas.json")) as f:
        alone = json.load(f)
    assert list(alone["tasks"]) == ["local_lights"] and list(alone["tasks"]["local_lights"]["methods"]) == ["sh_prt"]
    (row,) = alone["tasks"]["local_lights"]["methods"]["sh_prt"]["points"]
    (before,) = record["tasks"]["local_lights"]["methods"]["sh_prt"]["points"]
    assert row["indirect_rmse"] == pytest.approx(before["indirect_rmse"], rel=1e-6)
    # a re-run trains nothing: every point comes back from its summary
    assert cli_main(args) == 0
    with open(os.path.join(out, "atlas.json")) as f:
        again = json.load(f)
    for task in again["tasks"].values():
        for m in task["methods"].values():
            if m["status"] == "done":
                assert m["counts"]["cached"] == len(m["points"]) and m["counts"]["done"] == 0


def test_one_method_failing_keeps_the_others(tmp_path, monkeypatch):
    """A method whose sweep raises is recorded as failed (error, traceback) and the task's other
    methods, its front and table are still written."""
    from types import SimpleNamespace

    def sweep(config, task_name, name, curve, out, say, experiment=None):
        if name == "datadriven":
            raise RuntimeError("a method broke")
        row = {"status": "done", "indirect_rmse": 0.1, "frame_ms": 2.0}
        return {"status": "done", "knobs": [], "points": [row], "pareto": {"frame_ms": [0]}, "sweep_folder": "",
                "counts": {"done": 1, "cached": 0, "failed": 0}}

    monkeypatch.setattr(atlas, "method_sweep", sweep)
    monkeypatch.setattr(atlas, "task_data", lambda task: SimpleNamespace(dataset=[0], cameras=[0], lightings=[0]))
    monkeypatch.setattr(atlas, "mitsuba_curve", lambda task, e, say: [])
    monkeypatch.setattr(atlas, "plot_task", lambda path, entry: None)
    monkeypatch.setattr(atlas, "table", lambda record: "")
    config = merge(EXPERIMENT.CONFIG, {"eval": {"tasks": ["local_lights"], "methods": ["rrf", "datadriven", "sh_prt"]},
                                       "output": {"dir": str(tmp_path)}})
    record = EXPERIMENT.main(config)
    methods = record["tasks"]["local_lights"]["methods"]
    assert methods["datadriven"]["status"] == "failed" and methods["datadriven"]["error"] == "RuntimeError: a method broke"
    assert "Traceback" in methods["datadriven"]["traceback"]
    assert {n for n, m in methods.items() if m["status"] == "done"} >= {"sh_prt"}
    assert record["tasks"]["local_lights"]["front_frame_ms"]


def _picture_scene(assets) -> str:
    path = os.path.join(assets, "scenes", "cornell_box_picture", "scene_picture.xml")
    if not os.path.isfile(path):
        pytest.skip(f"the Cornell picture scene of ../shared/assets is absent ({path})")
    return path


@pytest.mark.mitsuba
@pytest.mark.parametrize("lighting", atlas.LIGHTINGS)
@pytest.mark.parametrize("preset", ["small", "test"])
def test_scene_task_resolves_for_every_method(mi, assets, lighting, preset):
    """A scene file's task under each lighting kind: every method that takes the kind runs on it
    (MRT, a block-layout method, excepted with its reason) and its configs resolve strictly."""
    config = atlas.atlas_config(_picture_scene(assets), lighting, preset)
    ((name, task),) = config["tasks"].items()
    assert name == "scene_picture" and task["scene"]["keep_emitters"] == (lighting == "file")
    ran = _resolves(name, task, config["eval"])
    takes = {n for n in REGISTRY if lighting in REGISTRY[n].task_lightings}
    assert ran == takes - {"mrt"}
    if "mrt" in takes:
        assert "block layout" in atlas.applicability(task, "mrt")


@pytest.mark.mitsuba
def test_scene_task_views_and_lights(mi, assets):
    """The file's camera and views turned about it; point lights in the scene's light region."""
    task = atlas.scene_task(_picture_scene(assets), "point")
    cams = atlas.task_cameras(task, resolution=8)
    assert len(cams) == 3 and np.allclose(cams[1].origin, cams[0].origin) and cams[1].target != cams[0].target
    lights = atlas.task_lightings(task)
    lo, hi = np.asarray(task["lights"]["lo"]), np.asarray(task["lights"]["hi"])
    assert len(lights) == 3 and all(np.all((lo <= li.position[0]) & (li.position[0] <= hi)) for li in lights)


@pytest.mark.slow  # an end-to-end run: every point-light method fitted and timed on a scene file
@pytest.mark.mitsuba
def test_atlas_on_a_scene_file(mi, assets, tmp_path):
    """``jprt atlas <scene.xml> --lighting point --select ... --minimize frame_ms --preset test``
    runs every method that takes point lights on the file and writes the table, the fronts and the
    selection as the built-in tasks do; a re-run with a target every point meets selects the
    cheapest frame (nothing refitted), and its selection runs alone from ``--config``."""
    out = str(tmp_path / "atlas")
    args = ["atlas", _picture_scene(assets), "--lighting", "point", "--minimize", "frame_ms", "--preset", "test",
            "--out", out]
    assert cli_main(args + ["--select", "indirect_rel_rmse<=0.3"]) == 0
    with open(os.path.join(out, "atlas.json")) as f:
        record = json.load(f)
    assert list(record["tasks"]) == ["scene_picture"]
    task = record["tasks"]["scene_picture"]
    assert os.path.isfile(os.path.join(out, "atlas_scene_picture.png"))
    with open(os.path.join(out, "atlas.md")) as f:
        assert "scene_picture: point lighting" in f.read()
    done = {n for n, m in task["methods"].items() if m["status"] == "done"}
    assert done == {n for n in REGISTRY if "point" in REGISTRY[n].task_lightings} - {"mrt"}
    assert task["front_frame_ms"] and task["selected"]["select"] == "indirect_rel_rmse<=0.3"
    for name in done:
        m = task["methods"][name]
        assert m["counts"]["failed"] == 0 and m["pareto"]["frame_ms"]
        assert all(np.isfinite(r["indirect_rmse"]) and r["frame_ms"] > 0 for r in m["points"])
        met = [r for r in m["points"] if r["indirect_rel_rmse"] <= 0.3]
        if met:  # the cheapest point meeting the target
            assert m["selected"]["frame_ms"] == min(r["frame_ms"] for r in met)
        else:  # the error names the best reached
            assert "no sweep point meets" in m["selected"]["error"]

    assert cli_main(args + ["--select", "indirect_rel_rmse<=100"]) == 0
    with open(os.path.join(out, "atlas.json")) as f:
        task = json.load(f)["tasks"]["scene_picture"]
    assert all(task["methods"][n]["counts"]["cached"] == len(task["methods"][n]["points"]) for n in done)
    fastest = min((task["methods"][n]["selected"]["frame_ms"], n) for n in done)[1]
    assert task["selected"]["method"] == fastest
    path = task["methods"][fastest]["selected"]["config"]
    with open(path) as f:
        chosen = json.load(f)
    assert chosen["command"] == f"jprt atlas --config {path}" and chosen["config"]["eval"]["methods"] == [fastest]
    assert cli_main(["atlas", "--config", path]) == 0
    with open(os.path.join(out, f"selected_scene_picture_{fastest}", "atlas.json")) as f:
        alone = json.load(f)["tasks"]["scene_picture"]["methods"]
    assert list(alone) == [fastest]
    (row,) = alone[fastest]["points"]
    assert row["indirect_rmse"] == pytest.approx(task["methods"][fastest]["selected"]["indirect_rmse"], rel=1e-6)
