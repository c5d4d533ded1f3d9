"""SG environment visibility (Currius et al. 2020 §5) end to end: glossy receivers in the open-top
Cornell box reflecting a distant environment, with visibility, from held-out views, under the map
W_E was computed for and under maps it never saw.

    jprt run experiments/sg_environment.py --preset test     # seconds
    jprt run experiments/sg_environment.py                   # `small`: 64^2 atlas, 32^2 W_E maps, 16 lobes
    jprt view results/sg_environment/<hash>                  # relight it with any map in the browser

Pipeline: capture the receivers' visibility and W_E (Eq. 7) under ``environment`` (cached) -> train
the §4 encoder on every texel's W_E map -> held-out views x lightings: the evaluator on each view's
atlas G-buffer with the lighting pre-convolved (Eq. 6) against Mitsuba's *direct* light of the same
view (the environment reflected once, visibility included; pixels on the receivers). The common
summary's ``indirect_*`` fields therefore hold this method's prediction, direct light (the
schema's one quantity per method); ``extra.psnr_by_lighting`` splits the score by lighting.
"""

from __future__ import annotations

import numpy as np

from jprt import eval as jeval
from jprt.methods import REGISTRY
from jprt.methods.sg_environment import data as adapter
from jprt.methods.sg_environment import model as sem
from jprt.methods.sg_lightfield.evaluation import HELD_OUT_VIEWS
from jprt.methods.sg_lightfield.evaluation import cameras as held_out_cameras
from jprt.runner import HeldOut, PathTracer

METHOD = "sg_environment"
LABEL = "sg_environment"

EVAL_DEFAULTS = {
    # held-out views on an arc in front of the box (as experiments/sg_lightfield.py)
    "views": dict(HELD_OUT_VIEWS),
    "resolution": 64,
    "reference_spp": 1024,
    "seed": 4000,
    # the lightings of the held-out set: the map W_E was computed for ("bake"), the same map turned
    # about +Y by these angles, and seeded synthetic skies W_E never saw
    "rotations": [90.0],
    "synthetic_skies": 1,
    "sky_face": 32,
    "timing_resolution": 256,
    "timing_repeats": 20,
    "equal_error_spp": [1, 2, 4, 8, 16, 32, 64, 128, 256, 512],
    "images": 3,
    "exposure": 0.0,
}

CONFIG = {**REGISTRY["sg_environment"].default_config, "eval": EVAL_DEFAULTS,
          "output": {"dir": "results/sg_environment"}}

PRESETS = {
    "small": {},
    "test": {
        **REGISTRY["sg_environment"].presets["test"],
        "eval": {"views": {"n": 1}, "resolution": 16, "reference_spp": 16, "timing_resolution": 16,
                 "timing_repeats": 2, "equal_error_spp": [1, 4], "images": 1, "sky_face": 8},
    },
}


def _cameras(config: dict, resolution: int | None = None) -> list:
    return held_out_cameras(config["eval"]["views"], int(resolution or config["eval"]["resolution"]))


def _lightings(run) -> list:
    """[(label, equirect radiance)] of the held-out set (``eval.rotations``, ``eval.synthetic_skies``)."""
    from jprt.sphere.envmap import render_equirect, rotate_equirect, synthetic_environments

    if "lightings" not in run.state:
        e = run.config["eval"]
        bake = np.asarray(run.dataset.environment, np.float32)
        out = [("bake", bake)] + [(f"bake turned {a:g} deg", np.asarray(rotate_equirect(bake, float(a)), np.float32))
                                  for a in e["rotations"]]
        skies = synthetic_environments(int(e["synthetic_skies"]), int(e["sky_face"]), seed=int(e["seed"]))
        out += [(f"synthetic sky {k}", np.asarray(render_equirect(c), np.float32)) for k, c in enumerate(skies)]
        run.state["lightings"] = out
    return run.state["lightings"]


def _handle(run, radiance):
    from jprt.render.lights import EnvMap

    handle = run.scene_handle()
    handle.set_lighting(EnvMap.create(radiance))
    return handle


def held_out(run) -> HeldOut:
    """Every held-out view under every lighting of ``_lightings``: the evaluator (lighting
    pre-convolved once per map) against Mitsuba's direct light at ``reference_spp``; only pixels on
    the receivers count."""
    from jprt.render.images import render

    e = run.config["eval"]
    cameras = _cameras(run.config)
    preds, refs, valid, labels = [], [], [], []
    for name, radiance in _lightings(run):
        handle = _handle(run, radiance)
        lighting = sem.preconvolved(radiance, run.method_config)
        for k, camera in enumerate(cameras):
            g = adapter.task_inputs(handle, run.dataset, camera)
            ref = render(handle, camera, spp=int(e["reference_spp"]), max_depth=2, seed=int(e["seed"]) + k)
            preds.append(np.asarray(run.evaluate(g, lighting)))
            refs.append(np.where(g.valid[..., None], ref, 0.0))
            valid.append(g.valid)
            labels.append(f"{name}, view {k}")
    run.state.update(cameras=cameras)
    return HeldOut(preds, refs, valid, None, labels)


def frame(run):
    """The first held-out view at ``eval.timing_resolution`` under the bake's map."""
    name, radiance = _lightings(run)[0]
    camera = _cameras(run.config, int(run.config["eval"]["timing_resolution"]))[0]
    return adapter.task_inputs(_handle(run, radiance), run.dataset, camera), sem.preconvolved(radiance, run.method_config)


def pathtracer(run) -> PathTracer:
    """Mitsuba's direct light (``max_depth = 2``, a seed unlike the references') of the held-out set."""
    from jprt.render.images import render

    timed = _cameras(run.config, int(run.config["eval"]["timing_resolution"]))[0]

    def render_at(spp):
        return [render(_handle(run, radiance), c, spp=spp, max_depth=2, seed=9001)
                for _, radiance in _lightings(run) for c in run.state["cameras"]]

    def time_at(spp):
        handle = _handle(run, _lightings(run)[0][1])
        render(handle, timed, spp=1, max_depth=2, seed=3)  # warm-up: Dr.Jit compiles for this film size
        return jeval.time_call(lambda: render(handle, timed, spp=spp, max_depth=2, seed=3), repeats=1,
                               warmup=0)["median_ms"]

    return PathTracer(render_at, time_at, "Mitsuba llvm_ad_rgb direct light (max_depth 2) of the open-top box")


def psnr_by_lighting(run) -> dict:
    """Tonemapped PSNR (as ``psnr_indirect``) and relative RMSE of the held-out images per lighting
    (the bake's map, turned maps, unseen skies; ``jprt.eval.score_images``): what relighting with a
    map W_E was not computed for costs."""
    held = run.state["held_out"]
    groups: dict = {}
    for item in zip(held.predictions, held.references, held.valid, held.labels):
        groups.setdefault(item[3].split(", view")[0], []).append(item[:3])
    scores = {k: jeval.score_images(*zip(*items), exposure=float(run.config["eval"]["exposure"]),
                                    scores=("psnr_indirect", "indirect_rel_rmse")) for k, items in groups.items()}
    out = {"psnr_by_lighting": {k: s["psnr_indirect"] for k, s in scores.items()},
           "rel_rmse_by_lighting": {k: s["indirect_rel_rmse"] for k, s in scores.items()}}
    run.say("by lighting: " + ", ".join(f"{k} {v:.2f} dB" for k, v in out["psnr_by_lighting"].items()))
    return out


STAGES = [psnr_by_lighting]
