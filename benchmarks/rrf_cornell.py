"""RRF speed-accuracy benchmark on the built-in Cornell box (Ren et al. 2013, §5).

Runs experiments/rrf_cornell.py with a named preset (default ``small``), then writes the
numbers the RRF issue asks for, with the targets and whether they were met, to
benchmarks/results/rrf_<preset-or-cornell>.json. Nothing is copied by hand: every value comes from
the run's summary.json (its folder is recorded too).

    python benchmarks/rrf_cornell.py                 # small config, ~1 hour on a 2-core CPU
    python benchmarks/rrf_cornell.py --preset paper  # on a machine with an accelerator
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import sys

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)

KEYS = ("indirect_rmse", "reference_spp", "equal_error_spp", "pathtrace_ms_equal_error", "eval_ms_512_1light",
        "eval_ms_512_4lights", "speedup_equal_error", "n_leaves", "model_bytes", "train_s", "rmse_basic_attributes",
        "rmse_augmented", "rmse_single_mlp_same_params", "std_subsets", "std_inits")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--preset", default="small")
    parser.add_argument("--set", dest="overrides", action="append", default=[])
    parser.add_argument("--out", default=None, help="results JSON (default benchmarks/results/rrf_cornell.json "
                                                    "for the small preset, rrf_cornell_<preset>.json otherwise)")
    args = parser.parse_args()
    sys.path.insert(0, ROOT)
    import jax

    from jprt.cli import load_experiment, resolve_config
    from jprt.io import write_json

    module = load_experiment(os.path.join(ROOT, "experiments", "rrf_cornell.py"))
    config = resolve_config(module, args.overrides, args.preset)
    summary = module.main(config)
    result = {k: summary.get(k) for k in KEYS}
    result.update({
        "targets": {
            "speedup_equal_error >= 50": summary["speedup_equal_error"] >= 50,
            "augmented beats basic attributes": summary["rmse_augmented"] < summary["rmse_basic_attributes"],
            "partitioned RRF beats one MLP of the same parameter count":
                summary["indirect_rmse"] < summary["rmse_single_mlp_same_params"],
        },
        "context": {
            "command": "python benchmarks/rrf_cornell.py " + " ".join(
                [f"--preset {args.preset}"] + [f"--set {o}" for o in args.overrides]),
            "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "device": f"{platform.machine()} CPU, {os.cpu_count()} cores; jax {jax.__version__} "
                      f"({jax.default_backend()}); Mitsuba llvm_ad_rgb",
            "preset": args.preset,
            "report": summary["output"],
            "config_hash": summary["config_hash"],
            "n_samples": summary["n_samples"],
            "n_params": summary["n_params"],
            "test_pairs_views_x_lights": summary["test_pairs"],
            "test_resolution": summary["test_resolution"],
            "indirect_relative_rmse": summary["indirect_relative_rmse"],
            "equal_error_search": summary["pathtrace_rmse_by_spp"],
            "pathtrace_note": summary["pathtrace_note"],
            "single_mlp": summary.get("single_mlp"),
            "robustness": summary.get("robustness"),
            "fig6_training_size": summary.get("fig6_training_size"),
            "fig7_training_spp": summary.get("fig7_training_spp"),
            "tree_levels": summary["tree_levels"],
            "leaves_per_object": summary["leaves_per_object"],
            "total_s": summary["total_s"],
        },
    })
    name = "rrf_cornell.json" if args.preset == "small" else f"rrf_cornell_{args.preset}.json"
    path = args.out or os.path.join(HERE, "results", name)
    write_json(path, result)
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
