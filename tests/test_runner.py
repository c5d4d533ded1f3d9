"""The runner (jprt.runner) on a fake method: the pipeline's order, the summary schema, the report
folder, equal error against a fake path tracer, strict method configs."""

import json
import os
import types

import fake_method
import numpy as np
import pytest

from jprt import runner
from jprt.config import ConfigError
from jprt.methods import REGISTRY


pytestmark = pytest.mark.usefixtures("small_machine_measurements")


@pytest.fixture
def fake(monkeypatch, tmp_path):
    monkeypatch.setitem(REGISTRY, "fake", fake_method.make_fake_method())
    calls = []

    def held_out(run):
        calls.append("held_out")
        return fake_method.held_out(run)

    def stage(run):
        calls.append("stage")
        assert run.summary["indirect_rmse"] is not None  # stages run after the common summary
        return {"gain": float(run.result.params["gain"])}

    module = types.SimpleNamespace(METHOD="fake", CONFIG=fake_method.config(str(tmp_path / "out")), held_out=held_out,
                                   pathtracer=fake_method.pathtracer, STAGES=[stage])
    return module, calls


def test_run_writes_the_common_summary(fake):
    module, calls = fake
    s = runner.run(module, {})
    assert list(s)[:len(runner.SUMMARY_SCHEMA)] == list(runner.SUMMARY_SCHEMA)  # schema keys first, in order
    assert calls == ["held_out", "stage"]
    assert s["method"] == "fake" and s["scene"] == {"name": "fake"}
    assert s["indirect_rmse"] < 1e-5 and s["extra"]["gain"] == pytest.approx(1.0, rel=1e-5)
    assert s["psnr_full"] is not None and s["ssim_indirect"] is not None
    assert s["train_s"] == 0.25 and s["model_bytes"] == 4 and s["frame_resolution"] == [fake_method.H, fake_method.W]
    # a method this exact is never reached by the noisy path tracer: stated, timed at the largest spp
    assert s["equal_error_spp"] is None and s["pathtrace_ms_equal_error"] == 512.0
    assert "NOT reached" in s["extra"]["pathtrace_note"]
    assert s["speedup_equal_error"] == pytest.approx(512.0 / s["frame_ms"])
    folder = s["output"]
    with open(os.path.join(folder, "config.json")) as f:
        assert json.load(f)["hash"] == s["config_hash"] == os.path.basename(folder)
    for name in ("summary.json", "model.npz", "side_by_side.png", "equal_error.png"):
        assert os.path.isfile(os.path.join(folder, name)), name


def test_a_methods_own_roof_is_the_summarys(fake, monkeypatch):
    """Without ``Method.frame_roofline`` the summary's roofline is the matmul one and nothing
    else is added; with one, the method's roofline is the summary's, the matmul one stays beside
    it under ``extra``, and both were judged against the same measured bandwidth."""
    from jprt import eval as jeval

    module, _ = fake
    s = runner.run(module, {})
    assert s["roofline"]["roof"] == "matmul" and s["roofline"]["matmul_gflops"] == s["matmul_peak_gflops"]
    assert "roofline_matmul" not in s["extra"] and "roofline_detail" not in s["extra"]

    def own(params, config, inputs, lighting, frame_ms, *, repeats, bandwidth_gbs):
        roof = jeval.roofline_of(1e6, 1e3, frame_ms=frame_ms, peak_gflops=1.0, bandwidth_gbs=bandwidth_gbs)
        return {"roofline": {**roof["roofline"], "roof": "own"}, "detail": {"repeats": repeats}}

    monkeypatch.setitem(REGISTRY, "fake", REGISTRY["fake"]._replace(frame_roofline=own))
    s = runner.run(module, {})
    r, m = s["roofline"], s["extra"]["roofline_matmul"]
    assert r["roof"] == "own" and r["matmul_gflops"] == 1.0 and r["frame_flops"] == 1e6
    assert m["roof"] == "matmul" and m["matmul_gflops"] == s["matmul_peak_gflops"]
    assert r["bandwidth_gbs"] == m["bandwidth_gbs"] > 0
    assert s["extra"]["roofline_detail"] == {"repeats": module.CONFIG["eval"].get("timing_repeats", 10)}


def test_equal_error_is_found_for_a_biased_method(fake):
    module, _ = fake
    s = runner.run(module, {"model": {"bias": 0.05}})
    assert s["indirect_rmse"] == pytest.approx(0.05, rel=1e-4)
    assert s["equal_error_spp"] in (1, 4, 16, 64, 256)
    tried = s["extra"]["pathtrace_rmse_by_spp"]
    assert tried[-1]["rmse"] <= s["indirect_rmse"] < min(t["rmse"] for t in tried[:-1])
    assert s["pathtrace_ms_equal_error"] == 2.0 * s["equal_error_spp"]
    curve = s["extra"]["pathtrace_curve"]  # Mitsuba's curve: every spp tried, each timed
    assert [c["spp"] for c in curve] == [t["spp"] for t in tried]
    assert all(c["ms"] == 2.0 * c["spp"] for c in curve) and [c["rmse"] for c in curve] == [t["rmse"] for t in tried]


def test_configs_are_strict(fake):
    module, _ = fake
    with pytest.raises(ConfigError, match="model.bias"):
        runner.run(module, {"model": {"bais": 1.0}})
    with pytest.raises(ValueError, match="lacks the fake sections"):
        runner.method_config(REGISTRY["fake"], {"scene": {"name": "fake"}})


def test_common_summary_refuses_lightmaps_and_handles_small_images():
    ref = np.ones((8, 8, 3))
    held = runner.HeldOut([ref * 1.1], [ref], [np.ones((8, 8), bool)])
    s = runner.common_summary(held)
    assert s["indirect_rmse"] == pytest.approx(0.1) and s["indirect_rel_rmse"] == pytest.approx(0.1)
    assert s["ssim_indirect"] is None and s["psnr_full"] is None  # 8 x 8 < SSIM window; no direct given
    with pytest.raises(ValueError, match=r"\(H, W, C\) images"):
        runner.common_summary(runner.HeldOut([np.ones((10, 3))], [np.ones((10, 3))], [np.ones(10, bool)]))


def test_preset_benchmark_runs_the_experiment_at_the_parsed_preset(monkeypatch):
    """A benchmark script's shared opening: --preset (default small) and --out (default the
    script's own), the experiment run at that preset, its summary flattened."""
    calls = []

    def fake_run_file(path, preset=None, overrides=()):
        calls.append((path, preset))
        return {"frame_ms": 1.0, "extra": {"psnr": 30.0, "frame_ms": 2.0}}

    monkeypatch.setattr(runner, "run_file", fake_run_file)
    args, s = runner.preset_benchmark("d", "exp.py", "default.json", argv=[])
    assert (args.preset, args.out) == ("small", "default.json") and calls == [("exp.py", "small")]
    assert s == {"frame_ms": 1.0, "psnr": 30.0}
    args, _ = runner.preset_benchmark("d", "exp.py", "default.json", argv=["--preset", "paper", "--out", "x.json"])
    assert (args.preset, args.out) == ("paper", "x.json") and calls[-1] == ("exp.py", "paper")
