"""SG light-field textures (Currius et al. 2020) end to end on glossy receivers: baked indirect light
seen from held-out views.

    jprt run experiments/sg_lightfield.py --preset test     # seconds
    jprt run experiments/sg_lightfield.py                   # `small`: 64^2 atlas, 32^2 maps, 16 lobes
    jprt run experiments/sg_lightfield.py --preset paper    # 256^2 atlas, 128^2 maps (an accelerator)

Capture the receivers' light field (cached), train the CNN encoder on every texel; held-out views:
the evaluator on each view's atlas G-buffer against Mitsuba's indirect render (pixels on the
receivers). Stages: per-texel baselines, float16 storage, PSNR by roughness, the references' noise,
quadrature shading, interpolation at captured midpoints, lobe counts, pixel- against texture-space
shading, frame times, §5's environment visibility (Table 3 setting); helpers in
``jprt.methods.sg_lightfield.evaluation``. Report: results/sg_lightfield/<config hash>/
(``benchmarks/sg_lightfield.py`` -> its benchmark JSON).
"""

from __future__ import annotations

import jax
import numpy as np

from jprt import eval as jeval
from jprt.config import merge
from jprt.inputs import LightScale
from jprt.methods import REGISTRY
from jprt.methods.sg_lightfield import baselines
from jprt.methods.sg_lightfield import evaluation as ev
from jprt.methods.sg_lightfield import model as sgm
from jprt.methods.sg_lightfield.data import ENV_DEFAULTS
from jprt.runner import HeldOut, PathTracer

METHOD = "sg_lightfield"
LABEL = "sg_lightfield"

EVAL_DEFAULTS = {
    # held-out views on an arc in front of the box (none of them is a capture position)
    "views": dict(ev.HELD_OUT_VIEWS),
    "resolution": 64,
    "reference_spp": 2048,
    "seed": 4000,
    "timing_resolution": 256,
    "timing_repeats": 20,
    "equal_error_spp": [1, 2, 4, 8, 16, 32, 64, 128, 256, 512, 1024],
    "baseline_steps": 500,
    "images": 3,
    "exposure": 0.0,
    # frame time of the evaluator at these square resolutions (the first held-out view)
    "frame_resolutions": [128, 256, 512],
    # lobe counts of the by-lobes study (each its own CNN; the run's own count is reused)
    "lobes": [4, 8, 16, 32],
    # the interpolation test: extra texels captured halfway between horizontally adjacent baked
    # texels of one object (at most this many pairs, seeded)
    "midpoints": 256,
    # the compression-free bound: raw captured maps shaded by quadrature (sub^2 directions per pixel)
    "quadrature_sub": 4,
    # a second reference set (another seed) for the references' own noise
    "reference_noise": True,
    # §5 under a distant environment (Table 3 setting): data.ENV_DEFAULTS keys, plus the
    # references' spp (Mitsuba's direct light of the env-lit receivers) and the W_E CNN's steps
    "environment": {"enabled": True, **ENV_DEFAULTS, "reference_spp": 1024, "steps": None},
}

CONFIG = {**REGISTRY["sg_lightfield"].default_config, "eval": EVAL_DEFAULTS, "output": {"dir": "results/sg_lightfield"}}

PRESETS = {
    "small": {},
    # the paper's sizes (§3, §7): 128^2 maps, a 256^2 light-field texture, 16 lobes
    "paper": {"lightmap": {"resolution": 256}, "capture": {"size": 128, "spp": 1024},
              "train": {"steps": 20000, "batch": 256},
              "eval": {"resolution": 512, "reference_spp": 16384, "lobes": [16, 32, 64],
                       "environment": {"visibility_size": 128, "size": 128, "samples": 16, "u_size": 128,
                                       "u_env_size": 256, "reference_spp": 8192}}},
    "test": {
        **REGISTRY["sg_lightfield"].presets["test"],
        "eval": {"views": {"n": 1}, "resolution": 16, "reference_spp": 16, "timing_resolution": 16,
                 "timing_repeats": 2, "equal_error_spp": [1, 4], "baseline_steps": 20, "images": 1,
                 "frame_resolutions": [16], "lobes": [1, 2], "midpoints": 8, "quadrature_sub": 1,
                 "environment": {"map": "synthetic", "visibility_size": 16, "samples": 1, "size": 8, "u_size": 16,
                                 "u_env_size": 32, "reference_spp": 16}},
    },
}


ONE = LightScale(np.ones(3, np.float32))  # the bake's own lighting


def _cameras(config: dict, resolution: int | None = None) -> list:
    return ev.cameras(config["eval"]["views"], int(resolution or config["eval"]["resolution"]))


