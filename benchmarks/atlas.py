"""The speed-accuracy atlas benchmark: experiments/atlas.py (``jprt.atlas`` on its built-in tasks)
at the ``small`` preset.

Writes benchmarks/results/atlas.json (per task, per method: the swept points with the common
summary keys, their Pareto fronts, Mitsuba's (spp, ms, rmse) curve measured in the same run), the
figures benchmarks/results/atlas_<task>.png and the README table benchmarks/results/atlas.md.
Every number is read from the run's own atlas.json (its folder is recorded, relative to the
repository); a re-run reuses the finished sweep points and cached renders, and re-measures
Mitsuba's curve. ``jprt atlas`` runs the same on one task or on any scene file.

    python benchmarks/atlas.py                  # the small atlas (< 90 min on a 2-core CPU, cold cache),
                                                # each method's cheapest point with relative RMSE <= 0.35
    python benchmarks/atlas.py --preset test    # seconds
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--preset", default="small")
    parser.add_argument("--runs", default=os.path.join(ROOT, "results", "atlas"), help="output.dir of the sweeps")
    parser.add_argument("--out", default=os.path.join(HERE, "results"), help="folder of atlas.json and the figures")
    parser.add_argument("--select", default="indirect_rel_rmse<=0.35", help="error target of the selection")
    parser.add_argument("--minimize", default="frame_ms", help="the cost the selection minimises")
    args = parser.parse_args()
    sys.path.insert(0, ROOT)
    from jprt.eval import write_benchmark
    from jprt.runner import run_file

    t0 = time.perf_counter()
    record = run_file(os.path.join(ROOT, "experiments", "atlas.py"), args.preset,
                      [f"output.dir={args.runs}", f"eval.select={args.select}", f"eval.minimize={args.minimize}"])
    wall_s = time.perf_counter() - t0
    os.makedirs(args.out, exist_ok=True)
    for task in record["tasks"]:
        shutil.copyfile(os.path.join(args.runs, f"atlas_{task}.png"), os.path.join(args.out, f"atlas_{task}.png"))
    shutil.copyfile(os.path.join(args.runs, "atlas.md"), os.path.join(args.out, "atlas.md"))
    record["preset"] = args.preset
    record["wall_s"] = wall_s
    record["runs"] = os.path.relpath(os.path.abspath(args.runs), ROOT)  # no machine's own folder in the record
    command = f"python benchmarks/atlas.py --preset {args.preset} --select '{args.select}' --minimize {args.minimize}"
    write_benchmark(os.path.join(args.out, "atlas.json"), record, command,
                    notes="indirect RMSE over every valid pixel and channel of a task's held-out images (linear "
                          "HDR); PSNR / SSIM / FLIP / LPIPS on sRGB-tonemapped images; frame_ms: one jitted "
                          "evaluator call at eval.timing_resolution on this CPU (JAX), Mitsuba's ms: one "
                          "llvm_ad_rgb frame (full + direct renders) at the same resolution; equal-error spp read "
                          "off Mitsuba's curve; wall_s includes dataset renders unless they were cached")
    return 0


if __name__ == "__main__":
    sys.exit(main())
