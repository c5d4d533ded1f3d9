"""The experiments end to end at tiny sizes (``test`` presets) through ``jprt.runner``: every
stage runs and writes its report; the summary has the common schema (``SUMMARY_SCHEMA``) and the
numbers are checked for consistency, not for accuracy (that is the benchmarks' job)."""

import json
import os

import numpy as np
import pytest

from jprt.cli import main as cli_main
from jprt.runner import SUMMARY_SCHEMA

pytestmark = pytest.mark.mitsuba


def _run(name: str, tmp_path) -> tuple[dict, str]:
    out = str(tmp_path / "out")
    assert cli_main(["run", f"experiments/{name}.py", "--preset", "test", "--set", f"output.dir={out}"]) == 0
    (folder,) = os.listdir(out)
    folder = os.path.join(out, folder)
    with open(os.path.join(folder, "summary.json")) as f:
        s = json.load(f)
    assert set(SUMMARY_SCHEMA) <= set(s), set(SUMMARY_SCHEMA) - set(s)
    for key in ("indirect_rmse", "indirect_rel_rmse", "psnr_indirect", "frame_ms", "model_bytes", "train_s",
                "dataset_s"):
        assert np.isfinite(s[key]) and s[key] >= 0, key
    with open(os.path.join(folder, "config.json")) as f:
        assert json.load(f)["hash"] == s["config_hash"] == os.path.basename(folder)
    for name in ("side_by_side.png", "model.npz"):
        assert os.path.isfile(os.path.join(folder, name)), name
    return s, folder


@pytest.mark.slow  # ~40 s: every stage of the Cornell pipeline (ablations, Table 3, Fig. 6-7)
def test_rrf_cornell_test_preset(mi, tmp_path, capsys):
    s, folder = _run("rrf_cornell", tmp_path)
    e = s["extra"]
    for key in ("reference_spp", "frame_ms_4lights", "n_leaves", "rmse_basic_attributes", "rmse_augmented",
                "rmse_single_mlp_same_params", "std_subsets", "std_inits"):
        assert key in e, key
    # the config's own set ("diffuse", the `small` config's) is neither: both ablations are fits of their own
    assert s["indirect_rmse"] > 0 and e["rmse_augmented"] > 0 and e["p999_over_rmse_augmented"] >= 1
    assert np.isclose(s["speedup_equal_error"], s["pathtrace_ms_equal_error"] / s["frame_ms"])
    assert s["frame_resolution"] == [16, 16]
    assert len(e["robustness"]["rmse_subsets"]) == 2 and e["std_subsets"] >= 0
    assert e["fig6_training_size"]["n_train"][-1] > e["fig6_training_size"]["n_train"][0]
    assert e["fig7_training_spp"]["spp"] == [4, 8]
    split = e["split_rule_ablation"]  # the paper's split rule against the config's (no light splits)
    assert split["split_on"] is None and split["splits"] >= split["splits_on_light"] >= 0
    assert split["rmse"] > 0 and split["frame_ms"] > 0 and split["config_frame_ms_4lights"] > 0
    noise = e["reference_noise"]  # a second reference set of the same pairs: the references' own noise
    assert noise["reference_spp"] == e["reference_spp"] and noise["rmse"] > 0 and noise["p999_over_rmse"] >= 1
    assert noise["fit_against_mean_of_two"]["rmse"] > 0 and noise["uniform_relative_error_p999_over_rmse"] >= 1
    for name in ("equal_error.png", "fig6_training_size.png", "fig7_training_spp.png"):
        assert os.path.isfile(os.path.join(folder, name)), name
    assert folder in capsys.readouterr().out  # says where the report is


