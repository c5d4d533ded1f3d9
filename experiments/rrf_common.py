"""The RRF report shared by rrf_cornell.py and rrf_glossy.py (Ren et al. 2013, §5), on
``jprt.runner``: held-out (view, light) references rendered by Mitsuba, Mitsuba as the
equal-error peer, and the paper's ablations (attribute sets, one MLP of equal size, Table 3
robustness, Fig. 6 training-set size, Fig. 7 training spp, four lights, Appendix B material edits);
helpers in ``jprt.methods.rrf.evaluation``.
"""

from __future__ import annotations

import os

import numpy as np

from jprt import eval as jeval
from jprt.config import merge
from jprt.methods import REGISTRY
from jprt.methods.rrf import data as rrf_data
from jprt.methods.rrf import evaluation as ev
from jprt.methods.rrf import kdtree
from jprt.methods.rrf import model as rrf
from jprt.runner import HeldOut, PathTracer

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
    return merge({**REGISTRY["rrf"].default_config, "eval": EVAL_DEFAULTS, "output": {"dir": output}}, overrides)


def _tail(run, params, method_config) -> tuple[float, float]:
    """RMSE and 99.9th-percentile error of an ablation's model (``params`` under ``method_config``)
    on the run's held-out set."""
    held = run.state["held_out"]
    t = ev.tail(ev.predict(rrf.evaluator(params, method_config), run.state["testset"]), held.references, held.valid)
    return t["rmse"], t["p999_abs_error"]


def held_out(run) -> HeldOut:
    """The held-out (view, light) pairs: references path traced along the pixel-centre rays at
    ``eval.reference_spp`` (``jprt.render.images.centre_rays``), and the RRF's predictions."""
    if run.config["data"]["mode"] == "material":
        raise ValueError("the RRF report evaluates view-mode RRFs; material editing is the material_edit stage")
    cameras, lightings, testset = ev.held_out_inputs(run.config)
    run.state.update(testset=testset, cameras=cameras, lightings=lightings)
    valid = [testset.gbuffer(item.camera).valid for item in testset.items]
    direct, refs = ev.held_out_references(run.config, cameras, lightings, testset)
    return HeldOut(ev.predict(run.evaluate, testset), refs, valid, direct, [f"pair {k}" for k in range(len(testset))])


def frame(run):
    """The first held-out view at ``eval.timing_resolution`` under its first light (``evaluation.timing_frame``)."""
    t = ev.timing_frame(run.config, run.state["cameras"], run.state["lightings"])
    run.state.update(timing_camera=t["camera"], handle=t["handle"], timing_gbuffer=t["gbuffer"],
                     gbuffer_ms=t["gbuffer_ms"])
    return t["gbuffer"], run.state["lightings"][0]


def pathtracer(run) -> PathTracer:
    """Mitsuba along the references' pixel-centre rays (``evaluation.pathtracer``), timed on the timing view."""
    st = run.state
    return ev.pathtracer(st["handle"], st["testset"], st["cameras"], st["lightings"], st["timing_camera"],
                         int(run.config["eval"]["pathtrace_repeats"]))


def tree_stats(run) -> dict:
    """kd-tree size, weights, per-leaf errors of the main fit (``evaluation.tree_stats``)."""
    return {**ev.tree_stats(*run.result), "reference_spp": int(run.config["eval"]["reference_spp"]),
            "test_pairs": [len(run.state["cameras"]), len(run.state["lightings"])]}


def _light_times(run, evaluators: dict) -> dict:
    """``evaluation.light_times`` on the timing frame and its four lights."""
    return ev.light_times(evaluators, run.state["timing_gbuffer"], run.state["lightings"][0],
                          ev.four_light_inputs(run.config), int(run.config["eval"]["timing_repeats"]))


def four_lights(run) -> dict:
    """Eq. 9 with four lights at the timing resolution (the first layer's light-free part is
    shared between lights in one leaf), against the one-light frame timed interleaved with it
    (their ratio is the program's), with its FLOPs against the machine; the G-buffer's time
    (Mitsuba), with the speedup at equal error counted with it (the paper counts without)."""
    t = _light_times(run, {"rrf": (run.result.params, run.method_config)})["rrf"]
    s, g = run.summary, run.state["gbuffer_ms"]
    out = {"frame_ms_4lights": t["ms4"], "frame_ms_4lights_min": t["ms4_min"], "frame_ms_1light_interleaved": t["ms1"],
           "frame_ms_1light_interleaved_min": t["ms1_min"], "frame_ms_4lights_over_1light": t["ms4"] / t["ms1"],
           "frame_flops_4lights": t["flops4"],
           "flops_fraction_of_peak_4lights": t["flops4"] / (t["ms4"] * 1e-3) / 1e9 / s["matmul_peak_gflops"],
           # the floor under the time ratio: the light-free part of the first layer is shared only
           # between lights in one leaf (``rrf.frame_flops``)
           "frame_flops_4lights_over_1light": t["flops4"] / s["frame_flops"] if s.get("frame_flops") else None,
           "gbuffer_ms": g}
    if s.get("pathtrace_ms_equal_error"):
        out["speedup_equal_error_with_gbuffer"] = s["pathtrace_ms_equal_error"] / (s["frame_ms"] + g)
    run.say(f"4 lights {t['ms4']:.2f} ms, one light {t['ms1']:.2f} ms, interleaved ({t['ms4'] / t['ms1']:.2f}x); "
            f"G-buffer {g:.1f} ms")
    return out


