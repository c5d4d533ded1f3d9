"""Evaluation protocol shared by the methods: errors against path-traced references, timings,
the equal-error sample count, and the figures of a report.

Pure NumPy/JAX: anything that renders is passed in as a callback, so this module never imports
Mitsuba (DESIGN.md: only ``jprt/render`` does).

Conventions (Ren et al. 2013, §5 "Method Validation"): the error of a method over a test set of
(view, light) pairs is the RMSE over all valid pixels and RGB channels of all images together,
i.e. sqrt(mean over images of the per-image mean squared error), each image weighted by its
number of valid pixels.
"""

from __future__ import annotations

import functools
import math
import os
import re
import statistics
import time
from typing import Callable, NamedTuple, Sequence

import numpy as np

from jprt import io, metrics
from jprt.metrics import error_map, tonemap

__all__ = ["set_rmse", "object_scores", "noise_removed", "DARK_OBJECT_SCALE", "HeldOut", "SCORES", "SUMMARY_SCORES",
           "score_images", "score_held_out", "optional_metric", "time_call", "interleaved_times", "xla_flops",
           "xla_cost", "loop_aware_cost", "gather_overcount", "matmul_peak_gflops", "stream_bandwidth_gbs", "roofline",
           "roofline_of", "stream_at_size",
           "PathTracer", "EqualErrorCurve", "equal_error_spp", "side_by_side", "plot_series"]


def set_rmse(predictions: Sequence, references: Sequence, valids: Sequence | None = None) -> float:
    """RMSE over all valid pixels and channels of a set of (H, W, C) images (module docstring).

    Anything but (H, W, C) images (with (H, W) masks) is refused: a (T, 3) lightmap read as an
    image would be a T x 3 image of one channel, and its RMSE over a mask would be wrong without a
    word (lightmaps are compared with ``jprt.methods.datadriven.model.lightmap_rmse``, or as atlas
    images through ``jprt.methods.lightmap_lookup``)."""
    if len(predictions) != len(references) or not len(predictions):
        raise ValueError(f"need equally many (>0) predictions and references, got {len(predictions)} and "
                         f"{len(references)}")
    total, count = 0.0, 0
    for k, (p, r) in enumerate(zip(predictions, references)):
        p, r = np.asarray(p, np.float64), np.asarray(r, np.float64)
        if p.shape != r.shape:
            raise ValueError(f"image {k}: prediction {p.shape} and reference {r.shape} differ")
        if p.ndim != 3:
            raise ValueError(f"image {k}: set_rmse takes (H, W, C) images, got shape {p.shape}")
        m = np.ones(p.shape[:2], bool) if valids is None else np.asarray(valids[k], bool)
        if m.shape != p.shape[:2]:
            raise ValueError(f"image {k}: valid mask {m.shape} does not match the image's (H, W) = {p.shape[:2]}")
        total += float(np.sum(np.square(p - r)[m]))
        count += int(m.sum()) * p.shape[-1]
    return float(np.sqrt(total / max(count, 1)))


#: An object whose reference RMS is below this fraction of the RMS of every labelled pixel of the
#: same images is scored on that image scale instead of its own (``object_scores``).
DARK_OBJECT_SCALE = 0.1


def object_scores(predictions: Sequence, references: Sequence, object_id, names: Sequence[str], *,
                  min_fraction: float = 0.0, dark_scale: float = DARK_OBJECT_SCALE) -> dict:
    """Relative RMSE of each object over a set of predictions, defined for dark objects too.

    ``predictions`` and ``references`` are equally long lists of arrays (..., C) (images
    (H, W, C), lightmap texels (T, C)); ``object_id`` is one integer array of their leading shape
    (-1: no object), shared by every item, or a list of one per item. For object k the score is

        rel_k = RMS(p - r over k's entries) / max(RMS(r over k), dark_scale * RMS(r over every
        labelled entry))

    pooled over all items (the brightest lighting weighs most). For a lit object it is
    ||p - r|| / ||r|| (predicting zero scores 1); an object whose reference is dark against its
    image (``scale`` "image") is judged on the image's own level, so a black reference never
    divides by zero or gives a huge number. Where every reference is black there is no scale:
    the score is 0 for a black prediction and 1 otherwise (``scale`` "none").

    Returns {name: {"pixels", "fraction", "rel_rmse", "scale", "rel_rmse_by_lighting",
    "mean_ratio"}} for objects with at least ``min_fraction`` of the labelled-or-not entries of
    the first item; ``mean_ratio`` is sum(p) / sum(r) on the object (None where it is scored on
    the image scale: a ratio of near-zero sums means nothing).
    """
    if len(predictions) != len(references) or not len(predictions):
        raise ValueError(f"need equally many (>0) predictions and references, got {len(predictions)} and "
                         f"{len(references)}")
    ids = list(object_id) if isinstance(object_id, (list, tuple)) else [object_id] * len(references)
    if len(ids) != len(references):
        raise ValueError(f"got {len(ids)} object-id arrays for {len(references)} items")
    preds = [np.asarray(p, np.float64) for p in predictions]
    refs = [np.asarray(r, np.float64) for r in references]
    ids = [np.asarray(i) for i in ids]
    for k, (p, r, i) in enumerate(zip(preds, refs, ids)):
        if p.shape != r.shape or p.shape[:-1] != i.shape:
            raise ValueError(f"item {k}: prediction {p.shape}, reference {r.shape} and object ids {i.shape} "
                             "do not match (ids have the items' leading shape)")

    def ms(x):  # mean square over entries and channels, and the entry count
        return float(np.sum(x * x)), x.size

    image_sq = [ms(r[i >= 0]) for r, i in zip(refs, ids)]
    image_rms = np.sqrt(sum(s for s, _ in image_sq) / max(sum(n for _, n in image_sq), 1))
    image_rms_each = [np.sqrt(s / max(n, 1)) for s, n in image_sq]

    def score(err_sq, n, ref_rms, scale_rms):
        floor = float(dark_scale) * scale_rms
        err = np.sqrt(err_sq / max(n, 1))
        if ref_rms >= floor and ref_rms > 0:
            return float(err / ref_rms), "object"
        if floor > 0:
            return float(err / floor), "image"
        return (0.0 if err == 0 else 1.0), "none"

    out = {}
    total = ids[0].size
    for k in np.unique(np.concatenate([i[i >= 0].ravel() for i in ids])):
        masks = [i == k for i in ids]
        count = int(masks[0].sum())
        fraction = count / max(total, 1)
        if fraction < float(min_fraction):
            continue
        p = np.concatenate([x[m].ravel() for x, m in zip(preds, masks)])
        r = np.concatenate([x[m].ravel() for x, m in zip(refs, masks)])
        rel, scale = score(float(np.sum((p - r) ** 2)), p.size, np.sqrt(ms(r)[0] / max(r.size, 1)), image_rms)
        by = []
        for x, y, m, s in zip(preds, refs, masks, image_rms_each):
            a, b = x[m], y[m]
            by.append(score(float(np.sum((a - b) ** 2)), a.size, np.sqrt(ms(b)[0] / max(b.size, 1)), s)[0])
        out[str(names[int(k)])] = {"pixels": count, "fraction": fraction, "rel_rmse": rel, "scale": scale,
                                   "rel_rmse_by_lighting": by,
                                   "mean_ratio": float(p.sum() / r.sum()) if scale == "object" else None}
    return out


