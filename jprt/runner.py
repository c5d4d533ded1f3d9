"""One pipeline for every experiment (DESIGN.md, "Data flow"):

    resolve config -> hash -> save resolved config -> dataset -> fit -> held-out predictions
    -> common summary -> timing and equal error -> the experiment's own stages -> report folder

An experiment file is its ``CONFIG``, ``PRESETS`` and what is special to its paper::

    METHOD = "rrf"                      # a key of jprt.methods.REGISTRY
    CONFIG = {**REGISTRY["rrf"].default_config, "eval": {...}, "output": {"dir": "results/rrf"}}
    PRESETS = {"test": {...}}

    def held_out(run) -> HeldOut: ...   # predictions and references of the held-out views / lights
    def fit(run) -> FitResult                     # optional: instead of METHOD's fit (checkpoints, ...)
    def frame(run) -> (inputs, lighting)          # optional: the frame the evaluator is timed on
                                                  #   (default: the method's ``example``)
    def pathtracer(run) -> PathTracer             # optional: Mitsuba at n spp, for equal error
    STAGES = [ablations, robustness, ...]         # optional: run -> dict, kept under summary["extra"]
    LABEL = "rrf"                                 # optional: the prefix of progress messages

``jprt run experiments/x.py`` calls ``run(module, config)``; ``main(config)`` in a file does the
same. Sections of the config that the method does not know (``eval``, ``output``, ...) are the
experiment's; the method gets exactly its own sections (``Run.method_config``), so an unknown key
anywhere is an error at the entry, never dropped.

Summary schema (``SUMMARY_SCHEMA``; every method, every experiment; ``None`` where a number does
not apply, e.g. no path tracer):
"""

from __future__ import annotations

import os
import sys
import time
from types import ModuleType
from typing import Any, Callable, Sequence

import jax
import numpy as np

from jprt import eval as jeval
from jprt import io
from jprt.config import merge, save_resolved
from jprt.hashing import config_hash
from jprt.methods import REGISTRY
from jprt.methods.base import FitResult, Method, model_bytes

__all__ = ["SUMMARY_SCHEMA", "Run", "HeldOut", "PathTracer", "run", "run_file", "preset_benchmark", "save_fit",
           "flat_summary", "method_config", "common_summary"]

