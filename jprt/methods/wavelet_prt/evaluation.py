"""What neural-wavelet PRT's report measures beyond the method contract (Raghavan et al. 2023, §5):
predictions and Table 1 scores of a test split, PSNR by held-out map, resumable training runs
keyed by their config, and the ground-truth transport check (Mitsuba's environment-to-pixel
transport of one view, projected onto the Haar basis, relit with the top-K wavelets).

Renders with Mitsuba through ``jprt.render``; the model's math stays in ``model.py``.
"""

from __future__ import annotations

import json
import os
import time

import jax
import jax.numpy as jnp
import numpy as np

from jprt import eval as jeval
from jprt import metrics
from jprt.inputs import CubeMap
from jprt.methods.base import FitResult
from jprt.methods.wavelet_prt import data as wp_data
from jprt.methods.wavelet_prt import model as wp
from jprt.sphere import haar

__all__ = ["camera", "scene_handle", "predict_split", "split_scores", "resumable_fit", "logged_train_s",
           "views_by_map", "psnr_by_map", "pair_mean", "transport_check", "write_transport_check", "baseline_scale",
           "table1", "map_scores", "by_map", "variant_dataset", "dataset_stats"]


def camera(config: dict, origin, width: int, height: int):
    """A camera at ``origin`` looking at the config's ``cameras.target`` with its fov."""
    from jprt.render.cameras import look_at

    return look_at(origin, tuple(config["cameras"]["target"]), fov=float(config["cameras"]["fov"]), width=int(width),
                   height=int(height))


def scene_handle(scene, cube, handle=None):
    """A Mitsuba scene lit by the cube map ``cube`` (6, n, n, 3): ``handle`` relit, or a new one."""
    from jprt.render.lights import EnvMap
    from jprt.render.scenes import SceneHandle
    from jprt.sphere.envmap import render_equirect

    lighting = EnvMap.create(render_equirect(cube))
    if handle is None:
        return SceneHandle(scene, lighting)
    handle.set_lighting(lighting)
    return handle


def _views(t: dict) -> list[dict]:
    """The per-image G-buffer (and vertex) fields of a test split."""
    names = [k for k in list(wp.GBUFFER_FIELDS) + list(wp.VERTEX_FIELDS) if k in t]
    return [{k: t[k][i] for k in names} for i in range(len(t["valid"]))]


def predict_split(evaluate, data: wp.WaveletData, split: str) -> list[np.ndarray]:
    """The evaluator's indirect image of every view of test split ``split`` ("near", "far") under its map."""
    t = data.tests[split]
    return [np.asarray(evaluate(g, CubeMap(data.test_envs[int(t["env"][i])]))) for i, g in enumerate(_views(t))]


def split_scores(preds, t: dict, exposure: float) -> dict:
    """Table 1's metrics over a split's views (``jprt.eval.score_images``): tonemapped PSNR / SSIM
    of indirect and of direct + indirect, mean over views, and the mean over views of each view's
    HDR indirect RMSE (``rmse_indirect``)."""
    s = jeval.score_images(preds, t["indirect"], t["valid"], t["direct"], exposure=exposure,
                           scores=("psnr_indirect", "psnr_full", "ssim_indirect", "ssim_full", "image_rmse_mean"))
    return {"psnr_indirect": s["psnr_indirect"], "psnr_full": s["psnr_full"], "ssim_indirect": s["ssim_indirect"],
            "ssim_full": s["ssim_full"], "rmse_indirect": s["image_rmse_mean"]}