def noise_removed(rel: float, floor: float) -> float:
    """The error against the truth with the reference's own noise taken out: sqrt(rel^2 - floor^2 / 2),
    where ``floor`` is two references of independent seeds scored against each other (so their
    difference carries the noise twice: E|p - r|^2 = |p - truth|^2 + |n|^2)."""
    return float(np.sqrt(max(float(rel) ** 2 - 0.5 * float(floor) ** 2, 0.0)))


class HeldOut(NamedTuple):
    """Held-out predictions and references, all (H, W, 3) images (one per view / lighting pair).

    Fields:
      predictions: list of (H, W, 3) indirect predictions of the method.
      references: list of (H, W, 3) path-traced indirect references.
      valid: list of (H, W) masks of the pixels that count.
      direct: list of (H, W, 3) direct radiance (for psnr_full), or None.
      labels: one label per image (figure rows).
    """

    predictions: list
    references: list
    valid: list
    direct: list | None = None
    labels: list | None = None


#: The scores of a held-out set that every run's summary carries (``score_images``' default).
SUMMARY_SCORES = ("indirect_rmse", "indirect_rel_rmse", "indirect_rel_rmse_worst_image", "p999_abs_error",
                  "psnr_indirect", "ssim_indirect", "psnr_full", "flip_indirect", "lpips_indirect")
#: Every score ``score_images`` computes: the summary's, SSIM of direct + indirect, the mean over
#: images of each image's RMSE (the per-image convention of some papers' tables) and each image's
#: relative RMSE.
SCORES = SUMMARY_SCORES + ("ssim_full", "image_rmse_mean", "indirect_rel_rmse_by_image")


def score_images(predictions: Sequence, references: Sequence, valid: Sequence | None = None,
                 direct: Sequence | None = None, *, exposure: float = 0.0, scores: Sequence[str] = SUMMARY_SCORES,
                 psnr_valid: bool = False) -> dict:
    """The scores of a held-out set of (H, W, C) images, the one definition every report uses.

    ``valid``: (H, W) masks of the pixels that count (None: all); ``direct``: the direct images,
    for the scores of direct + indirect (None: those scores are None). ``scores`` names the ones
    to compute (a subset of ``SCORES``; FLIP and LPIPS are the costly ones):

    * ``indirect_rmse``: ``set_rmse`` over every valid pixel and channel of all images (HDR);
    * ``indirect_rel_rmse``: that over the RMS of the references on the same pixels;
    * ``indirect_rel_rmse_by_image``: each image's own relative RMSE (its RMSE over its
      reference's RMS, on its valid pixels; inf for a black reference with any error), a list;
      ``indirect_rel_rmse_worst_image``: the largest of them (a set's score can hide one bad image);
    * ``p999_abs_error``: 99.9th percentile of |prediction - reference| over the same entries;
    * ``psnr_indirect``, ``ssim_indirect``, ``psnr_full``, ``ssim_full``: of the sRGB-tonemapped
      images at ``exposure`` (clipped, peak 1), mean over images; over the whole image (pixels that
      do not count are expected to be 0 in both), or over the valid pixels with ``psnr_valid``;
      SSIM is None for images smaller than its 11 x 11 window;
    * ``flip_indirect``, ``lpips_indirect``: ``jprt.metrics.flip`` / ``lpips`` of the tonemapped
      images, mean over images (None, with a warning, without their package; LPIPS None under
      ``metrics.LPIPS_MIN_SIZE`` pixels a side);
    * ``image_rmse_mean``: the mean over images of each image's RMSE over its valid pixels.

    Returns {name: float or None} in the order of ``scores``.
    """
    unknown = set(scores) - set(SCORES)
    if unknown:
        raise ValueError(f"unknown scores {sorted(unknown)}; known: {list(SCORES)}")
    preds, refs = list(predictions), list(references)
    valid = list(valid) if valid is not None else None
    masks = [np.ones(np.shape(r)[:2], bool) if m is None else np.asarray(m, bool)
             for r, m in zip(refs, valid if valid is not None else [None] * len(refs))]
    out: dict = {}
    if {"indirect_rmse", "indirect_rel_rmse"} & set(scores):
        out["indirect_rmse"] = set_rmse(preds, refs, valid)
        ref_rms = set_rmse([np.zeros_like(np.asarray(r)) for r in refs], refs, valid)
        out["indirect_rel_rmse"] = out["indirect_rmse"] / max(ref_rms, 1e-30)
    if {"indirect_rel_rmse_by_image", "indirect_rel_rmse_worst_image"} & set(scores):
        per = []
        for p, r, m in zip(preds, refs, masks):
            err = set_rmse([p], [r], [m])
            rms = set_rmse([np.zeros_like(np.asarray(r))], [r], [m])
            per.append(err / rms if rms > 0 else (0.0 if err == 0 else math.inf))
        out["indirect_rel_rmse_by_image"] = per
        out["indirect_rel_rmse_worst_image"] = max(per) if per else None
    if "p999_abs_error" in scores:
        errors = np.concatenate([np.abs(np.asarray(p, np.float64) - np.asarray(r, np.float64))[m].ravel()
                                 for p, r, m in zip(preds, refs, masks)])
        out["p999_abs_error"] = float(np.percentile(errors, 99.9)) if errors.size else None

    def mean(metric, pairs, **kw):
        return float(np.mean([float(metrics.tonemapped(metric, p, r, exposure, **kw)) for p, r in pairs]))

    def psnr(pairs):
        if not psnr_valid:
            return mean(metrics.psnr, pairs)
        return float(np.mean([float(metrics.tonemapped(metrics.psnr, p, r, exposure, valid=m))
                              for (p, r), m in zip(pairs, masks)]))

    small = min(min(np.shape(r)[:2]) for r in refs) < 11  # SSIM's 11 x 11 window does not fit
    full = None if direct is None else [(d + p, d + r) for p, r, d in zip(preds, refs, direct)]
    if "psnr_indirect" in scores:
        out["psnr_indirect"] = psnr(zip(preds, refs))
    if "ssim_indirect" in scores:
        out["ssim_indirect"] = None if small else mean(metrics.ssim, zip(preds, refs))
    if "psnr_full" in scores:
        out["psnr_full"] = None if full is None else psnr(full)
    if "ssim_full" in scores:
        out["ssim_full"] = None if full is None or small else mean(metrics.ssim, full)
    if "flip_indirect" in scores:
        out["flip_indirect"] = optional_metric(
            lambda: float(np.mean([metrics.flip(p, r, exposure) for p, r in zip(preds, refs)])))
    if "lpips_indirect" in scores:
        tiny = min(min(np.shape(r)[:2]) for r in refs) < metrics.LPIPS_MIN_SIZE
        out["lpips_indirect"] = None if tiny else optional_metric(
            lambda: float(np.mean([metrics.lpips(p, r, exposure) for p, r in zip(preds, refs)])))
    if "image_rmse_mean" in scores:
        out["image_rmse_mean"] = float(np.mean([float(metrics.rmse(p, r, None if valid is None else valid[k]))
                                                for k, (p, r) in enumerate(zip(preds, refs))]))
    return {k: out[k] for k in scores}


