"""The RRF stages shared by rrf_cornell.py and rrf_glossy.py (Ren et al. 2013, §5), on
``jprt.runner``: held-out (view, light) references rendered by Mitsuba, Mitsuba as the
equal-error peer, and the paper's ablations (attribute sets, one MLP of equal size, Table 3
robustness, Fig. 6 training-set size, Fig. 7 training spp, four lights, Appendix B material edits).
"""

from __future__ import annotations

import math
import os

import jax
import jax.numpy as jnp
import numpy as np

from jprt import eval as jeval
from jprt import io
from jprt.inputs import PointLights
from jprt.methods import REGISTRY
from jprt.methods.rrf import data as rrf_data
from jprt.methods.rrf import kdtree
from jprt.methods.rrf import model as rrf
from jprt.runner import HeldOut, PathTracer
from jprt.solve import adam

METHOD = "rrf"
LABEL = "rrf"

EVAL_DEFAULTS = {
    "n_views": 4,              # held-out views x lights (Ren et al.: 20 x 20)
    "n_lights": 4,
    "resolution": 64,
    "reference_spp": 4096,     # Ren et al.: 16384 for the Cornell box
    "seed": 1000,
    "images": 4,               # side-by-side rows written
    "exposure": 0.0,
    "ablations": True,         # basic attributes, single MLP of equal size
    "robustness": 10,          # Table 3: subsets and initialisations (0: skip)
    "sizes": [0.25, 0.5],      # Fig. 6: fractions of the training set (1.0 is the main fit)
    "train_spp": [64, 128],    # Fig. 7: training-data spp (the main fit's spp is added)
    "equal_error_spp": [1, 2, 4, 8, 16, 32, 64, 128, 256, 512, 1024, 2048],
    "timing_resolution": 512,
    "timing_repeats": 20,
    "pathtrace_repeats": 1,    # renders at the equal-error spp take minutes; one is enough
    "single_mlp_steps": 3000,
    "reference_noise": True,   # a second reference set: the references' own noise (reference_noise)
}

# Ren et al. 2013: ~10M training samples (N_l = N_v = 200), 4096-spp training data, 20 x 20
# held-out pairs at 512 x 512 against 16384-spp references, leaves with >= 10x their weights in
# samples, every candidate fitted to convergence. For a machine with an accelerator.
PAPER_PRESET = {
    "data": {"n_lights": 200, "n_views": 200, "n_rays": 250, "spp": 4096},
    "tree": {"max_depth": 12, "min_samples": 6500, "max_leaves": 4096, "split_on": None},
    "train": {"max_iters": 200, "trial_iters": 200, "trial_samples": 0},
    "eval": {"n_views": 20, "n_lights": 20, "resolution": 512, "reference_spp": 16384, "robustness": 10,
             "sizes": [0.01, 0.1, 0.3], "train_spp": [256, 1024, 16384],
             "equal_error_spp": [2 ** k for k in range(15)]},
}


def config(output: str, overrides: dict) -> dict:
    """An RRF experiment's CONFIG: the method's sections, ``eval`` and ``output``."""
    from jprt.config import merge

    return merge({**REGISTRY["rrf"].default_config, "eval": EVAL_DEFAULTS, "output": {"dir": output}}, overrides)


def held_out_pairs(config: dict):
    """Held-out views and lights (Latin hypercube in the same boxes, a different seed)."""
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


def _predict(evaluate, testset) -> list:
    return [np.asarray(evaluate(testset.gbuffer(item.camera), testset.lighting(item.lighting)))
            for item in testset.items]


def rmse_p999(preds, refs, valid) -> tuple[float, float]:
    """Indirect RMSE and 99.9th percentile of |preds - refs| over every valid pixel and channel
    of the held-out set (an ablation's predictions against ``held.references``, ``held.valid``)."""
    err = np.concatenate([np.abs(np.asarray(q) - np.asarray(r))[np.asarray(v, bool)].ravel()
                          for q, r, v in zip(preds, refs, valid)])
    return jeval.set_rmse(preds, refs, valid), float(np.percentile(err, 99.9))


