"""The RRF experiments end to end at tiny sizes (``test`` presets): every stage runs and writes its
report; the numbers are checked for consistency, not for accuracy (that is the benchmark's job)."""

import json
import os

import numpy as np
import pytest

from jprt.cli import main as cli_main

pytestmark = pytest.mark.mitsuba


@pytest.mark.slow  # ~40 s: every stage of the Cornell pipeline (ablations, Table 3, Fig. 6-7)
def test_rrf_cornell_test_preset(mi, tmp_path, capsys):
    out = str(tmp_path / "out")
    assert cli_main(["run", "experiments/rrf_cornell.py", "--preset", "test", "--set", f"output.dir={out}"]) == 0
    (folder,) = os.listdir(out)
    folder = os.path.join(out, folder)
    with open(os.path.join(folder, "summary.json")) as f:
        s = json.load(f)
    for key in ("indirect_rmse", "reference_spp", "equal_error_spp", "pathtrace_ms_equal_error", "eval_ms_512_1light",
                "eval_ms_512_4lights", "speedup_equal_error", "n_leaves", "model_bytes", "train_s",
                "rmse_basic_attributes", "rmse_augmented", "rmse_single_mlp_same_params", "std_subsets", "std_inits"):
        assert key in s, key
    assert s["rmse_augmented"] == s["indirect_rmse"] > 0
    assert np.isclose(s["speedup_equal_error"], s["pathtrace_ms_equal_error"] / s["eval_ms_512_1light"])
    assert len(s["robustness"]["rmse_subsets"]) == 2 and s["std_subsets"] >= 0
    assert s["fig6_training_size"]["n_train"][-1] > s["fig6_training_size"]["n_train"][0]
    assert s["fig7_training_spp"]["spp"] == [4, 8]
    for name in ("side_by_side.png", "equal_error.png", "fig6_training_size.png", "fig7_training_spp.png",
                 "model.npz", "config.json"):
        assert os.path.isfile(os.path.join(folder, name)), name
    assert folder in capsys.readouterr().out  # says where the report is


@pytest.mark.slow  # ~20 s (suite budget); the LM and material-edit paths are unit-tested in tests/methods
def test_rrf_glossy_test_preset_with_material_edit(mi, tmp_path):
    out = str(tmp_path / "out")
    assert cli_main(["run", "experiments/rrf_glossy.py", "--preset", "test", "--set", f"output.dir={out}"]) == 0
    found = [os.path.join(r, f) for r, _, fs in os.walk(out) for f in fs]
    assert any(p.endswith(os.path.join("material_edit", "material_edit.png")) for p in found)
    (summary,) = [p for p in found if p.endswith(os.path.join("material_edit", "summary.json"))]
    with open(summary) as f:
        s = json.load(f)
    assert len(s["edits"]) == 1 and s["edits"][0]["rmse"] >= 0


def test_datadriven_test_preset(mi, tmp_path):
    """Every stage of the data-driven PRT experiment at tiny size: summary keys are finite."""
    out = str(tmp_path / "out")
    assert cli_main(["run", "experiments/datadriven.py", "--preset", "test", "--set", f"output.dir={out}"]) == 0
    (summary,) = [os.path.join(r, f) for r, _, fs in os.walk(out) for f in fs if f == "summary.json"]
    with open(summary) as f:
        s = json.load(f)
    for key in ("rmse", "projection_rmse", "transfer_us", "frame_ms", "bake_s", "direct_measure_ms", "rmse_gamma"):
        assert np.isfinite(s[key]) and s[key] >= 0, key
    assert set(s["rmse_by_basis"]) == set(s["projection_rmse_by_basis"]) == {"2", "4"}
    assert set(s["rmse_out_of_scenario"]) >= {"point", "directional"}
    assert set(s["rmse_sh_prt"]) == {"2"}
    assert s["lambda"] in s["lambda_cv"]["lambdas"]
    folder = os.path.dirname(summary)
    for name in ("fig14_basis.png", "side_by_side.png", "basis_mean_and_first7.png", "lambda_sweep.png"):
        assert os.path.isfile(os.path.join(folder, name)), name


@pytest.mark.slow  # ~95 s: keeps `make test` under its 10-minute budget; the stages are unit-tested
def test_wavelet_prt_test_preset(mi, tmp_path, monkeypatch):
    """Every stage of the neural-wavelet PRT experiment at tiny size (procedural maps): the
    transport check, training, Table 1 metrics, timings, equal error, ablations."""
    monkeypatch.setenv("JPRT_CACHE", str(tmp_path / "cache"))
    out = str(tmp_path / "out")
    assert cli_main(["run", "experiments/wavelet_prt_cornell.py", "--preset", "test", "--set",
                     f"output.dir={out}"]) == 0
    (summary,) = [os.path.join(r, f) for r, _, fs in os.walk(out) for f in fs if f == "summary.json"]
    with open(summary) as f:
        s = json.load(f)
    for key in ("psnr_indirect_far", "psnr_full_far", "ssim_indirect_far", "psnr_indirect_near",
                "psnr_indirect_far_baseline", "model_bytes", "train_s", "speedup_equal_error",
                "gt_transport_noise_floor"):
        assert np.isfinite(s[key]), key
    assert set(s["gt_transport_rel_err_by_k"]) == {"8", "32"}
    assert s["gt_transport_parseval_err"] < 1e-4
    assert set(s["frame_ms"]) == {"8", "16"} and all(v > 0 for v in s["frame_ms"].values())
    assert set(s["ablations"]) == {"log2_table_size", "reflection", "spatial"}
    folder = os.path.dirname(summary)
    for name in ("side_by_side.png", "loss.png", "gt_transport_error_vs_k.png", "equal_error.png"):
        assert os.path.isfile(os.path.join(folder, name)), name