def score_held_out(held: HeldOut, exposure: float = 0.0, scores: Sequence[str] = SUMMARY_SCORES, **kw) -> dict:
    """``score_images`` of a ``HeldOut`` set (its predictions, references, masks and direct images)."""
    return score_images(held.predictions, held.references, held.valid, held.direct, exposure=exposure, scores=scores,
                        **kw)


def optional_metric(compute: Callable[[], float]) -> float | None:
    """A metric that needs an optional package: its value, or None (with a warning) without it."""
    try:
        return compute()
    except RuntimeError as e:  # the package is missing: say so, do not fail the whole run
        import warnings

        warnings.warn(str(e), RuntimeWarning, stacklevel=3)
        return None


def time_call(fn: Callable, *args, repeats: int = 10, warmup: int = 2) -> dict:
    """Wall time of ``fn(*args)`` in milliseconds: median (and min, all) of ``repeats`` runs after
    ``warmup`` runs; JAX results are waited for with ``block_until_ready``."""

    def run():
        out = fn(*args)
        for leaf in _leaves(out):
            if hasattr(leaf, "block_until_ready"):
                leaf.block_until_ready()
        return out

    for _ in range(max(0, int(warmup))):
        run()
    times = []
    for _ in range(max(1, int(repeats))):
        t0 = time.perf_counter()
        run()
        times.append(1e3 * (time.perf_counter() - t0))
    return {"median_ms": statistics.median(times), "min_ms": min(times), "times_ms": times}


def xla_cost(jitted: Callable, *args) -> dict:
    """XLA's cost analysis of one call of ``jitted`` (a ``jax.jit`` function) on ``args``, compiled
    once, with every loop counted as many times as it runs: {"flops": multiply-adds count 2,
    gathers, sorts and scatters nothing; "transcendentals": exp, log, sqrt and the like, each
    counted once (not in "flops"); "bytes": the bytes the frame moves to and from memory, by this
    model: XLA's "bytes accessed" of its fused operations (each fusion's operands and results,
    not what stays in registers or cache inside it), except that a table read only through
    gathers is charged for the rows they read (``gather_overcount``), not its whole size as XLA
    charges it, and that a loop moves each array it carries once (a tiled evaluator's ``lax.map``:
    its inputs read and its output written once; a tile's intermediates are sized to stay in cache,
    the reason it is tiled); "bytes_xla": XLA's own figure, every fusion of every loop iteration
    counted; "loops": the trip counts of the while loops it multiplied, "loops_unknown": loops
    counted once (no static trip count, or inside a conditional's branch); both None when the
    module's loops could not be counted (XLA's once-counted figures then stand)}, each None when
    the backend reports none.

    XLA's own analysis counts a while loop's body once whatever its trip count (a ``lax.map`` over
    16 tiles reported 1/16 of the frame's FLOPs); ``loop_aware_cost`` costs each body as a module
    of its own and counts it that many times.
    """
    try:
        compiled = jitted.lower(*args).compile()
        cost = compiled.cost_analysis()
    except Exception:  # noqa: BLE001 - a backend without cost analysis
        return {"flops": None, "transcendentals": None, "bytes": None, "bytes_xla": None, "loops": [],
                "loops_unknown": 0}
    cost = cost[0] if isinstance(cost, (list, tuple)) and cost else cost
    try:
        text = compiled.as_text()
    except Exception:  # noqa: BLE001 - no HLO text: XLA's figures stand
        text = ""
    try:
        looped = loop_aware_cost(text) if text else None
    except Exception:  # noqa: BLE001 - HLO text this parser does not follow: XLA's figures stand
        looped = None
    if looped is None:  # no loops, or loops this module's text did not let us count (``loops`` None)
        uncounted = " while(" in text or not text
        looped = {"flops": cost.get("flops") if cost else None, "transcendentals": cost.get("transcendentals")
                  if cost else None, "bytes_xla": cost.get("bytes accessed") if cost else None,
                  "overcount": gather_overcount(text) if text else 0.0, "loops": None if uncounted else [],
                  "loops_unknown": None if uncounted else 0}
    out = {}
    for key in ("flops", "transcendentals", "bytes_xla"):
        value = looped[key]
        out[key] = float(value) if value is not None and value > 0 else None
    moved = looped.get("bytes_moved")
    if moved is None and out["bytes_xla"] is not None:
        moved = max(out["bytes_xla"] - looped["overcount"], 0.0) or out["bytes_xla"]
    out["bytes"] = None if moved is None else float(moved)
    out["loops"], out["loops_unknown"] = looped["loops"], looped["loops_unknown"]
    return out


