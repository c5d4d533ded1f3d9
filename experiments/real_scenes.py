"""Real scenes as users bring them (issue 21): Mitsuba XML interiors through every method whose
lighting fits an interior, with no hand-set box, atlas or object list.

    jprt run experiments/real_scenes.py                 # both Bitterli scenes, every method below
    jprt run experiments/real_scenes.py --preset test   # tiny sizes, the Cornell picture scene only
    python benchmarks/real_scenes.py                    # -> benchmarks/results/real_scenes.json

For each scene file (``scenes``, under ``assets``; default ../shared/assets/scenes):

* the file is loaded as it is. RRF and data-driven PRT relight with point lights (Eq. 9 and the
  §4.1 scenario are linear in them), so the file's own emitters are removed for them
  (``keep_emitters = False``); SG light-field textures bake the light field of the file's own
  emitters (``LightScale``: only their power can change), so they keep them. The
  environment-lit methods (neural-wavelet PRT, SH PRT) see the file with its emitters removed and
  an opening cut into it (``environment.opening``, default "ceiling": ``jprt.render.scenes.xml``
  removes every up- or down-facing surface in the top 2 % of the scene's height), lit by held-out
  environment maps (``environment.maps``: never in neural-wavelet PRT's training set) through the
  opening and through the side the file's camera looks in from;
* every region comes from the scene (``jprt.render.sampling.scene_regions``: lights in the upper
  part of the room's bounds and outside geometry, views about the file's own camera); the atlas
  covers every object (xatlas charts where a mesh's UVs do not serve); nothing is set per scene;
* held-out: the file's camera at ``eval.resolution`` (no capture or training view), lit by
  ``eval.n_lights`` point lights drawn in the same light region with another seed, or by the
  file's emitters for the baked method, or by the held-out maps (as ``face_size`` cube maps; Mitsuba
  renders the same texels) for the environment-lit ones. References: Mitsuba's indirect light (full minus direct,
  same seed) at ``eval.reference_spp`` along the pixel-centre rays that the methods' G-buffers
  read (``jprt.render.images.centre_rays``: a rendered image averages each pixel's footprint,
  which no per-pixel prediction can show), and a second render of them with another seed (the
  references' own noise);
* per object covering at least ``eval.min_object_fraction`` of the image: the relative RMSE
  ||prediction - reference|| / ||reference|| over its pixels and all held-out lights, beside the
  noise floor ||reference' - reference|| / ||reference|| and the error with the reference's
  noise taken out (sqrt(rel^2 - floor^2 / 2): independent seeds). Predicting zero scores 1 by
  definition, so the issue's target (below half of predicting zero) is a relative RMSE below 0.5,
  judged on the raw number;
* the evaluator's frame time (inputs and lighting ready) and a side-by-side image per method.

SG environment visibility is not run (``not_run`` says why: it predicts the glossy part of the
direct light, and every object these views see at 1 % or more is diffuse); MRT is exempt (its
scenes are block layouts).
"""

from __future__ import annotations

import os
import time

import numpy as np

from jprt import eval as jeval
from jprt import io
from jprt.config import config_hash, merge, save_resolved

#: The Bitterli scenes of ../shared/assets (see its README), next to this checkout.
SHARED_SCENES = os.path.abspath(os.path.join(os.path.dirname(__file__), "..", "..", "shared", "assets", "scenes"))

