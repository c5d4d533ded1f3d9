"""Data-driven PRT (Belcour et al. 2022) end to end: Cornell box and Spot in a room.

    jprt run experiments/datadriven.py                    # Cornell box, `small` sizes (minutes)
    jprt run experiments/datadriven.py --preset spot      # Spot (../shared/assets) in a room corner
    jprt run experiments/datadriven.py --preset test      # smoke test

Pipeline: render N spot-light configurations (direct at dense surface samples, indirect
lightmaps) -> fit (blue-noise measurement points, SVD basis, ridge transfer) -> held-out
configurations: RMSE vs reference lightmaps for n = 4, 16, 64 basis elements next to the error of
projecting the reference onto the same basis (Fig. 14); lambda sweep; measurement-point sweep;
gamma vs linear; mono vs multi-channel; lights outside the training scenario (point lights near
the surface, directional lights: Fig. 8); classic SH PRT of order 3 and 5 (§6.4); timings; images.
The report goes to results/datadriven/<config hash>/ (``jprt.runner``: the common summary is over the
held-out lightmaps, as (R, R) atlas images whose valid pixels are the covered texels); helpers in
``jprt.methods.datadriven.evaluation``.
"""

from __future__ import annotations

import os

import jax
import numpy as np

from jprt import eval as jeval
from jprt import io
from jprt.inputs import PointRadiance
from jprt.methods import REGISTRY
from jprt.methods.base import FitResult
from jprt.methods.datadriven import data as dd_data
from jprt.methods.datadriven import evaluation as ev
from jprt.methods.datadriven import model as dd
from jprt.methods.lightmap_lookup import atlas_inputs
from jprt.runner import HeldOut, PathTracer

METHOD = "datadriven"
LABEL = "datadriven"

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SPOT_MESH = os.path.join(os.path.dirname(ROOT), "shared", "assets", "meshes", "c3d_spot.obj")

EVAL_DEFAULTS = {
    "basis_sizes": [4, 16, 64],
    "lambdas": [0.0, 1e-4, 1e-3, 1e-2, 1e-1, 1.0],
    "point_counts": [16, 32, 64, 128, 256, 512, 1024],
    "gamma": 2.2,
    "oos_n": 8,  # out-of-scenario configurations per light kind
    "point_offset": [0.15, 0.4],  # point lights this far above a surface sample of the asset
    "point_intensity": [0.2, 1.0],
    "directional_toward_lo": [-0.5, 0.1, 0.6],  # direction *towards* the light, before normalising
    "directional_toward_hi": [0.5, 0.6, 1.0],
    "directional_irradiance": [0.5, 2.0],
    "sh_orders": [3, 5],
    "sh_spp": 64,
    "sh_env_height": 32,
    "camera": {"origin": [0.0, 0.0, 3.9], "target": [0.0, 0.0, 0.0], "fov": 39.3077},
    "image_resolution": 128,
    "image_spp": 256,
    "images": 2,
    "timing_resolution": 512,
    "timing_repeats": 20,
    # Mitsuba rendering the held-out lightmap texels (full minus direct) at these spp: the
    # equal-error peer of the lightmap the evaluator produces
    "equal_error_spp": [1, 2, 4, 8, 16, 32, 64, 128, 256, 512],
    "pathtrace_repeats": 3,
    "exposure": 0.0,
    "seed": 2022,
}

CONFIG = {**dd.DEFAULT_CONFIG, "eval": EVAL_DEFAULTS, "output": {"dir": "results/datadriven"}}

SPOT = {
    "scene": {"name": "asset_room", "mesh": SPOT_MESH},
    "objects": ["asset"],
    "lightmap": {"resolution": 96},
    # the cow's indirect light is mostly floor and wall bounce: measure direct light there too
    "points": {"objects": ["asset", "floor", "back", "side"], "candidates": 8192},
    "lights": {"position_lo": [-1.2, 1.0, -1.3], "position_hi": [2.0, 2.4, 2.2],
               "target_lo": [-0.45, -0.7, -0.65], "target_hi": [0.45, 0.9, 1.0],
               "cutoff_deg": [15.0, 40.0], "intensity": [3.0, 15.0]},
    "eval": {"directional_toward_lo": [0.1, 0.3, 0.1], "directional_toward_hi": [1.0, 1.0, 1.0],
             "camera": {"origin": [2.6, 1.3, 2.4], "target": [0.0, 0.1, 0.2], "fov": 40.0}},
}

