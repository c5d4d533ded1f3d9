"""Lighting design through a fitted model: the lighting that meets an objective, found by
gradient descent through the model's evaluator and checked with Mitsuba.

    from jprt import design
    objective = design.load_objective("objective.json", object_names)
    result = design.design(model, objective, position, intensity)     # optax Adam
    report = design.design_run("results/rrf_cornell/<hash>", "objective.json")   # a run folder

An **objective file** (JSON) holds any of:

* ``image``: ``{"path": EXR, "quantity": "full" | "indirect", "mask": EXR or null, "weight": 1}``:
  match a target image (linear radiance, the G-buffer camera's frame) over the mask's pixels
  (any channel > 0.5; all valid pixels without one); the term is the relative squared error
  sum (L - T)^2 / sum T^2;
* ``objects``: ``[{"name": ..., "quantity": "irradiance" | "radiance", "min": a, "max": b,
  "weight": 1}]``: the mean irradiance E (W m^-2) or outgoing radiance L over a named object's
  pixels, kept within [min, max] (either bound may be absent, not both); each bound's term is
  the squared relative violation ((min - m) / min)^2 or ((m - max) / max)^2, 0 inside;
* ``power_penalty``: w >= 0, adding w x the total radiant intensity (W/sr, summed over lights and
  channels) over that of the starting lighting.

Paths are relative to the file. ``load_objective`` refuses, in one line, unknown keys, objects
the scene does not name, bounds that are negative, non-finite or crossed, and an empty objective.

The image a design sees is direct + indirect light. The **direct term** of point lights is
analytic (``point_direct``): sum_k f(w_k, v) I_k max(n . w_k, 0) / r_k^2 V_k with the G-buffer's
diffuse albedo / pi plus its GGX lobe (``ggx_brdf_cos``), and the visibility V_k traced by
Mitsuba (``point_visibility``, one shadow ray per pixel and light) every ``visibility_every``
steps and held constant between them (so the gradient does not see a shadow's edge move). The
**indirect term** is the fitted model's evaluator (RRF: Eq. 9, differentiable in the light's
position and intensity). Irradiance is E = E_direct + pi L_indirect / albedo where the albedo
is above 1e-4 (a diffuse reading; 0 elsewhere).

Point lights are parameterised so that they stay in the light region [lo, hi] (the box the
model was trained on): position = lo + (hi - lo) sigmoid(u), intensity = exp(s) per channel
(power and colour); ``optimise`` names which of ("position", "power", "colour") move.

``design_run`` then **corrects** point lights for the model's own error: one Mitsuba render of
the lights found, its difference to the model there held as an offset of the model's frames
(``model_offset``), the design run again from there, and its lights kept where a render with the
same seed says they are better.
"""

from __future__ import annotations

import difflib
import json
import math
import os
import time
from typing import Callable, NamedTuple, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from jprt.progress import bar as progress_bar

__all__ = ["ObjectiveError", "ImageTarget", "ObjectTarget", "Objective", "load_objective", "object_masks",
           "objective_terms", "LightParams", "to_params", "from_params", "point_direct", "irradiance_from",
           "point_visibility", "DesignResult", "design", "search_start", "design_frame", "rendered_terms", "model_offset",
           "gradient_check", "object_means", "bounds_report", "rendered_environment_terms",
           "Problem", "POINT_METHODS", "measurement_points", "load_problem", "design_run", "EnvironmentResult",
           "environment_transfer", "environment_frame", "design_environment", "ENVIRONMENT_METHODS", "OBJECTIVE_KEYS", "QUANTITIES",
           "report_lines", "plot_report", "run_design"]

#: Keys of an objective file, of its ``image`` entry and of each ``objects`` entry.
OBJECTIVE_KEYS = ("image", "objects", "power_penalty")
IMAGE_KEYS = ("path", "quantity", "mask", "weight")
OBJECT_KEYS = ("name", "quantity", "min", "max", "weight")
#: What an object bound is on: mean irradiance (W m^-2) or mean outgoing radiance (W m^-2 sr^-1).
QUANTITIES = ("irradiance", "radiance")
#: Diffuse albedo below which a pixel's indirect irradiance is not read from its radiance.
ALBEDO_FLOOR = 1e-4


class ObjectiveError(ValueError):
    """An objective file that cannot be used; the message is one line naming the file and key."""


class ImageTarget(NamedTuple):
    """``target`` (H, W, 3) linear radiance, ``mask`` (H, W) bool, ``quantity`` "full" or
    "indirect", ``weight``."""

    target: np.ndarray
    mask: np.ndarray | None
    quantity: str
    weight: float


class ObjectTarget(NamedTuple):
    """Bounds on one named object's mean ``quantity`` (``QUANTITIES``); a missing bound is None."""

    name: str
    quantity: str
    min: float | None
    max: float | None
    weight: float


class Objective(NamedTuple):
    """A validated objective (``load_objective``)."""

    image: ImageTarget | None
    objects: tuple
    power_penalty: float
    source: str


