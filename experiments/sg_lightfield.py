"""SG light-field textures (Currius et al. 2020) end to end on glossy receivers: baked indirect light
seen from held-out views.

    jprt run experiments/sg_lightfield.py --preset test     # seconds
    jprt run experiments/sg_lightfield.py                   # `small`: 64^2 atlas, 32^2 maps, 16 lobes
    jprt run experiments/sg_lightfield.py --preset paper    # 256^2 atlas, 128^2 maps (an accelerator)

Pipeline: capture the receivers' light field (``jprt.render.lightfield``, cached) -> train the CNN
encoder on every texel -> held-out views: the evaluator on each view's atlas G-buffer against
Mitsuba's indirect render of the same view (pixels on the receivers), the common summary, frame
time, equal error; stages: the per-texel baselines on the same texels and the same loss
(``jprt.methods.sg_lightfield.baselines``), the float16 storage's effect on the images, bytes per
texel. The report goes to results/sg_lightfield/<config hash>/.
"""

from __future__ import annotations

import numpy as np

from jprt import eval as jeval
from jprt.inputs import LightScale
from jprt.methods import REGISTRY
from jprt.methods.sg_lightfield import baselines
from jprt.methods.sg_lightfield import model as sgm
from jprt.runner import HeldOut, PathTracer

METHOD = "sg_lightfield"
LABEL = "sg_lightfield"

EVAL_DEFAULTS = {
    # held-out views on an arc in front of the box (none of them is a capture position)
    "views": {"n": 3, "radius": 3.9, "arc_deg": 50.0, "start_deg": -25.0, "height": 0.0},
    "resolution": 64,
    "reference_spp": 2048,
    "seed": 4000,
    "timing_resolution": 256,
    "timing_repeats": 5,
    "equal_error_spp": [1, 2, 4, 8, 16, 32, 64, 128, 256, 512, 1024],
    "baseline_steps": 500,
    "images": 3,
    "exposure": 0.0,
}

CONFIG = {**REGISTRY["sg_lightfield"].default_config, "eval": EVAL_DEFAULTS, "output": {"dir": "results/sg_lightfield"}}

PRESETS = {
    "small": {},
    # the paper's sizes (§3, §7): 128^2 maps, a 256^2 light-field texture, 16 lobes
    "paper": {"lightmap": {"resolution": 256}, "capture": {"size": 128, "spp": 1024},
              "train": {"steps": 20000, "batch": 256}, "eval": {"resolution": 512, "reference_spp": 16384}},
    "test": {
        **REGISTRY["sg_lightfield"].presets["test"],
        "eval": {"views": {"n": 1}, "resolution": 16, "reference_spp": 16, "timing_resolution": 16,
                 "timing_repeats": 2, "equal_error_spp": [1, 4], "baseline_steps": 20, "images": 1},
    },
}


def _cameras(config: dict, resolution: int | None = None) -> list:
    from jprt.render import cameras as cams

    v, res = config["eval"]["views"], int(resolution or config["eval"]["resolution"])
    return cams.orbit((0.0, float(v["height"]), 0.0), float(v["radius"]), int(v["n"]), arc_deg=float(v["arc_deg"]),
                      start_deg=float(v["start_deg"]), width=res, height=res)


def _handle(run):
    from jprt.render.scenes import SceneHandle

    if "handle" not in run.state:
        run.state["handle"] = SceneHandle(run.config["scene"])
    return run.state["handle"]


def _gbuffer(run, camera):
    from jprt.render import lightmap

    return lightmap.atlas_gbuffer(_handle(run), lightmap.Atlas(**run.dataset.atlas), camera)


# --------------------------------------------------------------------------------------------
# The runner's hooks