#: Every key of the common summary, with its meaning.
SUMMARY_SCHEMA: dict[str, str] = {
    "method": "the method's REGISTRY name",
    "scene": "the scene section of the config (name and options)",
    "config_hash": "hash of the resolved config (also the report folder's name; config.json holds the config)",
    "indirect_rmse": "RMSE of the indirect prediction over every valid pixel and channel of all held-out images "
                     "together (jprt.eval.set_rmse; HDR, linear)",
    "indirect_rel_rmse": "indirect_rmse / RMS of the reference indirect over the same pixels",
    "indirect_rel_rmse_worst_image": "the largest relative RMSE of one held-out image (its RMSE over its "
                                     "reference's RMS): the worst (view, lighting) pair, which the set's score "
                                     "can hide",
    "p999_abs_error": "99.9th percentile of |prediction - reference| over every valid pixel and channel of the "
                      "held-out images (linear HDR): seams and blotches that the RMSE averages away",
    "psnr_indirect": "PSNR (dB, sRGB-tonemapped, clipped, peak 1) of the indirect images, mean over images",
    "ssim_indirect": "SSIM of the tonemapped indirect images, mean over images; None for images under 11 x 11 "
                     "pixels (the SSIM window)",
    "psnr_full": "PSNR (dB, tonemapped) of direct + indirect, mean over images; None without held-out direct",
    "flip_indirect": "mean LDR FLIP (jprt.metrics.flip) of the tonemapped indirect images, mean over images",
    "lpips_indirect": "LPIPS AlexNet-lin (jprt.metrics.lpips) of the tonemapped indirect images, mean over images; "
                      "None for images under 31 pixels a side",
    "frame_ms": "median wall time (ms) of one jitted evaluator call after warm-up, at frame_resolution",
    "frame_resolution": "[H, W] of the timed frame",
    "equal_error_spp": "smallest Mitsuba spp whose indirect RMSE on the held-out set reaches indirect_rmse; None "
                       "when not reached within eval.equal_error_spp or no path tracer",
    "pathtrace_ms_equal_error": "Mitsuba wall time (ms) of the timed frame at equal_error_spp (at the largest spp "
                                "tried when not reached: a lower bound); extra.pathtrace_curve has (spp, ms, rmse) "
                                "of every spp the search tried",
    "speedup_equal_error": "pathtrace_ms_equal_error / frame_ms",
    "frame_flops": "FLOPs of the timed frame: the method's own count (Method.frame_flops) where it has one, else "
                   "XLA's cost analysis of the compiled evaluator (jprt.eval.xla_cost: gathers, sorts and scatters "
                   "count none, a loop's body as many times as it runs); extra.frame_flops_source says which",
    "matmul_peak_gflops": "f32 JAX matmul rate (GFLOP/s, 1024^3, fastest of 10) measured in the same run",
    "flops_fraction_of_peak": "frame_flops / frame_ms against matmul_peak_gflops: the evaluator judged against the "
                              "machine",
    "roofline": "the timed frame against its roofline (Method.frame_report): matmul_gflops (the compute roof), "
                "bandwidth_gbs (a STREAM triad in JAX over 256 MiB arrays, written in place, measured in the same "
                "process), frame_flops, frame_bytes (XLA's bytes accessed, a table read only through gathers charged "
                "for the rows they read, a loop's carried arrays once: jprt.eval.xla_cost), intensity, "
                "attainable_gflops = min(matmul, intensity x bandwidth), bound, fraction_of_roofline = achieved / "
                "attainable, roof: \"matmul\" (jprt.eval.roofline: the matmul rate, the summary's frame_flops) or "
                "the method's own where Method.frame_roofline names what bounds it (\"networks\" for RRF: "
                "matmul_gflops is its networks' products timed alone, frame_flops the FLOPs its tiles execute); "
                "then extra.roofline_matmul is the matmul one and extra.roofline_detail the method's counts",
    "model_bytes": "bytes of the arrays the evaluator needs at run time (FitResult.info['model_bytes'] when the "
                   "method states it, else every array of the params)",
    "train_s": "seconds of the fit",
    "dataset_s": "seconds to obtain the dataset (rendering, or reading the cache)",
    "extra": "method- and experiment-specific numbers (ablations, sweeps, paper tables)",
}
__doc__ += "\n" + "\n".join(f"* ``{k}``: {v}." for k, v in SUMMARY_SCHEMA.items()) + "\n"


#: Held-out images and Mitsuba as the peer: defined in ``jprt.eval`` (kept here under their old names).
HeldOut = jeval.HeldOut
PathTracer = jeval.PathTracer


class Run:
    """Everything a stage can read (one per ``run`` call).

    Attributes:
      method: the ``Method``; config: the resolved experiment config; method_config: the method's
      sections of it; out: the report folder; dataset; result (``FitResult``); evaluate (the
      evaluator of ``result.params``); summary (the summary built so far); state (a dict stages
      use to share work, e.g. a rendered test set); say (progress messages to stderr).
    """

    def __init__(self, method: Method, config: dict, out: str, label: str):
        self.method = method
        self.config = config
        self.method_config = method_config(method, config)
        self.out = out
        self.label = label
        self.dataset: Any = None
        self.result: FitResult | None = None
        self.evaluate: Callable | None = None
        self.summary: dict = {}
        self.state: dict = {}

    def say(self, msg: str) -> None:
        """A progress message on stderr, prefixed with the experiment's label."""
        print(f"[{self.label}] {msg}", file=sys.stderr, flush=True)

    def with_config(self, overrides: dict) -> dict:
        """The method config with ``overrides`` merged in (strict): for ablation fits."""
        return self.method.resolve(merge(self.method_config, overrides))

    def scene_handle(self, lighting=None):
        """The ``jprt.render.scenes.SceneHandle`` of the experiment's ``scene``, made on the first
        call (with ``lighting``, as ``SceneHandle`` takes it) and kept in ``state["handle"]``:
        the hooks of one run share one loaded scene."""
        from jprt.render.scenes import SceneHandle

        if "handle" not in self.state:
            self.state["handle"] = SceneHandle(self.config["scene"]) if lighting is None else \
                SceneHandle(self.config["scene"], lighting)
        return self.state["handle"]


