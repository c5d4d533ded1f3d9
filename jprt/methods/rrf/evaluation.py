"""What the RRF reports measure beyond the method contract (Ren et al. 2013, §5): the held-out
(view, light) pairs and their path-traced references, the timing frame and its four lights, the
single-MLP baseline of equal size, and the material-editing demo of Appendix B.

Renders with Mitsuba through ``jprt.render``; the model's math stays in ``model.py``.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from jprt import eval as jeval
from jprt.inputs import PointLights
from jprt.methods.rrf import data as rrf_data
from jprt.methods.rrf import model as rrf
from jprt.solve import adam

__all__ = ["NOISE_SEED_OFFSET", "held_out_pairs", "held_out_inputs", "held_out_references", "predict", "tail",
           "timing_camera", "four_light_inputs", "single_mlp", "material_edit", "light_times", "tree_stats",
           "timing_frame", "pathtracer", "reference_noise", "robustness",
           "worst_pixels", "tail_figure"]

#: Render seeds of a second reference set of the same pairs (the references' own noise), offset from the first's.
NOISE_SEED_OFFSET = 1_000_003


def held_out_pairs(config: dict):
    """Held-out cameras and point lights (``eval.n_views`` x ``eval.n_lights``): a Latin hypercube
    in the training boxes with the held-out seed ``eval.seed``, at ``eval.resolution``."""
    from jprt.render import cameras as cams
    from jprt.render.sampling import latin_hypercube

    d, e = rrf_data.resolve_regions(config["data"], config["scene"]), config["eval"]
    rng = np.random.default_rng(int(e["seed"]))
    lights = latin_hypercube(rng, e["n_lights"], d["light_lo"], d["light_hi"])
    origins = latin_hypercube(rng, e["n_views"], d["view_lo"], d["view_hi"])
    targets = np.asarray(d["view_target"]) + d["target_jitter"] * (2 * rng.random((len(origins), 3)) - 1)
    cameras = [cams.look_at(o, t, fov=d["fov"], width=e["resolution"], height=e["resolution"])
               for o, t in zip(origins, targets)]
    return cameras, [PointLights.create([p], [1.0, 1.0, 1.0]) for p in lights]


def held_out_inputs(config: dict):
    """(cameras, lightings, testset): the held-out pairs of ``held_out_pairs`` and their G-buffers
    (``render_dataset`` at 1 spp)."""
    from jprt.render.dataset import render_dataset

    cameras, lightings = held_out_pairs(config)
    testset = render_dataset(config["scene"], cameras, lightings, spp=1, seed=int(config["eval"]["seed"]),
                             gbuffers=True)
    return cameras, lightings, testset


def held_out_references(config: dict, cameras, lightings, testset, seed_offset: int = 0):
    """(direct, indirect) references of the held-out pairs along the pixel-centre rays at
    ``eval.reference_spp`` (``jprt.render.images.centre_rays``), 0 where the G-buffer is invalid;
    another ``seed_offset`` renders an independent set of the same pairs."""
    from jprt.render.images import centre_rays
    from jprt.render.scenes import SceneHandle

    e = config["eval"]
    handle = SceneHandle(config["scene"], lightings[0])
    refs, direct = [], []
    for k, item in enumerate(testset.items):
        valid = testset.gbuffer(item.camera).valid
        handle.set_lighting(lightings[item.lighting])
        rad = centre_rays(handle, cameras[item.camera], spp=int(e["reference_spp"]),
                          seed=int(e["seed"]) * 1009 + k + int(seed_offset))
        direct.append(np.where(valid[..., None], rad.direct, 0.0))
        refs.append(np.where(valid[..., None], rad.indirect, 0.0))
    return direct, refs


def predict(evaluate, testset) -> list:
    """The evaluator's image of every (view, light) item of ``testset``."""
    return [np.asarray(evaluate(testset.gbuffer(item.camera), testset.lighting(item.lighting)))
            for item in testset.items]


