"""ONNX frame times of the neural evaluators beside JAX's (``jprt export``'s ONNX models).

For RRF, neural-wavelet PRT and SG environment visibility: the ``test`` preset fitted (or a run
folder given with ``--run NAME=FOLDER``), exported with ``jprt.export.export_run`` at a
``size`` x ``size`` frame of the run's default view (256^2 by default), then on the same frame
and lighting: the jitted JAX evaluator and onnxruntime's CPU provider on ``evaluator.onnx``, each
timed as the median of ``repeats`` calls after warm-up, in one process on one machine, with the
largest difference between their frames relative to the frame's peak, and the JAX frame against
its roofline (``Method.frame_report``: the method's own roof where it has one, RRF's networks,
else the matmul rate; the triad bandwidth measured in the same process; the method's or XLA's FLOP
count and XLA's bytes). The device (CPU model, thread counts, versions) is recorded
with the numbers.

    python benchmarks/export.py                          # -> benchmarks/results/export.json
    python benchmarks/export.py --size 128 --repeats 5
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import sys
import tempfile
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

METHODS = ("rrf", "wavelet_prt", "sg_environment")


def _cpu_model() -> str:
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def measure(name: str, run: str | None, size: int, repeats: int, work: str) -> dict:
    """One method's ONNX and JAX frame times at ``size``^2 (module docstring)."""
    import jax
    import numpy as np

    from jprt import eval as jeval
    from jprt.export import export_run, load, read_manifest
    from jprt.export import onnx as jonnx
    from jprt.methods import REGISTRY
    from jprt.runner import save_fit
    from jprt.view import Session

    m = REGISTRY[name]
    if run is None:
        config = m.resolve(m.presets["test"])
        result = m.fit(m.make_dataset(config["scene"], config), config)
        run = save_fit(os.path.join(work, f"run_{name}"), name, config, result.params)
    out = os.path.join(work, f"export_{name}")
    t0 = time.perf_counter()
    export_run(run, out, size=size)
    export_s = time.perf_counter() - t0
    manifest = read_manifest(out)
    back = load(out)
    s = Session(run)  # the frame the export was made at: the run's view at size^2, its default lighting
    inputs, lighting = s.inputs(size), s.method_lighting()
    feeds = dict(zip(jonnx.input_names(inputs, lighting),
                     [np.asarray(x) for x in jax.tree_util.tree_leaves((inputs, lighting))]))
    fast = jax.jit(back.evaluate)
    want = np.asarray(fast(inputs, lighting))
    jax_ms = jeval.time_call(fast, inputs, lighting, repeats=repeats)["median_ms"]
    roof = m.frame_report(back.params, back.config, fast, inputs, lighting, jax_ms, repeats=repeats)

    import onnxruntime as ort

    options = ort.SessionOptions()
    options.log_severity_level = 3
    session = ort.InferenceSession(os.path.join(out, "evaluator.onnx"), options, providers=["CPUExecutionProvider"])
    got = session.run(None, feeds)[0]
    onnx_ms = jeval.time_call(session.run, None, feeds, repeats=repeats)["median_ms"]
    peak = float(np.abs(want).max())
    return {"frame_resolution": [size, size], "jax_frame_ms": jax_ms, "onnx_frame_ms": onnx_ms,
            "onnx_over_jax": onnx_ms / jax_ms, "max_abs_difference_over_peak": float(np.abs(got - want).max()) / peak,
            "frame_peak": peak, "export_s": export_s,
            # the JAX frame's (Method.frame_report: the method's own roof where it has one), measured in this process
            "roofline": roof["roofline"], "roofline_matmul": roof["roofline_matmul"],
            "onnx_bytes": os.path.getsize(os.path.join(out, "evaluator.onnx")),
            "hand_written": sorted(manifest["onnx"]["hand_written"]), "onnx_opset": manifest["onnx"]["opset"],
            "inputs": {i["name"]: i["shape"] for i in manifest["onnx"]["inputs"]},
            "run": None if run.startswith(work) else os.path.abspath(run),
            "preset": "test" if run.startswith(work) else "given"}


def main(argv: list[str] | None = None) -> int:
    """Measure every method of ``--methods`` and write the JSON (module docstring); returns 0."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--size", type=int, default=256)
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--run", action="append", default=[], metavar="NAME=FOLDER",
                        help="a run folder to export instead of fitting the test preset (repeatable)")
    parser.add_argument("--methods", default=",".join(METHODS))
    parser.add_argument("--out", default=os.path.join(ROOT, "benchmarks", "results", "export.json"))
    args = parser.parse_args(argv)
    import jax
    import onnxruntime

    from jprt import __version__, io

    runs = dict(item.split("=", 1) for item in args.run)
    results = {}
    with tempfile.TemporaryDirectory(prefix="jprt_export_bench_") as work:
        for name in args.methods.split(","):
            print(f"[export bench] {name} at {args.size}^2", file=sys.stderr, flush=True)
            results[name] = measure(name, runs.get(name), args.size, args.repeats, work)
            r = results[name]
            print(f"[export bench] {name}: JAX {r['jax_frame_ms']:.2f} ms, ONNX {r['onnx_frame_ms']:.2f} ms "
                  f"({r['onnx_over_jax']:.2f}x), max |diff| / peak {r['max_abs_difference_over_peak']:.2e}",
                  file=sys.stderr, flush=True)
    record = {
        "what": "ONNX (onnxruntime, CPU provider) against JAX (jitted) frame times of the neural evaluators' "
                "exports, same frame and lighting, median of repeats after warm-up",
        "date": datetime.date.today().isoformat(),
        "device": {"cpu": _cpu_model(), "cpu_count": os.cpu_count(), "jax_device": jax.devices()[0].device_kind,
                   "jax": jax.__version__, "onnxruntime": onnxruntime.__version__,
                   "onnxruntime_threads": "default (one per core)", "jprt": __version__},
        "repeats": args.repeats, "methods": results}
    io.write_json(args.out, record)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
