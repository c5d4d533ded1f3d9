"""Neural-wavelet PRT (Raghavan et al. 2023) on a glossy Cornell box relit by environment maps.

    jprt run experiments/wavelet_prt_cornell.py                   # `small`: trains in ~15 min on 2 CPU cores
    jprt run experiments/wavelet_prt_cornell.py --preset paper    # the paper's sizes (needs an accelerator)
    jprt run experiments/wavelet_prt_cornell.py --preset test     # smoke test (procedural maps)

Pipeline (the scene is the glossy Cornell box with its top open, lit by ../shared/assets
environment maps and their 120 / 240 degree rotations; two maps are held out):
  1. ground-truth transport check: Mitsuba's environment-to-pixel indirect transport of one view,
     projected onto the Haar basis, relit with the top K = 32, 64, 128, 300 wavelets vs Mitsuba's
     render of the same environment (and two Mitsuba renders against each other: the noise floor);
  2. training images on spherical + helix trajectories, G-buffers, importance maps (§5);
  3. Adam training of the CP feature field + MLP (resumable; checkpoint under $JPRT_CACHE);
  4. held-out maps on views near and far from the training trajectories: PSNR / SSIM of indirect
     and direct + indirect (Table 1 layout), against the baseline indirect = c * direct with the
     best RGB c from the training data; the K sweep;
  5. frame time by resolution and K (Table 2 layout), model size; equal-error spp of Mitsuba and
     the speedup at equal error;
  6. ablations (shorter runs, all at the same step count): hash-table size (Table 3) and the
     reflection encoding (Table 4);
  7. images (reference / ours / baseline / error), loss curve, error-vs-K plot.
The report goes to results/wavelet_prt_cornell/<config hash>/.
"""

from __future__ import annotations

import os
import sys
import time

import jax
import numpy as np

from jprt import eval as jeval
from jprt import io, metrics
from jprt.config import config_hash, merge, save_resolved
from jprt.methods import wavelet_prt as wp

EVAL_DEFAULTS = {
    "ks": [32, 64, 128],
    "gt_check": {"width": 16, "height": 16, "spp": 16384, "max_depth": 8, "ks": [32, 64, 128, 300]},
    "timing_resolutions": [[128, 128], [256, 256], [512, 512]],
    "timing_repeats": 3,
    "equal_error_spp": [1, 2, 4, 8, 16, 32, 64, 128, 256, 512],
    "ablation_steps": 250,
    # model.<key> values; "spatial": named model overrides (the multiresolution hash grid against one
    # single-resolution grid, the paper's "learned neural texture" alternative of §4, and against
    # per-vertex features on the subdivided scene mesh, Table 6)
    "ablations": {"log2_table_size": [10, 12, 14], "reflection": ["sh4", "raw", "none"],
                  "spatial": {"multiresolution": {},
                              "single_resolution": {"n_levels": 1, "features_per_level": 16,
                                                    "base_resolution": 32},
                              "per_vertex": {"spatial": "vertex", "vertex_edge": 0.1}}},
    "exposure": 0.0,
}

CONFIG = {**wp.DEFAULT_CONFIG, "eval": EVAL_DEFAULTS, "output": {"dir": "results/wavelet_prt_cornell"}}

