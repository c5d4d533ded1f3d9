"""SG light-field textures benchmark (Currius et al. 2020) on the glossy Cornell receivers.

Runs experiments/sg_lightfield.py with the ``small`` preset (64^2 atlas, 32^2 maps, 16 lobes) and
writes the numbers issue 15 asks for, with its targets and whether they were met, to
benchmarks/results/sg_lightfield.json. Every value is read from the run's summary.json (its
folder is recorded).

    python benchmarks/sg_lightfield.py                 # ~30 min on a 2-core CPU
"""

from __future__ import annotations

import os
import sys

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)

KEYS = ("fit_log_l2", "fit_s", "midpoint_log_l2", "midpoints", "log_l2_by_lobes", "psnr_indirect_by_lobes",
        "frame_ms_by_lobes", "psnr_indirect", "ssim_indirect", "psnr_full", "lpips_indirect", "indirect_rel_rmse",
        "psnr_indirect_by_roughness", "psnr_indirect_baselines", "psnr_oct_quadrature", "psnr_lobes_quadrature",
        "psnr_indirect_appendix_b", "psnr_indirect_by_space", "frame_ms_by_space",
        "reference_noise_psnr",
        "psnr_env_we", "psnr_env_reflected_visibility", "psnr_env_no_visibility", "psnr_env_we_raw",
        "psnr_env_quadrature",
        "env_fit_log_l2", "env_texels", "env_map", "roofline", "frame_ms", "frame_resolution", "frame_ms_by_resolution",
        "equal_error_spp", "pathtrace_ms_equal_error", "pathtrace_curve", "speedup_equal_error", "pathtrace_note",
        "bytes_per_texel", "psnr_delta_fp16", "psnr_indirect_fp32_lobes", "texels", "texels_inside",
        "texels_pushed", "capture_s", "train_s", "model_bytes")


def targets(s: dict) -> dict:
    """Issue 15's targets, each True / False as measured."""
    mid = s["midpoint_log_l2"]
    return {
        "midpoint_log_l2.cnn <= 0.8 x min(gd, em)": mid["cnn"] <= 0.8 * min(mid["gd"], mid["em"]),
        "psnr_indirect >= psnr_indirect_baselines.fixed_axes + 3 dB":
            s["psnr_indirect"] >= s["psnr_indirect_baselines"]["fixed_axes"] + 3.0,
        "psnr_indirect >= psnr_oct_quadrature - 3 dB": s["psnr_indirect"] >= s["psnr_oct_quadrature"] - 3.0,
        "psnr_env_we >= psnr_env_reflected_visibility + 2 dB":
            s["psnr_env_we"] >= s["psnr_env_reflected_visibility"] + 2.0,
        "speedup_equal_error >= 100": s["speedup_equal_error"] >= 100,
        "bytes_per_texel == 224 at 16 lobes": s["bytes_per_texel"] == 224,
        "|psnr_delta_fp16| <= 0.1 dB": abs(s["psnr_delta_fp16"]) <= 0.1,
    }


def main() -> int:
    sys.path.insert(0, ROOT)
    from jprt.eval import write_benchmark
    from jprt.runner import preset_benchmark

    args, s = preset_benchmark(__doc__.split("\n")[0], os.path.join(ROOT, "experiments", "sg_lightfield.py"),
                                 os.path.join(HERE, "results", "sg_lightfield.json"))
    result = {k: s.get(k) for k in KEYS}
    result["targets"] = targets(s)
    # FLOPs of the evaluator's program (XLA's count) beside its time, and the machine's matmul rate,
    # measured here in the same process after the run: the run's texture and held-out G-buffer
    sys.path.insert(0, HERE)
    from sg_lightfield_device import export, measure

    export(s["output"], os.path.join(s["output"], "device_inputs.npz"))
    result["evaluator_cost"] = measure(os.path.join(s["output"], "device_inputs.npz"), lobes=(4, 16, 64))
    result["report"] = s["output"]
    result["config_hash"] = s["config_hash"]
    write_benchmark(args.out, result, f"python benchmarks/sg_lightfield.py --preset {args.preset}",
                    notes="PSNR / SSIM on sRGB-tonemapped, clipped images (peak 1), mean over the held-out views, "
                          "over the whole image whose non-receiver pixels are 0 in prediction and reference "
                          "(psnr_indirect_by_roughness: that receiver's pixels alone); indirect = Mitsuba full minus "
                          "direct; psnr_env_*: Mitsuba's direct light (max_depth 2) of the receivers in the open-top box "
                          "under env_map; fit_log_l2: Eq. 9 at the pixel centres (solid-angle weighted, below-surface "
                          "masked); midpoint_log_l2: the same loss of lobes interpolated halfway between two baked "
                          "texels against the light field captured there; frame_ms: the jitted JAX evaluator on this "
                          "CPU at its default shading.space (auto: texture space where the atlas has no more texels "
                          "than the frame has pixels), G-buffer given; psnr_indirect_by_space / frame_ms_by_space: "
                          "the same lobes shaded per pixel (§6) and per texel in the same run; speedup against "
                          "Mitsuba's indirect (full + direct renders) at equal RMSE; evaluator_cost: the same "
                          "evaluator re-timed after the run at 128^2 to 1920x1080 (larger frames nearest-resampled from the 512^2 held-out "
                          "G-buffer), XLA's FLOP count of each program, the f32 matmul rate measured in the same "
                          "process, and random textures of 4 / 16 / 64 lobes at 1080p.")
    return 0


if __name__ == "__main__":
    sys.exit(main())
