"""Any registered method on a scene file as a user brings it: its config for that scene
(``scene_config``) and its fit, predictions and per-object scores on a lighting set-up of
``jprt.render.heldout.lighting_setup`` (``fit_and_score``).

Scores are ``jprt.eval.object_scores`` (relative RMSE, on the image's scale where an object is
dark against it) with the references' noise floor taken out (``jprt.eval.noise_removed``).
"""

from __future__ import annotations

import time

import numpy as np

from jprt import eval as jeval
from jprt.config import merge

__all__ = ["scene_config", "fit_and_score"]


def scene_config(name: str, scene: dict, regions: dict, sizes: dict) -> dict:
    """Method ``name``'s config for a scene file: its defaults, the scene, the sizes of ``sizes``;
    data-driven PRT's point lights in the scene's light region (its defaults are the Cornell
    box's), at a clearance of 2 % of the region's scale."""
    from jprt.methods import REGISTRY

    m = REGISTRY[name]
    cfg = m.resolve({"scene": scene, **sizes})
    if name == "rrf":
        cfg = merge(cfg, {"train": {"progress": False}})
    if name == "datadriven":
        lo, hi = np.asarray(regions["light_lo"]), np.asarray(regions["light_hi"])
        scale = float(np.max(hi - lo))
        cfg = merge(cfg, {"lights": {"kind": "point", "position_lo": regions["light_lo"],
                                     "position_hi": regions["light_hi"], "clearance": 0.02 * scale}})
    return m.resolve(cfg)


def _predictions(m, s: dict, cameras: list, dataset, result, cfg: dict, baked: bool):
    """The evaluator's image of every (view, lighting) item of set-up ``s`` (0 off the G-buffer),
    and the (inputs, lighting) of the first item: the frame that is timed."""
    import jax

    evaluate = jax.jit(m.evaluator(result.params, cfg))
    preds, timed = [], None
    for camera, g in zip(cameras, s["gbuffers"]):
        if baked:  # the atlas G-buffer of the view, the bake's own lighting
            from jprt.render import lightmap

            inputs = lightmap.atlas_gbuffer(s["handle"], lightmap.Atlas(**dataset.atlas), camera)
            task = s["method_lightings"]
        else:
            inputs = m.task_inputs(s["handle"], dataset, camera)
            task = [m.task_lighting(s["handle"], dataset, result.params, cfg, x) for x in s["method_lightings"]]
        preds += [np.where(g.valid[..., None], np.asarray(evaluate(inputs, lit)), 0.0) for lit in task]
        timed = timed or (inputs, task[0])
    return evaluate, preds, timed


def fit_and_score(name: str, s: dict, cameras: list, cfg: dict, e: dict, peak_gflops: float,
                  baked: bool = False) -> tuple[dict, np.ndarray]:
    """Fit method ``name`` (config ``cfg``) on set-up ``s`` and predict every (view, lighting)
    item; ``baked``: the method bakes the file's own emitters (the views' atlas G-buffers, the
    set-up's own lightings). Returns its report entry (per-object scores of the judged objects and
    of those apart, the worst and mean with the noise removed, whether ``e["target"]`` /
    ``e["target_mean"]`` are met, the method's self-check, frame time and FLOPs against
    ``peak_gflops``, dataset and fit seconds) and the first item's prediction."""
    from jprt.methods import REGISTRY

    m = REGISTRY[name]
    t0 = time.perf_counter()
    dataset = m.make_dataset(s["desc"], cfg, progress=False)
    t1 = time.perf_counter()
    result = m.fit(dataset, cfg)
    t2 = time.perf_counter()
    evaluate, preds, timed = _predictions(m, s, cameras, dataset, result, cfg, baked)
    timing = jeval.time_call(evaluate, *timed, repeats=int(e["timing_repeats"]))
    roof = m.frame_report(result.params, cfg, evaluate, *timed, timing["median_ms"], peak_gflops=peak_gflops,
                          repeats=int(e["timing_repeats"]))
    scores = jeval.object_scores(preds, s["refs"], s["ids"], s["names"])
    for obj, v in scores.items():
        v["noise_floor"] = s["floor"][obj]["rel_rmse"]
        v["rel_rmse_noise_removed"] = jeval.noise_removed(v["rel_rmse"], s["floor"][obj]["rel_rmse"])
    judged = {k: scores[k] for k in s["judged"] if k in scores}
    # the method's own check of its fit on held-out data of its training renders (None without
    # one); the check itself warns, in one line, when the fit should not be trusted
    check = None if m.self_check is None else m.self_check(dataset, result, cfg)
    worst = max((v["rel_rmse_noise_removed"] for v in judged.values()), default=float("nan"))
    mean = float(np.mean([v["rel_rmse_noise_removed"] for v in judged.values()])) if judged else float("nan")
    info = {k: v for k, v in result.info.items() if isinstance(v, (int, float, str))}
    report = getattr(result.info.get("report"), "_asdict", lambda: {})()
    meta = getattr(dataset, "meta", None)
    entry = {"per_object": judged,
             "apart": {k: {**scores[k], "why": why} for k, why in s["apart"].items() if k in scores},
             "worst_rel_rmse": max((v["rel_rmse"] for v in judged.values()), default=float("nan")),
             "worst_rel_rmse_noise_removed": worst, "mean_rel_rmse_noise_removed": mean,
             "target_met": bool(worst <= float(e["target"]) and mean <= float(e["target_mean"])),
             "self_check": check, "frame_ms": timing["median_ms"], "frame_flops": roof["frame_flops"],
             "frame_flops_source": roof["frame_flops_source"], "flops_fraction_of_peak": roof["flops_fraction_of_peak"],
             "roofline": roof["roofline"], "roofline_matmul": roof["roofline_matmul"],
             "roofline_detail": roof["roofline_detail"],
             "speedup_vs_reference_render": s["peer"]["ms"] / timing["median_ms"] if s["peer"] else None,
             "frame_resolution": list(np.shape(preds[0])[:2]), "dataset_s": t1 - t0, "fit_s": t2 - t1, "info": info,
             "grouped_objects": report.get("grouped", {}), "skipped_objects": report.get("skipped", {}),
             "regions": meta.get("regions") if isinstance(meta, dict) else None}
    return entry, preds[0]