def tail(predictions, references, valid) -> dict:
    """Indirect RMSE and 99.9th percentile of |error| over every valid pixel and channel
    (``jprt.eval.score_images``), and their ratio: {"rmse", "p999_abs_error", "p999_over_rmse"}."""
    s = jeval.score_images(predictions, references, valid, scores=("indirect_rmse", "p999_abs_error"))
    return {"rmse": s["indirect_rmse"], "p999_abs_error": s["p999_abs_error"],
            "p999_over_rmse": s["p999_abs_error"] / s["indirect_rmse"]}


def timing_camera(config: dict, cameras):
    """The timing frame's camera: the first held-out view (``cameras[0]``) at ``eval.timing_resolution``."""
    from jprt.render import cameras as cams

    res = int(config["eval"]["timing_resolution"])
    c0 = cameras[0]
    return cams.look_at(c0.origin, c0.target, fov=c0.fov, width=res, height=res)


def four_light_inputs(config: dict) -> PointLights:
    """The four lights of the timing frame: Latin hypercube in the light box (seed 5), RGB
    intensities in [0.5, 1.5]."""
    from jprt.render.sampling import latin_hypercube

    rng = np.random.default_rng(5)
    d = rrf_data.resolve_regions(config["data"], config["scene"])
    return PointLights.create(latin_hypercube(rng, 4, d["light_lo"], d["light_hi"]), rng.uniform(0.5, 1.5, (4, 3)))


def single_mlp(data, cfg: dict, n_params: int, steps: int, testset) -> tuple[list, dict]:
    """One tanh MLP (two hidden layers, h1 = 2 h2) with about ``n_params`` weights, trained on the
    RRF's training samples of ``data`` with Adam (full LM is O(P^2) memory / O(P^3) per step and
    infeasible at this size on a CPU) for ``steps`` steps of 4096 samples; its predictions of
    ``testset`` (summed over each item's lights) and {"hidden", "n_params", "optimizer", "final_loss"}."""
    import optax

    from jprt.nn.mlp import count_parameters, mlp, with_scaling

    x = rrf.data_features(data, cfg["model"]["attributes"])
    d = x.shape[1]
    # params(h2) = (d + 1) 2 h2 + (2 h2 + 1) h2 + 4 h2 = 2 h2^2 + (2 d + 7) h2 + 3
    h2 = max(2, int(round((-(2 * d + 7) + math.sqrt((2 * d + 7) ** 2 + 8 * (n_params - 3))) / 4)))
    net = mlp((d, 2 * h2, h2, 3), activation="tanh", init="glorot")
    is_train = rrf.split_samples(len(data), float(cfg["data"]["val_fraction"]), int(cfg["train"]["seed"]))
    xt, yt = jnp.asarray(x[is_train]), jnp.asarray(data.indirect[is_train])
    params = with_scaling(net.init(jax.random.PRNGKey(0)), xt, yt)
    scale = params["scaling"]["out_halfrange"]

    def loss_fn(p, batch):
        xb, yb = batch
        return jnp.mean(jnp.square((net.apply(p, xb) - yb) / scale[None, :]))

    def sampler(key, step):
        idx = jax.random.randint(key, (4096,), 0, xt.shape[0])
        return xt[idx], yt[idx]

    schedule = optax.cosine_decay_schedule(3e-3, steps, alpha=0.03)
    result = adam.train(loss_fn, params, sampler, key=jax.random.PRNGKey(1), steps=steps, learning_rate=schedule,
                        eps=1e-8)
    trained = result.state.params
    preds = []
    for item in testset.items:
        gb, lights = testset.gbuffer(item.camera), testset.lighting(item.lighting)
        brdf = rrf.brdf_vector(gb.diffuse_albedo, gb.specular_albedo, gb.roughness)
        outs = [np.asarray(net.apply(trained, rrf.features(cfg["model"]["attributes"], gb.position, gb.view,
                                                           np.broadcast_to(p, gb.position.shape), gb.normal,
                                                           brdf))) * c
                for p, c in zip(np.asarray(lights.position), np.asarray(lights.intensity))]
        preds.append(np.where(gb.valid[..., None], np.sum(outs, axis=0), 0.0))
    return preds, {"hidden": [2 * h2, h2], "n_params": count_parameters(trained),
                   "optimizer": f"adam, {steps} steps of 4096 samples", "final_loss": float(result.losses[-1])}


