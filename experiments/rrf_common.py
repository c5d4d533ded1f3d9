"""The RRF experiment pipeline shared by rrf_cornell.py and rrf_glossy.py (Ren et al. 2013, §5).

render training samples -> fit the kd-tree of RRFs -> render held-out (view, light) references
-> RMSE of the indirect images -> ablations (attribute sets, one MLP of equal size, Table 3
robustness, Fig. 6 training-set size, Fig. 7 training spp) -> equal-error spp and timings ->
report (summary.json, side-by-side images, plots) under ``output.dir/<config hash>/``.
"""

from __future__ import annotations

import math
import os
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

from jprt import eval as jeval
from jprt import io
from jprt.config import config_hash, merge, save_resolved
from jprt.methods import kdtree, rrf
from jprt.render import cameras as cams
from jprt.render.dataset import render_dataset
from jprt.render.gbuffer import gbuffer
from jprt.render.images import direct_indirect
from jprt.render.lights import PointLights
from jprt.render.sampling import latin_hypercube
from jprt.render.scenes import SceneHandle
from jprt.solve import adam

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
    "timing_repeats": 10,
    "pathtrace_repeats": 1,    # renders at the equal-error spp take minutes; one is enough
    "single_mlp_steps": 3000,
}

# Ren et al. 2013: ~10M training samples (N_l = N_v = 200), 4096-spp training data, 20 x 20
# held-out pairs at 512 x 512 against 16384-spp references, leaves with >= 10x their weights in
# samples, every candidate fitted to convergence. For a machine with an accelerator.
PAPER_PRESET = {
    "data": {"n_lights": 200, "n_views": 200, "n_rays": 250, "spp": 4096},
    "tree": {"max_depth": 12, "min_samples": 6500, "max_leaves": 4096},
    "train": {"max_iters": 200, "trial_iters": 200, "trial_samples": 0},
    "eval": {"n_views": 20, "n_lights": 20, "resolution": 512, "reference_spp": 16384, "robustness": 10,
             "sizes": [0.01, 0.1, 0.3], "train_spp": [256, 1024, 16384],
             "equal_error_spp": [2 ** k for k in range(15)]},
}


def _say(msg: str) -> None:
    print(f"[rrf] {msg}", file=sys.stderr, flush=True)


def _test_pairs(config: dict):
    """Held-out views and lights (Latin hypercube in the same boxes, a different seed)."""
    d, e = config["data"], config["eval"]
    rng = np.random.default_rng(int(e["seed"]))
    lights = latin_hypercube(rng, e["n_lights"], d["light_lo"], d["light_hi"])
    if d["mode"] == "material":
        cameras = [cams.look_at(d["material"]["view_origin"], d["view_target"], fov=d["fov"],
                                width=e["resolution"], height=e["resolution"])]
    else:
        origins = latin_hypercube(rng, e["n_views"], d["view_lo"], d["view_hi"])
        targets = np.asarray(d["view_target"]) + d["target_jitter"] * (2 * rng.random((len(origins), 3)) - 1)
        cameras = [cams.look_at(o, t, fov=d["fov"], width=e["resolution"], height=e["resolution"])
                   for o, t in zip(origins, targets)]
    return cameras, [PointLights.create([p], [1.0, 1.0, 1.0]) for p in lights]


def _predict_set(params, config, testset):
    evaluate = rrf.evaluator(params, config)
    preds, refs, valids = [], [], []
    for k, item in enumerate(testset.items):
        gb = testset.gbuffer(item.camera)
        preds.append(np.asarray(evaluate(gb, testset.lighting(item.lighting))))
        refs.append(testset.radiance(k)["indirect"])
        valids.append(gb.valid)
    return preds, refs, valids


def _rmse(params, config, testset) -> float:
    return jeval.set_rmse(*_predict_set(params, config, testset))


