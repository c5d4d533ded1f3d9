"""Sweeps (jprt.sweep, ``jprt sweep``) on the fake method of fake_method.py: grid expansion, one
runner run per point, re-runs that do nothing, failures recorded, Pareto fronts, ``--select``."""

import csv
import json
import os
import textwrap
import types

import fake_method
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from jprt import sweep
from jprt.cli import main as cli_main
from jprt.config import ConfigError, parse_value
from jprt.methods import REGISTRY


pytestmark = pytest.mark.usefixtures("small_machine_measurements")


@pytest.fixture
def experiment(monkeypatch, tmp_path):
    monkeypatch.setitem(REGISTRY, "fake", fake_method.make_fake_method())
    fake_method.CALLS.clear()
    return types.SimpleNamespace(METHOD="fake", CONFIG=fake_method.config(str(tmp_path / "out")),
                                 held_out=fake_method.held_out, pathtracer=fake_method.pathtracer)


def test_grid_parsing_and_points():
    grid = sweep.parse_grid(["model.hidden=[[12,6],[20,10]]", "render.k=[16, 32, 64]"])
    assert grid == {"model.hidden": [[12, 6], [20, 10]], "render.k": [16, 32, 64]}
    points = sweep.grid_points(grid)
    assert len(points) == 6 and points[0] == {"model.hidden": [12, 6], "render.k": 16}
    assert points[1]["render.k"] == 32  # the first key varies slowest
    for bad in (["render.k"], ["render.k=16"], ["render.k=[]"], ["render.k=[1]", "render.k=[2]"]):
        with pytest.raises(ConfigError):
            sweep.parse_grid(bad)


def test_sweep_runs_every_point_and_reruns_nothing(experiment):
    grid = {"model.bias": [0.0, 0.02], "data.n": [2, 3]}
    record = sweep.run_sweep(experiment, experiment.CONFIG, grid, progress=False)
    assert record["counts"] == {"done": 4, "cached": 0, "failed": 0}
    assert fake_method.CALLS == {"make_dataset": 4, "fit": 4}
    rows = record["rows"]
    assert [(r["model.bias"], r["data.n"]) for r in rows] == [(0.0, 2), (0.0, 3), (0.02, 2), (0.02, 3)]
    assert len({r["config_hash"] for r in rows}) == 4 and all(r["indirect_rmse"] is not None for r in rows)
    assert rows[0]["indirect_rmse"] < 1e-5 < rows[2]["indirect_rmse"]  # the bias shows in the error
    assert [c["spp"] for c in rows[0]["pathtrace_curve"]] == [1, 4, 16, 64, 256]  # Mitsuba's measured curve
    folder = record["folder"]
    for name in ("sweep.json", "sweep.csv", "pareto_frame_ms.png", "pareto_model_bytes.png", "pareto_train_s.png"):
        assert os.path.isfile(os.path.join(folder, name)), name
    with open(os.path.join(folder, "sweep.csv")) as f:
        table = list(csv.DictReader(f))
    assert len(table) == 4 and {"model.bias", "data.n", "status", "indirect_rmse", "frame_ms"} <= set(table[0])
    for x, front in record["pareto"].items():  # the recorded fronts are the brute-force ones
        xs, ys = [r[x] for r in rows], [r["indirect_rmse"] for r in rows]
        assert front == [i for i, on in enumerate(sweep.pareto_front(xs, ys)) if on], x

    fake_method.CALLS.clear()
    again = sweep.run_sweep(experiment, experiment.CONFIG, grid, progress=False)
    assert again["counts"] == {"done": 0, "cached": 4, "failed": 0} and not fake_method.CALLS  # nothing re-run
    assert [r["indirect_rmse"] for r in again["rows"]] == [r["indirect_rmse"] for r in rows]


def test_a_failing_point_is_recorded_and_the_sweep_goes_on(experiment):
    record = sweep.run_sweep(experiment, experiment.CONFIG, {"model.bias": [0.0, -1.0, 0.01]}, progress=False)
    assert record["counts"] == {"done": 2, "cached": 0, "failed": 1}
    failed = record["rows"][1]
    assert failed["status"] == "failed" and "negative bias" in failed["error"] and failed["indirect_rmse"] is None
    with open(os.path.join(failed["folder"], "error.txt")) as f:
        assert "ValueError" in f.read()
    assert all(1 not in front for front in record["pareto"].values())


def test_an_unknown_grid_key_stops_the_sweep_before_anything_runs(experiment):
    with pytest.raises(ConfigError, match="model.bias"):
        sweep.run_sweep(experiment, experiment.CONFIG, {"model.bais": [0.0]}, progress=False)
    assert not fake_method.CALLS


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.floats(0, 50), st.floats(0.1, 1000), st.booleans()), min_size=1, max_size=12),
       st.floats(0, 50))
def test_select_is_the_cheapest_point_meeting_the_target(table, target):
    rows = [{"psnr_indirect": p, "frame_ms": t, "status": "failed" if bad else "done"} for p, t, bad in table]
    ok = [r for r in rows if r["status"] == "done" and r["psnr_indirect"] >= target]
    if ok:
        chosen = sweep.select(rows, f"psnr_indirect>={target!r}", "frame_ms")
        assert chosen["frame_ms"] == min(r["frame_ms"] for r in ok) and chosen["psnr_indirect"] >= target
    else:
        with pytest.raises(ValueError, match="no sweep point meets") as err:
            sweep.select(rows, f"psnr_indirect>={target!r}", "frame_ms")
        done = [r["psnr_indirect"] for r in rows if r["status"] == "done"]
        if done:  # the refusal names the best value any point reached
            assert f"best psnr_indirect reached = {max(done):.6g}" in str(err.value)