def _fit_tail(run, params, method_config) -> tuple[float, float]:
    """``rmse_p999`` of an ablation's model (``params`` under ``method_config``) on the run's
    held-out set."""
    held = run.state["held_out"]
    preds = _predict(rrf.evaluator(params, method_config), run.state["testset"])
    return rmse_p999(preds, held.references, held.valid)


def _rmse(run, params, method_config) -> float:
    return _fit_tail(run, params, method_config)[0]


# --------------------------------------------------------------------------------------------
# The runner's hooks


def held_out(run) -> HeldOut:
    """The held-out (view, light) pairs: references path traced along the pixel-centre rays at
    ``eval.reference_spp`` (``jprt.render.images.centre_rays``), and the RRF's predictions."""
    if run.config["data"]["mode"] == "material":
        raise ValueError("the RRF report evaluates view-mode RRFs; material editing is the material_edit stage")
    cameras, lightings, testset = held_out_inputs(run.config)
    run.state.update(testset=testset, cameras=cameras, lightings=lightings)
    valid = [testset.gbuffer(item.camera).valid for item in testset.items]
    direct, refs = held_out_references(run.config, cameras, lightings, testset)
    return HeldOut(_predict(run.evaluate, testset), refs, valid, direct,
                   [f"pair {k}" for k in range(len(testset))])


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


def timing_camera(config: dict, cameras):
    """The timing frame's camera: the first held-out view (``cameras[0]``) at
    ``eval.timing_resolution``."""
    from jprt.render import cameras as cams

    res = int(config["eval"]["timing_resolution"])
    c0 = cameras[0]
    return cams.look_at(c0.origin, c0.target, fov=c0.fov, width=res, height=res)


def frame(run):
    """The first held-out view at ``eval.timing_resolution`` under its first light."""
    from jprt.render.gbuffer import gbuffer
    from jprt.render.scenes import SceneHandle

    cam = timing_camera(run.config, run.state["cameras"])
    handle = SceneHandle(run.config["scene"], run.state["lightings"][0])
    run.state.update(timing_camera=cam, handle=handle)
    gb = gbuffer(handle, cam)
    run.state["timing_gbuffer"] = gb
    # the G-buffer's own cost (Mitsuba's exact primary rays), for the speedup with it included
    run.state["gbuffer_ms"] = jeval.time_call(lambda: gbuffer(handle, cam), repeats=3, warmup=0)["median_ms"]
    return gb, run.state["lightings"][0]


def pathtracer(run) -> PathTracer:
    """Mitsuba's own indirect along the same pixel-centre rays (full minus direct, a seed unlike
    the reference's) of the held-out pairs, and its time for the timing view's rays."""
    from jprt.render.images import centre_rays

    handle, testset = run.state["handle"], run.state["testset"]
    cameras, lightings = run.state["cameras"], run.state["lightings"]

    def render_at(spp):
        images = []
        for k, item in enumerate(testset.items):
            handle.set_lighting(lightings[item.lighting])
            images.append(centre_rays(handle, cameras[item.camera], spp=spp, seed=7777 + k).indirect)
        return images

    def time_at(spp):
        cam = run.state["timing_camera"]
        handle.set_lighting(lightings[0])
        centre_rays(handle, cam, spp=1, seed=3)  # warm-up: Dr.Jit compiles its kernels for this ray count
        return jeval.time_call(lambda: centre_rays(handle, cam, spp=spp, seed=3),
                               repeats=int(run.config["eval"]["pathtrace_repeats"]), warmup=0)["median_ms"]

    return PathTracer(render_at, time_at, "Mitsuba llvm_ad_rgb along the pixel-centre rays, indirect = full "
                                          "(max_depth -1) minus direct (max_depth 2): both renders timed")


# --------------------------------------------------------------------------------------------
# Stages


