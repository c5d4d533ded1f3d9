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
The report goes to results/datadriven/<config hash>/.
"""

from __future__ import annotations

import os
import sys
import time
import warnings

import jax
import numpy as np

from jprt import eval as jeval
from jprt import io
from jprt.config import config_hash, merge, save_resolved
from jprt.methods import datadriven as dd
from jprt.methods import sh_prt

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SPOT_MESH = os.path.join(os.path.dirname(ROOT), "shared", "assets", "meshes", "c3d_spot.obj")

EVAL_DEFAULTS = {
    "basis_sizes": [4, 16, 64],
    "lambdas": [0.0, 1e-4, 1e-3, 1e-2, 1e-1, 1.0],
    "point_counts": [16, 32, 64, 128, 256],
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
    "exposure": 0.0,
    "seed": 2022,
}

CONFIG = merge({**dd.DEFAULT_CONFIG, "eval": EVAL_DEFAULTS, "output": {"dir": "results/datadriven"}}, {})

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
        "lightmap": {"resolution": 32},
        "points": {"candidates": 512, "count": 16, "supersample": 2},
        "data": {"n_train": 12, "n_test": 3, "spp": 4, "test_spp": 8},
        "eval": {"basis_sizes": [2, 4], "lambdas": [0.0, 1e-2], "point_counts": [8, 16], "oos_n": 2, "sh_orders": [2],
                 "sh_spp": 2, "sh_env_height": 8, "image_resolution": 16, "image_spp": 4, "images": 1,
                 "timing_resolution": 32, "timing_repeats": 2},
    },
}


def _say(msg: str) -> None:
    print(f"[datadriven] {msg}", file=sys.stderr, flush=True)


def _predict(params, direct) -> np.ndarray:
    evaluate = dd.evaluator(params)
    fine = np.asarray(params["fine_index"])
    return np.stack([np.asarray(evaluate.lightmap(d[fine])) for d in direct])


def _scores(params, direct, indirect) -> dict:
    pred = _predict(params, direct)
    proj = dd.project(params, direct[:, params["fine_index"]], indirect)
    return {"rmse": dd.lightmap_rmse(pred, indirect), "projection_rmse": dd.lightmap_rmse(proj, indirect)}


def _fit(data, config, **sections) -> dict:
    cfg = merge(config, sections)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", dd.IllConditionedWarning)
        params = dd.fit(data, cfg)
    params["meta"]["warnings"] = [str(w.message) for w in caught if issubclass(w.category, dd.IllConditionedWarning)]
    return params


def _oos_lights(config, data, rng):
    from jprt.render.lights import DirectionalLights, PointLights

    e = config["eval"]
    cand = data.candidates
    points, directional = [], []
    on_asset = np.nonzero(np.isin(cand["object_id"], np.atleast_1d(data.atlas["objects"])))[0]  # near the asset
    for _ in range(int(e["oos_n"])):
        k = rng.choice(on_asset)
        pos = cand["position"][k] + rng.uniform(*e["point_offset"]) * cand["normal"][k]
        colour = 0.4 + 0.6 * rng.random(3)
        points.append(PointLights.create(pos, rng.uniform(*e["point_intensity"]) * colour / colour.max()))
        lo, hi = np.asarray(e["directional_toward_lo"]), np.asarray(e["directional_toward_hi"])
        toward = lo + (hi - lo) * rng.random(3)
        colour = 0.4 + 0.6 * rng.random(3)
        directional.append(DirectionalLights.create(-toward, rng.uniform(*e["directional_irradiance"]) * colour
                                                    / colour.max()))
    return {"point": points, "directional": directional}


def main(config: dict) -> dict:
    """Render, fit, evaluate and report; returns the summary (also written as summary.json)."""
    from jprt.render import cameras as cams
    from jprt.render import images, lightmap
    from jprt.render.lights import SpotLights
    from jprt.render.scenes import SceneHandle

    t_start = time.perf_counter()
    config = merge(CONFIG, config)
    out = os.path.abspath(os.path.join(config["output"]["dir"], config_hash(config)))
    os.makedirs(out, exist_ok=True)
    save_resolved(config, out)
    e = config["eval"]
    summary: dict = {"config_hash": config_hash(config), "device": str(jax.devices()[0]),
                     "scene": config["scene"], "objects": config["objects"]}
    rng = np.random.default_rng(int(e["seed"]))

    # 1. Dataset and the main fit.
    t0 = time.perf_counter()
    data = dd.make_dataset(config["scene"], config)
    summary["dataset_s"] = time.perf_counter() - t0
    summary["render_train_s"] = data.meta["render_train_s"]
    summary["render_s"] = data.meta["render_s"]
    summary["texels"] = int(len(data.atlas["texel_index"]))
    summary["n_train"], summary["n_test"] = int(len(data.direct)), int(len(data.direct_test))
    params = _fit(data, config)
    summary["fit_s"] = params["meta"]["fit_s"]
    summary["lambda"] = params["meta"]["lam"]
    summary["lambda_cv"] = params["meta"]["lambda_cv"]
    summary["bake_s"] = summary["render_train_s"] + summary["fit_s"]
    summary["model_bytes"] = dd.model_bytes(params)
    summary["conditioning"] = params["meta"]["conditioning"]
    summary["fit_warnings"] = params["meta"]["warnings"]
    main_scores = _scores(params, data.direct_test, data.indirect_test)
    summary["rmse"] = main_scores["rmse"]
    summary["projection_rmse"] = main_scores["projection_rmse"]
    ref_rms = float(np.sqrt(np.mean(np.square(data.indirect_test))))
    summary["reference_rms"] = ref_rms
    summary["relative_rmse"] = summary["rmse"] / ref_rms
    _say(f"{summary['texels']} texels, {params['meta']['points']} points; n = {config['basis']['n']}: RMSE "
         f"{summary['rmse']:.5f} (projection {summary['projection_rmse']:.5f}, reference RMS {ref_rms:.4f})")
    io.save_checkpoint(os.path.join(out, "model.npz"), {k: v for k, v in params.items() if k != "meta"},
                       meta={"config_hash": summary["config_hash"]})

    # 2. Fig. 14: basis size, method vs projection.
    summary["rmse_by_basis"], summary["projection_rmse_by_basis"] = {}, {}
    for n in e["basis_sizes"]:
        p = _fit(data, config, basis={"n": int(n)})
        s = _scores(p, data.direct_test, data.indirect_test)
        summary["rmse_by_basis"][str(n)] = s["rmse"]
        summary["projection_rmse_by_basis"][str(n)] = s["projection_rmse"]
        _say(f"n = {n}: RMSE {s['rmse']:.5f}, projection {s['projection_rmse']:.5f}")
    other_mean = "linear" if config["basis"]["mean"] == "norm" else "norm"
    summary[f"rmse_by_basis_{other_mean}_mean"], summary[f"projection_rmse_by_basis_{other_mean}_mean"] = {}, {}
    for n in e["basis_sizes"]:
        p = _fit(data, config, basis={"n": int(n), "mean": other_mean})
        s = _scores(p, data.direct_test, data.indirect_test)
        summary[f"rmse_by_basis_{other_mean}_mean"][str(n)] = s["rmse"]
        summary[f"projection_rmse_by_basis_{other_mean}_mean"][str(n)] = s["projection_rmse"]
        _say(f"n = {n}, mean {other_mean}: RMSE {s['rmse']:.5f}, projection {s['projection_rmse']:.5f}")
    ns = [int(n) for n in e["basis_sizes"]]
    last = str(ns[-1])
    summary["ratio_last"] = summary["rmse_by_basis"][last] / max(summary["projection_rmse_by_basis"][last], 1e-30)
    rb, pb = summary[f"rmse_by_basis_{other_mean}_mean"], summary[f"projection_rmse_by_basis_{other_mean}_mean"]
    summary[f"ratio_last_{other_mean}_mean"] = rb[last] / max(pb[last], 1e-30)
    if "64" in summary["rmse_by_basis"]:
        summary["ratio_64"] = summary["rmse_by_basis"]["64"] / summary["projection_rmse_by_basis"]["64"]
        summary[f"ratio_64_{other_mean}_mean"] = rb["64"] / pb["64"]
    jeval.plot_series(os.path.join(out, "fig14_basis.png"),
                      {f"data-driven PRT (mean {config['basis']['mean']})":
                           (ns, [summary["rmse_by_basis"][str(n)] for n in ns]),
                       "projection onto the basis": (ns, [summary["projection_rmse_by_basis"][str(n)] for n in ns]),
                       f"data-driven PRT (mean {other_mean})": (ns, [rb[str(n)] for n in ns]),
                       f"projection (mean {other_mean})": (ns, [pb[str(n)] for n in ns])},
                      xlabel="basis elements n", ylabel="lightmap RMSE", title="Fig. 14: accuracy vs basis size",
                      logx=True, logy=True)
    norms = np.linalg.norm(data.direct.reshape(len(data.direct), -1), axis=1)
    a = (data.indirect[norms > 0] / norms[norms > 0, None, None]).reshape(int((norms > 0).sum()), -1)
    sv = np.linalg.svd(a - a.mean(0), compute_uv=False)
    summary["relative_eigenvalues"] = (sv ** 2 / np.sum(sv ** 2))[:32].tolist()
    jeval.plot_series(os.path.join(out, "fig3_eigenvalues.png"),
                      {"indirect dataset": (list(range(1, len(summary["relative_eigenvalues"]) + 1)),
                                            summary["relative_eigenvalues"])},
                      xlabel="index", ylabel="relative eigenvalue", title="Fig. 3: spectrum of the indirect data",
                      logy=True)

    # 3. lambda, measurement points, gamma, channels.
    summary["lambda_sweep"] = {}
    for lam in e["lambdas"]:
        p = _fit(data, config, transfer={"lam": float(lam), "lam_cv": []})
        summary["lambda_sweep"][repr(float(lam))] = {**_scores(p, data.direct_test, data.indirect_test),
                                                      "warnings": len(p["meta"]["warnings"])}
    summary["points_sweep"] = {}
    for count in e["point_counts"]:
        if int(count) * int(config["points"]["supersample"]) > int(config["points"]["candidates"]):
            continue
        p = _fit(data, config, points={"count": int(count)})
        summary["points_sweep"][str(count)] = _scores(p, data.direct_test, data.indirect_test)["rmse"]
    lams = [float(k) for k in summary["lambda_sweep"]]
    jeval.plot_series(os.path.join(out, "lambda_sweep.png"),
                      {"RMSE": ([max(l, 1e-6) for l in lams], [v["rmse"] for v in summary["lambda_sweep"].values()])},
                      xlabel="lambda (0 plotted at 1e-6)", ylabel="lightmap RMSE", title="ridge regularisation",
                      logx=True)
    counts = [int(k) for k in summary["points_sweep"]]
    jeval.plot_series(os.path.join(out, "points_sweep.png"),
                      {"RMSE": (counts, list(summary["points_sweep"].values()))},
                      xlabel="measurement points P", ylabel="lightmap RMSE", title="measurement-point count",
                      logx=True)
    p_gamma = _fit(data, config, basis={"gamma": float(e["gamma"])})
    summary["rmse_gamma"] = _scores(p_gamma, data.direct_test, data.indirect_test)["rmse"]
    summary["rmse_linear"] = summary["rmse"] if float(config["basis"]["gamma"]) <= 0 else None
    other = "multi" if config["basis"]["channels"] == "mono" else "mono"
    p_other = _fit(data, config, basis={"channels": other})
    summary[f"rmse_{config['basis']['channels']}"] = summary["rmse"]
    summary[f"rmse_{other}"] = _scores(p_other, data.direct_test, data.indirect_test)["rmse"]
    _say(f"gamma {e['gamma']}: {summary['rmse_gamma']:.5f}; {other}-channel: {summary[f'rmse_{other}']:.5f}")

    # 4. Out-of-scenario lights (Fig. 8) and the SH PRT baseline (§6.4).
    first = data.lights_test
    handle = SceneHandle(config["scene"], SpotLights.create(first["position"][0], first["target"][0],
                                                            first["intensity"][0], first["cutoff_deg"][0],
                                                            first["beam_deg"][0]))
    atlas = data.atlas
    spp_test = int(config["data"]["test_spp"])
    summary["rmse_out_of_scenario"] = {}
    oos = _oos_lights(config, data, rng)
    oos_data = {}
    for kind, lightings in oos.items():
        d, i = dd.render_examples(handle, atlas, data.candidates, lightings, spp=spp_test, seed=99,
                                  desc=f"{kind} lights (out of scenario)")
        oos_data[kind] = (d, i, lightings)
        summary["rmse_out_of_scenario"][kind] = _scores(params, d, i)["rmse"]
        summary["rmse_out_of_scenario"][f"{kind}_relative"] = summary["rmse_out_of_scenario"][kind] / float(
            np.sqrt(np.mean(np.square(i))))
    summary["rmse_out_of_scenario"]["spot_relative (in scenario)"] = summary["relative_rmse"]
    _say(f"out of scenario: {summary['rmse_out_of_scenario']}")

    t0 = time.perf_counter()
    degree = max(sh_prt.order_to_degree(o) for o in e["sh_orders"])
    transfer = sh_prt.bake(handle, atlas, degree, spp=int(e["sh_spp"]), env_height=int(e["sh_env_height"]))
    summary["sh_bake_s"] = time.perf_counter() - t0
    center = np.asarray(atlas["position"]).mean(axis=0)
    test_lights = [SpotLights.create(first["position"][k], first["target"][k], first["intensity"][k],
                                     first["cutoff_deg"][k], first["beam_deg"][k]) for k in range(len(data.direct_test))]
    summary["rmse_sh_prt"], summary["rmse_sh_prt_out_of_scenario"] = {}, {}
    for order in e["sh_orders"]:
        deg = sh_prt.order_to_degree(order)

        def sh_lightmaps(lightings):
            out_ = []
            for lighting in lightings:
                dirs, irr = lightmap.incident_delta_lights(handle, center, lighting)
                out_.append(sh_prt.lightmap(transfer, sh_prt.delta_light_coefficients(dirs, irr, deg)))
            return np.stack(out_)

        summary["rmse_sh_prt"][str(order)] = dd.lightmap_rmse(sh_lightmaps(test_lights), data.indirect_test)
        summary["rmse_sh_prt_out_of_scenario"][str(order)] = {
            kind: dd.lightmap_rmse(sh_lightmaps(v[2]), v[1]) for kind, v in oos_data.items()}
    summary["sh_prt_note"] = ("classic SH PRT (Sloan et al. 2002): transfer vectors baked with Mitsuba from SH "
                              "environment maps (positive and negative parts), each light projected as a delta "
                              "from its direction at the asset centre")
    summary["beats_sh_prt"] = summary["rmse"] < min(summary["rmse_sh_prt"].values())
    _say(f"SH PRT: {summary['rmse_sh_prt']} vs data-driven {summary['rmse']:.5f}")

    # 5. Images: a camera view of held-out lights, method vs path-traced reference.
    c = e["camera"]
    res = int(e["image_resolution"])
    cam = cams.look_at(c["origin"], c["target"], fov=float(c["fov"]), width=res, height=res)
    atlas_nt = lightmap.Atlas(**atlas)
    gb = lightmap.atlas_gbuffer(handle, atlas_nt, cam)
    evaluate = dd.evaluator(params)
    rows = []
    for k in range(min(int(e["images"]), len(test_lights))):
        handle.set_lighting(test_lights[k])
        rad = images.direct_indirect(handle, cam, spp=int(e["image_spp"]), seed=5 + k)
        ref = np.where(gb.valid[..., None], rad.indirect, 0.0)
        pred = np.asarray(evaluate(gb, data.direct_test[k][params["fine_index"]]))
        rows.append((f"held-out light {k}", ref, pred))
        io.write_exr(os.path.join(out, f"light{k:02d}_reference.exr"), ref)
        io.write_exr(os.path.join(out, f"light{k:02d}_datadriven.exr"), pred)
        io.write_png(os.path.join(out, f"light{k:02d}_final_datadriven.png"), rad.direct + pred,
                     exposure=float(e["exposure"]))
        io.write_png(os.path.join(out, f"light{k:02d}_final_reference.png"), rad.direct + ref,
                     exposure=float(e["exposure"]))
    if rows:
        jeval.side_by_side(os.path.join(out, "side_by_side.png"), rows, exposure=float(e["exposure"]))
        summary["image_rmse"] = jeval.set_rmse([r[2] for r in rows], [r[1] for r in rows], [gb.valid] * len(rows))
    r = int(atlas["resolution"])
    basis_img = np.asarray(params["basis"])[np.asarray(atlas["fill_index"])]
    tiles = [np.asarray(params["mean"])[np.asarray(atlas["fill_index"])]] + [basis_img[:, j] for j in
                                                                             range(min(7, basis_img.shape[1]))]
    tiles = [t.reshape(r, r) / max(np.abs(t).max(), 1e-30) for t in tiles]
    io.write_png(os.path.join(out, "basis_mean_and_first7.png"),
                 np.repeat(0.5 + 0.5 * np.concatenate(tiles, axis=1)[..., None], 3, axis=-1), tonemapped=True)

    # 6. Timings: the transfer product alone, and a whole frame at the timing resolution.
    x = dd.coarse_direct(data.direct_test[0][params["fine_index"]], params["group"], params["counts"])
    summary["transfer_us"] = 1e3 * jeval.time_call(evaluate.transfer, jax.numpy.asarray(x, jax.numpy.float32),
                                                   repeats=int(e["timing_repeats"]) * 5)["median_ms"]
    tr = int(e["timing_resolution"])
    tcam = cams.look_at(c["origin"], c["target"], fov=float(c["fov"]), width=tr, height=tr)
    tgb = lightmap.atlas_gbuffer(handle, atlas_nt, tcam)
    uv, valid = jax.numpy.asarray(tgb.uv), jax.numpy.asarray(tgb.valid)
    direct0 = jax.numpy.asarray(data.direct_test[0][params["fine_index"]], jax.numpy.float32)
    summary["frame_ms"] = jeval.time_call(evaluate.jitted, uv, valid, direct0, repeats=int(e["timing_repeats"]))[
        "median_ms"]
    summary["timing_resolution"] = tr
    if tr == 512:
        summary["frame_ms_512"] = summary["frame_ms"]
    handle.set_lighting(test_lights[0])
    fine_pos = np.asarray(data.candidates["position"])[params["fine_index"]]
    fine_nrm = np.asarray(data.candidates["normal"])[params["fine_index"]]
    lightmap.radiance_at_points(handle, fine_pos, fine_nrm, spp=1)  # warm-up (kernel compile)
    summary["direct_measure_ms"] = jeval.time_call(
        lambda: lightmap.radiance_at_points(handle, fine_pos, fine_nrm, spp=1), repeats=5, warmup=0)["median_ms"]
    summary["timing_note"] = ("transfer_us: u = M_n x alone (jitted, CPU); frame_ms: coarse averaging, transfer, "
                              "lightmap reconstruction and bilinear lookup for every pixel (jitted, CPU); "
                              "direct_measure_ms: Mitsuba shading of the fine measurement points (outside JAX)")
    _say(f"transfer {summary['transfer_us']:.1f} us, frame {summary['frame_ms']:.2f} ms at {tr}^2, "
         f"direct measurement {summary['direct_measure_ms']:.1f} ms")
    return jeval.write_report(out, summary, t_start, "data-driven PRT")
