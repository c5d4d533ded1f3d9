"""Levenberg-Marquardt benchmark: jprt.solve.lm vs jaxopt.LevenbergMarquardt vs scipy's MINPACK.

A tanh 12-20-10-3 MLP (503 weights, RRF initialisation and [-1, 1] scaling) is fitted to N
samples of a smooth 3-output function of 12 inputs, from the same start, with the same iteration
budget, by

* ours:   jprt.solve.lm.solve (J^T J accumulated in chunks, Nielsen damping);
* jaxopt: jaxopt.LevenbergMarquardt(materialize_jac=True, solver="qr") on flattened parameters;
* scipy:  scipy.optimize.least_squares(method="lm") with the exact Jacobian from JAX (float64).

Each measurement runs in a fresh subprocess (``--worker``) so peak memory is its own: a thread
samples the resident set size (/proc/self/statm) every 2 ms during the solve. "Working memory"
is the peak above the RSS just before the solve (data loaded, program compiled by a warm-up run
of the same shapes, freed memory returned to the OS with malloc_trim), which is what the chunked
design bounds; total peak RSS is reported too.

Also measured: the memory growth from 100k to 1M samples (ours, 2 iterations) and the speed-up of
solving 64 leaf problems of 2k samples in one vmapped call over 64 sequential calls.

Writes benchmarks/results/lm.json.   python benchmarks/lm.py [--n 100000] [--iters 20]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import threading
import time
import warnings

import numpy as np

RESULTS = os.path.join(os.path.dirname(os.path.abspath(__file__)), "results", "lm.json")
SIZES = (12, 20, 10, 3)


def target(x: np.ndarray) -> np.ndarray:
    return np.stack([
        np.sin(2 * x[:, 0]) * np.cos(x[:, 1]) + 0.3 * x[:, 2] * x[:, 3],
        np.exp(-x[:, 4] ** 2 - x[:, 5] ** 2) - 0.5 * x[:, 6],
        np.tanh(x[:, 7] + x[:, 8] * x[:, 9]) + 0.2 * x[:, 10] * x[:, 11],
    ], axis=1).astype(np.float32)


def make_problem(n: int, seed: int = 0):
    import jax

    from jprt.nn import mlp, with_scaling

    x = np.random.default_rng(seed).uniform(-1, 1, (n, 12)).astype(np.float32)
    y = target(x)
    net = mlp(SIZES, activation="tanh", init="rrf")
    params = with_scaling(net.init(jax.random.PRNGKey(seed)), x, y)

    def residual(p, s):
        return net.apply(p, s["x"]) - s["y"]

    # On the device once, before any measurement: the baseline RSS then includes the data.
    return net, params, {"x": jax.numpy.asarray(x), "y": jax.numpy.asarray(y)}, residual


class RSSMonitor:
    """Peak resident set size (bytes) of this process while active, sampled every 2 ms."""

    def __init__(self):
        self.page = os.sysconf("SC_PAGE_SIZE")
        self.peak = 0
        self._stop = threading.Event()

    def rss(self) -> int:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * self.page

    def __enter__(self):
        # Return memory freed by the warm-up run to the OS, so the baseline does not hide it.
        try:
            import ctypes

            ctypes.CDLL("libc.so.6").malloc_trim(0)
        except OSError:
            pass
        self.baseline = self.rss()
        self.peak = self.baseline
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()
        return self

    def _run(self):
        while not self._stop.is_set():
            self.peak = max(self.peak, self.rss())
            time.sleep(0.002)

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join()
        self.peak = max(self.peak, self.rss())


def worker(kind: str, n: int, iters: int) -> dict:
    import jax
    import jax.numpy as jnp
    from jax.flatten_util import ravel_pytree

    from jprt.solve import lm

    if kind == "vmap64":
        return vmap64(n, iters)
    net, params, data, residual = make_problem(n)
    flat0, unravel = ravel_pytree(params)

    def rmse_of(p):
        r = net.apply(p, data["x"]) - data["y"]
        return float(jnp.sqrt(jnp.mean(jnp.square(r))))

    out = {"kind": kind, "n": n, "iters_budget": iters, "start_rmse": rmse_of(params)}
    if kind in ("ours", "jaxopt"):
        backend = "jax" if kind == "ours" else "jaxopt"
        run = lambda: lm.solve(residual, params, data, backend=backend,  # noqa: E731
                               settings=lm.LMSettings(max_iters=iters))
        warm = run()  # compiles the identical program
        jax.block_until_ready(warm.loss)
        with RSSMonitor() as mon:
            t0 = time.perf_counter()
            result = run()
            jax.block_until_ready(result.loss)
            elapsed = time.perf_counter() - t0
        iterations = int(result.iterations)
        out.update(final_rmse=rmse_of(result.params), iterations=iterations, wall_s=elapsed,
                   per_iter_s=elapsed / max(iterations, 1))
        if kind == "ours":
            out.update(_flops(residual, params, data, result, n, lm.LMSettings(max_iters=iters), elapsed))
    elif kind == "scipy":
        from scipy.optimize import least_squares

        def all_res(f):
            p = unravel(f)
            return (net.apply(p, data["x"]) - data["y"]).reshape(-1)

        def all_jac(f):  # per-sample reverse mode, (N * 3, P); a jacrev of all N * 3 outputs would not fit
            per = lambda g, s: net.apply(unravel(g), s["x"]) - s["y"]  # noqa: E731
            return jax.vmap(jax.jacrev(per), in_axes=(None, 0))(f, data).reshape(-1, f.shape[0])

        res_fn = jax.jit(all_res)
        jac_fn = jax.jit(all_jac)
        fun = lambda f: np.asarray(res_fn(jnp.asarray(f, jnp.float32)), np.float64)  # noqa: E731
        jac = lambda f: np.asarray(jac_fn(jnp.asarray(f, jnp.float32)), np.float64)  # noqa: E731
        fun(np.asarray(flat0))
        jac(np.asarray(flat0))  # compile outside the timing
        with RSSMonitor() as mon:
            t0 = time.perf_counter()
            result = least_squares(fun, np.asarray(flat0, np.float64), jac=jac, method="lm", max_nfev=iters)
            elapsed = time.perf_counter() - t0
        out.update(final_rmse=rmse_of(unravel(jnp.asarray(result.x, jnp.float32))), iterations=int(result.njev),
                   function_evals=int(result.nfev), wall_s=elapsed, per_iter_s=elapsed / max(int(result.njev), 1))
    else:
        raise ValueError(kind)
    out.update(peak_rss_mb=mon.peak / 2**20, baseline_rss_mb=mon.baseline / 2**20,
               working_mb=(mon.peak - mon.baseline) / 2**20)
    return out


def _flops(residual, params, data, result, n: int, settings, wall_s: float) -> dict:
    """The solve's arithmetic against the machine: XLA's FLOP count of one chunk of the normal
    pass (per-sample Jacobians, J^T J, J^T r) and of the residual pass, times the chunks; one
    normal pass at the start and one per accepted step, one residual pass per iteration, and the
    Cholesky solve (P^3 / 3 + 2 P^2) per iteration; over the wall time, against the f32 matmul
    rate measured in the same process."""
    import jax
    import jax.numpy as jnp
    import numpy as np_
    from jax.flatten_util import ravel_pytree

    from jprt.eval import matmul_peak_gflops, xla_flops
    from jprt.solve import lm

    chunk = min(int(settings.chunk_size), n)
    one = jax.tree_util.tree_map(lambda a: a[:chunk], data)
    normal = xla_flops(jax.jit(lambda p, d: lm.normal_equations(residual, p, d, chunk_size=chunk)), params, one)
    res = xla_flops(jax.jit(lambda p, d: jnp.sum(jnp.square(jax.vmap(lambda s: residual(p, s))(d)))), params, one)
    p = int(ravel_pytree(params)[0].shape[0])
    it = int(result.iterations)
    hist = np_.asarray(result.history)[:it]
    start = float(jnp.sum(jnp.square(jax.vmap(lambda s: residual(params, s))(data))))
    accepted = int(np_.sum(np_.diff(np_.concatenate([[start], hist])) < 0))
    scale = n / chunk
    total = (1 + accepted) * normal * scale + it * (res * scale + p ** 3 / 3 + 2 * p ** 2)
    peak = matmul_peak_gflops()
    return {"flops_normal_pass": normal * scale, "flops_residual_pass": res * scale, "accepted_steps": accepted,
            "flops_total": total, "gflops_per_s": total / wall_s / 1e9, "matmul_peak_gflops": peak,
            "flops_fraction_of_peak": total / wall_s / 1e9 / peak}


def vmap64(n_leaf: int, iters: int) -> dict:
    """64 leaf problems of n_leaf samples: one vmapped solve vs 64 sequential solves (both compiled first)."""
    import jax
    import jax.numpy as jnp

    from jprt.solve import lm

    problems = [make_problem(n_leaf, seed=s) for s in range(64)]
    stacked_params = jax.tree_util.tree_map(lambda *a: jnp.stack(a), *[p for _, p, _, _ in problems])
    stacked_data = jax.tree_util.tree_map(lambda *a: jnp.stack(a), *[d for _, _, d, _ in problems])
    res = problems[0][3]  # same network structure: one residual function serves all leaves
    settings = lm.LMSettings(max_iters=iters)
    batched = lambda: lm.solve_batched(res, stacked_params, stacked_data, settings=settings)  # noqa: E731
    jax.block_until_ready(batched().loss)
    t0 = time.perf_counter()
    jax.block_until_ready(batched().loss)
    t_batched = time.perf_counter() - t0
    jax.block_until_ready(lm.solve(res, problems[0][1], problems[0][2], settings=lm.LMSettings(max_iters=iters)).loss)
    t0 = time.perf_counter()
    for _, p, d, _ in problems:
        jax.block_until_ready(lm.solve(res, p, d, settings=lm.LMSettings(max_iters=iters)).loss)
    t_seq = time.perf_counter() - t0
    return {"kind": "vmap64", "n_leaf": n_leaf, "iters_budget": iters, "batched_s": t_batched, "sequential_s": t_seq,
            "speedup": t_seq / t_batched}


def run_worker(kind: str, n: int, iters: int, timeout: float) -> dict:
    cmd = [sys.executable, os.path.abspath(__file__), "--worker", kind, "--n", str(n), "--iters", str(iters)]
    print(f"  {kind} n={n} iters={iters} ...", file=sys.stderr, flush=True)
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return {"kind": kind, "n": n, "error": f"timed out after {timeout:.0f} s"}
    if proc.returncode != 0:
        return {"kind": kind, "n": n, "error": proc.stderr.strip().splitlines()[-1] if proc.stderr else "failed"}
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    print(f"    {json.dumps(result)}", file=sys.stderr, flush=True)
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--worker", default=None)
    parser.add_argument("--n", type=int, default=100_000)
    parser.add_argument("--iters", type=int, default=20)
    parser.add_argument("--jaxopt-iters", type=int, default=5,
                        help="jaxopt's budget (its per-iteration time is what is compared; it is ~20x slower)")
    parser.add_argument("--timeout", type=float, default=1800)
    parser.add_argument("--only-vmap64", action="store_true",
                        help="re-measure only the vmap64 entry and update it in the existing results file")
    parser.add_argument("--only-ours", action="store_true",
                        help="re-measure only our solver (speed, FLOP/s fraction, memory growth) and update those "
                             "entries in the existing results file (jaxopt's and scipy's stay from their run)")
    args = parser.parse_args()
    warnings.filterwarnings("ignore", category=DeprecationWarning)
    if args.worker:
        print(json.dumps(worker(args.worker, args.n, args.iters)))
        return
    from jprt.eval import write_benchmark

    if args.only_vmap64:
        with open(RESULTS) as f:
            result = json.load(f)
        vmap = run_worker("vmap64", 2000, args.iters, args.timeout)
        result.update(vmap64=vmap, vmap64_speedup=vmap.get("speedup"))
        print(json.dumps(vmap, indent=2))
        write_benchmark(RESULTS, result, f"python benchmarks/lm.py --only-vmap64 --iters {args.iters}",
                        updated="the vmap64 entry only; the other entries are from the run named before")
        return

    if args.only_ours:
        with open(RESULTS) as f:
            result = json.load(f)
        ours = run_worker("ours", args.n, args.iters, args.timeout)
        mem_small = run_worker("ours", 100_000, 2, args.timeout)
        mem_large = run_worker("ours", 1_000_000, 2, args.timeout)
        result.update(ours=ours, memory_runs={"100k": mem_small, "1m": mem_large},
                      flops_fraction_of_peak=ours.get("flops_fraction_of_peak"),
                      mem_growth_100k_to_1m=mem_large["working_mb"] / mem_small["working_mb"],
                      mem_growth_100k_to_1m_total_rss=mem_large["peak_rss_mb"] / mem_small["peak_rss_mb"])
        result["targets"] = dict(result.get("targets", {}), flops_fraction_of_peak="reported (issue 17)",
                                 mem_growth_100k_to_1m_total_rss="<= 1.2")
        print(json.dumps({k: v for k, v in result.items() if not isinstance(v, dict)}, indent=2))
        write_benchmark(RESULTS, result, f"python benchmarks/lm.py --only-ours --n {args.n} --iters {args.iters}",
                        updated="ours, memory_runs and the keys derived from them; speedup_vs_jaxopt / _vs_scipy "
                                "and rmse_ratio_vs_scipy are from the full run before and compare with that run's "
                                "ours entry")
        return

    ours = run_worker("ours", args.n, args.iters, args.timeout)
    theirs = run_worker("jaxopt", args.n, args.jaxopt_iters, args.timeout)
    scipy_run = run_worker("scipy", args.n, args.iters, args.timeout)
    mem_small = run_worker("ours", 100_000, 2, args.timeout)
    mem_large = run_worker("ours", 1_000_000, 2, args.timeout)
    vmap = run_worker("vmap64", 2000, args.iters, args.timeout)

    def ratio(a, b, key):
        return a[key] / b[key] if key in a and key in b and b[key] else None

    result = {
        "problem": (f"tanh MLP {SIZES}, {args.n} samples, smooth 3-output target, same start; budget {args.iters} "
                    f"iterations for ours and scipy, {args.jaxopt_iters} for jaxopt"),
        "ours": ours, "jaxopt": theirs, "scipy": scipy_run,
        "speedup_vs_jaxopt": ratio(theirs, ours, "per_iter_s"),
        "speedup_vs_scipy": ratio(scipy_run, ours, "per_iter_s"),
        "rmse_ratio_vs_scipy": ratio(ours, scipy_run, "final_rmse"),
        "mem_growth_100k_to_1m": ratio(mem_large, mem_small, "working_mb"),
        "mem_growth_100k_to_1m_total_rss": ratio(mem_large, mem_small, "peak_rss_mb"),
        "flops_fraction_of_peak": ours.get("flops_fraction_of_peak"),
        "memory_runs": {"100k": mem_small, "1m": mem_large},
        "vmap64_speedup": vmap.get("speedup"),
        "vmap64": vmap,
        "targets": {"speedup_vs_jaxopt": ">= 10", "rmse_ratio_vs_scipy": "<= 1.05", "mem_growth_100k_to_1m": "<= 1.2",
                    "vmap64_speedup": ">= 5", "flops_fraction_of_peak": "reported (issue 17)",
                    "mem_growth_100k_to_1m_total_rss": "<= 1.2"},
    }
    print(json.dumps({k: v for k, v in result.items() if not isinstance(v, dict)}, indent=2))
    write_benchmark(RESULTS, result,
                    f"python benchmarks/lm.py --n {args.n} --iters {args.iters} --jaxopt-iters {args.jaxopt_iters}")


if __name__ == "__main__":
    main()
