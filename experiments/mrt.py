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
``benchmarks/mrt.py`` turns the report into benchmarks/results/mrt.json.
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
from jprt.methods.mrt import model, operators
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


# --------------------------------------------------------------------------------------------
# helpers


def _scene(run) -> dict:
    from jprt.render.scenes import describe

    return describe(run.config["scene"])


def _mask(run) -> np.ndarray:
    return np.asarray(run.result.params["mask"], bool)


def _rmse(pred, ref, mask) -> tuple[float, float]:
    """RMSE and relative RMSE over the existing texels of (N, B, n, 3) arrays."""
    m = np.broadcast_to(mask[None, ..., None], np.shape(ref))
    err = np.asarray(pred, np.float64)[m] - np.asarray(ref, np.float64)[m]
    rmse = float(np.sqrt(np.mean(err ** 2)))
    return rmse, rmse / max(float(np.sqrt(np.mean(np.asarray(ref, np.float64)[m] ** 2))), 1e-30)


def _atlas_images(texels, albedo_shape) -> list:
    """(N, B, n, 3) texel arrays -> padded-atlas images (R, R, 3) (gutters 0)."""
    b, t = model.texels_of(np.zeros(albedo_shape))
    res, texel_index, _ = model.atlas_layout(b, t)
    out = []
    for x in np.asarray(texels, np.float32):
        img = np.zeros((res * res, 3), np.float32)
        img[texel_index] = x.reshape(-1, 3)
        out.append(img.reshape(res, res, 3))
    return out


def _predict(params, direct, albedo, cfg, **kw) -> np.ndarray:
    arrays = {k: jnp.asarray(params[k]) for k in model.RUNTIME_KEYS if k in params}
    opts = {"feedback": int(cfg["runtime"]["feedback"]), "interfaces": bool(cfg["interfaces"]["enabled"])} | kw
    return np.asarray(model.lightmap(arrays, jnp.asarray(direct, jnp.float32), jnp.asarray(albedo, jnp.float32),
                                     **opts))


def _fit_layout(run, layout: dict, overrides: dict | None = None) -> tuple[dict, dict]:
    cfg = run.with_config(overrides or {})
    dic = model.dictionary(cfg)
    return model.layout_operators(dic, layout, cfg), cfg


# --------------------------------------------------------------------------------------------
# The runner's hooks


def held_out(run) -> HeldOut:
    """The held-out lightings of the layout: the evaluator on the padded atlas (every texel)
    against Mitsuba's indirect at the same texels."""
    ds = run.dataset
    inputs = model.atlas_gbuffer_inputs(ds.albedo)
    ev = jax.jit(run.evaluate)
    from jprt.inputs import PointRadiance

    preds = [np.asarray(ev(inputs, PointRadiance(d.reshape(-1, 3).astype(np.float32)))) for d in ds.direct_test]
    refs = _atlas_images(ds.indirect_test, ds.albedo.shape)
    direct = _atlas_images(ds.direct_test, ds.albedo.shape)
    valid = [np.asarray(inputs.valid, bool)] * len(preds)
    return HeldOut(preds, refs, valid, direct, [f"lighting {k}" for k in range(len(preds))])


def pathtracer(run) -> PathTracer:
    """Mitsuba rendering the same texels (full minus direct at the texel centres, ``spp`` paths
    each, a seed unlike the references'); timed on the first held-out lighting."""
    from jprt.inputs import PointLights
    from jprt.render import lightmap
    from jprt.render.scenes import SceneHandle

    ds = run.dataset
    handle = SceneHandle(run.config["scene"])
    lights = [PointLights.create(p, i) for p, i in zip(ds.lights_test["position"], ds.lights_test["intensity"])]
    p, nrm = ds.positions.reshape(-1, 3), ds.normals.reshape(-1, 3)

    def render_at(spp):
        out = []
        for k, l in enumerate(lights):
            handle.set_lighting(l)
            out.append(lightmap.indirect_at_points(handle, p, nrm, spp=int(spp), seed=777 + k).reshape(ds.positions.shape))
        return _atlas_images(np.stack(out), ds.albedo.shape)

    def time_at(spp):
        handle.set_lighting(lights[0])
        t0 = time.perf_counter()
        lightmap.indirect_at_points(handle, p, nrm, spp=int(spp), seed=999)
        return (time.perf_counter() - t0) * 1e3

    return PathTracer(render_at, time_at, "Mitsuba path (LLVM, this CPU): indirect at every texel centre = full "
                                          "minus direct (two renders, equal seeds); MRT's time is the lightmap at "
                                          "the same texels with Mitsuba's direct given")


