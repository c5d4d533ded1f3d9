"""What data-driven PRT's report measures beyond the method contract (Belcour et al. 2022): fits
with their ill-conditioning warnings kept, the method's error beside the error of projecting the
references onto its basis (Fig. 14), the data's spectrum (Fig. 3), lights outside the training
scenario (Fig. 8), classic SH PRT on the same atlas (§6.4) and the basis as pictures.
"""

from __future__ import annotations

import os
import warnings

import numpy as np

from jprt.methods.base import FitResult
from jprt.methods.datadriven import model as dd
from jprt.methods.lightmap_lookup import shown_texels

__all__ = ["fit_recorded", "scores", "lightmap_image", "spot_lights", "spectrum", "out_of_scenario_lights",
           "sh_prt_lightmaps", "basis_picture", "basis_sizes", "regularisation_sweeps",
           "camera_images", "sh_prt_baseline", "timings"]


def fit_recorded(data, cfg: dict) -> FitResult:
    """``model.fit`` of ``data`` under ``cfg``; the ill-conditioning warnings it raised are kept
    in ``info["warnings"]`` and the config in ``info["config"]``."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", dd.IllConditionedWarning)
        result = dd.fit(data, cfg)
    result.info["warnings"] = [str(w.message) for w in caught if issubclass(w.category, dd.IllConditionedWarning)]
    result.info["config"] = cfg
    return result


def scores(result: FitResult, direct, indirect, atlas=None) -> dict:
    """Lightmap RMSE of a fit (``fit_recorded``) on (direct, indirect) lightmaps, and of projecting
    the references onto its basis (Fig. 14): {"rmse", "projection_rmse"}, over every texel. Given
    the ``atlas``, also "rmse_shown": over the texels whose atlas pixel shows them
    (``lightmap_lookup.shown_texels``), the set the runner's held-out images score."""
    params, cfg = result.params, result.info["config"]
    fine = np.asarray(params["fine_index"])
    pred = np.asarray(dd.lightmap(params, direct[:, fine], cfg))
    proj = dd.project(params, direct[:, fine], indirect, cfg)
    out = {"rmse": dd.lightmap_rmse(pred, indirect), "projection_rmse": dd.lightmap_rmse(proj, indirect)}
    if atlas is not None:
        shown = shown_texels(atlas["texel_index"], atlas["fill_index"])
        out["rmse_shown"] = dd.lightmap_rmse(pred[:, shown], np.asarray(indirect)[:, shown])
    return out


def lightmap_image(texels, atlas) -> np.ndarray:
    """Lightmap texels (T, 3) -> (R, R, 3) atlas image (zeros outside the covered texels)."""
    r = int(atlas["resolution"])
    image = np.zeros((r * r, 3), np.float32)
    image[np.asarray(atlas["texel_index"])] = texels
    return image.reshape(r, r, 3)


def spot_lights(lights: dict, n: int | None = None) -> list:
    """The spot lights of a dataset's light table (``lights_test``: position, target, intensity,
    cutoff_deg, beam_deg), the first ``n`` (all when None)."""
    from jprt.render.lights import SpotLights

    n = len(lights["position"]) if n is None else int(n)
    return [SpotLights.create(lights["position"][k], lights["target"][k], lights["intensity"][k],
                              lights["cutoff_deg"][k], lights["beam_deg"][k]) for k in range(n)]


def spectrum(direct, indirect, n: int = 32) -> list:
    """Fig. 3: the first ``n`` relative eigenvalues of the indirect data (each example scaled by
    its direct light's norm, centred)."""
    norms = np.linalg.norm(direct.reshape(len(direct), -1), axis=1)
    a = (indirect[norms > 0] / norms[norms > 0, None, None]).reshape(int((norms > 0).sum()), -1)
    sv = np.linalg.svd(a - a.mean(0), compute_uv=False)
    return (sv ** 2 / np.sum(sv ** 2))[:n].tolist()


