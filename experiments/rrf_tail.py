"""Where the RRF's worst pixels are, and what training settings do to them (issue 17's seam item).

Fits the ``small`` config of experiments/rrf_cornell.py with each named override and scores it on
that experiment's held-out pairs (64^2, references along the pixel-centre rays at its
``eval.reference_spp``; rendered once, cached beside the output): indirect RMSE, the 99.9th
percentile of |error| over every valid pixel and channel, their ratio, and which surfaces the
worst 0.1 % lie on ("object/normal axis": 1/1 the ceiling, 2/2 the back wall, 6/1 the tall box's
top face in the built-in Cornell box).

    python experiments/rrf_tail.py '{"small": {}, "face1": {"data": {"min_face_rays": 1}}}'
    python experiments/rrf_tail.py --noise '{"small": {}}'
    python experiments/rrf_tail.py --figure results/rrf_tail '{"small": {}}'
    python experiments/rrf_tail.py --timing '{"small": {}, "no_light_split": {"tree": {"split_on":
        ["position", "view", "normal", "brdf"]}}}'

One JSON line per variant on stdout. The numbers of 2026-11-30 are in experiments/rrf_cornell.py.
With ``--noise`` a second reference set of the same pairs (other seeds) is rendered too: a first
line gives the references' own noise (|A - B| / sqrt 2: its RMSE, 99.9th percentile and their
ratio), and each variant is also scored against the mean of the two (half the noise variance).
With ``--figure DIR`` each variant writes ``DIR/tail_<name>.png``: the four held-out pairs that
hold most of the worst 0.1 %, one row each: reference | RRF | |error| (white at 0.1), the worst
0.1 % in red. With ``--timing`` each variant's frame is timed too, as rrf_cornell times it: the
first held-out view at ``eval.timing_resolution`` (512^2) with one light and with its four lights
(median of ``eval.timing_repeats``, the two alternating), their ratio, and the FLOP counts.
"""

from __future__ import annotations

import json
import os
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)


def held_out(config: dict, cache: str, seed_offset: int = 0):
    """(testset, references, valid masks) of rrf_cornell's held-out pairs; references cached in ``cache``."""
    import rrf_common

    cameras, lights, testset = rrf_common.held_out_inputs(config)
    valid = [np.asarray(testset.gbuffer(item.camera).valid, bool) for item in testset.items]
    if os.path.exists(cache):
        return testset, list(np.load(cache)["references"]), valid
    refs = rrf_common.held_out_references(config, cameras, lights, testset, seed_offset)[1]
    os.makedirs(os.path.dirname(os.path.abspath(cache)), exist_ok=True)
    np.savez(cache, references=np.stack(refs))
    return testset, refs, valid


def abs_errors(preds, refs, valid) -> list[np.ndarray]:
    """|preds - refs| per pair, (H, W, 3), 0 where the G-buffer is invalid."""
    return [np.where(v[..., None], np.abs(p - r), 0.0) for p, r, v in zip(preds, refs, valid)]


def tail(preds, refs, valid) -> dict:
    """RMSE and 99.9th percentile of |preds - refs| over every valid pixel and channel
    (``rrf_common.rmse_p999``), and their ratio."""
    import rrf_common

    rmse, p999 = rrf_common.rmse_p999(preds, refs, valid)
    return {"rmse": rmse, "p999_abs_error": p999, "p999_over_rmse": p999 / rmse}


def figure(path: str, preds, refs, errors, counts, threshold: float, rows: int = 4, scale: int = 4) -> list[int]:
    """The tail figure of ``--figure`` (module docstring) from each pair's ``abs_errors`` and its
    count of channels at or above ``threshold``; returns the pairs shown, worst first."""
    from jprt import io
    from jprt.metrics import tonemap

    err = [e.max(-1) for e in errors]
    shown = [int(i) for i in np.argsort(counts, kind="stable")[::-1][:rows]]
    lines = []
    for i in shown:
        grey = np.clip(err[i] / 0.1, 0.0, 1.0)
        worst = err[i] >= threshold
        panel = np.stack([grey, np.where(worst, 0.0, grey), np.where(worst, 0.0, grey)], -1)
        panel[worst, 0] = 1.0
        lines.append(np.concatenate([np.asarray(tonemap(refs[i])), np.asarray(tonemap(preds[i])), panel], axis=1))
    image = np.concatenate(lines, axis=0)
    image = np.repeat(np.repeat(image, scale, axis=0), scale, axis=1)
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    io.write_png(path, image, tonemapped=True)
    return shown


def timing_inputs(config: dict):
    """(G-buffer, one light, four lights) of rrf_cornell's timing frame (``rrf_common.frame`` and
    ``four_light_inputs``: the first held-out view at ``eval.timing_resolution``)."""
    import rrf_common

    from jprt.render.gbuffer import gbuffer
    from jprt.render.scenes import SceneHandle

    cameras, lightings = rrf_common.held_out_pairs(config)
    gb = gbuffer(SceneHandle(config["scene"], lightings[0]), rrf_common.timing_camera(config, cameras))
    return gb, lightings[0], rrf_common.four_light_inputs(config)