def material_edit(scene, cfg: dict, demo: dict, e: dict, say=print) -> tuple[dict, list]:
    """Appendix B: a fixed-view RRF (``cfg``, a material-mode config) whose view inputs are
    replaced by one object's roughness and albedo, fitted on its own data; each edit of
    ``demo["edits"]`` ((roughness, albedo) pairs) rendered by the RRF and by Mitsuba at
    ``demo["reference_spp"]`` under one held-out light, at ``e["resolution"]`` (seed
    ``e["seed"]`` + 1). Returns (summary, side-by-side rows (label, reference, prediction))."""
    from jprt.methods.rrf import kdtree
    from jprt.render import cameras as cams
    from jprt.render.gbuffer import gbuffer
    from jprt.render.images import direct_indirect
    from jprt.render.sampling import latin_hypercube
    from jprt.render.scenes import SceneHandle, describe

    data = rrf_data.make_dataset(scene, cfg)
    params, info = rrf.fit(data, cfg)
    evaluate = rrf.evaluator(params, cfg)
    d = rrf_data.resolve_regions(cfg["data"], scene)
    mat = d["material"]
    camera = cams.look_at(mat["view_origin"], d["view_target"], fov=d["fov"], width=e["resolution"],
                          height=e["resolution"])
    rng = np.random.default_rng(int(e["seed"]) + 1)
    light = PointLights.create(latin_hypercube(rng, 1, d["light_lo"], d["light_hi"]), [1.0, 1.0, 1.0])
    base_desc = describe(scene)
    gb = gbuffer(SceneHandle(base_desc, light), camera)
    rows, results = [], []
    for roughness, albedo in demo["edits"]:
        desc = rrf_data.edit_description(base_desc, mat["object"], roughness, albedo)
        ref = direct_indirect(SceneHandle(desc, light), camera, spp=int(demo["reference_spp"]), seed=11).indirect
        pred = np.asarray(evaluate(rrf.EditInputs(gb, np.asarray([roughness, albedo], np.float32)), light))
        rmse = jeval.set_rmse([pred], [ref], [gb.valid])
        results.append({"roughness": roughness, "albedo": albedo, "rmse": rmse})
        rows.append((f"r={roughness:g} a={albedo:g}", ref, pred))
        say(f"material edit roughness {roughness:g}, albedo {albedo:g}: RMSE {rmse:.5f}")
    summary = {"object": mat["object"], "n_samples": len(data), "train_s": info["train_s"],
               "n_leaves": kdtree.KDTree(**{k: np.asarray(v) for k, v in params["tree"].items()}).n_leaves,
               "reference_spp": int(demo["reference_spp"]), "edits": results}
    return summary, rows


def light_times(evaluators: dict, gbuffer, one: PointLights, four: PointLights, repeats: int) -> dict:
    """Frame times of RRF evaluators with one light and with four: each of ``evaluators``
    ({name: (params, cfg)}) jitted and timed on ``gbuffer`` under ``one`` and ``four``
    interleaved (``jprt.eval.interleaved_times``, so the ratios are the programs'), with its FLOP
    counts (``model.frame_flops``). Returns {name: {"ms1", "ms1_min", "ms4", "ms4_min", "flops1",
    "flops4"}}."""
    dev = jax.device_put((gbuffer, one, four))
    fns = {name: jax.jit(rrf.evaluator(params, cfg)) for name, (params, cfg) in evaluators.items()}
    timed = jeval.interleaved_times(fns, dev[0], {1: dev[1], 4: dev[2]}, repeats)
    return {name: {"ms1": timed[(name, 1)]["median_ms"], "ms1_min": timed[(name, 1)]["min_ms"],
                   "ms4": timed[(name, 4)]["median_ms"], "ms4_min": timed[(name, 4)]["min_ms"],
                   "flops1": rrf.frame_flops(params, cfg, gbuffer, one),
                   "flops4": rrf.frame_flops(params, cfg, gbuffer, four)}
            for name, (params, cfg) in evaluators.items()}


