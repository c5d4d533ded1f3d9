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
held-out lightmaps, as (R, R) atlas images whose valid pixels are the covered texels).
"""

from __future__ import annotations

import os
import time
import warnings

import jax
import numpy as np

from jprt import eval as jeval
from jprt import io
from jprt.inputs import PointRadiance
from jprt.methods.base import FitResult
from jprt.methods.datadriven import data as dd_data
from jprt.methods.datadriven import model as dd
from jprt.methods.lightmap_lookup import atlas_inputs
from jprt.methods.sh_prt import model as sh_prt
from jprt.methods import REGISTRY
from jprt.runner import HeldOut

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
    """A fit of the run's dataset with ``sections`` overriding the method config; the
    ill-conditioning warnings it raised are kept in ``info["warnings"]``."""
    cfg = run.with_config(sections)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", dd.IllConditionedWarning)
        result = dd.fit(run.dataset, cfg)
    result.info["warnings"] = [str(w.message) for w in caught if issubclass(w.category, dd.IllConditionedWarning)]
    result.info["config"] = cfg
    return result


def _scores(result: FitResult, direct, indirect) -> dict:
    """Lightmap RMSE of the method and of projecting the references onto its basis (Fig. 14)."""
    params, cfg = result.params, result.info["config"]
    fine = np.asarray(params["fine_index"])
    pred = np.asarray(dd.lightmap(params, direct[:, fine], cfg))
    proj = dd.project(params, direct[:, fine], indirect, cfg)
    return {"rmse": dd.lightmap_rmse(pred, indirect), "projection_rmse": dd.lightmap_rmse(proj, indirect)}


def _lightmap_image(texels, atlas) -> np.ndarray:
    """Lightmap texels (T, 3) -> (R, R, 3) atlas image (zeros outside the covered texels)."""
    r = int(atlas["resolution"])
    image = np.zeros((r * r, 3), np.float32)
    image[np.asarray(atlas["texel_index"])] = texels
    return image.reshape(r, r, 3)


def _handle(run):
    from jprt.render.lights import SpotLights
    from jprt.render.scenes import SceneHandle

    if "handle" not in run.state:
        first = run.dataset.lights_test
        run.state["handle"] = SceneHandle(run.config["scene"], SpotLights.create(
            first["position"][0], first["target"][0], first["intensity"][0], first["cutoff_deg"][0],
            first["beam_deg"][0]))
    return run.state["handle"]


def _test_lights(run) -> list:
    from jprt.render.lights import SpotLights

    first = run.dataset.lights_test
    return [SpotLights.create(first["position"][k], first["target"][k], first["intensity"][k], first["cutoff_deg"][k],
                              first["beam_deg"][k]) for k in range(len(run.dataset.direct_test))]


# --------------------------------------------------------------------------------------------
# The runner's hooks


def fit(run) -> FitResult:
    """The main fit (lambda by cross-validation), with its warnings."""
    result = _fit(run)
    result.info["train_s"] = result.info["fit_s"]
    return result


def held_out(run) -> HeldOut:
    """The held-out lighting configurations: each lightmap as an atlas image, predicted by the
    evaluator on the atlas itself (``jprt.methods.lightmap_lookup.atlas_inputs``)."""
    data, params = run.dataset, run.result.params
    inputs = atlas_inputs(int(data.atlas["resolution"]), data.atlas["texel_index"])
    fine = np.asarray(params["fine_index"])
    preds = [np.asarray(run.evaluate(inputs, PointRadiance(d[fine]))) for d in data.direct_test]
    refs = [_lightmap_image(i, data.atlas) for i in data.indirect_test]
    return HeldOut(preds, refs, [inputs.valid] * len(refs), None, [f"held-out light {k}" for k in range(len(refs))])


def frame(run):
    """The lightmap itself, as the equal-error peer renders it: the atlas (every covered texel)
    under the first held-out configuration's direct light at the fine measurement points (the
    camera view is timed by the ``camera_frame`` stage)."""
    data = run.dataset
    inputs = atlas_inputs(int(data.atlas["resolution"]), data.atlas["texel_index"])
    return inputs, PointRadiance(np.asarray(data.direct_test[0][run.result.params["fine_index"]], np.float32))


def pathtracer(run):
    """Mitsuba rendering the held-out lightmap texels (indirect = full minus direct, equal seeds;
    a seed unlike the references'), timed for one configuration's whole lightmap."""
    from jprt.render import lightmap
    from jprt.runner import PathTracer

    data, handle = run.dataset, _handle(run)
    lights = _test_lights(run)
    pos, nrm = data.atlas["position"], data.atlas["normal"]

    def render_at(spp):
        out = []
        for k, lighting in enumerate(lights):
            handle.set_lighting(lighting)
            out.append(_lightmap_image(lightmap.indirect_at_points(handle, pos, nrm, spp=spp, seed=4242 + k),
                                       data.atlas))
        return out

    def time_at(spp):
        handle.set_lighting(lights[0])
        lightmap.indirect_at_points(handle, pos, nrm, spp=spp, seed=3)  # warm-up (kernel compile)
        return jeval.time_call(lambda: lightmap.indirect_at_points(handle, pos, nrm, spp=spp, seed=3),
                               repeats=int(run.config["eval"]["pathtrace_repeats"]), warmup=0)["median_ms"]

    return PathTracer(render_at, time_at, "Mitsuba llvm_ad_rgb at the lightmap texels: indirect = full (max_depth "
                                          "-1) minus direct (max_depth 2), both renders timed; the evaluator's "
                                          "frame is the same lightmap (transfer, reconstruction, atlas lookup)")


# --------------------------------------------------------------------------------------------
# Stages


def fit_report(run) -> dict:
    """The main fit: sizes, lambda, conditioning, and its method-vs-projection score."""
    data, result = run.dataset, run.result
    s = {"render_train_s": data.meta["render_train_s"], "render_s": data.meta["render_s"],
         "texels": int(len(data.atlas["texel_index"])), "n_train": int(len(data.direct)),
         "n_test": int(len(data.direct_test)), "fit_s": result.info["fit_s"], "lambda": result.info["lam"],
         "lambda_cv": result.info["lambda_cv"], "conditioning": result.info["conditioning"],
         "fit_warnings": result.info["warnings"]}
    s["bake_s"] = s["render_train_s"] + s["fit_s"]
    scores = _scores(result, data.direct_test, data.indirect_test)
    s["rmse"], s["projection_rmse"] = scores["rmse"], scores["projection_rmse"]
    s["reference_rms"] = float(np.sqrt(np.mean(np.square(data.indirect_test))))
    s["relative_rmse"] = s["rmse"] / s["reference_rms"]
    run.say(f"{s['texels']} texels, {result.info['points']} points; n = {run.method_config['basis']['n']}: RMSE "
            f"{s['rmse']:.5f} (projection {s['projection_rmse']:.5f}, reference RMS {s['reference_rms']:.4f})")
    return s


def basis_sizes(run) -> dict:
    """Fig. 14: accuracy against the basis size n, for the method and for projecting the
    references onto the basis, with both mean conventions; Fig. 3: the spectrum of the data."""
    data, e, mean = run.dataset, run.config["eval"], run.method_config["basis"]["mean"]
    other = "linear" if mean == "norm" else "norm"
    ns = [int(n) for n in e["basis_sizes"]]
    table = {}
    for label, extra in ((mean, {}), (other, {"mean": other})):
        rmse, proj = {}, {}
        for n in ns:
            sc = _scores(_fit(run, basis={"n": n, **extra}), data.direct_test, data.indirect_test)
            rmse[str(n)], proj[str(n)] = sc["rmse"], sc["projection_rmse"]
            run.say(f"n = {n}, mean {label}: RMSE {sc['rmse']:.5f}, projection {sc['projection_rmse']:.5f}")
        table[label] = (rmse, proj)
    (rb, pb), (rbo, pbo) = table[mean], table[other]
    last = str(ns[-1])
    s = {"rmse_by_basis": rb, "projection_rmse_by_basis": pb, f"rmse_by_basis_{other}_mean": rbo,
         f"projection_rmse_by_basis_{other}_mean": pbo, "ratio_last": rb[last] / max(pb[last], 1e-30),
         f"ratio_last_{other}_mean": rbo[last] / max(pbo[last], 1e-30)}
    if "64" in rb:
        s["ratio_64"], s[f"ratio_64_{other}_mean"] = rb["64"] / pb["64"], rbo["64"] / pbo["64"]
    jeval.plot_series(os.path.join(run.out, "fig14_basis.png"),
                      {f"data-driven PRT (mean {mean})": (ns, [rb[str(n)] for n in ns]),
                       "projection onto the basis": (ns, [pb[str(n)] for n in ns]),
                       f"data-driven PRT (mean {other})": (ns, [rbo[str(n)] for n in ns]),
                       f"projection (mean {other})": (ns, [pbo[str(n)] for n in ns])},
                      xlabel="basis elements n", ylabel="lightmap RMSE", title="Fig. 14: accuracy vs basis size",
                      logx=True, logy=True)
    norms = np.linalg.norm(data.direct.reshape(len(data.direct), -1), axis=1)
    a = (data.indirect[norms > 0] / norms[norms > 0, None, None]).reshape(int((norms > 0).sum()), -1)
    sv = np.linalg.svd(a - a.mean(0), compute_uv=False)
    s["relative_eigenvalues"] = (sv ** 2 / np.sum(sv ** 2))[:32].tolist()
    jeval.plot_series(os.path.join(run.out, "fig3_eigenvalues.png"),
                      {"indirect dataset": (list(range(1, len(s["relative_eigenvalues"]) + 1)),
                                            s["relative_eigenvalues"])},
                      xlabel="index", ylabel="relative eigenvalue", title="Fig. 3: spectrum of the indirect data",
                      logy=True)
    return s


def sweeps(run) -> dict:
    """Ridge lambda, measurement-point count, gamma space (§5.3), mono vs multi-channel (§5.2)."""
    data, e, mcfg = run.dataset, run.config["eval"], run.method_config
    s = {"lambda_sweep": {}, "points_sweep": {}}
    for lam in e["lambdas"]:
        r = _fit(run, transfer={"lam": float(lam), "lam_cv": []})
        s["lambda_sweep"][repr(float(lam))] = {**_scores(r, data.direct_test, data.indirect_test),
                                               "warnings": len(r.info["warnings"])}
    for count in e["point_counts"]:
        if int(count) * int(mcfg["points"]["supersample"]) > int(mcfg["points"]["candidates"]):
            continue
        s["points_sweep"][str(count)] = _scores(_fit(run, points={"count": int(count)}), data.direct_test,
                                                data.indirect_test)["rmse"]
    lams = [float(k) for k in s["lambda_sweep"]]
    jeval.plot_series(os.path.join(run.out, "lambda_sweep.png"),
                      {"RMSE": ([max(v, 1e-6) for v in lams], [v["rmse"] for v in s["lambda_sweep"].values()])},
                      xlabel="lambda (0 plotted at 1e-6)", ylabel="lightmap RMSE", title="ridge regularisation",
                      logx=True)
    counts = [int(k) for k in s["points_sweep"]]
    jeval.plot_series(os.path.join(run.out, "points_sweep.png"), {"RMSE": (counts, list(s["points_sweep"].values()))},
                      xlabel="measurement points P", ylabel="lightmap RMSE", title="measurement-point count", logx=True)
    main_rmse = run.summary["extra"]["rmse"]
    s["rmse_gamma"] = _scores(_fit(run, basis={"gamma": float(e["gamma"])}), data.direct_test,
                              data.indirect_test)["rmse"]
    s["rmse_linear"] = main_rmse if float(mcfg["basis"]["gamma"]) <= 0 else None
    other = "multi" if mcfg["basis"]["channels"] == "mono" else "mono"
    s[f"rmse_{mcfg['basis']['channels']}"] = main_rmse
    s[f"rmse_{other}"] = _scores(_fit(run, basis={"channels": other}), data.direct_test, data.indirect_test)["rmse"]
    run.say(f"gamma {e['gamma']}: {s['rmse_gamma']:.5f}; {other}-channel: {s[f'rmse_{other}']:.5f}")
    return s


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


def out_of_scenario(run) -> dict:
    """Fig. 8: point lights near the asset and directional lights, outside the training scenario."""
    data = run.dataset
    if int(run.config["eval"]["oos_n"]) <= 0:
        return {}
    rng = np.random.default_rng(int(run.config["eval"]["seed"]))
    spp_test = int(run.method_config["data"]["test_spp"])
    s = {}
    run.state["oos"] = {}
    for kind, lightings in _oos_lights(run.config, data, rng).items():
        d, i = dd_data.render_examples(_handle(run), data.atlas, data.candidates, lightings, spp=spp_test, seed=99,
                                       desc=f"{kind} lights (out of scenario)")
        run.state["oos"][kind] = (d, i, lightings)
        s[kind] = _scores(run.result, d, i)["rmse"]
        s[f"{kind}_relative"] = s[kind] / float(np.sqrt(np.mean(np.square(i))))
    s["spot_relative (in scenario)"] = run.summary["extra"]["relative_rmse"]
    run.say(f"out of scenario: {s}")
    return {"rmse_out_of_scenario": s}


def sh_prt_baseline(run) -> dict:
    """§6.4: classic SH PRT of the asset (``jprt.methods.sh_prt``), each light a delta from its
    direction at the asset centre, on the held-out and out-of-scenario lights."""
    from jprt.render import lightmap

    e, data = run.config["eval"], run.dataset
    handle, atlas = _handle(run), data.atlas
    t0 = time.perf_counter()
    sh_config = {"scene": run.config["scene"], "objects": run.method_config["objects"],
                 "lightmap": run.method_config["lightmap"],  # the same atlas as the data-driven fit
                 "sh": {"order": max(int(o) for o in e["sh_orders"]), "spp": int(e["sh_spp"]),
                        "env_height": int(e["sh_env_height"])}}
    baked = REGISTRY["sh_prt"].make_dataset(run.config["scene"], sh_config)  # cached by jprt.cache
    if not np.array_equal(baked.atlas["texel_index"], atlas["texel_index"]):
        raise RuntimeError("the SH PRT atlas differs from the data-driven one")
    transfer = baked.transfer
    s = {"sh_bake_s": baked.meta["bake_s"], "sh_stage_s": time.perf_counter() - t0, "rmse_sh_prt": {},
         "rmse_sh_prt_out_of_scenario": {}}
    center = np.asarray(atlas["position"]).mean(axis=0)

    def sh_lightmaps(lightings, deg):
        out = []
        for lighting in lightings:
            dirs, irr = lightmap.incident_delta_lights(handle, center, lighting)
            out.append(sh_prt.lightmap(transfer, sh_prt.delta_light_coefficients(dirs, irr, deg)))
        return np.stack(out)

    for order in e["sh_orders"]:
        deg = sh_prt.order_to_degree(order)
        s["rmse_sh_prt"][str(order)] = dd.lightmap_rmse(sh_lightmaps(_test_lights(run), deg), data.indirect_test)
        s["rmse_sh_prt_out_of_scenario"][str(order)] = {
            kind: dd.lightmap_rmse(sh_lightmaps(v[2], deg), v[1]) for kind, v in run.state.get("oos", {}).items()}
    s["sh_prt_note"] = ("classic SH PRT (Sloan et al. 2002): transfer vectors baked with Mitsuba from SH environment "
                        "maps (positive and negative parts), each light projected as a delta from its direction at "
                        "the asset centre")
    s["beats_sh_prt"] = run.summary["extra"]["rmse"] < min(s["rmse_sh_prt"].values())
    run.say(f"SH PRT: {s['rmse_sh_prt']} vs data-driven {run.summary['extra']['rmse']:.5f}")
    return s


def camera_images(run) -> dict:
    """Held-out lights seen by a camera: the method against path-traced references
    (camera_side_by_side.png, EXRs, tonemapped finals) and the basis pictures."""
    from jprt.render import cameras as cams
    from jprt.render import images, lightmap

    e, data, params = run.config["eval"], run.dataset, run.result.params
    c, res = e["camera"], int(e["image_resolution"])
    cam = cams.look_at(c["origin"], c["target"], fov=float(c["fov"]), width=res, height=res)
    handle = _handle(run)
    gb = lightmap.atlas_gbuffer(handle, lightmap.Atlas(**data.atlas), cam)
    rows, s = [], {}
    lights = _test_lights(run)
    for k in range(min(int(e["images"]), len(lights))):
        handle.set_lighting(lights[k])
        rad = images.direct_indirect(handle, cam, spp=int(e["image_spp"]), seed=5 + k)
        ref = np.where(gb.valid[..., None], rad.indirect, 0.0)
        pred = np.asarray(run.evaluate(gb, PointRadiance(data.direct_test[k][params["fine_index"]])))
        rows.append((f"held-out light {k}", ref, pred))
        io.write_exr(os.path.join(run.out, f"light{k:02d}_reference.exr"), ref)
        io.write_exr(os.path.join(run.out, f"light{k:02d}_datadriven.exr"), pred)
        for name, image in (("datadriven", pred), ("reference", ref)):
            io.write_png(os.path.join(run.out, f"light{k:02d}_final_{name}.png"), rad.direct + image,
                         exposure=float(e["exposure"]))
    if rows:
        jeval.side_by_side(os.path.join(run.out, "camera_side_by_side.png"), rows, exposure=float(e["exposure"]))
        s["image_rmse"] = jeval.set_rmse([r[2] for r in rows], [r[1] for r in rows], [gb.valid] * len(rows))
    r = int(data.atlas["resolution"])
    fill = np.asarray(data.atlas["fill_index"])
    basis_img = np.asarray(params["basis"])[fill]
    tiles = [np.asarray(params["mean"])[fill]] + [basis_img[:, j] for j in range(min(7, basis_img.shape[1]))]
    tiles = [t.reshape(r, r) / max(np.abs(t).max(), 1e-30) for t in tiles]
    io.write_png(os.path.join(run.out, "basis_mean_and_first7.png"),
                 np.repeat(0.5 + 0.5 * np.concatenate(tiles, axis=1)[..., None], 3, axis=-1), tonemapped=True)
    return s


def camera_frame(run) -> dict:
    """A camera view of the asset at ``eval.timing_resolution`` (atlas G-buffer) under the first
    held-out configuration: the evaluator's time and roofline for a rendered frame."""
    from jprt.render import cameras as cams
    from jprt.render import lightmap

    e, params = run.config["eval"], run.result.params
    c, tr = e["camera"], int(e["timing_resolution"])
    cam = cams.look_at(c["origin"], c["target"], fov=float(c["fov"]), width=tr, height=tr)
    gb = lightmap.atlas_gbuffer(_handle(run), lightmap.Atlas(**run.dataset.atlas), cam)
    gb, light = jax.device_put((gb, PointRadiance(np.asarray(run.dataset.direct_test[0][params["fine_index"]],
                                                              np.float32))))
    fast = jax.jit(run.evaluate)
    ms = jeval.time_call(fast, gb, light, repeats=int(e["timing_repeats"]))["median_ms"]
    roof = jeval.roofline(fast, gb, light, frame_ms=ms, peak_gflops=run.summary["matmul_peak_gflops"])
    return {"frame_ms_camera": ms, "frame_resolution_camera": [tr, tr], "frame_flops_camera": roof["frame_flops"],
            "flops_fraction_of_peak_camera": roof["flops_fraction_of_peak"]}


def timings(run) -> dict:
    """The transfer product alone (jitted), and Mitsuba's shading of the fine measurement points;
    the speedup at equal error counting that shading too (the paper's run time measures direct
    light by deferred shading on the GPU, §4.3)."""
    from jprt.render import lightmap

    e, data, params = run.config["eval"], run.dataset, run.result.params
    x = dd.coarse_direct(data.direct_test[0][params["fine_index"]], params["group"], params["counts"])
    transfer = jax.jit(lambda v: dd.transfer_coefficients(params, v, run.method_config))
    s = {"transfer_us": 1e3 * jeval.time_call(transfer, jax.numpy.asarray(x, jax.numpy.float32),
                                               repeats=int(e["timing_repeats"]) * 5)["median_ms"]}
    handle = _handle(run)
    handle.set_lighting(_test_lights(run)[0])
    fine_pos = np.asarray(data.candidates["position"])[params["fine_index"]]
    fine_nrm = np.asarray(data.candidates["normal"])[params["fine_index"]]
    lightmap.radiance_at_points(handle, fine_pos, fine_nrm, spp=1)  # warm-up (kernel compile)
    s["direct_measure_ms"] = jeval.time_call(
        lambda: lightmap.radiance_at_points(handle, fine_pos, fine_nrm, spp=1), repeats=5, warmup=0)["median_ms"]
    s["timing_note"] = ("transfer_us: u = M_n x alone (jitted, CPU); frame_ms: coarse averaging, transfer, lightmap "
                        "reconstruction and lookup of every covered texel of the atlas (jitted, CPU); frame_ms_camera: "
                        "the same for every pixel of a camera view; direct_measure_ms: Mitsuba shading of the fine "
                        "measurement points (outside JAX)")
    pt = run.summary.get("pathtrace_ms_equal_error")
    if pt:
        s["speedup_equal_error_with_direct"] = pt / (run.summary["frame_ms"] + s["direct_measure_ms"])
    run.say(f"transfer {s['transfer_us']:.1f} us, direct measurement {s['direct_measure_ms']:.1f} ms")
    return s


#: The stages of the data-driven PRT report, in order.
STAGES = [fit_report, basis_sizes, sweeps, out_of_scenario, sh_prt_baseline, camera_images, camera_frame, timings]