PRESETS = {
    "small": {},
    "spot": SPOT,
    "test": {
        **REGISTRY["datadriven"].presets["test"],  # the method's own smoke-test sizes
        "eval": {"basis_sizes": [2, 4], "lambdas": [0.0, 1e-2], "point_counts": [8, 16], "oos_n": 2, "sh_orders": [2],
                 "sh_spp": 2, "sh_env_height": 8, "image_resolution": 16, "image_spp": 4, "images": 1,
                 "timing_resolution": 32, "timing_repeats": 2, "equal_error_spp": [1, 4], "pathtrace_repeats": 1},
    },
}


def _fit(run, **sections) -> FitResult:
    """A fit of the run's dataset with ``sections`` overriding the method config (``evaluation.fit_recorded``)."""
    return ev.fit_recorded(run.dataset, run.with_config(sections))


def _scores(result: FitResult, data=None, oos=None) -> dict:
    """``evaluation.scores`` of a fit on the held-out lightmaps (or on ``oos``: (direct, indirect))."""
    return ev.scores(result, *(oos or (data.direct_test, data.indirect_test)))


def _handle(run):
    """The run's scene handle (made once), lit by the first held-out spot light."""
    return run.scene_handle(ev.spot_lights(run.dataset.lights_test, 1)[0])


def _test_lights(run) -> list:
    return ev.spot_lights(run.dataset.lights_test, len(run.dataset.direct_test))


def fit(run) -> FitResult:
    """The main fit (lambda by cross-validation), with its warnings."""
    result = _fit(run)
    result.info["train_s"] = result.info["fit_s"]
    return result


def held_out(run) -> HeldOut:
    """The held-out lighting configurations: each lightmap as an atlas image, predicted by the
    evaluator on the atlas itself (``jprt.methods.lightmap_lookup.atlas_inputs``), over the texels
    whose atlas pixel shows them (an unseen texel's pixel shows a seen neighbour)."""
    data, params = run.dataset, run.result.params
    inputs = atlas_inputs(int(data.atlas["resolution"]), data.atlas["texel_index"], data.atlas["fill_index"])
    fine = np.asarray(params["fine_index"])
    preds = [np.asarray(run.evaluate(inputs, PointRadiance(d[fine]))) for d in data.direct_test]
    refs = [ev.lightmap_image(i, data.atlas) for i in data.indirect_test]
    return HeldOut(preds, refs, [inputs.valid] * len(refs), None, [f"held-out light {k}" for k in range(len(refs))])


def frame(run):
    """The lightmap itself, as the equal-error peer renders it: the atlas (every covered texel)
    under the first held-out configuration's direct light at the fine measurement points (the
    camera view is timed by the ``camera_frame`` stage)."""
    data = run.dataset
    inputs = atlas_inputs(int(data.atlas["resolution"]), data.atlas["texel_index"])
    return inputs, PointRadiance(np.asarray(data.direct_test[0][run.result.params["fine_index"]], np.float32))


def pathtracer(run) -> PathTracer:
    """Mitsuba rendering the held-out lightmap texels (indirect = full minus direct, equal seeds;
    a seed unlike the references'), timed for one configuration's whole lightmap."""
    from jprt.render import lightmap

    atlas = run.dataset.atlas
    return lightmap.points_pathtracer(
        _handle(run), atlas["position"], atlas["normal"], _test_lights(run),
        lambda texels: [ev.lightmap_image(t, atlas) for t in texels], seed=4242, time_seed=3, warmup=True,
        repeats=int(run.config["eval"]["pathtrace_repeats"]),
        note="Mitsuba llvm_ad_rgb at the lightmap texels: indirect = full (max_depth -1) minus direct (max_depth "
             "2), both renders timed; the evaluator's frame is the same lightmap (transfer, reconstruction, atlas "
             "lookup)")