@pytest.mark.slow  # ~60 s: two RRF fits, two reference sets, figures and frame times
def test_rrf_tail_takes_its_variants_from_set(mi, tmp_path, monkeypatch):
    """rrf_tail is configured like any experiment (``--set tail.*``): a row of the references' own
    noise, then one row per variant with its tail statistics, timing, figure and score against the
    mean of two reference sets; every row also in tail.json."""
    monkeypatch.setenv("JPRT_CACHE", str(tmp_path / "cache"))
    out = str(tmp_path / "out")
    assert cli_main(["run", "experiments/rrf_tail.py", "--preset", "test", "--set", f"output.dir={out}", "--set",
                     'tail.variants={"small": {}, "short": {"train": {"max_iters": 1}}}']) == 0
    (folder,) = os.listdir(out)
    with open(os.path.join(out, folder, "tail.json")) as f:
        rows = json.load(f)["rows"]
    assert [r["name"] for r in rows] == ["reference noise (|A - B| / sqrt 2)", "small", "short"]
    for r in rows[1:]:
        assert r["p999_over_rmse"] >= 1 and sum(r["worst_0.1%_by_pair"]) == sum(r["worst_0.1%_by_surface"].values())
        assert r["timing"]["frame_ms"] > 0 and r["timing"]["frame_flops_4lights"] > r["timing"]["frame_flops"]
        assert os.path.isfile(r["figure"]["path"]) and r["against_mean_of_two_references"]["rmse"] > 0


@pytest.mark.slow  # ~20 s (suite budget); the LM and material-edit paths are unit-tested in tests/methods
def test_rrf_glossy_test_preset_with_material_edit(mi, tmp_path):
    s, folder = _run("rrf_glossy", tmp_path)
    assert s["ssim_indirect"] is None  # 10 x 10 images: smaller than SSIM's window, stated not faked
    assert os.path.isfile(os.path.join(folder, "material_edit", "material_edit.png"))
    edits = s["extra"]["material_edit"]["edits"]
    assert len(edits) == 1 and edits[0]["rmse"] >= 0


@pytest.mark.slow  # ~11 s (suite budget): the runner is unit-tested on a fake method, the method by its contract
def test_datadriven_test_preset(mi, tmp_path):
    """Every stage of the data-driven PRT experiment at tiny size: summary keys are finite, and
    the common indirect_rmse over the atlas images is the fit report's lightmap RMSE over the
    texels those images show (an unseen texel's pixel shows a neighbour)."""
    s, folder = _run("datadriven", tmp_path)
    e = s["extra"]
    for key in ("rmse", "projection_rmse", "transfer_us", "bake_s", "direct_measure_ms", "rmse_gamma"):
        assert np.isfinite(e[key]) and e[key] >= 0, key
    assert np.isclose(s["indirect_rmse"], e["rmse_shown"], rtol=1e-5)
    assert s["psnr_full"] is None  # no held-out direct lightmap
    # Mitsuba at the lightmap texels is the equal-error peer; the camera view is timed apart
    assert s["extra"]["pathtrace_rmse_by_spp"] and s["pathtrace_ms_equal_error"] > 0
    assert s["frame_resolution"] == [32, 32] and e["frame_ms_camera"] > 0 and s["frame_flops"] > 0
    assert set(e["rmse_by_basis"]) == set(e["projection_rmse_by_basis"]) == {"2", "4"}
    assert set(e["rmse_out_of_scenario"]) >= {"point", "directional"}
    assert set(e["rmse_sh_prt"]) == {"2"}
    assert e["lambda"] in e["lambda_cv"]["lambdas"]
    for name in ("fig14_basis.png", "camera_side_by_side.png", "basis_mean_and_first7.png", "lambda_sweep.png"):
        assert os.path.isfile(os.path.join(folder, name)), name


