"""SG light-field textures' run-time shading of one lobe against a brute-force integral.

One spherical-Gaussian light lobe exp(lambda (l . u - 1)) (lambda 0.5 ... 300, its axis on the
mirror direction of the view or off it) reflected by the GGX BRDF the method shades with
(``jprt.methods.sg_lightfield.model``: GGX D, separable Smith G, Schlick's Fresnel), against a
float64 sum over 400 000 Fibonacci directions of the upper hemisphere, at GGX alpha 0.05 ... 0.6
and views 0 ... 84 degrees from the normal, for a plastic (f0 0.04) and a metal (f0 0.9):

* ``shade_sampled`` with every lobe's directions drawn from the lobe (``brdf_sampled`` off);
* ``shade_sampled`` as the evaluator runs it (lobes broader than the BRDF integrated at
  directions drawn from its visible normals), and at other bounds between the two
  (``broad_bound``, in units of lambda alpha^2 / 2);
* Appendix B's SG x ASG product (``shade``, ``shading.samples`` 0).

Per shading: the median and 90th percentile over the grid of |shaded - exact| / exact, and the
summed |shaded - exact| over the summed exact integral. No scene is involved: the bound between
the two integrals was chosen here. Writes benchmarks/results/sg_shading.json.

    python benchmarks/sg_shading.py
"""

from __future__ import annotations

import math
import os

import jax.numpy as jnp
import numpy as np

from jprt.eval import write_benchmark
from jprt.methods.sg_lightfield import model as sgm

RESULTS = os.path.join(os.path.dirname(os.path.abspath(__file__)), "results", "sg_shading.json")
ALPHAS = (0.05, 0.15, 0.3, 0.6)
VIEWS_COS = (0.1, 0.25, 0.5, 1.0)
SHARPNESS = (0.5, 2.0, 8.0, 30.0, 300.0)
OFF_AXIS = np.array([-0.5, 0.3, 0.8]) / np.linalg.norm([-0.5, 0.3, 0.8])


def hemisphere(count: int = 400_000):
    """Fibonacci directions of the sphere (float64) kept above z = 0, and each one's solid angle."""
    i = np.arange(count) + 0.5
    z = 1.0 - 2.0 * i / count
    r = np.sqrt(1.0 - z * z)
    phi = math.pi * (1.0 + 5.0 ** 0.5) * i
    d = np.stack([r * np.cos(phi), r * np.sin(phi), z], -1)
    return d[d[:, 2] > 0], 4.0 * math.pi / count


def exact(directions, d_omega, axis, lam, view, alpha, f0) -> float:
    """The lobe's reflection by the GGX BRDF (Schlick f0, separable Smith G), float64 sum."""
    h = directions + view
    h /= np.linalg.norm(h, axis=-1, keepdims=True)
    a2 = alpha ** 2
    ndf = a2 / (np.pi * (h[:, 2] ** 2 * (a2 - 1) + 1) ** 2)
    g1 = lambda x: 2 * x / (x + np.sqrt(a2 + (1 - a2) * x * x))  # noqa: E731
    fresnel = f0 + (1 - f0) * (1 - np.clip(np.sum(directions * h, -1), 0, 1)) ** 5
    fcos = ndf * g1(directions[:, 2]) * g1(view[2]) * fresnel / (4 * view[2])
    return float(np.sum(np.exp(lam * (directions @ axis - 1.0)) * fcos) * d_omega)


def summary(errors: list[tuple[float, float]]) -> dict:
    e = np.asarray(errors)
    rel = np.abs(e[:, 0]) / e[:, 1]
    return {"median_relative_error": float(np.median(rel)), "p90_relative_error": float(np.quantile(rel, 0.9)),
            "summed_error_over_summed_integral": float(np.abs(e[:, 0]).sum() / e[:, 1].sum())}


def main() -> None:
    directions, d_omega = hemisphere()
    n = np.array([0.0, 0.0, 1.0])
    shadings = {"lobe_drawn": dict(brdf_sampled=False), "default": {},
                **{f"broad_bound_{b:g}": dict(broad_bound=b) for b in (0.25, 2.0, 4.0)}}
    result = {"grid": {"alpha": list(ALPHAS), "n_dot_v": list(VIEWS_COS), "sharpness": list(SHARPNESS),
                       "axis": ["mirror", "off (fixed)"], "directions": len(directions)}, "per_f0": {}}
    for f0 in (0.04, 0.9):
        errors = {k: [] for k in (*shadings, "appendix_b")}
        for alpha in ALPHAS:
            for nv in VIEWS_COS:
                view = np.array([math.sqrt(max(1.0 - nv * nv, 0.0)), 0.0, nv])
                mirror = 2 * nv * n - view
                for lam in SHARPNESS:
                    for axis in (mirror, OFF_AXIS):
                        ref = exact(directions, d_omega, axis, lam, view, alpha, f0)
                        lobes = sgm.Lobes(jnp.asarray(axis[None], jnp.float32), jnp.asarray([lam], jnp.float32),
                                          jnp.ones((1, 3), jnp.float32))
                        args = (jnp.asarray(n, jnp.float32), jnp.asarray(view, jnp.float32), jnp.float32(alpha),
                                jnp.full(3, f0, jnp.float32), jnp.zeros(3, jnp.float32), jnp.zeros(3, jnp.float32))
                        for name, kw in shadings.items():
                            errors[name].append((float(sgm.shade_sampled(lobes, *args, **kw)[0]) - ref, ref))
                        errors["appendix_b"].append((float(sgm.shade(lobes, *args)[0]) - ref, ref))
        result["per_f0"][f"{f0:g}"] = {k: summary(v) for k, v in errors.items()}
        print(f"f0 {f0:g}: " + ", ".join(f"{k} {v['summed_error_over_summed_integral']:.3f}"
                                          for k, v in result["per_f0"][f"{f0:g}"].items()), flush=True)
    write_benchmark(RESULTS, result, "python benchmarks/sg_shading.py")


if __name__ == "__main__":
    main()