def out_of_scenario_lights(e: dict, data, rng) -> dict:
    """Fig. 8: {"point": ``e["oos_n"]`` point lights above surface samples of the asset (offset
    ``e["point_offset"]`` along the normal, intensity ``e["point_intensity"]``), "directional":
    as many directional lights toward directions in the box ``e["directional_toward_lo"]`` ..
    ``_hi`` (irradiance ``e["directional_irradiance"]``)}, random colours."""
    from jprt.render.lights import DirectionalLights, PointLights

    cand = data.candidates
    points, directional = [], []
    on_asset = np.nonzero(np.isin(cand["object_id"], np.atleast_1d(data.atlas["objects"])))[0]  # near the asset
    for _ in range(int(e["oos_n"])):
        k = rng.choice(on_asset)
        pos = cand["position"][k] + rng.uniform(*e["point_offset"]) * cand["normal"][k]
        colour = 0.4 + 0.6 * rng.random(3)
        points.append(PointLights.create(pos, rng.uniform(*e["point_intensity"]) * colour / colour.max()))
        lo, hi = np.asarray(e["directional_toward_lo"]), np.asarray(e["directional_toward_hi"])
        toward = lo + (hi - lo) * rng.random(3)
        colour = 0.4 + 0.6 * rng.random(3)
        directional.append(DirectionalLights.create(-toward, rng.uniform(*e["directional_irradiance"]) * colour
                                                    / colour.max()))
    return {"point": points, "directional": directional}


def sh_prt_lightmaps(handle, transfer, center, lightings, degree: int) -> np.ndarray:
    """Classic SH PRT's lightmaps (Sloan et al. 2002; ``transfer`` baked by ``jprt.methods.sh_prt``)
    of each lighting, every light a delta from its direction at ``center`` (§6.4)."""
    from jprt.methods.sh_prt import model as sh_prt
    from jprt.render import lightmap

    out = []
    for lighting in lightings:
        dirs, irr = lightmap.incident_delta_lights(handle, center, lighting)
        out.append(sh_prt.lightmap(transfer, sh_prt.delta_light_coefficients(dirs, irr, degree)))
    return np.stack(out)


def basis_picture(params, atlas, n: int = 7) -> np.ndarray:
    """The mean and the first ``n`` basis lightmaps side by side, each scaled to [-1, 1] and shown
    as 0.5 + 0.5 x (grey RGB, (R, (n + 1) R, 3))."""
    r = int(atlas["resolution"])
    fill = np.asarray(atlas["fill_index"])
    basis_img = np.asarray(params["basis"])[fill]
    tiles = [np.asarray(params["mean"])[fill]] + [basis_img[:, j] for j in range(min(n, basis_img.shape[1]))]
    tiles = [t.reshape(r, r) / max(np.abs(t).max(), 1e-30) for t in tiles]
    return np.repeat(0.5 + 0.5 * np.concatenate(tiles, axis=1)[..., None], 3, axis=-1)


def basis_sizes(fit, data, ns, mean: str, out: str, say=print) -> dict:
    """Fig. 14: the method's and the projection's held-out lightmap RMSE against the basis size
    n (each of ``ns``), with the config's ``mean`` convention and the other one ("norm" /
    "linear"), ``fit(**sections)`` fitting with config overrides; Fig. 3: the spectrum of the data.
    Plots fig14_basis.png and fig3_eigenvalues.png in the folder ``out``."""
    from jprt import eval as jeval

    other = "linear" if mean == "norm" else "norm"
    table = {}
    for label, extra in ((mean, {}), (other, {"mean": other})):
        rmse, proj = {}, {}
        for n in ns:
            sc = scores(fit(basis={"n": n, **extra}), data.direct_test, data.indirect_test)
            rmse[str(n)], proj[str(n)] = sc["rmse"], sc["projection_rmse"]
            say(f"n = {n}, mean {label}: RMSE {sc['rmse']:.5f}, projection {sc['projection_rmse']:.5f}")
        table[label] = (rmse, proj)
    (rb, pb), (rbo, pbo) = table[mean], table[other]
    last = str(ns[-1])
    s = {"rmse_by_basis": rb, "projection_rmse_by_basis": pb, f"rmse_by_basis_{other}_mean": rbo,
         f"projection_rmse_by_basis_{other}_mean": pbo, "ratio_last": rb[last] / max(pb[last], 1e-30),
         f"ratio_last_{other}_mean": rbo[last] / max(pbo[last], 1e-30)}
    if "64" in rb:
        s["ratio_64"], s[f"ratio_64_{other}_mean"] = rb["64"] / pb["64"], rbo["64"] / pbo["64"]
    jeval.plot_series(os.path.join(out, "fig14_basis.png"),
                      {f"data-driven PRT (mean {mean})": (ns, [rb[str(n)] for n in ns]),
                       "projection onto the basis": (ns, [pb[str(n)] for n in ns]),
                       f"data-driven PRT (mean {other})": (ns, [rbo[str(n)] for n in ns]),
                       f"projection (mean {other})": (ns, [pbo[str(n)] for n in ns])},
                      xlabel="basis elements n", ylabel="lightmap RMSE", title="Fig. 14: accuracy vs basis size",
                      logx=True, logy=True)
    s["relative_eigenvalues"] = spectrum(data.direct, data.indirect)
    jeval.plot_series(os.path.join(out, "fig3_eigenvalues.png"),
                      {"indirect dataset": (list(range(1, len(s["relative_eigenvalues"]) + 1)),
                                            s["relative_eigenvalues"])},
                      xlabel="index", ylabel="relative eigenvalue", title="Fig. 3: spectrum of the indirect data",
                      logy=True)
    return s