def fit_report(run) -> dict:
    """The main fit: sizes, lambda, conditioning, and its method-vs-projection score."""
    data, result = run.dataset, run.result
    s = {"render_train_s": data.meta["render_train_s"], "render_s": data.meta["render_s"],
         "texels": int(len(data.atlas["texel_index"])), "n_train": int(len(data.direct)),
         "n_test": int(len(data.direct_test)), "fit_s": result.info["fit_s"], "lambda": result.info["lam"],
         "lambda_cv": result.info["lambda_cv"], "conditioning": result.info["conditioning"],
         "fit_warnings": result.info["warnings"]}
    s["bake_s"] = s["render_train_s"] + s["fit_s"]
    s.update(ev.scores(result, data.direct_test, data.indirect_test, data.atlas))
    s["reference_rms"] = float(np.sqrt(np.mean(np.square(data.indirect_test))))
    s["relative_rmse"] = s["rmse"] / s["reference_rms"]
    run.say(f"{s['texels']} texels, {result.info['points']} points; n = {run.method_config['basis']['n']}: RMSE "
            f"{s['rmse']:.5f} ({s['rmse_shown']:.5f} over the texels an image shows; projection "
            f"{s['projection_rmse']:.5f}, reference RMS {s['reference_rms']:.4f})")
    return s


def basis_sizes(run) -> dict:
    """Fig. 14: accuracy against the basis size n, for the method and for projecting the
    references onto the basis, with both mean conventions; Fig. 3: the spectrum of the data
    (``evaluation.basis_sizes``)."""
    return ev.basis_sizes(lambda **sections: _fit(run, **sections), run.dataset,
                          [int(n) for n in run.config["eval"]["basis_sizes"]], run.method_config["basis"]["mean"],
                          run.out, run.say)