# --------------------------------------------------------------------------------------------
# Stages


def held_out_layouts(run) -> dict:
    """RMSE on the main layout's texels and on the held-out layouts of ``eval.layouts``."""
    ds = run.dataset
    cfg = run.method_config
    pred = _predict(run.result.params, ds.direct_test, ds.albedo, cfg)
    rmse, rel = _rmse(pred, ds.indirect_test, _mask(run))
    out = {"rmse": rmse, "relative_rmse": rel, "blocks": len(layouts.layout_from_dict(ds.layout).cells),
           "layout": ds.layout, "by_layout": {}}
    run.state["pred"] = pred
    e = run.config["eval"]
    for spec in e["layouts"]:
        lay = layouts.random_maze(int(spec["blocks"]), seed=int(spec["seed"]), extra_edges=int(spec["cycles"]))
        scene = merge(run.config["scene"], {"layout": lay.as_dict()})
        cfg2 = run.with_config({"scene": scene, "data": {"n_test": int(e["layout_lightings"])}})
        ds2 = mdata.make_dataset(scene, cfg2)
        ops2, _ = _fit_layout(run, lay.as_dict())
        p2 = _predict(ops2, ds2.direct_test, ds2.albedo, cfg)
        r2, rel2 = _rmse(p2, ds2.indirect_test, np.asarray(ops2["mask"], bool))
        out["by_layout"][str(spec["blocks"])] = {"rmse": r2, "relative_rmse": rel2, "cycles": lay.has_cycle(),
                                                 "lightings": int(e["layout_lightings"]),
                                                 "tbr_build_s": float(ops2["tbr_build_s"])}
        run.state.setdefault("layouts", {})[str(spec["blocks"])] = (ops2, ds2)
        run.say(f"held-out layout of {spec['blocks']} blocks: relative RMSE {rel2:.3f}")
    run.say(f"layout of {out['blocks']} blocks: RMSE {rmse:.4f}, relative {rel:.3f}")
    return {"texel_rmse": out}


def projection_floor(run) -> dict:
    """The projection floor: the reference projected on each block's own bases (``model.projection``)."""
    ds = run.dataset
    proj = np.stack([model.projection(run.result.params, r) for r in ds.indirect_test])
    proj_within = np.stack([model.projection(run.result.params, r, use_interfaces=False) for r in ds.indirect_test])
    rmse, rel = _rmse(proj, ds.indirect_test, _mask(run))
    rmse_w, rel_w = _rmse(proj_within, ds.indirect_test, _mask(run))
    return {"projection_rmse": rmse, "projection_relative_rmse": rel, "projection_rmse_within_only": rmse_w,
            "projection_relative_rmse_within_only": rel_w}


def ablations(run) -> dict:
    """RMSE by k_b, k_rlf, k_r (each a dictionary of its own), without interfaces, without
    enrichment, and by feedback bounces."""
    ds = run.dataset
    cfg = run.method_config
    a = run.config["eval"]["ablations"]
    mask = _mask(run)
    out = {}

    def score(overrides, **kw):
        ops, c = _fit_layout(run, ds.layout, overrides)
        return _rmse(_predict(ops, ds.direct_test, ds.albedo, c, **kw), ds.indirect_test, mask)[0]

    out["rmse_by_kb"] = {str(k): score({"dictionary": {"k_b": int(k)}}) for k in a["k_b"]}
    out["rmse_by_krlf"] = {str(k): score({"interfaces": {"k_rlf": int(k)}}) for k in a["k_rlf"]}
    out["rmse_by_kr"] = {str(k): score({"interfaces": {"k_r": int(k)}}) for k in a["k_r"]}
    out["rmse_no_interfaces"] = _rmse(_predict(run.result.params, ds.direct_test, ds.albedo, cfg, interfaces=False),
                                      ds.indirect_test, mask)[0]
    # App. A for both priors (the block prior and H_rlf), then each alone
    out["rmse_no_enrichment"] = score({"dictionary": {"enrich": False}, "interfaces": {"enrich_iterations": 0}})
    out["rmse_no_block_enrichment"] = score({"dictionary": {"enrich": False}})
    out["rmse_no_interface_enrichment"] = score({"interfaces": {"enrich_iterations": 0}})
    out["rmse_by_feedback"] = {str(f): _rmse(_predict(run.result.params, ds.direct_test, ds.albedo, cfg,
                                                      feedback=int(f)), ds.indirect_test, mask)[0]
                               for f in a["feedback"]}
    run.say(f"ablations: k_b {out['rmse_by_kb']}, no interfaces {out['rmse_no_interfaces']:.4f}, "
            f"no enrichment {out['rmse_no_enrichment']:.4f}")
    return out


