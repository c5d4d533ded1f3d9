"""Modular Radiance Transfer (Loos et al. 2011) end to end: indirect light at the texels of block
layouts it was never tuned on, under point lights it never saw.

    jprt run experiments/mrt.py --preset test     # seconds
    jprt run experiments/mrt.py                   # `small`: 8^2 texels per face, 11- and 41-block layouts
    jprt run experiments/mrt.py --preset paper    # 16^2 texels per face, 12^2 x 24^2 lightfields

Pipeline: the dictionary (``jprt.methods.mrt.model.dictionary``: analytic, scene-independent,
cached) -> the layout's operators (T_b->r) -> held-out point lightings of the layout rendered by
Mitsuba at every texel (direct exact, indirect at ``data.test_spp``) -> the run time of §7.3 from
the direct texels -> RMSE over all texels (each held-out "image" is the padded lightmap atlas,
invalid where no texel is). Mitsuba's peer renders the same texels at n spp (equal error).

Stages (``STAGES``): a second held-out layout (``eval.layouts``: 41 blocks at ``small``); the
projection floor; ablations (k_b, k_rlf, k_r, no interfaces, no enrichment, feedback bounces);
Table 2 redone; data-driven PRT (Belcour et al. 2022) trained on this layout at the same texels,
with its per-layout setup time, and the ambient term; vector irradiance (§6.4) and irradiance
volumes (§6.5) against quadrature of the reference radiance; frame time by block count with its
log-log slope, T_b->r build times, FLOPs per frame and the f32 matmul rate of this process.
Helpers in ``jprt.methods.mrt.evaluation``; ``benchmarks/mrt.py`` turns the report into
benchmarks/results/mrt.json.
"""

from __future__ import annotations

import time

import jax
import jax.numpy as jnp
import numpy as np

from jprt import eval as jeval
from jprt import layouts
from jprt.config import merge
from jprt.methods import REGISTRY
from jprt.methods.mrt import data as mdata
from jprt.methods.mrt import evaluation as ev
from jprt.methods.mrt import model, operators
from jprt.methods.mrt.block_atlas import atlas_gbuffer_inputs
from jprt.runner import HeldOut, PathTracer

METHOD = "mrt"
LABEL = "mrt"

EVAL_DEFAULTS = {
    # held-out layouts besides the config's scene: random mazes (cells, seed, extra edges = cycles)
    "layouts": [{"blocks": 41, "seed": 11, "cycles": 4}],
    "layout_lightings": 4,
    "timing_repeats": 20,
    "equal_error_spp": [1, 2, 4, 8, 16, 32, 64, 128, 256, 512, 1024, 2048],
    "ablations": {"k_b": [4, 8, 16, 32], "k_rlf": [8, 16, 32, 64], "k_r": [4, 8, 16, 32], "feedback": [0, 1, 2, 4]},
    "table2_texels": [8, 16],
    # data-driven PRT on the same layout and texels: training lightings, their spp, basis sizes
    "datadriven": {"n_train": 64, "spp": 64, "basis": 16, "points": 256},
    "vector": {"tilt_deg": 45.0},
    "frame_blocks": [1, 4, 11, 19, 41, 64],
    "images": 2,
    "exposure": 0.0,
}

CONFIG = {**REGISTRY["mrt"].default_config, "eval": EVAL_DEFAULTS, "output": {"dir": "results/mrt"}}