def test_select_several_constraints_and_bad_ones():
    rows = [{"psnr_indirect": 31.0, "ssim_indirect": 0.8, "frame_ms": 5.0},
            {"psnr_indirect": 33.0, "ssim_indirect": 0.95, "frame_ms": 9.0},
            {"psnr_indirect": 35.0, "ssim_indirect": 0.97, "frame_ms": 20.0}]
    assert sweep.select(rows, "psnr_indirect>=30,ssim_indirect>=0.9", "frame_ms") is rows[1]
    with pytest.raises(ValueError, match=r"best ssim_indirect reached = 0.97 \(target >= 0.99\)"):
        sweep.select(rows, ["ssim_indirect>=0.99"], "frame_ms")
    with pytest.raises(ValueError, match="not of the form"):
        sweep.select(rows, "psnr_indirect=>30", "frame_ms")


def test_cli_sweep_select_and_run_the_selected_config(monkeypatch, tmp_path):
    monkeypatch.setitem(REGISTRY, "fake", fake_method.make_fake_method())
    path = tmp_path / "fake_experiment.py"
    path.write_text(textwrap.dedent(f"""
        import sys
        sys.path.insert(0, {os.path.dirname(os.path.abspath(fake_method.__file__))!r})
        import fake_method
        from fake_method import held_out, pathtracer

        METHOD = "fake"
        CONFIG = fake_method.config({str(tmp_path / "out")!r})
    """))
    argv = ["sweep", str(path), "--grid", "model.bias=[0.0, 0.01, 0.2]", "--select", "indirect_rmse<=0.05",
            "--minimize", "model_bytes"]
    assert cli_main(argv) == 0
    (folder,) = [os.path.join(r, d) for r, ds, _ in os.walk(tmp_path / "out") for d in ds if d.startswith("sweep_")]
    with open(os.path.join(folder, "selected.json")) as f:
        selected = json.load(f)
    assert selected["point"]["model.bias"] in (0.0, 0.01) and selected["summary"]["indirect_rmse"] <= 0.05
    assert selected["config"]["model"]["bias"] == selected["point"]["model.bias"]
    assert cli_main(["run", str(path), "--config", os.path.join(folder, "selected.json"), "--set",
                     f"output.dir={tmp_path / 'rerun'}"]) == 0
    (rerun,) = os.listdir(tmp_path / "rerun")
    with open(os.path.join(tmp_path / "rerun", rerun, "summary.json")) as f:
        assert np.isclose(json.load(f)["indirect_rmse"], selected["summary"]["indirect_rmse"])
    assert cli_main(["sweep", str(path), "--grid", "model.bias=[0.2]", "--select", "indirect_rmse<=0.05",
                     "--minimize", "frame_ms"]) == 2  # no point meets it: a one-line error, exit 2


@pytest.mark.parametrize("name", sorted(f for f in os.listdir(os.path.join(os.path.dirname(os.path.dirname(
    os.path.abspath(__file__))), "experiments", "sweeps")) if f.endswith(".py")))
def test_sweep_files_are_valid_for_their_experiments(name):
    """Every shipped sweep file names an experiment, a preset and grid keys that exist (no run)."""
    from jprt.experiment import load_experiment, resolve_config

    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    spec = sweep.load_sweep_file(os.path.join(root, "experiments", "sweeps", name))
    module = load_experiment(spec["experiment"])
    config = resolve_config(module, spec.get("set", []), spec.get("preset"))
    for item in spec.get("set", []):  # every `set` item takes effect (an empty dict merged into one would not)
        key, value = item.split("=", 1)
        at = config
        for part in key.split("."):
            at = at[part]
        assert at == parse_value(value), item
    points = sweep.grid_points(spec["grid"])
    assert len(points) >= 4
    for point in points:
        sweep.point_config(config, point)  # raises on an unknown key or a wrong type


def test_ray_resources_come_from_the_config(experiment, monkeypatch):
    """A point's Ray CPU / GPU needs: the config's ``resources`` section, unless given explicitly."""
    from jprt import distributed

    seen = []

    def fake_map(fn, args, *, num_cpus, num_gpus, on_done, **kwargs):
        seen.append((num_cpus, num_gpus))
        for i, _ in enumerate(args):
            on_done(i, ("failed", None, "not run here"))

    monkeypatch.setattr(distributed, "map_tasks", fake_map)
    experiment.__file__ = "fake_experiment.py"
    experiment.CONFIG = {**experiment.CONFIG, "resources": {"cpus": 2, "gpus": 0.5}}
    grid = {"model.bias": [0.0, 0.1]}
    record = sweep.run_sweep(experiment, experiment.CONFIG, grid, progress=False, ray=True)
    assert record["counts"]["failed"] == 2 and seen == [(2.0, 0.5)]
    sweep.run_sweep(experiment, experiment.CONFIG, grid, progress=False, ray=True, num_cpus=1, num_gpus=0)
    assert seen[-1] == (1.0, 0.0)