#: ``tree.split_on`` without the light: every leaf serves every light (``split_rule_ablation``).
NO_LIGHT_SPLIT = ["position", "view", "normal", "brdf"]


def split_rule_ablation(run) -> dict:
    """The kd-tree's split rule: the paper's (every axis, ``tree.split_on`` None) against the
    light barred from the splits, whichever the config does not use, same samples. Held-out RMSE
    and 99.9th-percentile error, leaves, and the timing frame with one and four lights for both
    models, timed interleaved in this stage."""
    if not run.config["eval"]["ablations"]:
        return {}
    mine = run.method_config["tree"].get("split_on")
    own = rrf.ATTRIBUTE_SETS[run.method_config["model"]["attributes"]]  # NO_LIGHT_SPLIT on this set's attributes
    other = [a for a in NO_LIGHT_SPLIT if a in own] if mine is None else None
    cfg = run.with_config({"tree": {"split_on": other}})
    p, _ = rrf.fit(run.dataset, cfg)
    rmse, p999 = _tail(run, p, cfg)
    t = _light_times(run, {"config": (run.result.params, run.method_config), "other": (p, cfg)})
    o, c = t["other"], t["config"]
    splits = np.asarray(p["tree"]["axis"])
    light = rrf.split_dims({**cfg, "tree": {"split_on": ["light"]}})  # the light's columns of x
    out = {"split_on": other, "rmse": rmse, "p999_abs_error": p999, "p999_over_rmse": p999 / rmse,
           "n_leaves": kdtree.KDTree(**p["tree"]).n_leaves,
           "splits_on_light": int(np.isin(splits, light).sum()), "splits": int(np.sum(splits >= 0)),
           "frame_ms": o["ms1"], "frame_ms_4lights": o["ms4"], "frame_ms_4lights_over_1light": o["ms4"] / o["ms1"],
           "frame_flops": o["flops1"], "frame_flops_4lights": o["flops4"], "config_frame_ms": c["ms1"],
           "config_frame_ms_4lights": c["ms4"], "config_frame_ms_4lights_over_1light": c["ms4"] / c["ms1"]}
    run.say(f"split_on {other}: RMSE {rmse:.5f}, p99.9 / RMSE {out['p999_over_rmse']:.1f}, {out['n_leaves']} leaves; "
            f"frames {out['frame_ms']:.1f} / {out['frame_ms_4lights']:.1f} ms against this config's "
            f"{out['config_frame_ms']:.1f} / {out['config_frame_ms_4lights']:.1f} ms (1 / 4 lights, interleaved)")
    return {"split_rule_ablation": out}


def sampling_ablation(run) -> dict:
    """The training rays: uniform over the screen (``data.oversample`` 1, the paper's) against
    the surface-balanced draw (the default), same budget, RMSE and 99.9th-percentile error."""
    if not run.config["eval"]["ablations"]:
        return {}
    other = 1 if int(run.method_config["data"]["oversample"]) > 1 else 8
    cfg = run.with_config({"data": {"oversample": other}})
    rmse, p999 = _tail(run, rrf.fit(rrf_data.make_dataset(run.config["scene"], cfg), cfg).params, cfg)
    run.say(f"training rays with oversample {other}: RMSE {rmse:.5f}, p99.9 {p999:.4f}")
    return {"sampling_ablation": {"oversample": other, "rmse": rmse, "p999_abs_error": p999}}


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
        out[key], p999 = _tail(run, p, cfg)
        if own not in ("basic", "augmented"):
            out[key.replace("rmse_", "p999_over_rmse_")] = p999 / out[key]
        out[key.replace("rmse_", "n_leaves_")] = kdtree.KDTree(**p["tree"]).n_leaves
        run.say(f"{attrs} attributes: RMSE {out[key]:.5f}")
    return out