PRESETS = {
    "small": {},
    # the paper's sizes (§7.1): 16^2 texels per face, k_rlf 128, 12^2 x 24^2 lightfields; 11 / 19 / 41 blocks
    "paper": {"dictionary": {"texels": 16}, "interfaces": {"spatial": 12, "directional": 24, "spatial_ss": 1,
                                                           "directional_ss": 5, "k_rlf": 128, "k_r": 32},
              "eval": {"layouts": [{"blocks": 19, "seed": 19, "cycles": 2}, {"blocks": 41, "seed": 11, "cycles": 4}],
                       "table2_texels": [16]}},
    "test": {
        **REGISTRY["mrt"].presets["test"],
        "eval": {"layouts": [{"blocks": 4, "seed": 1, "cycles": 1}], "layout_lightings": 1, "timing_repeats": 2,
                 "equal_error_spp": [1, 4], "ablations": {"k_b": [4, 12], "k_rlf": [8, 24], "k_r": [4, 12],
                                                          "feedback": [0, 1]},
                 "table2_texels": [4], "datadriven": {"n_train": 6, "spp": 4, "basis": 3, "points": 8},
                 "frame_blocks": [1, 4], "images": 1},
    },
}


def _scene(run) -> dict:
    from jprt.render.scenes import describe

    return describe(run.config["scene"])


def _mask(run) -> np.ndarray:
    return np.asarray(run.result.params["mask"], bool)


def _texel_rmse(run, pred) -> tuple[float, float]:
    """``evaluation.texel_rmse`` of texels of the run's layout against its held-out references."""
    return ev.texel_rmse(pred, run.dataset.indirect_test, _mask(run))


def held_out(run) -> HeldOut:
    """The held-out lightings of the layout: the evaluator on the padded atlas (every texel)
    against Mitsuba's indirect at the same texels."""
    from jprt.inputs import PointRadiance

    ds = run.dataset
    inputs = atlas_gbuffer_inputs(ds.albedo)
    evaluate = jax.jit(run.evaluate)
    preds = [np.asarray(evaluate(inputs, PointRadiance(d.reshape(-1, 3).astype(np.float32)))) for d in ds.direct_test]
    refs = ev.atlas_images(ds.indirect_test, ds.albedo.shape)
    direct = ev.atlas_images(ds.direct_test, ds.albedo.shape)
    valid = [np.asarray(inputs.valid, bool)] * len(preds)
    return HeldOut(preds, refs, valid, direct, [f"lighting {k}" for k in range(len(preds))])


def pathtracer(run) -> PathTracer:
    """Mitsuba rendering the same texels (full minus direct at the texel centres, ``spp`` paths
    each, a seed unlike the references'); timed on the first held-out lighting."""
    from jprt.inputs import PointLights
    from jprt.render import lightmap
    from jprt.render.scenes import SceneHandle

    ds = run.dataset
    lights = [PointLights.create(p, i) for p, i in zip(ds.lights_test["position"], ds.lights_test["intensity"])]
    return lightmap.points_pathtracer(
        SceneHandle(run.config["scene"]), ds.positions.reshape(-1, 3), ds.normals.reshape(-1, 3), lights,
        lambda texels: ev.atlas_images(np.stack([t.reshape(ds.positions.shape) for t in texels]), ds.albedo.shape),
        seed=777, time_seed=999,
        note="Mitsuba path (LLVM, this CPU): indirect at every texel centre = full minus direct (two renders, "
             "equal seeds); MRT's time is the lightmap at the same texels with Mitsuba's direct given")