def resumable_fit(cfg: dict, data, say=print, label: str = "training", progress: bool | None = None) -> FitResult:
    """``model.fit`` with its checkpoint and metrics log in a folder of ``jprt.cache`` keyed by the
    config (``model.run_key``): an interrupted run resumes, a finished one is reused.
    ``info["log_path"]`` is its metrics log; a resumed run's ``info["train_s"]`` is read back from
    it (``info["train_s_source"]`` says which)."""
    from jprt.cache import cache_root

    folder = os.path.join(cache_root(), "wavelet_prt", "runs", wp.run_key(cfg))
    os.makedirs(folder, exist_ok=True)
    say(f"{label}: checkpoint {folder}")
    log_path = os.path.join(folder, "metrics.jsonl")
    result = wp.fit(data, cfg, checkpoint_path=os.path.join(folder, "ckpt.npz"), log_path=log_path, progress=progress)
    result.info["log_path"] = log_path
    result.info["train_s_source"] = "this run"
    if result.info["resumed_from"]:  # the time of every segment, from the log
        result.info["train_s"] = logged_train_s(log_path)
        result.info["train_s_source"] = "metrics.jsonl (resumed run)"
    return result


def logged_train_s(log_path: str) -> float | None:
    """Training wall time from a run's metrics.jsonl: the sum over its segments (a resumed run
    restarts elapsed_s) of each segment's last elapsed_s; None without a log."""
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


def views_by_map(data) -> dict:
    """{held-out map name: indices of the far images it lights} (maps lighting none left out)."""
    env = [int(v) for v in data.tests["far"]["env"]]
    views = {name: [i for i, e in enumerate(env) if e == j] for j, name in enumerate(data.test_env_names)}
    return {name: v for name, v in views.items() if v}


def psnr_by_map(images, data, exposure: float) -> dict:
    """{map: mean tonemapped PSNR of ``images`` (one per far image) against the references}."""
    ref = data.tests["far"]["indirect"]
    return {name: float(np.mean([metrics.tonemapped(metrics.psnr, images[i], ref[i], exposure) for i in views]))
            for name, views in views_by_map(data).items()}


def pair_mean(by: dict, pair) -> float | None:
    """The mean of ``by`` over the maps of ``pair`` it has (None when it has none)."""
    have = [m for m in pair if m in by]
    return float(np.mean([by[m] for m in have])) if have else None


def _rel(a, b) -> float:
    return float(np.linalg.norm(a - b) / max(np.linalg.norm(b), 1e-30))


def transport_check(config: dict, data, check: dict) -> dict:
    """The ground-truth transport check on a small far view (``check``: width, height, spp,
    max_depth, ks): Mitsuba's environment-to-pixel indirect transport (``jprt.render.transport``)
    projected onto the Haar basis and relit with the top-K wavelets of the first held-out map,
    against Mitsuba's render of that map (and two such renders against each other: the noise
    floor).

    Returns {"summary": the report's numbers, "ks": the K used (at most 6 n^2), "mitsuba" and
    "wavelets_all": the (H, W, 3) images, "learned_err": params, cfg -> {K: relative error of a
    model's T_k against Mitsuba's over the top-K wavelets}}."""
    from jprt.render.cameras import camera_rays
    from jprt.render.images import indirect_rays
    from jprt.render.transport import environment_transport

    n = int(config["envmaps"]["face_size"])
    cube = data.test_envs[0]
    origin = data.cameras["far"][0] if len(data.cameras["far"]) else data.cameras["train"][0]
    cam = camera(config, origin, check["width"], check["height"])
    handle = scene_handle(config["scene"], cube)
    o, d = camera_rays(cam)
    depth = int(check["max_depth"])
    t0 = time.perf_counter()
    transport = environment_transport(handle, o, d, face_size=n, spp=int(check["spp"]), seed=11, max_depth=depth)
    t_transport = time.perf_counter() - t0
    ref, ref2 = (indirect_rays(handle, o, d, spp=int(check["spp"]), seed=s, max_depth=depth).indirect for s in (21, 22))
    ks = [min(int(k), 6 * n * n) for k in check["ks"]]
    res = wp.transport_check(transport, cube, ks)
    # Mitsuba's T_k (Haar coefficients of the texel transport, the T_k that B = sum_k L_k T_k asks
    # for) on the same pixels, over the top-K wavelets of this held-out map
    g = wp_data.gbuffer_fields(handle, cam)
    t_true = np.asarray(jnp.moveaxis(haar.forward(jnp.moveaxis(jnp.asarray(transport), 0, 3)), 3, 0))
    t_true = t_true.reshape(t_true.shape[0], -1, 3)
    valid = g["valid"].reshape(-1) > 0
    coeffs = haar.forward(jnp.asarray(cube))
    top = {k: np.asarray(wp.select_wavelets(coeffs, k)[0]) for k in ks}

    def learned_err(params, cfg) -> dict:
        """Relative error of a model's T_k against Mitsuba's over the top-K wavelets, by K."""
        m = wp.model(cfg)
        flat = {f: jnp.asarray(g[f].reshape((-1,) + g[f].shape[2:])) for f in m.fields}
        t_learned = np.asarray(m.transport(params, flat, jnp.arange(6 * n * n, dtype=jnp.int32)))
        return {str(k): _rel(t_learned[valid][:, idx], t_true[valid][:, idx]) for k, idx in top.items()}

    summary = {
        "gt_transport_rel_err_by_k": {str(k): _rel(res["by_k"][k], ref) for k in ks},
        "gt_transport_rel_err_all": _rel(res["wavelet_all"], ref),
        "gt_transport_truncation_by_k": {str(k): _rel(res["by_k"][k], res["full"]) for k in ks},
        "gt_transport_parseval_err": _rel(res["wavelet_all"], res["full"]),
        "gt_transport_noise_floor": _rel(ref2, ref),
        "gt_transport_mean_ratio": float(res["full"].mean() / max(ref.mean(), 1e-30)),
        "gt_transport_s": t_transport,
        "gt_transport_setup": {"pixels": [int(check["width"]), int(check["height"])], "spp": int(check["spp"]),
                               "max_depth": depth, "face_size": n, "environment": data.test_env_names[0]},
    }
    shape = (int(check["height"]), int(check["width"]), 3)
    return {"summary": summary, "ks": ks, "mitsuba": ref.reshape(shape),
            "wavelets_all": res["wavelet_all"].reshape(shape), "learned_err": learned_err}