CONFIG = {
    "assets": "",  # folder of the scene files; "" = SHARED_SCENES
    "scenes": ["veach-bidir/scene.xml", "cornell_box_picture/scene_picture.xml"],
    "methods": ["rrf", "datadriven", "sg_lightfield", "wavelet_prt", "sh_prt"],
    # reference_spp_file_emitters: the file's own emitters light veach-bidir through its lamp's
    # glass (the scene made to defeat path tracing): at 512 spp its references differ from each
    # other by 0.89 of their norm, at 16384 by about 0.16
    "eval": {"resolution": 64, "n_lights": 3, "reference_spp": 512, "reference_spp_file_emitters": 16384,
             "seed": 7100, "min_object_fraction": 0.01, "timing_repeats": 10, "target": 0.5},
    # the environment-lit methods: the opening cut into each file, the held-out maps (one indoor, one
    # overcast, one clear sky with sun; all held out of neural-wavelet PRT's training maps) as cube
    # maps at neural-wavelet PRT's cube face size, normalised to mean radiance 1
    "environment": {"opening": "ceiling", "maps": ["st_fagans_interior_1k", "potsdamer_platz_1k", "rooitou_park_1k"]},
    # the methods' own sections (their defaults are scene-aware; these are sizes only)
    "rrf": {"data": {"n_lights": 16, "n_views": 12, "n_rays": 256, "spp": 256, "min_object_rays": 8},
            "tree": {"max_leaves": 32, "min_samples": 600}, "train": {"max_iters": 30}},
    "datadriven": {"lightmap": {"resolution": 96}, "points": {"candidates": 8192, "count": 512},
                   "data": {"n_train": 128, "n_test": 4, "spp": 64, "test_spp": 64}},
    "sg_lightfield": {"objects": [], "lightmap": {"resolution": 128}, "capture": {"size": 16, "spp": 64, "jitter": True},
                      "model": {"n_lobes": 8, "channels": [16, 32, 64]}, "train": {"steps": 1000, "batch": 64}},
    # views from the scene (target None: about the file's camera); one held-out view of its own (the
    # report scores the file's camera); the procedural training skies named so that `--set
    # wavelet_prt.envmaps.procedural=sun` can try suns (2026-12-01, Cornell picture: worst / mean
    # object 0.590 / 0.500 with suns against 0.598 / 0.428 with the default lobes); its training maps
    # named too (`[]`: every map not held out) so a validation run can leave one out; `envmaps.tilt`
    # and `train.objective` named so validation runs can try them (README, 2026-12-02), and so is
    # `train.fine_penalty` (the light the finest Haar levels carry, penalised; 0: off); the share of
    # procedural lightings and the training seed named so validation runs can vary them.
    # model.lighting_levels 2: the model reads the lighting's scaling wavelets and two coarsest
    # detail levels (96 per channel at face 16, fewer than the 150 training lightings), chosen on the
    # strong-light validation (studio_small_03 held out, README 2026-12-02 evening): worst / mean
    # object 0.557 / 0.371 and 0.557 / 0.374 (two seeds) against 4.81 / 2.33 with every level;
    # 3 levels 6.41 / 3.19, 1 level 0.83 / 0.64
    "wavelet_prt": {"envmaps": {"face_size": 16, "procedural": "lobes", "procedural_fraction": 0.2, "train": [],
                                 "tilt": 0.0},
                    "cameras": {"width": 64, "height": 64, "target": None, "sphere": {"n": 40}, "helix": {"n": 35},
                                "near": 1, "far": 1},
                    "data": {"spp": 128, "test_spp": 64, "envs_per_view": 2, "test_pairs": "cycle", "rays": "image"},
                    "model": {"n_levels": 8, "log2_table_size": 14, "n_features": 32, "hidden": 128,
                              "lighting_levels": 2},
                    "train": {"steps": 1500, "pixels": 256, "wavelets": 300, "objective": "paper",
                              "fine_penalty": 0.0, "fine_levels": 2, "seed": 0}, "render": {"k": 64}},
    "sh_prt": {"lightmap": {"resolution": 96}, "sh": {"order": 3, "spp": 64, "env_height": 32}},
    "output": {"dir": "results/real_scenes"},
}

