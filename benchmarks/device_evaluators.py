"""Evaluator frame times on whatever JAX device is present (issue 17's accelerator check): the
RRF of a finished ``rrf_cornell`` run at 512^2 with one and four lights (its trained tree: the
renderer's cost follows the leaves each tile reaches), and neural-wavelet PRT networks of the
``small`` and ``paper`` sizes at 256^2 and 512^2, K = 64, on the same Cornell G-buffer.

The wavelet networks are freshly initialised, not trained: their cost does not depend on the
weights' values (dense layers, a hash-grid lookup, a top-K of the lighting), so a frame time of
an initialised network is the trained one's; their images are not compared with anything.

Each frame comes with its FLOP count (the method's own ``frame_flops``), the device's matmul rate
measured in the same process (float32 at JAX's default precision, which lets XLA use TF32 on
NVIDIA GPUs, and at "highest", and bfloat16) and the fraction of the float32 rate achieved. The
RRF's frames are also compared with the same frames rendered here on the CPU (the export), at
the default precision and at "highest": a TF32 dot has a 10-bit mantissa, which a tanh network
whose outputs are differences of large terms may not tolerate.

    python benchmarks/device_evaluators.py export results/rrf_cornell/<hash> .gpu/rrf.npz   # here (Mitsuba)
    python benchmarks/device_evaluators.py measure .gpu/rrf.npz out.json                    # on the device
"""

from __future__ import annotations

import json
import os
import sys
import traceback

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

#: RRF renderer layouts (``render.tile``, ``render.chunk``) timed besides the automatic one
#: (``jprt.methods.rrf.model.render_layout``).
RRF_LAYOUTS = ((8, 64), (8, 512), (16, 64), (16, 256), (32, 64))
#: neural-wavelet PRT ``render.chunk`` values (pixels per step) timed besides the automatic one.
WAVELET_CHUNKS = ()


def export(run_dir: str, out: str) -> None:
    """The run's RRF, its 512^2 timing G-buffer (the first held-out view, rendered by Mitsuba), the
    one- and four-light inputs of ``experiments/rrf_common.py``'s timing, and the CPU's frames,
    times and FLOP counts for them, in one .npz."""
    import jax

    from jprt import eval as jeval
    from jprt import io
    from jprt.methods import REGISTRY
    from jprt.methods.rrf import model as rrf
    from jprt.render import cameras as cams
    from jprt.render.gbuffer import gbuffer
    from jprt.render.scenes import SceneHandle
    from jprt.runner import method_config

    sys.path.insert(0, os.path.join(ROOT, "experiments"))
    import rrf_common

    with open(os.path.join(run_dir, "config.json")) as f:
        config = json.load(f)["config"]
    params = io.load_tree(os.path.join(run_dir, "model.npz"))[0]
    mc = method_config(REGISTRY["rrf"], config)
    cameras, lightings = rrf_common.held_out_pairs(config)
    res = int(config["eval"]["timing_resolution"])
    c0 = cameras[0]
    cam = cams.look_at(c0.origin, c0.target, fov=c0.fov, width=res, height=res)
    gb = gbuffer(SceneHandle(config["scene"], lightings[0]), cam)
    four = rrf_common.four_light_inputs(config)
    evaluate = REGISTRY["rrf"].evaluator(params, mc)
    fast = jax.jit(evaluate)
    arrays, meta = {}, {"run": os.path.abspath(run_dir), "method_config": mc, "cpu": {}}
    for name, lights in (("1light", lightings[0]), ("4lights", four)):
        arrays[f"{name}_position"] = np.asarray(lights.position, np.float32)
        arrays[f"{name}_intensity"] = np.asarray(lights.intensity, np.float32)
        arrays[f"{name}_cpu_frame"] = np.asarray(evaluate(gb, lights))
        meta["cpu"][name] = {"frame_ms": jeval.time_call(fast, gb, lights, repeats=10)["median_ms"],
                             "frame_flops": rrf.frame_flops(params, mc, gb, lights)}
    meta["cpu"]["matmul_peak_gflops"] = jeval.matmul_peak_gflops()
    meta["cpu"]["device"] = jax.devices()[0].device_kind
    arrays.update({f"gb_{f}": np.asarray(getattr(gb, f)) for f in gb._fields})
    os.makedirs(os.path.dirname(os.path.abspath(out)), exist_ok=True)
    io.save_checkpoint(out + ".params.npz", params, meta=meta)
    np.savez_compressed(out, **arrays)
    print(f"wrote {out} and {out}.params.npz; CPU: {json.dumps(meta['cpu'])}")