def method_config(method: Method, config: dict) -> dict:
    """The sections of an experiment config that belong to ``method`` (all of them must be there)."""
    missing = [k for k in method.default_config if k not in config]
    if missing:
        raise ValueError(f"experiment config lacks the {method.name} sections {missing}")
    return method.resolve({k: config[k] for k in method.default_config})


def common_summary(held: HeldOut, exposure: float = 0.0, per_image: bool = False) -> dict:
    """The accuracy keys of ``SUMMARY_SCHEMA`` for a held-out set (``jprt.eval.score_held_out``):
    indirect_rmse, indirect_rel_rmse, indirect_rel_rmse_worst_image, p999_abs_error,
    psnr_indirect, ssim_indirect, psnr_full, flip_indirect, lpips_indirect (None where a metric
    does not apply: images too small for its window, no direct images, its package not
    installed); with ``per_image`` also indirect_rel_rmse_by_image, each image's own."""
    return jeval.score_held_out(held, exposure, jeval.SUMMARY_SCORES + (("indirect_rel_rmse_by_image",)
                                                                        if per_image else ()))


def _figures(run: Run, held: HeldOut, n: int, exposure: float, rel: Sequence[float]) -> None:
    """The side-by-side of the first ``n`` held-out images (each labelled with its relative RMSE,
    ``rel``) and their EXRs."""
    rows = []
    for k in range(min(int(n), len(held.predictions))):
        label = held.labels[k] if held.labels else f"held-out {k}"
        rows.append((f"{label} (rel. RMSE {rel[k]:.3f})", held.references[k], held.predictions[k]))
        io.write_exr(os.path.join(run.out, f"heldout{k:02d}_reference.exr"), held.references[k])
        io.write_exr(os.path.join(run.out, f"heldout{k:02d}_{run.method.name}.exr"), held.predictions[k])
    if rows:
        jeval.side_by_side(os.path.join(run.out, "side_by_side.png"), rows, exposure=exposure)


def _timing(run: Run, experiment: ModuleType, repeats: int) -> None:
    s = run.summary
    frame = getattr(experiment, "frame", None)
    inputs, lighting = frame(run) if frame else run.method.example(run.dataset, run.method_config)
    inputs, lighting = jax.device_put((inputs, lighting))
    fast = jax.jit(run.evaluate)  # the pure program: input checks run on concrete calls only
    timed = jeval.time_call(fast, inputs, lighting, repeats=repeats)
    s["frame_ms"] = timed["median_ms"]
    s["extra"]["frame_ms_min"] = timed["min_ms"]  # the program's cost with the least interference
    s["frame_resolution"] = list(np.shape(fast(inputs, lighting))[:2])
    roof = run.method.frame_report(run.result.params, run.method_config, fast, inputs, lighting, s["frame_ms"],
                                   repeats=repeats)
    s.update({k: roof[k] for k in ("frame_flops", "matmul_peak_gflops", "flops_fraction_of_peak", "roofline")})
    s["extra"]["frame_flops_source"] = roof["frame_flops_source"]
    if roof["roofline_matmul"] is not None:  # the method's own roof is the summary's; the generic one stays beside it
        s["extra"].update(roofline_matmul=roof["roofline_matmul"], roofline_detail=roof["roofline_detail"])
    r = roof["roofline"]
    frac = "" if roof["flops_fraction_of_peak"] is None else (
        f", {roof['frame_flops'] / 1e6:.1f} MFLOP = {100 * roof['flops_fraction_of_peak']:.1f} % of the "
        f"{roof['matmul_peak_gflops']:.0f} GFLOP/s matmul peak")
    if r["fraction_of_roofline"] is not None:
        frac += (f"; {r['frame_bytes'] / 1e6:.1f} MB moved at {r['bandwidth_gbs']:.1f} GB/s: {r['bound']}-bound, "
                 f"{100 * r['fraction_of_roofline']:.1f} % of its roofline ({r['attainable_gflops']:.1f} GFLOP/s, "
                 f"roof: {r.get('roof', 'matmul')})")
    run.say(f"frame {s['frame_resolution'][0]}x{s['frame_resolution'][1]}: {s['frame_ms']:.2f} ms{frac}")