def sweeps(run) -> dict:
    """Ridge lambda, measurement-point count (``evaluation.regularisation_sweeps``), gamma space
    (§5.3), mono vs multi-channel (§5.2)."""
    data, e, mcfg = run.dataset, run.config["eval"], run.method_config
    s = ev.regularisation_sweeps(lambda **sections: _fit(run, **sections), data, e["lambdas"], e["point_counts"],
                                 int(mcfg["points"]["candidates"]) // int(mcfg["points"]["supersample"]), run.out)
    main_rmse = run.summary["extra"]["rmse"]
    s["rmse_gamma"] = _scores(_fit(run, basis={"gamma": float(e["gamma"])}), data)["rmse"]
    s["rmse_linear"] = main_rmse if float(mcfg["basis"]["gamma"]) <= 0 else None
    other = "multi" if mcfg["basis"]["channels"] == "mono" else "mono"
    s[f"rmse_{mcfg['basis']['channels']}"] = main_rmse
    s[f"rmse_{other}"] = _scores(_fit(run, basis={"channels": other}), data)["rmse"]
    run.say(f"gamma {e['gamma']}: {s['rmse_gamma']:.5f}; {other}-channel: {s[f'rmse_{other}']:.5f}")
    return s


def out_of_scenario(run) -> dict:
    """Fig. 8: point lights near the asset and directional lights, outside the training scenario."""
    data = run.dataset
    if int(run.config["eval"]["oos_n"]) <= 0:
        return {}
    rng = np.random.default_rng(int(run.config["eval"]["seed"]))
    spp_test = int(run.method_config["data"]["test_spp"])
    s = {}
    run.state["oos"] = {}
    for kind, lightings in ev.out_of_scenario_lights(run.config["eval"], data, rng).items():
        d, i = dd_data.render_examples(_handle(run), data.atlas, data.candidates, lightings, spp=spp_test, seed=99,
                                       desc=f"{kind} lights (out of scenario)")
        run.state["oos"][kind] = (d, i, lightings)
        s[kind] = _scores(run.result, oos=(d, i))["rmse"]
        s[f"{kind}_relative"] = s[kind] / float(np.sqrt(np.mean(np.square(i))))
    s["spot_relative (in scenario)"] = run.summary["extra"]["relative_rmse"]
    run.say(f"out of scenario: {s}")
    return {"rmse_out_of_scenario": s}


def sh_prt_baseline(run) -> dict:
    """§6.4: classic SH PRT of the asset (``evaluation.sh_prt_baseline``), each light a delta from
    its direction at the asset centre, on the held-out and out-of-scenario lights."""
    s = ev.sh_prt_baseline(run.config["scene"], run.method_config, run.config["eval"], run.dataset, _handle(run),
                           _test_lights(run), run.state.get("oos", {}))
    s["beats_sh_prt"] = run.summary["extra"]["rmse"] < min(s["rmse_sh_prt"].values())
    run.say(f"SH PRT: {s['rmse_sh_prt']} vs data-driven {run.summary['extra']['rmse']:.5f}")
    return s


def _camera(run, resolution: int):
    from jprt.render import cameras as cams

    c = run.config["eval"]["camera"]
    return cams.look_at(c["origin"], c["target"], fov=float(c["fov"]), width=int(resolution), height=int(resolution))


def camera_images(run) -> dict:
    """Held-out lights seen by a camera (``evaluation.camera_images``): the method against
    path-traced references (camera_side_by_side.png, EXRs, tonemapped finals) and the basis pictures."""
    e, data, params = run.config["eval"], run.dataset, run.result.params
    fine, lights = params["fine_index"], _test_lights(run)[:int(e["images"])]
    s = ev.camera_images(_handle(run), data.atlas, _camera(run, e["image_resolution"]), lights,
                         lambda k, gb: np.asarray(run.evaluate(gb, PointRadiance(data.direct_test[k][fine]))),
                         int(e["image_spp"]), float(e["exposure"]), run.out)
    io.write_png(os.path.join(run.out, "basis_mean_and_first7.png"), ev.basis_picture(params, data.atlas),
                 tonemapped=True)
    return s


def camera_frame(run) -> dict:
    """A camera view of the asset at ``eval.timing_resolution`` (atlas G-buffer) under the first
    held-out configuration: the evaluator's time and roofline for a rendered frame."""
    from jprt.render import lightmap

    e, params = run.config["eval"], run.result.params
    tr = int(e["timing_resolution"])
    gb = lightmap.atlas_gbuffer(_handle(run), lightmap.Atlas(**run.dataset.atlas), _camera(run, tr))
    gb, light = jax.device_put((gb, PointRadiance(np.asarray(run.dataset.direct_test[0][params["fine_index"]],
                                                              np.float32))))
    fast = jax.jit(run.evaluate)
    ms = jeval.time_call(fast, gb, light, repeats=int(e["timing_repeats"]))["median_ms"]
    roof = jeval.roofline(fast, gb, light, frame_ms=ms, peak_gflops=run.summary["matmul_peak_gflops"])
    return {"frame_ms_camera": ms, "frame_resolution_camera": [tr, tr], "frame_flops_camera": roof["frame_flops"],
            "flops_fraction_of_peak_camera": roof["flops_fraction_of_peak"]}


def timings(run) -> dict:
    """The transfer product alone and Mitsuba's shading of the fine measurement points
    (``evaluation.timings``); the speedup at equal error counting that shading too (the paper's
    run time measures direct light by deferred shading on the GPU, §4.3)."""
    s = ev.timings(_handle(run), _test_lights(run)[0], run.dataset, run.result.params, run.method_config,
                   int(run.config["eval"]["timing_repeats"]) * 5)
    pt = run.summary.get("pathtrace_ms_equal_error")
    if pt:
        s["speedup_equal_error_with_direct"] = pt / (run.summary["frame_ms"] + s["direct_measure_ms"])
    run.say(f"transfer {s['transfer_us']:.1f} us, direct measurement {s['direct_measure_ms']:.1f} ms")
    return s


#: The stages of the data-driven PRT report, in order.
STAGES = [fit_report, basis_sizes, sweeps, out_of_scenario, sh_prt_baseline, camera_images, camera_frame, timings]