def _energy_counts(sv: np.ndarray, levels=(0.8, 0.9, 0.95)) -> dict:
    e = np.cumsum(np.asarray(sv, np.float64) ** 2)
    e = e / e[-1]
    return {f"{int(round(100 * q))}%": int(np.searchsorted(e, q) + 1) for q in levels}


def table2(run) -> dict:
    """Table 2 redone: singular values needed for 80 / 90 / 95 % of the energy (sum of squared
    singular values) of F, L_d and M for the closed cube at each ``eval.table2_texels``."""
    cfg = run.method_config
    out = {}
    for t in run.config["eval"]["table2_texels"]:
        c = merge(cfg, {"dictionary": {"texels": int(t), "enrich": False}})
        f = operators.form_factors(int(t), int(c["dictionary"]["quadrature"]))
        ops = model.block_operators(f, int(t), (), c)
        sv_f = np.linalg.svd(f, compute_uv=False)
        out[f"n={6 * int(t) ** 2}"] = {"F": _energy_counts(sv_f), "L_d": _energy_counts(ops["sv_Ld"]),
                                       "M": _energy_counts(ops["sv_M"]),
                                       "paper (n=1536)": {"F": [164, 240, 313], "L_d": [22, 41, 62], "M": [1, 5, 8]}}
    return {"sv_energy_counts": out}


def baselines(run) -> dict:
    """Data-driven PRT trained on this layout's texels (per-layout setup: its training renders
    and fit) and the ambient term (per block: c x its mean direct, c least squares on the same
    training renders), on the same held-out lightings."""
    from jprt.methods.datadriven import model as ddm
    from jprt.render.scenes import SceneHandle

    ds = run.dataset
    e = run.config["eval"]["datadriven"]
    cfg = run.method_config
    mask = _mask(run)
    t0 = time.perf_counter()
    lights = mdata.random_lights(np.random.default_rng([int(cfg["data"]["seed"]), 99]), _scene(run),
                                 int(e["n_train"]), cfg["lights"], cfg)
    d_tr, i_tr = mdata.render_texels(SceneHandle(_scene(run)), ds.positions, ds.normals, lights,
                                     spp=int(e["spp"]), seed=int(cfg["data"]["seed"]) + 5, desc="data-driven training")
    t_render = time.perf_counter() - t0
    flat = mask.reshape(-1)
    t1 = time.perf_counter()
    pts = ddm.select_points(ds.positions.reshape(-1, 3)[flat], min(int(e["points"]), int(flat.sum())))
    fine = np.flatnonzero(flat)[pts.fine_index]
    dcfg = {"basis": {"n": int(e["basis"]), "mean": "linear"}, "transfer": {"lam": 0.01, "lam_cv": []}}
    fitted = ddm.fit_arrays(d_tr.reshape(len(lights), -1, 3)[:, fine], i_tr.reshape(len(lights), -1, 3)[:, flat],
                            pts.group, dcfg)
    t_fit = time.perf_counter() - t1
    dd = np.zeros_like(ds.indirect_test).reshape(len(ds.direct_test), -1, 3)
    dd[:, flat] = np.asarray(ddm.lightmap(fitted.params, ds.direct_test.reshape(len(ds.direct_test), -1, 3)[:, fine],
                                          dcfg))
    rmse_dd = _rmse(dd.reshape(ds.indirect_test.shape), ds.indirect_test, mask)[0]
    # ambient: c x (mean direct over the block's texels)
    md_tr = np.stack([np.broadcast_to(np.sum(d * mask[..., None], 1, keepdims=True) / mask.sum(1)[:, None, None],
                                      d.shape) for d in d_tr])
    m = np.broadcast_to(mask[None, ..., None], md_tr.shape)
    c = float(np.sum(md_tr[m] * i_tr[m]) / max(np.sum(md_tr[m] ** 2), 1e-30))
    md = np.stack([np.broadcast_to(np.sum(d * mask[..., None], 1, keepdims=True) / mask.sum(1)[:, None, None], d.shape)
                   for d in ds.direct_test])
    rmse_amb = _rmse(c * md, ds.indirect_test, mask)[0]
    rmse_zero = _rmse(np.zeros_like(ds.indirect_test), ds.indirect_test, mask)[0]
    run.say(f"data-driven PRT on this layout: RMSE {rmse_dd:.4f} after {t_render + t_fit:.1f} s of setup; "
            f"ambient {rmse_amb:.4f}; zero {rmse_zero:.4f}")
    return {"rmse_datadriven": rmse_dd, "datadriven_setup_s": t_render + t_fit, "datadriven_render_s": t_render,
            "datadriven_fit_s": t_fit, "datadriven_config": {**e, "mean": "linear", "lam": 0.01},
            "rmse_ambient": rmse_amb, "ambient_c": c, "rmse_zero": rmse_zero,
            "mrt_setup_s": float(run.result.info["tbr_build_s"])}


