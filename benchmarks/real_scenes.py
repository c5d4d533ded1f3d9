"""Real-scene benchmark (issues 21, 45): experiments/real_scenes.py on the four Bitterli interiors of
../shared/assets/scenes, every number read from the run's report.json.

    python benchmarks/real_scenes.py            # hours on a 2-core CPU (references until their noise is small)
    python benchmarks/real_scenes.py --scene living-room/scene.xml --merge   # one scene, the others kept

``--scene`` runs one scene file of the experiment's list (the others' entries of ``--out`` are
kept with ``--merge``; each scene records the command and config hash that measured it, and
``missing`` lists the experiment's scenes the file has no entry for yet).

Per scene and method: per judged object (>= 1 % of a view, not purely specular, not an emitter)
the relative RMSE of the indirect light with the references' own noise removed, the raw score and
the noise floor, the method's self-check, the evaluator's frame time and the fit time, or the
``failed`` error of a method that raised; the objects scored apart; the spp the references needed;
the target (every judged object <= 0.35 and their mean <= 0.25, noise removed) as measured.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)

#: per-method keys copied from the report as they are
METHOD_KEYS = ("lighting", "worst_rel_rmse", "worst_rel_rmse_noise_removed", "mean_rel_rmse_noise_removed",
               "target_met", "frame_ms", "frame_flops", "frame_flops_source", "flops_fraction_of_peak",
               "speedup_vs_reference_render", "roofline", "roofline_matmul", "roofline_detail", "frame_resolution",
               "dataset_s", "fit_s", "grouped_objects", "skipped_objects", "failed")


def summary(report: dict) -> dict:
    """The benchmark's record of a real_scenes report: per scene and method, the keys of
    ``METHOD_KEYS``, per-object scores and the self-check."""
    result = {"scenes": {}, "not_run": report["not_run"], "config_hash": report["config_hash"],
              "target_met_everywhere": report["target_met_everywhere"], "total_s": report["total_s"],
              "matmul_peak_gflops": report["matmul_peak_gflops"]}
    for scene, entry in report["scenes"].items():
        if "failed" in entry:
            result["scenes"][scene] = {"failed": entry["failed"]}
            continue
        methods = {}
        for name, m in entry["methods"].items():
            out = {k: m[k] for k in METHOD_KEYS if k in m}
            if "failed" not in m:
                out["per_object"] = {k: {"rel_rmse_noise_removed": v["rel_rmse_noise_removed"], "rel_rmse": v["rel_rmse"],
                                         "noise_floor": v["noise_floor"], "scale": v["scale"],
                                         "mean_ratio": v["mean_ratio"], "rel_rmse_by_lighting": v["rel_rmse_by_lighting"]}
                                     for k, v in m["per_object"].items()}
                out["apart"] = {k: {"rel_rmse": v["rel_rmse"], "why": v["why"]} for k, v in m["apart"].items()}
                check = m.get("self_check")
                out["self_check"] = None if check is None else {
                    k: check.get(k) for k in ("rel_rmse", "per_object", "train_rel_rmse", "held_out", "warning")}
            methods[name] = out
        result["scenes"][scene] = {"objects": len(entry["objects"]), "regions": entry["regions"],
                                   "cameras": entry["cameras"], "setups": entry["setups"], "methods": methods,
                                   "side_by_side": entry["side_by_side"]}
        if "environment" in entry:  # the opening the environment-lit methods saw, and their held-out maps
            result["scenes"][scene]["environment"] = entry["environment"]
    return result


def merged(old: dict | None, new: dict, scenes: list[str]) -> dict:
    """``new`` (a ``summary``) with the scene entries of ``old`` that ``new`` does not measure, and
    in a scene it measures the method entries it does not (``--merge``; each keeps its
    ``measured``: the command, date and config hash that measured it); ``missing``: the stems of ``scenes`` without an entry; ``target_met_everywhere``
    over the entries present (False while any is missing)."""
    out = dict(new)
    before = {} if old is None else old.get("scenes", {})
    out["scenes"] = {**before, **new["scenes"]}
    for scene, entry in new["scenes"].items():  # a scene run for some methods keeps the others' entries
        if "methods" not in entry:  # the scene failed as a whole
            continue
        kept = {m: e for m, e in before.get(scene, {}).get("methods", {}).items() if m not in entry["methods"]}
        if not kept:
            continue
        for e in kept.values():
            e.setdefault("measured", {k: before[scene].get(k) for k in ("command", "date", "config_hash")})
        entry["methods"] = {**kept, **entry["methods"]}
        # the set-ups (lightings, references) the kept methods were judged under, where this run had none
        entry["setups"] = {**before[scene].get("setups", {}), **entry.get("setups", {})}
        if "environment" in before[scene] and "environment" not in entry:
            entry["environment"] = before[scene]["environment"]
    stems = [os.path.basename(os.path.dirname(s)) for s in scenes]
    out["missing"] = [s for s in stems if s not in out["scenes"]]
    out["target_met_everywhere"] = not out["missing"] and all(
        "failed" not in e and all(m.get("target_met") for m in e["methods"].values()) for e in out["scenes"].values())
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--preset", default=None)
    parser.add_argument("--set", action="append", default=[], help="config override KEY=VALUE (as jprt run)")
    parser.add_argument("--scene", default=None, help="run only this scene file (relative to the assets folder)")
    parser.add_argument("--merge", action="store_true",
                        help="keep --out's entries of the scenes not run, and of the methods not run in a scene that is")
    parser.add_argument("--out", default=os.path.join(HERE, "results", "real_scenes.json"))
    args = parser.parse_args()
    sys.path.insert(0, ROOT)
    from jprt.experiment import load_experiment, resolve_config
    from jprt.eval import write_benchmark

    module = load_experiment(os.path.join(ROOT, "experiments", "real_scenes.py"))
    every = resolve_config(module, args.set, args.preset)["scenes"]
    extra = [f"scenes=[{json.dumps(args.scene)}]"] if args.scene else []
    report = module.main(resolve_config(module, args.set + extra, args.preset))
    command = "python benchmarks/real_scenes.py" + (f" --preset {args.preset}" if args.preset else "") + "".join(
        f" --set '{s}'" for s in args.set) + (f" --scene {args.scene}" if args.scene else "") + (
        " --merge" if args.merge else "")
    result = summary(report)
    for entry in result["scenes"].values():  # each scene says what measured it (--merge keeps others')
        entry.update({"command": command, "config_hash": report["config_hash"], "date": time.strftime("%Y-%m-%d"),
                      "run_total_s": report["total_s"], "matmul_peak_gflops": report["matmul_peak_gflops"]})
        for method in entry["methods"].values():
            method["measured"] = {k: entry[k] for k in ("command", "date", "config_hash")}
    old = None
    if args.merge and os.path.exists(args.out):
        with open(args.out) as f:
            old = json.load(f)
    write_benchmark(args.out, merged(old, result, every), command,
                    notes="relative RMSE = ||prediction - reference|| / ||reference|| over an object's pixels in every "
                          "held-out view and lighting (linear HDR indirect light, Mitsuba full minus direct along the "
                          "pixel-centre rays the methods' G-buffers read); an object darker than 0.1 of its images' RMS "
                          "is scored on that image scale (scale 'image'); predicting zero scores 1 on a lit object; "
                          "noise_floor: the second reference set against the first; rel_rmse_noise_removed: "
                          "sqrt(rel^2 - floor^2 / 2); setups.*.reference_spp: the spp per view and lighting the "
                          "references needed for their own noise to be <= 1/3 of the target on every judged object "
                          "(or the cap); apart: objects scored outside the target, with the reason; self_check: the "
                          "method's score on held-out data of its own training renders; frame_ms: the jitted evaluator "
                          "at the file camera's held-out resolution; pathtracer: Mitsuba's time for one reference "
                          "frame of the same view (the peer).")
    return 0


if __name__ == "__main__":
    sys.exit(main())
