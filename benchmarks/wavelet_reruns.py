"""Neural-wavelet PRT across machines: the ``small`` model rebuilt from nothing, twice (issue 18).

Each rerun is a fresh process with an empty jprt dataset cache (Mitsuba renders the training
images and the held-out references again), JAX's persistent compilation cache off, and its own
XLA CPU flags standing in for a second machine (another vector width and optimisation level
change the generated code the way another CPU does). It trains the default model of
experiments/wavelet_prt_cornell.py's ``small`` preset and scores the benchmark's far views under
every held-out map, exactly as ``wavelet_prt.json`` does. The spread is the largest difference
between the reruns' mean PSNR (``psnr_spread_reruns``), per map too. Results go to
benchmarks/results/wavelet_reruns.json; ``benchmarks/wavelet_prt.py`` copies the spread into
wavelet_prt.json when the model config (``wavelet_prt.model.run_key``) is the one it ran.

    python benchmarks/wavelet_reruns.py          # ~20 min on a 2-core CPU (two reruns)
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
EXPERIMENT = os.path.join(ROOT, "experiments", "wavelet_prt_cornell.py")
OUT = os.path.join(HERE, "results", "wavelet_reruns.json")

#: (name, XLA_FLAGS) of each rerun: XLA's default code, and code built for 128-bit vectors without
#: LLVM's optimisation passes (what a CPU without AVX, or another compiler set-up, runs).
RERUNS = (("default XLA flags", ""),
          ("128-bit vectors, LLVM optimisation off",
           "--xla_cpu_prefer_vector_width=128 --xla_backend_optimization_level=0"))


def experiment_config(preset: str):
    """(the experiment module, its resolved config for ``preset``, the method, the method's config)."""
    sys.path.insert(0, ROOT)
    from jprt.experiment import load_experiment, resolve_config
    from jprt.methods import REGISTRY
    from jprt.runner import method_config

    module = load_experiment(EXPERIMENT)
    config = resolve_config(module, [], preset)
    method = REGISTRY[module.METHOD]
    return module, config, method, method_config(method, config)


def child(preset: str, out: str) -> None:
    """One rerun in this process: dataset, training, far-view PSNR per held-out map -> ``out``."""
    import jax
    import numpy as np

    from jprt.methods.wavelet_prt import model as wp
    from jprt.methods.wavelet_prt.evaluation import far_map_scores

    module, config, method, cfg = experiment_config(preset)
    t0 = time.perf_counter()
    data = method.make_dataset(config["scene"], cfg)
    dataset_s = time.perf_counter() - t0
    result = wp.fit(data, cfg, progress=False)
    scores = far_map_scores(wp.evaluator(result.params, cfg), data, float(config["eval"]["exposure"]),
                            module.ORIGINAL_PAIR)
    with open(out, "w") as f:
        json.dump({**scores, "run_key": wp.run_key(cfg), "dataset_s": dataset_s,
                   "train_s": float(result.info["train_s"]), "final_loss": float(np.asarray(result.info["losses"])[-1]),
                   "xla_flags": os.environ.get("XLA_FLAGS", ""), "jax": jax.__version__,
                   "compilation_cache": bool(jax.config.jax_enable_compilation_cache)}, f)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--preset", default="small")
    parser.add_argument("--out", default=OUT)
    parser.add_argument("--child", default=None, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        child(args.preset, args.child)
        return 0
    sys.path.insert(0, ROOT)
    from jprt.eval import write_benchmark

    runs = []
    with tempfile.TemporaryDirectory(prefix="jprt_reruns_") as tmp:
        for i, (name, flags) in enumerate(RERUNS):
            cache = os.path.join(tmp, f"cache{i}")
            os.makedirs(cache)
            env = {**os.environ, "JPRT_CACHE": cache, "XLA_FLAGS": flags, "JAX_ENABLE_COMPILATION_CACHE": "false"}
            out = os.path.join(tmp, f"run{i}.json")
            t0 = time.perf_counter()
            print(f"rerun {i + 1}/{len(RERUNS)} ({name}): empty cache {cache}", flush=True)
            subprocess.run([sys.executable, os.path.abspath(__file__), "--preset", args.preset, "--child", out],
                           env=env, check=True, cwd=ROOT)
            with open(out) as f:
                run = json.load(f)
            run.update(name=name, wall_s=time.perf_counter() - t0)
            print(f"  PSNR indirect far {run['psnr_indirect_far']:.3f} dB (worst {run['psnr_indirect_far_worst']:.3f}), "
                  f"{run['wall_s']:.0f} s", flush=True)
            runs.append(run)
    keys = {r["run_key"] for r in runs}
    if len(keys) != 1:
        raise RuntimeError(f"the reruns trained different configs: {sorted(keys)}")
    spread = lambda v: float(max(v) - min(v))  # noqa: E731
    maps = sorted(runs[0]["psnr_indirect_far_by_map"])
    by_map = {m: spread([r["psnr_indirect_far_by_map"][m] for r in runs]) for m in maps}
    result = {
        "psnr_spread_reruns": spread([r["psnr_indirect_far"] for r in runs]),
        "psnr_spread_reruns_by_map": by_map,
        "psnr_spread_reruns_worst_map": max(by_map.values()),
        "psnr_spread_reruns_worst": spread([r["psnr_indirect_far_worst"] for r in runs]),
        "run_key": runs[0]["run_key"],
        "reruns": runs,
    }
    result["targets"] = {"psnr_spread_reruns <= 0.3": result["psnr_spread_reruns"] <= 0.3}
    write_benchmark(args.out, result, f"python benchmarks/wavelet_reruns.py --preset {args.preset}",
                    preset=args.preset,
                    notes="each rerun: a fresh process, an empty dataset cache (renders redone), JAX's "
                          "compilation cache off, its own XLA_FLAGS; PSNR as in wavelet_prt.json (far views, "
                          "every held-out map, tonemapped, the default K)")
    print(f"psnr_spread_reruns {result['psnr_spread_reruns']:.3f} dB (per map up to "
          f"{result['psnr_spread_reruns_worst_map']:.3f}) -> {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