def _gbuffer(run, camera):
    from jprt.render import lightmap

    return lightmap.atlas_gbuffer(run.scene_handle(), lightmap.Atlas(**run.dataset.atlas), camera)


def held_out(run) -> HeldOut:
    """Mitsuba's indirect light of the held-out views (the scene's own emitters, ``reference_spp``)
    against the evaluator on each view's atlas G-buffer; only pixels on the receivers count
    (the references are zero elsewhere, like the predictions)."""
    e = run.config["eval"]
    cameras = _cameras(run.config)
    gbs = [_gbuffer(run, c) for c in cameras]
    run.state.update(cameras=cameras, gbuffers=gbs)
    # only the receivers have a light-field texture: every metric (tonemapped ones too) sees them alone
    refs, direct = ev.references(run.config["scene"], cameras, gbs, e["reference_spp"], e["seed"])
    return HeldOut([np.asarray(run.evaluate(g, ONE)) for g in gbs], refs, [g.valid for g in gbs], direct,
                   [f"view {k}" for k in range(len(gbs))])


def frame(run):
    """The first held-out view at ``eval.timing_resolution``."""
    return _gbuffer(run, _cameras(run.config, int(run.config["eval"]["timing_resolution"]))[0]), ONE


def pathtracer(run) -> PathTracer:
    """Mitsuba's indirect (full minus direct, a seed unlike the references') of the held-out views."""
    timed = _cameras(run.config, int(run.config["eval"]["timing_resolution"]))[0]
    return ev.pathtracer(run.scene_handle(), run.state["cameras"], timed)


def _psnr(run, predictions, references=None, masks=None) -> float:
    """Mean over the held-out views of the runner's PSNR (``jprt.eval.score_images``: sRGB-tonemapped,
    peak 1; over the whole image, whose non-receiver pixels are 0 in both, unless ``masks``
    selects pixels)."""
    refs = run.state["held_out"].references if references is None else references
    return jeval.score_images(predictions, refs, masks, exposure=float(run.config["eval"]["exposure"]),
                              scores=("psnr_indirect",), psnr_valid=masks is not None)["psnr_indirect"]


def _images(run, params, config: dict | None = None) -> list:
    """The evaluator of ``params`` (and ``config``, default the run's) at every held-out view's G-buffer."""
    evaluate = sgm.evaluator(params, run.method_config if config is None else config)
    return [np.asarray(evaluate(g, ONE)) for g in run.state["gbuffers"]]


def fit_report(run) -> dict:
    """The light-field texture and the fit: texels, flags, capture seconds, the CNN's log-L2 at
    the pixel centres, bytes per texel."""
    data, result = run.dataset, run.result
    return {"texels": int(len(data.images)), "texels_inside": int((data.flags == 2).sum()),
            "texels_pushed": int((data.flags == 1).sum()), "capture_s": float(data.meta["capture_s"]),
            "fit_log_l2_cnn": baselines.cnn_log_l2(ev.stored_lobes(result.params), data.images, data.below),
            "bytes_per_texel": int(result.info["bytes_per_texel"])}


def baseline_comparison(run) -> dict:
    """§7: every per-texel baseline on the same texels, lobe budget and loss."""
    data, model_cfg = run.dataset, run.method_config["model"]
    out = baselines.compare(data.images, data.below, data.atlas, int(model_cfg["n_lobes"]),
                            steps=int(run.config["eval"]["baseline_steps"]),
                            max_sharpness=float(model_cfg["max_sharpness"]))
    run.state["baselines"] = out
    s = {"fit_log_l2": {"cnn": run.summary["extra"]["fit_log_l2_cnn"], **{k: v["log_l2"] for k, v in out.items()}},
         "fit_s": {"cnn": run.summary["train_s"], **{k: v["fit_s"] for k, v in out.items()}}}
    run.say("fit log-L2: " + ", ".join(f"{k} {v:.5f}" for k, v in s["fit_log_l2"].items()))
    # the lobe baselines through the same evaluator at the held-out views (SH has no lobes to shade)
    store = lambda lobes: sgm.storage_params(lobes, data, max_sharpness=float(model_cfg["max_sharpness"]))  # noqa: E731
    s["psnr_indirect_baselines"] = {k: _psnr(run, _images(run, store(v["lobes"])))
                                    for k, v in out.items() if "lobes" in v}
    run.say("held-out PSNR of the baselines' lobes: " +
            ", ".join(f"{k} {v:.2f} dB" for k, v in s["psnr_indirect_baselines"].items()))
    return s