def _tilted_normals(rng, shape, max_deg: float) -> np.ndarray:
    theta = np.radians(max_deg) * np.sqrt(rng.random(shape))
    phi = 2 * np.pi * rng.random(shape)
    return np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], -1)


def vector_and_volume(run) -> dict:
    """§6.4 and §6.5 against quadrature of the reference radiance (direct + Mitsuba indirect at
    the texels): irradiance / pi at normals tilted up to ``eval.vector.tilt_deg`` (scalar F l
    ignoring the tilt, OHLSH, quadratic SH) against each block's own surfaces, with b from the
    same reference radiance (so the representation alone is compared); the probes' SH from the
    run time's b's and r's (and from b's alone) against the radiance each probe sees across the
    layout."""
    ds = run.dataset
    cfg = run.method_config
    t = int(cfg["dictionary"]["texels"])
    params = run.result.params
    mask = _mask(run)
    total = (ds.direct_test + ds.indirect_test) * mask[None, ..., None]
    b = np.einsum("bkn,lbnc->lbkc", np.asarray(params["T_db"], np.float64), total)
    rng = np.random.default_rng(5)
    normals = _tilted_normals(rng, total.shape[:3], float(run.config["eval"]["vector"]["tilt_deg"]))
    # the reference clamps at the tilted normal's own hemisphere: quadrature per texel and normal
    ref = _tilted_quadrature(t, normals, total, 2 * int(cfg["vector"]["directions"]))
    out = {}
    for kind in ("scalar", "ohlsh", "quadratic"):
        pred = np.stack([np.asarray(model.vector_irradiance({k: jnp.asarray(params[k]) for k in ("U_quad", "U_b")},
                                                            jnp.asarray(bb, jnp.float32),
                                                            jnp.asarray(nn, jnp.float32), kind))
                         for bb, nn in zip(b, normals)])
        out[kind] = _rmse(pred, ref, mask)[1]
    # irradiance volumes (§6.5): the run time's probes (b's, and b's and r's) against SH quadrature
    # of the reference radiance the probe sees across the whole layout (rays marched through open sides)
    dic = model.dictionary(cfg)
    lay = layouts.layout_from_dict(ds.layout)
    probes = np.asarray(dic["probes"])
    k = 2 * int(cfg["volume"]["directions"])
    d, w = operators.sphere_directions(k, hemisphere=False)
    y = operators.sh9(d) * w[:, None]
    ref_vol = []
    for bi, blk in enumerate(lay.blocks):
        origin = np.array([blk.cell[0], 0.0, blk.cell[1]]) + probes  # (P, 3)
        o = np.repeat(origin, len(d), 0)
        dd = np.tile(d, (len(origin), 1))
        rad = _march(lay, t, o, dd, total)  # (L, P * D, 3)
        ref_vol.append(np.einsum("dq,lpdc->lpqc", y, rad.reshape(len(total), len(origin), len(d), 3)))
    ref_vol = np.stack(ref_vol, 1)  # (L, B, P, 9, 3)
    arrays = {k2: jnp.asarray(params[k2]) for k2 in model.RUNTIME_KEYS + ("U_vol", "U_rvol") if k2 in params}
    fb = int(cfg["runtime"]["feedback"])
    vol, vol_b = [], []
    for direct in ds.direct_test:
        bt, rt = model.coefficients(arrays, jnp.asarray(direct * mask[..., None], jnp.float32),
                                    jnp.asarray(ds.albedo, jnp.float32), feedback=fb)
        # the probes see surfaces' outgoing radiance: direct plus every bounce (b of the direct
        # light plus the bounces' b); the light through the sides is r's lightfield
        vol.append(np.asarray(model.volume_probes(arrays, bt, rt)))
        vol_b.append(np.asarray(model.volume_probes(arrays, bt)))
    rel = lambda a: float(np.sqrt(np.mean((np.stack(a) - ref_vol) ** 2) / np.mean(ref_vol ** 2)))  # noqa: E731
    out_vol = {"volume_sh_relative_rmse": rel(vol), "volume_sh_relative_rmse_within_only": rel(vol_b)}
    run.say(f"vector irradiance relative RMSE: {out}; volume SH {out_vol}")
    return {"vector_irradiance_rmse": out, **out_vol}