PRESETS = {
    "test": {"scenes": ["cornell_box_picture/scene_picture.xml"],
             "eval": {"resolution": 16, "n_lights": 1, "reference_spp": 8, "reference_spp_file_emitters": 8,
                      "timing_repeats": 2},
             "rrf": {"data": {"n_lights": 4, "n_views": 3, "n_rays": 48, "spp": 8, "min_object_rays": 2},
                     "tree": {"max_leaves": 8, "min_samples": 200}, "train": {"max_iters": 5}},
             "datadriven": {"lightmap": {"resolution": 32}, "points": {"candidates": 512, "count": 16},
                            "data": {"n_train": 12, "n_test": 2, "spp": 4, "test_spp": 4}},
             "sg_lightfield": {"lightmap": {"resolution": 32}, "capture": {"size": 8, "spp": 2},
                               "model": {"n_lobes": 2, "channels": [4, 8]}, "train": {"steps": 20, "batch": 16}},
             "environment": {"maps": ["rooitou_park_1k"]},
             "wavelet_prt": {"envmaps": {"face_size": 4},
                             "cameras": {"width": 12, "height": 12, "sphere": {"n": 3}, "helix": {"n": 3}},
                             "data": {"spp": 4, "test_spp": 4, "envs_per_view": 1},
                             "model": {"n_levels": 3, "log2_table_size": 8, "n_features": 8, "hidden": 16},
                             "train": {"steps": 20, "pixels": 32, "wavelets": 24}, "render": {"k": 16}},
             "sh_prt": {"lightmap": {"resolution": 32}, "sh": {"order": 2, "spp": 2, "env_height": 8}}},
}


def _say(msg: str) -> None:
    print(f"[real_scenes] {msg}", flush=True)


def method_config(name: str, scene: dict, regions: dict, sizes: dict) -> dict:
    """The method's config for a scene file: its defaults, the scene, the sizes of ``sizes``;
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


def _held_out(desc: dict, regions: dict, e: dict):
    """(camera, [PointLights], handle): the file's camera and the held-out lights."""
    from jprt.inputs import PointLights
    from jprt.render.sampling import free_lights, latin_hypercube
    from jprt.render.scenes import SceneHandle

    handle = SceneHandle(desc)
    camera = handle.default_camera(int(e["resolution"]), int(e["resolution"]))
    rng = np.random.default_rng(int(e["seed"]))
    positions = latin_hypercube(rng, int(e["n_lights"]), regions["light_lo"], regions["light_hi"])
    positions = free_lights(desc, positions, regions["light_lo"], regions["light_hi"], rng)
    return camera, [PointLights.create([p], [1.0, 1.0, 1.0]) for p in positions], handle


def _per_object(preds, refs, object_id, names, min_fraction: float) -> dict:
    """{object name: {"pixels", "fraction", "rel_rmse", "rel_rmse_by_lighting", "mean_ratio"}} for
    objects covering at least ``min_fraction`` of the image: ``rel_rmse`` over all images (the
    brightest lighting weighs most), ``rel_rmse_by_lighting`` image by image, ``mean_ratio`` the
    prediction's mean over the reference's (all images and channels: 1 when no light is missing
    or added overall, whatever the error's pattern)."""
    out = {}
    count = object_id.size
    for k in np.unique(object_id[object_id >= 0]):
        mask = object_id == k
        fraction = float(mask.sum() / count)
        if fraction < min_fraction:
            continue
        p = np.concatenate([np.asarray(x)[mask] for x in preds])
        r = np.concatenate([np.asarray(x)[mask] for x in refs])
        out[names[int(k)]] = {"pixels": int(mask.sum()), "fraction": fraction, "rel_rmse": _rel(p, r),
                              "mean_ratio": float(np.sum(p, dtype=np.float64) / max(float(np.sum(r, dtype=np.float64)),
                                                                                   1e-30)),
                              "rel_rmse_by_lighting": [_rel(np.asarray(a)[mask], np.asarray(b)[mask])
                                                       for a, b in zip(preds, refs)]}
    return out


def _rel(p, r) -> float:
    """||p - r|| / ||r|| in float64."""
    p, r = np.asarray(p, np.float64), np.asarray(r, np.float64)
    return float(np.sqrt(np.sum((p - r) ** 2)) / max(float(np.sqrt(np.sum(r * r))), 1e-30))


#: Methods baked under the scene file's own emitters (their lighting is ``LightScale``).
BAKED = ("sg_lightfield",)
#: Methods relit by environment maps: run on the file with an opening cut into it.
ENVIRONMENT_LIT = ("wavelet_prt", "sh_prt")
#: Registered methods this experiment does not run, and why (the report's ``not_run``).
NOT_RUN = {"sg_environment": "predicts the glossy part of the direct light (the environment reflected once); every "
                             "object these views see at >= 1 % is diffuse, where its prediction is 0 by construction",
           "mrt": "exempt (block layouts)"}