def storage_precision(run) -> dict:
    """The held-out images with the lobes in float32 instead of float16: PSNR change (dB)."""
    params32 = {k: (np.asarray(v, np.float32) if np.asarray(v).dtype == np.float16 else v)
                for k, v in run.result.params.items()}
    psnr32 = _psnr(run, _images(run, params32))
    return {"psnr_indirect_fp32_lobes": psnr32, "psnr_delta_fp16": run.summary["psnr_indirect"] - psnr32}


def by_roughness(run) -> dict:
    """PSNR of the held-out views over each receiver's pixels alone, keyed by its GGX alpha."""
    masks = ev.roughness_masks(run.state["gbuffers"], run.scene_handle().object_names(),
                               run.config["scene"]["materials"])
    out = {alpha: _psnr(run, run.state["held_out"].predictions, masks=m) for alpha, m in masks.items()}
    run.say("PSNR by roughness: " + ", ".join(f"alpha {k}: {v:.2f} dB" for k, v in sorted(out.items())))
    return {"psnr_indirect_by_roughness": out}


def reference_noise(run) -> dict:
    """The references' own noise: PSNR between them and a second set at the same spp and another seed
    (two noisy images: about 3 dB below either one's PSNR against the converged image)."""
    e = run.config["eval"]
    if not e["reference_noise"]:
        return {}
    second, _ = ev.references(run.config["scene"], run.state["cameras"], run.state["gbuffers"], e["reference_spp"],
                              int(e["seed"]) + 7919)
    out = {"reference_noise_psnr": _psnr(run, second)}
    run.say(f"reference noise: PSNR {out['reference_noise_psnr']:.2f} dB between two {e['reference_spp']} spp sets")
    return out


def oct_quadrature(run) -> dict:
    """§3's raw light-field texture without lobes, shaded by quadrature of the rendered BRDF
    (``evaluation.quadrature_images``): what the lobes could reach with no compression at all;
    and the run's lobes shaded the same way: the gap between the two is the fit's, the gap from
    there to ``psnr_indirect`` that of the run's shading (``shading.samples``); the lobes through
    Appendix B's SG x ASG product too (``psnr_indirect_appendix_b``)."""
    raw, lobed = ev.quadrature_images(run.dataset, run.result.params, run.state["gbuffers"],
                                      int(run.config["eval"]["quadrature_sub"]))
    # the same lobes through Appendix B's SG x ASG product (shading.samples 0), whatever the run shades with
    product = _images(run, run.result.params, {**run.method_config, "shading": {"samples": 0}})
    out = {"psnr_oct_quadrature": _psnr(run, raw), "psnr_lobes_quadrature": _psnr(run, lobed),
           "psnr_indirect_appendix_b": _psnr(run, product)}
    run.say(f"shaded by quadrature of the rendered BRDF: raw captured maps {out['psnr_oct_quadrature']:.2f} dB, "
            f"the CNN's lobes {out['psnr_lobes_quadrature']:.2f} dB; the evaluator (shading.samples "
            f"{run.method_config['shading']['samples']}) {run.summary['psnr_indirect']:.2f} dB, Appendix B's "
            f"product {out['psnr_indirect_appendix_b']:.2f} dB")
    return out


def midpoint_interpolation(run) -> dict:
    """The paper's interpolation claim (§4, Fig. 2; ``evaluation.midpoint_log_l2``): the lobes
    halfway between two baked texels, as the run time filters them, scored by log-L2 against the
    light field captured at that midpoint (``evaluation.midpoints``). SH interpolates its coefficients."""
    e = run.config["eval"]
    first, second, images, below = ev.midpoints(run.scene_handle(), run.config["scene"], run.dataset,
                                                run.method_config["capture"], int(e["midpoints"]), int(e["seed"]))
    fitted = run.state["baselines"]
    lobe_sets = {"cnn": ev.stored_lobes(run.result.params)} | {k: v["lobes"] for k, v in fitted.items() if "lobes" in v}
    out = ev.midpoint_log_l2(first, second, images, below, lobe_sets,
                             {k: v for k, v in fitted.items() if "lobes" not in v})
    run.say("midpoint log-L2: " + ", ".join(f"{k} {v:.5f}" for k, v in out.items()))
    return {"midpoint_log_l2": out, "midpoints": int(len(images))}


