"""SG environment visibility benchmark (Currius et al. 2020, §5): experiments/sg_environment.py at
its default (``small``) preset, its frame judged against the machine.

Writes benchmarks/results/sg_environment.json: the held-out score (relative RMSE and PSNR of the
receivers' direct light, per lighting), the 256^2 frame's time, FLOPs and roofline (the f32 matmul
rate and a streaming triad measured in the same process: ``jprt.eval.roofline``), and the equal-error
point on Mitsuba's curve. Every value is read from the run's summary.json (its folder is recorded).

    python benchmarks/sg_environment.py              # ~10 min on a 2-core CPU with the capture cached
"""

from __future__ import annotations

import os
import sys

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)

#: summary keys copied as they are (``extra``'s lifted to the top level)
KEYS = ("indirect_rmse", "indirect_rel_rmse", "indirect_rel_rmse_worst_image", "psnr_indirect", "psnr_by_lighting",
        "rel_rmse_by_lighting", "ssim_indirect", "frame_ms", "frame_ms_min", "frame_resolution", "frame_flops",
        "frame_flops_source", "matmul_peak_gflops", "flops_fraction_of_peak", "roofline", "equal_error_spp",
        "pathtrace_ms_equal_error", "speedup_equal_error", "pathtrace_rmse_by_spp", "model_bytes", "train_s",
        "dataset_s", "config_hash")


def main() -> int:
    sys.path.insert(0, ROOT)
    from jprt.eval import write_benchmark
    from jprt.runner import preset_benchmark

    args, summary = preset_benchmark(__doc__.split("\n")[0], os.path.join(ROOT, "experiments", "sg_environment.py"),
                                 os.path.join(HERE, "results", "sg_environment.json"))
    result = {k: summary.get(k) for k in KEYS}
    roof = summary.get("roofline") or {}
    result["targets"] = {"fraction_of_roofline >= 0.5 (issue 49)": (roof.get("fraction_of_roofline") or 0.0) >= 0.5}
    result["preset"] = args.preset
    result["report"] = summary["output"]
    write_benchmark(args.out, result, f"python benchmarks/sg_environment.py --preset {args.preset}",
                    notes="indirect_* hold the method's prediction of the receivers' direct light (the environment "
                          "reflected once, visibility included) against Mitsuba's at eval.reference_spp over the "
                          "held-out views x lightings (the map W_E was computed for, the same map turned, a "
                          "synthetic sky); frame_ms: the jitted evaluator on the first held-out view at "
                          "eval.timing_resolution under the bake's map; "
                          "roofline: jprt.eval.roofline (XLA's FLOPs and bytes, the f32 matmul rate and the "
                          "in-place triad of this process).")
    return 0


if __name__ == "__main__":
    sys.exit(main())