def regularisation_sweeps(fit, data, lambdas, point_counts, max_points: int, out: str) -> dict:
    """The ridge lambda (each of ``lambdas``, no cross-validation; with the warnings each fit
    raised) and the measurement-point count (each of ``point_counts`` up to ``max_points``):
    held-out scores, ``fit(**sections)`` fitting with config overrides. Plots lambda_sweep.png and
    points_sweep.png in the folder ``out``."""
    from jprt import eval as jeval

    s = {"lambda_sweep": {}, "points_sweep": {}}
    for lam in lambdas:
        r = fit(transfer={"lam": float(lam), "lam_cv": []})
        s["lambda_sweep"][repr(float(lam))] = {**scores(r, data.direct_test, data.indirect_test),
                                               "warnings": len(r.info["warnings"])}
    for count in point_counts:
        if int(count) <= int(max_points):
            s["points_sweep"][str(count)] = scores(fit(points={"count": int(count)}), data.direct_test,
                                                   data.indirect_test)["rmse"]
    lams = [float(k) for k in s["lambda_sweep"]]
    jeval.plot_series(os.path.join(out, "lambda_sweep.png"),
                      {"RMSE": ([max(v, 1e-6) for v in lams], [v["rmse"] for v in s["lambda_sweep"].values()])},
                      xlabel="lambda (0 plotted at 1e-6)", ylabel="lightmap RMSE", title="ridge regularisation",
                      logx=True)
    counts = [int(k) for k in s["points_sweep"]]
    jeval.plot_series(os.path.join(out, "points_sweep.png"), {"RMSE": (counts, list(s["points_sweep"].values()))},
                      xlabel="measurement points P", ylabel="lightmap RMSE", title="measurement-point count", logx=True)
    return s


def camera_images(handle, atlas, camera, lights, predict, spp: int, exposure: float, out: str) -> dict:
    """Held-out lights seen by a camera: for each of ``lights`` (k-th), ``predict(k, gbuffer)``
    (the method on the camera's atlas G-buffer) against Mitsuba's indirect at ``spp``: EXRs,
    tonemapped direct + indirect PNGs of both and camera_side_by_side.png in the folder ``out``;
    {"image_rmse": over all of them} (nothing without lights)."""
    from jprt import eval as jeval
    from jprt import io
    from jprt.render import images, lightmap

    gb = lightmap.atlas_gbuffer(handle, lightmap.Atlas(**atlas), camera)
    rows = []
    for k, lighting in enumerate(lights):
        handle.set_lighting(lighting)
        rad = images.direct_indirect(handle, camera, spp=int(spp), seed=5 + k)
        ref = np.where(gb.valid[..., None], rad.indirect, 0.0)
        pred = predict(k, gb)
        rows.append((f"held-out light {k}", ref, pred))
        io.write_exr(os.path.join(out, f"light{k:02d}_reference.exr"), ref)
        io.write_exr(os.path.join(out, f"light{k:02d}_datadriven.exr"), pred)
        for name, image in (("datadriven", pred), ("reference", ref)):
            io.write_png(os.path.join(out, f"light{k:02d}_final_{name}.png"), rad.direct + image, exposure=exposure)
    if not rows:
        return {}
    jeval.side_by_side(os.path.join(out, "camera_side_by_side.png"), rows, exposure=exposure)
    return {"image_rmse": jeval.set_rmse([r[2] for r in rows], [r[1] for r in rows], [gb.valid] * len(rows))}