PRESETS = {
    "small": {},
    # the paper's sizes (§5): 64^2 cube faces, M = L = 64, 32-level hash grid with 2^19 entries,
    # 2048 pixels per step, 512^2 images; 1000 maps x 3 rotations and ~2000 views in the paper
    "paper": {
        "envmaps": {"face_size": 64},
        "cameras": {"width": 512, "height": 512, "sphere": {"n": 600}, "helix": {"n": 300}, "near": 16, "far": 16},
        "data": {"spp": 1024, "test_spp": 4096},
        "model": {"n_levels": 32, "features_per_level": 2, "log2_table_size": 19, "base_resolution": 16,
                  "per_level_scale": 1.3, "n_features": 64},
        "train": {"steps": 100000, "pixels": 2048, "learning_rate": 1e-2, "checkpoint_every": 2000},
        "eval": {"timing_resolutions": [[512, 512], [800, 600]], "ablation_steps": 20000,
                 "ablations": {"log2_table_size": [17, 18, 19, 20]}},
    },
    "test": {
        "envmaps": {"synthetic": 3, "face_size": 4, "rotations_deg": [0.0]},
        "cameras": {"width": 12, "height": 12, "sphere": {"n": 3}, "helix": {"n": 3}, "near": 2, "far": 2},
        "data": {"spp": 8, "test_spp": 32, "envs_per_view": 1},
        "model": {"n_levels": 3, "log2_table_size": 8, "n_features": 8, "hidden": 16},
        "train": {"steps": 30, "pixels": 32, "wavelets": 24, "checkpoint_every": 10, "log_every": 10},
        "render": {"k": 16, "chunk": 64},
        "eval": {"ks": [8, 16], "gt_check": {"width": 6, "height": 6, "spp": 64, "max_depth": 4, "ks": [8, 32]},
                 "timing_resolutions": [[16, 16]], "timing_repeats": 1, "equal_error_spp": [1, 4],
                 "ablation_steps": 10, "ablations": {"log2_table_size": [6], "reflection": ["none"],
                                                     "spatial": {"single_resolution": {"base_resolution": 4},
                                                                 "per_vertex": {"vertex_edge": 0.5}}}},
    },
}