_COMP_HEAD = r"^(ENTRY )?%([\w.\-]+) \(.*\{\s*$"


def _computation_blocks(text: str) -> tuple[str, dict, str | None]:
    """An HLO module's text split into its header line and its computations: (header, {name:
    (head line without ENTRY, body lines)}, the entry's name)."""
    head = re.compile(_COMP_HEAD)
    header, blocks, entry, current = "", {}, None, None
    for line in text.splitlines():
        if line.startswith("HloModule"):
            header = line
            continue
        m = head.match(line)
        if m:
            current = m.group(2)
            blocks[current] = (line[len("ENTRY "):] if m.group(1) else line, [])
            entry = current if m.group(1) else entry
            continue
        if current is None:
            continue
        if line.startswith("}"):
            current = None
            continue
        # stack frame ids point into a table the computations alone do not carry
        blocks[current][1].append(re.sub(r"\s*stack_frame_id=\d+", "", line))
    return header, blocks, entry


def _reachable(blocks: dict, roots) -> list:
    """The computations of ``blocks`` (``_computation_blocks``) that ``roots`` reach through the
    names their lines mention, ``roots`` included, in the order first reached."""
    seen, order, frontier = set(), [], [r for r in roots if r in blocks]
    while frontier:
        name = frontier.pop()
        if name in seen:
            continue
        seen.add(name)
        order.append(name)
        for line in blocks[name][1]:
            frontier += [n for n in re.findall(r"%([\w.\-]+)", line) if n in blocks and n not in seen]
    return order


def _module_as(header: str, blocks: dict, entry: str) -> str:
    """The module text with ``entry`` as its entry computation and only the computations it reaches."""
    order = _reachable(blocks, [entry])
    # the header's entry layout names the original entry's signature: left out
    header = re.sub(r", entry_computation_layout=\{.*?\}(?=, [a-z_]+=|$)", "", header)
    parts = [header, ""]
    for name in reversed(order):  # callees first, as XLA prints them
        head, body = blocks[name]
        parts += [("ENTRY " if name == entry else "") + head] + body + ["}", ""]
    return "\n".join(parts)


def _module_cost(text: str) -> dict | None:
    """XLA's cost analysis of an HLO module given as text (loops counted once): {"flops",
    "transcendentals", "bytes_xla", "overcount" (``gather_overcount``)}, None if it does not parse."""
    try:
        from jax._src import xla_bridge
        from jax._src.lib import xla_client
        from jaxlib import _hlo

        cost = xla_client._xla.hlo_module_cost_analysis(xla_bridge.get_backend(), _hlo.hlo_module_from_text(text))
    except Exception:  # noqa: BLE001 - a module the parser or this jaxlib does not take
        return None
    return {"flops": float(cost.get("flops", 0.0)), "transcendentals": float(cost.get("transcendentals", 0.0)),
            "bytes_xla": float(cost.get("bytes accessed", 0.0)), "overcount": gather_overcount(text)}


def loop_aware_cost(hlo_text: str) -> dict | None:
    """XLA's cost of a compiled module (its ``as_text()``) with each while loop of a known trip
    count ("known_trip_count" in its backend config) counted that many times: cost(C) = XLA's
    cost of C (every loop body in it once) + sum over C's loops of (trips x cost(body) - XLA's
    cost of the body), recursively for loops in loops. A loop without a known trip count is
    counted once (its inner loops at their trip counts), and so is a loop inside a conditional's
    branch (XLA costs a conditional as its larger branch, which a loop's extra iterations would
    not stay inside); both are counted in "loops_unknown". Returns {"flops", "transcendentals",
    "bytes_xla", "overcount" (``gather_overcount``, loops counted the same way), "bytes_moved"
    (``xla_cost``'s model: the entry's fused operations outside its loops, gathered tables
    charged for their rows, plus each loop's carried arrays once: what a body reads and writes
    in an iteration is taken to stay in cache, true of a tile; for a loop over state larger than
    the cache it is a lower bound), "loops" (trip counts), "loops_unknown"}, or None when the
    module has no while loop or does not parse."""
    if " while(" not in hlo_text:
        return None
    header, blocks, entry = _computation_blocks(hlo_text)
    if entry is None:
        return None
    loop_re = re.compile(r"\swhile\(.*?body=%?([\w.\-]+)")
    trips_re = re.compile(r'"known_trip_count":\{"n":"(\d+)"\}')
    branch_re = re.compile(r"(?:branch_computations=\{([^}]*)\}|true_computation=%?([\w.\-]+)|"
                           r"false_computation=%?([\w.\-]+))")
    names = set(blocks)
    record = {"loops": [], "loops_unknown": 0}
    keys = ("flops", "transcendentals", "bytes_xla", "overcount")
    once_cache: dict = {}

    def once(name: str) -> dict | None:  # XLA's cost of computation ``name`` as the entry (loops once)
        if name not in once_cache:
            once_cache[name] = _module_cost(_module_as(header, blocks, name))
        return None if once_cache[name] is None else dict(once_cache[name])

    def loops_in(name: str) -> tuple[list, int]:
        """(body, trips, line) of the whiles ``name`` reaches outside other loops and outside
        conditionals' branches, and the number of whiles inside those branches."""
        found, in_branches, frontier, seen = [], 0, [name], set()
        while frontier:
            comp = frontier.pop()
            if comp in seen:
                continue
            seen.add(comp)
            for line in blocks[comp][1]:
                m = loop_re.search(line)
                if m:
                    t = trips_re.search(line)
                    found.append((m.group(1), int(t.group(1)) if t else None, line))
                    continue
                if " conditional(" in line:
                    branches = [n for g in branch_re.findall(line) for part in g
                                for n in re.findall(r"%?([\w.\-]+)", part) if n in names]
                    in_branches += sum(" while(" in x for b in _reachable(blocks, branches)
                                      for x in blocks[b][1])
                    continue
                frontier += [n for n in re.findall(r"%([\w.\-]+)", line) if n in names]
        return found, in_branches

    def cost(name: str) -> dict | None:
        own = once(name)
        if own is None:
            return None
        found, in_branches = loops_in(name)
        record["loops_unknown"] += in_branches
        for body, trips, _ in found:
            single, full = once(body), cost(body)
            if single is None or full is None:
                return None
            if trips is None:  # run count unknown: once, with the loops inside it counted
                record["loops_unknown"] += 1
                trips = 1
            else:
                record["loops"].append(trips)
            for k in keys:
                own[k] += trips * full[k] - single[k]
        return own

    total = cost(entry)
    if total is None:
        return None
    outer = once(entry)
    moved = outer["bytes_xla"] - outer["overcount"]
    for body, _, line in loops_in(entry)[0]:  # a loop's traffic: its carried arrays once, not its body's
        single = once(body)
        if single is None:
            return None
        carried = re.match(r"^\s*(?:ROOT )?%[\w.\-]+ = \((.*?)\) while\(", line)
        moved += -(single["bytes_xla"] - single["overcount"]) + (_shapes_bytes(carried.group(1)) if carried else 0.0)
    return {**total, **record, "bytes_moved": max(moved, 0.0)}