def by_lobes(run) -> dict:
    """Lobe count N: its own CNN (same steps), fit log-L2, held-out PSNR and frame time."""
    data, e = run.dataset, run.config["eval"]
    n_run = int(run.method_config["model"]["n_lobes"])
    gb, one = jax.device_put(frame(run))
    log_l2, psnr, ms = {}, {}, {}
    for n in [int(k) for k in e["lobes"]]:
        if n == n_run:
            params = run.result.params
        else:
            run.say(f"by lobes: training the CNN with {n} lobes")
            _, lobes, _ = sgm.fit_cnn(data.images, data.below, run.with_config({"model": {"n_lobes": n}}),
                                      progress=False)
            params = sgm.storage_params(lobes, data)
        log_l2[str(n)] = baselines.cnn_log_l2(ev.stored_lobes(params), data.images, data.below)
        psnr[str(n)] = _psnr(run, _images(run, params))
        evaluate = jax.jit(sgm.evaluator(params, run.method_config))  # timed as the runner times frame_ms
        ms[str(n)] = jeval.time_call(evaluate, gb, one, repeats=int(e["timing_repeats"]))["median_ms"]
        run.say(f"{n} lobes: log-L2 {log_l2[str(n)]:.5f}, PSNR {psnr[str(n)]:.2f} dB, {ms[str(n)]:.1f} ms")
    return {"log_l2_by_lobes": log_l2, "psnr_indirect_by_lobes": psnr, "frame_ms_by_lobes": ms}


def shading_space(run) -> dict:
    """Where the lobes are shaded (``shading.space``, ``model.evaluator``): §6's pixel space (each
    pixel's filtered lobes) against texture space (each texel once, read bilinearly), the same
    lobes: held-out PSNR and the frame time at ``eval.timing_resolution``, timed as the runner
    times frame_ms."""
    e = run.config["eval"]
    gb, one = jax.device_put(frame(run))
    psnr, ms = {}, {}
    for space in ("pixel", "texel"):
        config = merge(run.method_config, {"shading": {"space": space}})
        psnr[space] = _psnr(run, _images(run, run.result.params, config))
        evaluate = jax.jit(sgm.evaluator(run.result.params, config))
        ms[space] = jeval.time_call(evaluate, gb, one, repeats=int(e["timing_repeats"]))["median_ms"]
        run.say(f"shading in {space} space: PSNR {psnr[space]:.2f} dB, {ms[space]:.1f} ms")
    return {"psnr_indirect_by_space": psnr, "frame_ms_by_space": ms}


def frame_times(run) -> dict:
    """The evaluator's frame time at each of ``eval.frame_resolutions`` (the first held-out view)."""
    e = run.config["eval"]
    out = {}
    evaluate = jax.jit(run.evaluate)  # as the runner times frame_ms
    for res in [int(r) for r in e["frame_resolutions"]]:
        g = jax.device_put(_gbuffer(run, _cameras(run.config, res)[0]))
        out[str(res)] = jeval.time_call(evaluate, g, ONE, repeats=int(e["timing_repeats"]))["median_ms"]
        run.say(f"frame {res}x{res}: {out[str(res)]:.1f} ms")
    return {"frame_ms_by_resolution": out}


def environment_visibility(run) -> dict:
    """§5 (Table 3 setting): the receivers in the open-top box under a distant environment.
    W_E (Eq. 7) per texel, fitted by the same CNN; shaded by Eq. 8 at the held-out views against
    Mitsuba's direct light of the receivers, and compared with visibility tested only along the
    reflected direction, with no visibility, with the raw W_E maps (no lobes), and with Eq. 3 by
    quadrature (``evaluation.environment_images``)."""
    from jprt.methods.sg_lightfield import data as sgdata

    e = run.config["eval"]["environment"]
    if not e.get("enabled", True):
        return {}
    spec = {k: v for k, v in e.items() if k in sgdata.ENV_DEFAULTS}
    ed = sgdata.make_environment_dataset(run.method_config, spec)
    run.say(f"environment: {len(ed.images)} texels, visibility {ed.meta['capture_s']:.1f} s, "
            f"quadrature {ed.meta['quadrature_s']:.1f} s")
    cfg = run.with_config({"train": {"steps": int(e.get("steps") or run.method_config["train"]["steps"])}})
    _, lobes, _ = sgm.fit_cnn(ed.images, ed.below, cfg, progress=False)
    preds, refs = ev.environment_images(ed, lobes, run.state["cameras"], int(e["reference_spp"]),
                                        int(run.config["eval"]["seed"]))
    out = {f"psnr_env_{name}": _psnr(run, p, refs) for name, p in preds.items()}
    out["env_fit_log_l2"] = baselines.cnn_log_l2(lobes, ed.images, ed.below)
    out["env_texels"] = int(len(ed.images))
    out["env_map"] = spec.get("map", sgdata.ENV_DEFAULTS["map"])
    run.say("environment PSNR: " + ", ".join(f"{k} {v:.2f} dB" for k, v in out.items() if k.startswith("psnr")))
    return out


#: The stages of the SG light-field report, in order.
STAGES = [fit_report, baseline_comparison, storage_precision, by_roughness, reference_noise, oct_quadrature,
          midpoint_interpolation, by_lobes, shading_space, frame_times, environment_visibility]