def tree_stats(run) -> dict:
    """kd-tree size, weights, per-leaf errors of the main fit."""
    params, info = run.result
    tree = kdtree.KDTree(**{k: np.asarray(v) for k, v in params["tree"].items()})
    return {"n_samples": int(info["n_samples"]), "n_leaves": tree.n_leaves, "max_depth": tree.max_depth,
            "leaves_per_object": kdtree.leaf_stats(tree)["leaves_per_object"],
            "n_params": rrf.parameter_count(params), "tree_levels": info["report"].levels,
            "leaf_train_error_median": float(np.nanmedian(info["leaf_train_error"])),
            "leaf_val_error_median": float(np.nanmedian(info["leaf_val_error"])),
            "reference_spp": int(run.config["eval"]["reference_spp"]),
            "test_pairs": [len(run.state["cameras"]), len(run.state["lightings"])]}


def four_light_inputs(config: dict) -> PointLights:
    """The four lights of the timing frame: Latin hypercube in the light box (seed 5), RGB
    intensities in [0.5, 1.5]."""
    from jprt.render.sampling import latin_hypercube

    rng = np.random.default_rng(5)
    d = rrf_data.resolve_regions(config["data"], config["scene"])
    return PointLights.create(latin_hypercube(rng, 4, d["light_lo"], d["light_hi"]), rng.uniform(0.5, 1.5, (4, 3)))


def interleaved_times(fns: dict, gb, lights: dict, repeats: int) -> dict:
    """Median and fastest wall time (ms) of each jitted function in ``fns`` under each lighting in
    ``lights``, one call at a time in turn (f1 l1, f1 l4, f2 l1, ...) ``repeats`` times after one
    warm-up call each, so that every (function, lighting) sees the same spells of machine load.
    Twenty consecutive calls of one frame are over in half a second, and on a shared 2-core VM
    their median moved between 14 and 29 ms from one such burst to the next (2026-12-02)."""
    times = {(f, n): [] for f in fns for n in lights}
    for r in range(max(1, int(repeats))):
        for f, fn in fns.items():
            for n, lighting in lights.items():
                times[(f, n)] += jeval.time_call(fn, gb, lighting, repeats=1, warmup=0 if r else 1)["times_ms"]
    return {key: {"median_ms": float(np.median(v)), "min_ms": float(np.min(v))} for key, v in times.items()}


def four_lights(run) -> dict:
    """Eq. 9 with four lights at the timing resolution (the first layer's light-free part is
    shared between lights in one leaf), with its roofline, timed interleaved with the one-light
    frame (``interleaved_times``: both see the same machine state, so their ratio is the program's);
    and the G-buffer's time (Mitsuba), with the speedup at equal error counted with it (the paper
    counts without)."""
    host = four_light_inputs(run.config)
    gb, one, four = jax.device_put((run.state["timing_gbuffer"], run.state["lightings"][0], host))
    fast = jax.jit(run.evaluate)
    timed = interleaved_times({"rrf": fast}, gb, {1: one, 4: four}, int(run.config["eval"]["timing_repeats"]))
    ms1, ms = timed[("rrf", 1)]["median_ms"], timed[("rrf", 4)]["median_ms"]
    flops = rrf.frame_flops(run.result.params, run.method_config, run.state["timing_gbuffer"], host)
    roof = jeval.roofline(fast, gb, four, frame_ms=ms, flops=flops, peak_gflops=run.summary["matmul_peak_gflops"])
    s, g = run.summary, run.state["gbuffer_ms"]
    out = {"frame_ms_4lights": ms, "frame_ms_4lights_min": timed[("rrf", 4)]["min_ms"],
           "frame_ms_1light_interleaved": ms1, "frame_ms_1light_interleaved_min": timed[("rrf", 1)]["min_ms"],
           "frame_ms_4lights_over_1light": ms / ms1,
           "frame_flops_4lights": flops, "flops_fraction_of_peak_4lights": roof["flops_fraction_of_peak"],
           # the floor under the time ratio: the light-free part of the first layer is shared only
           # between lights in one leaf (``rrf.frame_flops``)
           "frame_flops_4lights_over_1light": flops / s["frame_flops"] if s.get("frame_flops") else None,
           "gbuffer_ms": g}
    if s.get("pathtrace_ms_equal_error"):
        out["speedup_equal_error_with_gbuffer"] = s["pathtrace_ms_equal_error"] / (s["frame_ms"] + g)
    run.say(f"4 lights {ms:.2f} ms, one light {ms1:.2f} ms, interleaved ({ms / ms1:.2f}x); G-buffer {g:.1f} ms")
    return out