def setup_kind(name: str) -> str:
    """The lighting set-up a method is scored under: "file emitters", "environment" or "point"."""
    return "file emitters" if name in BAKED else "environment" if name in ENVIRONMENT_LIT else "point"


def _environments(env: dict, face_size: int) -> tuple[list, list]:
    """(method-side ``CubeMap`` lightings, Mitsuba-side ``EnvMap`` of the same texels) of the
    held-out maps ``env["maps"]`` at cube face size ``face_size``."""
    from jprt.inputs import CubeMap
    from jprt.methods.wavelet_prt import data as wp_data
    from jprt.methods.wavelet_prt import model as wp
    from jprt.render.lights import EnvMap

    cubes, _ = wp_data.load_environments(list(env["maps"]), [0.0], int(face_size))
    return [CubeMap(c) for c in cubes], [EnvMap.create(wp.render_equirect(c)) for c in cubes]


def _references(desc, handle, camera, lightings, e) -> tuple[list, list]:
    """Mitsuba's indirect light along the camera's pixel-centre rays (``images.centre_rays``) under
    each lighting (None: the file's emitters, at ``reference_spp_file_emitters``), at two seeds:
    (references, second references). Each image is a ``jprt.cache`` entry (scene description,
    camera, lighting, spp, seed): a second run of the report (another method, another setting)
    does not render them again."""
    from jprt import cache
    from jprt.render.images import centre_rays
    from jprt.render.lights import lighting_description
    from jprt.render.scenes import describe

    scene = describe(desc)  # reads and hashes the file once
    refs, refs2 = [], []
    for i, lighting in enumerate(lightings):
        spp = int(e["reference_spp"] if lighting is not None else e["reference_spp_file_emitters"])
        for seed, out in ((int(e["seed"]) + i, refs), (int(e["seed"]) + 1000 + i, refs2)):
            # format 2: pixel-centre rays (format 1 was box-filtered rendered images)
            spec = {"format": 2, "scene": scene, "camera": camera._asdict(), "spp": spp, "seed": seed,
                    "lighting": None if lighting is None else lighting_description(lighting)}

            def render(lighting=lighting, spp=spp, seed=seed):
                handle.set_lighting(lighting)
                return {"indirect": centre_rays(handle, camera, spp=spp, seed=seed).indirect}

            out.append(cache.cached("real_scenes_reference", spec, render)[0]["indirect"])
    return refs, refs2


def _pathtrace_ms(handle, camera, lighting, e) -> dict:
    """The peer: Mitsuba's time for one reference frame of the held-out view (full and direct
    paths along the pixel-centre rays, the indirect light at the references' spp), after a 1-spp
    warm-up (Dr.Jit compiles per ray count)."""
    from jprt.render.images import centre_rays

    handle.set_lighting(lighting)
    spp = int(e["reference_spp"] if lighting is not None else e["reference_spp_file_emitters"])
    centre_rays(handle, camera, spp=1, seed=3)
    t0 = time.perf_counter()
    centre_rays(handle, camera, spp=spp, seed=3)
    return {"spp": spp, "ms": 1e3 * (time.perf_counter() - t0),
            "note": "Mitsuba llvm_ad_rgb, full (max_depth -1) and direct (max_depth 2) paths along the "
                    "pixel-centre rays at the references' spp"}


def _face_counts(handle) -> list[int]:
    """Triangles of each shape of ``handle`` in object-id order (0 for shapes that are not meshes)."""
    return [int(s.face_count()) if hasattr(s, "face_count") else 0 for s in handle.shapes()]


