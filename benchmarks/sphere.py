"""Spherical-basis benchmarks, each against a peer measured in the same run.

* Cube-map Haar forward + inverse (6 x 64 x 64 x 3): jprt.sphere.haar (jit) vs PyWavelets
  (``wavedec2`` / ``waverec2``, "haar", per face and channel).
* SH projection to degree 8 of a 6 x 64 x 64 x 3 cube map: jprt.sphere.sh (jit) vs a NumPy
  reference (scipy.special.sph_harm_y basis, then a weighted sum).
* The SG x warped-GGX ASG convolution error table (Currius et al. 2020, Appendix B) against
  float64 quadrature, over roughness 0.05..1, light sharpness 1..1e3, view angles 0..80 degrees.

Timings: median of repeated runs after warm-up, ``block_until_ready`` for JAX.
Writes benchmarks/results/sphere.json.

    python benchmarks/sphere.py [--repeats 20]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time

import jax
import jax.numpy as jnp
import numpy as np

from jprt.eval import write_benchmark
from jprt.sphere import cubemap, haar, quadrature, sg, sh

RESULTS = os.path.join(os.path.dirname(os.path.abspath(__file__)), "results", "sphere.json")


def median_ms(fn, repeats: int) -> float:
    fn()  # warm-up (compilation)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return 1e3 * float(np.median(times))


def bench_haar(cube: np.ndarray, repeats: int) -> dict:
    import pywt

    x = jnp.asarray(cube)
    roundtrip = jax.jit(lambda c: haar.inverse(haar.forward(c)))
    ours = median_ms(lambda: roundtrip(x).block_until_ready(), repeats)

    def pywt_roundtrip():
        out = np.empty_like(cube)
        for f in range(6):
            for c in range(cube.shape[3]):
                out[f, :, :, c] = pywt.waverec2(pywt.wavedec2(cube[f, :, :, c], "haar"), "haar")
        return out

    peer = median_ms(pywt_roundtrip, repeats)
    err_ours = float(np.abs(np.asarray(roundtrip(x)) - cube).max())
    err_peer = float(np.abs(pywt_roundtrip() - cube).max())
    return {"haar_ms": ours, "haar_pywt_ms": peer, "haar_max_roundtrip_error": err_ours,
            "haar_pywt_max_roundtrip_error": err_peer}


def bench_sh(cube: np.ndarray, repeats: int, degree: int = 8) -> dict:
    n = cube.shape[1]
    x = jnp.asarray(cube)
    project = jax.jit(lambda c: sh.project_cubemap(c, degree))
    ours = median_ms(lambda: project(x).block_until_ready(), repeats)
    d = np.asarray(cubemap.texel_directions(n), np.float64).reshape(-1, 3)
    w = np.asarray(cubemap.texel_solid_angles(n), np.float64).reshape(-1)
    flat = cube.reshape(-1, cube.shape[3]).astype(np.float64)

    def numpy_project():
        return (quadrature.scipy_real_sh(d, degree) * w[:, None]).T @ flat

    peer = median_ms(numpy_project, max(3, repeats // 4))
    diff = float(np.abs(np.asarray(project(x)) - numpy_project()).max())
    return {"sh_ms": ours, "sh_numpy_ms": peer, "sh_degree": degree, "sh_max_abs_diff_vs_numpy": diff}


def sg_asg_table() -> list[dict]:
    rows = []
    with jax.enable_x64(True):
        n = jnp.array([0.0, 0.0, 1.0])
        for roughness in (0.05, 0.1, 0.25, 0.5, 1.0):
            for light in (1.0, 10.0, 100.0, 1000.0):
                for view_deg in (0.0, 20.0, 40.0, 60.0, 80.0):
                    for offset in (0.0, 0.1, 0.3):
                        t = np.radians(view_deg)
                        asg = sg.warp_ndf_to_asg(n, jnp.array([np.sin(t), 0.0, np.cos(t)]), jnp.asarray(roughness))
                        z, y = np.asarray(asg.z), np.asarray(asg.y)
                        axis = z * np.cos(offset) + y * np.sin(offset)
                        closed = float(sg.convolve_sg_asg(jnp.asarray(axis), jnp.asarray(light), 1.0, asg))
                        pole = axis if light > float(asg.sharpness_x) else z
                        numeric = quadrature.integrate(
                            lambda v: np.asarray(sg.evaluate(jnp.asarray(v), jnp.asarray(axis), light, 1.0)
                                                 * sg.asg_evaluate(jnp.asarray(v), asg)), pole,
                            n_theta=2000, n_phi=600)
                        effective = 0.5 * light + min(float(asg.sharpness_x), float(asg.sharpness_y))
                        rows.append({"roughness": roughness, "light_sharpness": light, "view_deg": view_deg,
                                     "offset_rad": offset, "closed_form": closed, "quadrature": numeric,
                                     "rel_error": abs(closed / numeric - 1.0) if numeric > 0 else None,
                                     "effective_sharpness": effective,
                                     "in_region": bool(effective >= 8.0 and offset * np.sqrt(effective) <= 4.0)})
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeats", type=int, default=20)
    args = parser.parse_args()
    rng = np.random.default_rng(0)
    cube = rng.lognormal(0.0, 1.5, size=(6, 64, 64, 3)).astype(np.float32)
    result = {"device": f"{platform.processor() or platform.machine()} ({os.cpu_count()} cores), "
                        f"jax {jax.__version__} {jax.devices()[0].platform}"}
    result.update(bench_haar(cube, args.repeats))
    result.update(bench_sh(cube, args.repeats))
    table = sg_asg_table()
    in_region = [r["rel_error"] for r in table if r["in_region"]]
    outside = [r["rel_error"] for r in table if not r["in_region"]]
    result.update({
        "sg_asg_region": "effective sharpness s = nu + min(lambda_x, lambda_y) >= 8 (nu = light sharpness / 2) "
                         "and light-axis offset from the reflected direction <= 4 / sqrt(s)",
        "sg_asg_max_rel_error_in_region": max(in_region),
        "sg_asg_max_rel_error_outside_region": max(outside) if outside else None,
        "sg_asg_error_table": table,
    })
    print(json.dumps({k: v for k, v in result.items() if k != "sg_asg_error_table"}, indent=2))
    write_benchmark(RESULTS, result, "python benchmarks/sphere.py --repeats %d" % args.repeats)


if __name__ == "__main__":
    main()