def _single_mlp(data, config, n_params: int, testset, steps: int) -> dict:
    """One tanh MLP (two hidden layers, h1 = 2 h2) with about ``n_params`` weights, trained on
    the same samples with Adam (full LM is O(P^2) memory / O(P^3) per step and infeasible at this
    size on a CPU); evaluated on the same test set."""
    from jprt.nn.mlp import count_parameters, mlp, with_scaling

    x = rrf._data_features(data, config["model"]["attributes"])
    d = x.shape[1]
    # params(h2) = (d + 1) 2 h2 + (2 h2 + 1) h2 + 4 h2 = 2 h2^2 + (2 d + 7) h2 + 3
    h2 = max(2, int(round((-(2 * d + 7) + math.sqrt((2 * d + 7) ** 2 + 8 * (n_params - 3))) / 4)))
    net = mlp((d, 2 * h2, h2, 3), activation="tanh", init="glorot")
    is_train = rrf._split(len(data), float(config["data"]["val_fraction"]), int(config["train"]["seed"]))
    xt, yt = jnp.asarray(x[is_train]), jnp.asarray(data.indirect[is_train])
    params = with_scaling(net.init(jax.random.PRNGKey(0)), xt, yt)
    scale = params["scaling"]["out_halfrange"]

    def loss_fn(p, batch):
        xb, yb = batch
        return jnp.mean(jnp.square((net.apply(p, xb) - yb) / scale[None, :]))

    def sampler(key, step):
        idx = jax.random.randint(key, (4096,), 0, xt.shape[0])
        return xt[idx], yt[idx]

    import optax

    schedule = optax.cosine_decay_schedule(3e-3, steps, alpha=0.03)
    result = adam.train(loss_fn, params, sampler, key=jax.random.PRNGKey(1), steps=steps, learning_rate=schedule,
                        eps=1e-8, progress=True)
    trained = result.state.params

    def evaluate(gb, lights):
        outs = []
        for p, c in zip(np.asarray(lights.position), np.asarray(lights.intensity)):
            feats = rrf.features(config["model"]["attributes"], gb.position, gb.view,
                                 np.broadcast_to(p, gb.position.shape), gb.normal, rrf._brdf_vector(gb))
            outs.append(np.asarray(net.apply(trained, feats)) * c)
        return np.where(gb.valid[..., None], np.sum(outs, axis=0), 0.0)

    preds, refs, valids = [], [], []
    for k, item in enumerate(testset.items):
        gb = testset.gbuffer(item.camera)
        preds.append(evaluate(gb, testset.lighting(item.lighting)))
        refs.append(testset.radiance(k)["indirect"])
        valids.append(gb.valid)
    return {"rmse": jeval.set_rmse(preds, refs, valids), "hidden": [2 * h2, h2],
            "n_params": count_parameters(trained), "optimizer": f"adam, {steps} steps of 4096 samples",
            "final_loss": float(result.losses[-1])}