def held_out_layouts(run) -> dict:
    """RMSE on the main layout's texels and on the held-out layouts of ``eval.layouts``."""
    ds, cfg, e = run.dataset, run.method_config, run.config["eval"]
    pred = ev.predict(run.result.params, ds.direct_test, ds.albedo, cfg)
    rmse, rel = _texel_rmse(run, pred)
    out = {"rmse": rmse, "relative_rmse": rel, "blocks": len(layouts.layout_from_dict(ds.layout).cells),
           "layout": ds.layout, "by_layout": {}}
    run.state["pred"] = pred
    for spec in e["layouts"]:
        lay = layouts.random_maze(int(spec["blocks"]), seed=int(spec["seed"]), extra_edges=int(spec["cycles"]))
        scene = merge(run.config["scene"], {"layout": lay.as_dict()})
        cfg2 = run.with_config({"scene": scene, "data": {"n_test": int(e["layout_lightings"])}})
        ds2 = mdata.make_dataset(scene, cfg2)
        ops2 = ev.layout_operators(run.with_config({}), lay.as_dict())
        p2 = ev.predict(ops2, ds2.direct_test, ds2.albedo, cfg)
        r2, rel2 = ev.texel_rmse(p2, ds2.indirect_test, np.asarray(ops2["mask"], bool))
        out["by_layout"][str(spec["blocks"])] = {"rmse": r2, "relative_rmse": rel2, "cycles": lay.has_cycle(),
                                                 "lightings": int(e["layout_lightings"]),
                                                 "tbr_build_s": float(ops2["tbr_build_s"])}
        run.state.setdefault("layouts", {})[str(spec["blocks"])] = (ops2, ds2)
        run.say(f"held-out layout of {spec['blocks']} blocks: relative RMSE {rel2:.3f}")
    run.say(f"layout of {out['blocks']} blocks: RMSE {rmse:.4f}, relative {rel:.3f}")
    return {"texel_rmse": out}


def projection_floor(run) -> dict:
    """The projection floor: the reference projected on each block's own bases (``model.projection``)."""
    ref = run.dataset.indirect_test
    rmse, rel = _texel_rmse(run, np.stack([model.projection(run.result.params, r) for r in ref]))
    rmse_w, rel_w = _texel_rmse(run, np.stack([model.projection(run.result.params, r, use_interfaces=False)
                                               for r in ref]))
    return {"projection_rmse": rmse, "projection_relative_rmse": rel, "projection_rmse_within_only": rmse_w,
            "projection_relative_rmse_within_only": rel_w}


def ablations(run) -> dict:
    """RMSE by k_b, k_rlf, k_r (each a dictionary of its own), without interfaces, without
    enrichment, and by feedback bounces."""
    ds, a = run.dataset, run.config["eval"]["ablations"]

    def score(overrides=None, params=None, **kw):
        c = run.with_config(overrides or {})
        ops = ev.layout_operators(c, ds.layout) if params is None else params
        return _texel_rmse(run, ev.predict(ops, ds.direct_test, ds.albedo, c, **kw))[0]

    out = {"rmse_by_kb": {str(k): score({"dictionary": {"k_b": int(k)}}) for k in a["k_b"]},
           "rmse_by_krlf": {str(k): score({"interfaces": {"k_rlf": int(k)}}) for k in a["k_rlf"]},
           "rmse_by_kr": {str(k): score({"interfaces": {"k_r": int(k)}}) for k in a["k_r"]},
           "rmse_no_interfaces": score(params=run.result.params, interfaces=False),
           # App. A for both priors (the block prior and H_rlf), then each alone
           "rmse_no_enrichment": score({"dictionary": {"enrich": False}, "interfaces": {"enrich_iterations": 0}}),
           "rmse_no_block_enrichment": score({"dictionary": {"enrich": False}}),
           "rmse_no_interface_enrichment": score({"interfaces": {"enrich_iterations": 0}}),
           "rmse_by_feedback": {str(f): score(params=run.result.params, feedback=int(f)) for f in a["feedback"]}}
    run.say(f"ablations: k_b {out['rmse_by_kb']}, no interfaces {out['rmse_no_interfaces']:.4f}, "
            f"no enrichment {out['rmse_no_enrichment']:.4f}")
    return out


