"""SG light-field textures (Currius et al. 2020) end to end on glossy receivers: baked indirect light
seen from held-out views.

    jprt run experiments/sg_lightfield.py --preset test     # seconds
    jprt run experiments/sg_lightfield.py                   # `small`: 64^2 atlas, 32^2 maps, 16 lobes
    jprt run experiments/sg_lightfield.py --preset paper    # 256^2 atlas, 128^2 maps (an accelerator)

Pipeline: capture the receivers' light field (``jprt.render.lightfield``, cached) -> train the CNN
encoder on every texel -> held-out views: the evaluator on each view's atlas G-buffer against
Mitsuba's indirect render of the same view (pixels on the receivers), the common summary, frame
time, equal error; stages: the per-texel baselines on the same texels and loss (fit, and their lobes
at the held-out views), float16 storage, PSNR by roughness, the references' noise, the raw maps and
the lobes shaded by quadrature, interpolation at captured midpoints, lobe counts, frame times by
resolution, and §5's environment visibility in the open-top box (Table 3 setting). The report goes
to results/sg_lightfield/<config hash>/; ``benchmarks/sg_lightfield.py`` turns it into
benchmarks/results/sg_lightfield.json.
"""

from __future__ import annotations

import jax
import numpy as np

from jprt import eval as jeval
from jprt.inputs import LightScale
from jprt.methods import REGISTRY
from jprt.methods.sg_lightfield import baselines
from jprt.methods.sg_lightfield.data import ENV_DEFAULTS
from jprt.methods.sg_lightfield import model as sgm
from jprt.runner import HeldOut, PathTracer
from jprt.sphere import octahedral, sg

METHOD = "sg_lightfield"
LABEL = "sg_lightfield"