def held_out(run) -> HeldOut:
    """Mitsuba's indirect light of the held-out views (the scene's own emitters, ``reference_spp``)
    against the evaluator on each view's atlas G-buffer; only pixels on the receivers count
    (the references are zero elsewhere, like the predictions)."""
    from jprt.render.dataset import render_dataset

    e = run.config["eval"]
    cameras = _cameras(run.config)
    refs = render_dataset(run.config["scene"], cameras, [None], spp=int(e["reference_spp"]), seed=int(e["seed"]),
                          gbuffers=False)
    gbs = [_gbuffer(run, c) for c in cameras]
    run.state.update(cameras=cameras, gbuffers=gbs)
    one = LightScale(np.ones(3, np.float32))
    preds = [np.asarray(run.evaluate(g, one)) for g in gbs]
    rad = [refs.radiance(k) for k in range(len(refs))]
    # only the receivers have a light-field texture: every metric (tonemapped ones too) sees them alone
    mask = [g.valid[..., None] for g in gbs]
    return HeldOut(preds, [np.where(m, r["indirect"], 0.0) for m, r in zip(mask, rad)], [g.valid for g in gbs],
                   [np.where(m, r["direct"], 0.0) for m, r in zip(mask, rad)], [f"view {k}" for k in range(len(gbs))])


def frame(run):
    """The first held-out view at ``eval.timing_resolution``."""
    return _gbuffer(run, _cameras(run.config, int(run.config["eval"]["timing_resolution"]))[0]), \
        LightScale(np.ones(3, np.float32))


def pathtracer(run) -> PathTracer:
    """Mitsuba's indirect (full minus direct, a seed unlike the references') of the held-out views."""
    from jprt.render.images import direct_indirect

    handle = _handle(run)
    timed = _cameras(run.config, int(run.config["eval"]["timing_resolution"]))[0]

    def render_at(spp):
        return [direct_indirect(handle, c, spp=spp, seed=9001).indirect for c in run.state["cameras"]]

    def time_at(spp):
        direct_indirect(handle, timed, spp=1, seed=3)  # warm-up: Dr.Jit compiles for this film size
        return jeval.time_call(lambda: direct_indirect(handle, timed, spp=spp, seed=3), repeats=1, warmup=0)["median_ms"]

    return PathTracer(render_at, time_at, "Mitsuba llvm_ad_rgb, indirect = full (max_depth -1) minus direct "
                                          "(max_depth 2), both renders timed")


# --------------------------------------------------------------------------------------------
# Stages


def fit_report(run) -> dict:
    """The light-field texture and the fit: texels, flags, capture seconds, the CNN's log-L2 at
    the pixel centres, bytes per texel."""
    data, result = run.dataset, run.result
    lobes = sgm.Lobes(*(np.asarray(result.params[k], np.float32) for k in ("axes", "sharpness", "amplitude")))
    return {"texels": int(len(data.images)), "texels_inside": int((data.flags == 2).sum()),
            "texels_pushed": int((data.flags == 1).sum()), "capture_s": float(data.meta["capture_s"]),
            "fit_log_l2_cnn": baselines.cnn_log_l2(lobes, data.images, data.below),
            "bytes_per_texel": int(result.info["bytes_per_texel"])}


def baseline_comparison(run) -> dict:
    """§7: every per-texel baseline on the same texels, lobe budget and loss."""
    data = run.dataset
    n = int(run.method_config["model"]["n_lobes"])
    out = baselines.compare(data.images, data.below, data.atlas, n, steps=int(run.config["eval"]["baseline_steps"]))
    s = {"fit_log_l2": {"cnn": run.summary["extra"]["fit_log_l2_cnn"], **{k: v["log_l2"] for k, v in out.items()}},
         "fit_s": {"cnn": run.summary["train_s"], **{k: v["fit_s"] for k, v in out.items()}}}
    run.say("fit log-L2: " + ", ".join(f"{k} {v:.5f}" for k, v in s["fit_log_l2"].items()))
    return s


def storage_precision(run) -> dict:
    """The held-out images with the lobes in float32 instead of float16: PSNR change (dB)."""
    from jprt import metrics

    params32 = {k: (np.asarray(v, np.float32) if np.asarray(v).dtype == np.float16 else v)
                for k, v in run.result.params.items()}
    evaluate32 = sgm.evaluator(params32, run.method_config)
    held = run.state["held_out"]
    one = LightScale(np.ones(3, np.float32))
    e = float(run.config["eval"]["exposure"])
    psnr32 = float(np.mean([metrics.tonemapped(metrics.psnr, np.asarray(evaluate32(g, one)), r, e)
                            for g, r in zip(run.state["gbuffers"], held.references)]))
    return {"psnr_indirect_fp32_lobes": psnr32, "psnr_delta_fp16": run.summary["psnr_indirect"] - psnr32}


#: The stages of the SG light-field report, in order.
STAGES = [fit_report, baseline_comparison, storage_precision]