def run_scene(path: str, config: dict, out: str) -> dict:
    """Every method of ``config['methods']`` on the scene file ``path``: its report entry."""
    import jax

    from jprt.inputs import LightScale
    from jprt.methods import REGISTRY
    from jprt.render.gbuffer import gbuffer
    from jprt.render.sampling import scene_regions
    from jprt.render.scenes import SceneHandle

    e = config["eval"]
    stem = os.path.basename(os.path.dirname(path))
    dark = {"name": "xml", "path": path, "keep_emitters": False}
    regions = scene_regions(dark)
    camera, lights, handle = _held_out(dark, regions, e)
    # kind: (description, handle, lightings Mitsuba renders, the same lightings as the methods take)
    setups = {"point": (dark, handle, lights, lights)}
    kinds = {setup_kind(name) for name in config["methods"]}
    if "file emitters" in kinds:
        lit = {**dark, "keep_emitters": True}
        setups["file emitters"] = (lit, SceneHandle(lit), [None], [LightScale(np.ones(3, np.float32))])
    if "environment" in kinds:
        opened = {**dark, "opening": config["environment"]["opening"]}
        face = int(config["wavelet_prt"]["envmaps"]["face_size"])
        cubes, envmaps = _environments(config["environment"], face)
        setups["environment"] = (opened, SceneHandle(opened), envmaps, cubes)
    t0 = time.perf_counter()
    per_setup, peers = {}, {}
    for kind, (desc, h, lightings, _) in setups.items():
        g = gbuffer(h, camera)
        refs, refs2 = _references(desc, h, camera, lightings, e)
        per_setup[kind] = (g, refs, refs2, h.object_names())
        peers[kind] = _pathtrace_ms(h, camera, lightings[0], e)
    names = handle.object_names()
    _say(f"{stem}: {len(names)} objects, references in {time.perf_counter() - t0:.1f} s")
    entry = {"file": path, "objects": names, "regions": regions, "camera": camera._asdict(),
             "lights": [np.asarray(x.position).tolist()[0] for x in lights], "noise_floor": {}, "methods": {},
             "pathtracer": peers}
    if "environment" in setups:  # what the opening took away: {object: "removed" or "a -> b triangles"}
        before = dict(zip(names, _face_counts(handle)))
        after = dict(zip(per_setup["environment"][3], _face_counts(setups["environment"][1])))
        entry["environment"] = {
            "opening": config["environment"]["opening"], "maps": list(config["environment"]["maps"]),
            "face_size": int(config["wavelet_prt"]["envmaps"]["face_size"]),
            "opened": {n: "removed" if n not in after else f"{k} -> {after[n]} triangles"
                       for n, k in before.items() if after.get(n) != k}}
    for kind, (g, refs, refs2, objects) in per_setup.items():
        entry["noise_floor"][kind] = _per_object(refs2, refs, g.object_id, objects, float(e["min_object_fraction"]))
    # one exposure per lighting setup: its first reference's 99th percentile shown at 0.8
    exposure = {kind: float(np.log2(0.8 / max(float(np.percentile(v[1][0], 99)), 1e-12))) for kind, v in per_setup.items()}
    panels = []
    for name in config["methods"]:
        kind = setup_kind(name)
        desc, h, _, lightings = setups[kind]
        g, refs, _, objects = per_setup[kind]
        m = REGISTRY[name]
        adapter = __import__(f"jprt.methods.{name}.data", fromlist=["data"])
        cfg = method_config(name, desc, regions, config[name])
        t0 = time.perf_counter()
        dataset = m.make_dataset(desc, cfg, progress=False)
        t1 = time.perf_counter()
        result = m.fit(dataset, cfg)
        t2 = time.perf_counter()
        evaluate = jax.jit(m.evaluator(result.params, cfg))
        if name in BAKED:  # the atlas G-buffer of the view, the bake's own lighting
            from jprt.render import lightmap

            inputs = lightmap.atlas_gbuffer(h, lightmap.Atlas(**dataset.atlas), camera)
            task = lightings
        else:
            inputs = adapter.task_inputs(h, dataset, camera)
            task = [adapter.task_lighting(h, dataset, result.params, cfg, light) for light in lightings]
        preds = [np.where(g.valid[..., None], np.asarray(evaluate(inputs, lit)), 0.0) for lit in task]
        timing = jeval.time_call(evaluate, inputs, task[0], repeats=int(e["timing_repeats"]))
        own = m.frame_flops(result.params, cfg, inputs, task[0]) if m.frame_flops else None
        roof = jeval.roofline(evaluate, inputs, task[0], frame_ms=timing["median_ms"], flops=own,
                              peak_gflops=config["_peak_gflops"])
        scores = _per_object(preds, refs, g.object_id, objects, float(e["min_object_fraction"]))
        for obj, v in scores.items():  # the error against the truth, the reference's own noise taken out:
            # E|p - r|^2 = |p - truth|^2 + |n|^2 and the two references differ by 2 |n|^2 (independent seeds)
            floor = entry["noise_floor"][kind].get(obj, {}).get("rel_rmse", 0.0)
            v["rel_rmse_noise_removed"] = float(np.sqrt(max(v["rel_rmse"] ** 2 - 0.5 * floor ** 2, 0.0)))
        worst = max(v["rel_rmse"] for v in scores.values())
        info = {k: v for k, v in result.info.items() if isinstance(v, (int, float, str))}
        report = getattr(result.info.get("report"), "_asdict", lambda: {})()
        meta = getattr(dataset, "meta", None)
        entry["methods"][name] = {
            "lighting": kind, "per_object": scores, "worst_rel_rmse": worst,
            "mean_rel_rmse": float(np.mean([v["rel_rmse"] for v in scores.values()])),
            "target_met": bool(worst < float(e["target"])), "frame_ms": timing["median_ms"],
            "frame_flops": roof["frame_flops"], "frame_flops_source": "method" if own else "xla",
            "flops_fraction_of_peak": roof["flops_fraction_of_peak"],
            "speedup_vs_reference_render": peers[kind]["ms"] / timing["median_ms"],
            "frame_resolution": list(np.shape(preds[0])[:2]), "dataset_s": t1 - t0, "fit_s": t2 - t1,
            "info": info, "grouped_objects": report.get("grouped", {}), "skipped_objects": report.get("skipped", {}),
            "regions": meta.get("regions") if isinstance(meta, dict) else None}
        _say(f"  {name} ({kind}): worst object relative RMSE {worst:.3f}, mean "
             f"{entry['methods'][name]['mean_rel_rmse']:.3f}, frame {timing['median_ms']:.2f} ms (data {t1 - t0:.0f} s, "
             f"fit {t2 - t1:.0f} s)")
        show = lambda image: io.preview_pixels(image, exposure=exposure[kind])  # noqa: E731
        panels.append(np.concatenate([show(preds[0]), show(refs[0]), show(4.0 * np.abs(preds[0] - refs[0]))], axis=1))
    io.write_png(os.path.join(out, f"{stem}_side_by_side.png"), np.concatenate(panels, axis=0) / 255.0,
                 tonemapped=True)
    entry["side_by_side"] = (f"{stem}_side_by_side.png (a row per method, in config order: prediction | reference "
                             "| 4x |difference| under its first held-out lighting, one exposure per lighting setup)")
    return entry