EVAL_DEFAULTS = {
    # held-out views on an arc in front of the box (none of them is a capture position)
    "views": {"n": 3, "radius": 3.9, "arc_deg": 50.0, "start_deg": -25.0, "height": 0.0},
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
    out = baselines.compare(data.images, data.below, data.atlas, n, steps=int(run.config["eval"]["baseline_steps"]),
                            max_sharpness=float(run.method_config["model"]["max_sharpness"]))
    run.state["baselines"] = out
    s = {"fit_log_l2": {"cnn": run.summary["extra"]["fit_log_l2_cnn"], **{k: v["log_l2"] for k, v in out.items()}},
         "fit_s": {"cnn": run.summary["train_s"], **{k: v["fit_s"] for k, v in out.items()}}}
    run.say("fit log-L2: " + ", ".join(f"{k} {v:.5f}" for k, v in s["fit_log_l2"].items()))
    # the lobe baselines through the same evaluator at the held-out views (SH has no lobes to shade)
    s["psnr_indirect_baselines"] = {k: _psnr(run, _images(run, sgm.storage_params(v["lobes"], data, max_sharpness=float(run.method_config["model"]["max_sharpness"]))))
                                    for k, v in out.items() if "lobes" in v}
    run.say("held-out PSNR of the baselines' lobes: " +
            ", ".join(f"{k} {v:.2f} dB" for k, v in s["psnr_indirect_baselines"].items()))
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


def _images(run, params) -> list:
    """The evaluator of ``params`` at every held-out view's G-buffer."""
    evaluate = sgm.evaluator(params, run.method_config)
    one = LightScale(np.ones(3, np.float32))
    return [np.asarray(evaluate(g, one)) for g in run.state["gbuffers"]]


def _psnr(run, predictions, references=None, masks=None) -> float:
    """Mean over the held-out views of the runner's PSNR (sRGB-tonemapped, peak 1; over the whole
    image, whose non-receiver pixels are 0 in both, unless ``masks`` selects pixels)."""
    from jprt import metrics

    refs = run.state["held_out"].references if references is None else references
    e = float(run.config["eval"]["exposure"])
    masks = [None] * len(refs) if masks is None else masks
    return float(np.mean([metrics.tonemapped(metrics.psnr, p, r, e, valid=m) for p, r, m in zip(predictions, refs, masks)]))


def by_roughness(run) -> dict:
    """PSNR of the held-out views over each receiver's pixels alone, keyed by its GGX alpha."""
    names = _handle(run).object_names()
    held = run.state["held_out"]
    out = {}
    for obj in np.unique(np.concatenate([np.unique(g.object_id[g.valid]) for g in run.state["gbuffers"]])):
        alpha = run.config["scene"]["materials"][names[int(obj)]].get("roughness")
        masks = [g.valid & (g.object_id == obj) for g in run.state["gbuffers"]]
        if alpha is not None and all(m.any() for m in masks):
            out[f"{float(alpha):g}"] = _psnr(run, held.predictions, masks=masks)
    run.say("PSNR by roughness: " + ", ".join(f"alpha {k}: {v:.2f} dB" for k, v in sorted(out.items())))
    return {"psnr_indirect_by_roughness": out}


def reference_noise(run) -> dict:
    """The references' own noise: PSNR between them and a second set at the same spp and another seed
    (two noisy images: about 3 dB below either one's PSNR against the converged image)."""
    from jprt.render.dataset import render_dataset

    e = run.config["eval"]
    if not e["reference_noise"]:
        return {}
    refs = render_dataset(run.config["scene"], run.state["cameras"], [None], spp=int(e["reference_spp"]),
                          seed=int(e["seed"]) + 7919, gbuffers=False)
    second = [np.where(g.valid[..., None], refs.radiance(k)["indirect"], 0.0) for k, g in enumerate(run.state["gbuffers"])]
    out = {"reference_noise_psnr": _psnr(run, second)}
    run.say(f"reference noise: PSNR {out['reference_noise_psnr']:.2f} dB between two {e['reference_spp']} spp sets")
    return out


def oct_quadrature(run) -> dict:
    """§3's raw light-field texture without lobes: each pixel's captured map filtered bilinearly
    between its texels like the lobes, shaded by quadrature of the rendered BRDF
    (``model.shade_quadrature``): what the lobes could reach with no compression at all. And the
    run's lobes shaded the same way: the gap between the two is the fit's, the gap from there to
    ``psnr_indirect`` that of Appendix B's SG x ASG shading."""
    from jprt.methods.lightmap_lookup import atlas_image, atlas_lookup

    data, e = run.dataset, run.config["eval"]
    n = data.images.shape[1]
    table = atlas_image(np.asarray(data.images, np.float32).reshape(len(data.images), -1),
                        np.asarray(data.atlas["fill_index"]))
    dirs = octahedral.texel_directions(n).reshape(-1, 3)
    preds, lobe_preds = [], []
    for g in run.state["gbuffers"]:
        quadrature = lambda maps: np.where(g.valid[..., None], np.asarray(sgm.shade_quadrature(  # noqa: E731
            maps, g.normal, g.view, g.roughness, g.specular_albedo, sub=int(e["quadrature_sub"]))), 0.0)
        preds.append(quadrature(np.asarray(atlas_lookup(table, g.uv)).reshape(g.uv.shape[:2] + (n, n, 3))))
        lobes = sgm.lookup_lobes(run.result.params, g.uv)  # the run's lobes as the evaluator filters them
        lobe_preds.append(quadrature(np.asarray(sgm.lobe_radiance(lobes, dirs)).reshape(g.uv.shape[:2] + (n, n, 3))))
    out = {"psnr_oct_quadrature": _psnr(run, preds), "psnr_lobes_quadrature": _psnr(run, lobe_preds)}
    run.say(f"shaded by quadrature of the rendered BRDF: raw captured maps {out['psnr_oct_quadrature']:.2f} dB, "
            f"the CNN's lobes {out['psnr_lobes_quadrature']:.2f} dB (Appendix B's shading: "
            f"{run.summary['psnr_indirect']:.2f} dB)")
    return out


def _midpoints(run):
    """Pairs (a, b) of horizontally adjacent texels of one object, both captured as OK, and the
    light field captured halfway between them (cached like the light field)."""
    from jprt import cache
    from jprt.render import lightfield as lf

    data, e, c = run.dataset, run.config["eval"], run.method_config["capture"]
    a = data.atlas
    r, index, obj = int(a["resolution"]), np.asarray(a["texel_index"]), np.asarray(a["texel_object"])
    where = np.full(r * r, -1)
    where[index] = np.arange(len(index))
    right = np.where(index % r < r - 1, where[np.minimum(index + 1, r * r - 1)], -1)
    ok = (right >= 0) & (data.flags == lf.OK)
    ok &= (obj[np.maximum(right, 0)] == obj) & (data.flags[np.maximum(right, 0)] == lf.OK)
    first = np.nonzero(ok)[0]
    rng = np.random.default_rng(int(e["seed"]))
    first = np.sort(rng.choice(first, min(int(e["midpoints"]), len(first)), replace=False))
    second = right[first]
    pos = 0.5 * (np.asarray(a["position"])[first] + np.asarray(a["position"])[second])
    nrm = np.asarray(a["normal"])[first] + np.asarray(a["normal"])[second]
    nrm /= np.linalg.norm(nrm, axis=-1, keepdims=True)
    handle = _handle(run)
    points, flags = lf.capture_points(handle, pos, nrm, float(a["texel_size"]))
    spec = {"format": 1, "scene": run.config["scene"], "points": lf.atlas_digest(points, nrm), "size": int(c["size"]),
            "spp": int(c["spp"]), "seed": int(c["seed"]) + 104729}
    maps, _ = cache.cached("lightfield_midpoints", spec, lambda: lf.capture_block(
        handle, points, nrm, flags, int(c["size"]), spp=int(c["spp"]), seed=spec["seed"]))
    keep = flags == lf.OK
    return first[keep], second[keep], maps[c["field"]][keep], maps["below"][keep]


def midpoint_interpolation(run) -> dict:
    """The paper's interpolation claim (§4, Fig. 2): the lobes halfway between two baked texels,
    as the run time filters them (every parameter linear, axes renormalised), scored by log-L2
    against the light field captured at that midpoint. SH interpolates its coefficients."""
    first, second, images, below = _midpoints(run)
    size = images.shape[1]
    dirs = np.asarray(octahedral.texel_directions(size)).reshape(-1, 3)
    targets, weights = images.reshape(len(images), -1, 3), sgm.pixel_weights(size, below)
    at = np.broadcast_to(dirs, (len(images),) + dirs.shape)
    p = run.result.params
    lobe_sets = {"cnn": sgm.Lobes(*(np.asarray(p[k], np.float32) for k in ("axes", "sharpness", "amplitude")))}
    out = {}
    for name, res in run.state["baselines"].items():
        if "lobes" in res:
            lobe_sets[name] = res["lobes"]
        else:  # SH: linear in its coefficients
            mid = 0.5 * (res["sh"][first] + res["sh"][second])
            out[name] = float(sg.log_l2(baselines.sh_radiance(mid, dirs), targets, weights))
    for name, lobes in lobe_sets.items():
        pick = lambda idx: sgm.Lobes(*(np.asarray(x)[idx] for x in lobes))  # noqa: E731
        mid = baselines.interpolate_lobes(pick(first), pick(second))
        out[name] = float(sgm.log_l2_loss(mid, at, targets, weights))
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
        lobes = sgm.Lobes(*(np.asarray(params[k], np.float32) for k in ("axes", "sharpness", "amplitude")))
        log_l2[str(n)] = baselines.cnn_log_l2(lobes, data.images, data.below)
        psnr[str(n)] = _psnr(run, _images(run, params))
        evaluate = jax.jit(sgm.evaluator(params, run.method_config))  # timed as the runner times frame_ms
        ms[str(n)] = jeval.time_call(evaluate, gb, one, repeats=int(e["timing_repeats"]))["median_ms"]
        run.say(f"{n} lobes: log-L2 {log_l2[str(n)]:.5f}, PSNR {psnr[str(n)]:.2f} dB, {ms[str(n)]:.1f} ms")
    return {"log_l2_by_lobes": log_l2, "psnr_indirect_by_lobes": psnr, "frame_ms_by_lobes": ms}


def frame_times(run) -> dict:
    """The evaluator's frame time at each of ``eval.frame_resolutions`` (the first held-out view)."""
    e = run.config["eval"]
    out = {}
    evaluate = jax.jit(run.evaluate)  # as the runner times frame_ms
    for res in [int(r) for r in e["frame_resolutions"]]:
        g = jax.device_put(_gbuffer(run, _cameras(run.config, res)[0]))
        out[str(res)] = jeval.time_call(evaluate, g, LightScale(np.ones(3, np.float32)),
                                        repeats=int(e["timing_repeats"]))["median_ms"]
        run.say(f"frame {res}x{res}: {out[str(res)]:.1f} ms")
    return {"frame_ms_by_resolution": out}


def environment_visibility(run) -> dict:
    """§5 (Table 3 setting): the receivers in the open-top box under a distant environment.
    W_E (Eq. 7) per texel, fitted by the same CNN; shaded by Eq. 8 at the held-out views against
    Mitsuba's direct light of the receivers (the environment reflected once, visibility
    included), and compared with visibility tested only along the reflected direction (exact per
    pixel: one ray), with no visibility, with the raw W_E maps (no lobes), and with Eq. 3 by
    quadrature of the captured visibility x environment (no split-sum approximation at all)."""
    from jprt.methods.lightmap_lookup import atlas_image, atlas_lookup
    from jprt.methods.sg_lightfield import data as sgdata
    from jprt.methods.sg_lightfield import environment as env
    from jprt.render import lightmap
    from jprt.render.images import render
    from jprt.render.lights import EnvMap
    from jprt.render.scenes import SceneHandle

    e = run.config["eval"]["environment"]
    if not e.get("enabled", True):
        return {}
    spec = {k: v for k, v in e.items() if k in sgdata.ENV_DEFAULTS}
    ed = sgdata.make_environment_dataset(run.method_config, spec)
    run.say(f"environment: {len(ed.images)} texels, visibility {ed.meta['capture_s']:.1f} s, "
            f"quadrature {ed.meta['quadrature_s']:.1f} s")
    steps = e.get("steps") or run.method_config["train"]["steps"]
    cfg = run.with_config({"train": {"steps": int(steps)}})
    _, lobes, _ = sgm.fit_cnn(ed.images, ed.below, cfg, progress=False)
    stored = sgm.to_storage(lobes)
    handle = SceneHandle(sgdata.ENV_RECEIVERS, EnvMap.create(ed.environment))
    atlas = lightmap.Atlas(**ed.atlas)
    texture = {"axes": stored.axes, "sharpness": stored.sharpness, "amplitude": stored.amplitude,
               "fill_index": np.asarray(ed.atlas["fill_index"])}
    raw = atlas_image(np.asarray(ed.images).reshape(len(ed.images), -1), np.asarray(ed.atlas["fill_index"]))
    eps = lightmap.ray_offset(handle)
    m, size = ed.visible.shape[1], ed.images.shape[1]
    lit = np.asarray(ed.visible)[..., None] * env.octahedral_environment(ed.environment, m)[None]  # V L per texel
    lit_table = atlas_image(lit.reshape(len(lit), -1), np.asarray(ed.atlas["fill_index"]))
    preds = {"we": [], "we_raw": [], "reflected_visibility": [], "no_visibility": [], "quadrature": []}
    refs = []
    for k, camera in enumerate(run.state["cameras"]):
        g = lightmap.atlas_gbuffer(handle, atlas, camera)
        ref = render(handle, camera, spp=int(e["reference_spp"]), max_depth=2, seed=int(run.config["eval"]["seed"]) + k)
        refs.append(np.where(g.valid[..., None], ref, 0.0))
        r = 2.0 * np.sum(g.normal * g.view, axis=-1, keepdims=True) * g.normal - g.view
        u = env.lookup_preconvolved(ed.u, ed.alphas, r, g.roughness)
        w = env.evaluate_lobes(sgm.lookup_lobes(texture, g.uv), r)
        w_raw = np.asarray(jax.vmap(env.octahedral_lookup)(
            np.asarray(atlas_lookup(raw, g.uv)).reshape(-1, size, size, 3), r.reshape(-1, 3))).reshape(r.shape)
        hit = lightmap.intersect(handle, (g.position + eps * g.normal).reshape(-1, 3), r.reshape(-1, 3))
        v_r = (~np.array(hit.is_valid(), bool)).reshape(r.shape[:2] + (1,)).astype(np.float32)
        for name, vis in (("we", w), ("we_raw", w_raw), ("reflected_visibility", v_r), ("no_visibility", 1.0)):
            img = env.shade_environment(u, vis, g.normal, g.view, g.roughness, g.specular_albedo)
            preds[name].append(np.where(g.valid[..., None], np.asarray(img), 0.0))
        # Eq. 3 itself: the captured V L maps, filtered between texels, by quadrature of the BRDF
        maps = np.asarray(atlas_lookup(lit_table, g.uv)).reshape(g.uv.shape[:2] + (m, m, 3))
        img = sgm.shade_quadrature(maps, g.normal, g.view, g.roughness, g.specular_albedo, sub=2)
        preds["quadrature"].append(np.where(g.valid[..., None], np.asarray(img), 0.0))
    out = {f"psnr_env_{name}": _psnr(run, p, refs) for name, p in preds.items()}
    out["env_fit_log_l2"] = baselines.cnn_log_l2(lobes, ed.images, ed.below)
    out["env_texels"] = int(len(ed.images))
    out["env_map"] = spec.get("map", sgdata.ENV_DEFAULTS["map"])
    run.say("environment PSNR: " + ", ".join(f"{k} {v:.2f} dB" for k, v in out.items() if k.startswith("psnr")))
    return out


#: The stages of the SG light-field report, in order.
STAGES = [fit_report, baseline_comparison, storage_precision, by_roughness, reference_noise, oct_quadrature,
          midpoint_interpolation, by_lobes, frame_times, environment_visibility]