#: ``tree.split_on`` without the light: every leaf serves every light (``split_rule_ablation``).
NO_LIGHT_SPLIT = ["position", "view", "normal", "brdf"]


def split_rule_ablation(run) -> dict:
    """The kd-tree's split rule: the paper's (every axis, ``tree.split_on`` None) against the
    light barred from the splits, whichever the config does not use, same samples. Held-out RMSE
    and 99.9th-percentile error, leaves, and the timing frame with one and four lights for both
    models, timed interleaved in this stage (``interleaved_times``)."""
    if not run.config["eval"]["ablations"]:
        return {}
    mine = run.method_config["tree"].get("split_on")
    own = rrf.ATTRIBUTE_SETS[run.method_config["model"]["attributes"]]  # NO_LIGHT_SPLIT on this set's attributes
    other = [a for a in NO_LIGHT_SPLIT if a in own] if mine is None else None
    cfg = run.with_config({"tree": {"split_on": other}})
    p, _ = rrf.fit(run.dataset, cfg)
    rmse, p999 = _fit_tail(run, p, cfg)
    host = (run.state["timing_gbuffer"], run.state["lightings"][0], four_light_inputs(run.config))
    dev = jax.device_put(host)
    fns = {"config": jax.jit(run.evaluate), "other": jax.jit(rrf.evaluator(p, cfg))}
    timed = interleaved_times(fns, dev[0], {1: dev[1], 4: dev[2]}, int(run.config["eval"]["timing_repeats"]))
    ms = {key: v["median_ms"] for key, v in timed.items()}
    flops = {n: rrf.frame_flops(p, cfg, host[0], lights) for n, lights in ((1, host[1]), (4, host[2]))}
    splits = np.asarray(p["tree"]["axis"])
    light = rrf.split_dims({**cfg, "tree": {"split_on": ["light"]}})  # the light's columns of x
    out = {"split_on": other, "rmse": rmse, "p999_abs_error": p999, "p999_over_rmse": p999 / rmse,
           "n_leaves": kdtree.KDTree(**p["tree"]).n_leaves,
           "splits_on_light": int(np.isin(splits, light).sum()), "splits": int(np.sum(splits >= 0)),
           "frame_ms": ms[("other", 1)], "frame_ms_4lights": ms[("other", 4)],
           "frame_ms_4lights_over_1light": ms[("other", 4)] / ms[("other", 1)],
           "frame_flops": flops[1], "frame_flops_4lights": flops[4],
           "config_frame_ms": ms[("config", 1)], "config_frame_ms_4lights": ms[("config", 4)],
           "config_frame_ms_4lights_over_1light": ms[("config", 4)] / ms[("config", 1)]}
    run.say(f"split_on {other}: RMSE {rmse:.5f}, p99.9 / RMSE {out['p999_over_rmse']:.1f}, {out['n_leaves']} leaves; "
            f"frames {out['frame_ms']:.1f} / {out['frame_ms_4lights']:.1f} ms against this config's "
            f"{out['config_frame_ms']:.1f} / {out['config_frame_ms_4lights']:.1f} ms (1 / 4 lights, interleaved)")
    return {"split_rule_ablation": out}


def sampling_ablation(run) -> dict:
    """The training rays: uniform over the screen (``data.oversample`` 1, the paper's) against
    the surface-balanced draw (the default), same budget, RMSE and 99.9th-percentile error."""
    if not run.config["eval"]["ablations"]:
        return {}
    over = int(run.method_config["data"]["oversample"])
    other = 1 if over > 1 else 8
    cfg = run.with_config({"data": {"oversample": other}})
    p, _ = rrf.fit(rrf_data.make_dataset(run.config["scene"], cfg), cfg)
    rmse, p999 = _fit_tail(run, p, cfg)
    out = {"oversample": other, "rmse": rmse, "p999_abs_error": p999}
    run.say(f"training rays with oversample {other}: RMSE {out['rmse']:.5f}, p99.9 {out['p999_abs_error']:.4f}")
    return {"sampling_ablation": out}