def tree_stats(params, info: dict) -> dict:
    """The fit's kd-tree and networks: samples, leaves, depth, leaves per object, weights, tree
    levels, median per-leaf training and validation errors."""
    from jprt.methods.rrf import kdtree

    tree = kdtree.KDTree(**{k: np.asarray(v) for k, v in params["tree"].items()})
    return {"n_samples": int(info["n_samples"]), "n_leaves": tree.n_leaves, "max_depth": tree.max_depth,
            "leaves_per_object": kdtree.leaf_stats(tree)["leaves_per_object"],
            "n_params": rrf.parameter_count(params), "tree_levels": info["report"].levels,
            "leaf_train_error_median": float(np.nanmedian(info["leaf_train_error"])),
            "leaf_val_error_median": float(np.nanmedian(info["leaf_val_error"]))}


def timing_frame(config: dict, cameras, lightings) -> dict:
    """The timing frame: the first held-out view at ``eval.timing_resolution`` (``camera``) under
    its first light, a scene handle lit by it (``handle``), its G-buffer (``gbuffer``) and the
    G-buffer's own cost, Mitsuba's exact primary rays (``gbuffer_ms``, median of 3)."""
    from jprt.render.gbuffer import gbuffer
    from jprt.render.scenes import SceneHandle

    cam = timing_camera(config, cameras)
    handle = SceneHandle(config["scene"], lightings[0])
    gb = gbuffer(handle, cam)
    ms = jeval.time_call(lambda: gbuffer(handle, cam), repeats=3, warmup=0)["median_ms"]
    return {"camera": cam, "handle": handle, "gbuffer": gb, "gbuffer_ms": ms}


def pathtracer(handle, testset, cameras, lightings, timed_camera, repeats: int) -> jeval.PathTracer:
    """Mitsuba's own indirect along the same pixel-centre rays as the references (full minus
    direct, a seed unlike theirs) of the held-out pairs, and its time (median of ``repeats``) for
    the rays of ``timed_camera`` under the first light."""
    from jprt.render.images import centre_rays

    def render_at(spp):
        images = []
        for k, item in enumerate(testset.items):
            handle.set_lighting(lightings[item.lighting])
            images.append(centre_rays(handle, cameras[item.camera], spp=spp, seed=7777 + k).indirect)
        return images

    def time_at(spp):
        handle.set_lighting(lightings[0])
        centre_rays(handle, timed_camera, spp=1, seed=3)  # warm-up: Dr.Jit compiles its kernels for this ray count
        return jeval.time_call(lambda: centre_rays(handle, timed_camera, spp=spp, seed=3), repeats=int(repeats),
                               warmup=0)["median_ms"]

    return jeval.PathTracer(render_at, time_at, "Mitsuba llvm_ad_rgb along the pixel-centre rays, indirect = full "
                                                "(max_depth -1) minus direct (max_depth 2): both renders timed")


def reference_noise(config: dict, cameras, lightings, testset, held: jeval.HeldOut) -> dict:
    """The references' own noise: a second reference set of the held-out pairs (seeds offset by
    ``NOISE_SEED_OFFSET``, same spp) and (A - B) / sqrt 2 scored as an error image (``tail``: what
    a perfect predictor scores against one set); ``held``'s predictions against the mean of the
    two sets (half the noise variance, ``fit_against_mean_of_two``); and the p99.9 / RMSE ratio of
    an error of one relative size everywhere (the reference times seeded standard normals), which
    depends only on how the held-out radiance is spread."""
    refs, valid = held.references, held.valid
    second = held_out_references(config, cameras, lightings, testset, NOISE_SEED_OFFSET)[1]
    own = tail([a / math.sqrt(2.0) for a in refs], [b / math.sqrt(2.0) for b in second], valid)
    fit = tail(held.predictions, [(a + b) / 2 for a, b in zip(refs, second)], valid)
    rng = np.random.default_rng(0)
    relative = tail([a * rng.standard_normal(a.shape) for a in refs], [np.zeros_like(a) for a in refs], valid)
    return {"reference_spp": int(config["eval"]["reference_spp"]), **own,
            "uniform_relative_error_p999_over_rmse": relative["p999_over_rmse"], "fit_against_mean_of_two": fit}