@pytest.mark.slow  # ~95 s: keeps `make test` under its budget; the stages are unit-tested
def test_wavelet_prt_test_preset(mi, tmp_path, monkeypatch):
    """Every stage of the neural-wavelet PRT experiment at tiny size (procedural maps): the
    transport check, training, Table 1 metrics, timings, equal error, ablations."""
    monkeypatch.setenv("JPRT_CACHE", str(tmp_path / "cache"))
    s, folder = _run("wavelet_prt_cornell", tmp_path)
    e = s["extra"]
    for key in ("psnr_indirect_far", "psnr_full_far", "ssim_indirect_far", "psnr_indirect_near",
                "psnr_indirect_far_baseline", "gt_transport_noise_floor"):
        assert np.isfinite(e[key]), key
    assert s["psnr_indirect"] == e["psnr_indirect_far"] and np.isfinite(s["speedup_equal_error"])
    assert set(e["gt_transport_rel_err_by_k"]) == {"8", "32"}
    assert e["gt_transport_parseval_err"] < 1e-4
    assert set(e["frame_ms_by_resolution"]["16x16"]) == {"8", "16"}
    assert set(e["ablations"]) == {"log2_table_size", "reflection", "spatial"}
    assert set(e["psnr_indirect_far_by_map"]) == {"synthetic_held_out"} and np.isfinite(e["psnr_indirect_far_worst"])
    assert all(v >= 0 for v in e["min_pixel_indirect_by_map"].values())  # model.nonnegative
    assert set(e["transport_rel_err_learned_by_k"]) == {"8", "32"}
    assert set(e["generalisation"]) == {"default", "unbiased objective"}
    assert e["generalisation"]["default"]["psnr_indirect_far"] == pytest.approx(e["psnr_indirect_far"])
    # every variant's learned T_k is scored against Mitsuba's too; the default's is the stage's own
    assert e["generalisation"]["default"]["transport_rel_err_learned_by_k"] == e["transport_rel_err_learned_by_k"]
    assert set(e["generalisation"]["unbiased objective"]["transport_rel_err_learned_by_k"]) == {"8", "32"}
    for name in ("loss.png", "gt_transport_error_vs_k.png", "equal_error.png", "side_by_side_baseline.png"):
        assert os.path.isfile(os.path.join(folder, name)), name


@pytest.mark.slow  # ~40 s: capture, CNN, held-out views, equal error, baselines, midpoints, lobes, environment
def test_sg_lightfield_test_preset(mi, tmp_path):
    s, folder = _run("sg_lightfield", tmp_path)
    e = s["extra"]
    assert set(e["fit_log_l2"]) == {"cnn", "gd", "gd_aligned", "em", "fixed_axes", "sh"}
    assert all(np.isfinite(v) and v >= 0 for v in e["fit_log_l2"].values())
    assert e["bytes_per_texel"] == 2 * 7 * 2  # the test preset's 2 lobes of 7 float16 numbers
    assert e["texels"] > 0 and np.isfinite(e["psnr_delta_fp16"])
    # every method interpolated at the captured midpoints, every lobe count, every environment variant
    assert set(e["midpoint_log_l2"]) == set(e["fit_log_l2"]) and e["midpoints"] > 0
    assert set(e["log_l2_by_lobes"]) == set(e["psnr_indirect_by_lobes"]) == set(e["frame_ms_by_lobes"]) == {"1", "2"}
    assert set(e["psnr_indirect_baselines"]) == {"gd", "gd_aligned", "em", "fixed_axes"}
    values = [*e["midpoint_log_l2"].values(), *e["psnr_indirect_baselines"].values(), *e["log_l2_by_lobes"].values(),
              e["psnr_oct_quadrature"], e["reference_noise_psnr"], *e["psnr_indirect_by_roughness"].values(),
              e["psnr_env_we"], e["psnr_env_we_raw"], e["psnr_env_reflected_visibility"], e["psnr_env_no_visibility"],
              e["psnr_env_quadrature"], e["psnr_lobes_quadrature"], e["psnr_indirect_appendix_b"]]
    assert np.isfinite(values).all(), values
    # nothing in the way is never better than the visibility the scene has (the box's walls block light)
    assert e["psnr_env_no_visibility"] < e["psnr_env_reflected_visibility"]


@pytest.mark.slow  # ~10 s (suite budget): the MRT pieces are unit-tested in tests/methods/test_mrt.py
def test_mrt_test_preset(mi, tmp_path):
    s, folder = _run("mrt", tmp_path)
    e = s["extra"]
    assert e["texel_rmse"]["rmse"] == pytest.approx(s["indirect_rmse"], rel=1e-5)  # the atlas holds every texel once
    assert set(e["rmse_by_kb"]) == {"4", "12"} and set(e["rmse_by_feedback"]) == {"0", "1"}
    assert e["projection_rmse"] <= e["texel_rmse"]["rmse"]  # no coefficients beat the projection
    assert set(e["vector_irradiance_rmse"]) == {"scalar", "ohlsh", "quadratic"}
    assert set(e["frame_ms_by_blocks"]) == {"1", "4"} and e["tbr_build_s"] >= 0
    assert set(e["sv_energy_counts"]["n=96"]) >= {"F", "L_d", "M"}
    values = [e["rmse_datadriven"], e["rmse_ambient"], e["rmse_no_interfaces"], e["rmse_no_enrichment"],
              *e["rmse_by_krlf"].values(), *e["rmse_by_kr"].values(), e["volume_sh_relative_rmse"]]
    assert np.isfinite(values).all() and min(values) > 0


