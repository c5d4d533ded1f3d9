"""Neural-wavelet PRT (Raghavan et al. 2023) on a glossy Cornell box relit by environment maps.

    jprt run experiments/wavelet_prt_cornell.py                   # `small`: trains in ~7 min on 2 CPU cores
    jprt run experiments/wavelet_prt_cornell.py --preset paper    # the paper's sizes (needs an accelerator)
    jprt run experiments/wavelet_prt_cornell.py --preset test     # smoke test (procedural maps)
    jprt sweep experiments/sweeps/wavelet_prt_front.py            # the speed-accuracy front (width, M, K)

The glossy Cornell box with its top open, lit by ../shared/assets environment maps and their
rotations; Adam fits the CP feature field + MLP on spherical + helix trajectories (§5, resumable).
The common summary is over the far views under held-out maps (Mitsuba on the same views the
equal-error peer). Stages: the ground-truth transport check, Table 1 (near / far views against
indirect = c * direct), PSNR by held-out map, the K sweep, Table 2 (frame time by resolution and
K), one generalisation change at a time, ablations (Tables 3, 4, 6) at a common reduced step
count; helpers in ``jprt.methods.wavelet_prt.evaluation``. Report: results/wavelet_prt_cornell/<hash>/.
"""

from __future__ import annotations

import os

import jax
import numpy as np

from jprt import eval as jeval
from jprt import io
from jprt.inputs import CubeMap
from jprt.methods import REGISTRY
from jprt.methods.base import FitResult
from jprt.methods.wavelet_prt import data as wp_data
from jprt.methods.wavelet_prt import evaluation as ev
from jprt.methods.wavelet_prt import model as wp
from jprt.runner import HeldOut, PathTracer

METHOD = "wavelet_prt"
LABEL = "wavelet_prt"

EVAL_DEFAULTS = {
    "ks": [32, 64, 128],  # run-time wavelet counts K of the K sweep and the frame times
    # the ground-truth transport check: view size (pixels), spp and path depth of Mitsuba's
    # transport, the K relit ([] skips the check)
    "gt_check": {"width": 16, "height": 16, "spp": 16384, "max_depth": 8, "ks": [32, 64, 128, 300]},
    "timing_resolutions": [[128, 128], [256, 256], [512, 512]],  # [width, height] of the frame times
    "timing_repeats": 5,
    "equal_error_spp": [1, 2, 4, 8, 16, 32, 64, 128, 256, 512],
    "ablation_steps": 250,  # training steps of every ablation model (0: no ablations)
    # one change from the default at a time, each trained at the full step count: [name, overrides
    # of the method config] pairs (a list: a preset replaces it whole)
    "generalisation": [["Eq. 4's null transport (f(0, pixel) kept)", {"model": {"null_transport": "free"}}],
                       ["unbiased objective (inverse inclusion weights)", {"train": {"objective": "unbiased"}}],
                       ["last Adam iterate (no moving average)", {"train": {"ema": 0.0}}],
                       ["no exposure / white-balance jitter", {"train": {"exposure_stops": 0.0, "white_balance": 0.0}}],
                       ["no procedural skies, no mirroring", {"envmaps": {"procedural_fraction": 0.0, "mirror": False}}]],
    # model.<key> values; "spatial": named model overrides (the multiresolution hash grid against one
    # single-resolution grid, the paper's "learned neural texture" alternative of §4, and against
    # per-vertex features on the subdivided scene mesh, Table 6)
    "ablations": {"log2_table_size": [10, 12, 14], "reflection": ["sh4", "raw", "none"],
                  "spatial": {"multiresolution": {},
                              "single_resolution": {"n_levels": 1, "features_per_level": 16,
                                                    "base_resolution": 32},
                              "per_vertex": {"spatial": "vertex", "vertex_edge": 0.1}}},
    "exposure": 0.0,  # tonemapping exposure (stops) of every PSNR / SSIM and image
}

# resources: what one sweep point asks of a Ray cluster (``jprt sweep --ray``; training uses every core it gets)
CONFIG = {**wp.DEFAULT_CONFIG, "eval": EVAL_DEFAULTS, "output": {"dir": "results/wavelet_prt_cornell"},
          "resources": {"cpus": 2, "gpus": 0}}