def _equal_error(run: Run, experiment: ModuleType, held: HeldOut) -> None:
    """Mitsuba's curve on the held-out set (``jeval.EqualErrorCurve``), measured up to the model's
    error, and the model's equal-error numbers read off it; the curve and the path tracer stay in
    ``run.state`` ("pathtrace_curve", "pathtracer") for stages that read other models off it."""
    s = run.summary
    s.update(equal_error_spp=None, pathtrace_ms_equal_error=None, speedup_equal_error=None)
    make = getattr(experiment, "pathtracer", None)
    spp_list = run.config.get("eval", {}).get("equal_error_spp", [])
    if make is None or not spp_list:
        return
    pt = make(run)
    curve = jeval.EqualErrorCurve().measure(pt, held.references, held.valid, spp_list, target=s["indirect_rmse"],
                                            progress=run.say)
    run.state.update(pathtracer=pt, pathtrace_curve=curve)
    read = curve.read(s["indirect_rmse"], s["frame_ms"])
    s.update({k: read[k] for k in ("equal_error_spp", "pathtrace_ms_equal_error", "speedup_equal_error")})
    s["extra"]["pathtrace_rmse_by_spp"] = curve.tried
    jeval.plot_series(os.path.join(run.out, "equal_error.png"),
                      {"Mitsuba path tracing": ([p["spp"] for p in curve.points], [p["rmse"] for p in curve.points])},
                      xlabel="spp", ylabel="indirect RMSE (held-out set)", title=f"path tracing vs {run.method.name}",
                      logx=True, logy=True, hlines={run.method.name: s["indirect_rmse"]})
    # every spp tried is timed at the frame resolution; a search that never reaches the error
    # tries the largest spp last: its time is the lower bound reported
    s["extra"]["pathtrace_curve"] = [dict(p) for p in curve.points]
    s["extra"]["pathtrace_spp_timed"] = read["equal_error_spp"] or curve.points[-1]["spp"]
    s["extra"]["pathtrace_note"] = pt.note + ("" if read["equal_error_reached"] else "; equal error NOT reached: "
                                              "timed at the largest spp tried (a lower bound)")
    run.say(f"equal-error spp {read['equal_error_spp']}: Mitsuba {s['pathtrace_ms_equal_error']:.0f} ms -> speedup "
            f"{s['speedup_equal_error']:.2f}x")