def _shapes_bytes(shapes: str) -> float:
    """The bytes of the arrays in an HLO tuple type's text ("s32[], f32[16,4096]{1,0}, ...")."""
    return float(sum(_DTYPE_BYTES.get(dtype, 4) * math.prod(int(d) for d in dims.split(",") if d)
                     for dtype, dims in re.findall(r"\b([a-z]+\d*)\[([\d,]*)\]", shapes)))


_DTYPE_BYTES = {"pred": 1, "s8": 1, "u8": 1, "s16": 2, "u16": 2, "f16": 2, "bf16": 2, "s32": 4, "u32": 4,
                "f32": 4, "s64": 8, "u64": 8, "f64": 8, "c64": 8, "c128": 16}
# ops that pass a table through unchanged in what a gather of it reads (a view or a per-element cast)
_PASS_THROUGH = ("bitcast", "convert", "copy", "reshape")


def _hlo_computations(text: str) -> dict:
    """The computations of an HLO module's text: name -> {"entry": bool, "ops": {instruction name:
    (dtype, dims, opcode, operand names, attribute text)}}; array-shaped instructions only."""
    import re

    comps, current = {}, None
    head = re.compile(_COMP_HEAD)
    line_re = re.compile(r"^\s*(?:ROOT )?%([\w.\-]+) = (\w+)\[([\d,]*)\]\S* ([\w\-]+)\((.*)$")
    for line in text.splitlines():
        m = head.match(line)
        if m:
            current = comps.setdefault(m.group(2), {"entry": bool(m.group(1)), "ops": {}})
            continue
        if line.startswith("}"):
            current = None
            continue
        m = line_re.match(line) if current is not None else None
        if not m:
            continue
        name, dtype, dims, opcode, rest = m.groups()
        depth, end = 1, len(rest)
        for i, ch in enumerate(rest):  # the operand list ends at the parenthesis that closes it
            depth += {"(": 1, ")": -1}.get(ch, 0)
            if depth == 0:
                end = i
                break
        operands = re.findall(r"%([\w.\-]+)", rest[:end])
        current["ops"][name] = (dtype, [int(d) for d in dims.split(",") if d], opcode, operands, rest[end:])
    return comps


def gather_overcount(hlo_text: str, line_bytes: int = 64) -> float:
    """Bytes XLA's "bytes accessed" charges for gathered tables beyond what their gathers read.

    XLA charges a gather's table operand at its full size; a lightmap or feature-grid lookup reads
    only the rows its indices name. For every table a gather reads (a fusion's parameter used only
    by gathers, through views and casts; or an unfused gather's operand), this counts its size minus
    the rows read (each gathered slice rounded up to ``line_bytes``, one cache line; the table's
    size at most), summed over the module of ``hlo_text`` (a compiled executable's ``as_text()``).
    """
    import re

    total = 0.0
    for comp in _hlo_computations(hlo_text).values():
        ops = comp["ops"]
        users: dict = {}
        for name, (_, _, _, operands, _) in ops.items():
            for o in operands:
                users.setdefault(o, []).append(name)

        def size(name: str) -> float:
            dtype, dims, *_ = ops[name]
            return float(_DTYPE_BYTES.get(dtype, 4) * math.prod(dims))

        def read(gather: str, elem_bytes: int) -> float:  # the rows one gather reads, in lines
            _, dims, _, _, attrs = ops[gather]
            m = re.search(r"slice_sizes=\{([\d,]*)\}", attrs)
            slice_elems = math.prod(int(d) for d in m.group(1).split(",") if d) if m else 1
            n = math.prod(dims) / max(slice_elems, 1)
            return n * line_bytes * math.ceil(slice_elems * elem_bytes / line_bytes)

        tables: dict = {}
        for name, (dtype, dims, opcode, operands, _) in ops.items():
            if opcode != "gather" or not operands or operands[0] not in ops:
                continue
            source = operands[0]
            if not comp["entry"]:  # inside a fusion: follow views and casts back to its parameter
                while ops[source][2] in _PASS_THROUGH and ops[source][3] and ops[source][3][0] in ops:
                    source = ops[source][3][0]
                if ops[source][2] != "parameter":
                    continue
                tables.setdefault(source, []).append(name)
            else:  # an unfused gather is charged its own operand in full
                src = ops[source]
                total += max(size(source) - read(name, _DTYPE_BYTES.get(src[0], 4)), 0.0)
        for param, gathers in tables.items():
            # every use of the parameter (through views and casts) must be one of these gathers
            frontier, ok = [param], True
            while frontier and ok:
                for u in users.get(frontier.pop(), []):
                    if ops[u][2] in _PASS_THROUGH:
                        frontier.append(u)
                    elif not (ops[u][2] == "gather" and u in gathers):
                        ok = False
            if ok:
                elem = _DTYPE_BYTES.get(ops[param][0], 4)
                total += max(size(param) - sum(read(g, elem) for g in gathers), 0.0)
    return total