def _march(lay: layouts.Layout, t: int, origins: np.ndarray, dirs: np.ndarray, radiance: np.ndarray) -> np.ndarray:
    """Radiance (L, R, 3) of the texel each ray meets first, marching from cell to cell through
    open sides (a blocks layout of unit cells); rays that leave through an exterior side see 0.
    ``radiance`` (L, B, n, 3) per lighting."""
    index = {c: k for k, c in enumerate(lay.cells)}
    blocks = lay.blocks
    o = origins.copy()
    cell = np.floor(o[:, [0, 2]] + 1e-9 * dirs[:, [0, 2]]).astype(int)
    out = np.zeros((radiance.shape[0], len(o), 3))
    active = np.ones(len(o), bool)
    for _ in range(len(lay.cells) + 1):
        if not active.any():
            break
        ids = np.flatnonzero(active)
        b = np.array([index.get((int(i), int(j)), -1) for i, j in cell[ids]])
        gone = b < 0
        active[ids[gone]] = False
        ids, b = ids[~gone], b[~gone]
        off = np.stack([cell[ids, 0], np.zeros(len(ids)), cell[ids, 1]], -1)
        face, hit = layouts.exit_face(o[ids] - off, dirs[ids])
        side = face - 2
        is_open = np.array([s >= 0 and s in blocks[bb].open_sides for s, bb in zip(side, b)], bool)
        stop = ~is_open
        tex = layouts.locate(hit[stop], t, layouts.FACE_NORMALS[face[stop]])
        out[:, ids[stop]] = radiance[:, b[stop], tex]
        active[ids[stop]] = False
        go = ids[is_open]
        o[go] = hit[is_open] + off[is_open]
        step = np.array([layouts.SIDE_STEPS[s] for s in side[is_open]]).reshape(-1, 2)
        cell[go] = cell[go] + step
    return out