def _time(fn, *args, repeats: int = 20) -> dict:
    from jprt.eval import time_call

    t = time_call(fn, *args, repeats=repeats, warmup=3)
    return {"median_ms": t["median_ms"], "min_ms": t["min_ms"]}


def _rates(n: int) -> dict:
    """The device's n^3 matmul rate (TFLOP/s) for float32 at the default and highest precision
    and for bfloat16 (``jprt.eval.matmul_peak_gflops``)."""
    from jprt.eval import matmul_peak_gflops

    return {name: matmul_peak_gflops(n=n, dtype=dtype, precision=precision) / 1e3
            for name, dtype, precision in (("f32_default", "float32", None), ("f32_highest", "float32", "highest"),
                                           ("bf16", "bfloat16", None))}


def _compare(frame, ref, valid) -> dict:
    d = (np.asarray(frame, np.float64) - np.asarray(ref, np.float64))[valid]
    scale = float(np.sqrt(np.mean(np.asarray(ref, np.float64)[valid] ** 2)))
    return {"max_abs_diff": float(np.max(np.abs(d))), "rmse_diff": float(np.sqrt(np.mean(d ** 2))),
            "rel_rmse_diff": float(np.sqrt(np.mean(d ** 2)) / max(scale, 1e-30))}


def measure(path: str, out: str, *, rrf_layouts=RRF_LAYOUTS, wavelet_chunks=WAVELET_CHUNKS,
            precisions=("default", "highest")) -> dict:
    """Time the exported RRF and the wavelet networks on ``jax.devices()[0]``; write ``out``
    (rewritten after every case, so a run cut short keeps what it measured)."""
    import jax

    dev = jax.devices()[0]
    n = 8192 if dev.platform == "gpu" else 1024
    rates = _rates(n)
    result = {"device": str(dev), "device_kind": dev.device_kind, "platform": dev.platform, "jax": jax.__version__,
              "matmul_tflops": rates, "matmul_n": n, "rrf": {}, "wavelet_prt": {}}
    print(f"{dev.device_kind}: matmul {json.dumps(rates)} TFLOP/s", flush=True)
    exported = dict(np.load(path))
    for name, cases in (("rrf", _rrf_cases(exported, path, result, rrf_layouts, precisions)),
                        ("wavelet_prt", _wavelet_cases(exported, wavelet_chunks))):
        for key, case in cases:
            try:
                entry = case(rates["f32_default"] * 1e3)
            except Exception as e:  # noqa: BLE001 - one failing case must not lose the device run
                entry = {"error": repr(e)}
                traceback.print_exc()
            result[name][key] = entry
            print(f"{name} {key}: {json.dumps(entry)}", flush=True)
            _write(out, result)
    return result


def _roof(fn, args: tuple, flops: float, peak_gflops: float) -> dict:
    """``fn(*args)``'s time and its roofline (``jprt.eval.roofline``) at ``flops`` per call."""
    from jprt.eval import roofline

    t = _time(fn, *args)
    return {**t, **roofline(fn, *args, frame_ms=t["median_ms"], peak_gflops=peak_gflops, flops=flops)}


def _rrf_cases(d: dict, path: str, result: dict, rrf_layouts, precisions) -> list:
    """(key, case) per (matmul precision, renderer layout): the exported RRF's 1- and 4-light frames."""
    import functools

    import jax

    from jprt import io
    from jprt.inputs import GBuffer, PointLights
    from jprt.methods import REGISTRY
    from jprt.methods.rrf import model as rrf

    params, _, meta = io.load_tree(path + ".params.npz")
    result["cpu_export"] = meta["cpu"]
    gb = jax.device_put(GBuffer(*(d[f"gb_{f}"] for f in GBuffer._fields)))
    valid = np.asarray(d["gb_valid"], bool)
    lights = {k: jax.device_put(PointLights(d[f"{k}_position"], d[f"{k}_intensity"])) for k in ("1light", "4lights")}
    mc = meta["method_config"]
    layouts = [(None, None)] + [t for t in rrf_layouts]  # None: the renderer's layout for this backend

    def case(precision, tile, chunk, peak):
        with jax.default_matmul_precision(None if precision == "default" else "highest"):
            cfg = {**mc, "render": {**mc["render"], "tile": tile, "chunk": chunk}}
            fast = jax.jit(REGISTRY["rrf"].evaluator(params, cfg))
            entry = {name: {**_roof(fast, (gb, light), meta["cpu"][name]["frame_flops"], peak),
                            "vs_cpu": _compare(fast(gb, light), d[f"{name}_cpu_frame"], valid)}
                     for name, light in lights.items()}
        entry["4lights_over_1light"] = entry["4lights"]["median_ms"] / entry["1light"]["median_ms"]
        entry["tile"], entry["chunk"] = rrf.render_layout(cfg["render"])
        return entry

    return [(f"{precision}_" + (f"tile{tile}_chunk{chunk}" if tile else "auto"),
             functools.partial(case, precision, tile, chunk)) for precision in precisions for tile, chunk in layouts]