@pytest.mark.slow  # ~20 s (suite budget): the method's contract and evaluator are tested in tests/methods
def test_sg_environment_test_preset(mi, tmp_path):
    s, folder = _run("sg_environment", tmp_path)
    by = s["extra"]["psnr_by_lighting"]
    assert set(by) == {"bake", "bake turned 90 deg", "synthetic sky 0"} and all(np.isfinite(v) for v in by.values())
    assert set(s["extra"]["rel_rmse_by_lighting"]) == set(by)
    assert s["psnr_full"] is None  # the prediction is direct light: no separate direct term


def _real_scenes():
    import importlib.util

    spec = importlib.util.spec_from_file_location("real_scenes", "experiments/real_scenes.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_real_scenes_references_follow_the_gbuffer_rays(mi):
    """The real-scenes references are path traced along the pixel-centre rays the G-buffers read:
    exactly 0 wherever those rays miss the scene, also at pixels whose footprint the box partly
    covers, and lit where they hit it; a rendered image (box-filtered over each pixel) has light
    at such pixels, which no per-pixel prediction can show."""
    from jprt.render import cameras, heldout, images
    from jprt.render.gbuffer import gbuffer
    from jprt.render.lights import PointLights
    from jprt.render.scenes import SceneHandle, cornell_box

    scene, light = cornell_box(area_light=False), PointLights.create([0.1, 0.7, 0.2], [4.0, 4.0, 4.0])
    handle = SceneHandle(scene, light)
    camera = cameras.look_at((0.13, 0.07, 6.3), (0.21, -0.17, 0.0), width=16, height=16)  # the box amid empty space
    valid = gbuffer(handle, camera).valid
    assert valid.any() and (~valid).any()
    e = {"reference_spp": 8, "reference_spp_max": 8, "reference_noise": 1 / 3, "target": 0.35, "seed": 1}
    refs, refs2, spp = heldout.references(scene, handle, camera, [light], e)
    assert spp == [8]
    for ref in refs + refs2:
        assert ref.shape == (16, 16, 3) and (ref[~valid] == 0.0).all()
        assert (ref[valid].sum(-1) > 0).mean() > 0.9
    rendered = images.direct_indirect(handle, camera, spp=8, seed=1).indirect
    assert (rendered[~valid].sum(-1) > 0).any()


@pytest.mark.slow  # ~2.5 min: every method on a Bitterli scene file with nothing set per scene
def test_real_scenes_test_preset(mi, tmp_path):
    module = _real_scenes()
    path = os.path.join(module.SHARED_SCENES, "cornell_box_picture", "scene_picture.xml")
    if not os.path.isfile(path):
        pytest.skip(f"the Bitterli scenes of ../shared/assets are absent ({path})")
    out = str(tmp_path / "out")
    assert cli_main(["run", "experiments/real_scenes.py", "--preset", "test", "--set", f"output.dir={out}"]) == 0
    (folder,) = os.listdir(out)
    with open(os.path.join(out, folder, "report.json")) as f:
        report = json.load(f)
    entry = report["scenes"]["cornell_box_picture"]
    assert entry["regions"]["source"] == "scene bounds"
    assert set(entry["methods"]) == {"rrf", "datadriven", "sg_lightfield", "wavelet_prt", "sh_prt"}
    assert entry["methods"]["wavelet_prt"]["lighting"] == entry["methods"]["sh_prt"]["lighting"] == "environment"
    assert entry["environment"]["opened"] == {"Ceiling": "removed"}  # the environment lights it from above
    assert len(entry["cameras"]) == 2  # the file's view and one drawn about it
    assert entry["setups"]["file emitters"]["apart"] == {"Light": "an emitter (its look is its emission)"}
    for m in entry["methods"].values():
        assert "failed" not in m, m.get("traceback")
        assert m["per_object"] and all(np.isfinite(v["rel_rmse"]) for v in m["per_object"].values())
        for v in m["per_object"].values():  # one lighting, two views: a score per view, the pooled one between
            by = v["rel_rmse_by_lighting"]
            assert len(by) == 2 and min(by) - 1e-9 <= v["rel_rmse"] <= max(by) + 1e-9
        assert m["frame_ms"] > 0
        assert m["self_check"] is None or np.isfinite(m["self_check"]["rel_rmse"])
    assert os.path.isfile(os.path.join(out, folder, "cornell_box_picture_side_by_side.png"))


def test_real_scenes_references_double_until_their_noise_is_small(mi):
    """Each reference set doubles its samples until the two sets' difference says its own noise is
    at most reference_noise x target on every judged object (or the cap): a strict bound takes
    more samples than a loose one, and the cap holds."""
    from jprt.render import cameras, heldout
    from jprt.render.gbuffer import gbuffer
    from jprt.render.lights import PointLights
    from jprt.render.scenes import SceneHandle, cornell_box

    scene, light = cornell_box(area_light=False), PointLights.create([0.1, 0.7, 0.2], [4.0, 4.0, 4.0])
    handle = SceneHandle(scene, light)
    camera = cameras.look_at((0.0, 0.0, 3.9), (0.0, 0.0, 0.0), width=8, height=8)
    g = gbuffer(handle, camera)
    scored = (g.object_id, handle.object_names(), None)
    base = {"reference_spp": 2, "target": 0.35, "seed": 3}
    _, _, loose = heldout.references(scene, handle, camera, [light], {**base, "reference_spp_max": 64,
                                                                      "reference_noise": 100.0}, scored)
    refs, refs2, strict = heldout.references(scene, handle, camera, [light],
                                             {**base, "reference_spp_max": 16, "reference_noise": 1e-6}, scored)
    assert loose == [2] and strict == [16]
    assert refs[0].shape == refs2[0].shape == (8, 8, 3) and not np.array_equal(refs[0], refs2[0])


def test_real_scenes_one_method_failing_keeps_the_others(mi, tmp_path, monkeypatch):
    """A method that raises is recorded with its error and traceback; the methods after it still
    run and their results stay in the report."""
    module = _real_scenes()
    scene = tmp_path / "room.xml"
    scene.write_text(_SMALL_ROOM)
    calls = []

    def predict(name, s, cameras, cfg, e, peak_gflops, baked=False):
        calls.append(name)
        if name == "datadriven":
            raise RuntimeError("a method broke")
        first = np.zeros_like(s["refs"][0])
        scores = {k: {"rel_rmse": 1.0, "rel_rmse_noise_removed": 1.0} for k in s["judged"]}
        return {"per_object": scores, "apart": {}, "worst_rel_rmse_noise_removed": 1.0,
                "mean_rel_rmse_noise_removed": 1.0, "target_met": False, "self_check": None, "frame_ms": 1.0,
                "dataset_s": 0.0, "fit_s": 0.0}, first

    monkeypatch.setattr(module, "fit_and_score", predict)
    config = module.CONFIG | {"methods": ["datadriven", "rrf"],  # point lights: no asset needed
                              "eval": module.CONFIG["eval"] | {"resolution": 8, "n_lights": 1, "reference_spp": 2,
                                                                "reference_spp_max": 2, "extra_views": 1}}
    config["_peak_gflops"] = 1.0
    entry = module.run_scene(str(scene), config, str(tmp_path))
    assert calls == ["datadriven", "rrf"]
    failed = entry["methods"]["datadriven"]
    assert failed["failed"] == "RuntimeError: a method broke" and "Traceback" in failed["traceback"]
    assert not failed["target_met"]
    assert entry["methods"]["rrf"]["per_object"]
    assert len(entry["cameras"]) == 2 and entry["cameras"][0] != entry["cameras"][1]
    assert entry["setups"]["point"]["pathtracer"]["ms"] > 0  # the peer is timed by default
    config["eval"] = config["eval"] | {"time_peer": False}  # a diagnostic run skips the peer's timing
    assert module.run_scene(str(scene), config, str(tmp_path))["setups"]["point"]["pathtracer"] is None



def test_real_scenes_benchmark_merges_scenes_and_names_the_missing():
    """``benchmarks/real_scenes.py --scene X --merge`` keeps the other scenes' entries, and the
    file is never "met everywhere" while a scene of the experiment has no entry or failed."""
    import importlib.util

    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    spec = importlib.util.spec_from_file_location("bench_real_scenes", os.path.join(root, "benchmarks", "real_scenes.py"))
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    met = {"methods": {"rrf": {"target_met": True}}}
    scenes = ["a/scene.xml", "b/scene.xml"]
    first = bench.merged(None, {"scenes": {"a": met}}, scenes)
    assert first["missing"] == ["b"] and first["target_met_everywhere"] is False
    both = bench.merged(first, {"scenes": {"b": met}}, scenes)
    assert set(both["scenes"]) == {"a", "b"} and both["missing"] == [] and both["target_met_everywhere"] is True
    again = bench.merged(both, {"scenes": {"b": {"failed": "RuntimeError: x"}}}, scenes)
    assert again["scenes"]["a"] == met and again["target_met_everywhere"] is False
    # a scene run again for one method keeps the other methods' entries, each saying what measured it
    two = {"command": "run 1", "date": "d1", "config_hash": "h1", "setups": {"point": 1, "environment": 2},
           "methods": {"rrf": {"target_met": True}, "sh_prt": {"target_met": False}}}
    one = {"command": "run 2", "date": "d2", "config_hash": "h2", "setups": {"environment": 3},
           "methods": {"sh_prt": {"target_met": True, "measured": {"command": "run 2"}}}}
    out = bench.merged(bench.merged(None, {"scenes": {"a": two}}, scenes), {"scenes": {"a": dict(one)}}, scenes)
    entry = out["scenes"]["a"]
    assert entry["methods"]["sh_prt"] == {"target_met": True, "measured": {"command": "run 2"}}
    assert entry["methods"]["rrf"]["measured"] == {"command": "run 1", "date": "d1", "config_hash": "h1"}
    assert entry["setups"] == {"point": 1, "environment": 3}  # rrf's set-up kept, sh_prt's the new one

#: A closed grey room with a white box and a point-lit ceiling opening's worth of height.
_SMALL_ROOM = """<scene version="3.0.0">
  <bsdf type="diffuse" id="grey"><rgb name="reflectance" value="0.5"/></bsdf>
  <sensor type="perspective">
    <float name="fov" value="60"/>
    <transform name="to_world"><lookat origin="0, 1, 2.5" target="0, 1, 0" up="0, 1, 0"/></transform>
    <film type="hdrfilm"><integer name="width" value="8"/><integer name="height" value="8"/></film>
  </sensor>
  <shape type="cube" id="room"><ref id="grey"/><boolean name="flip_normals" value="true"/>
    <transform name="to_world"><scale x="2" y="1.5" z="3"/><translate y="1.5"/></transform></shape>
  <shape type="cube" id="box"><ref id="grey"/>
    <transform name="to_world"><scale value="0.4"/><translate y="0.4"/></transform></shape>
</scene>
"""


@pytest.mark.slow  # ~15 s: a test-preset dataset, fit and scoring in this process (the suite's budget)
def test_wavelet_reruns_child_scores_like_the_experiment(mi, tmp_path, monkeypatch):
    """``benchmarks/wavelet_reruns.py``'s child trains the preset's model and scores it as the
    experiment does (``evaluation.far_map_scores`` with its original pair), so the spread it
    records is the PSNR of ``wavelet_prt.json``."""
    import importlib.util

    monkeypatch.setenv("JPRT_CACHE", str(tmp_path / "cache"))
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    spec = importlib.util.spec_from_file_location("bench_wavelet_reruns",
                                                  os.path.join(root, "benchmarks", "wavelet_reruns.py"))
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    out = str(tmp_path / "run.json")
    bench.child("test", out)
    with open(out) as f:
        run = json.load(f)
    assert set(run["psnr_indirect_far_by_map"]) == {"synthetic_held_out"}
    assert np.isfinite(run["psnr_indirect_far"]) and run["psnr_indirect_far"] == run["psnr_indirect_far_worst"]
    assert run["run_key"] and run["train_s"] > 0 and np.isfinite(run["final_loss"])
