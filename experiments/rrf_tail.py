"""Where the RRF's worst pixels are, and what training settings do to them.

Fits experiments/rrf_cornell.py's config with each named variant of ``tail.variants`` (overrides
of that config) and scores it on that experiment's held-out pairs (references along the
pixel-centre rays at ``eval.reference_spp``, cached by ``jprt.cache``): indirect RMSE, the 99.9th
percentile of |error| over every valid pixel and channel, their ratio, and which surfaces the
worst 0.1 % lie on ("object/normal axis": 1/1 the ceiling, 2/2 the back wall, 6/1 the tall box's
top face in the built-in Cornell box).

    jprt run experiments/rrf_tail.py                      # the config itself ("small")
    jprt run experiments/rrf_tail.py --set 'tail.variants={"small": {}, "face1": {"data": {"min_face_rays": 1}}}'
    jprt run experiments/rrf_tail.py --set tail.noise=true --set tail.figures=true --set tail.timing=true
    jprt run experiments/rrf_tail.py --preset test        # tiny sizes

With ``tail.noise`` a second reference set of the same pairs (other seeds) is rendered too: a first
row gives the references' own noise (|A - B| / sqrt 2: its RMSE, 99.9th percentile and their
ratio), and each variant is also scored against the mean of the two (half the noise variance).
With ``tail.figures`` each variant writes ``tail_<name>.png`` into the report folder: the four
held-out pairs that hold most of the worst 0.1 %, one row each: reference | RRF | |error| (white
at 0.1), the worst 0.1 % in red. With ``tail.timing`` each variant's frame is timed as
rrf_cornell times it: the first held-out view at ``eval.timing_resolution`` with one light and
with its four lights, interleaved (``jprt.methods.rrf.evaluation.light_times``), and the FLOPs.
One JSON line per row on stdout; every row in ``<output.dir>/<config hash>/tail.json``.
"""

from __future__ import annotations

import json
import math
import os
import time

import numpy as np
import rrf_cornell

from jprt import cache, io
from jprt.config import merge, save_resolved
from jprt.hashing import config_hash
from jprt.methods import REGISTRY
from jprt.methods.rrf import data as rrf_data
from jprt.methods.rrf import evaluation as ev
from jprt.runner import method_config

CONFIG = merge(rrf_cornell.CONFIG, {"output": {"dir": "results/rrf_tail"}}) | {
    # variants: {name: overrides of rrf_cornell's config} ({}: the config itself, as "small");
    # noise: also score against a second reference set; figures: a tail figure per variant;
    # timing: time each variant's frame with one and four lights
    "tail": {"variants": {}, "noise": False, "figures": False, "timing": False},
}

PRESETS = {"test": {**rrf_cornell.PRESETS["test"], "tail": {"noise": True, "figures": True, "timing": True}}}


def references(config: dict, testset, cameras, lightings, seed_offset: int = 0) -> list:
    """The held-out references of ``config`` (``evaluation.held_out_references``), a ``jprt.cache`` entry."""
    spec = {"scene": config["scene"], "data": config["data"], "eval": config["eval"], "seed_offset": int(seed_offset)}
    arrays, _ = cache.cached("rrf_tail_references", spec, lambda: {"references": np.stack(
        ev.held_out_references(config, cameras, lightings, testset, seed_offset)[1])})
    return list(arrays["references"])


def score(config: dict, override: dict, testset, refs, refs2=None, figure_path: str | None = None) -> dict:
    """Fit ``config`` with ``override`` merged in; its tail statistics on the held-out set (and,
    with ``refs2``, against the mean of two reference sets), its figure and frame times."""
    method = REGISTRY["rrf"]
    cfg = method_config(method, merge(config, override))
    t0 = time.perf_counter()
    fit = method.fit(rrf_data.make_dataset(config["scene"], cfg, progress=False), cfg)
    gbs = [testset.gbuffer(item.camera) for item in testset.items]
    preds = ev.predict(method.evaluator(fit.params, cfg), testset)
    worst = ev.worst_pixels(preds, refs, gbs)
    errors = worst.pop("errors")
    n_leaves, n_inputs = np.shape(fit.params["leaves"]["layers"][0]["w"])[:2]
    axes = np.asarray(fit.params["tree"]["axis"])
    out = {**worst, "n_leaves": int(n_leaves),
           "splits_per_axis": np.bincount(axes[axes >= 0], minlength=n_inputs).tolist()}
    if config["tail"]["timing"]:
        cameras, lightings = ev.held_out_pairs(config)
        frame = ev.timing_frame(config, cameras, lightings)
        t = ev.light_times({"rrf": (fit.params, cfg)}, frame["gbuffer"], lightings[0], ev.four_light_inputs(config),
                           int(config["eval"]["timing_repeats"]))["rrf"]
        out["timing"] = {"frame_ms": t["ms1"], "frame_ms_4lights": t["ms4"],
                         "frame_ms_4lights_over_1light": t["ms4"] / t["ms1"], "frame_flops": t["flops1"],
                         "frame_flops_4lights": t["flops4"],
                         "frame_flops_4lights_over_1light": t["flops4"] / t["flops1"]}
    if refs2 is not None:
        valid = [g.valid for g in gbs]
        out["against_mean_of_two_references"] = ev.tail(preds, [(a + b) / 2 for a, b in zip(refs, refs2)], valid)
    if figure_path:
        shown = ev.tail_figure(figure_path, preds, refs, errors, worst["worst_0.1%_by_pair"], worst["p999_abs_error"])
        out["figure"] = {"path": figure_path, "pairs": shown}
    return {**out, "seconds": round(time.perf_counter() - t0)}


def main(config: dict) -> dict:
    """Score every variant (module docstring); write ``tail.json`` (and the figures) to
    ``<output.dir>/<config hash>/``; returns {"rows": [...], "output": folder}."""
    out = os.path.abspath(os.path.join(config["output"]["dir"], config_hash(config)))
    os.makedirs(out, exist_ok=True)
    save_resolved(config, out)
    tc = config["tail"]
    base = {k: v for k, v in config.items() if k != "tail"}
    cameras, lightings, testset = ev.held_out_inputs(base)
    refs = references(base, testset, cameras, lightings)
    rows, refs2 = [], None

    def emit(row: dict) -> None:
        rows.append(row)
        print(json.dumps(row), flush=True)

    if tc["noise"]:
        refs2 = references(base, testset, cameras, lightings, ev.NOISE_SEED_OFFSET)
        valid = [testset.gbuffer(item.camera).valid for item in testset.items]
        emit({"name": "reference noise (|A - B| / sqrt 2)", "reference_spp": int(config["eval"]["reference_spp"]),
              **ev.tail([a / math.sqrt(2.0) for a in refs], [b / math.sqrt(2.0) for b in refs2], valid)})
    for name, override in (tc["variants"] or {"small": {}}).items():
        figure = os.path.join(out, f"tail_{name}.png") if tc["figures"] else None
        emit({"name": name, "override": override, **score(config, override, testset, refs, refs2, figure)})
    io.write_json(os.path.join(out, "tail.json"), {"rows": rows})
    print(f"rrf_tail report (tail.json{', figures' if tc['figures'] else ''}) written to {out}")
    return {"rows": rows, "output": out}