def xla_flops(jitted: Callable, *args) -> float | None:
    """FLOPs of one call of ``jitted`` on ``args`` as XLA counts them (``xla_cost``)."""
    return xla_cost(jitted, *args)["flops"]


def _triad():
    """STREAM's triad as ``stream_bandwidth_gbs`` runs it: (a, b, c) -> 0 a + b + 3 c, ``a`` donated."""
    import jax

    return jax.jit(lambda a, b, c: 0.0 * a + b + 3.0 * c, donate_argnums=0)


@functools.lru_cache(maxsize=None)
def stream_bandwidth_gbs(n_bytes: int = 256 << 20, repeats: int = 5) -> float:
    """The memory bandwidth of this process (GB/s): the STREAM triad a = b + 3 c in JAX over
    float32 arrays of ``n_bytes`` each (default 256 MiB, far larger than CPU caches), written into
    ``a``'s own buffer, the fastest of ``repeats`` timed calls after warm-up. Measured once per
    process and argument set (about a second on a CPU).

    ``a`` is donated and enters the sum times 0, so XLA writes the result in place: a triad into a
    fresh 256 MiB output spends most of its time faulting in new pages, which no evaluator's
    stream pays (CHANGELOG.md has the two rates side by side). The bytes counted are what the
    kernel moves: ``a``, ``b``, ``c`` read and ``a`` written."""
    import jax
    import jax.numpy as jnp

    n = max(int(n_bytes) // 4, 1)
    b = jax.device_put(jnp.ones((n,), jnp.float32))
    c = jax.device_put(jnp.full((n,), 0.5, jnp.float32))
    a = jax.device_put(jnp.zeros((n,), jnp.float32))
    triad = _triad()
    times = []
    for i in range(2 + max(1, int(repeats))):
        t0 = time.perf_counter()
        a = triad(a, b, c)
        a.block_until_ready()
        if i >= 2:
            times.append(time.perf_counter() - t0)
    return 4.0 * 4 * n / min(times) / 1e9


#: The triad's repeats at a frame's size (``stream_at_size``): a frame-sized triad takes
#: microseconds to milliseconds, and its fastest call needs more tries than a 256 MiB one.
SIZED_STREAM_REPEATS = 50


def stream_at_size(moved: float, bandwidth_gbs: float) -> dict:
    """A pure stream of a frame's own size against the memory roof: ``stream_bandwidth_gbs``'s
    triad with its four arrays moving ``moved`` bytes in one call (each array ``moved`` / 4,
    rounded up to 64 KiB, at most 256 MiB: the roof's own size), the fastest of
    ``SIZED_STREAM_REPEATS`` (of 5 past 16 MiB an array). Returns
    {``stream_gbs_at_frame_bytes``, ``stream_fraction_at_frame_bytes``: that rate over
    ``bandwidth_gbs``}.

    A small call does not reach the 256 MiB triad's rate (below about 1 MB each call's fixed cost
    outweighs its bytes; CHANGELOG.md, 2026-12-08), and a mid-size one beats it (its arrays stay
    in cache). Where the fraction is below a target
    fraction of the roofline, no single call moving the frame's bytes reaches that target on its
    memory roof: the yardstick says what the frame's size alone allows."""
    chunk = 64 << 10
    n_bytes = min(max(int(math.ceil(float(moved) / 4.0 / chunk)) * chunk, chunk), 256 << 20)
    # past 16 MiB an array a call takes milliseconds and the 256 MiB triad's five tries do
    rate = stream_bandwidth_gbs(n_bytes=n_bytes, repeats=SIZED_STREAM_REPEATS if n_bytes <= 16 << 20 else 5)
    return {"stream_gbs_at_frame_bytes": rate, "stream_fraction_at_frame_bytes": rate / float(bandwidth_gbs)}


def matmul_peak_gflops(n: int = 1024, repeats: int = 10, dtype: str = "float32",
                       precision: str | None = None) -> float:
    """The JAX matmul rate of this process (GFLOP/s): an n x n by n x n product, the fastest of
    ``repeats`` timed runs after warm-up: what "near the machine's limit" is judged against.
    ``precision`` is ``jnp.matmul``'s (None: JAX's default, which lets XLA use TF32 for float32
    on NVIDIA GPUs; "highest": full float32)."""
    import jax
    import jax.numpy as jnp

    a = jax.device_put(jnp.asarray(np.random.default_rng(0).random((n, n)), dtype))
    ms = time_call(jax.jit(lambda x: jnp.matmul(x, x, precision=precision)), a, repeats=repeats, warmup=2)["min_ms"]
    return 2.0 * n ** 3 / (ms * 1e-3) / 1e9


def roofline(jitted: Callable, *args, frame_ms: float, peak_gflops: float | None = None,
             flops: float | None = None, bandwidth_gbs: float | None = None,
             frame_bytes: float | None = None) -> dict:
    """A frame time judged against the machine.

    Returns ``frame_flops`` (``flops`` when given, else XLA's count), the achieved
    ``frame_gflops_per_s``, ``matmul_peak_gflops`` (measured now unless given),
    ``flops_fraction_of_peak`` = achieved / peak, and ``roofline``: {``matmul_gflops``,
    ``bandwidth_gbs`` (``stream_bandwidth_gbs``, measured now unless given), ``frame_flops``,
    ``frame_bytes`` (``frame_bytes`` when given, else ``xla_cost``'s bytes: XLA's bytes accessed
    with gathered tables charged for the rows read and loops' carried arrays once),
    ``frame_bytes_xla`` (XLA's own figure, every loop iteration's fusions counted),
    ``frame_transcendentals`` (XLA's count, loops counted), ``intensity`` (FLOP per byte),
    ``attainable_gflops`` = min(peak, intensity x bandwidth), ``bound`` ("compute" or "memory":
    which of the two is the smaller), ``fraction_of_roofline`` = achieved / attainable, and
    ``stream_at_size``'s two numbers for the frame's bytes}. None where nothing counts (no FLOP or
    byte count)."""
    cost = xla_cost(jitted, *args)
    out = roofline_of(cost["flops"] if flops is None else float(flops),
                      cost["bytes"] if frame_bytes is None else float(frame_bytes), frame_ms=frame_ms,
                      peak_gflops=peak_gflops, bandwidth_gbs=bandwidth_gbs)
    out["roofline"]["frame_bytes_xla"] = cost.get("bytes_xla")
    out["roofline"]["frame_transcendentals"] = cost.get("transcendentals")
    return out


def roofline_of(flops: float | None, moved: float | None, *, frame_ms: float, peak_gflops: float | None = None,
                bandwidth_gbs: float | None = None) -> dict:
    """``roofline``'s report from counts already known: ``flops`` and bytes ``moved`` per call
    (e.g. ``xla_cost`` of a program compiled elsewhere) taking ``frame_ms``; the matmul rate and
    the triad bandwidth measured now unless given, the triad at the frame's size
    (``stream_at_size``) measured now where ``moved`` is known."""
    peak = matmul_peak_gflops() if peak_gflops is None else float(peak_gflops)
    bandwidth = stream_bandwidth_gbs() if bandwidth_gbs is None else float(bandwidth_gbs)
    rate = None if flops is None else flops / (frame_ms * 1e-3) / 1e9
    intensity = None if flops is None or not moved else flops / moved
    attainable = None if intensity is None else min(peak, intensity * bandwidth)
    return {"frame_flops": flops, "frame_gflops_per_s": rate, "matmul_peak_gflops": peak,
            "flops_fraction_of_peak": None if rate is None else rate / peak,
            "roofline": {"matmul_gflops": peak, "bandwidth_gbs": bandwidth, "frame_flops": flops, "frame_bytes": moved,
                         "intensity": intensity, "attainable_gflops": attainable,
                         "bound": None if attainable is None else ("compute" if attainable >= peak else "memory"),
                         "fraction_of_roofline": None if attainable is None else rate / attainable,
                         **(stream_at_size(moved, bandwidth) if moved and math.isfinite(moved) else
                            {"stream_gbs_at_frame_bytes": None, "stream_fraction_at_frame_bytes": None})}}


def _leaves(out):
    if isinstance(out, (tuple, list)):
        for o in out:
            yield from _leaves(o)
    elif isinstance(out, dict):
        for o in out.values():
            yield from _leaves(o)
    else:
        yield out


class PathTracer(NamedTuple):
    """Mitsuba as the peer of the evaluator.

    Fields:
      render_at: ``spp -> list`` of indirect images of the held-out set (a seed unlike the references').
      time_at: ``spp -> ms``: wall time of one frame of the timed view at ``spp`` (None: not timed).
      note: how it was timed (stored in ``extra``).
    """

    render_at: Callable[[int], Sequence]
    time_at: Callable[[int], float] | None
    note: str = ""


class EqualErrorCurve:
    """Mitsuba's speed-accuracy curve on a held-out set, and a model's error read off it.

    ``points`` are Mitsuba's measurements, ascending in spp: {"spp", "ms", "rmse"} (``ms`` the
    wall time of one timed frame at that spp, None when not timed; ``rmse`` the ``set_rmse`` of
    the held-out set path traced at that spp against the references). ``measure`` adds points;
    ``read`` answers "how many samples, and how much time, does Mitsuba need to be as accurate as
    a model of this error".
    """

    def __init__(self, points: Sequence[dict] = ()):
        self.points: list[dict] = sorted((dict(p) for p in points), key=lambda p: p["spp"])

    @property
    def tried(self) -> list[dict]:
        """The measured points as {"spp", "rmse"} (without their times)."""
        return [{"spp": p["spp"], "rmse": p["rmse"]} for p in self.points]

    def measure(self, tracer: PathTracer, references: Sequence, valid: Sequence | None, spp_list: Sequence[int], *,
                target: float = -math.inf, progress: Callable | None = None) -> "EqualErrorCurve":
        """Measure the spp of ``spp_list`` above the largest measured one, ascending, until one's
        RMSE is at most ``target`` (default: every one): each rendered by ``tracer.render_at`` and
        scored against ``references`` (``set_rmse`` over ``valid``), then timed by
        ``tracer.time_at`` (when it has one). Returns the curve itself."""
        done = max((p["spp"] for p in self.points), default=0)
        for spp in sorted(int(s) for s in spp_list):
            if spp <= done:
                continue
            rmse = set_rmse(tracer.render_at(spp), references, valid)
            if progress:
                progress(f"path tracing at {spp} spp: RMSE {rmse:.5f} (target {target:.5f})")
            ms = None if tracer.time_at is None else float(tracer.time_at(spp))
            self.points.append({"spp": spp, "ms": ms, "rmse": rmse})
            if rmse <= target:
                break
        return self

    def read(self, rmse: float | None, frame_ms: float | None = None) -> dict:
        """A model's equal-error numbers: the smallest measured spp whose RMSE is at most ``rmse``
        (``equal_error_spp``), its time (``pathtrace_ms_equal_error``) and the speedup over a frame of
        ``frame_ms``; when no spp reaches it, spp None and the time of the largest spp (a lower
        bound; ``equal_error_reached`` False). All None without an error or a curve."""
        if rmse is None or not self.points:
            return {"equal_error_spp": None, "pathtrace_ms_equal_error": None, "speedup_equal_error": None,
                    "equal_error_reached": None}
        hit = next((p for p in self.points if p["rmse"] <= rmse), None)
        ms = (hit or self.points[-1])["ms"]
        return {"equal_error_spp": hit["spp"] if hit else None, "pathtrace_ms_equal_error": ms,
                "speedup_equal_error": ms / frame_ms if frame_ms and ms is not None else None,
                "equal_error_reached": hit is not None}


def equal_error_spp(render_at: Callable[[int], Sequence], references: Sequence, target_rmse: float,
                    spp_list: Sequence[int], valids: Sequence | None = None, progress: Callable | None = None) -> dict:
    """The smallest sample count whose path-traced images are at least as accurate as a method
    (``EqualErrorCurve`` without timing).

    Args:
      render_at: spp -> list of images for the test pairs (independent of the reference's seed).
      references: the high-spp reference images.
      target_rmse: the method's ``set_rmse`` against the same references.
      spp_list: increasing sample counts to try; the search stops at the first one that reaches
        the target.

    Returns {"spp": int or None (not reached within spp_list), "tried": [{"spp", "rmse"}, ...]}.
    """
    curve = EqualErrorCurve().measure(PathTracer(render_at, None), references, valids, spp_list, target=target_rmse,
                                      progress=progress)
    return {"spp": curve.read(target_rmse)["equal_error_spp"], "tried": curve.tried}


def interleaved_times(fns: dict, inputs, lightings: dict, repeats: int) -> dict:
    """Median and fastest wall time (ms) of each jitted evaluator in ``fns`` on ``inputs`` under
    each lighting in ``lightings``, one call at a time in turn (f1 l1, f1 l2, f2 l1, ...)
    ``repeats`` times after one warm-up call each: every (evaluator, lighting) sees the same spells
    of machine load, so their ratios are the programs' even on a busy machine where a burst of
    consecutive calls of one frame moves by 2x from one burst to the next.
    Returns {(fn name, lighting name): {"median_ms", "min_ms"}}."""
    times = {(f, n): [] for f in fns for n in lightings}
    for r in range(max(1, int(repeats))):
        for f, fn in fns.items():
            for n, lighting in lightings.items():
                times[(f, n)] += time_call(fn, inputs, lighting, repeats=1, warmup=0 if r else 1)["times_ms"]
    return {key: {"median_ms": float(np.median(v)), "min_ms": float(np.min(v))} for key, v in times.items()}


def side_by_side(path: str, rows: Sequence[tuple], *, exposure: float = 0.0, diff_scale: float | None = None,
                 titles: Sequence[str] = ("reference", "method", "|difference|")) -> None:
    """A PNG grid, one row per (label, reference, prediction[, valid]): reference, prediction
    (tonemapped at ``exposure``) and the absolute difference (colour-mapped; ``diff_scale`` the
    value shown as full scale, default the 99th percentile over all rows)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    diffs = [np.abs(np.asarray(r[2]) - np.asarray(r[1])).mean(axis=-1) for r in rows]
    vmax = diff_scale or float(np.percentile(np.concatenate([d.ravel() for d in diffs]), 99)) or 1.0
    fig, axes = plt.subplots(len(rows), 3, figsize=(8.4, 2.8 * len(rows)), squeeze=False)
    for i, row in enumerate(rows):
        label, ref, pred = row[:3]
        for j, image in enumerate((np.asarray(tonemap(np.asarray(ref), exposure)),
                                   np.asarray(tonemap(np.asarray(pred), exposure)),
                                   error_map(pred, ref, vmax=vmax))):
            ax = axes[i, j]
            ax.imshow(np.clip(image, 0, 1), interpolation="nearest")
            ax.set_xticks([])
            ax.set_yticks([])
            ax.set_title(f"{label}: {titles[j]}" if j == 0 else titles[j], fontsize=8)
    fig.suptitle(f"difference full scale = {vmax:.3g}", fontsize=8)
    fig.tight_layout()
    with io.atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=90, format="png")
    plt.close(fig)


def plot_series(path: str, series: dict, *, xlabel: str, ylabel: str, title: str = "", logx: bool = False,
                logy: bool = False, hlines: dict | None = None) -> None:
    """A line plot of named series {label: (xs, ys)} with optional horizontal reference lines
    {label: y}, saved as PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5, 3.4))
    for label, (xs, ys) in series.items():
        ax.plot(xs, ys, marker="o", label=label)
    for label, y in (hlines or {}).items():
        ax.axhline(y, linestyle="--", color="gray")
        ax.annotate(label, (0.02, y), xycoords=("axes fraction", "data"), fontsize=7, va="bottom")
    if logx:
        ax.set_xscale("log", base=2)
    if logy:
        ax.set_yscale("log")
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title, fontsize=9)
    ax.grid(True, alpha=0.3)
    if series:
        ax.legend(fontsize=7)
    fig.tight_layout()
    with io.atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=100, format="png")
    plt.close(fig)