PRESETS = {
    "small": {},
    # the paper's sizes (§5): 64^2 cube faces, M = L = 64, 32-level hash grid with 2^19 entries,
    # 2048 pixels per step, 512^2 images; 1000 maps x 3 rotations and ~2000 views in the paper
    "paper": {
        "resources": {"cpus": 4, "gpus": 1},
        "envmaps": {"face_size": 64},
        "cameras": {"width": 512, "height": 512, "sphere": {"n": 600}, "helix": {"n": 300}, "near": 16, "far": 16},
        "data": {"spp": 1024, "test_spp": 4096},
        "model": {"n_levels": 32, "features_per_level": 2, "log2_table_size": 19, "base_resolution": 16,
                  "per_level_scale": 1.3, "n_features": 64},
        "train": {"steps": 100000, "pixels": 2048, "learning_rate": 1e-2, "checkpoint_every": 2000},
        "eval": {"timing_resolutions": [[512, 512], [800, 600]], "ablation_steps": 20000,
                 "ablations": {"log2_table_size": [17, 18, 19, 20]}},
    },
    "test": {
        **REGISTRY["wavelet_prt"].presets["test"],  # the method's own smoke-test sizes
        "eval": {"ks": [8, 16], "gt_check": {"width": 6, "height": 6, "spp": 64, "max_depth": 4, "ks": [8, 32]},
                 "timing_resolutions": [[16, 16]], "timing_repeats": 1, "equal_error_spp": [1, 4],
                 "ablation_steps": 10,
                 "generalisation": [["unbiased objective", {"train": {"objective": "unbiased"}}]],
                 "ablations": {"log2_table_size": [6], "reflection": ["none"],
                               "spatial": {"single_resolution": {"base_resolution": 4},
                                           "per_vertex": {"vertex_edge": 0.5}}}},
    },
}

#: Two held-out maps whose mean PSNR the benchmark compares with its first protocol's value.
ORIGINAL_PAIR = ("st_fagans_interior_1k", "venice_sunset_1k")


def _handle(run, cube):
    """The run's scene handle (made once), lit by the cube map ``cube``."""
    run.state["handle"] = ev.scene_handle(run.config["scene"], cube, run.state.get("handle"))
    return run.state["handle"]


def _train(run, cfg: dict, data, label: str, progress: bool = True) -> FitResult:
    return ev.resumable_fit(cfg, data, run.say, label, progress)


def _scores(evaluate, data, exposure: float) -> dict:
    return ev.split_scores(ev.predict_split(evaluate, data, "far"), data.tests["far"], exposure)


def fit(run) -> FitResult:
    """Training (§5), resumable (``evaluation.resumable_fit``)."""
    return _train(run, run.method_config, run.dataset, "training")


def held_out(run) -> HeldOut:
    """The far views (off the training trajectories) under held-out maps."""
    t = run.dataset.tests["far"]
    preds = ev.predict_split(run.evaluate, run.dataset, "far")
    run.state["far"] = preds
    return HeldOut(preds, list(t["indirect"]), list(t["valid"]), list(t["direct"]),
                   [f"far {i}" for i in range(len(preds))])


def _timing_key(run) -> str:
    keys = [f"{w}x{h}" for w, h in run.config["eval"]["timing_resolutions"]]
    return "256x256" if "256x256" in keys else keys[0]


def _far_camera(run, k: int, size: str | None = None):
    """Far view ``k`` at ``size`` ("WxH"; default the data's image size)."""
    c = run.config["cameras"]
    w, h = (int(v) for v in size.split("x")) if size else (c["width"], c["height"])
    return ev.camera(run.config, run.dataset.cameras["far"][k], w, h)


def frame(run):
    """The first far view at the timing resolution (256 x 256 when listed) under the first held-out map."""
    cube = run.dataset.test_envs[0]
    return wp_data.gbuffer_fields(_handle(run, cube), _far_camera(run, 0, _timing_key(run))), CubeMap(cube)