def single_mlp(run) -> dict:
    """One tanh MLP with about as many weights as the whole RRF (``evaluation.single_mlp``),
    trained on the same samples; evaluated on the same test set."""
    if not run.config["eval"]["ablations"]:
        return {}
    n_params = rrf.parameter_count(run.result.params)
    preds, single = ev.single_mlp(run.dataset, run.method_config, n_params, int(run.config["eval"]["single_mlp_steps"]),
                                  run.state["testset"])
    held = run.state["held_out"]
    single = {"rmse": jeval.set_rmse(preds, held.references, held.valid), **single}
    run.say(f"one MLP {single['hidden']} ({single['n_params']} weights vs {n_params}): RMSE {single['rmse']:.5f}")
    return {"rmse_single_mlp_same_params": single["rmse"], "single_mlp": single}


def robustness(run) -> dict:
    """Table 3 (``evaluation.robustness``): the kd-tree fixed, every leaf refitted on 70 % subsets
    and from new initial weights, ``eval.robustness`` of each (0: skipped)."""
    n = int(run.config["eval"]["robustness"])
    if not n:
        return {}
    params, info = run.result
    out = ev.robustness(params, run.dataset, run.method_config, info, n,
                        lambda p: _tail(run, p, run.method_config)[0])
    run.say(f"robustness: std over subsets {out['std_subsets']:.5f}, over inits {out['std_inits']:.5f}")
    return out


def _curve(run, values: list, own, overrides, fit) -> list[float]:
    """Held-out RMSE of a refit at each value (``overrides(value)`` of the method config; the main
    fit's at ``own``), ``fit(cfg)`` making its params."""
    errs = []
    for v in values:
        if v == own:
            errs.append(run.summary["indirect_rmse"])
            continue
        cfg = run.with_config(overrides(v))
        errs.append(_tail(run, fit(cfg), cfg)[0])
    return errs


def training_size(run) -> dict:
    """Fig. 6: accuracy against the fraction of the training set."""
    if not run.config["eval"]["sizes"]:
        return {}
    sizes = sorted(set(float(s) for s in run.config["eval"]["sizes"]) | {1.0})
    errs = _curve(run, sizes, 1.0, lambda s: {"train": {"subset": s}}, lambda cfg: rrf.fit(run.dataset, cfg).params)
    n_train = [int(round(s * run.result.info["is_train"].sum())) for s in sizes]
    jeval.plot_series(os.path.join(run.out, "fig6_training_size.png"), {"RRF": (n_train, errs)},
                      xlabel="training samples", ylabel="indirect RMSE", title="accuracy vs training-set size",
                      logx=True)
    return {"fig6_training_size": {"n_train": n_train, "rmse": errs}}


def training_spp(run) -> dict:
    """Fig. 7: accuracy against the samples per pixel of the training data."""
    if not run.config["eval"]["train_spp"]:
        return {}
    own = int(run.method_config["data"]["spp"])
    spps = sorted(set(int(s) for s in run.config["eval"]["train_spp"]) | {own})
    errs = _curve(run, spps, own, lambda s: {"data": {"spp": s}},
                  lambda cfg: rrf.fit(rrf_data.make_dataset(run.config["scene"], cfg), cfg).params)
    jeval.plot_series(os.path.join(run.out, "fig7_training_spp.png"), {"RRF": (spps, errs)},
                      xlabel="training spp", ylabel="indirect RMSE", title="accuracy vs training-data spp", logx=True)
    return {"fig7_training_spp": {"spp": spps, "rmse": errs}}


def reference_noise(run) -> dict:
    """The references' own noise in the report's statistics (``evaluation.reference_noise``): a
    second reference set of the same pairs, scored against the first; this fit against the mean of
    the two. Skipped with ``eval.reference_noise`` False."""
    if not run.config["eval"]["reference_noise"]:
        return {}
    st = run.state
    out = ev.reference_noise(run.config, st["cameras"], st["lightings"], st["testset"], st["held_out"])
    fit = out["fit_against_mean_of_two"]
    run.say(f"reference noise at {out['reference_spp']} spp: RMSE {out['rmse']:.5f}, p99.9 / RMSE "
            f"{out['p999_over_rmse']:.2f} (an error of one relative size everywhere: "
            f"{out['uniform_relative_error_p999_over_rmse']:.2f}); the fit against the mean of two sets: RMSE "
            f"{fit['rmse']:.5f}, p99.9 / RMSE {fit['p999_over_rmse']:.2f}")
    return {"reference_noise": out}


#: The stages of an RRF report, in order.
STAGES = [tree_stats, reference_noise, four_lights, split_rule_ablation, sampling_ablation, attribute_ablation,
          single_mlp, robustness, training_size, training_spp]