def attribute_ablation(run) -> dict:
    """Fig. 3: basic (x_p, v, l) against augmented (x_p, v, l, n, a) attributes, the same
    samples and split rule; their held-out RMSE, and their 99.9th-percentile error beside it when
    the config's own set is neither (the `small` config's "diffuse", augmented without v)."""
    if not run.config["eval"]["ablations"]:
        return {}
    out = {}
    own = run.method_config["model"]["attributes"]
    for attrs in ("basic", "augmented"):
        key = "rmse_basic_attributes" if attrs == "basic" else "rmse_augmented"
        if attrs == own:
            out[key] = run.summary["indirect_rmse"]
            continue
        split_on = run.method_config["tree"].get("split_on")  # the config's rule, on this set's attributes
        kept = None if split_on is None else [a for a in split_on if a in rrf.ATTRIBUTE_SETS[attrs]]
        cfg = run.with_config({"model": {"attributes": attrs}, "tree": {"split_on": kept}})
        p, _ = rrf.fit(run.dataset, cfg)
        if own in ("basic", "augmented"):
            out[key] = _rmse(run, p, cfg)
        else:
            out[key], p999 = _fit_tail(run, p, cfg)
            out[key.replace("rmse_", "p999_over_rmse_")] = p999 / out[key]
        out[key.replace("rmse_", "n_leaves_")] = kdtree.KDTree(**p["tree"]).n_leaves
        run.say(f"{attrs} attributes: RMSE {out[key]:.5f}")
    return out


def single_mlp(run) -> dict:
    """One tanh MLP (two hidden layers, h1 = 2 h2) with about as many weights as the whole RRF,
    trained on the same samples with Adam (full LM is O(P^2) memory / O(P^3) per step and
    infeasible at this size on a CPU); evaluated on the same test set."""
    from jprt.nn.mlp import count_parameters, mlp, with_scaling

    import optax

    if not run.config["eval"]["ablations"]:
        return {}
    cfg, data, steps = run.method_config, run.dataset, int(run.config["eval"]["single_mlp_steps"])
    n_params = rrf.parameter_count(run.result.params)
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
    testset = run.state["testset"]
    for item in testset.items:
        gb, lights = testset.gbuffer(item.camera), testset.lighting(item.lighting)
        brdf = rrf.brdf_vector(gb.diffuse_albedo, gb.specular_albedo, gb.roughness)
        outs = [np.asarray(net.apply(trained, rrf.features(cfg["model"]["attributes"], gb.position, gb.view,
                                                           np.broadcast_to(p, gb.position.shape), gb.normal,
                                                           brdf))) * c
                for p, c in zip(np.asarray(lights.position), np.asarray(lights.intensity))]
        preds.append(np.where(gb.valid[..., None], np.sum(outs, axis=0), 0.0))
    held = run.state["held_out"]
    single = {"rmse": jeval.set_rmse(preds, held.references, held.valid), "hidden": [2 * h2, h2],
              "n_params": count_parameters(trained), "optimizer": f"adam, {steps} steps of 4096 samples",
              "final_loss": float(result.losses[-1])}
    run.say(f"one MLP {single['hidden']} ({single['n_params']} weights vs {n_params}): RMSE {single['rmse']:.5f}")
    return {"rmse_single_mlp_same_params": single["rmse"], "single_mlp": single}