def pathtracer(run) -> PathTracer:
    """Mitsuba's indirect of the far views (seeds unlike the references'), and its time at the
    timing resolution."""
    from jprt.render import images as mimages

    data = run.dataset
    t = data.tests["far"]
    # far image i shows view i // maps under every held-out map ("all"), or view i ("cycle")
    per_view = len(data.test_envs) if run.method_config["data"]["test_pairs"] == "all" else 1

    def render_at(spp):
        return [mimages.direct_indirect(_handle(run, data.test_envs[int(t["env"][i])]), _far_camera(run, i // per_view),
                                        spp=spp, seed=4242 + i).indirect for i in range(len(t["valid"]))]

    def time_at(spp):
        cam, handle = _far_camera(run, 0, _timing_key(run)), _handle(run, data.test_envs[0])
        mimages.direct_indirect(handle, cam, spp=1, seed=3)  # warm-up: kernels for this film size
        return jeval.time_call(lambda: mimages.direct_indirect(handle, cam, spp=spp, seed=3),
                               repeats=int(run.config["eval"]["timing_repeats"]), warmup=0)["median_ms"]

    k = run.method_config["render"]["k"]
    return PathTracer(render_at, time_at, f"Mitsuba llvm_ad_rgb indirect (full max_depth -1 and direct max_depth 2 "
                                          f"renders, both timed) at {_timing_key(run)} and the equal-error spp, over "
                                          f"our K={k} frame (JAX on {jax.default_backend()})")


def dataset_stats(run) -> dict:
    """Sizes of the training set, the held-out maps, the training curve (loss.png)."""
    return ev.dataset_stats(run.dataset, run.result.info, run.out)


def gt_transport_check(run) -> dict:
    """Step 1 (``evaluation.transport_check``) with its figure and images; skipped when
    ``eval.gt_check.ks`` is empty. Leaves the learned-T_k probe in ``run.state`` for generalisation."""
    if not run.config["eval"]["gt_check"]["ks"]:
        return {}
    check = ev.transport_check(run.config, run.dataset, run.config["eval"]["gt_check"])
    ev.write_transport_check(run.out, check)
    s = check["summary"]
    run.state["transport_rel_err_learned"] = check["learned_err"]  # the generalisation stage scores its models too
    s["transport_rel_err_learned_by_k"] = learned = check["learned_err"](run.result.params, run.method_config)
    run.say("transport check: rel. error vs Mitsuba " + ", ".join(
        f"K={k}: {v:.3f}" for k, v in s["gt_transport_rel_err_by_k"].items())
        + f"; all wavelets {s['gt_transport_rel_err_all']:.3f}; noise floor {s['gt_transport_noise_floor']:.3f}; "
        "learned T_k vs Mitsuba's, top K: " + ", ".join(f"K={k}: {v:.3f}" for k, v in learned.items()))
    return s


def table1(run) -> dict:
    """Table 1 (``evaluation.table1``): near / far views on held-out maps against the baseline
    indirect = c * direct; images with the baseline (side_by_side_baseline.png)."""
    data = run.dataset
    preds = {split: run.state["far"] if split == "far" else ev.predict_split(run.evaluate, data, split)
             for split in ("near", "far") if data.tests[split]}
    s = ev.table1(data, preds, run.config["eval"]["exposure"])
    for split in preds:
        run.say(f"{split} views: PSNR indirect {s[f'psnr_indirect_{split}']:.2f} dB (baseline c*direct "
                f"{s[f'psnr_indirect_{split}_baseline']:.2f}), full {s[f'psnr_full_{split}']:.2f} dB, SSIM indirect "
                f"{s[f'ssim_indirect_{split}']:.4f}")
    t, c, k = data.tests["far"], np.asarray(s["baseline_scale"]), run.method_config["render"]["k"]
    rows = [row for i in range(min(3, len(t["valid"])))
            for row in ((f"far {i}: ours (K={k})", t["indirect"][i], run.state["far"][i]),
                        (f"far {i}: c * direct", t["indirect"][i], c[None, None, :] * t["direct"][i]))]
    jeval.side_by_side(os.path.join(run.out, "side_by_side_baseline.png"), rows, exposure=1.0,
                       titles=("reference indirect", "prediction", "|difference|"))
    return s


def by_map(run) -> dict:
    """The held-out protocol by map (``evaluation.by_map``): every far view under every held-out
    map, PSNR per map and category against the baseline's, the worst map, the original pair's
    mean, the smallest mean and smallest pixel of the predicted indirect per map."""
    data = run.dataset
    c = ev.baseline_scale(data)
    out = ev.by_map(run.state["far"], [c[None, None, :] * d for d in data.tests["far"]["direct"]], data,
                    dict(run.method_config["envmaps"]["categories"]), run.config["eval"]["exposure"], ORIGINAL_PAIR)
    for name, v in out["psnr_indirect_far_by_map"].items():
        run.say(f"held-out map {name} ({out['held_out_categories'][name]}): PSNR indirect {v:.2f} dB (baseline "
                f"{out['psnr_indirect_far_baseline_by_map'][name]:.2f}), smallest mean "
                f"{out['min_mean_indirect_by_map'][name]:.4f}")
    return out


def k_sweep(run) -> dict:
    """PSNR of the far views by the number K of lighting wavelets at run time."""
    by_k = {}
    for k in run.config["eval"]["ks"]:
        evaluate = run.evaluate if int(k) == int(run.method_config["render"]["k"]) else wp.evaluator(
            run.result.params, run.with_config({"render": {"k": int(k)}}))
        by_k[str(k)] = _scores(evaluate, run.dataset, run.config["eval"]["exposure"])["psnr_indirect"]
    return {"psnr_indirect_far_by_k": by_k}


def frame_times(run) -> dict:
    """Table 2: frame time by resolution and K."""
    e, cube = run.config["eval"], run.dataset.test_envs[0]
    frame_ms = {}
    for w, h in e["timing_resolutions"]:
        g = jax.device_put(wp_data.gbuffer_fields(_handle(run, cube), _far_camera(run, 0, f"{w}x{h}")))
        for k in e["ks"]:
            evaluate = wp.evaluator(run.result.params, run.with_config({"render": {"k": int(k)}}))
            ms = jeval.time_call(evaluate, g, CubeMap(cube), repeats=int(e["timing_repeats"]), warmup=1)["median_ms"]
            frame_ms.setdefault(f"{w}x{h}", {})[str(k)] = ms
            run.say(f"frame {w}x{h}, K={k}: {ms:.0f} ms")
    return {"frame_ms_by_resolution": frame_ms}


def generalisation(run) -> dict:
    """The default against one change at a time (``eval.generalisation``), each trained at the
    full step count on its own data (same cameras and render budget), all scored on the same
    held-out maps and views (``evaluation.map_scores``), and (when the ground-truth stage ran)
    their learned T_k against Mitsuba's (``transport_rel_err_learned_by_k``)."""
    e = run.config["eval"]
    probe = run.state.get("transport_rel_err_learned")  # set by gt_transport_check when it ran

    def scores(evaluate, data, params, cfg) -> dict:
        out = ev.far_map_scores(evaluate, data, e["exposure"], ORIGINAL_PAIR)
        return out | ({} if probe is None else {"transport_rel_err_learned_by_k": probe(params, cfg)})

    rows = {"default": scores(run.evaluate, run.dataset, run.result.params, run.method_config)}
    for name, overrides in e["generalisation"]:
        cfg = run.with_config(overrides)
        data = ev.variant_dataset(cfg, run.method_config, run.dataset, run.config["scene"])
        r = _train(run, cfg, data, f"generalisation: {name}", progress=False)
        rows[name] = scores(wp.evaluator(r.params, cfg), data, r.params, cfg)
        run.say(f"generalisation {name}: PSNR indirect far {rows[name]['psnr_indirect_far']:.2f} dB, worst "
                f"{rows[name]['psnr_indirect_far_worst']:.2f} (default {rows['default']['psnr_indirect_far']:.2f} / "
                f"{rows['default']['psnr_indirect_far_worst']:.2f})")
    return {"generalisation": rows}


def ablations(run) -> dict:
    """Tables 3, 4 and 6 at a common reduced step count (``eval.ablation_steps``; 0 skips them):
    hash-table size, reflection encoding, spatial feature field (hash grid, one grid, per vertex)."""
    e, data = run.config["eval"], run.dataset
    steps = int(e["ablation_steps"])
    if not steps:
        return {}
    out = {}
    for key, values in e["ablations"].items():
        out[key] = {}
        variants = values.items() if isinstance(values, dict) else ((v, {key: v}) for v in values)
        for value, overrides in variants:
            cfg = run.with_config({"model": overrides, "train": {"steps": steps}})
            d = ev.variant_dataset(cfg, run.method_config, data, run.config["scene"])
            r = _train(run, cfg, d, f"ablation {key}={value}", progress=False)
            sc = _scores(wp.evaluator(r.params, cfg), d, e["exposure"])
            out[key][str(value)] = {"psnr_indirect_far": sc["psnr_indirect"], "psnr_full_far": sc["psnr_full"],
                                    "ssim_indirect_far": sc["ssim_indirect"], "model_bytes": wp.model_bytes(r.params)}
            run.say(f"ablation {key}={value}: PSNR indirect far {sc['psnr_indirect']:.2f} dB")
    return {"ablations": out, "ablation_steps": steps}


#: The stages of the neural-wavelet PRT report, in order.
STAGES = [dataset_stats, gt_transport_check, table1, by_map, k_sweep, frame_times, generalisation, ablations]