def write_transport_check(out: str, check: dict) -> None:
    """The transport check's figure (gt_transport_error_vs_k.png: error against K, the truncation
    error and the noise floor) and images (gt_transport_mitsuba.exr, gt_transport_wavelets_all.exr)
    in the folder ``out``."""
    from jprt import io

    s, ks = check["summary"], check["ks"]
    jeval.plot_series(os.path.join(out, "gt_transport_error_vs_k.png"),
                      {"top-K wavelets vs Mitsuba": (ks, [s["gt_transport_rel_err_by_k"][str(k)] for k in ks]),
                       "top-K vs all wavelets (truncation)": (ks, [s["gt_transport_truncation_by_k"][str(k)]
                                                                 for k in ks])},
                      xlabel="K (wavelets)", ylabel="relative L2 error", title="ground-truth transport check",
                      logx=True, logy=True, hlines={"Mitsuba vs Mitsuba (noise)": s["gt_transport_noise_floor"]})
    io.write_exr(os.path.join(out, "gt_transport_mitsuba.exr"), check["mitsuba"])
    io.write_exr(os.path.join(out, "gt_transport_wavelets_all.exr"), check["wavelets_all"])


def baseline_scale(data) -> np.ndarray:
    """The baseline's best RGB c (indirect = c * direct) on the training data (``model.indirect_baseline_scale``)."""
    return wp.indirect_baseline_scale(data.train["direct"], data.train["indirect"], data.train["valid"])


def table1(data, predictions: dict, exposure: float) -> dict:
    """Table 1: ``split_scores`` of each split of ``predictions`` ({"near": images, "far": images};
    a split without test views is left out) and of the baseline c * direct, as
    {"baseline_scale", "<score>_<split>", "<score>_<split>_baseline"}."""
    c = baseline_scale(data)
    s = {"baseline_scale": c.tolist()}
    for split, preds in predictions.items():
        t = data.tests[split]
        sc = split_scores(preds, t, exposure)
        base = split_scores([c[None, None, :] * d for d in t["direct"]], t, exposure)
        s.update({f"{k}_{split}": v for k, v in sc.items()} | {f"{k}_{split}_baseline": base[k] for k in sc})
    return s