def robustness(run) -> dict:
    """Table 3: the kd-tree fixed, every leaf refitted on 70 % subsets and from new initial weights."""
    import time

    n_rob = int(run.config["eval"]["robustness"])
    if not n_rob:
        return {}
    variants = [{"seed": 100 + i, "subset": 0.7} for i in range(n_rob)]
    variants += [{"seed": 200 + i, "subset": 1.0} for i in range(n_rob)]
    t0 = time.perf_counter()
    params, info = run.result
    refits = rrf.refit_leaves(params, run.dataset, run.method_config, info, variants)
    errs = [_rmse(run, p, run.method_config) for p in refits]
    out = {"std_subsets": float(np.std(errs[:n_rob])), "std_inits": float(np.std(errs[n_rob:])),
           "robustness": {"rmse_subsets": errs[:n_rob], "rmse_inits": errs[n_rob:],
                          "mean_subsets": float(np.mean(errs[:n_rob])), "mean_inits": float(np.mean(errs[n_rob:])),
                          "seconds": time.perf_counter() - t0,
                          "protocol": "kd-tree fixed; all leaves refitted (LM, same iterations)"}}
    run.say(f"robustness: std over subsets {out['std_subsets']:.5f}, over inits {out['std_inits']:.5f}")
    return out


def training_size(run) -> dict:
    """Fig. 6: accuracy against the fraction of the training set."""
    e = run.config["eval"]
    if not e["sizes"]:
        return {}
    sizes = sorted(set(float(s) for s in e["sizes"]) | {1.0})
    errs = []
    for s in sizes:
        if s == 1.0:
            errs.append(run.summary["indirect_rmse"])
            continue
        cfg = run.with_config({"train": {"subset": s}})
        errs.append(_rmse(run, rrf.fit(run.dataset, cfg).params, cfg))
    n_train = [int(round(s * run.result.info["is_train"].sum())) for s in sizes]
    jeval.plot_series(os.path.join(run.out, "fig6_training_size.png"), {"RRF": (n_train, errs)},
                      xlabel="training samples", ylabel="indirect RMSE", title="accuracy vs training-set size",
                      logx=True)
    return {"fig6_training_size": {"n_train": n_train, "rmse": errs}}


def training_spp(run) -> dict:
    """Fig. 7: accuracy against the samples per pixel of the training data."""
    e = run.config["eval"]
    if not e["train_spp"]:
        return {}
    spps = sorted(set(int(s) for s in e["train_spp"]) | {int(run.method_config["data"]["spp"])})
    errs = []
    for s in spps:
        if s == int(run.method_config["data"]["spp"]):
            errs.append(run.summary["indirect_rmse"])
            continue
        cfg = run.with_config({"data": {"spp": s}})
        errs.append(_rmse(run, rrf.fit(rrf_data.make_dataset(run.config["scene"], cfg), cfg).params, cfg))
    jeval.plot_series(os.path.join(run.out, "fig7_training_spp.png"), {"RRF": (spps, errs)},
                      xlabel="training spp", ylabel="indirect RMSE", title="accuracy vs training-data spp", logx=True)
    return {"fig7_training_spp": {"spp": spps, "rmse": errs}}


def material_edit(run) -> dict:
    """Appendix B: a fixed-view RRF whose view inputs are replaced by one object's roughness and
    albedo; a few edits rendered by the RRF and by Mitsuba (same held-out light), side by side
    with their RMSE, in the ``material_edit/`` folder. ``config['material_demo']`` holds them."""
    from jprt.render import cameras as cams
    from jprt.render.gbuffer import gbuffer
    from jprt.render.images import direct_indirect
    from jprt.render.sampling import latin_hypercube
    from jprt.render.scenes import SceneHandle, describe

    demo = run.config["material_demo"]
    if not demo["enabled"]:
        return {}
    cfg = run.with_config({"data": {**demo["data"], "mode": "material"}})
    out = os.path.join(run.out, "material_edit")
    os.makedirs(out, exist_ok=True)
    data = rrf_data.make_dataset(run.config["scene"], cfg)
    params, info = rrf.fit(data, cfg)
    evaluate = rrf.evaluator(params, cfg)
    d, e = rrf_data.resolve_regions(cfg["data"], run.config["scene"]), run.config["eval"]
    mat = d["material"]
    camera = cams.look_at(mat["view_origin"], d["view_target"], fov=d["fov"], width=e["resolution"],
                          height=e["resolution"])
    rng = np.random.default_rng(int(e["seed"]) + 1)
    light = PointLights.create(latin_hypercube(rng, 1, d["light_lo"], d["light_hi"]), [1.0, 1.0, 1.0])
    base_desc = describe(run.config["scene"])
    gb = gbuffer(SceneHandle(base_desc, light), camera)
    rows, results = [], []
    for roughness, albedo in demo["edits"]:
        desc = rrf_data.edit_description(base_desc, mat["object"], roughness, albedo)
        ref = direct_indirect(SceneHandle(desc, light), camera, spp=int(demo["reference_spp"]), seed=11).indirect
        pred = np.asarray(evaluate(rrf.EditInputs(gb, np.asarray([roughness, albedo], np.float32)), light))
        rmse = jeval.set_rmse([pred], [ref], [gb.valid])
        results.append({"roughness": roughness, "albedo": albedo, "rmse": rmse})
        rows.append((f"r={roughness:g} a={albedo:g}", ref, pred))
        run.say(f"material edit roughness {roughness:g}, albedo {albedo:g}: RMSE {rmse:.5f}")
    jeval.side_by_side(os.path.join(out, "material_edit.png"), rows, exposure=float(e["exposure"]))
    summary = {"object": mat["object"], "n_samples": len(data), "train_s": info["train_s"],
               "n_leaves": kdtree.KDTree(**{k: np.asarray(v) for k, v in params["tree"].items()}).n_leaves,
               "reference_spp": int(demo["reference_spp"]), "edits": results}
    io.write_json(os.path.join(out, "summary.json"), summary)
    return {"material_edit": summary}