def run_context(command: str, **extra) -> dict:
    """What a benchmark JSON records about its run: the command, the UTC date and the device
    (CPU, cores, JAX version and backend, GPU name when JAX has one), plus ``extra`` entries."""
    import datetime
    import platform

    import jax

    backend = jax.default_backend()
    gpu = "; " + ", ".join(d.device_kind for d in jax.devices()) if backend == "gpu" else "; no GPU"
    return {"command": command,
            "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "device": f"{platform.machine()} CPU, {os.cpu_count()} cores; jax {jax.__version__} ({backend}); "
                      f"Mitsuba llvm_ad_rgb{gpu}", **extra}


#: The checkout this package lives in: benchmark records name their paths relative to it.
REPOSITORY = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def portable_paths(value, root: str = REPOSITORY):
    """``value`` (nested dicts, lists, strings) with every absolute path that names no particular
    machine: paths inside ``root``'s parent folder (the checkout and the shared assets beside it)
    relative to ``root``, paths under the user's home as ``~/...``; other values unchanged. A
    committed result then reads the same whichever machine or folder ran it."""
    if isinstance(value, dict):
        return {k: portable_paths(v, root) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return type(value)(portable_paths(v, root) for v in value)
    if not isinstance(value, str) or not os.path.isabs(value) or "\n" in value:
        return value
    parent = os.path.dirname(os.path.abspath(root))
    if value == parent or value.startswith(parent + os.sep):
        return os.path.relpath(value, root)
    home = os.path.expanduser("~")
    if home not in ("", "/") and value.startswith(home + os.sep):
        return "~" + value[len(home):]
    return value


def write_benchmark(path: str, result: dict, command: str, **context) -> dict:
    """Write a benchmark's ``result`` to ``path`` (JSON, atomic) with ``result["context"] =
    run_context(command, **context)`` and say where it went. Absolute paths in it are recorded
    relative to the repository (``portable_paths``), so the file names no machine."""
    result["context"] = run_context(command, **context)
    result = portable_paths(result)
    io.write_json(path, result)
    print(f"wrote {path}")
    return result


def write_report(out: str, summary: dict, t_start: float, label: str) -> dict:
    """Finish an experiment report: add ``total_s`` (since ``t_start``, a ``time.perf_counter()``
    value) and ``output``, write ``out/summary.json`` and say where the report is."""
    summary["total_s"] = time.perf_counter() - t_start
    summary["output"] = out
    io.write_json(os.path.join(out, "summary.json"), summary)
    print(f"{label} report (summary.json, side_by_side.png, plots, EXRs) written to {out}")
    return summary