def run(config: dict) -> dict:
    """Run the whole RRF experiment for ``config`` (``rrf.DEFAULT_CONFIG`` + ``eval`` + ``output``);
    returns the summary dict (also written as summary.json)."""
    t_start = time.perf_counter()
    config = merge({**rrf.DEFAULT_CONFIG, "eval": EVAL_DEFAULTS, "output": {"dir": "results/rrf"}},
                   config)
    out = os.path.abspath(os.path.join(config["output"]["dir"], config_hash(config)))
    os.makedirs(out, exist_ok=True)
    save_resolved(config, out)
    e = config["eval"]
    scene = config["scene"]
    summary: dict = {"config_hash": config_hash(config), "device": str(jax.devices()[0]),
                     "backend": jax.default_backend()}

    # 1. Training data and the main fit.
    t0 = time.perf_counter()
    data = rrf.make_dataset(scene, config)
    summary["n_samples"] = len(data)
    summary["data_s"] = time.perf_counter() - t0
    _say(f"{len(data)} training samples ({summary['data_s']:.1f} s incl. rendering if not cached)")
    params, info = rrf.fit(data, config)
    io.save_checkpoint(os.path.join(out, "model.npz"), params, meta={"config_hash": summary["config_hash"]})
    tree = kdtree.KDTree(**{k: np.asarray(v) for k, v in params["tree"].items()})
    summary.update({"train_s": info.train_s, "n_leaves": tree.n_leaves, "max_depth": tree.max_depth,
                    "leaves_per_object": kdtree.leaf_stats(tree)["leaves_per_object"],
                    "n_params": rrf.parameter_count(params), "model_bytes": rrf.model_bytes(params),
                    "tree_levels": info.report.levels,
                    "leaf_train_error_median": float(np.nanmedian(info.leaf_train_error)),
                    "leaf_val_error_median": float(np.nanmedian(info.leaf_val_error))})

    # 2. Held-out references.
    cameras, lightings = _test_pairs(config)
    if config["data"]["mode"] == "material":
        raise ValueError("run() evaluates view-mode RRFs; material editing has its own demo (material_demo)")
    t0 = time.perf_counter()
    testset = render_dataset(scene, cameras, lightings, spp=int(e["reference_spp"]), seed=int(e["seed"]),
                             gbuffers=True)
    summary["reference_render_s"] = time.perf_counter() - t0
    summary["reference_spp"] = int(e["reference_spp"])
    summary["test_pairs"] = [len(cameras), len(lightings)]
    summary["test_resolution"] = int(e["resolution"])
    preds, refs, valids = _predict_set(params, config, testset)
    summary["indirect_rmse"] = jeval.set_rmse(preds, refs, valids)
    summary["indirect_relative_rmse"] = summary["indirect_rmse"] / float(
        np.sqrt(np.mean([np.mean(np.square(r[v])) for r, v in zip(refs, valids)])))
    _say(f"indirect RMSE on {len(preds)} held-out pairs: {summary['indirect_rmse']:.5f} "
         f"(relative {summary['indirect_relative_rmse']:.3f})")
    rows = [(f"pair {k}", refs[k], preds[k]) for k in range(min(int(e["images"]), len(preds)))]
    jeval.side_by_side(os.path.join(out, "side_by_side.png"), rows, exposure=float(e["exposure"]))
    for k, (_, ref, pred) in enumerate(rows):
        io.write_exr(os.path.join(out, f"pair{k:02d}_reference.exr"), ref)
        io.write_exr(os.path.join(out, f"pair{k:02d}_rrf.exr"), pred)
        gb = testset.gbuffer(testset.items[k].camera)
        direct = testset.radiance(k)["direct"]
        io.write_png(os.path.join(out, f"pair{k:02d}_final_rrf.png"), direct + pred, exposure=float(e["exposure"]))
        io.write_png(os.path.join(out, f"pair{k:02d}_final_reference.png"), direct + ref,
                     exposure=float(e["exposure"]))
        del gb
    summary["rmse_augmented"] = summary["indirect_rmse"] if config["model"]["attributes"] == "augmented" else None

    # 3. Ablations.
    if e["ablations"]:
        for attrs in ("basic", "augmented"):
            if attrs == config["model"]["attributes"]:
                summary[f"rmse_{'basic_attributes' if attrs == 'basic' else 'augmented'}"] = summary["indirect_rmse"]
                continue
            cfg = merge(config, {"model": {"attributes": attrs}})
            p, _ = rrf.fit(data, cfg)
            key = "rmse_basic_attributes" if attrs == "basic" else "rmse_augmented"
            summary[key] = _rmse(p, cfg, testset)
            summary[key.replace("rmse_", "n_leaves_")] = kdtree.KDTree(**p["tree"]).n_leaves
            _say(f"{attrs} attributes: RMSE {summary[key]:.5f}")
        single = _single_mlp(data, config, summary["n_params"], testset, int(e["single_mlp_steps"]))
        summary["rmse_single_mlp_same_params"] = single["rmse"]
        summary["single_mlp"] = single
        _say(f"one MLP {single['hidden']} ({single['n_params']} weights vs {summary['n_params']}): "
             f"RMSE {single['rmse']:.5f}")

    # 4. Robustness (Table 3): fixed tree, leaves refitted on 70 % subsets / from new initial weights.
    n_rob = int(e["robustness"])
    if n_rob:
        variants = [{"seed": 100 + i, "subset": 0.7} for i in range(n_rob)]
        variants += [{"seed": 200 + i, "subset": 1.0} for i in range(n_rob)]
        t0 = time.perf_counter()
        refits = rrf.refit_leaves(params, data, config, info, variants)
        errs = [_rmse(p, config, testset) for p in refits]
        summary["std_subsets"] = float(np.std(errs[:n_rob]))
        summary["std_inits"] = float(np.std(errs[n_rob:]))
        summary["robustness"] = {"rmse_subsets": errs[:n_rob], "rmse_inits": errs[n_rob:],
                                 "mean_subsets": float(np.mean(errs[:n_rob])),
                                 "mean_inits": float(np.mean(errs[n_rob:])), "seconds": time.perf_counter() - t0,
                                 "protocol": "kd-tree fixed; all leaves refitted (LM, same iterations)"}
        _say(f"robustness: std over subsets {summary['std_subsets']:.5f}, over inits {summary['std_inits']:.5f}")

    # 5. Fig. 6 (training-set size) and Fig. 7 (training spp).
    if e["sizes"]:
        sizes = sorted(set(float(s) for s in e["sizes"]) | {1.0})
        errs = []
        for s in sizes:
            if s == 1.0:
                errs.append(summary["indirect_rmse"])
                continue
            cfg = merge(config, {"train": {"subset": s}})
            p, _ = rrf.fit(data, cfg)
            errs.append(_rmse(p, cfg, testset))
        n_train = [int(round(s * info.is_train.sum())) for s in sizes]
        summary["fig6_training_size"] = {"n_train": n_train, "rmse": errs}
        jeval.plot_series(os.path.join(out, "fig6_training_size.png"), {"RRF": (n_train, errs)},
                          xlabel="training samples", ylabel="indirect RMSE", title="accuracy vs training-set size",
                          logx=True)
    if e["train_spp"]:
        spps = sorted(set(int(s) for s in e["train_spp"]) | {int(config["data"]["spp"])})
        errs = []
        for s in spps:
            if s == int(config["data"]["spp"]):
                errs.append(summary["indirect_rmse"])
                continue
            cfg = merge(config, {"data": {"spp": s}})
            p, _ = rrf.fit(rrf.make_dataset(scene, cfg), cfg)
            errs.append(_rmse(p, cfg, testset))
        summary["fig7_training_spp"] = {"spp": spps, "rmse": errs}
        jeval.plot_series(os.path.join(out, "fig7_training_spp.png"), {"RRF": (spps, errs)},
                          xlabel="training spp", ylabel="indirect RMSE", title="accuracy vs training-data spp",
                          logx=True)

    # 6. Equal-error spp: Mitsuba's own indirect images (full - direct, a seed unlike the reference's).
    handle = SceneHandle(scene, lightings[0])

    def render_at(spp):
        images = []
        for item in testset.items:
            handle.set_lighting(lightings[item.lighting])
            images.append(direct_indirect(handle, cameras[item.camera], spp=spp, seed=7777).indirect)
        return images

    eq = jeval.equal_error_spp(render_at, refs, summary["indirect_rmse"], e["equal_error_spp"], valids, _say)
    summary["equal_error_spp"] = eq["spp"]
    summary["pathtrace_rmse_by_spp"] = eq["tried"]
    jeval.plot_series(os.path.join(out, "equal_error.png"),
                      {"Mitsuba path tracing": ([t["spp"] for t in eq["tried"]], [t["rmse"] for t in eq["tried"]])},
                      xlabel="spp", ylabel="indirect RMSE", title="path tracing vs RRF error", logx=True, logy=True,
                      hlines={"RRF": summary["indirect_rmse"]})

    # 7. Timings at the timing resolution (median after warm-up).
    res = int(e["timing_resolution"])
    cam = cams.look_at(cameras[0].origin, cameras[0].target, fov=cameras[0].fov, width=res, height=res)
    gb = gbuffer(handle, cam)
    evaluate = rrf.evaluator(params, config)
    lights_1 = lightings[0]
    rng = np.random.default_rng(5)
    lights_4 = PointLights.create(latin_hypercube(rng, 4, config["data"]["light_lo"], config["data"]["light_hi"]),
                                  rng.uniform(0.5, 1.5, (4, 3)))
    args1 = rrf.evaluator_arguments(gb, lights_1)
    args4 = rrf.evaluator_arguments(gb, lights_4)
    summary["eval_ms_512_1light"] = jeval.time_call(evaluate.jitted, *args1, repeats=int(e["timing_repeats"]))["median_ms"]
    summary["eval_ms_512_4lights"] = jeval.time_call(evaluate.jitted, *args4,
                                                     repeats=int(e["timing_repeats"]))["median_ms"]
    summary["timing_resolution"] = res
    _say(f"RRF {res}x{res}: {summary['eval_ms_512_1light']:.1f} ms (1 light), "
         f"{summary['eval_ms_512_4lights']:.1f} ms (4 lights)")
    spp_eq = eq["spp"] or max(int(s) for s in e["equal_error_spp"])
    handle.set_lighting(lights_1)
    direct_indirect(handle, cam, spp=1, seed=3)  # warm-up: Dr.Jit compiles its kernels for this film size
    pt = jeval.time_call(lambda: direct_indirect(handle, cam, spp=spp_eq, seed=3), repeats=int(e["pathtrace_repeats"]),
                         warmup=0)
    summary["pathtrace_ms_equal_error"] = pt["median_ms"]
    summary["pathtrace_spp_timed"] = spp_eq
    summary["pathtrace_note"] = ("Mitsuba llvm_ad_rgb, indirect = full (max_depth -1) minus direct (max_depth 2): "
                                 "both renders timed" + ("" if eq["spp"] else "; equal error NOT reached, timed at "
                                                         "the largest spp tried (a lower bound)"))
    summary["speedup_equal_error"] = summary["pathtrace_ms_equal_error"] / summary["eval_ms_512_1light"]
    _say(f"equal-error spp {eq['spp']}: Mitsuba {pt['median_ms']:.0f} ms -> speedup "
         f"{summary['speedup_equal_error']:.1f}x")
    return jeval.write_report(out, summary, t_start, "RRF")