def sh_prt_baseline(scene, method_config: dict, e: dict, data, handle, test_lights, oos: dict) -> dict:
    """§6.4: classic SH PRT of the asset (``jprt.methods.sh_prt``, baked on the same atlas at the
    largest order of ``e["sh_orders"]``, ``e["sh_spp"]``, ``e["sh_env_height"]``), each light a
    delta from its direction at the asset centre: lightmap RMSE at each order on the held-out
    lights (``test_lights``) and on the out-of-scenario ones (``oos``: {kind: (direct, indirect,
    lightings)})."""
    import time

    from jprt.methods import REGISTRY
    from jprt.methods.sh_prt import model as sh_prt

    t0 = time.perf_counter()
    sh_config = {"scene": scene, "objects": method_config["objects"],
                 "lightmap": method_config["lightmap"],  # the same atlas as the data-driven fit
                 "sh": {"order": max(int(o) for o in e["sh_orders"]), "spp": int(e["sh_spp"]),
                        "env_height": int(e["sh_env_height"])}}
    baked = REGISTRY["sh_prt"].make_dataset(scene, sh_config)  # cached by jprt.cache
    if not np.array_equal(baked.atlas["texel_index"], data.atlas["texel_index"]):
        raise RuntimeError("the SH PRT atlas differs from the data-driven one")
    s = {"sh_bake_s": baked.meta["bake_s"], "sh_stage_s": time.perf_counter() - t0, "rmse_sh_prt": {},
         "rmse_sh_prt_out_of_scenario": {}}
    center = np.asarray(data.atlas["position"]).mean(axis=0)
    for order in e["sh_orders"]:
        deg = sh_prt.order_to_degree(order)
        s["rmse_sh_prt"][str(order)] = dd.lightmap_rmse(
            sh_prt_lightmaps(handle, baked.transfer, center, test_lights, deg), data.indirect_test)
        s["rmse_sh_prt_out_of_scenario"][str(order)] = {
            kind: dd.lightmap_rmse(sh_prt_lightmaps(handle, baked.transfer, center, v[2], deg), v[1])
            for kind, v in oos.items()}
    s["sh_prt_note"] = ("classic SH PRT (Sloan et al. 2002): transfer vectors baked with Mitsuba from SH environment "
                        "maps (positive and negative parts), each light projected as a delta from its direction at "
                        "the asset centre")
    return s


def timings(handle, lighting, data, params, cfg: dict, repeats: int) -> dict:
    """The transfer product u = M_n x alone (jitted; median of ``repeats``, in microseconds) on
    the first held-out configuration, and Mitsuba's shading of the fine measurement points under
    ``lighting`` (``direct_measure_ms``, median of 5 after a warm-up): what the paper's run time
    measures by deferred shading on the GPU (§4.3)."""
    import jax

    from jprt import eval as jeval
    from jprt.render import lightmap

    x = dd.coarse_direct(data.direct_test[0][params["fine_index"]], params["group"], params["counts"])
    transfer = jax.jit(lambda v: dd.transfer_coefficients(params, v, cfg))
    s = {"transfer_us": 1e3 * jeval.time_call(transfer, jax.numpy.asarray(x, jax.numpy.float32),
                                               repeats=int(repeats))["median_ms"]}
    handle.set_lighting(lighting)
    fine_pos = np.asarray(data.candidates["position"])[params["fine_index"]]
    fine_nrm = np.asarray(data.candidates["normal"])[params["fine_index"]]
    lightmap.radiance_at_points(handle, fine_pos, fine_nrm, spp=1)  # warm-up (kernel compile)
    s["direct_measure_ms"] = jeval.time_call(
        lambda: lightmap.radiance_at_points(handle, fine_pos, fine_nrm, spp=1), repeats=5, warmup=0)["median_ms"]
    s["timing_note"] = ("transfer_us: u = M_n x alone (jitted, CPU); frame_ms: coarse averaging, transfer, lightmap "
                        "reconstruction and lookup of every covered texel of the atlas (jitted, CPU); frame_ms_camera: "
                        "the same for every pixel of a camera view; direct_measure_ms: Mitsuba shading of the fine "
                        "measurement points (outside JAX)")
    return s