def map_scores(far_predictions, data, exposure: float, pair) -> dict:
    """Far-view PSNR per held-out map, their mean, the worst, the mean over the maps of ``pair``."""
    by = psnr_by_map(far_predictions, data, exposure)
    return {"psnr_indirect_far": float(np.mean(list(by.values()))), "psnr_indirect_far_worst": min(by.values()),
            "psnr_indirect_far_original_pair": pair_mean(by, pair), "psnr_indirect_far_by_map": by}


def far_map_scores(evaluate, data, exposure: float, pair) -> dict:
    """``map_scores`` of ``evaluate``'s images of the far views (``predict_split``): the
    experiment's generalisation rows and ``benchmarks/wavelet_reruns.py`` score with it."""
    return map_scores(predict_split(evaluate, data, "far"), data, exposure, pair)


def by_map(far_predictions, baseline, data, categories: dict, exposure: float, pair) -> dict:
    """The held-out protocol by map: PSNR per map of the far predictions and of ``baseline`` (one
    image per far view), each map's category (``categories``: {map: category}), the smallest mean
    and the smallest pixel of the predicted indirect per map (negative radiance would show there);
    the worst map against the baseline's worst, the mean over the maps of ``pair``, the mean by
    category."""
    t = data.tests["far"]
    by = psnr_by_map(far_predictions, data, exposure)
    base = psnr_by_map(baseline, data, exposure)
    out = {"psnr_indirect_far_by_map": by, "psnr_indirect_far_baseline_by_map": base, "min_mean_indirect_by_map": {},
           "min_pixel_indirect_by_map": {}, "held_out_categories": {}}
    for name, views in views_by_map(data).items():
        out["min_mean_indirect_by_map"][name] = float(min(
            np.asarray(far_predictions[i])[np.asarray(t["valid"][i], bool)].mean() for i in views))
        out["min_pixel_indirect_by_map"][name] = float(min(np.asarray(far_predictions[i]).min() for i in views))
        out["held_out_categories"][name] = categories.get(name, "uncategorised")
    if by:
        worst = min(by, key=by.get)
        out.update(psnr_indirect_far_worst=by[worst], psnr_indirect_far_worst_map=worst,
                   psnr_indirect_far_baseline_worst=min(base.values()))
        mean = pair_mean(by, pair)
        if mean is not None:
            out["psnr_indirect_far_original_pair"] = mean
        by_cat = {}
        for name, v in by.items():
            by_cat.setdefault(out["held_out_categories"][name], []).append(v)
        out["psnr_indirect_far_by_category"] = {k: float(np.mean(v)) for k, v in by_cat.items()}
    return out


def variant_dataset(cfg: dict, base_cfg: dict, data, scene):
    """The dataset a variant config trains on: ``data`` (made under ``base_cfg``) unless the
    variant changes the maps, cameras or data sections (then its own, through ``jprt.cache``),
    with per-vertex features interpolated when its model reads them (``model.spatial`` "vertex")."""
    if any(cfg[k] != base_cfg[k] for k in ("envmaps", "cameras", "data")):
        data = wp_data.make_dataset(scene, cfg)
    if cfg["model"]["spatial"] == "vertex":
        data = wp_data.add_vertex_interpolation(data, scene, float(cfg["model"]["vertex_edge"]))
    return data


def dataset_stats(data, info: dict, out: str) -> dict:
    """Sizes of the training set and the held-out maps, how the fit ran (``info``); the training
    curve as ``out``/loss.png."""
    losses = np.asarray(info["losses"])
    if len(losses):
        steps_run = np.arange(len(losses)) + 1 + info["resumed_from"]
        jeval.plot_series(os.path.join(out, "loss.png"), {"mu-law L2": (steps_run, losses)},
                          xlabel="step", ylabel="loss", title="training loss", logy=True)
    return {"n_train_images": int(np.prod(data.train["valid"].shape[:2])), "n_train_envs": len(data.env_names),
            "held_out_envs": data.test_env_names, "render_s": data.stats["render_s"],
            "image_size": list(data.train["valid"].shape[2:]), "train_s_source": info["train_s_source"],
            "train_resumed_from": info["resumed_from"]}