def _number(where: str, value, *, positive: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ObjectiveError(f"{where} must be a finite number, got {value!r}")
    if value < 0 or (positive and value == 0):
        raise ObjectiveError(f"{where} must be {'> 0' if positive else '>= 0'}, got {value!r}")
    return float(value)


def _unknown(where: str, entry: dict, known: Sequence[str]) -> None:
    if not isinstance(entry, dict):
        raise ObjectiveError(f"{where} must be a JSON object, got {type(entry).__name__}")
    extra = sorted(set(entry) - set(known))
    if extra:
        raise ObjectiveError(f"{where}: unknown key {extra[0]!r} (known: {', '.join(known)})")


def _read_image(path: str, where: str, *, mask: bool = False) -> np.ndarray:
    """An EXR (RGB; a mask: the largest of its channels) or a .npy array; ObjectiveError if unreadable."""
    from jprt import io

    if not os.path.isfile(path):
        raise ObjectiveError(f"{where}: no such file {path}")
    try:
        if path.endswith(".npy"):
            return np.asarray(np.load(path), np.float32)
        if mask:
            channels = io.read_exr(path, None)
            return np.max(np.stack([np.asarray(v, np.float32) for v in channels.values()], axis=-1), axis=-1)
        return np.asarray(io.read_exr(path, "RGB"), np.float32)
    except Exception as e:  # noqa: BLE001 (any reader failure is the file's fault: say which file)
        raise ObjectiveError(f"{where}: cannot read {path} ({type(e).__name__}: {e})".replace("\n", " ")) from None


def load_objective(source, object_names: Sequence[str], *, shape: tuple | None = None) -> Objective:
    """The objective of a JSON file (``source`` a path) or of a dict (paths then relative to the
    working directory), checked against the scene's ``object_names`` and, for a target image,
    the frame ``shape`` (H, W) when given. Raises ``ObjectiveError`` (one line) on any defect.

    Numerics: not differentiable (reads and validates a file).
    """
    if isinstance(source, (str, os.PathLike)):
        name = os.fspath(source)
        if not os.path.isfile(name):
            raise ObjectiveError(f"objective file not found: {name}")
        try:
            with open(name) as f:
                spec = json.load(f)
        except json.JSONDecodeError as e:
            raise ObjectiveError(f"{name}: not JSON ({e})") from None
        base = os.path.dirname(os.path.abspath(name))
    else:
        name, spec, base = "objective", source, os.getcwd()
    _unknown(name, spec, OBJECTIVE_KEYS)
    image = None
    if spec.get("image") is not None:
        entry = spec["image"]
        where = f"{name}: image"
        _unknown(where, entry, IMAGE_KEYS)
        if "path" not in entry:
            raise ObjectiveError(f"{where} needs a 'path' (an EXR of the target radiance)")
        quantity = entry.get("quantity", "full")
        if quantity not in ("full", "indirect"):
            raise ObjectiveError(f"{where}.quantity must be 'full' or 'indirect', got {quantity!r}")
        target = _read_image(os.path.join(base, entry["path"]), f"{where}.path")
        if target.ndim != 3 or target.shape[-1] != 3 or not np.all(np.isfinite(target)):
            raise ObjectiveError(f"{where}.path must hold a finite (H, W, 3) image, got shape {target.shape}")
        if shape is not None and tuple(target.shape[:2]) != tuple(shape):
            raise ObjectiveError(f"{where}.path is {target.shape[0]} x {target.shape[1]}, the frame is "
                                 f"{shape[0]} x {shape[1]}")
        mask = None
        if entry.get("mask") is not None:
            m = _read_image(os.path.join(base, entry["mask"]), f"{where}.mask", mask=True)
            m = m.max(axis=-1) if m.ndim == 3 else m
            if m.shape != target.shape[:2]:
                raise ObjectiveError(f"{where}.mask is {m.shape}, the target {target.shape[:2]}")
            mask = m > 0.5
            if not mask.any():
                raise ObjectiveError(f"{where}.mask selects no pixel")
        image = ImageTarget(target, mask, quantity, _number(f"{where}.weight", entry.get("weight", 1.0)))
    objects = []
    entries = spec.get("objects", [])
    if not isinstance(entries, list):
        raise ObjectiveError(f"{name}: objects must be a list, got {type(entries).__name__}")
    known = list(object_names)
    for i, entry in enumerate(entries):
        where = f"{name}: objects[{i}]"
        _unknown(where, entry, OBJECT_KEYS)
        obj = entry.get("name")
        if obj not in known:
            close = difflib.get_close_matches(str(obj), known, n=3, cutoff=0.6)
            raise ObjectiveError(f"{where}.name {obj!r} is not an object of the scene"
                                 + (f" (did you mean {', '.join(close[:3])}?)" if close else
                                    f" (it has {len(known)}: {', '.join(known[:8])}{', ...' if len(known) > 8 else ''})"))
        quantity = entry.get("quantity", "irradiance")
        if quantity not in QUANTITIES:
            raise ObjectiveError(f"{where}.quantity must be one of {', '.join(QUANTITIES)}, got {quantity!r}")
        lo = None if entry.get("min") is None else _number(f"{where}.min", entry["min"])
        hi = None if entry.get("max") is None else _number(f"{where}.max", entry["max"], positive=True)
        if lo is None and hi is None:
            raise ObjectiveError(f"{where} ({obj}) needs a 'min' or a 'max'")
        if lo is not None and hi is not None and lo > hi:
            raise ObjectiveError(f"{where} ({obj}): min {lo} is above max {hi}")
        if lo == 0.0:
            lo = None  # a lower bound of 0 holds for any light
        twin = next((j for j, t in enumerate(objects) if (t.name, t.quantity) == (obj, quantity)), None)
        if twin is not None:
            raise ObjectiveError(f"{where} repeats objects[{twin}] ({obj}, {quantity}): give its min and max in "
                                 "one entry")
        objects.append(ObjectTarget(obj, quantity, lo, hi, _number(f"{where}.weight", entry.get("weight", 1.0))))
    penalty = _number(f"{name}: power_penalty", spec.get("power_penalty", 0.0))
    if image is None and not objects:
        raise ObjectiveError(f"{name}: nothing to optimise (give an image, objects or both)")
    return Objective(image, tuple(objects), penalty, name)


def object_masks(objective: Objective, object_id, object_names: Sequence[str], valid=None) -> np.ndarray:
    """(O, H, W) float32: each objective object's pixels (its id in ``object_id``, valid), in the
    objective's order; raises ``ObjectiveError`` when an object has no pixel in the frame.

    Numerics: not differentiable (integer object ids to masks).
    """
    oid = np.asarray(object_id)
    ok = np.ones(oid.shape, bool) if valid is None else np.asarray(valid, bool)
    names = list(object_names)
    out = []
    for t in objective.objects:
        m = (oid == names.index(t.name)) & ok
        if not m.any():
            raise ObjectiveError(f"{objective.source}: object {t.name!r} is not seen in the design's frame")
        out.append(m)
    return np.stack(out).astype(np.float32) if out else np.zeros((0,) + oid.shape, np.float32)


def objective_terms(objective: Objective, masks, full, indirect, irradiance, intensity, reference_power: float):
    """{term name: scalar} of ``objective`` for one frame: ``full`` / ``indirect`` radiance and
    ``irradiance`` (H, W, 3), ``intensity`` (K, 3) of the lights; ``masks`` from ``object_masks``;
    the image term over its mask's pixels (every pixel without one: ``load_problem`` gives it the
    frame's valid pixels).
    Differentiable (JAX); the objective is the sum of the values.

    Numerics:
        case: design_objective (an 8 x 8 target in [0, 1e3] with a mask, two objects' bounds in
          [1e-2, 1e3], frames in [0, 1e3], two lights' intensities in [0, 1e3])
        fd: off (the bounds' hinges max(., 0) are kinks the drawn frames can sit on)
        float32: value rtol 1e-4 atol 1e-6; grad rtol 1e-4 atol 1e-6
    """
    terms = {}
    if objective.image is not None:
        im = objective.image
        pred = full if im.quantity == "full" else indirect
        w = jnp.ones(pred.shape[:2]) if im.mask is None else jnp.asarray(im.mask, jnp.float32)
        t = jnp.asarray(im.target)
        denom = jnp.maximum(jnp.sum(w[..., None] * t * t), 1e-30)
        terms["image"] = im.weight * jnp.sum(w[..., None] * jnp.square(pred - t)) / denom
    for target, mean in zip(objective.objects, object_means(objective, masks, full, irradiance).values()):
        v = 0.0
        if target.min is not None:
            v = v + jnp.square(jnp.maximum(target.min - mean, 0.0) / target.min)
        if target.max is not None:
            v = v + jnp.square(jnp.maximum(mean - target.max, 0.0) / target.max)
        terms[f"{target.name}.{target.quantity}"] = target.weight * v
    if objective.power_penalty > 0:
        terms["power"] = objective.power_penalty * jnp.sum(intensity) / max(float(reference_power), 1e-30)
    return terms


def object_means(objective: Objective, masks, full, irradiance) -> dict:
    """{"name.quantity": mean} of each object target of ``objective``: its pixels' (``masks``)
    mean ``irradiance`` or ``full`` radiance over pixels and RGB, the number its bounds are on
    (JAX scalars; ``objective_terms`` takes its gradient through them).

    Numerics: not differentiable (masked means of a frame; ``objective_terms``' float32 case differentiates through them).
    """
    out = {}
    for i, target in enumerate(objective.objects):
        field = irradiance if target.quantity == "irradiance" else full
        m = jnp.asarray(masks[i])
        out[f"{target.name}.{target.quantity}"] = jnp.sum(m[..., None] * field) / (3.0 * jnp.sum(m))
    return out


def bounds_report(objective: Objective, means: dict) -> dict:
    """Each object target's bounds beside a frame's ``means`` (``object_means``, as floats):
    {"name.quantity": {"mean", "min", "max", "met"}}; ``met`` when the mean is within both bounds.

    Numerics: not differentiable (a report).
    """
    out = {}
    for target in objective.objects:
        key = f"{target.name}.{target.quantity}"
        mean = float(means[key])
        out[key] = {"mean": mean, "min": target.min, "max": target.max,
                    "met": bool((target.min is None or mean >= target.min) and (target.max is None or mean <= target.max))}
    return out


# --------------------------------------------------------------------------------------------
# Point lights: parameters, direct light, visibility


class LightParams(NamedTuple):
    """Unconstrained design parameters of K point lights: ``u`` (K, 3) (position = lo + (hi - lo)
    sigmoid(u)), ``log_intensity`` (K, 3) (intensity = exp per channel)."""

    u: jax.Array
    log_intensity: jax.Array


#: How close to the light region's faces a starting position is put (fraction of the region's
#: side): at a face itself sigmoid's inverse is infinite.
EDGE = 1e-4


def to_params(position, intensity, lo, hi) -> LightParams:
    """``LightParams`` of lights at ``position`` (K, 3) (clipped into the region, ``EDGE`` inside
    its faces) with ``intensity`` (K, 3) > 0 (clipped at 1e-12 of the largest).

    Numerics: not differentiable (float64 NumPy set-up of the starting parameters).
    """
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    if np.any(hi <= lo):
        raise ValueError(f"the light region must have hi > lo on every axis, got lo {lo} and hi {hi}")
    f = np.clip((np.asarray(position, np.float64) - lo) / (hi - lo), EDGE, 1.0 - EDGE)
    i = np.asarray(intensity, np.float64)
    i = np.maximum(i, 1e-12 * max(float(i.max(initial=0.0)), 1e-30))
    return LightParams(jnp.asarray(np.log(f) - np.log1p(-f), jnp.float32), jnp.asarray(np.log(i), jnp.float32))


def from_params(params: LightParams, lo, hi):
    """(position (K, 3), intensity (K, 3)) of ``params``: inside [lo, hi], intensity > 0.

    Numerics:
        case: design_lights (u in [-20, 20], log_intensity in [-20, 20], a region [-1, 2] x [0.5, 3] x [-2, 1])
        float32: value rtol 1e-6 atol 1e-6; grad rtol 1e-5 atol 1e-6
    """
    dtype = jnp.asarray(params.u).dtype
    lo, hi = jnp.asarray(lo, dtype).reshape(1, 3), jnp.asarray(hi, dtype).reshape(1, 3)
    return lo + (hi - lo) * jax.nn.sigmoid(params.u), jnp.exp(params.log_intensity)


def _ggx_brdf_cos(normal, view, wi, roughness, specular):
    from jprt.methods.sg_lightfield.model import ggx_brdf_cos

    return ggx_brdf_cos(normal, view, wi, roughness, specular)


def point_direct(gbuffer, position, intensity, visibility, *, glossy: bool = True):
    """Direct light of K point lights at every G-buffer pixel: (radiance (H, W, 3), irradiance
    (H, W, 3)). radiance = sum_k (albedo / pi n.w_k + f_ggx(w_k, v) n.w_k) I_k / r_k^2 V_k and
    irradiance = sum_k I_k max(n . w_k, 0) / r_k^2 V_k, w_k the unit direction to light k,
    ``visibility`` (H, W, K) in [0, 1] (``point_visibility``; held constant: no gradient flows
    through it). ``glossy``: add the G-buffer's GGX lobe (``ggx_brdf_cos``; Mitsuba's rough
    conductor reading). Invalid pixels are 0. Differentiable in ``position`` and ``intensity``.

    Numerics:
        case: design_direct (8 pixels at points in [-1, 1]^3 with unit normals, views within 89.9
          degrees of them, albedo and specular in [0, 1], roughness in [0.1, 1]; two lights at
          [2, 3]^3 with intensities in [0, 1e3]; visibility 1 or 0)
        fd: off (max(n . w, 0) has a kink where a light grazes a pixel's plane)
        float32: value rtol 1e-4 atol 1e-3; grad rtol 1e-3 atol 1e-2
        (GGX peaks to ~30 at roughness 0.1, times intensities to 1e3 over r^2 >= 1: values to ~3e4)
    """
    valid = jnp.asarray(gbuffer.valid, bool)[..., None]
    p = jnp.asarray(gbuffer.position)[..., None, :]  # (H, W, 1, 3)
    # invalid pixels get a unit normal and view and a rough surface: their zero attributes make the
    # BRDF 0 / 0 there, masked out of the value but not out of a reverse-mode gradient
    up = jnp.asarray([0.0, 0.0, 1.0], p.dtype)
    n = jnp.where(valid, jnp.asarray(gbuffer.normal), up)
    lead = (1,) * (p.ndim - 2)
    position = jnp.asarray(position).reshape(lead + (-1, 3))  # (1, 1, K, 3)
    intensity = jnp.asarray(intensity).reshape(-1, 3)  # (K, 3)
    d = position - p  # (H, W, K, 3)
    r2 = jnp.maximum(jnp.sum(d * d, axis=-1), 1e-12)
    w = d * jax.lax.rsqrt(r2)[..., None]
    cos = jnp.maximum(jnp.sum(n[..., None, :] * w, axis=-1), 0.0)  # (H, W, K)
    vis = jax.lax.stop_gradient(jnp.asarray(visibility))
    # the sums over the lights are contractions (einsum), not a broadcast product summed over K:
    # XLA:CPU (jax 0.10.2) compiled that form wrongly for K = 2 when the intensities came from a
    # mean over RGB broadcast back (``_light_map``'s power), about half the light or NaN
    irradiance = jnp.einsum("...k,kc->...c", cos * vis / r2, intensity)
    radiance = jnp.asarray(gbuffer.diffuse_albedo) / jnp.pi * irradiance
    if glossy:
        spec = jnp.asarray(gbuffer.specular_albedo)
        view = jnp.where(valid, jnp.asarray(gbuffer.view), up)
        rough = jnp.where(valid[..., 0], jnp.asarray(gbuffer.roughness), 1.0)
        f = _ggx_brdf_cos(n[..., None, :], view[..., None, :], w, rough[..., None], spec[..., None, :])
        radiance = radiance + jnp.einsum("...kc,...k,kc->...c", f, vis / r2, intensity)
    return jnp.where(valid, radiance, 0.0), jnp.where(valid, irradiance, 0.0)


def irradiance_from(indirect, diffuse_albedo):
    """Indirect irradiance pi L / albedo where the albedo is above ``ALBEDO_FLOOR`` (else 0).

    Numerics:
        indirect: (32, 3) in [0, 1e3]
        diffuse_albedo: (32, 3) in [1e-2, 1]
        float32: value rtol 1e-6 atol 1e-30; grad rtol 1e-6 atol 1e-30
    """
    a = jnp.asarray(diffuse_albedo)
    ok = a > ALBEDO_FLOOR
    return jnp.where(ok, jnp.pi * indirect / jnp.where(ok, a, 1.0), 0.0)


def point_visibility(handle, gbuffer, position) -> np.ndarray:
    """(H, W, K) 1 where light k is visible from the pixel's point (a shadow ray from the point,
    offset along its normal, reaches the light without a hit), else 0; invalid pixels 0.

    Numerics: not differentiable (Mitsuba's shadow rays: a 0/1 visibility).
    """
    from jprt.render.lightmap import ray_offset, unoccluded

    valid = np.asarray(gbuffer.valid, bool)
    shape = valid.shape
    pos = np.asarray(gbuffer.position, np.float64).reshape(-1, 3)
    nrm = np.asarray(gbuffer.normal, np.float64).reshape(-1, 3)
    idx = np.flatnonzero(valid.reshape(-1))
    lights = np.asarray(position, np.float64).reshape(-1, 3)
    eps = ray_offset(handle)
    out = np.zeros((pos.shape[0], lights.shape[0]), np.float32)
    if idx.size == 0:
        return out.reshape(shape + (lights.shape[0],))
    out[idx] = unoccluded(handle, pos[idx] + eps * nrm[idx], lights, slack=2.0 * eps).T
    return out.reshape(shape + (lights.shape[0],))


# --------------------------------------------------------------------------------------------
# The design loop


class DesignResult(NamedTuple):
    """What ``design`` found: ``position``, ``intensity`` (K, 3) float64, ``history`` (steps taken,)
    objective per step (with the visibility of that step), ``terms`` {name: value} at the end,
    ``seconds`` the loop's wall time, ``visibility_updates`` how often visibility was traced,
    ``means`` the object targets' means at the end (``object_means``, floats), ``step_cost``
    XLA's count of one step ({"flops", "bytes"}, ``jprt.eval.xla_cost``)."""

    position: np.ndarray
    intensity: np.ndarray
    history: np.ndarray
    terms: dict
    seconds: float
    visibility_updates: int
    means: dict | None = None
    step_cost: dict | None = None


def search_start(frame_fn: Callable, objective: Objective, masks, lo, hi, lights: int, *,
                 visibility_fn: Callable | None = None, candidates: int = 64, rounds: int = 2,
                 level: float = 1.0, reference_power: float | None = None, seed: int = 0,
                 mode: str = "joint", refine: int | None = None,
                 progress: bool | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Starting lights for ``design`` from a search over candidate positions: (position (K, 3),
    intensity (K, 3)) float64, white.

    Why: ``design`` holds visibility constant between its traces, so its gradient sees the
    lights' shadows as painted on the surfaces and never moves them; from a start whose shadows
    fall elsewhere than the target's, it settles where the lit parts match and the shadows do not
    (CHANGELOG.md, 2026-12-07, has the measurement). The search looks at the shadows themselves:
    every candidate is traced.

    ``candidates`` positions of a scrambled Sobol set in [``lo``, ``hi``] (seeded by ``seed``),
    each traced once (``visibility_fn``, all candidates in one call) and rendered once as a white
    light of unit intensity through ``frame_fn``. The frame is taken to be linear in the lights'
    intensities and a sum over the lights (point lights in a PRT model are: the direct term and
    the transport are both linear in the emitted power), so a light's frame at intensity s is s
    times its unit frame and the lights' frames add.

    ``mode`` "joint" (default): every candidate gets a non-negative white intensity at once,
    minimising the objective (``_candidate_weights``: the objective is convex in them, since every
    term is a convex function of frames linear in them); neighbouring candidates that share one
    light's weight are merged into K lights (``_merge_candidates``: weighted k-means, each light at
    its group's weighted centroid with the group's summed intensity, its frame their weighted
    sum); lights no weight is left for are placed greedily. ``mode`` "greedy": light k goes to the
    candidate and white intensity (``level`` x 2^-6 ... 2^6, 49 steps) that minimise the objective
    beside the lights placed before it; it explains two nearby lights with one bright candidate
    first. Then, either way, ``rounds`` passes move each light in turn to its best candidate and
    intensity given the others, where that lowers the objective (cyclic matching pursuit).
    "joint" was chosen on `staircase` (a 3.5x lower verified objective with three lights); on the
    Cornell box, held out, it finds the same one light and three lights of the same model
    objective as "greedy" (CHANGELOG.md, 2026-12-07 (from 03:36)). Last, ``refine`` passes of a
    traced local search (``_refine_lights``) move the lights off the candidates' grid, and split a
    light that explains two nearby ones: 64 candidates lie about a quarter of the light region
    apart per axis, too coarse for two lights a few percent of the scene apart, and ``design``'s
    held-visibility gradient does not reach them from there. ``refine`` None (default): 8 passes
    for two or more lights, none for one. Chosen on `staircase` (three lights, two of them 3.8 %
    of the diagonal apart: 0.26 / 0.41 / 0.60 % and powers 0.92-1.04 after the design, against
    1.0 / 1.3 / 11.5 % and 0.12-1.43 without it; one light 1.08 % against 0.61 %, since the
    design goes further from the grid's start) and validated on the Cornell box (three lights
    within 0.5 % and 7 % as without it; one light 0.09 % against 0.06 %), CHANGELOG.md,
    2026-12-07 (from 06:10). ``reference_power``: the power the
    objective's power penalty is relative to (default ``lights`` x 3 x ``level``, ``design``'s
    sum of the starting intensities).

    Numerics: not differentiable (a discrete search; each candidate's frame evaluated once).
    """
    from scipy.stats import qmc

    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    k_lights, m = int(lights), int(candidates)
    if k_lights < 1 or m < 1:
        raise ValueError(f"search_start needs lights >= 1 and candidates >= 1, got {lights} and {candidates}")
    if mode not in ("joint", "greedy"):
        raise ValueError(f"search_start's mode is 'joint' or 'greedy', got {mode!r}")
    pos = lo + (hi - lo) * qmc.Sobol(3, scramble=True, seed=int(seed)).random(m)
    reference = float(3 * k_lights * level) if reference_power is None else float(reference_power)
    unit = np.ones((1, 3), np.float32)
    frame = jax.jit(frame_fn)

    def render(pos):
        """The unit frames of candidates at ``pos`` (N, 3): three (N, H, W, 3) float32 NumPy
        arrays (full, indirect, irradiance). The plumbing around the compiled frame is NumPy: an
        op-by-op JAX slice or stack compiles a program of its own per shape, seconds in all."""
        vis = (None if visibility_fn is None else
               jax.tree_util.tree_map(lambda a: np.asarray(a, np.float32), visibility_fn(pos)))  # last axis: the candidates
        out = []
        for c in progress_bar(range(len(pos)), progress=progress, desc="candidate lights", unit="light"):
            v = ({"pixels": np.ones((1, 1, 1), np.float32)} if vis is None else
                 jax.tree_util.tree_map(lambda a, c=c: np.ascontiguousarray(a[..., c:c + 1]), vis))
            out.append(frame(np.asarray(pos[c:c + 1], np.float32), unit, v))
        return [np.stack([np.asarray(u[i]) for u in out]) for i in range(3)]

    units = render(pos)
    scales = np.asarray(float(level) * 2.0 ** np.linspace(-6.0, 6.0, 49), np.float32)

    @jax.jit
    def best(units, others, other_power):
        """The objective's least value over candidates x scales beside ``others`` (the frames of the
        lights not being placed; ``other_power`` their summed intensity, (1, 3): the power penalty
        reads only the sum) and its (candidate, scale). The frames are arguments, not constants of
        the program, and every call has the same shapes: one compilation, small."""
        def at(c, s):
            frames = [o + s * u[c] for o, u in zip(others, units)]
            inten = jnp.concatenate([other_power, jnp.full((1, 3), s)], axis=0)
            return sum(objective_terms(objective, masks, *frames, inten, reference).values())

        levels = jnp.asarray(scales)
        values = jax.lax.map(lambda c: jax.vmap(lambda s: at(c, s))(levels),
                             jnp.arange(units[0].shape[0]))  # (M, scales)
        flat = jnp.argmin(values)
        return values.reshape(-1)[flat], flat // levels.shape[0], levels[flat % levels.shape[0]]

    @jax.jit
    def value(frames, power):
        return sum(objective_terms(objective, masks, *frames, power, reference).values())

    found = []  # the lights so far: (position (3,), white intensity, their three frames)

    def placed(skip: int | None):
        """The frames and summed intensity ((1, 3): the power penalty reads only the sum) of the
        lights found, but light ``skip``."""
        rest = [f for j, f in enumerate(found) if j != skip]
        frames = [sum((f[2][i] for f in rest), np.zeros_like(u[0])) for i, u in enumerate(units)]
        return frames, np.full((1, 3), sum(f[1] for f in rest), np.float32)

    def candidate(c, s):
        return pos[int(c)], float(s), [float(s) * u[int(c)] for u in units]

    solver = _weights_solver(objective, masks, reference)
    if mode == "joint":
        weights = _candidate_weights(units, objective, masks, reference, scales / np.float32(m), solver=solver)
        for g in _merge_candidates((pos - lo) / np.where(hi > lo, hi - lo, 1.0), weights, k_lights):
            w = np.asarray(weights[g], np.float32)
            found.append((np.sum(weights[g, None] * pos[g], axis=0) / np.sum(weights[g]), float(np.sum(weights[g])),
                          [np.tensordot(w, u[g], axes=1) for u in units]))
    while len(found) < k_lights:  # greedy, beside the lights found
        _, c, s = best(units, *placed(None))
        found.append(candidate(c, s))
    for _ in range(int(rounds)):  # each light again, given the others, where that is better
        for k in range(k_lights):
            v, c, s = best(units, *placed(k))
            if float(v) <= float(value(*placed(None))):
                found[k] = candidate(c, s)
    refine = (8 if k_lights > 1 else 0) if refine is None else int(refine)
    if refine > 0:
        found = _refine_lights(render, objective, masks, found, lo, hi, reference, refine=refine,
                               radius=0.5 * (hi - lo) * m ** (-1.0 / 3.0), seed=int(seed), solver=solver)
    return (np.stack([f[0] for f in found]),
            np.repeat(np.asarray([f[1] for f in found], np.float64).reshape(-1, 1), 3, axis=1))


def _refine_lights(render: Callable, objective: Objective, masks, found: list, lo, hi, reference: float, *,
                   refine: int, radius, seed: int, local: int = 16, solver: Callable | None = None) -> list:
    """Lights ``found`` ((position (3,), white intensity, frames) each) moved by a traced local
    search: around every light ``local`` scrambled Sobol points in a box of half-width ``radius``
    (per axis, (3,)); the intensities of the lights and their local points solved jointly
    (``_candidate_weights``, non-negative, started at the lights' own); each light goes to its
    group's weighted centroid with the group's summed intensity. The moved lights are traced and
    rendered once more, their intensities solved again at their new positions, and kept where
    that lowers the objective. Where it does not, the weakest light tries to split a brighter one
    (the brightest first): the two lights' intensity is spread over the brighter light's local
    points (the other lights held), the points grouped in two (``_merge_candidates``) and the two
    lights put at the groups' centroids, kept where that lowers the objective. Where neither
    helps, the radius halves. ``refine`` such passes; the lights' intensities are the objective's
    best at their positions throughout.

    Numerics: not differentiable (a search; every point traced).
    """
    from scipy.stats import qmc

    solver = _weights_solver(objective, masks, reference) if solver is None else solver
    k = len(found)
    pos = np.stack([f[0] for f in found])
    inten = np.asarray([f[1] for f in found], np.float64)

    def value_of(units, w):
        return float(solver[2](np.asarray(w, np.float32), units, [np.zeros(np.shape(u)[1:], np.float32) for u in units],
                               np.float32(0.0)))

    units = render(pos)
    inten = _candidate_weights(units, objective, masks, reference, None, init=inten, solver=solver)
    current = value_of(units, inten)
    for r in range(int(refine)):
        qmc_points = qmc.Sobol(3, scramble=True, seed=int(seed) + 1 + r).random(local) * 2.0 - 1.0
        cand = np.concatenate([pos[:, None], np.clip(pos[:, None] + qmc_points[None] * radius, lo, hi)],
                              axis=1).reshape(-1, 3)  # (K * (local + 1), 3), light-major
        start = np.zeros((k, local + 1))
        start[:, 0] = inten
        cand_units = render(cand)
        w = _candidate_weights(cand_units, objective, masks, reference, None, init=start.reshape(-1),
                               solver=solver)
        w = w.reshape(k, local + 1)
        total = w.sum(axis=1)
        if np.any(total <= 0):
            radius = radius * 0.5
            continue
        new_pos = np.einsum("kc,kcd->kd", w, cand.reshape(k, local + 1, 3)) / total[:, None]
        new_units = render(new_pos)
        total = _candidate_weights(new_units, objective, masks, reference, None, init=total, solver=solver)
        v = value_of(new_units, total)
        if v < current:
            pos, inten, units, current = new_pos, total, new_units, v
            continue
        moved = False
        weak = int(np.argmin(inten))
        for j in np.argsort(-inten):  # the weakest light splits a brighter one, the brightest first
            if k < 2 or j == weak:
                continue
            block = slice(j * (local + 1), (j + 1) * (local + 1))  # light j and its points, rendered above
            cloud = cand[block]
            start = np.zeros(local + 1)
            start[0] = inten[j] + inten[weak]
            rest = [i for i in range(k) if i not in (j, weak)]
            fixed = [np.tensordot(np.asarray(inten[rest], np.float32), u[np.asarray(rest, int)], axes=1)
                     for u in units]
            w = _candidate_weights([u[block] for u in cand_units], objective, masks, reference, None, init=start,
                                   fixed=fixed, fixed_power=float(np.sum(inten[rest])), solver=solver)
            groups = _merge_candidates((cloud - lo) / np.where(hi > lo, hi - lo, 1.0), w, 2)
            if len(groups) < 2:
                continue
            trial_pos, trial_int = pos.copy(), inten.copy()
            for i, g in zip((j, weak), groups):
                trial_pos[i] = np.sum(w[g, None] * cloud[g], axis=0) / np.sum(w[g])
                trial_int[i] = np.sum(w[g])
            trial_units = render(trial_pos)
            trial_int = _candidate_weights(trial_units, objective, masks, reference, None, init=trial_int,
                                           solver=solver)
            v = value_of(trial_units, trial_int)
            if v < current:
                pos, inten, units, current, moved = trial_pos, trial_int, trial_units, v, True
                break
        if not moved:
            radius = radius * 0.5
    return [(pos[j], float(inten[j]), [float(inten[j]) * u[j] for u in units]) for j in range(k)]


def _candidate_weights(units, objective: Objective, masks, reference: float, levels, steps: int = 200,
                       init: np.ndarray | None = None, fixed=None, fixed_power: float = 0.0,
                       solver: Callable | None = None) -> np.ndarray:
    """Non-negative white intensities (M,) float64 of M candidate lights, each with unit frames
    ``units`` (three (M, H, W, 3) arrays: full, indirect, irradiance), that minimise ``objective``
    of their summed frames. The objective is convex in them (the image term is quadratic and the
    bounds' hinges squared in frames linear in the intensities, the power penalty linear), so
    projected descent finds its minimum: Adam on the intensities in units of the best common
    intensity among ``levels`` (every candidate equally bright), clipped at 0 after every step,
    the rate decaying on a cosine from 1 to 0.01 over ``steps`` steps. The result is a start for
    ``design``, not an exact solve: 200 steps against 600 were chosen on `staircase` (one light
    0.61 % of the diagonal away after the design against 1.02 %, three lights alike) and
    validated on the Cornell box (three lights 0.13-0.47 % and powers within 3 % against
    0.50-0.67 % and 0.87; one light alike), in a third less time (CHANGELOG.md, 2026-12-07
    (from 03:36)). ``init`` (M,): start there instead (Adam's unit then the largest of it;
    ``levels`` unused). ``fixed``: three frames of lights held, added to the candidates' sum,
    ``fixed_power`` their summed intensity (the power penalty reads the total). ``solver``: a
    ``_weights_solver`` of the same objective, masks, reference and steps to reuse (its programs
    are compiled once per candidate count, not once per call).

    Numerics: not differentiable (an optimisation).
    """
    best_common, descend, _ = _weights_solver(objective, masks, reference, steps) if solver is None else solver
    m = units[0].shape[0]
    fixed = [np.zeros(np.shape(u)[1:], np.float32) for u in units] if fixed is None else list(fixed)
    power = np.float32(fixed_power)
    if init is None:
        common = best_common(units, np.asarray(levels, np.float32), fixed, power)
        v0 = np.ones((m,), np.float32)
    else:
        v0 = np.asarray(init, np.float32)
        common = np.float32(max(float(np.max(v0)), 1e-30))
        v0 = v0 / common
    return np.asarray(descend(units, common, v0, fixed, power), np.float64)


def _weights_solver(objective: Objective, masks, reference: float,
                    steps: int = 200) -> tuple[Callable, Callable, Callable]:
    """The compiled programs of ``_candidate_weights`` for one objective: ``best_common(units,
    levels, fixed, fixed_power)``, the level among ``levels`` best for every candidate at once,
    and ``descend(units, common, v0, fixed, fixed_power)``, ``steps`` projected Adam steps from
    ``v0`` in units of ``common``; and ``value(w, units, fixed, fixed_power)``, the objective of
    the candidates at intensities ``w`` beside the held lights. The frames are arguments, not
    constants of the programs, so each compiles once per candidate count.

    Numerics: not differentiable (builds an optimisation).
    """
    import optax

    def value(w, units, fixed, fixed_power):
        frames = [jnp.tensordot(w, u, axes=1) + f for u, f in zip(units, fixed)]
        power = jnp.full((1, 3), jnp.sum(w) + fixed_power)
        return sum(objective_terms(objective, masks, *frames, power, reference).values())

    @jax.jit
    def best_common(units, levels, fixed, fixed_power):
        m = units[0].shape[0]
        return levels[jnp.argmin(jax.vmap(lambda s: value(jnp.full((m,), s), units, fixed, fixed_power))(levels))]

    @jax.jit
    def descend(units, common, v0, fixed, fixed_power):
        opt = optax.adam(optax.cosine_decay_schedule(1.0, steps, alpha=0.01))

        def body(carry, _):
            v, state = carry
            g = jax.grad(lambda v: value(common * v, units, fixed, fixed_power))(v)
            upd, state = opt.update(g, state, v)
            return (jnp.maximum(optax.apply_updates(v, upd), 0.0), state), None

        (v, _), _ = jax.lax.scan(body, (v0, opt.init(v0)), None, length=int(steps))
        return common * v

    return best_common, descend, jax.jit(value)


def _merge_candidates(x: np.ndarray, weights: np.ndarray, k: int, iterations: int = 20) -> list[np.ndarray]:
    """At most ``k`` groups (index arrays) of the candidates at ``x`` (M, 3) with positive
    ``weights``: weighted k-means (Lloyd), its centres started at the heaviest candidate and then,
    each, at the candidate of largest weight x squared distance to the centres so far. One light's
    weight spread over neighbouring candidates becomes one group; fewer than ``k`` candidates with
    weight give fewer groups.

    Numerics: not differentiable (a clustering).
    """
    idx = np.flatnonzero(weights > 0)
    if idx.size == 0:
        return []
    pts, w = x[idx], weights[idx]
    k = min(int(k), idx.size)
    centres = [pts[np.argmax(w)]]
    while len(centres) < k:
        d2 = np.min(np.sum((pts[:, None] - np.asarray(centres)[None]) ** 2, axis=-1), axis=1)
        centres.append(pts[np.argmax(w * d2)])
    centres = np.asarray(centres)
    for _ in range(int(iterations)):
        label = np.argmin(np.sum((pts[:, None] - centres[None]) ** 2, axis=-1), axis=1)
        new = np.asarray([np.sum(w[label == j, None] * pts[label == j], axis=0) / np.sum(w[label == j])
                          if np.any(label == j) else centres[j] for j in range(k)])
        if np.allclose(new, centres):
            break
        centres = new
    label = np.argmin(np.sum((pts[:, None] - centres[None]) ** 2, axis=-1), axis=1)
    return [idx[label == j] for j in range(k) if np.any(label == j)]


def _light_map(p0: LightParams, optimise: Sequence[str], lo, hi) -> Callable:
    """``lights(params) -> (position, intensity)`` (K, 3) each, JAX) of design parameters
    starting at ``p0``: what ``optimise`` leaves out ("position", "power": the overall intensity
    per light, "colour": its RGB ratios) keeps its starting value (``_held``, NumPy constants of
    a traced program: closed-over device arrays gave the jitted step of an earlier, forward-mode
    loop garbage values here, run to run)."""
    lights, held = _light_map_held(optimise, lo, hi), _held(p0)
    return lambda params: lights(params, held)


def _held(p0: LightParams) -> dict:
    """The starting values of ``p0`` a design keeps where ``optimise`` leaves them out: {"u" (K, 3),
    "level" (K, 1): the mean log intensity over RGB, "tint" (K, 3): the rest}, float32 NumPy."""
    s0 = np.asarray(p0.log_intensity, np.float32)
    level0 = s0.mean(axis=-1, keepdims=True)
    return {"u": np.asarray(p0.u, np.float32), "level": level0, "tint": s0 - level0}


def _light_map_held(optimise: Sequence[str], lo, hi) -> Callable:
    """``lights(params, held) -> (position, intensity)``: ``_light_map`` with the held starting
    values (``_held``) an argument, so one compiled program serves every start."""
    bad = sorted(set(optimise) - {"position", "power", "colour"})
    if bad or not optimise:
        raise ValueError(f"optimise names 'position', 'power' and 'colour', got {list(optimise)}")
    free_u = "position" in optimise
    free_power, free_colour = "power" in optimise, "colour" in optimise

    def lights(params, held):
        # what does not move keeps its starting value (not the current parameter under
        # stop_gradient: Adam's per-element steps would let a held mean drift)
        u = params.u if free_u else held["u"]
        s = params.log_intensity
        # the mean over RGB as a product with a constant, not a reduction broadcast back: the
        # latter met an XLA:CPU miscompilation for two lights (``point_direct``'s note)
        mean = s @ jnp.full((3, 1), 1.0 / 3.0, s.dtype)
        level = mean if free_power else held["level"]
        tint = s - mean if free_colour else held["tint"]
        position, _ = from_params(LightParams(u, s), lo, hi)
        return position, jnp.exp(level) * jnp.exp(tint)

    return lights


class _DesignProgram(NamedTuple):
    """``design``'s compiled pieces for one problem, the same for every start: ``step(params,
    state, aux, scale)`` (``_adam``'s step; ``aux`` the traced visibility, {"held": ``_held``}
    and {"offset": the frames' held correction, ``_design_aux``}), ``init(params)`` (Adam's
    state), ``lights(params, held)`` (jitted ``_light_map_held``), ``key`` (what it was built
    for: ``_design_key``), ``shape`` (the frame's (H, W)) and ``warm``, a thread compiling them
    (``_warm_design``) or None."""

    step: Callable
    init: Callable
    lights: Callable
    key: tuple
    shape: tuple = ()
    warm: object = None


def _design_program(frame_fn: Callable, objective: Objective, masks, lo, hi, *, optimise: Sequence[str],
                    reference: float, steps: int, learning_rate: float) -> _DesignProgram:
    """``design``'s programs (``_DesignProgram``) for a problem, before its start is known."""
    lights = _light_map_held(optimise, lo, hi)

    def model(params, aux):
        pos, inten = lights(params, aux["held"])
        # the held correction (``model_offset``; zeros without one) added to the model's frames
        return tuple(f + o for f, o in zip(frame_fn(pos, inten, aux), aux["offset"])), inten

    def loss(frames, inten):
        terms = objective_terms(objective, masks, *frames, inten, reference)
        return sum(terms.values()), (terms, object_means(objective, masks, frames[0], frames[2]))

    step, init = _adam_program(model, loss, steps=steps, learning_rate=learning_rate)
    return _DesignProgram(step, init, jax.jit(lights),
                          _design_key(frame_fn, objective, masks, lo, hi, optimise, reference, steps, learning_rate),
                          tuple(int(n) for n in np.shape(masks)[1:]))


def _design_key(frame_fn, objective, masks, lo, hi, optimise, reference, steps, learning_rate) -> tuple:
    """What a ``_DesignProgram`` is built for, to compare with a ``design`` call that passes it."""
    return (id(frame_fn), id(objective), id(masks), tuple(np.asarray(lo, np.float64).tolist()),
            tuple(np.asarray(hi, np.float64).tolist()), tuple(sorted(optimise)), float(reference), int(steps),
            float(learning_rate))


def _warm_design(program: _DesignProgram, visibility_fn: Callable | None, lights: int, lo, hi) -> _DesignProgram:
    """``program`` with a thread that compiles its step and light map (one call each on lights at
    the region's centre, run once) while the caller goes on, e.g. searching for the start: XLA's
    backend compilation runs without Python's lock (tracing and lowering hold it), so most of
    the compilation overlaps the search. The visibility the call needs is traced here, in the
    caller's thread (Mitsuba is called from one thread only). The caller joins the thread
    (``design`` does) before it stops its clock."""
    import threading

    k = int(lights)
    centre = np.repeat((0.5 * (np.asarray(lo, np.float64) + np.asarray(hi, np.float64)))[None], k, axis=0)
    params = to_params(centre, np.ones((k, 3)), lo, hi)
    aux = _design_aux(visibility_fn, centre, _held(params), k, _zero_offset(program.shape))

    def run():
        try:
            jax.block_until_ready(program.step(params, program.init(params), aux, jnp.float32(1.0)))
            jax.block_until_ready(program.lights(params, aux["held"]))
        except Exception:  # noqa: BLE001 -- the design's own call compiles again and reports the error
            pass

    thread = threading.Thread(target=run, name="jprt-design-compile", daemon=True)
    thread.start()
    return program._replace(warm=thread)


def _design_aux(visibility_fn: Callable | None, position, held: dict, k: int, offset: tuple) -> dict:
    """``_adam``'s ``aux`` for ``design``: the visibility traced for lights at ``position`` (every
    light visible everywhere without ``visibility_fn``), the held starting values and the frames'
    held correction ``offset`` (three (H, W, 3) arrays)."""
    if visibility_fn is None:
        vis = {"pixels": jnp.ones((1, 1, int(k)), jnp.float32)}
    else:
        vis = jax.tree_util.tree_map(jnp.asarray, visibility_fn(np.asarray(position, np.float64)))
    return {**vis, "held": held, "offset": offset}


def _zero_offset(shape: tuple) -> tuple:
    """No correction: three (H, W, 3) float32 zeros (full, indirect, irradiance)."""
    return tuple(np.zeros(tuple(shape) + (3,), np.float32) for _ in range(3))


def design(frame_fn: Callable, objective: Objective, masks, position, intensity, lo, hi, *,
           visibility_fn: Callable | None = None, steps: int = 200, learning_rate: float = 0.05,
           visibility_every: int = 10, optimise: Sequence[str] = ("position", "power"),
           keep_best: bool = True, tol: float = 1e-3, reference_power: float | None = None,
           offset: tuple | None = None, program: _DesignProgram | None = None,
           progress: bool | None = None) -> DesignResult:
    """Optimise K point lights with optax Adam (the rate decaying to 1 % of ``learning_rate`` on a
    cosine) so that ``objective`` is smallest.

    ``frame_fn(position, intensity, visibility) -> (full, indirect, irradiance)`` (each (H, W, 3),
    differentiable JAX; ``design_frame`` builds it from a G-buffer and a model); ``visibility_fn
    (position) -> {"pixels": (H, W, K), ...}`` (the pixels' visibility and whatever else the model
    needs, e.g. its measurement points') traced every ``visibility_every`` steps (None: every
    light visible everywhere). ``lo``,
    ``hi``: the light region. ``optimise``: which of "position", "power" (the overall intensity
    per light) and "colour" (its RGB ratios) move; the rest keep their starting values. The
    gradient is reverse mode (``_adam``): ``frame_fn`` must go through ``jax.grad``. ``keep_best``:
    at every trace, return to the best traced point and halve the steps where the objective with
    the fresh visibility is worse (``_adam``'s ``keep_best``); the result is the best traced point.
    ``tol``: with ``keep_best``, stop before ``steps`` once three traces in a row have not lowered
    the best traced objective by more than ``tol`` of it (0: run every step). Both defaults were
    chosen on `staircase` and validated on the Cornell box (CHANGELOG.md, 2026-12-07 (from 03:36)).
    ``reference_power``: the power the objective's power penalty is relative to (default the sum of
    the starting intensities; a start from ``search_start`` passes the search's, so both score the
    same objective). ``program``: the problem's compiled pieces (``_design_program`` with the same
    objective, masks, region, ``optimise``, reference, ``steps`` and ``learning_rate``), e.g.
    compiled while the start was searched (``_warm_design``); default built here. ``offset``:
    three (H, W, 3) arrays added to ``frame_fn``'s full, indirect and irradiance frames, held
    constant (``model_offset``: the model's error measured on a render; ``design_run``'s
    correction); None: none.

    Numerics: not differentiable (an optimisation loop over ``objective_terms``, ``point_direct`` and the model).
    """
    p0 = to_params(position, intensity, lo, hi)
    reference = float(np.sum(intensity)) if reference_power is None else float(reference_power)
    if program is None:
        program = _design_program(frame_fn, objective, masks, lo, hi, optimise=optimise, reference=reference,
                                  steps=steps, learning_rate=learning_rate)
    else:
        key = _design_key(frame_fn, objective, masks, lo, hi, optimise, reference, steps, learning_rate)
        if program.key != key:
            raise ValueError("design's program was built for another problem, objective, region, optimise, "
                             "reference power, steps or learning rate than this call's")
        if program.warm is not None:
            program.warm.join()  # its compilation done, the step below is a cache hit
    held, k = _held(p0), int(np.shape(position)[0])
    if offset is None:
        offset = _zero_offset(program.shape)
    else:
        offset = tuple(np.asarray(o, np.float32) for o in offset)
        if len(offset) != 3 or any(o.shape != tuple(program.shape) + (3,) for o in offset):
            raise ValueError(f"design's offset is three {tuple(program.shape) + (3,)} arrays (full, indirect, "
                             f"irradiance), got {[np.shape(o) for o in offset]}")
    offset = tuple(jnp.asarray(o) for o in offset)  # on the device once, not copied every step

    def refresh(params):
        return _design_aux(visibility_fn, program.lights(params, held)[0], held, k, offset)

    params, history, (terms, means), seconds, updates, cost = _adam(
        (program.step, program.init), p0, steps=steps, refresh=refresh, every=visibility_every,
        progress=progress, keep_best=keep_best, tol=tol)
    pos, inten = program.lights(params, held)
    return DesignResult(np.asarray(pos, np.float64), np.asarray(inten, np.float64), history, terms, seconds,
                        updates if visibility_fn is not None else 0, means, cost)


class PeerResult(NamedTuple):
    """What ``mitsuba_design`` found: the lights after the last step, the objective of each step
    (Mitsuba's noisy estimate), the seconds the steps took and, every ``every`` steps, a
    checkpoint {"step", "seconds", "position", "intensity"} (the lights after that step, the
    clock then) for verifying the way there."""

    position: np.ndarray
    intensity: np.ndarray
    history: np.ndarray
    seconds: float
    checkpoints: list


def mitsuba_design(peer, position, intensity, lo, hi, *, steps: int = 200, learning_rate: float = 0.05,
                   optimise: Sequence[str] = ("position", "power"), every: int = 25, seed: int = 0,
                   progress: bool | None = None) -> PeerResult:
    """The peer of ``design``: the same parameters (``to_params``, ``_light_map``), the same optax
    Adam and rate schedule from the same start, the gradient from Mitsuba's differentiable
    renderers instead of a fitted model (``peer``: a ``jprt.render.inverse.SphereLights``, image
    objective only), a new seed every step.

    Numerics: not differentiable (an optimisation loop over Mitsuba renders).
    """
    import optax

    p0 = to_params(position, intensity, lo, hi)
    light_map = _light_map(p0, optimise, lo, hi)
    lights = jax.jit(light_map)  # compiled, as jprt's own loop is: the peer's clock is Mitsuba's
    opt = optax.adam(optax.cosine_decay_schedule(float(learning_rate), max(int(steps), 1), alpha=0.01))
    state, params = opt.init(p0), p0
    lights_vjp = jax.jit(lambda p, g: jax.vjp(light_map, p)[1](g)[0])

    @jax.jit
    def update(grads, state, params):
        updates, state = opt.update(grads, state, params)
        return optax.apply_updates(params, updates), state

    history, checkpoints = [], []
    every = max(int(every), 1)
    t0 = time.perf_counter()
    bar = progress_bar(range(int(steps)), progress=progress, desc="Mitsuba design", unit="step")
    for i in bar:
        pos, inten = (np.asarray(a, np.float64) for a in lights(params))
        value, d_pos, d_inten = peer.loss_and_grad(pos, inten, seed=int(seed) * 100003 + i)
        grads = lights_vjp(params, (jnp.asarray(d_pos, jnp.float32), jnp.asarray(d_inten, jnp.float32)))
        params, state = update(grads, state, params)
        history.append(value)
        if hasattr(bar, "set_postfix"):
            bar.set_postfix(objective=f"{value:.3g}")
        if (i + 1) % every == 0 or i + 1 == int(steps):
            pos, inten = lights(params)
            checkpoints.append({"step": i + 1, "seconds": time.perf_counter() - t0,
                                "position": np.asarray(pos, np.float64).tolist(),
                                "intensity": np.asarray(inten, np.float64).tolist()})
    pos, inten = lights(params)
    return PeerResult(np.asarray(pos, np.float64), np.asarray(inten, np.float64), np.asarray(history),
                      time.perf_counter() - t0, checkpoints)


def _adam(program: tuple[Callable, Callable], params, *, steps: int, refresh: Callable, every: int,
          progress: bool | None, keep_best: bool = False, tol: float = 0.0, patience: int = 3):
    """Adam for ``steps`` steps through ``program``, the (step, init) pair of ``_adam_program``
    (the objective ``objective(*model(params, aux)) -> (value, (terms, means))``, the rate decaying
    on a cosine to 1 %); ``aux = refresh(params)`` first, every ``every`` steps and at the end.
    Each step is one compiled program, the objective's value and its gradient in the parameters
    (``jax.value_and_grad``) and the update. Returns (params, history, (terms, means) at the end
    as floats, seconds, refreshes, XLA's count of one step: ``jprt.eval.xla_cost``, compiled
    again after the loop, outside ``seconds``).

    ``keep_best``: at every refresh the objective is evaluated with the fresh ``aux``; where it is
    worse than at the best refresh so far, the parameters, Adam's state and ``aux`` return there
    and the steps from then on are halved; the result is the best refreshed point. The refreshed
    objective is the true one (for point lights: visibility traced where the lights are), while
    the steps between refreshes follow a gradient that holds ``aux``; this is a trust region on
    the true objective around that gradient's steps. With ``keep_best`` and ``tol`` > 0 the loop
    also stops early, once ``patience`` refreshes in a row have not lowered the best refreshed
    objective by more than ``tol`` of it (converged: the returned history is shorter)."""
    step, init = program
    state = init(params)
    aux, refreshes, history = None, 0, []
    best, scale, stale, end = None, 1.0, 0, None
    every = max(int(every), 1)
    t0 = time.perf_counter()
    bar = progress_bar(range(int(steps)), progress=progress, desc="design", unit="step")
    for i in bar:
        if i % every == 0:
            aux = refresh(params)
            refreshes += 1
            # the step's value is the objective with the fresh ``aux`` at ``params``: keep-best
            # reads it there instead of evaluating the objective in a program of its own
            nxt = step(params, state, aux, jnp.float32(scale))
            end = nxt[3]
            if keep_best:
                now = float(nxt[2])
                stale = 0 if best is None or now < best[0] * (1.0 - tol) else stale + 1
                if best is None or now <= best[0]:
                    best = (now, params, state, aux, end)
                else:  # the held gradient's steps made the true objective worse: back, shorter steps
                    _, params, state, aux, end = best
                    scale *= 0.5
                    nxt = None
                if tol > 0 and stale >= int(patience):
                    break  # converged; ``aux`` is fresh for ``params``, ``end`` their terms
                if nxt is None:
                    nxt = step(params, state, aux, jnp.float32(scale))
        else:
            nxt = step(params, state, aux, jnp.float32(scale))
        params, state, value, _ = nxt
        history.append(float(value))
        if hasattr(bar, "set_postfix"):
            bar.set_postfix(objective=f"{history[-1]:.3g}")
    else:
        aux = refresh(params)
        refreshes += 1
        _, _, last, end = step(params, state, aux, jnp.float32(scale))
        if keep_best and best is not None and float(last) > best[0]:
            _, params, _, aux, end = best
    terms, means = ({k: float(v) for k, v in d.items()} for d in end)
    seconds = time.perf_counter() - t0
    from jprt.eval import xla_cost

    return params, np.asarray(history), (terms, means), seconds, refreshes, xla_cost(step, params, state, aux,
                                                                                      jnp.float32(1.0))


def _adam_program(model: Callable, objective: Callable, *, steps: int, learning_rate: float):
    """``_adam``'s (step, init): the jitted step (the objective's value and gradient, Adam's
    update scaled by ``scale``; it returns the value and (terms, means) at the parameters before
    the update) and Adam's ``init``."""
    import optax

    # cosine decay to 1 % of the rate: the last steps settle instead of circling the optimum
    opt = optax.adam(optax.cosine_decay_schedule(float(learning_rate), max(int(steps), 1), alpha=0.01))

    @jax.jit
    def step(params, state, aux, scale):
        (value, out), grads = jax.value_and_grad(lambda p: objective(*model(p, aux)), has_aux=True)(params)
        updates, state = opt.update(grads, state, params)
        params = optax.apply_updates(params, jax.tree_util.tree_map(lambda u: scale * u, updates))
        return params, state, value, out  # value and out: at the parameters before the update

    return step, opt.init


def design_frame(gbuffer, indirect_fn: Callable, *, glossy: bool = True) -> Callable:
    """``frame_fn`` for ``design``: direct (``point_direct`` with ``visibility["pixels"]``) +
    ``indirect_fn(position, intensity, visibility)`` (the model's (H, W, 3) indirect radiance) at
    the pixels of ``gbuffer``, and their irradiance.

    Numerics: not differentiable (builds the frame function: ``point_direct`` plus ``irradiance_from``).
    """
    gb = type(gbuffer)(*(jnp.asarray(a) for a in gbuffer))

    def frame(position, intensity, visibility):
        direct, e_direct = point_direct(gb, position, intensity, visibility["pixels"], glossy=glossy)
        ind = indirect_fn(position, intensity, visibility)
        return direct + ind, ind, e_direct + irradiance_from(ind, gb.diffuse_albedo)

    return frame


def rendered_terms(handle, camera, gbuffer, objective: Objective, masks, position, intensity, *, spp: int,
                   seed: int = 0, reference_power: float = 1.0, means: bool = False):
    """``objective_terms`` on Mitsuba's render of point lights (``position``, ``intensity`` (K, 3))
    at ``camera`` (``_terms_on_render``); the direct irradiance is the lights' (exact for point
    lights, with traced visibility). With ``means``: (terms, the objects' ``object_means`` there).

    Numerics: not differentiable (Mitsuba renders).
    """
    from jprt.inputs import PointLights

    def e_direct():
        vis = point_visibility(handle, gbuffer, position)
        return point_direct(gbuffer, position, intensity, vis, glossy=False)[1]

    return _terms_on_render(handle, camera, gbuffer, objective, masks,
                            PointLights.create(np.asarray(position, np.float32), np.asarray(intensity, np.float32)),
                            e_direct, np.asarray(intensity), spp=spp, seed=seed, reference_power=reference_power,
                            means=means)


def _render_frames(handle, camera, gbuffer, lighting, *, spp: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Mitsuba's full and indirect radiance ((H, W, 3) float32 NumPy each) of ``lighting`` at
    ``camera`` (``spp``, ``seed``), along the pixel-centre rays the G-buffer traces
    (``jprt.render.images.centre_rays``); invalid G-buffer pixels 0."""
    from jprt.render import images

    handle.set_lighting(lighting)
    r = images.centre_rays(handle, camera, spp=int(spp), seed=int(seed))
    valid = np.asarray(gbuffer.valid, bool)[..., None]
    full = np.where(valid, np.asarray(r.direct, np.float32) + np.asarray(r.indirect, np.float32), 0.0)
    return full, np.where(valid, np.asarray(r.indirect, np.float32), 0.0)


def model_offset(handle, camera, gbuffer, frame_fn: Callable, position, intensity, *,
                 visibility_fn: Callable | None = None, spp: int = 256, seed: int = 0) -> tuple:
    """The model's error at point lights ``position``, ``intensity`` (K, 3), measured on one
    Mitsuba render: (full, indirect, irradiance) of the render (``spp``, ``seed``; irradiance the
    lights' direct irradiance, ``point_direct`` with traced visibility, plus ``irradiance_from``
    its indirect radiance, as ``rendered_terms`` reads it) minus ``frame_fn``'s at the same lights
    (visibility from ``visibility_fn``; the frame evaluated one light at a time and summed, as a
    point-light frame is), three (H, W, 3) float32 NumPy arrays, 0 at invalid pixels.

    ``design_run`` adds it, held constant, to the model's frames (``design``'s ``offset``) and
    designs again from the lights it found: the corrected model equals the render at those lights,
    and its gradient is the model's. Where the model's error changes slowly with the lighting
    (the second design moves the lights by a small fraction of the scene), the corrected design's
    optimum is the render's to first order, instead of the model's own, which its bias shifts
    (a defect correction). The render's noise enters the offset; ``spp`` sets how much.

    Numerics: not differentiable (a Mitsuba render).
    """
    from jprt.inputs import PointLights

    position = np.asarray(position, np.float64)
    intensity = np.asarray(intensity, np.float32)
    full, ind = _render_frames(handle, camera, gbuffer, PointLights.create(np.asarray(position, np.float32),
                                                                            intensity), spp=spp, seed=seed)
    k = position.shape[0]
    vis = jax.tree_util.tree_map(lambda a: np.asarray(a, np.float32),
                                 {"pixels": np.ones((1, 1, k), np.float32)} if visibility_fn is None
                                 else visibility_fn(position))  # last axis: the lights
    # the model's frames one light at a time, summed (the frame is a sum over point lights, as
    # ``search_start`` takes it): the one-light program the search compiled serves any K
    frame = jax.jit(frame_fn)
    model = [np.zeros(full.shape, np.float32) for _ in range(3)]
    for j in range(k):
        one = frame(np.asarray(position[j:j + 1], np.float32), intensity[j:j + 1],
                    jax.tree_util.tree_map(lambda a, j=j: np.ascontiguousarray(a[..., j:j + 1]), vis))
        model = [m + np.asarray(a, np.float32) for m, a in zip(model, one)]
    e_direct = point_direct(gbuffer, position, intensity, vis["pixels"], glossy=False)[1]
    irr = np.asarray(e_direct) + np.asarray(irradiance_from(ind, gbuffer.diffuse_albedo))
    valid = np.asarray(gbuffer.valid, bool)[..., None]
    return tuple(np.where(valid, r - m, 0.0).astype(np.float32) for r, m in zip((full, ind, irr), model))


def _terms_on_render(handle, camera, gbuffer, objective: Objective, masks, lighting, e_direct: Callable, power, *,
                     spp: int, seed: int, reference_power: float, means: bool = False):
    """``objective_terms`` on Mitsuba's render of ``lighting`` at ``camera`` (``spp``, ``seed``;
    full and indirect along the pixel-centre rays the G-buffer traces,
    ``jprt.render.images.centre_rays``; invalid G-buffer pixels 0). Irradiance there is
    ``e_direct()`` (the design's own direct irradiance, asked for only when an object term needs
    it) plus the render's indirect radiance read as irradiance (``irradiance_from``); ``power``:
    the lighting's intensity (K, 3) or scale (1, 3) for the power penalty. With ``means``:
    (terms, {"name.quantity": the object's mean there} (``object_means``))."""
    full, ind = _render_frames(handle, camera, gbuffer, lighting, spp=spp, seed=seed)
    irr = 0.0 * full
    if objective.objects:
        irr = np.asarray(e_direct()) + np.asarray(irradiance_from(ind, gbuffer.diffuse_albedo))
    terms = {k: float(v) for k, v in objective_terms(objective, masks, full, ind, irr, power, reference_power).items()}
    if not means:
        return terms
    return terms, {k: float(v) for k, v in object_means(objective, masks, full, irr).items()}


def gradient_check(handle, camera, gbuffer, frame_fn: Callable, objective: Objective, masks, position, intensity,
                   *, visibility_fn: Callable | None = None, spp: int = 1024, step: float = 0.01,
                   log_step: float = 0.05, seeds: Sequence[int] = (11, 12), size: float | None = None) -> dict:
    """The model's gradient of ``objective`` against central finite differences of Mitsuba renders
    (``rendered_terms`` at ``spp``, the same seed on both sides of each difference), at point
    lights ``position``, ``intensity`` (K, 3), the model's visibility from ``visibility_fn``
    (``Problem.visibility``; None: the pixels' only). Parameters: every light's position (world units;
    step ``step`` x ``size``, the scene's diagonal by default) and its log intensity scale (step
    ``log_step``). The finite differences are taken once per seed of ``seeds``: their mean is
    compared with the model, and their spread is the Mitsuba noise level.

    Returns {"model", "mitsuba" (per seed), "cosine" (model against the seeds' mean), "cosine_seeds"
    (seed against seed), "noise" (|g_1 - g_2| / |g_1 + g_2|), "parameters", "spp", "step"}.

    Numerics: not differentiable (compares a gradient with Mitsuba's finite differences).
    """
    position = np.asarray(position, np.float64).reshape(-1, 3)
    intensity = np.asarray(intensity, np.float64).reshape(-1, 3)
    k = position.shape[0]
    if size is None:
        box = handle.scene.bbox()
        size = float(np.linalg.norm(np.asarray(box.max) - np.asarray(box.min)))
    vis = jax.tree_util.tree_map(jnp.asarray, (visibility_fn or (lambda p: {
        "pixels": point_visibility(handle, gbuffer, p)}))(position))
    reference = float(np.sum(intensity))

    def model(theta):
        pos = theta[:3 * k].reshape(k, 3)
        inten = jnp.asarray(intensity, theta.dtype) * jnp.exp(theta[3 * k:])[:, None]
        full, ind, irr = frame_fn(pos, inten, vis)
        return sum(objective_terms(objective, masks, full, ind, irr, inten, reference).values())

    theta0 = np.concatenate([position.reshape(-1), np.zeros(k)])
    g_model = np.asarray(jax.jacfwd(model)(jnp.asarray(theta0, jnp.float32)), np.float64)
    steps = np.concatenate([np.full(3 * k, float(step) * size), np.full(k, float(log_step))])
    per_seed = []
    for seed in seeds:
        g = np.zeros_like(theta0)
        for i in range(theta0.size):
            value = []
            for sign in (1.0, -1.0):
                t = theta0.copy()
                t[i] += sign * steps[i]
                pos, inten = t[:3 * k].reshape(k, 3), intensity * np.exp(t[3 * k:])[:, None]
                value.append(sum(rendered_terms(handle, camera, gbuffer, objective, masks, pos, inten, spp=spp,
                                                seed=seed, reference_power=reference).values()))
            g[i] = (value[0] - value[1]) / (2.0 * steps[i])
        per_seed.append(g)
    mean = np.mean(per_seed, axis=0)

    def cos(a, b):
        return float(np.dot(a, b) / max(np.linalg.norm(a) * np.linalg.norm(b), 1e-300))

    noise = (float(np.linalg.norm(per_seed[0] - per_seed[1]) / max(np.linalg.norm(per_seed[0] + per_seed[1]), 1e-300))
             if len(per_seed) > 1 else None)
    return {"model": g_model.tolist(), "mitsuba": [g.tolist() for g in per_seed], "cosine": cos(g_model, mean),
            "cosine_seeds": cos(per_seed[0], per_seed[1]) if len(per_seed) > 1 else None, "noise": noise,
            "parameters": [f"light{j}.{c}" for j in range(k) for c in "xyz"] + [f"light{j}.log_scale" for j in range(k)],
            "spp": int(spp), "step": {"position": float(step) * size, "log_scale": float(log_step)}}


# --------------------------------------------------------------------------------------------
# Environment lighting: rotation about +Y and scale


class EnvironmentResult(NamedTuple):
    """What ``design_environment`` found: ``angle`` (radians about +Y), ``scale`` (3,) per channel,
    ``history``, ``terms`` at the end, ``seconds``, ``means`` the object targets' means at the
    end (``object_means``, floats), ``step_cost`` XLA's count of one step (as ``DesignResult``)."""

    angle: float
    scale: np.ndarray
    history: np.ndarray
    terms: dict
    seconds: float
    means: dict | None = None
    step_cost: dict | None = None


def environment_transfer(handle, gbuffer, face: int, *, chunk: int = 64) -> np.ndarray:
    """(H, W, 6 face^2) direct-light transfer of an environment cube map of face ``face`` to the
    G-buffer's pixels: T[p, j] = V(p, w_j) max(n_p . w_j, 0) Omega_j, w_j the texel centres'
    directions and Omega_j their solid angles, V traced by Mitsuba (a ray from the point, offset
    along its normal, that escapes the scene). The direct irradiance under a map L is T L; the map's
    detail below a texel (a sun's disk) is spread over its texel. Invalid pixels are 0.

    Numerics: not differentiable (Mitsuba's visibility rays; the transfer is a constant of the design).
    """
    from jprt.render.lightmap import intersect, ray_offset
    from jprt.sphere import cubemap

    valid = np.asarray(gbuffer.valid, bool)
    shape = valid.shape
    dirs = np.asarray(cubemap.texel_directions(int(face)), np.float64).reshape(-1, 3)
    omega = np.asarray(cubemap.texel_solid_angles(int(face)), np.float64).reshape(-1)
    pos = np.asarray(gbuffer.position, np.float64).reshape(-1, 3)
    nrm = np.asarray(gbuffer.normal, np.float64).reshape(-1, 3)
    idx = np.flatnonzero(valid.reshape(-1))
    out = np.zeros((pos.shape[0], dirs.shape[0]), np.float32)
    origin = pos[idx] + ray_offset(handle) * nrm[idx]
    for j0 in range(0, dirs.shape[0], int(chunk)):
        d = dirs[j0:j0 + int(chunk)]  # (J, 3)
        cos = np.maximum(nrm[idx] @ d.T, 0.0)  # (P, J)
        o = np.repeat(origin, d.shape[0], axis=0)
        dd = np.tile(d, (origin.shape[0], 1))
        hit = np.asarray(intersect(handle, o, dd).is_valid(), bool).reshape(origin.shape[0], d.shape[0])
        out[idx, j0:j0 + d.shape[0]] = (cos * ~hit * omega[None, j0:j0 + d.shape[0]]).astype(np.float32)
    return out.reshape(shape + (dirs.shape[0],))


def environment_frame(gbuffer, indirect_fn: Callable, transfer, *, predicts: str = "indirect") -> Callable:
    """``frame(cube, angle, scale) -> (full, indirect, irradiance)`` for an environment cube map
    (6, n, n, 3) that is the map turned by ``angle`` (radians) about +Y and scaled by ``scale``
    (3,) already (``design_environment`` passes both beside it, for a model whose lighting turns
    without the cube: SG environment visibility's U): direct = albedo / pi x T L (``environment_transfer``:
    diffuse only), the model's ``indirect_fn(cube, angle, scale)``, irradiance = T L + pi
    L_indirect / albedo. ``predicts`` "indirect" (neural-wavelet PRT, SH PRT): the model's is
    the indirect light; "direct" (SG environment visibility): the model's is the environment's
    glossy direct light, added to the diffuse direct light, and the frame has no indirect light.

    Numerics: not differentiable (builds the frame function: a linear map plus ``irradiance_from``).
    """
    if predicts not in ("indirect", "direct"):
        raise ValueError(f"environment_frame's predicts is 'indirect' or 'direct', got {predicts!r}")
    t = jnp.asarray(transfer)
    albedo = jnp.asarray(gbuffer.diffuse_albedo)
    valid = jnp.asarray(gbuffer.valid, bool)[..., None]

    def frame(cube, angle, scale):
        e_direct = jnp.einsum("hwj,jc->hwc", t, jnp.reshape(cube, (-1, 3)))
        out = indirect_fn(cube, angle, jnp.asarray(scale, jnp.float32).reshape(3))
        direct = jnp.where(valid, albedo / jnp.pi * e_direct, 0.0)
        if predicts == "direct":
            return direct + out, jnp.zeros_like(out), e_direct
        return direct + out, out, e_direct + irradiance_from(out, albedo)

    return frame


def design_environment(frame_fn: Callable, objective: Objective, masks, cube, *, angle: float = 0.0,
                       scale=(1.0, 1.0, 1.0), steps: int = 200, learning_rate: float = 0.05,
                       optimise: Sequence[str] = ("rotation", "scale"), progress: bool | None = None
                       ) -> EnvironmentResult:
    """Turn the environment ``cube`` (6, n, n, 3) about +Y and scale it (per channel, > 0) so that
    ``objective`` is smallest: Adam (``_adam``) on (angle, log scale), the lighting
    exp(log scale) x ``jprt.sphere.cubemap.rotate_cubemap_y(cube, angle)`` handed to
    ``frame_fn(cube, angle, scale) -> (full, indirect, irradiance)`` (``environment_frame``), the
    angle and scale beside it. ``optimise``
    names which of "rotation", "scale" (the overall level) and "colour" (the RGB ratios) move.

    Numerics: not differentiable (an optimisation loop over ``objective_terms``, ``rotate_cubemap_y`` and the model).
    """
    from jprt.sphere import cubemap

    bad = sorted(set(optimise) - {"rotation", "scale", "colour"})
    if bad or not optimise:
        raise ValueError(f"optimise names 'rotation', 'scale' and 'colour', got {list(optimise)}")
    base = jnp.asarray(cube, jnp.float32)
    s0 = np.maximum(np.asarray(scale, np.float64).reshape(3), 1e-12)
    p0 = (jnp.asarray(float(angle), jnp.float32), jnp.asarray(np.log(s0), jnp.float32))
    reference = float(np.sum(s0))

    s0 = np.asarray(p0[1])
    a0, level0, tint0 = float(angle), float(s0.mean()), s0 - s0.mean()  # NumPy constants (as in ``design``)

    def lighting(params):
        a, s = params  # what does not move keeps its starting value (as in ``design``)
        a = a if "rotation" in optimise else a0
        mean = jnp.mean(s)
        level = mean if "scale" in optimise else level0
        tint = s - mean if "colour" in optimise else tint0
        scale_rgb = jnp.exp(level + tint)
        return cubemap.rotate_cubemap_y(base, a) * scale_rgb.reshape(1, 1, 1, 3), scale_rgb

    def model(params, aux):
        turned, scale_rgb = lighting(params)
        a = params[0] if "rotation" in optimise else a0
        return frame_fn(turned, a, scale_rgb), scale_rgb.reshape(1, 3)

    def loss(frames, scale_rgb):
        terms = objective_terms(objective, masks, *frames, scale_rgb, reference)
        return sum(terms.values()), (terms, object_means(objective, masks, frames[0], frames[2]))

    program = _adam_program(model, loss, steps=steps, learning_rate=learning_rate)
    params, history, (terms, means), seconds, _, cost = _adam(program, p0, steps=steps, refresh=lambda p: None,
                                                              every=max(int(steps), 1), progress=progress)
    return EnvironmentResult(float(params[0]), np.asarray(lighting(params)[1], np.float64), history, terms, seconds,
                             means, cost)


def _region(session) -> tuple[np.ndarray, np.ndarray]:
    meta = getattr(session.dataset, "meta", None)
    if isinstance(meta, dict) and "light_lo" in meta:
        return np.asarray(meta["light_lo"], np.float64), np.asarray(meta["light_hi"], np.float64)
    from jprt.render.sampling import scene_regions

    r = scene_regions(session.method_config["scene"])
    return np.asarray(r["light_lo"], np.float64), np.asarray(r["light_hi"], np.float64)


class Problem(NamedTuple):
    """A run folder's design problem at its camera: the ``jprt.view.Session``, the ``camera`` and its
    G-buffer ``gbuffer``, the validated ``objective`` and its object ``masks``, the light region
    ``lo``, ``hi``, ``frame`` (``design_frame`` of the run's evaluator) and ``visibility``
    (position -> the visibility dict ``frame`` reads); for an environment-lit model (``kind``
    "environment") ``frame`` takes a cube map (``environment_frame``), ``environments`` are the
    run's maps {name: (6, n, n, 3)} and ``transfer`` their direct transfer, and there is no light
    region or visibility."""

    session: object
    camera: object
    gbuffer: object
    objective: Objective
    masks: np.ndarray
    lo: np.ndarray | None
    hi: np.ndarray | None
    frame: Callable
    visibility: Callable | None
    kind: str = "point"
    environments: dict | None = None
    transfer: np.ndarray | None = None


#: Environment-lit methods ``jprt design`` turns and scales the map of: neural-wavelet PRT takes the
#: cube map itself, SH PRT its SH projection (``jprt.sphere.sh.project_cubemap``, differentiable),
#: SG environment visibility its pre-convolved map U (Eq. 6), made once and turned
#: (``rotate_preconvolved_y``); it predicts the map's glossy direct light, not indirect light.
ENVIRONMENT_METHODS = ("wavelet_prt", "sh_prt", "sg_environment")

#: Methods ``jprt design`` optimises point lights for: RRF takes the lights themselves (Eq. 9);
#: data-driven PRT and MRT take the direct radiance at their measurement points or texels, which
#: the design computes with ``point_direct`` there (diffuse, seen along the normal).
POINT_METHODS = ("rrf", "datadriven", "mrt")


def measurement_points(session):
    """The G-buffer (S, ...) of the points where a method measures its lights' direct radiance
    (data-driven PRT: its fine measurement points; MRT: every texel of its layout, valid where
    its face exists), seen along their normals (view = normal), with their diffuse albedo and no
    specular lobe; None for a method that takes the lights themselves.

    Numerics: not differentiable (reads a dataset).
    """
    from jprt.inputs import GBuffer

    name, ds = session.method.name, session.dataset
    if name == "datadriven":
        fine = np.asarray(session.params["fine_index"])
        pos = np.asarray(ds.candidates["position"], np.float32)[fine]
        nrm = np.asarray(ds.candidates["normal"], np.float32)[fine]
        alb = np.asarray(ds.candidates["albedo"], np.float32)[fine]
        valid = np.ones(len(pos), bool)
    elif name == "mrt":
        pos = np.asarray(ds.positions, np.float32).reshape(-1, 3)
        nrm = np.asarray(ds.normals, np.float32).reshape(-1, 3)
        alb = np.asarray(ds.albedo, np.float32).reshape(-1, 3)
        valid = np.asarray(session.params["mask"], bool).reshape(-1)  # texels of faces that exist
    else:
        return None
    s = pos.shape[0]
    return GBuffer(pos, nrm, nrm, nrm, np.zeros((s, 2), np.float32), alb, np.zeros((s, 3), np.float32),
                   np.ones(s, np.float32), np.zeros(s, np.int32), valid)


def _environment_cube(session, env: str | None) -> tuple[str, np.ndarray]:
    """(name, (6, n, n, 3) cube) of ``env``: one of the run's maps (default the first), or an
    environment-map file (resampled to the model's cube face: neural-wavelet PRT's
    ``envmaps.face_size``, else 32; radiance as in the file)."""
    envs = dict(session.environments)
    if env is not None and os.path.isfile(env):
        from jprt.render.lights import EnvMap
        from jprt.sphere.envmap import prepare_environment

        face = int(session.method_config.get("envmaps", {}).get("face_size", 32))
        return os.path.basename(env), np.asarray(prepare_environment(EnvMap.from_file(env).radiance, face,
                                                                     normalise=False), np.float32)
    if not envs:
        raise ValueError(f"{session.folder}: the run has no environment maps: give --env an environment-map file")
    name = next(iter(envs)) if env is None else env
    if name not in envs:
        raise ValueError(f"no environment {name!r} in the run (it has {', '.join(envs)}), and no such file")
    return name, np.asarray(envs[name], np.float32)


def _on_valid(objective: Objective, valid) -> Objective:
    """The objective with its image term restricted to the frame's valid pixels (the mask's, or
    all of them without one): elsewhere the model predicts nothing and the verification is 0."""
    if objective.image is None:
        return objective
    ok = np.asarray(valid, bool)
    mask = ok if objective.image.mask is None else (np.asarray(objective.image.mask, bool) & ok)
    if not mask.any():
        raise ObjectiveError(f"{objective.source}: image.mask selects no pixel the model sees")
    return objective._replace(image=objective.image._replace(mask=mask))


def load_problem(folder: str, objective_path, *, size: int = 64, env: str | None = None,
                 progress: bool | None = None) -> Problem:
    """The ``Problem`` of the run folder ``folder`` (a point-light method, ``POINT_METHODS``) and
    the objective file ``objective_path`` at the run's camera, ``size`` x ``size`` (or the target
    image's size). The objective is checked against the scene's object names before the run's
    data is loaded. Environment-lit models: ``env`` chooses the map (``_environment_cube``), whose
    direct transfer is traced here; ``environments`` holds it alone.

    Numerics: not differentiable (loads a run folder).
    """
    from jprt.inputs import PointLights, PointRadiance
    from jprt.methods import REGISTRY
    from jprt.render.scenes import SceneHandle
    from jprt.runner import method_config
    from jprt.view import Session, check_run_folder

    summary, config = check_run_folder(folder)
    m = REGISTRY[summary["method"]]
    if m.name not in POINT_METHODS + ENVIRONMENT_METHODS:
        raise ValueError(f"jprt design places point lights for {', '.join(POINT_METHODS)} and turns and scales the "
                         f"environment of {', '.join(ENVIRONMENT_METHODS)}; {m.name} takes {m.lighting.__name__}")
    names = list(SceneHandle(method_config(m, config)["scene"]).object_names())
    probe = load_objective(objective_path, names)
    session = Session(folder, progress=progress)
    if probe.image is not None:
        size = int(probe.image.target.shape[0])
        if probe.image.target.shape[1] != size:
            raise ObjectiveError(f"{probe.source}: image must be square (the run's camera at size x size)")
    camera = session.camera(int(size))
    model_inputs = session.inputs(int(size))
    from jprt.inputs import GBuffer

    if isinstance(model_inputs, GBuffer):
        gb = model_inputs
    else:  # a model that reads a few fields of its own (neural-wavelet PRT): the full G-buffer for the design
        from jprt.render.gbuffer import gbuffer

        gb = gbuffer(session.handle, camera)
    objective = _on_valid(load_objective(objective_path, names, shape=np.shape(gb.valid)), gb.valid)
    masks = object_masks(objective, gb.object_id, names, gb.valid)
    evaluate = session.evaluator(gradient=True)
    if m.name in ENVIRONMENT_METHODS:
        from jprt.inputs import CubeMap, SHLighting
        from jprt.sphere import sh

        name, cube = _environment_cube(session, env)
        transfer = environment_transfer(session.handle, gb, int(cube.shape[1]))
        degree = int(session.dataset.meta["degree"]) if m.name == "sh_prt" else 0
        if m.name == "sg_environment":  # its lighting, U (Eq. 6), pre-convolved once and turned
            from jprt.inputs import PreconvolvedEnvironment
            from jprt.methods.sg_lightfield.environment import rotate_preconvolved_y

            base = m.task_lighting(session.handle, session.dataset, session.params, session.method_config,
                                   CubeMap(cube))
            u0, alphas = jnp.asarray(base.u), jnp.asarray(base.alphas)

            def indirect_env(cube, angle, scale):
                u = rotate_preconvolved_y(u0, angle) * jnp.reshape(scale, (1, 1, 1, 3))
                return evaluate(model_inputs, PreconvolvedEnvironment(u, alphas))
        else:
            def indirect_env(cube, angle, scale):
                lighting = SHLighting(sh.project_cubemap(cube, degree)) if m.name == "sh_prt" else CubeMap(cube)
                return evaluate(model_inputs, lighting)

        if m.predicts == "direct" and objective.image is not None and objective.image.quantity == "indirect":
            raise ObjectiveError(f"{objective.source}: {m.name} predicts the environment's direct light, not "
                                 "indirect light: an image objective on it takes quantity 'full'")
        frame = environment_frame(gb, indirect_env, transfer, predicts=m.predicts)
        return Problem(session, camera, gb, objective, masks, None, None, frame, None, "environment", {name: cube},
                       transfer)
    lo, hi = _region(session)
    points = measurement_points(session)
    handle = session.handle

    if points is None:
        def indirect(position, intensity, visibility):
            return evaluate(model_inputs, PointLights(position, intensity))

        def visibility(position):
            return {"pixels": point_visibility(handle, gb, position)}
    else:
        def indirect(position, intensity, visibility):
            direct, _ = point_direct(points, position, intensity, visibility["points"], glossy=False)
            return evaluate(model_inputs, PointRadiance(direct))

        def visibility(position):
            return {"pixels": point_visibility(handle, gb, position),
                    "points": point_visibility(handle, points, position)}

    return Problem(session, camera, gb, objective, masks, lo, hi, design_frame(gb, indirect), visibility)


def design_run(folder: str, objective_path: str, *, lights: int = 1, size: int = 64, steps: int = 200,
               learning_rate: float = 0.05, visibility_every: int = 10,
               optimise: Sequence[str] | None = None, start: dict | str | None = None, verify_spp: int = 256,
               correct: int = 1, correct_spp: int = 256, seed: int = 0, env: str | None = None,
               progress: bool | None = None) -> dict:
    """Design the lighting of the run folder ``folder`` for the objective file ``objective_path``:
    point lights (RRF, data-driven PRT, MRT) or the turn and scale of an environment map (``env``,
    one of the run's maps; default the first: neural-wavelet PRT, SH PRT, SG environment visibility,
    ``_design_environment_run``).
    ``optimise``: what moves (default position and power, or rotation and scale). Point lights:
    (``load_problem``); ``lights`` point lights start at ``start`` ({"position", "intensity"},
    (K, 3) each), at the lights ``search_start`` finds among candidate positions (``start``
    "search": traced candidates, the frame linear in the lights) or spread over the light region
    (None; seeded). Then ``correct`` passes of the **correction**: the lights found are rendered
    by Mitsuba at ``correct_spp``, the model's error there (``model_offset``) is held as an
    offset of its frames, and the design runs again from those lights (same program, no new
    compilation; the same step budget, stopping once its traces stop improving); where its
    lights moved (``correction["moved"]``) they are kept only where a second render, of them,
    with the same seed scores lower than the first (``correction["kept"]``, one flag a pass).
    One or two renders a pass; their time and the design loop's count in ``design_s``
    (``correction["seconds"]`` apart). Then the
    **verification**: the found lighting rendered by Mitsuba at ``verify_spp`` (full and
    indirect; another seed), the objective's terms on that render (``rendered_terms``) beside the
    model's (with the correction's offset). ``uncorrected`` in the report holds the lights before
    the correction. Returns the report (a dict, JSON-ready).

    Numerics: not differentiable (loads a run folder, designs, renders with Mitsuba).
    """
    if int(correct) < 0 or int(correct_spp) < 1:
        raise ValueError(f"design_run's correct is >= 0 passes and correct_spp >= 1, got {correct} and {correct_spp}")
    pb = load_problem(folder, objective_path, size=size, env=env, progress=progress)
    if pb.kind == "environment":
        return _design_environment_run(pb, folder, objective_path, steps=steps,
                                       learning_rate=learning_rate, optimise=optimise, verify_spp=verify_spp,
                                       seed=seed, progress=progress)
    lo, hi, gb, handle = pb.lo, pb.hi, pb.gbuffer, pb.session.handle
    search_s, reference, program = None, None, None
    optimise = ("position", "power") if optimise is None else optimise
    if start is None:
        rng = np.random.default_rng(seed)
        pos0 = lo + (hi - lo) * rng.uniform(0.25, 0.75, (int(lights), 3))
        inten0 = np.ones((int(lights), 3))
    elif isinstance(start, str):
        if start != "search":
            raise ValueError(f"start is a dict of lights, 'search' or None, got {start!r}")
        from scipy.stats import qmc  # noqa: F401 -- the search's import (0.6 s once a process), before the clock

        t0 = time.perf_counter()
        reference = 3.0 * int(lights)  # search_start's reference at its default level 1
        # the design's programs compile in a thread while the search runs
        program = _warm_design(_design_program(pb.frame, pb.objective, pb.masks, lo, hi, optimise=optimise,
                                               reference=reference, steps=steps, learning_rate=learning_rate),
                               pb.visibility, int(lights), lo, hi)
        try:
            pos0, inten0 = search_start(pb.frame, pb.objective, pb.masks, lo, hi, int(lights),
                                        visibility_fn=pb.visibility, seed=seed, reference_power=reference,
                                        progress=progress)
        finally:
            program.warm.join()  # the compilation that outlasts the search is counted with it
        search_s = time.perf_counter() - t0
    else:
        pos0 = np.asarray(start["position"], np.float64).reshape(-1, 3)
        inten0 = np.asarray(start["intensity"], np.float64).reshape(-1, 3)
    # the power penalty's reference, one for the search, the design and the verification
    reference = float(np.sum(inten0)) if reference is None else reference
    if program is None:  # one program for the design and its corrections
        program = _design_program(pb.frame, pb.objective, pb.masks, lo, hi, optimise=optimise, reference=reference,
                                  steps=steps, learning_rate=learning_rate)

    def run(pos, inten, offset):
        return design(pb.frame, pb.objective, pb.masks, pos, inten, lo, hi, visibility_fn=pb.visibility, steps=steps,
                      learning_rate=learning_rate, visibility_every=visibility_every, optimise=optimise,
                      reference_power=reference, offset=offset, program=program, progress=progress)

    result = first = run(pos0, inten0, None)
    correct_s, kept, moved = 0.0, [], []
    for c in range(int(correct)):  # the model's error at the lights found, measured and held
        s = int(seed) + 1009 + c  # apart from the verification's seed + 101
        t0 = time.perf_counter()
        offset = model_offset(handle, pb.camera, gb, pb.frame, result.position, result.intensity,
                              visibility_fn=pb.visibility, spp=int(correct_spp), seed=s)
        correct_s += time.perf_counter() - t0
        trial = run(result.position, result.intensity, offset)
        correct_s += trial.seconds  # its loop; XLA's cost analysis after it is the report's, not the design's
        p0 = to_params(result.position, result.intensity, lo, hi)  # its start (clipped off the region's faces)
        start = [np.asarray(a, np.float64) for a in program.lights(p0, _held(p0))]
        scale = max(float(np.max(np.abs(np.asarray(hi) - np.asarray(lo)))), 1e-30)
        moved.append(bool(np.max(np.abs(trial.position - start[0])) > 1e-6 * scale
                          or np.max(np.abs(trial.intensity / start[1] - 1.0)) > 1e-6))
        if not moved[-1]:  # the second design kept its start: nothing to check
            kept.append(False)
            continue
        # kept only where a render of its lights with the same seed (the same random numbers, so
        # the two renders' noise mostly cancels in the comparison) scores lower than the render the
        # offset came from; the corrected model's first value is that render's objective
        t0 = time.perf_counter()
        after = sum(rendered_terms(handle, pb.camera, gb, pb.objective, pb.masks, trial.position, trial.intensity,
                                   spp=int(correct_spp), seed=s, reference_power=reference).values())
        correct_s += time.perf_counter() - t0
        kept.append(bool(len(trial.history) and after < float(trial.history[0])))
        if kept[-1]:
            result = trial
    # verification: Mitsuba under the found lights, the objective on its render
    t0 = time.perf_counter()
    verified, verified_means = rendered_terms(handle, pb.camera, gb, pb.objective, pb.masks, result.position,
                                              result.intensity, spp=int(verify_spp), seed=int(seed) + 101,
                                              reference_power=reference, means=True)
    verify_s = time.perf_counter() - t0
    return {"run": os.path.abspath(folder), "method": pb.session.method.name,
            "objective": os.path.abspath(objective_path),
            "frame": list(np.shape(gb.valid)), "light_region": {"lo": lo.tolist(), "hi": hi.tolist()},
            "start": {"position": pos0.tolist(), "intensity": inten0.tolist()},
            "found": {"position": result.position.tolist(), "intensity": result.intensity.tolist()},
            "steps": int(steps), "steps_taken": int(len(first.history)), "search_s": search_s,
            "design_s": first.seconds + correct_s + (search_s or 0.0), "step_cost": result.step_cost,
            "visibility_updates": result.visibility_updates,
            "correction": {"passes": int(correct), "spp": int(correct_spp), "seconds": correct_s, "moved": moved,
                           "kept": kept},
            "uncorrected": {"position": first.position.tolist(), "intensity": first.intensity.tolist(),
                            "design_s": first.seconds + (search_s or 0.0),
                            "model_objective": float(sum(first.terms.values()))},
            "history": first.history.tolist(), "model_terms": result.terms,
            "model_objective": float(sum(result.terms.values())), "verified_terms": verified,
            "verified_objective": float(sum(verified.values())), "verify_spp": int(verify_spp),
            "verify_s": verify_s, "reference_power": reference, **_bounds(pb.objective, result.means, verified_means),
            "direct": "analytic point lights (diffuse + GGX) with Mitsuba shadow rays every "
                      f"{int(visibility_every)} steps, held constant between"}


def _design_environment_run(pb: Problem, folder: str, objective_path: str, *, steps: int,
                            learning_rate: float, optimise, verify_spp: int, seed: int, progress) -> dict:
    """``design_run`` for an environment-lit model: turn and scale the problem's map (from angle 0
    and scale 1), then render the found map with Mitsuba (``jprt.render.lights.EnvMap`` of its
    equirect) and evaluate the objective there (``_terms_on_render``; the direct irradiance is the
    traced transfer's, T L; ``rendered_environment_terms``)."""
    name, cube = next(iter(pb.environments.items()))
    optimise = ("rotation", "scale") if optimise is None else optimise
    result = design_environment(pb.frame, pb.objective, pb.masks, cube, steps=steps, learning_rate=learning_rate,
                                optimise=optimise, progress=progress)
    model_terms = result.terms
    t0 = time.perf_counter()
    gb = pb.gbuffer
    verified, verified_means = rendered_environment_terms(pb, result.angle, result.scale, spp=int(verify_spp),
                                                          seed=int(seed) + 101, means=True)
    verify_s = time.perf_counter() - t0
    return {"run": os.path.abspath(folder), "method": pb.session.method.name,
            "objective": os.path.abspath(objective_path), "frame": list(np.shape(gb.valid)), "environment": name,
            "found": {"rotation_deg": float(np.degrees(result.angle)), "scale": result.scale.tolist()},
            "steps": int(steps), "design_s": result.seconds, "step_cost": result.step_cost,
            "history": result.history.tolist(),
            "model_terms": model_terms, "model_objective": float(sum(model_terms.values())),
            "verified_terms": verified, "verified_objective": float(sum(verified.values())),
            "verify_spp": int(verify_spp), "verify_s": verify_s,
            **_bounds(pb.objective, result.means, verified_means),
            "direct": "the map's direct light through a traced transfer at the cube's face size (diffuse; visibility "
                      "per texel direction, one ray)"}


def rendered_environment_terms(pb: Problem, angle: float, scale, *, spp: int, seed: int = 0, means: bool = False):
    """``objective_terms`` on Mitsuba's render of an environment problem's map (``load_problem``
    with ``env``) turned by ``angle`` (radians) about +Y and scaled by ``scale`` (3,) per channel
    (``_terms_on_render``: the map as a ``jprt.render.lights.EnvMap`` of its equirect; the
    direct irradiance is the traced transfer's, T L). With ``means``: (terms, the objects'
    ``object_means`` there).

    Numerics: not differentiable (Mitsuba renders).
    """
    from jprt.render.lights import EnvMap
    from jprt.sphere import cubemap
    from jprt.sphere.envmap import render_equirect

    if pb.kind != "environment":
        raise ValueError("rendered_environment_terms takes an environment problem (load_problem of an "
                         f"environment-lit run); this one places {pb.kind} lights")
    scale = np.asarray(scale, np.float64).reshape(1, 3)
    cube = next(iter(pb.environments.values()))
    found = np.asarray(cubemap.rotate_cubemap_y(cube, float(angle)), np.float64) * scale.reshape(1, 1, 1, 3)
    return _terms_on_render(pb.session.handle, pb.camera, pb.gbuffer, pb.objective, pb.masks,
                            EnvMap.create(render_equirect(found.astype(np.float32))),
                            lambda: np.einsum("hwj,jc->hwc", pb.transfer, found.reshape(-1, 3)), scale,
                            spp=int(spp), seed=int(seed), reference_power=3.0, means=means)


def _bounds(objective: Objective, model_means: dict, verified_means: dict) -> dict:
    """The report's object bounds: each target's bounds and mean on the model's frame and on the
    verification render (``bounds_report``), and whether every bound is met on the render."""
    if not objective.objects:
        return {}
    on_model = bounds_report(objective, model_means)
    on_render = bounds_report(objective, verified_means)
    return {"bounds": {k: {"min": v["min"], "max": v["max"], "model_mean": on_model[k]["mean"],
                           "verified_mean": v["mean"], "met_on_model": on_model[k]["met"], "met_verified": v["met"]}
                       for k, v in on_render.items()},
            "bounds_met_verified": all(v["met"] for v in on_render.values())}


def report_lines(report: dict) -> list[str]:
    """``design_run``'s report in words, one line each: the lighting found, the objective on the
    model beside Mitsuba's verification and the times, the correction (point lights), and every
    bound met or missed on the render. What ``jprt design`` and ``experiments/design.py`` print.

    Numerics: not differentiable (formats a report).
    """
    lines = []
    if "rotation_deg" in report["found"]:
        lines.append(f"environment {report['environment']}: turned {report['found']['rotation_deg']:.2f} degrees "
                     f"about +Y, scale {', '.join(f'{v:.4g}' for v in report['found']['scale'])}")
    else:
        for k, (p, i) in enumerate(zip(report["found"]["position"], report["found"]["intensity"])):
            lines.append(f"light {k}: position {', '.join(f'{v:.4g}' for v in p)}; intensity "
                         f"{', '.join(f'{v:.4g}' for v in i)}")
    lines.append(f"objective: model {report['model_objective']:.4g}, Mitsuba at {report['verify_spp']} spp "
                 f"{report['verified_objective']:.4g} (design {report['design_s']:.1f} s, verification "
                 f"{report['verify_s']:.1f} s)")
    corr = report.get("correction", {})
    if corr.get("passes"):
        lines.append(f"correction: {corr['passes']} pass(es), the model's error held from a Mitsuba render at "
                     f"{corr['spp']} spp, lights kept: {', '.join('yes' if k else 'no' for k in corr['kept'])} "
                     f"({corr['seconds']:.1f} s of the design; model objective before it "
                     f"{report['uncorrected']['model_objective']:.4g})")
    for key, b in report.get("bounds", {}).items():
        within = " and ".join(x for x in (f">= {b['min']:.4g}" if b["min"] is not None else "",
                                          f"<= {b['max']:.4g}" if b["max"] is not None else "") if x)
        lines.append(f"{key} {within}: model {b['model_mean']:.4g}, Mitsuba {b['verified_mean']:.4g} "
                     f"({'met' if b['met_verified'] else 'MISSED'} on the render)")
    return lines


def plot_report(report: dict, path: str) -> None:
    """``design_run``'s report as a figure (PNG at ``path``): left, the objective on the model at
    every design step (log scale; the design before its correction); right, each objective term
    on the model beside the same term on Mitsuba's verification render.

    Numerics: not differentiable (draws a report).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from jprt import io

    fig, (a, b) = plt.subplots(1, 2, figsize=(10, 3.8))
    history = np.asarray(report["history"], np.float64)
    a.plot(np.arange(len(history)), np.maximum(history, 1e-30), lw=1.2)
    a.set_yscale("log")
    a.set_xlabel("design step")
    a.set_ylabel("objective on the model")
    a.set_title(f"design: {report['design_s']:.1f} s", fontsize=9)
    a.grid(True, which="both", alpha=0.2)
    keys = sorted(report["model_terms"])
    x = np.arange(len(keys))
    b.bar(x - 0.2, [report["model_terms"][k] for k in keys], 0.4, label="model")
    b.bar(x + 0.2, [report["verified_terms"][k] for k in keys], 0.4,
          label=f"Mitsuba, {report['verify_spp']} spp")
    b.set_xticks(x, keys, rotation=20, fontsize=7)
    b.set_ylabel("objective term")
    b.set_title(f"objective: model {report['model_objective']:.3g}, Mitsuba {report['verified_objective']:.3g}",
                fontsize=9)
    b.legend(fontsize=7)
    b.grid(True, axis="y", alpha=0.2)
    fig.tight_layout()
    with io.atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)


def run_design(config: dict) -> dict:
    """``experiments/design.py``'s run of ``config``: the run folder ``config["run"]`` (or, when
    it is None, a fit of ``config["fit"]["experiment"]`` at ``config["fit"]["preset"]`` through
    ``jprt.runner.run``, its own output folder), the objective ``config["objective"]`` (a file's
    path, or an objective file's content; written as ``objective.json`` with its image paths made
    absolute: a file's relative to the file, the content's to the working directory), ``design_run`` with
    ``config["design"]``'s keywords; writes ``<output.dir>/<config hash>/`` (config.json,
    objective.json, design.json: the report, design.png: ``plot_report``), prints
    ``report_lines`` and where the report is, and returns the report.

    Numerics: not differentiable (fits, designs, renders with Mitsuba).
    """
    from jprt.config import config_hash, save_resolved
    from jprt.io import write_json

    out = os.path.abspath(os.path.join(config["output"]["dir"], config_hash(config)))
    os.makedirs(out, exist_ok=True)
    save_resolved(config, out)
    folder = config.get("run")
    objective = config["objective"]
    if isinstance(objective, str):  # a file: its image paths are relative to it
        source = os.path.abspath(objective)
        with open(source) as f:
            spec, base = json.load(f), os.path.dirname(source)
    else:  # the config's content: its image paths are relative to the working directory
        spec, base = json.loads(json.dumps(objective)), os.getcwd()
    image = spec.get("image") if isinstance(spec, dict) else None
    if isinstance(image, dict):
        for key in ("path", "mask"):
            if isinstance(image.get(key), str):
                image[key] = os.path.join(base, image[key])
    path = os.path.join(out, "objective.json")
    write_json(path, spec)  # the objective as run, beside the report
    if folder is None:
        from jprt.experiment import load_experiment, resolve_config
        from jprt.runner import run

        fit = config["fit"]
        module = load_experiment(fit["experiment"])
        folder = run(module, resolve_config(module, [], fit.get("preset")))["output"]
    report = design_run(folder, path, **config.get("design", {}))
    write_json(os.path.join(out, "design.json"), report)
    plot_report(report, os.path.join(out, "design.png"))
    print("\n".join(report_lines(report)))
    print(f"design report (design.json, design.png) written to {out}")
    return report