def material_demo(config: dict) -> dict:
    """Appendix B: a fixed-view RRF whose view inputs are replaced by one object's roughness and
    albedo; renders a few edits with the RRF and with Mitsuba (same held-out light) and writes
    them side by side with their RMSE. ``config['material_demo']`` holds the edits to show."""
    base = merge({**rrf.DEFAULT_CONFIG, "eval": EVAL_DEFAULTS, "output": {"dir": "results/rrf"}},
                 {k: v for k, v in config.items() if k != "material_demo"})
    cfg = merge(base, {"data": {"mode": "material"}})
    demo = config["material_demo"]
    out = os.path.abspath(os.path.join(cfg["output"]["dir"], config_hash(config), "material_edit"))
    os.makedirs(out, exist_ok=True)
    t0 = time.perf_counter()
    data = rrf.make_dataset(cfg["scene"], cfg)
    params, info = rrf.fit(data, cfg)
    evaluate = rrf.evaluator(params, cfg)
    d, e = cfg["data"], cfg["eval"]
    mat = d["material"]
    camera = cams.look_at(mat["view_origin"], d["view_target"], fov=d["fov"], width=e["resolution"],
                          height=e["resolution"])
    rng = np.random.default_rng(int(e["seed"]) + 1)
    light = PointLights.create(latin_hypercube(rng, 1, d["light_lo"], d["light_hi"]), [1.0, 1.0, 1.0])
    from jprt.render.scenes import describe

    base_desc = describe(cfg["scene"])
    gb = gbuffer(SceneHandle(base_desc, light), camera)
    rows, results = [], []
    for roughness, albedo in demo["edits"]:
        desc = rrf._edit_description(base_desc, mat["object"], roughness, albedo)
        ref = direct_indirect(SceneHandle(desc, light), camera, spp=int(demo["reference_spp"]), seed=11).indirect
        pred = np.asarray(evaluate(gb, light, edit=(roughness, albedo)))
        rmse = jeval.set_rmse([pred], [ref], [gb.valid])
        results.append({"roughness": roughness, "albedo": albedo, "rmse": rmse})
        rows.append((f"r={roughness:g} a={albedo:g}", ref, pred))
        _say(f"material edit roughness {roughness:g}, albedo {albedo:g}: RMSE {rmse:.5f}")
    jeval.side_by_side(os.path.join(out, "material_edit.png"), rows, exposure=float(e["exposure"]))
    summary = {"object": mat["object"], "n_samples": len(data), "train_s": info.train_s,
               "n_leaves": kdtree.KDTree(**{k: np.asarray(v) for k, v in params["tree"].items()}).n_leaves,
               "reference_spp": int(demo["reference_spp"]), "edits": results, "total_s": time.perf_counter() - t0}
    io.write_json(os.path.join(out, "summary.json"), summary)
    print(f"material-editing report written to {out}")
    return summary