def _tilted_quadrature(t: int, normals: np.ndarray, radiance: np.ndarray, k: int) -> np.ndarray:
    """Irradiance / pi at each texel for its tilted local normal: quadrature of the block's own
    surface radiance over the directions above both the surface and the tilted normal."""
    pos, normal, face = layouts.texel_centres(t)
    d_loc, w = operators.sphere_directions(k, hemisphere=True)
    out = np.zeros(normals.shape[:3] + (3,))
    for i in range(len(pos)):
        frame = np.stack([layouts.FACE_U[face[i]], layouts.FACE_V[face[i]], normal[i]])
        f, hit = layouts.exit_face(np.repeat(pos[i:i + 1], len(d_loc), 0) + 1e-9 * normal[i], d_loc @ frame)
        tex = layouts.locate(hit, t, layouts.FACE_NORMALS[f])
        cosn = np.maximum(np.einsum("lbk,dk->lbd", normals[:, :, i], d_loc), 0.0) * w / np.pi  # (L, B, D)
        out[:, :, i] = np.einsum("lbd,lbdc->lbc", cosn, radiance[:, :, tex])
    return out


def frame_times(run) -> dict:
    """Frame time of the run time (§7.3 steps 1-5, ``runtime.feedback`` bounces in the reduced
    spaces with the level's ``feedback_operators``, texels out) by
    block count, T_b->r build times, XLA's FLOP count, and the f32 matmul rate of this process
    (``jprt.eval.xla_flops``, ``jprt.eval.matmul_peak_gflops``)."""
    cfg = run.method_config
    dic = model.dictionary(cfg)
    reps = int(run.config["eval"]["timing_repeats"])
    rng = np.random.default_rng(0)
    by, tbr, flops = {}, {}, {}
    for nb in run.config["eval"]["frame_blocks"]:
        nb = int(nb)  # random mazes with a cycle per ten blocks
        lay = layouts.random_maze(nb, seed=nb, extra_edges=max(0, nb // 10)) if nb > 1 else layouts.corridor(1)
        ops = model.layout_operators(dic, lay.as_dict(), cfg)
        t = int(cfg["dictionary"]["texels"])
        alb = layouts.texel_albedo(lay, t, _scene(run)["albedo"])
        ops.update(model.level_feedback(ops, alb))
        arrays = jax.device_put({k: jnp.asarray(ops[k]) for k in model.RUNTIME_KEYS})
        albedo = jax.device_put(jnp.asarray(alb, jnp.float32))
        direct = jax.device_put(jnp.asarray(rng.random((nb, layouts.texel_count(t), 3)), jnp.float32))
        fb = int(cfg["runtime"]["feedback"])
        fn = jax.jit(lambda a, d, al: model.lightmap(a, d, al, feedback=fb))
        by[str(nb)] = jeval.time_call(fn, arrays, direct, albedo, repeats=reps)["median_ms"]
        tbr[str(nb)] = float(ops["tbr_build_s"])
        flops[str(nb)] = jeval.xla_flops(fn, arrays, direct, albedo)
    xs = np.log([int(k) for k in by])
    ys = np.log([by[k] for k in by])
    slope = float(np.polyfit(xs, ys, 1)[0]) if len(by) > 1 else None
    peak = jeval.matmul_peak_gflops(repeats=reps)
    run.say(f"frame ms by blocks {by} (log-log slope {slope})")
    return {"frame_ms_by_blocks": by, "frame_ms_slope": slope, "tbr_build_s_by_blocks": tbr,
            "tbr_build_s": max(tbr.values()), "flops_by_blocks": flops, "matmul_f32_gflops": peak,
            "flops_fraction_of_peak": {k: flops[k] / (by[k] * 1e-3) / 1e9 / peak for k in by if flops[k]},
            "precompute_s": float(dic["info_precompute_s"]),
            "model_bytes_per_block_type": _bytes_per_type(dic)}


def _bytes_per_type(dic: dict) -> dict:
    """Run-time bytes of one dictionary type (float32 T_d->b, U_b, U_quad, U_vol) and of the
    shared interface operators (U_r, R_b for every type)."""
    per = {name: int(sum(np.asarray(dic[k][i], np.float32).nbytes for k in ("T_db", "U_b")))
           for i, name in enumerate(model.TYPES)}
    per["_vector_and_volume_per_type"] = int(np.asarray(dic["U_quad"][0], np.float32).nbytes
                                             + np.asarray(dic["U_vol"][0], np.float32).nbytes)
    if "U_r" in dic:
        per["_interfaces_shared"] = int(np.asarray(dic["U_r"], np.float32).nbytes)
    return per


STAGES = [held_out_layouts, projection_floor, ablations, table2, baselines, vector_and_volume, frame_times]