def timing(evaluate, params, cfg, inputs, repeats: int) -> dict:
    """Median 512^2 frame times with one and four lights, measured interleaved
    (``rrf_common.interleaved_times``), and the FLOPs."""
    import jax
    import rrf_common

    from jprt.methods.rrf import model as rrf

    gb, one, four = inputs
    dev = jax.device_put((gb, one, four))
    timed = rrf_common.interleaved_times({"rrf": jax.jit(evaluate)}, dev[0], {1: dev[1], 4: dev[2]}, repeats)
    ms1, ms4 = timed[("rrf", 1)]["median_ms"], timed[("rrf", 4)]["median_ms"]
    f1, f4 = rrf.frame_flops(params, cfg, gb, one), rrf.frame_flops(params, cfg, gb, four)
    return {"frame_ms": ms1, "frame_ms_4lights": ms4, "frame_ms_4lights_over_1light": ms4 / ms1,
            "frame_flops": f1, "frame_flops_4lights": f4, "frame_flops_4lights_over_1light": f4 / f1}


def score(config: dict, override: dict, testset, refs, valid, refs2=None, figure_path: str | None = None,
          frame_inputs=None) -> dict:
    """Fit rrf_cornell's config with ``override`` merged in; its tail statistics on the held-out set
    (and with ``refs2``, a second reference set, against the mean of the two)."""
    from jprt.config import merge
    from jprt.methods import REGISTRY
    from jprt.methods.rrf import data as rrf_data
    from jprt.runner import method_config

    method = REGISTRY["rrf"]
    cfg = method_config(method, merge(config, override))
    t0 = time.perf_counter()
    fit = method.fit(rrf_data.make_dataset(config["scene"], cfg, progress=False),
                     {**cfg, "train": {**cfg["train"], "progress": False}})
    evaluate = method.evaluator(fit.params, cfg)
    gbs = [testset.gbuffer(item.camera) for item in testset.items]
    preds = [np.asarray(evaluate(g, testset.lighting(item.lighting))) for g, item in zip(gbs, testset.items)]
    errors = abs_errors(preds, refs, valid)
    err = np.concatenate([e[v].ravel() for e, v in zip(errors, valid)])
    stats = tail(preds, refs, valid)
    p999 = stats["p999_abs_error"]
    surface = np.concatenate([np.repeat(np.asarray(g.object_id)[v] * 10 + np.argmax(np.abs(np.asarray(g.normal)), -1)[v], 3)
                              for g, v in zip(gbs, valid)])
    ids, counts = np.unique(surface[err >= p999], return_counts=True)
    worst = {f"{i // 10}/{i % 10}": int(c) for i, c in sorted(zip(ids, counts), key=lambda t: -t[1])}
    per_pair = [int(np.sum(e >= p999)) for e in errors]
    n_leaves, n_inputs = np.shape(fit.params["leaves"]["layers"][0]["w"])[:2]
    axes = np.asarray(fit.params["tree"]["axis"])
    out = {**stats, "n_leaves": int(n_leaves), "splits_per_axis": np.bincount(axes[axes >= 0], minlength=n_inputs).tolist(),
           "worst_0.1%_by_surface": worst, "worst_0.1%_by_pair": per_pair}
    if frame_inputs is not None:  # ``timing_inputs``
        out["timing"] = timing(evaluate, fit.params, cfg, frame_inputs, int(config["eval"]["timing_repeats"]))
    if refs2 is not None:
        out["against_mean_of_two_references"] = tail(preds, [(a + b) / 2 for a, b in zip(refs, refs2)], valid)
    if figure_path:
        out["figure"] = {"path": figure_path, "pairs": figure(figure_path, preds, refs, errors, per_pair, p999)}
    return {**out, "seconds": round(time.perf_counter() - t0)}


def main() -> None:
    import rrf_cornell

    from jprt.config import merge

    args = sys.argv[1:]
    noise, timed = "--noise" in args, "--timing" in args
    args = [a for a in args if a not in ("--noise", "--timing")]
    figures = None
    if "--figure" in args:
        at = args.index("--figure")
        if at + 1 >= len(args):
            sys.exit(__doc__)
        figures = args[at + 1]
        del args[at:at + 2]
    if len(args) != 1:
        sys.exit(__doc__)
    config = merge(rrf_cornell.CONFIG, {})
    folder = config["output"]["dir"]
    testset, refs, valid = held_out(config, os.path.join(folder, "tail_references.npz"))
    refs2 = None
    if noise:
        import rrf_common

        refs2 = held_out(config, os.path.join(folder, "tail_references_2.npz"), rrf_common.NOISE_SEED_OFFSET)[1]
        own = tail([a / np.sqrt(2) for a in refs], [b / np.sqrt(2) for b in refs2], valid)
        print(json.dumps({"name": "reference noise (|A - B| / sqrt 2)", "reference_spp":
                          int(config["eval"]["reference_spp"]), **own}), flush=True)
    inputs = timing_inputs(config) if timed else None
    for name, override in json.loads(args[0]).items():
        print(json.dumps({"name": name, "override": override,
                          **score(config, override, testset, refs, valid, refs2,
                                  figures and os.path.join(figures, f"tail_{name}.png"), inputs)}), flush=True)


if __name__ == "__main__":
    main()
