"""Frame time of the SG light-field evaluator on whatever JAX device is present (the accelerator
check of issue 15): the trained 16-lobe texture of a ``small`` run and its 512^2 held-out view's
atlas G-buffer (``--export`` writes both from a finished run, here, with Mitsuba), timed at
128^2 ... 1920x1080 (the larger frames nearest-resampled from the 512^2 G-buffer: same content,
more pixels), plus random textures of 4-64 lobes at 1080p, at the evaluator's default
``shading.space`` ("auto": every frame here has more pixels than the texture has texels, so each
texel is shaded once). Reports the XLA FLOP count of each program and this device's dense matmul
rate measured in the same run.

    python benchmarks/sg_lightfield_device.py --export results/sg_lightfield/<hash> .gpu/sg.npz   # here
    python benchmarks/sg_lightfield_device.py .gpu/sg.npz out.json                                 # on the device
"""

from __future__ import annotations

import json
import os
import sys
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)


def export(run_dir: str, out: str) -> None:
    """The run's stored lobes and the 512^2 atlas G-buffer of its first held-out view."""
    from jprt.render import lightmap
    from jprt.render.scenes import SceneHandle

    sys.path.insert(0, os.path.join(ROOT, "experiments"))
    import sg_lightfield as exp

    with open(os.path.join(run_dir, "config.json")) as f:
        config = json.load(f)["config"]
    model = {k.split("['")[1].split("']")[0]: v for k, v in np.load(os.path.join(run_dir, "model.npz")).items()
             if "['" in k}  # the runner's checkpoint: keys "<index>|['<name>']"
    from jprt.methods.sg_lightfield import data as sgdata

    atlas = sgdata.make_dataset(None, {k: config[k] for k in ("scene", "objects", "lightmap", "capture")},
                                progress=False).atlas
    g = lightmap.atlas_gbuffer(SceneHandle(config["scene"]), lightmap.Atlas(**atlas), exp._cameras(config, 512)[0])
    arrays = {k: v for k, v in model.items()}
    arrays.update({f"gb_{f}": np.asarray(getattr(g, f)) for f in g._fields})
    os.makedirs(os.path.dirname(out) or ".", exist_ok=True)
    np.savez_compressed(out, **arrays)
    print(f"wrote {out} ({os.path.getsize(out) / 2**20:.1f} MiB)")


def _resample(g, h: int, w: int):
    rows = np.minimum(((np.arange(h) + 0.5) / h * g.uv.shape[0]).astype(int), g.uv.shape[0] - 1)
    cols = np.minimum(((np.arange(w) + 0.5) / w * g.uv.shape[1]).astype(int), g.uv.shape[1] - 1)
    return type(g)(*(np.asarray(a)[rows][:, cols] for a in g))


def _time(fn, *args, repeats: int = 10) -> float:
    import jax

    for _ in range(3):
        jax.block_until_ready(fn(*args))
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - t)
    return float(np.median(times) * 1e3)


def measure(path: str, out: str | None = None, *, lobes=(4, 8, 16, 32, 64)) -> dict:
    import jax

    from jprt.eval import matmul_peak_gflops, xla_flops
    from jprt.inputs import GBuffer, LightScale
    from jprt.methods.sg_lightfield import model as M

    d = np.load(path)
    params = {k: d[k] for k in ("axes", "sharpness", "amplitude", "irradiance", "fill_index")}
    g512 = GBuffer(*(d[f"gb_{f}"] for f in GBuffer._fields))
    one = LightScale(np.ones(3, np.float32))
    result = {"device": str(jax.devices()[0]), "device_kind": jax.devices()[0].device_kind, "jax": jax.__version__,
              "frame_ms": {}, "flops": {}, "frame_ms_by_lobes_1080p": {}}
    n = 8192 if jax.devices()[0].platform == "gpu" else 2048
    result["matmul_f32_tflops"] = matmul_peak_gflops(n=n, repeats=10) / 1e3
    evaluate = jax.jit(M.evaluator(params))
    for h, w in ((128, 128), (256, 256), (512, 512), (1080, 1920)):
        g = jax.device_put(_resample(g512, h, w))
        key = f"{w}x{h}"
        result["frame_ms"][key] = _time(evaluate, g, one)
        result["flops"][key] = xla_flops(evaluate, g, one)  # every tile counted (jprt.eval.loop_aware_cost)
        print(key, result["frame_ms"][key], "ms", flush=True)
    rng = np.random.default_rng(0)
    g = jax.device_put(_resample(g512, 1080, 1920))
    t = params["sharpness"].shape[0]
    for lobes in lobes:
        ax = rng.normal(size=(t, lobes, 3))
        ax /= np.linalg.norm(ax, axis=-1, keepdims=True)
        p = {"axes": ax.astype(np.float16), "sharpness": rng.uniform(1, 100, (t, lobes)).astype(np.float16),
             "amplitude": rng.uniform(0, 1, (t, lobes, 3)).astype(np.float16), "irradiance": params["irradiance"],
             "fill_index": params["fill_index"]}
        result["frame_ms_by_lobes_1080p"][str(lobes)] = _time(jax.jit(M.evaluator(p)), g, one)
    if out:
        with open(out, "w") as f:
            json.dump(result, f, indent=2)
        print(json.dumps(result, indent=2))
    return result


if __name__ == "__main__":
    if sys.argv[1] == "--export":
        export(sys.argv[2], sys.argv[3])
    else:
        measure(sys.argv[1], sys.argv[2])