def table2(run) -> dict:
    """Table 2 redone: singular values needed for 80 / 90 / 95 % of the energy (sum of squared
    singular values) of F, L_d and M for the closed cube at each ``eval.table2_texels``."""
    out = {}
    for t in run.config["eval"]["table2_texels"]:
        c = merge(run.method_config, {"dictionary": {"texels": int(t), "enrich": False}})
        f = operators.form_factors(int(t), int(c["dictionary"]["quadrature"]))
        ops = model.block_operators(f, int(t), (), c)
        out[f"n={6 * int(t) ** 2}"] = {"F": ev.energy_counts(np.linalg.svd(f, compute_uv=False)),
                                       "L_d": ev.energy_counts(ops["sv_Ld"]), "M": ev.energy_counts(ops["sv_M"]),
                                       "paper (n=1536)": {"F": [164, 240, 313], "L_d": [22, 41, 62], "M": [1, 5, 8]}}
    return {"sv_energy_counts": out}


def baselines(run) -> dict:
    """Data-driven PRT trained on this layout's texels (per-layout setup: its training renders
    and fit, ``evaluation.datadriven_baseline``) and the ambient term (per block: c x its mean
    direct, c least squares on the same training renders), on the same held-out lightings."""
    from jprt.render.scenes import SceneHandle

    ds, e, cfg, mask = run.dataset, run.config["eval"]["datadriven"], run.method_config, _mask(run)
    t0 = time.perf_counter()
    lights = mdata.random_lights(np.random.default_rng([int(cfg["data"]["seed"]), 99]), _scene(run),
                                 int(e["n_train"]), cfg["lights"], cfg)
    d_tr, i_tr = mdata.render_texels(SceneHandle(_scene(run)), ds.positions, ds.normals, lights,
                                     spp=int(e["spp"]), seed=int(cfg["data"]["seed"]) + 5, desc="data-driven training")
    t_render = time.perf_counter() - t0
    dcfg = {"basis": {"n": int(e["basis"]), "mean": "linear"}, "transfer": {"lam": 0.01, "lam_cv": []}}
    dd, t_fit = ev.datadriven_baseline(d_tr, i_tr, ds.positions, mask, ds.direct_test, dcfg, int(e["points"]),
                                       ds.indirect_test.dtype)
    rmse_dd = _texel_rmse(run, dd)[0]
    ambient, c = ev.ambient_baseline(d_tr, i_tr, mask, ds.direct_test)
    rmse_amb = _texel_rmse(run, ambient)[0]
    rmse_zero = _texel_rmse(run, np.zeros_like(ds.indirect_test))[0]
    run.say(f"data-driven PRT on this layout: RMSE {rmse_dd:.4f} after {t_render + t_fit:.1f} s of setup; "
            f"ambient {rmse_amb:.4f}; zero {rmse_zero:.4f}")
    return {"rmse_datadriven": rmse_dd, "datadriven_setup_s": t_render + t_fit, "datadriven_render_s": t_render,
            "datadriven_fit_s": t_fit, "datadriven_config": {**e, "mean": "linear", "lam": 0.01},
            "rmse_ambient": rmse_amb, "ambient_c": c, "rmse_zero": rmse_zero,
            "mrt_setup_s": float(run.result.info["tbr_build_s"])}