def robustness(params, data, cfg: dict, info: dict, n: int, score) -> dict:
    """Table 3: the kd-tree fixed, every leaf refitted (LM, the same iterations) on ``n`` 70 %
    subsets and from ``n`` new initial weights (``model.refit_leaves``), each refit scored by
    ``score(params) -> RMSE``: the spread of the scores over subsets and over initialisations."""
    import time

    variants = [{"seed": 100 + i, "subset": 0.7} for i in range(n)] + [{"seed": 200 + i, "subset": 1.0}
                                                                       for i in range(n)]
    t0 = time.perf_counter()
    errs = [score(p) for p in rrf.refit_leaves(params, data, cfg, info, variants)]
    return {"std_subsets": float(np.std(errs[:n])), "std_inits": float(np.std(errs[n:])),
            "robustness": {"rmse_subsets": errs[:n], "rmse_inits": errs[n:], "mean_subsets": float(np.mean(errs[:n])),
                           "mean_inits": float(np.mean(errs[n:])), "seconds": time.perf_counter() - t0,
                           "protocol": "kd-tree fixed; all leaves refitted (LM, same iterations)"}}


def worst_pixels(predictions, references, gbuffers) -> dict:
    """Where the worst 0.1 % of a held-out set's errors lie: ``tail`` of the predictions over the
    G-buffers' valid pixels; the pixel channels at or above its 99.9th percentile counted by
    surface ("object/normal axis": the object id and the axis of the largest normal component)
    and by pair; each pair's |error| image (0 where invalid)."""
    valid = [np.asarray(g.valid, bool) for g in gbuffers]
    errors = [np.where(v[..., None], np.abs(p - r), 0.0) for p, r, v in zip(predictions, references, valid)]
    err = np.concatenate([e[v].ravel() for e, v in zip(errors, valid)])
    stats = tail(predictions, references, valid)
    p999 = stats["p999_abs_error"]
    axis = [np.argmax(np.abs(np.asarray(g.normal)), -1) for g in gbuffers]
    surface = np.concatenate([np.repeat(np.asarray(g.object_id)[v] * 10 + a[v], 3)
                              for g, a, v in zip(gbuffers, axis, valid)])
    ids, counts = np.unique(surface[err >= p999], return_counts=True)
    return {**stats, "worst_0.1%_by_surface": {f"{i // 10}/{i % 10}": int(c)
                                               for i, c in sorted(zip(ids, counts), key=lambda t: -t[1])},
            "worst_0.1%_by_pair": [int(np.sum(e >= p999)) for e in errors], "errors": errors}


def tail_figure(path: str, predictions, references, errors, counts, threshold: float, rows: int = 4,
                scale: int = 4) -> list[int]:
    """A PNG of the ``rows`` pairs with the most error channels (``counts``) at or above
    ``threshold``, one row each: reference | prediction | |error| (``errors``, white at 0.1) with
    those channels' pixels in red; returns the pairs shown, worst first."""
    import os

    from jprt import io
    from jprt.metrics import tonemap

    err = [e.max(-1) for e in errors]
    shown = [int(i) for i in np.argsort(counts, kind="stable")[::-1][:rows]]
    lines = []
    for i in shown:
        grey = np.clip(err[i] / 0.1, 0.0, 1.0)
        worst = err[i] >= threshold
        panel = np.stack([grey, np.where(worst, 0.0, grey), np.where(worst, 0.0, grey)], -1)
        panel[worst, 0] = 1.0
        lines.append(np.concatenate([np.asarray(tonemap(references[i])), np.asarray(tonemap(predictions[i])), panel],
                                    axis=1))
    image = np.concatenate(lines, axis=0)
    image = np.repeat(np.repeat(image, scale, axis=0), scale, axis=1)
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    io.write_png(path, image, tonemapped=True)
    return shown