#: render seeds of the second reference set (``reference_noise``), offset from the first's
NOISE_SEED_OFFSET = 1_000_003


def reference_noise(run) -> dict:
    """The references' own noise in the report's statistics: a second reference set of the same
    held-out pairs (other seeds, same ``eval.reference_spp``), and (A - B) / sqrt 2 scored as an
    error image: its RMSE, 99.9th percentile and their ratio are what a perfect predictor scores
    against one set. Beside them, this fit against the mean of the two sets (half the noise
    variance). Monte Carlo noise is heavier-tailed than a Gaussian's (3.3x): brighter pixels are
    noisier. A yardstick beside them: the ratio of an error of one relative size everywhere (the
    reference times seeded standard normals), which depends only on how the held-out radiance is
    spread. Skipped with ``eval.reference_noise`` False."""
    if not run.config["eval"]["reference_noise"]:
        return {}
    held = run.state["held_out"]
    refs, valid = held.references, held.valid
    second = held_out_references(run.config, run.state["cameras"], run.state["lightings"], run.state["testset"],
                                 NOISE_SEED_OFFSET)[1]
    rmse, p999 = rmse_p999([a / math.sqrt(2.0) for a in refs], [b / math.sqrt(2.0) for b in second], valid)
    fit_rmse, fit_p999 = rmse_p999(held.predictions, [(a + b) / 2 for a, b in zip(refs, second)], valid)
    rng = np.random.default_rng(0)
    relative = rmse_p999([a * rng.standard_normal(a.shape) for a in refs], [np.zeros_like(a) for a in refs], valid)
    out = {"reference_spp": int(run.config["eval"]["reference_spp"]), "rmse": rmse, "p999_abs_error": p999,
           "p999_over_rmse": p999 / rmse, "uniform_relative_error_p999_over_rmse": relative[1] / relative[0],
           "fit_against_mean_of_two": {
               "rmse": fit_rmse, "p999_abs_error": fit_p999, "p999_over_rmse": fit_p999 / fit_rmse}}
    run.say(f"reference noise at {out['reference_spp']} spp: RMSE {rmse:.5f}, p99.9 / RMSE {p999 / rmse:.2f} (an "
            f"error of one relative size everywhere: {relative[1] / relative[0]:.2f}); "
            f"the fit against the mean of two sets: RMSE {fit_rmse:.5f}, p99.9 / RMSE {fit_p999 / fit_rmse:.2f}")
    return {"reference_noise": out}


#: The stages of an RRF report, in order.
STAGES = [tree_stats, reference_noise, four_lights, split_rule_ablation, sampling_ablation, attribute_ablation, single_mlp, robustness,
          training_size, training_spp]