def vector_and_volume(run) -> dict:
    """§6.4 and §6.5 against quadrature of the reference radiance (direct + Mitsuba indirect at
    the texels): irradiance / pi at normals tilted up to ``eval.vector.tilt_deg`` (scalar F l
    ignoring the tilt, OHLSH, quadratic SH) against each block's own surfaces
    (``evaluation.tilted_quadrature``), with b from the same reference radiance (so the
    representation alone is compared); the probes' SH from the run time's b's and r's (and from
    b's alone) against the radiance each probe sees across the layout (``evaluation.volume_reference``)."""
    ds, cfg, params, mask = run.dataset, run.method_config, run.result.params, _mask(run)
    t = int(cfg["dictionary"]["texels"])
    total = (ds.direct_test + ds.indirect_test) * mask[None, ..., None]
    b = np.einsum("bkn,lbnc->lbkc", np.asarray(params["T_db"], np.float64), total)
    tilt = float(run.config["eval"]["vector"]["tilt_deg"])
    normals = ev.tilted_normals(np.random.default_rng(5), total.shape[:3], tilt)
    # the reference clamps at the tilted normal's own hemisphere: quadrature per texel and normal
    ref = ev.tilted_quadrature(t, normals, total, 2 * int(cfg["vector"]["directions"]))
    quad = {k: jnp.asarray(params[k]) for k in ("U_quad", "U_b")}
    out = {kind: ev.texel_rmse(np.stack([np.asarray(model.vector_irradiance(
        quad, jnp.asarray(bb, jnp.float32), jnp.asarray(nn, jnp.float32), kind)) for bb, nn in zip(b, normals)]),
        ref, mask)[1] for kind in ("scalar", "ohlsh", "quadratic")}
    # irradiance volumes (§6.5): the run time's probes (b's, and b's and r's) against SH quadrature
    # of the reference radiance the probe sees across the whole layout (rays marched through open sides)
    ref_vol = ev.volume_reference(layouts.layout_from_dict(ds.layout), t, np.asarray(model.dictionary(cfg)["probes"]),
                                  total, 2 * int(cfg["volume"]["directions"]))  # (L, B, P, 9, 3)
    arrays = {k: jnp.asarray(params[k]) for k in model.RUNTIME_KEYS + ("U_vol", "U_rvol") if k in params}
    vol, vol_b = [], []
    for direct in ds.direct_test:
        bt, rt = model.coefficients(arrays, jnp.asarray(direct * mask[..., None], jnp.float32),
                                    jnp.asarray(ds.albedo, jnp.float32), feedback=int(cfg["runtime"]["feedback"]))
        # the probes see surfaces' outgoing radiance: direct plus every bounce (b of the direct
        # light plus the bounces' b); the light through the sides is r's lightfield
        vol.append(np.asarray(model.volume_probes(arrays, bt, rt)))
        vol_b.append(np.asarray(model.volume_probes(arrays, bt)))
    rel = lambda a: float(np.sqrt(np.mean((np.stack(a) - ref_vol) ** 2) / np.mean(ref_vol ** 2)))  # noqa: E731
    out_vol = {"volume_sh_relative_rmse": rel(vol), "volume_sh_relative_rmse_within_only": rel(vol_b)}
    run.say(f"vector irradiance relative RMSE: {out}; volume SH {out_vol}")
    return {"vector_irradiance_rmse": out, **out_vol}


def frame_times(run) -> dict:
    """Frame time of the run time by block count (``evaluation.frame_times``: random mazes) with
    its log-log slope, T_b->r build times, XLA's FLOP count, and the f32 matmul rate of this
    process (``jprt.eval.xla_flops``, ``jprt.eval.matmul_peak_gflops``)."""
    dic = model.dictionary(run.method_config)
    reps = int(run.config["eval"]["timing_repeats"])
    t = ev.frame_times(dic, run.method_config, run.config["eval"]["frame_blocks"], _scene(run)["albedo"], reps)
    by, flops = t["frame_ms"], t["flops"]
    slope = float(np.polyfit(np.log([int(k) for k in by]), np.log(list(by.values())), 1)[0]) if len(by) > 1 else None
    peak = jeval.matmul_peak_gflops(repeats=reps)
    run.say(f"frame ms by blocks {by} (log-log slope {slope})")
    return {"frame_ms_by_blocks": by, "frame_ms_slope": slope, "tbr_build_s_by_blocks": t["tbr_build_s"],
            "tbr_build_s": max(t["tbr_build_s"].values()), "flops_by_blocks": flops, "matmul_f32_gflops": peak,
            "flops_fraction_of_peak": {k: flops[k] / (by[k] * 1e-3) / 1e9 / peak for k in by if flops[k]},
            "precompute_s": float(dic["info_precompute_s"]), "model_bytes_per_block_type": ev.bytes_per_type(dic)}


STAGES = [held_out_layouts, projection_floor, ablations, table2, baselines, vector_and_volume, frame_times]