def _say(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def _views(t: dict) -> list[dict]:
    names = [k for k in list(wp.GBUFFER_FIELDS) + list(wp.VERTEX_FIELDS) if k in t]
    return [{k: t[k][i] for k in names} for i in range(len(t["valid"]))]


def _camera(config: dict, origin, width: int, height: int):
    """A camera at ``origin`` looking at the configured target, with the configured fov."""
    from jprt.render.cameras import look_at

    return look_at(origin, tuple(config["cameras"]["target"]), fov=float(config["cameras"]["fov"]), width=int(width),
                   height=int(height))


def _predict(ev, data: wp.WaveletData, split: str) -> list[np.ndarray]:
    t = data.tests[split]
    return [np.asarray(ev(g, data.test_envs[int(t["env"][i])])) for i, g in enumerate(_views(t))]


def _scores(preds, t: dict, exposure: float) -> dict:
    """Table 1 metrics over a split's views: tonemapped (sRGB, clipped, peak 1) PSNR / SSIM of
    indirect and direct + indirect, HDR RMSE of indirect."""
    out = {"psnr_indirect": [], "psnr_full": [], "ssim_indirect": [], "ssim_full": [], "rmse_indirect": []}
    for i, p in enumerate(preds):
        ref, direct, valid = t["indirect"][i], t["direct"][i], t["valid"][i]
        out["psnr_indirect"].append(float(metrics.tonemapped(metrics.psnr, p, ref, exposure)))
        out["psnr_full"].append(float(metrics.tonemapped(metrics.psnr, direct + p, direct + ref, exposure)))
        out["ssim_indirect"].append(float(metrics.tonemapped(metrics.ssim, p, ref, exposure)))
        out["ssim_full"].append(float(metrics.tonemapped(metrics.ssim, direct + p, direct + ref, exposure)))
        out["rmse_indirect"].append(float(metrics.rmse(p, ref, valid)))
    return {k: float(np.mean(v)) for k, v in out.items()}


def gt_transport_check(config: dict, data: wp.WaveletData, out: str) -> dict:
    """Step 1: Mitsuba transport of a small far view -> Haar -> top-K relighting vs Mitsuba."""
    from jprt.render.cameras import camera_rays
    from jprt.render.images import indirect_rays
    from jprt.render.lights import EnvMap
    from jprt.render.scenes import SceneHandle
    from jprt.render.transport import environment_transport

    gc = config["eval"]["gt_check"]
    n = int(config["envmaps"]["face_size"])
    cube = data.test_envs[0]
    origin = data.cameras["far"][0] if len(data.cameras["far"]) else data.cameras["train"][0]
    cam = _camera(config, origin, gc["width"], gc["height"])
    handle = SceneHandle(config["scene"], EnvMap.create(wp.render_equirect(cube)))
    o, d = camera_rays(cam)
    t0 = time.perf_counter()
    transport = environment_transport(handle, o, d, face_size=n, spp=int(gc["spp"]), seed=11,
                                      max_depth=int(gc["max_depth"]))
    t_transport = time.perf_counter() - t0
    depth = int(gc["max_depth"])

    def mitsuba(seed):
        return indirect_rays(handle, o, d, spp=int(gc["spp"]), seed=seed, max_depth=depth).indirect

    ref, ref2 = mitsuba(21), mitsuba(22)
    ks = [min(int(k), 6 * n * n) for k in gc["ks"]]
    res = wp.transport_check(transport, cube, ks)
    rel = lambda a, b: float(np.linalg.norm(a - b) / max(np.linalg.norm(b), 1e-30))  # noqa: E731
    summary = {
        "gt_transport_rel_err_by_k": {str(k): rel(res["by_k"][k], ref) for k in ks},
        "gt_transport_rel_err_all": rel(res["wavelet_all"], ref),
        "gt_transport_truncation_by_k": {str(k): rel(res["by_k"][k], res["full"]) for k in ks},
        "gt_transport_parseval_err": rel(res["wavelet_all"], res["full"]),
        "gt_transport_noise_floor": rel(ref2, ref),
        "gt_transport_mean_ratio": float(res["full"].mean() / max(ref.mean(), 1e-30)),
        "gt_transport_s": t_transport,
        "gt_transport_setup": {"pixels": [int(gc["width"]), int(gc["height"])], "spp": int(gc["spp"]),
                               "max_depth": depth, "face_size": n, "environment": data.test_env_names[0]},
    }
    jeval.plot_series(os.path.join(out, "gt_transport_error_vs_k.png"),
                      {"top-K wavelets vs Mitsuba": (ks, [summary["gt_transport_rel_err_by_k"][str(k)] for k in ks]),
                       "top-K vs all wavelets (truncation)": (ks, [summary["gt_transport_truncation_by_k"][str(k)]
                                                                 for k in ks])},
                      xlabel="K (wavelets)", ylabel="relative L2 error", title="ground-truth transport check",
                      logx=True, logy=True, hlines={"Mitsuba vs Mitsuba (noise)": summary["gt_transport_noise_floor"]})
    h, w = int(gc["height"]), int(gc["width"])
    io.write_exr(os.path.join(out, "gt_transport_mitsuba.exr"), ref.reshape(h, w, 3))
    io.write_exr(os.path.join(out, "gt_transport_wavelets_all.exr"), res["wavelet_all"].reshape(h, w, 3))
    _say("transport check: rel. error vs Mitsuba " + ", ".join(
        f"K={k}: {v:.3f}" for k, v in summary["gt_transport_rel_err_by_k"].items())
        + f"; all wavelets {summary['gt_transport_rel_err_all']:.3f}; noise floor "
        f"{summary['gt_transport_noise_floor']:.3f}")
    return summary


def _logged_train_s(log_path: str) -> float | None:
    """Training wall time from a run's metrics.jsonl: the sum over its segments (a resumed run
    restarts elapsed_s) of each segment's last elapsed_s."""
    import json

    if not os.path.isfile(log_path):
        return None
    total, last = 0.0, 0.0
    with open(log_path) as f:
        for line in f:
            t = float(json.loads(line)["elapsed_s"])
            if t < last:
                total += last
            last = t
    return total + last


def _train(config: dict, data, label: str, progress: bool = True) -> dict:
    from jprt.render.dataset import cache_root

    folder = os.path.join(cache_root(), "wavelet_prt", "runs", wp.run_key(config))
    os.makedirs(folder, exist_ok=True)
    _say(f"{label}: checkpoint {folder}")
    log_path = os.path.join(folder, "metrics.jsonl")
    run = wp.fit(data, config, checkpoint_path=os.path.join(folder, "ckpt.npz"), log_path=log_path, progress=progress)
    return dict(run, log_path=log_path)


def main(config: dict) -> dict:
    """Run the experiment; returns the summary (also written as summary.json)."""
    config = merge(CONFIG, config)
    e = config["eval"]
    out = os.path.join(config["output"]["dir"], config_hash(config))
    os.makedirs(out, exist_ok=True)
    save_resolved(config, out)
    t_start = time.perf_counter()
    summary: dict = {"config_hash": config_hash(config)}

    data = wp.make_dataset(None, config)
    summary.update(n_train_images=int(np.prod(data.train["valid"].shape[:2])), n_train_envs=len(data.env_names),
                   held_out_envs=data.test_env_names, render_s=data.stats["render_s"],
                   image_size=list(data.train["valid"].shape[2:]))
    summary.update(gt_transport_check(config, data, out))

    run = _train(config, data, "training")
    params = run["params"]
    summary["train_s"], summary["train_s_source"] = run["train_s"], "this run"
    if run["resumed_from"]:
        summary["train_s"], summary["train_s_source"] = _logged_train_s(run["log_path"]), "metrics.jsonl (resumed run)"
    summary["train_resumed_from"] = run["resumed_from"]
    summary["model_bytes"] = wp.model_bytes(params)
    losses = np.asarray(run["losses"])
    if len(losses):
        steps_run = np.arange(len(losses)) + 1 + run["resumed_from"]
        jeval.plot_series(os.path.join(out, "loss.png"), {"mu-law L2": (steps_run, losses)},
                          xlabel="step", ylabel="loss", title="training loss", logy=True)

    # Table 1: near / far views on held-out maps, and the c * direct baseline
    c = wp.indirect_baseline_scale(data.train["direct"], data.train["indirect"], data.train["valid"])
    summary["baseline_scale"] = c.tolist()
    preds = {}
    ev_default = wp.evaluator(params, config)
    for split in ("near", "far"):
        if not data.tests[split]:
            continue
        ev = ev_default
        preds[split] = _predict(ev, data, split)
        s = _scores(preds[split], data.tests[split], e["exposure"])
        base = _scores([c[None, None, :] * d for d in data.tests[split]["direct"]], data.tests[split], e["exposure"])
        for k, v in s.items():
            summary[f"{k}_{split}"] = v
            summary[f"{k}_{split}_baseline"] = base[k]
        _say(f"{split} views: PSNR indirect {s['psnr_indirect']:.2f} dB (baseline c*direct "
             f"{base['psnr_indirect']:.2f}), full {s['psnr_full']:.2f} dB, SSIM indirect {s['ssim_indirect']:.4f}")
    by_k = {}
    for k in e["ks"]:
        ev = ev_default if int(k) == int(config["render"]["k"]) else wp.evaluator(params, config, k=int(k))
        by_k[str(k)] = _scores(_predict(ev, data, "far"), data.tests["far"], e["exposure"])["psnr_indirect"]
    summary["psnr_indirect_far_by_k"] = by_k

    # images
    t = data.tests["far"]
    rows = []
    for i in range(min(3, len(t["valid"]))):
        rows.append((f"far {i}: ours (K={config['render']['k']})", t["indirect"][i], preds["far"][i], t["valid"][i]))
        rows.append((f"far {i}: c * direct", t["indirect"][i], c[None, None, :] * t["direct"][i], t["valid"][i]))
        io.write_exr(os.path.join(out, f"far_{i}_ours.exr"), preds["far"][i])
        io.write_exr(os.path.join(out, f"far_{i}_reference.exr"), t["indirect"][i])
    jeval.side_by_side(os.path.join(out, "side_by_side.png"), rows, exposure=1.0,
                       titles=("reference indirect", "prediction", "|difference|"))

    # Table 2: frame time by resolution and K; equal error against Mitsuba
    from jprt.render import images as mimages
    from jprt.render.lights import EnvMap
    from jprt.render.scenes import SceneHandle

    handle = SceneHandle(config["scene"], EnvMap.create(wp.render_equirect(data.test_envs[0])))
    origin = data.cameras["far"][0]
    frame_ms = {}
    for w, h in e["timing_resolutions"]:
        cam = _camera(config, origin, w, h)
        g = wp._gbuffer_arrays(handle, cam)
        g = {k: jax.device_put(v) for k, v in g.items()}
        for k in e["ks"]:
            ev = wp.evaluator(params, config, k=int(k))
            ms = jeval.time_call(ev, g, data.test_envs[0], repeats=int(e["timing_repeats"]), warmup=1)["median_ms"]
            frame_ms.setdefault(f"{w}x{h}", {})[str(k)] = ms
            _say(f"frame {w}x{h}, K={k}: {ms:.0f} ms")
    summary["frame_ms_by_resolution"] = frame_ms
    timing_key = "256x256" if "256x256" in frame_ms else next(iter(frame_ms))
    summary["frame_ms"] = frame_ms[timing_key]
    summary["frame_ms_resolution"] = timing_key

    refs, valids = t["indirect"], t["valid"]
    target_rmse = jeval.set_rmse(preds["far"], refs, valids)
    summary["rmse_indirect_far_set"] = target_rmse
    far_cams = [_camera(config, o, config["cameras"]["width"], config["cameras"]["height"])
                for o in data.cameras["far"]]

    def render_at(spp):
        out_images = []
        for i, cam in enumerate(far_cams):
            handle.set_lighting(EnvMap.create(wp.render_equirect(data.test_envs[int(t["env"][i])])))
            out_images.append(mimages.direct_indirect(handle, cam, spp=spp, seed=4242 + i).indirect)
        return out_images

    eq = jeval.equal_error_spp(render_at, refs, target_rmse, e["equal_error_spp"], valids, _say)
    summary["equal_error_spp"] = eq["spp"]
    summary["pathtrace_rmse_by_spp"] = eq["tried"]
    jeval.plot_series(os.path.join(out, "equal_error.png"),
                      {"Mitsuba path tracing": ([x["spp"] for x in eq["tried"]], [x["rmse"] for x in eq["tried"]])},
                      xlabel="spp", ylabel="indirect RMSE (far views)", title="path tracing vs neural-wavelet PRT",
                      logx=True, logy=True, hlines={"neural-wavelet PRT (K=64)": target_rmse})
    spp_eq = eq["spp"] or max(int(s) for s in e["equal_error_spp"])
    w, h = (int(v) for v in timing_key.split("x"))
    cam = _camera(config, origin, w, h)
    handle.set_lighting(EnvMap.create(wp.render_equirect(data.test_envs[0])))
    mimages.direct_indirect(handle, cam, spp=1, seed=3)  # warm-up: kernels for this film size
    pt = jeval.time_call(lambda: mimages.direct_indirect(handle, cam, spp=spp_eq, seed=3),
                         repeats=int(e["timing_repeats"]), warmup=0)
    summary["pathtrace_ms_equal_error"] = pt["median_ms"]
    summary["pathtrace_spp_timed"] = spp_eq
    k_default = str(config["render"]["k"])
    ours_ms = summary["frame_ms"].get(k_default, next(iter(summary["frame_ms"].values())))
    summary["speedup_equal_error"] = pt["median_ms"] / ours_ms
    summary["speedup_note"] = (f"Mitsuba llvm_ad_rgb indirect (full max_depth -1 and direct max_depth 2 renders, both "
                               f"timed) at {timing_key} and the equal-error spp, over our K={k_default} frame at "
                               f"{timing_key} (JAX on {jax.default_backend()})"
                               + ("" if eq["spp"] else "; equal error NOT reached: timed at the largest spp tried"))
    _say(f"equal-error spp {eq['spp']}: Mitsuba {pt['median_ms']:.0f} ms vs ours {ours_ms:.0f} ms -> speedup "
         f"{summary['speedup_equal_error']:.2f}x")

    # Tables 3 and 4: ablations at a reduced, common step count
    steps = int(e["ablation_steps"])
    ablations = {}
    for key, values in e["ablations"].items():
        rows = {}
        variants = values.items() if isinstance(values, dict) else ((v, {key: v}) for v in values)
        for value, overrides in variants:
            cfg = merge(config, {"model": overrides, "train": {"steps": steps}})
            d = data
            if cfg["model"]["spatial"] == "vertex":
                d = wp.add_vertex_interpolation(data, config["scene"], float(cfg["model"]["vertex_edge"]))
            r = _train(cfg, d, f"ablation {key}={value}", progress=False)
            ev = wp.evaluator(r["params"], cfg)
            s = _scores(_predict(ev, d, "far"), d.tests["far"], e["exposure"])
            rows[str(value)] = {"psnr_indirect_far": s["psnr_indirect"], "psnr_full_far": s["psnr_full"],
                                "ssim_indirect_far": s["ssim_indirect"], "model_bytes": wp.model_bytes(r["params"])}
            _say(f"ablation {key}={value}: PSNR indirect far {s['psnr_indirect']:.2f} dB")
        ablations[key] = rows
    summary["ablations"] = ablations
    summary["ablation_steps"] = steps
    return jeval.write_report(out, summary, t_start, "Neural-wavelet PRT")