def main(config: dict) -> dict:
    """Run every scene; write ``report.json`` and the side-by-side images to
    ``<output.dir>/<config hash>/``; returns the report."""
    digest = config_hash(config)
    out = os.path.abspath(os.path.join(config["output"]["dir"], digest))
    os.makedirs(out, exist_ok=True)
    save_resolved(config, out)
    folder = config["assets"] or SHARED_SCENES
    config = {**config, "_peak_gflops": jeval.matmul_peak_gflops()}  # measured once, in this run
    report = {"config_hash": digest, "matmul_peak_gflops": None, "scenes": {}, "not_run": dict(NOT_RUN)}
    t0 = time.perf_counter()
    for rel in config["scenes"]:
        path = os.path.join(folder, rel)
        if not os.path.isfile(path):
            raise FileNotFoundError(f"scene file not found: {path} (set assets= to the folder of the Bitterli scenes)")
        report["scenes"][os.path.basename(os.path.dirname(path))] = run_scene(path, config, out)
    report["matmul_peak_gflops"] = config["_peak_gflops"]
    report["target_met_everywhere"] = all(m["target_met"] for s in report["scenes"].values()
                                          for m in s["methods"].values())
    report["total_s"] = time.perf_counter() - t0
    io.write_json(os.path.join(out, "report.json"), report)
    print(f"real_scenes report (report.json, side-by-side images) written to {out}")
    return report