def run(experiment: ModuleType, config: dict) -> dict:
    """Run an experiment module (module docstring) on ``config`` (its CONFIG with presets and
    overrides merged in); writes ``<output.dir>/<config hash>/`` (config.json, summary.json,
    model.npz, side_by_side.png, equal_error.png, the stages' files) and returns the summary."""
    t_start = time.perf_counter()
    method = REGISTRY[experiment.METHOD]
    config = merge(experiment.CONFIG, config)
    digest = config_hash(config)
    out = os.path.abspath(os.path.join(config["output"]["dir"], digest))
    os.makedirs(out, exist_ok=True)
    save_resolved(config, out)
    r = Run(method, config, out, getattr(experiment, "LABEL", method.name))
    e = config.get("eval", {})
    r.summary = s = {"method": method.name, "scene": config.get("scene"), "config_hash": digest}

    t0 = time.perf_counter()
    r.dataset = method.make_dataset(config.get("scene"), r.method_config)
    s["dataset_s"] = time.perf_counter() - t0
    fit = getattr(experiment, "fit", None)
    t0 = time.perf_counter()
    r.result = fit(r) if fit else method.fit(r.dataset, r.method_config)
    s["train_s"] = float(r.result.info.get("train_s", time.perf_counter() - t0))
    s["model_bytes"] = int(r.result.info.get("model_bytes", model_bytes(r.result.params)))
    io.save_checkpoint(os.path.join(out, "model.npz"), r.result.params, meta={"config_hash": digest})
    r.evaluate = method.evaluator(r.result.params, r.method_config)
    s["extra"] = {}

    held = experiment.held_out(r)
    r.state["held_out"] = held
    scores = common_summary(held, float(e.get("exposure", 0.0)), per_image=True)
    s["extra"]["indirect_rel_rmse_by_image"] = scores.pop("indirect_rel_rmse_by_image")
    s.update(scores)
    r.say(f"{len(held.predictions)} held-out images: indirect RMSE {s['indirect_rmse']:.5f} "
          f"(relative {s['indirect_rel_rmse']:.3f}, worst image {s['indirect_rel_rmse_worst_image']:.3f}), "
          f"PSNR {s['psnr_indirect']:.2f} dB")
    _figures(r, held, int(e.get("images", 4)), float(e.get("exposure", 0.0)),
             s["extra"]["indirect_rel_rmse_by_image"])
    _timing(r, experiment, int(e.get("timing_repeats", 10)))
    _equal_error(r, experiment, held)
    for stage in getattr(experiment, "STAGES", []):
        s["extra"].update(stage(r) or {})
    s = {k: s[k] for k in SUMMARY_SCHEMA if k in s} | {k: v for k, v in s.items() if k not in SUMMARY_SCHEMA}
    s["total_s"] = time.perf_counter() - t_start
    s["output"] = out
    io.write_json(os.path.join(out, "summary.json"), s)
    print(f"{r.label} report (summary.json, side_by_side.png, plots, EXRs) written to {out}")
    return s


def save_fit(out: str, method: str, config: dict, params) -> str:
    """A run folder (config.json, model.npz, summary.json with the method, scene and config hash)
    for a fit made outside ``run``: what ``jprt view`` and the viewer's tests load. ``config``
    holds the method's sections (an experiment config, or the method config itself)."""
    out = os.path.abspath(out)
    os.makedirs(out, exist_ok=True)
    digest = save_resolved(config, out)
    io.save_checkpoint(os.path.join(out, "model.npz"), params, meta={"config_hash": digest})
    io.write_json(os.path.join(out, "summary.json"), {"method": method, "scene": config.get("scene"),
                                                      "config_hash": digest, "output": out})
    return out


def run_file(path: str, preset: str | None = None, overrides: Sequence[str] = ()) -> dict:
    """Run an experiment file as ``jprt run path --preset preset --set ...`` does; returns the summary."""
    from jprt.experiment import load_experiment, resolve_config

    module = load_experiment(path)
    config = resolve_config(module, list(overrides), preset)
    return module.main(config) if callable(getattr(module, "main", None)) else run(module, config)


def preset_benchmark(description: str, experiment: str, out: str, argv: Sequence[str] | None = None):
    """A benchmark script's run of one experiment file: parses ``--preset`` (default "small") and
    ``--out`` (default ``out``) from ``argv`` (default the command line), runs ``experiment`` at
    that preset (``run_file``) and returns (the parsed arguments, ``flat_summary`` of its summary)."""
    import argparse

    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("--preset", default="small")
    parser.add_argument("--out", default=out)
    args = parser.parse_args(argv)
    return args, flat_summary(run_file(experiment, args.preset))


def flat_summary(summary: dict) -> dict:
    """The summary with its ``extra`` entries lifted to the top level (the common keys win)."""
    return {**summary.get("extra", {}), **{k: v for k, v in summary.items() if k != "extra"}}