def _wavelet_cases(d: dict, chunks) -> list:
    """(key, case) per (preset, resolution, chunk): freshly initialised networks at the ``small`` and
    ``paper`` sizes of experiments/wavelet_prt_cornell.py, K = 64, on the exported G-buffer
    (every other pixel at 256^2)."""
    import functools

    import jax

    from jprt.experiment import resolve_config
    from jprt.inputs import CubeMap
    from jprt.methods import REGISTRY
    from jprt.methods.wavelet_prt import model as wp
    from jprt.runner import method_config

    sys.path.insert(0, os.path.join(ROOT, "experiments"))
    import wavelet_prt_cornell as wexp

    valid = np.asarray(d["gb_valid"], bool)

    def case(cfg, res, chunk, peak):
        m = wp.model(cfg)
        pos = np.asarray(d["gb_position"])[valid]
        bbox = np.stack([pos.min(0) - 0.02, pos.max(0) + 0.02]).astype(np.float32)
        params = m.init(jax.random.PRNGKey(0), bbox)
        rng = np.random.default_rng(0)
        cube = CubeMap(rng.uniform(0.0, 1.0, (6, m.face_size, m.face_size, 3)).astype(np.float32))
        step = 512 // res
        g = {f: np.asarray(d[f"gb_{f}"])[::step, ::step] for f in wp.GBUFFER_FIELDS}
        g["valid"] = g["valid"].astype(np.float32)
        g, cube_d = jax.device_put((g, cube))
        evaluate = jax.jit(REGISTRY["wavelet_prt"].evaluator(params, cfg))
        entry = _roof(evaluate, (g, cube_d), wp.frame_flops(params, cfg, g, cube), peak)
        with jax.default_matmul_precision("highest"):  # what the default precision (TF32 on NVIDIA) costs
            exact = jax.jit(REGISTRY["wavelet_prt"].evaluator(params, cfg))(g, cube_d)
        entry["vs_highest_precision"] = _compare(evaluate(g, cube_d), exact, np.asarray(g["valid"]) > 0)
        entry["chunk_pixels"] = chunk or wp.auto_chunk(cfg["render"]["k"])
        entry.update(hidden=cfg["model"]["hidden"], layers=cfg["model"]["layers"],
                     n_features=cfg["model"]["n_features"], face_size=m.face_size, k=cfg["render"]["k"])
        return entry

    cases = []
    for preset in ("small", "paper"):
        configs = {chunk: method_config(REGISTRY["wavelet_prt"], resolve_config(wexp, [f"render.chunk={chunk}"], preset))
                   for chunk in (0,) + tuple(c for c in chunks if c)}  # 0: the method's automatic chunk
        cases += [(f"{preset}_{res}x{res}_k{cfg['render']['k']}_chunk{chunk}", functools.partial(case, cfg, res, chunk))
                  for res in (256, 512) for chunk, cfg in configs.items()]
    return cases


def _write(path: str, result: dict) -> None:
    with open(path, "w") as f:
        json.dump(result, f, indent=2)


def main() -> None:
    import argparse

    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("step", choices=("export", "measure"))
    parser.add_argument("source", help="export: an rrf_cornell run folder; measure: the exported .npz")
    parser.add_argument("out", help="export: the .npz to write; measure: the JSON to write")
    parser.add_argument("--rrf-layouts", default=",".join(f"{t}x{c}" for t, c in RRF_LAYOUTS),
                        help="RRF render.tile x render.chunk pairs timed besides the run's own, e.g. 8x64,32x64")
    parser.add_argument("--wavelet-chunks", default=",".join(map(str, WAVELET_CHUNKS)),
                        help="wavelet render.chunk values (pixels) timed besides the automatic one")
    parser.add_argument("--precisions", default="default,highest", help="matmul precisions of the RRF cases")
    args = parser.parse_args()
    if args.step == "export":
        export(args.source, args.out)
        return
    layouts = tuple(tuple(int(v) for v in p.split("x")) for p in args.rrf_layouts.split(",") if p)
    chunks = tuple(int(v) for v in args.wavelet_chunks.split(",") if v)
    measure(args.source, args.out, rrf_layouts=layouts, wavelet_chunks=chunks,
            precisions=tuple(args.precisions.split(",")))


if __name__ == "__main__":
    main()
