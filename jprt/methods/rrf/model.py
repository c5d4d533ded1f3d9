"""Radiance Regression Functions (Ren, Wang, Gong, Lin, Tong, Guo 2013).

The indirect radiance s+(x_p, v, l) of a static scene lit by a unit point light at l is regressed
by small tanh networks Phi_N (Eq. 8: two hidden layers, 20 and 10 nodes) of the *augmented*
attributes x = (x_p, v, l, n, a) (Eq. 4: position, unit view direction, light position, normal,
BRDF parameters), trained by Levenberg–Marquardt on path-traced samples (Eq. 6, Eq. 10) and
partitioned per object by an error-driven kd-tree (§4, ``jprt.methods.rrf.kdtree``). Rendering is
linear in the light colours (Eq. 9):

    indirect(pixel) = sum_k c_k Phi(x_p, v, l_k, n, a).

Contract (``jprt.methods.base``): ``data.make_dataset(scene, config)`` -> ``RRFData`` (rendered
once, cached by ``jprt.cache``), ``fit(data, config)`` -> ``FitResult(params, info)``,
``evaluator(params, config)`` -> ``evaluate(gbuffer, lights)`` -> (H, W, 3) indirect image.
This module is the paper's math in pure JAX/NumPy and imports no Mitsuba.

Training data (Appendix A): N_l light positions and N_v viewpoints by Latin hypercube sampling in
user boxes; N_r random primary rays per (light, view) pair; attributes at the first hit and the
path-traced indirect radiance (full minus direct, same seed). A 70/30 split into training and
validation samples; every node scales its inputs and outputs to [-1, 1] by their ranges and keeps
the scale factors with its weights (Appendix A, Beale et al.'s mapminmax).

Material editing (Appendix B, ``data.mode = "material"``): the viewpoint is fixed and the view
direction inputs are replaced by the roughness and albedo of one object; training samples vary
them by Latin hypercube sampling, and ``evaluate(EditInputs(gbuffer, (roughness, albedo)), lights)``
renders any edit.

Training stops early on each node's validation samples (Beale et al.'s trainlm, which Appendix A
follows: the parameters with the lowest validation error are kept; ``train.max_fail`` accepted
steps without improvement end the fit; 0 disables it).

Deviations, stated: candidate children are warm-started from their parent (its weights mapped
exactly into the child's input/output scaling) and, when every axis is tried, fitted for
``train.trial_iters`` iterations on at most ``train.trial_samples`` of their training samples
before the chosen pair is refined on all its samples to ``train.max_iters``; the paper fits every
candidate from scratch to convergence, which costs ~D times more here.
"""

from __future__ import annotations

import functools
import hashlib
import math
import os
import time
import warnings
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jprt.hashing import stable_hash
from jprt.inputs import GBuffer, PointLights
from jprt.methods.base import FitResult, resolve
from jprt.methods.rrf import kdtree
from jprt.nn.mlp import MLP, constant_up_to_rounding, mlp, ranges
from jprt.progress import say as progress_say
from jprt.solve.lm import LMSettings, solve_batched

__all__ = ["DEFAULT_CONFIG", "ATTRIBUTE_SETS", "RRFData", "EditInputs", "features", "brdf_vector", "data_features",
           "split_samples", "split_dims", "input_size", "fit", "fit_arrays", "evaluator", "frame_flops", "check_inputs", "example",
           "refit_leaves", "parameter_count", "light_box", "raw_thresholds", "RENDER_LAYOUTS", "render_layout"]

#: Inputs of Phi for each attribute set (Ren et al. Fig. 3: basic vs augmented attributes).
ATTRIBUTE_SETS = {
    "basic": ("position", "view", "light"),
    "basic+a": ("position", "view", "light", "brdf"),
    "augmented": ("position", "view", "light", "normal", "brdf"),
    # without v: for a scene whose surfaces are all Lambertian the indirect radiance leaving x does
    # not depend on the view direction (L_o = rho / pi * int L_i cos), so v can only carry the
    # finite set of training views' directions, which a held-out view leaves (view mode only)
    "diffuse": ("position", "light", "normal", "brdf"),
}
_WIDTHS = {"position": 3, "view": 3, "light": 3, "normal": 3, "brdf": 7}

DEFAULT_CONFIG: dict = {
    "scene": {"name": "cornell_box", "area_light": False},
    "data": {
        "mode": "view",  # "view" (x_p, v, l, ...) or "material" (Appendix B: v replaced by an edit)
        # sampling regions of lights and views; None: from the scene (data.scene_regions: the
        # built-in boxes' tuned regions, else the scene's bounds and free space)
        "light_lo": None,
        "light_hi": None,
        "view_lo": None,
        "view_hi": None,
        "view_target": None,
        "target_jitter": 0.15,
        "fov": None,  # None: from the scene, as the regions above (the built-in boxes' 39.3077)
        "n_lights": 20,
        "n_views": 20,
        "n_rays": 100,
        # > 1: n_rays drawn from oversample x n_rays screen rays, balanced over the surfaces they hit
        # (data.py): for small budgets, where uniform rays miss faces seen at grazing angles
        "oversample": 1,
        # at least this many of each view-light pair's rays on every object the candidate rays hit
        # (drawn first; 0: none). Small objects then get samples (issue 21: one ray or none before)
        "min_object_rays": 0,
        # at least this many of each view-light pair's rays on every face (object x signed dominant
        # normal axis) that 16 x n_rays candidate screen rays hit, drawn first, the rest uniform
        # (0: none): a face seen only at grazing angles (the tall box's top) gets samples
        "min_face_rays": 0,
        "spp": 512,
        "seed": 0,
        "val_fraction": 0.3,
        # held-out point lights (their own seed stream, never fitted) rendered from every view (or
        # material) at n_rays / 2 rays each for the self-check (data.self_check; at the defaults
        # 5 % of the training render; 0: none). Not part of the training data's cache key
        "check_lights": 2,
        "material": {"object": "floor", "roughness": [0.05, 0.5], "albedo": [0.1, 0.8], "n_materials": 8,
                     "view_origin": [0.0, 0.0, 3.9]},
    },
    "model": {"hidden": [20, 10], "attributes": "augmented"},
    # split_on: the attributes (ATTRIBUTE_SETS names) whose axes a node may split; None, every
    # axis, is the paper's. Without "light" every leaf serves every light, so a frame's lights
    # share each pixel's traversal and the light-free part of the first layer (experiments/
    # rrf_cornell.py's `small` config bars it). That config on 2026-12-02 (benchmarks/results/
    # rrf_cornell.json, 2-core AMD CPU, both rules on the same samples, frames timed interleaved):
    # without the light 31 leaves, RMSE 0.0065, p99.9 8.4x, 512^2 frame 16.3 ms, four lights 1.83x;
    # None: 28 leaves (20 of 21 splits on the light), 0.0067, 7.6x, 12.2 ms, 3.68x
    "tree": {"threshold": 0.05, "axis": "all", "expand": 0.1, "max_depth": 6, "min_samples": 1500, "max_leaves": 64,
             "group_below": 32, "split_on": None},
    # progress: the fit's messages on stderr; None follows jprt.progress (JPRT_PROGRESS, else
    # whether stderr is a terminal), as every fit does; fit's progress= argument wins over it
    "train": {"max_iters": 40, "trial_iters": 10, "trial_samples": 1024, "max_fail": 6, "rtol": 1e-6, "damping": 1e-3, "chunk_size": 1024, "seed": 0,
              "subset": 1.0, "progress": None},
    # evaluator: lights outside the trained box ("error" | "clamp" | "allow", box grown by
    # `tolerance` of its size); the tiled networks (None: by JAX's default backend, ``RENDER_LAYOUTS``)
    # and their input / output clamps (evaluator docstring)
    "render": {"extrapolation": "error", "tolerance": 0.02, "tile": None, "chunk": None,
               "clamp_inputs": True, "nonnegative": True},
}


#: ``render.tile`` x ``render.chunk`` by JAX backend when the config leaves them None, each the
#: fastest one-light 512^2 frame of ``benchmarks/device_evaluators.py`` on that kind of device
#: (benchmarks/results/device_evaluators.json): on a 2-core CPU small tiles and chunks keep a
#: chunk's activations in cache (8 x 64: 17 ms; 32 x 64: 23 ms); on an H200 each loop step is a
#: few kernel launches, so fewer, larger steps win (8 x 64: 3.1 ms; 32 x 64: 0.7-0.9 ms, and the
#: fastest four-light frame, 3.8 ms).
RENDER_LAYOUTS = {"cpu": (8, 64), "gpu": (32, 64)}


def render_layout(render: dict, backend: str | None = None) -> tuple[int, int]:
    """(tile, chunk) of the tiled renderer: ``render["tile"]`` and ``render["chunk"]`` where set,
    else ``RENDER_LAYOUTS`` of ``backend`` (default: JAX's default backend; others take the GPU's).

    Numerics: not differentiable (a layout choice; every layout gives the same image).
    """
    auto = RENDER_LAYOUTS.get(backend or jax.default_backend(), RENDER_LAYOUTS["gpu"])
    tile = auto[0] if render.get("tile") is None else int(render["tile"])
    chunk = auto[1] if render.get("chunk") is None else int(render["chunk"])
    if tile < 1 or chunk < 1:
        raise ValueError(f"render.tile and render.chunk must be >= 1 (or None: automatic), got {tile}, {chunk}")
    return tile, chunk


def _cfg(config: dict | None) -> dict:
    """``DEFAULT_CONFIG`` merged strictly with ``config`` (an unknown key raises ConfigError)."""
    return resolve(DEFAULT_CONFIG, config)


# --------------------------------------------------------------------------------------------
# Training data (Appendix A; rendered by ``jprt.methods.rrf.data``)


class RRFData(NamedTuple):
    """Per-sample training data (N samples).

    Fields: position, view (unit, surface to camera), light (light position), normal (unit,
    facing the viewer), brdf (diffuse rgb, specular rgb, GGX alpha), edit ((N, 2) roughness and
    albedo of the edited object in material mode, (N, 0) otherwise), object_id (N,), direct and
    indirect (N, 3) radiance for a unit white light, pair (N,) index of the (light, view or
    material) pair, and ``meta`` (a dict: boxes, object names, spp, seed).
    """

    position: np.ndarray
    view: np.ndarray
    light: np.ndarray
    normal: np.ndarray
    brdf: np.ndarray
    edit: np.ndarray
    object_id: np.ndarray
    direct: np.ndarray
    indirect: np.ndarray
    pair: np.ndarray
    meta: dict

    def __len__(self) -> int:
        return int(self.position.shape[0])

    def subset(self, index) -> "RRFData":
        """The samples at ``index`` (bool mask or integer indices)."""
        return RRFData(*(np.asarray(a)[index] for a in self[:-1]), self.meta)


# --------------------------------------------------------------------------------------------
# Attributes


def features(attributes: str, position, view, light, normal, brdf, edit=None):
    """The input vector x of Phi for an attribute set (``ATTRIBUTE_SETS``), last axis features.

    In material mode (``edit`` given, (..., 2)) the edit parameters take the place of ``view``
    (Appendix B). Works on NumPy and JAX arrays of any batch shape.

    Numerics:
        case: rrf_features (every attribute set; positions, lights in [-1e3, 1e3], unit views and
          normals, BRDF attributes in [0, 1])
        float32: value rtol 0 atol 0; grad rtol 1e-6 atol 0
        (a concatenation: exact; the case's gradient sums the cotangents of several attribute sets)
    """
    if attributes not in ATTRIBUTE_SETS:
        raise ValueError(f"unknown attribute set {attributes!r}; use one of {sorted(ATTRIBUTE_SETS)}")
    parts = {"position": position, "view": view if edit is None else edit, "light": light, "normal": normal,
             "brdf": brdf}
    # float32 (NumPy training data is float64); JAX float64 inputs stay float64 (x64 tests)
    wide = any(isinstance(v, jax.Array) and v.dtype == jnp.float64 for v in parts.values())
    dtype = jnp.float64 if wide else jnp.float32
    return jnp.concatenate([jnp.asarray(parts[name], dtype) for name in ATTRIBUTE_SETS[attributes]], axis=-1)


def brdf_vector(diffuse_albedo, specular_albedo, roughness):
    """The BRDF attributes a of Eq. 4 per pixel or sample: diffuse rgb, specular rgb, GGX alpha
    (..., 7). NumPy in, NumPy out (training data); JAX in, JAX out (the evaluator).

    Numerics:
        diffuse_albedo: (16, 3) in [0, 1]
        specular_albedo: (16, 3) in [0, 1]
        roughness: (16,) in [1e-4, 1]
        float32: value rtol 0 atol 0; grad rtol 0 atol 0
        (a concatenation: exact)
    """
    xp = jnp if isinstance(roughness, jax.Array) else np
    return xp.concatenate([diffuse_albedo, specular_albedo, xp.asarray(roughness)[..., None]], axis=-1)


def data_features(data: RRFData, attributes: str) -> np.ndarray:
    """The inputs x of Phi for every sample of ``data`` (N, D).

    Numerics: not differentiable (training data in NumPy).
    """
    edit = data.edit if data.meta.get("mode") == "material" else None
    return np.asarray(features(attributes, data.position, data.view, data.light, data.normal, data.brdf, edit))


def _columns(attributes: str, mode: str = "view") -> dict:
    """{attribute name: (first, end) columns of x} in ``features``' layout for an attribute set
    (the view is 2 wide, the edit, in material mode)."""
    widths = dict(_WIDTHS, view=2 if mode == "material" else 3)
    out, start = {}, 0
    for name in ATTRIBUTE_SETS[attributes]:
        out[name] = (start, start + widths[name])
        start += widths[name]
    return out


def split_dims(config: dict) -> list[int] | None:
    """The input axes the kd-tree may split under ``config["tree"]["split_on"]``: None where that is
    None (every axis, the paper's), else the columns of the named ``ATTRIBUTE_SETS`` attributes in
    ``features``' layout.

    Numerics: not differentiable (integer axes).
    """
    split_on = config["tree"].get("split_on")
    if split_on is None:
        return None
    columns = _columns(config["model"]["attributes"], config["data"].get("mode", "view"))
    if isinstance(split_on, str) or not set(split_on) <= set(columns) or not split_on:
        raise ValueError(f"tree.split_on must be None or a non-empty list of {list(columns)}, got {split_on!r}")
    return [c for name, (a, b) in columns.items() if name in split_on for c in range(a, b)]


def input_size(attributes: str, mode: str = "view") -> int:
    """Number of inputs of Phi for an attribute set (and data mode).

    Numerics: not differentiable (an integer size).
    """
    return max(end for _, end in _columns(attributes, mode).values())


# --------------------------------------------------------------------------------------------
# Fitting (Eq. 6, Eq. 10, §4)


@functools.lru_cache(maxsize=None)
def _network(sizes: tuple) -> MLP:
    """Phi_N of Eq. 8: the tanh MLP family of layer ``sizes`` (``jprt.nn.mlp``), with Appendix A's
    [-1, 1] scaling (the node payload is exactly its params) and uniform [-1, 1] initial weights."""
    return mlp(sizes, activation="tanh", init="rrf")


def _sizes(layers) -> tuple:
    """Layer sizes of a network's layers (stacked leaf networks too: the last two axes of w)."""
    return (int(np.shape(layers[0]["w"])[-2]),) + tuple(int(np.shape(layer["w"])[-1]) for layer in layers)


@functools.lru_cache(maxsize=None)
def _jitted_apply(sizes: tuple):
    return jax.jit(_network(sizes).apply)


def _phi(payload, x) -> np.ndarray:
    """Phi_N(x) of one node (payload = its MLP params) for samples x (N, D), on the host: the
    jitted ``jprt.nn.mlp`` apply on rows padded to a few bucket sizes (few compiled shapes)."""
    n = len(x)
    xp = np.zeros((_bucket(n, 64), np.shape(x)[1]), np.float32)
    xp[:n] = x
    return np.asarray(_jitted_apply(_sizes(payload["layers"]))(payload, xp))[:n]


@functools.lru_cache(maxsize=None)
def _residual_fn(sizes: tuple):
    """Eq. 6 residual of one sample in the node's scaled space, Phi_N(x) - y, for the LM solver
    (the parameters are the layers; the scaling is the identity there)."""
    net = _network(sizes)
    identity = net.init(np.random.default_rng(0))["scaling"]

    def residual(layers, sample):
        x, y = sample
        return net.apply({"layers": layers, "scaling": identity}, x[None, :])[0] - y

    return residual


def _rescale(layers, src: dict, dst: dict):
    """Express a network trained under scaling ``src`` under scaling ``dst`` (same function):
    x_src = x_dst * h_dst / h_src + (c_dst - c_src) / h_src folds into the first layer, and the
    output map into the last."""
    layers = [dict(layer) for layer in layers]
    a = dst["in_halfrange"] / src["in_halfrange"]
    shift = (dst["in_center"] - src["in_center"]) / src["in_halfrange"]
    w0 = layers[0]["w"]
    layers[0]["b"] = layers[0]["b"] + shift @ w0
    layers[0]["w"] = a[:, None] * w0
    ratio = src["out_halfrange"] / dst["out_halfrange"]
    last = layers[-1]
    last["b"] = (last["b"] * src["out_halfrange"] + src["out_center"] - dst["out_center"]) / dst["out_halfrange"]
    last["w"] = last["w"] * ratio[None, :]
    return layers


def _bucket(n: int, minimum: int = 256) -> int:
    """Padded sample count: steps of sqrt(2) rounded up to multiples of 256 (few compiled shapes,
    at most ~40 % padding)."""
    size = minimum
    while size < n:
        size = int(math.ceil(size * math.sqrt(2.0) / 256.0) * 256)
    return size


class _NodeFitter:
    """The kd-tree's ``fit_nodes``: fits many nodes at once with ``solve_batched`` (problems
    grouped by padded sample count), returns weights + scaling and relative errors."""

    def __init__(self, x, y, sizes, cfg, seed: int, say):
        self.x, self.y, self.sizes, self.cfg, self.say = x, y, tuple(sizes), cfg, say
        self.rng = np.random.default_rng(seed)
        self.calls = 0

    def __call__(self, problems, iters: int | None = None):
        t = self.cfg["train"]
        iters = int(iters or t["max_iters"])
        out: list = [None] * len(problems)
        groups: dict[int, list[int]] = {}
        for i, p in enumerate(problems):
            groups.setdefault(_bucket(len(p.train)), []).append(i)
        for npad, members in sorted(groups.items()):
            results = self._fit_group([problems[i] for i in members], npad, iters)
            for i, r in zip(members, results):
                out[i] = r
        self.calls += 1
        return out

    def errors(self, problem) -> tuple[float, float]:
        """(train, val) relative errors of ``problem.init`` (a payload) on the problem's samples."""
        def err(idx):
            return _relative_error(_phi(problem.init, self.x[idx]), self.y[idx])

        train = err(problem.train)
        return train, (err(problem.val) if len(problem.val) else train)

    def _fit_group(self, problems, npad, iters):
        t = self.cfg["train"]
        d, r = self.x.shape[1], self.y.shape[1]
        b = len(problems)
        xs = np.zeros((b, npad, d), np.float32)
        ys = np.zeros((b, npad, r), np.float32)
        mask = np.zeros((b, npad), np.float32)
        nv = _bucket(max(len(p.val) if len(p.val) else len(p.train) for p in problems), 64)
        xv = np.zeros((b, nv, d), np.float32)
        yv = np.zeros((b, nv, r), np.float32)
        mask_v = np.zeros((b, nv), np.float32)
        scalings, inits = [], []
        for j, p in enumerate(problems):
            xi, yi = self.x[p.train], self.y[p.train]
            ic, ih = ranges(xi)
            oc, oh = ranges(yi, eps=1e-8)  # outputs: any spread is signal (dim texels are small)
            scaling = {"in_center": ic, "in_halfrange": ih, "out_center": oc, "out_halfrange": oh,
                       "in_min": xi.min(axis=0), "in_max": xi.max(axis=0)}  # the range the renderer clips to
            scalings.append(scaling)
            n = len(p.train)
            xs[j, :n] = (xi - ic) / ih
            ys[j, :n] = (yi - oc) / oh
            mask[j, :n] = 1.0
            val = p.val if len(p.val) else p.train  # no validation samples: no early stopping
            xv[j, :len(val)] = (self.x[val] - ic) / ih
            yv[j, :len(val)] = (self.y[val] - oc) / oh
            mask_v[j, :len(val)] = 1.0
            if p.init is not None:
                layers = _rescale([{k: np.asarray(v) for k, v in layer.items()} for layer in p.init["layers"]],
                                  {k: np.asarray(v) for k, v in p.init["scaling"].items()}, scaling)
            else:
                layers = _network(self.sizes).init(self.rng)["layers"]  # uniform [-1, 1], on the host
            inits.append(layers)
        params = jax.tree_util.tree_map(lambda *a: np.stack(a).astype(np.float32), *inits)
        settings = LMSettings(max_iters=iters, rtol=float(t["rtol"]), damping=float(t["damping"]),
                              chunk_size=int(t["chunk_size"]), max_fail=max(int(t["max_fail"]), 1))
        res = solve_batched(_residual_fn(self.sizes), params, (jnp.asarray(xs), jnp.asarray(ys)),
                            mask=jnp.asarray(mask), settings=settings,
                            val_data=(jnp.asarray(xv), jnp.asarray(yv)) if t["max_fail"] > 0 else None,
                            val_mask=jnp.asarray(mask_v) if t["max_fail"] > 0 else None)
        layers = jax.tree_util.tree_map(np.asarray, res.params)
        fits = []
        for j, p in enumerate(problems):
            s = scalings[j]
            n = len(p.train)
            payload = {"layers": [{k: v[j] for k, v in layer.items()} for layer in layers], "scaling": s}
            train_err = _relative_error(_phi(payload, self.x[p.train]), self.y[p.train])
            val_err = train_err
            if len(p.val):
                val_err = _relative_error(_phi(payload, self.x[p.val]), self.y[p.val])
            fits.append(kdtree.NodeFit(payload, train_err, val_err))
        return fits


def _relative_error(pred, ref) -> float:
    """sqrt(sum ||pred - ref||^2 / sum ||ref||^2) (§4: the 5 % relative error)."""
    return float(np.sqrt(np.sum(np.square(pred - ref)) / max(float(np.sum(np.square(ref))), 1e-30)))


def split_samples(n: int, val_fraction: float, seed: int) -> np.ndarray:
    """The seeded training / validation split of Appendix A: True for the training samples.

    Numerics: not differentiable (a boolean split).
    """
    if not (0.0 <= val_fraction < 1.0):
        raise ValueError(f"data.val_fraction must be in [0, 1), got {val_fraction}")
    rng = np.random.default_rng(seed + 7)
    is_train = np.ones(n, bool)
    is_train[rng.permutation(n)[: int(round(val_fraction * n))]] = False
    return is_train


def fit(data: RRFData, config: dict | None = None, *, is_train=None, checkpoint_dir: str | None = None,
        progress: bool | None = None) -> FitResult:
    """Fit the kd-tree of RRFs to ``data`` (§4, Appendix A). Returns ``FitResult(params, info)``.

    ``params`` is a pytree of arrays (kd-tree, per-object input boxes, stacked leaf networks with
    their scaling, the trained light box) for ``evaluator``; ``info`` a dict: ``train_s``,
    ``report`` (the kd-tree build report), ``leaf_train_error`` / ``leaf_val_error`` (per leaf),
    ``is_train`` (the split mask) and ``n_samples``.
    ``is_train`` overrides the seeded 70/30 split; ``train.subset`` < 1 keeps that random
    fraction of the training samples (the Table 3 / Fig. 6 experiments); ``checkpoint_dir`` and
    ``progress``: see ``fit_arrays``.

    Numerics: not differentiable (a fitting or training procedure).
    """
    cfg = _cfg(config)
    if data.meta.get("mode") == "material" and "view" not in ATTRIBUTE_SETS[cfg["model"]["attributes"]]:
        raise ValueError(f"model.attributes {cfg['model']['attributes']!r} has no view, where material mode "
                         "puts the edit parameters (Appendix B); use one with a view")
    x = data_features(data, cfg["model"]["attributes"])
    if is_train is None:
        is_train = split_samples(len(data), float(cfg["data"]["val_fraction"]), int(cfg["train"]["seed"]))
    is_train = np.asarray(is_train, bool).copy()
    subset = float(cfg["train"]["subset"])
    if not (0.0 < subset <= 1.0):
        raise ValueError(f"train.subset must be in (0, 1], got {subset}")
    if subset < 1.0:
        rng = np.random.default_rng(int(cfg["train"]["seed"]) + 13)
        train_idx = np.flatnonzero(is_train)
        drop = rng.permutation(train_idx)[int(round(subset * len(train_idx))):]
        keep = np.ones(len(data), bool)
        keep[drop] = False
        x, data, is_train = x[keep], data.subset(keep), is_train[keep]
    params, info = fit_arrays(x, data.indirect, data.object_id, cfg, is_train=is_train, checkpoint_dir=checkpoint_dir,
                              progress=progress)
    params["light_lo"] = jnp.asarray(data.meta["light_lo"], jnp.float32)
    params["light_hi"] = jnp.asarray(data.meta["light_hi"], jnp.float32)
    return FitResult(params, info)


def fit_arrays(x, y, object_id, config: dict | None = None, *, is_train=None, checkpoint_dir: str | None = None,
               progress: bool | None = None):
    """Fit the partitioned RRF to arbitrary inputs ``x`` (N, D) and outputs ``y`` (N, R).

    The generic core of ``fit`` (synthetic targets in tests use it directly). Returns
    ``(params, info)``; ``params`` has no light box (add ``light_lo``/``light_hi`` for rendering).

    ``checkpoint_dir``: every batch of LM node fits is saved there as it finishes (in a folder
    named by the data and config), and read back by a rerun: a fit killed and restarted repeats
    at most the batch it was in and ends bit-identical to an uninterrupted one (``info
    ["checkpoint"]`` counts the batches loaded and fitted).

    ``progress``: one-line messages of the kd-tree build on stderr (``jprt.progress``); None:
    ``train.progress``, and when that is None too, the ``jprt.progress`` policy.

    Numerics: not differentiable (a fitting or training procedure).
    """
    cfg = _cfg(config)
    x = np.asarray(x, np.float32)
    y = np.asarray(y, np.float32)
    object_id = np.asarray(object_id, np.int32)
    if x.ndim != 2 or y.ndim != 2 or len(x) != len(y) or object_id.shape != (len(x),):
        raise ValueError(f"need x (N, D), y (N, R), object_id (N,); got {x.shape}, {y.shape}, {object_id.shape}")
    if not (np.isfinite(x).all() and np.isfinite(y).all()):
        raise ValueError("RRF training data contains NaN or infinite values")
    if is_train is None:
        is_train = split_samples(len(x), float(cfg["data"]["val_fraction"]), int(cfg["train"]["seed"]))
    t = cfg["train"]
    tree_cfg = cfg["tree"]
    sizes = (x.shape[1], *cfg["model"]["hidden"], y.shape[1])
    say = progress_say("rrf", t["progress"] if progress is None else progress)
    t0 = time.perf_counter()

    # Per-object normalisation of the input box to the unit hypercube (§4, Fig. 4 c-d).
    n_obj = int(object_id.max()) + 1
    obj_lo = np.zeros((n_obj, x.shape[1]), np.float32)
    obj_hi = np.ones((n_obj, x.shape[1]), np.float32)
    for o in np.unique(object_id):
        if o < 0:
            continue
        sel = x[object_id == o]
        obj_lo[o], obj_hi[o] = sel.min(axis=0), sel.max(axis=0)
    # A coordinate constant up to rounding (a wall's x spans an ulp or two) gets a zero span, so
    # ``_unit`` keeps it at x - lo ~ 1e-7 instead of stretching its rounding to [0, 1]: the tree
    # split the floor, the ceiling and both side walls at their root on that noise (two leaves per
    # wall, each fitted on a random half of its samples, alternating pixel by pixel in a frame)
    obj_hi = np.where(constant_up_to_rounding(obj_lo, obj_hi), obj_lo, obj_hi)
    xn = _normalise(x, object_id, obj_lo, obj_hi)

    fitter = _NodeFitter(x, y, sizes, cfg, int(t["seed"]), say)
    checkpoint = None
    max_iters = int(t["max_iters"])
    trial_iters = min(int(t["trial_iters"]), max_iters) if tree_cfg["axis"] == "all" else max_iters

    def fit_nodes(problems, stage):
        if stage == "root":
            say(f"fitting {len(problems)} root RRF(s) on {int(is_train.sum())} training samples")
            return fitter(problems, max_iters)
        if stage == "candidate":
            cap = int(t["trial_samples"])
            if cap > 0:  # compare axes on a random subsample of each candidate's training samples
                rng = np.random.default_rng(int(t["seed"]) + 17)
                problems = [p._replace(train=np.sort(rng.permutation(p.train)[:cap])) if len(p.train) > cap else p
                            for p in problems]
            return fitter(problems, trial_iters)
        if trial_iters >= max_iters:  # candidates were fitted to the full budget already
            return [kdtree.NodeFit(p.init, *fitter.errors(p)) for p in problems]
        return fitter(problems, max_iters - trial_iters)

    if checkpoint_dir is not None:
        key = stable_hash({"config": cfg, "data": [hashlib.sha256(np.ascontiguousarray(a).tobytes()).hexdigest()
                                                   for a in (x, y, object_id, np.asarray(is_train, bool))]})
        fit_nodes, checkpoint = _checkpointed(fit_nodes, fitter, os.path.join(checkpoint_dir, f"rrf_{key}"))
    tree, payloads, report = kdtree.build(
        xn, object_id, is_train, fit_nodes, threshold=float(tree_cfg["threshold"]), axis=tree_cfg["axis"],
        expand=float(tree_cfg["expand"]), max_depth=int(tree_cfg["max_depth"]),
        min_samples=int(tree_cfg["min_samples"]), max_leaves=int(tree_cfg["max_leaves"]), seed=int(t["seed"]),
        group_below=int(tree_cfg["group_below"]), dims=split_dims(cfg), progress=say)
    params = _pack(tree, obj_lo, obj_hi, payloads)
    train_err, val_err = _leaf_errors(params, xn, x, y, object_id, is_train)
    info = {"train_s": time.perf_counter() - t0, "report": report, "leaf_train_error": train_err,
            "leaf_val_error": val_err, "is_train": is_train, "n_samples": len(x)}
    if checkpoint is not None:
        info["checkpoint"] = dict(checkpoint)
    say(f"{tree.n_leaves} leaves, max depth {tree.max_depth}, {info['train_s']:.1f} s; leaf relative error "
        f"train median {np.median(train_err):.3f} / val median {np.median(val_err):.3f}")
    return FitResult(params, info)


def _checkpointed(fit_nodes, fitter: "_NodeFitter", folder: str):
    """``fit_nodes`` whose every call's node fits are saved to ``folder`` (``nodes_KKKKK.npz``,
    in call order, with the fitter's host RNG state after the call: fresh networks draw their
    initial weights from it) and read back on a rerun. The kd-tree build is deterministic given
    its fits, so the rerun asks for the same calls in the same order; a file made for other nodes
    or a damaged one is fitted again with a warning. Returns (wrapped, counts)."""
    from jprt import io

    os.makedirs(folder, exist_ok=True)
    counts = {"folder": folder, "loaded": 0, "fitted": 0}
    calls = [0]

    def wrapped(problems, stage):
        k = calls[0]
        calls[0] += 1
        if not problems:
            return fit_nodes(problems, stage)
        path = os.path.join(folder, f"nodes_{k:05d}.npz")
        digest = stable_hash({"stage": stage, "nodes": [hashlib.sha256(np.concatenate(
            [np.asarray(p.train, np.int64), [-1], np.asarray(p.val, np.int64)]).tobytes()).hexdigest() for p in problems]})
        if os.path.exists(path):
            try:
                tree, _, meta = io.load_tree(path)
                if meta.get("digest") != digest or len(tree) != len(problems):
                    raise io.CorruptCheckpoint(f"checkpoint {path} was made for other nodes")
                fits = [kdtree.NodeFit(f["payload"], float(f["train_error"]), float(f["val_error"])) for f in tree]
                fitter.rng.bit_generator.state = meta["rng"]
                counts["loaded"] += 1
                return fits
            except io.CorruptCheckpoint as e:
                warnings.warn(f"{e}; fitting those nodes again", stacklevel=2)
        fits = fit_nodes(problems, stage)
        io.save_checkpoint(path, [{"payload": f.payload, "train_error": np.float64(f.train_error),
                                   "val_error": np.float64(f.val_error)} for f in fits],
                           step=k, meta={"digest": digest, "rng": fitter.rng.bit_generator.state})
        counts["fitted"] += 1
        return fits

    return wrapped, counts


def _leaf_problem(xn, object_id, is_train, obj, lo, hi, expand):
    """A leaf's training samples (cell grown by ``expand``) and validation samples (the cell)."""
    idx = np.flatnonzero(object_id == obj)
    train = kdtree.node_samples(xn, lo, hi, expand, idx[is_train[idx]])
    return kdtree.Problem(train, kdtree.cell_members(xn, lo, hi, idx[~is_train[idx]]))


def _unit(x, lo, hi, xp=np):
    """x mapped to the box [lo, hi] -> [0, 1] (§4, Fig. 4 c-d); a constant feature maps to x - lo.
    The one rule of the fit (NumPy) and the renderer (``xp=jnp``)."""
    span = hi - lo
    return (x - lo) / xp.where(span > 1e-8, span, 1.0)


def _normalise(x, object_id, obj_lo, obj_hi) -> np.ndarray:
    """Inputs mapped to each object's unit box (``_unit``)."""
    safe = np.maximum(object_id, 0)
    return _unit(x, np.asarray(obj_lo)[safe], np.asarray(obj_hi)[safe])


def _pack(tree: kdtree.KDTree, obj_lo, obj_hi, payloads) -> dict:
    stack = lambda *a: jnp.asarray(np.stack([np.asarray(v) for v in a]), jnp.float32)  # noqa: E731
    leaves = jax.tree_util.tree_map(stack, *payloads)
    return {"tree": {k: jnp.asarray(v) for k, v in tree._asdict().items()},
            "obj_lo": jnp.asarray(obj_lo), "obj_hi": jnp.asarray(obj_hi), "leaves": leaves}


def _tree(params) -> kdtree.KDTree:
    return kdtree.KDTree(**params["tree"])


def _leaf_errors(params, xn, x, y, object_id, is_train):
    """Per-leaf relative errors on the samples routed to each leaf (training / validation)."""
    tree = kdtree.KDTree(*(np.asarray(a) for a in _tree(params)))
    leaf = kdtree.traverse(tree, object_id, xn, xp=np)
    leaves = jax.tree_util.tree_map(np.asarray, params["leaves"])
    n_leaves = leaves["layers"][0]["w"].shape[0]
    tr, va = np.full(n_leaves, np.nan), np.full(n_leaves, np.nan)
    for i in range(n_leaves):
        payload = jax.tree_util.tree_map(lambda v: v[i], leaves)
        for out, sel in ((tr, (leaf == i) & is_train), (va, (leaf == i) & ~is_train)):
            if sel.any():
                out[i] = _relative_error(_phi(payload, x[sel]), y[sel])
    return tr, va


# --------------------------------------------------------------------------------------------
# Evaluation (Eq. 8, Eq. 9)


#: tanh(x) = x P(x^2) / Q(x^2) on |x| <= 7.905 (+-1 beyond in float32): the 13/6 minimax rational
#: approximation Eigen uses for float tanh (generic_fast_tanh_float), written out so the renderer's
#: hidden layers stay one fused multiply-add chain (XLA's tanh streams each layer through memory
#: again on this CPU: 2-4x slower per element). Within 3.2e-7 of tanh in float64, about 5 float32 ulps
#: near +-1 (XLA's own tanh: 2.6e-7; tested).
_TANH_P = (-2.76076847742355e-16, 2.00018790482477e-13, -8.60467152213735e-11, 5.12229709037114e-08,
           1.48572235717979e-05, 6.37261928875436e-04, 4.89352455891786e-03)
_TANH_Q = (1.19825839466702e-06, 1.18534705686654e-04, 2.26843463243900e-03, 4.89352518554385e-03)


def _tanh(x):
    """tanh by the rational approximation above (float32)."""
    x = jnp.clip(x, -7.90531110763549805, 7.90531110763549805)
    x2 = x * x
    p = functools.reduce(lambda acc, c: acc * x2 + c, _TANH_P[1:], jnp.full_like(x, _TANH_P[0]))
    q = functools.reduce(lambda acc, c: acc * x2 + c, _TANH_Q[1:], jnp.full_like(x, _TANH_Q[0]))
    return x * p / q


def _leaf_apply(leaves, leaf, x, *, clamp: bool):
    """Phi_N of Eq. 8 (``jprt.nn.mlp`` apply) for rows ``x`` (B, R, D), the network of leaf
    ``leaf[b]`` on row block b; with ``clamp`` the inputs first clipped to the range of the leaf's
    training samples (a tanh network is not extrapolated; a feature constant in training stays at
    its constant)."""
    per_block = jax.tree_util.tree_map(lambda a: a[leaf], leaves)
    if clamp:
        x = jnp.clip(x, per_block["scaling"]["in_min"][:, None, :], per_block["scaling"]["in_max"][:, None, :])
    return jax.vmap(_network(_sizes(leaves["layers"])).apply)(per_block, x)


def _leaf_of(params, x, object_id):
    """kd-tree leaf of each sample x (..., D) of objects ``object_id`` (...,); -1 for objects
    without a tree (or object_id < 0)."""
    obj = jnp.clip(object_id, 0, params["obj_lo"].shape[0] - 1)
    return kdtree.traverse(_tree(params), object_id, _unit(x, params["obj_lo"][obj], params["obj_hi"][obj], jnp))


def _predict_sorted(params, x, object_id, block: int = 512, clamp: bool = True):
    """Phi(x) for samples x (N, D) of objects ``object_id`` (N,) in any order; 0 for samples of
    objects without a tree (or object_id < 0).

    Samples are sorted by leaf into a padded layout where every leaf owns whole blocks of
    ``block`` samples, so each block is one small dense matrix product with its leaf's weights
    (N + (L + 1) x block padded rows). For samples in any order (the tests' oracle); on images
    the renderer's ``_predict_tiles`` gives the same numbers without XLA's sort and scatter, which
    dominate this function's time on a CPU."""
    n, d = x.shape
    leaves = params["leaves"]
    n_leaves = leaves["layers"][0]["w"].shape[0]
    leaf = _leaf_of(params, x, object_id)
    group = jnp.where(leaf >= 0, leaf, n_leaves)  # group n_leaves: no network, output 0
    counts = jnp.bincount(group, length=n_leaves + 1)
    padded = (counts + block - 1) // block * block
    ends = jnp.cumsum(padded)
    starts = ends - padded
    order = jnp.argsort(group, stable=True)
    g_sorted = group[order]
    rank = jnp.arange(n) - (jnp.cumsum(counts) - counts)[g_sorted]
    dest = starts[g_sorted] + rank
    n_blocks = -(-(n + (n_leaves + 1) * block) // block)
    xp = jnp.zeros((n_blocks * block, d), x.dtype).at[dest].set(x[order])
    block_group = jnp.searchsorted(ends, jnp.arange(n_blocks) * block, side="right")
    has_net = block_group < n_leaves
    y = _leaf_apply(leaves, jnp.minimum(block_group, n_leaves - 1), xp.reshape(n_blocks, block, d), clamp=clamp)
    y = jnp.where(has_net[:, None, None], y, 0.0).reshape(n_blocks * block, -1)
    return jnp.zeros((n, y.shape[-1]), y.dtype).at[order].set(y[dest])


def _tile_leaves(leaf, n_leaves: int):
    """Which leaves occur in each tile: ``leaf`` (K, th, tile, tw, tile) leaf ids (-1: none) ->
    (n_leaves, th, tw) bool. Each id is one bit of a 32-bit word, OR-reduced over the tile's
    pixels and the lights: one pass over the pixels per 32 leaves (a one-hot comparison against
    every leaf is one pass per leaf, and was a sixth of a one-light frame)."""
    words = []
    for w in range(-(-n_leaves // 32)):
        mine = (leaf >= 32 * w) & (leaf < 32 * (w + 1))
        bits = jnp.where(mine, jnp.left_shift(jnp.uint32(1), (leaf - 32 * w).astype(jnp.uint32) & 31), jnp.uint32(0))
        words.append(jax.lax.reduce(bits, jnp.uint32(0), jax.lax.bitwise_or, (0, 2, 4)))  # (th, tw)
    bit = jnp.arange(n_leaves, dtype=jnp.uint32)
    word = jnp.stack(words)[bit // 32]  # (L, th, tw)
    return (jnp.right_shift(word, (bit % 32)[:, None, None]) & 1) == 1


def _predict_tiles(params, parts, light_pos, light_rgb, object_id, *, light_cols: tuple, tile: int, chunk: int,
                   clamp: bool, nonnegative: bool):
    """Eq. 9, sum over lights k of c_k Phi(x_p, l_k) (each term max(., 0) with ``nonnegative``),
    for the pixels of an H x W image without a sort or a per-pixel scatter: (H, W, R).

    ``parts`` is a list of (H, W, c_i) arrays whose concatenation is every input of x but the
    light position, in x's column order; the light's columns in x are ``light_cols``;
    ``object_id`` (H, W) (-1: no network, output 0). The image is cut into ``tile`` x ``tile``
    pixel tiles (neighbouring pixels' leaves agree almost everywhere). Every (leaf, tile) pair
    that some pixel of the tile needs under some light is one work item (``_tile_leaves``).
    Items are listed leaf by leaf, each leaf's list padded to whole chunks of ``chunk`` items, so
    a chunk is one network applied to ``chunk`` x tile^2 pixels: one dense product per layer,
    features x pixels (the layout XLA's CPU dot runs fastest for layers 20 wide), in cache. A
    loop runs over exactly the chunks there are; each finds its items by cumulative sums and a
    binary search, reads its tiles straight from the G-buffer parts (one gather of tile-sized
    slices per part, fused with the clip to the leaf's range and one transposing copy to features
    x pixels), and adds its result into the output, kept as R planes of tile rows (R, tiles,
    tile^2), by one indexed add of whole tile rows (the chunk's items are distinct tiles). The
    light is constant over a frame, so its part of the first layer is one bias per (leaf, light),
    as is the input scaling (folded into the weights), and the rest of the first layer, the
    widest product, is computed once for all the lights whose inputs fall in the leaf (Eq. 9's
    sum shares the position / view / normal / BRDF part)."""
    hh, ww = object_id.shape
    k = light_pos.shape[0]
    leaves = params["leaves"]
    layers = leaves["layers"]
    n_leaves = layers[0]["w"].shape[0]
    n_out = light_rgb.shape[-1]
    ds = sum(int(q.shape[-1]) for q in parts)
    lc = np.asarray(light_cols)
    d = ds + 3
    rest = np.asarray([c for c in range(d) if c not in light_cols])
    th, tw = -(-hh // tile), -(-ww // tile)
    n_tiles, tp = th * tw, tile * tile
    if (th * tile, tw * tile) != (hh, ww):
        pad = ((0, th * tile - hh), (0, tw * tile - ww))
        parts = [jnp.pad(q, pad + ((0, 0),)) for q in parts]
        object_id = jnp.pad(object_id, pad, constant_values=-1)
    where = np.cumsum([0] + [int(q.shape[-1]) for q in parts])  # x column c_s of shared is in part i
    # params are constants of the program: the trees' thresholds are mapped once from each object's
    # unit box back to x's own units (``raw_thresholds``), so traversal compares each pixel's raw
    # inputs, selected per node without a per-pixel gather of x's columns or a division
    tree = _tree(params)
    tree = tree._replace(threshold=jnp.asarray(raw_thresholds(params)))
    split_axes = [int(a) for a in np.unique(np.asarray(params["tree"]["axis"])) if a >= 0]
    # no node splits the light: every light of the frame falls in each pixel's one leaf
    shared_leaf = not any(a in light_cols for a in split_axes)

    def column(cs):  # column cs of the shared inputs, (H, W)
        i = int(np.searchsorted(where, cs, side="right") - 1)
        return parts[i][..., cs - where[i]]

    def leaf_under(lp):  # kd-tree leaf of every pixel under light lp, x never materialised
        raw = {a: lp[a - int(lc[0])] if a in light_cols else column(int(np.flatnonzero(rest == a)[0]))
               for a in split_axes}

        def value(axis):
            out = jnp.zeros(axis.shape, jnp.float32)
            for a, v in raw.items():
                out = jnp.where(axis == a, v, out)
            return out

        return kdtree.traverse(tree, object_id, None, column=value)

    leaf = jnp.stack([leaf_under(light_pos[kk]) for kk in range(1 if shared_leaf else k)])  # (K or 1, H, W)
    kl = leaf.shape[0]
    present = _tile_leaves(leaf.reshape(kl, th, tile, tw, tile), n_leaves).reshape(n_leaves, n_tiles)  # (L, T)
    rank = jnp.cumsum(present.astype(jnp.int32), axis=1)  # (L, T): 1 + the item's rank in its leaf's list
    count = rank[:, -1]
    padded = (count + chunk - 1) // chunk * chunk
    end = jnp.cumsum(padded)
    start = end - padded
    # the r-th present tile of leaf l: leaf l's ranks offset by l (T + 1) are one increasing list
    keys = (rank + (jnp.arange(n_leaves) * (n_tiles + 1))[:, None]).reshape(-1)

    def tiled(a):  # (H, W, ...) -> (T, tile^2, ...): each tile's pixels contiguous, tiles in raster order
        rest_shape = a.shape[2:]
        a = a.reshape((th, tile, tw, tile) + rest_shape)
        return jnp.swapaxes(a, 1, 2).reshape((n_tiles, tp) + rest_shape)

    leaf_t = jax.vmap(tiled)(leaf)  # (K, T, tile^2)

    def tiles_of(a, y0, x0):  # the tiles at (y0, x0) of an (H, W, ...) array: (chunk, tile, tile, ...)
        size = (tile, tile) + a.shape[2:]
        return jax.vmap(lambda y, x: jax.lax.dynamic_slice(a, (y, x) + (0,) * (a.ndim - 2), size))(y0, x0)

    def chunk_body(c, out):  # chunk c: its leaf's network on its tiles' pixels, added into out
        slot = c * chunk + jnp.arange(chunk)
        lf = jnp.clip(jnp.searchsorted(end, c * chunk, side="right", method="compare_all"), 0, n_leaves - 1)
        r = slot - start[lf]
        live = r < count[lf]
        tl = jnp.searchsorted(keys, lf * (n_tiles + 1) + r + 1, side="left", method="scan_unrolled") - lf * n_tiles
        tl = jnp.where(live, jnp.clip(tl, 0, n_tiles - 1), 0)
        mine = (leaf_t[:, tl] == lf) & live[None, :, None]  # (K or 1, chunk, tile^2)
        mine = mine.reshape(kl, chunk * tp)
        s = jax.tree_util.tree_map(lambda a: a[lf], leaves["scaling"])
        y0, x0 = tl // tw * tile, tl % tw * tile
        z = jnp.concatenate([tiles_of(q, y0, x0) for q in parts], axis=-1).reshape(chunk * tp, ds)  # (N, Ds)
        zl = light_pos  # (K, 3)
        if clamp:
            z = jnp.clip(z, s["in_min"][rest][None, :], s["in_max"][rest][None, :])
            zl = jnp.clip(zl, s["in_min"][lc][None, :], s["in_max"][lc][None, :])
        zl = (zl - s["in_center"][lc][None, :]) / s["in_halfrange"][lc][None, :]
        w0 = layers[0]["w"][lf]
        # the input scaling folded into the first layer: W^T (z - c) / h = (W / h)^T z - (W / h)^T c
        w_rest = w0[rest] / s["in_halfrange"][rest][:, None]  # (Ds, H1)
        # (H1, N): the light-free part, once for all lights. The barrier keeps z's transpose a copy
        # of its own: fused into the product as a transposed operand, XLA's CPU dot ran at half the
        # rate (49 against 136 GFLOP/s for this 20 x 16 x 4096 product, 2026-12-02)
        h0 = w_rest.T @ jax.lax.optimization_barrier(z.T)
        bias = zl @ w0[lc] + layers[0]["b"][lf][None, :] - (s["in_center"][rest] @ w_rest)[None, :]  # (K, H1)

        def light_term(kk, y_sum):  # light kk's term of Eq. 9 on the chunk's pixels of this leaf
            h = _tanh(h0 + bias[kk][:, None])
            for i, layer in enumerate(layers[1:], start=1):
                h = layer["w"][lf].T @ h + layer["b"][lf][:, None]
                h = _tanh(h) if i < len(layers) - 1 else h
            y = h * s["out_halfrange"][:, None] + s["out_center"][:, None]
            y = jnp.maximum(y, 0.0) if nonnegative else y
            y = y * light_rgb[kk][:, None]
            return y_sum + (y if kl == 1 else jnp.where(mine[kk][None, :], y, 0.0))

        y_sum = jnp.zeros((n_out, chunk * tp), h0.dtype)
        for kk in range(k):  # Eq. 9's sum; where the trees split on the light: skip lights not in this leaf
            y_sum = light_term(kk, y_sum) if kl == 1 else jax.lax.cond(
                jnp.any(mine[kk]), functools.partial(light_term, kk), lambda v: v, y_sum)
        if kl == 1:  # one leaf for every light: the pixels of other leaves masked once
            y_sum = jnp.where(mine[0][None, :], y_sum, 0.0)
        # into each item's tile, one indexed add for the chunk (padding items add zeros to tile 0)
        return out.at[:, tl].add(y_sum.reshape(n_out, chunk, tp))

    out = jnp.zeros((n_out, n_tiles, tp), light_rgb.dtype)  # output planes, tile rows (no transpose per chunk)
    out = jax.lax.fori_loop(0, end[-1] // chunk, chunk_body, out)
    out = jnp.moveaxis(out.reshape(n_out, th, tw, tile, tile), 0, -1)  # (th, tw, tile, tile, R)
    out = jnp.swapaxes(out, 1, 2).reshape(th * tile, tw * tile, n_out)
    return out[:hh, :ww]


def raw_thresholds(params) -> np.ndarray:
    """Every kd-tree node's split value in the units of x (M,) float32: the normalised threshold
    t of its axis a mapped back through its object's box, lo_a + t (hi_a - lo_a) (``_unit``'s
    inverse, a constant axis's span taken as 1, as there); leaves keep their value. Comparing raw
    inputs against these is the traversal of normalised inputs up to float rounding at the
    boundary itself, without a per-sample division.

    Numerics: not differentiable (split values of a trained tree).
    """
    tree = kdtree.KDTree(*(np.asarray(a) for a in _tree(params)))
    owner = np.maximum(kdtree.node_objects(tree), 0)
    axis = np.maximum(tree.axis, 0)
    lo = np.asarray(params["obj_lo"], np.float64)[owner, axis]
    span = np.asarray(params["obj_hi"], np.float64)[owner, axis] - lo
    span = np.where(span > 1e-8, span, 1.0)
    return np.where(tree.axis >= 0, lo + np.asarray(tree.threshold, np.float64) * span,
                    tree.threshold).astype(np.float32)


def light_box(params) -> tuple[np.ndarray, np.ndarray]:
    """The light-position box the model was trained on (lo, hi).

    Numerics: not differentiable (the trained light box).
    """
    return np.asarray(params["light_lo"]), np.asarray(params["light_hi"])


class EditInputs(NamedTuple):
    """Evaluator inputs of a material-editing RRF (Appendix B).

    Fields:
      gbuffer: a ``jprt.inputs.GBuffer`` (H, W, ...).
      edit: (2,) roughness and albedo of the edited object.
    """

    gbuffer: GBuffer
    edit: Any


jax.export.register_namedtuple_serialization(EditInputs, serialized_name="jprt.methods.rrf.EditInputs")


def _render(params, gb: dict, light_pos, light_rgb, edit, *, attributes: str, material: bool,
            clamp: bool, render: dict):
    """Eq. 9 for every pixel of ``gb``: sum over lights k of c_k max(Phi(x_p, v, l_k, n, a), 0)
    (indirect radiance is never negative; the clamp is per light, so the image stays linear in
    the light colours)."""
    h, w = gb["object_id"].shape
    if clamp:
        light_pos = jnp.clip(light_pos, params["light_lo"][None, :], params["light_hi"][None, :])
    # the BRDF attributes stay three parts (``brdf_vector``'s columns in its order): XLA's CPU
    # concatenation along the minor axis of a 512^2 x 7 array alone took 3.7 ms of a 19 ms frame
    parts = {"position": [gb["position"]], "normal": [gb["normal"]],
             "view": [jnp.broadcast_to(edit, (h, w, 2)) if material else gb["view"]],
             "brdf": [gb["diffuse_albedo"], gb["specular_albedo"], gb["roughness"][..., None]]}
    names = ATTRIBUTE_SETS[attributes]
    light_cols = tuple(range(*_columns(attributes, "material" if material else "view")["light"]))
    # x of ``features`` without its light columns, as (H, W, c) parts: every pixel's own inputs
    shared = [jnp.asarray(q, jnp.float32) for n in names if n != "light" for q in parts[n]]
    obj = jnp.where(gb["valid"], gb["object_id"], -1)
    tile, chunk = render_layout(render)
    return _predict_tiles(params, shared, light_pos, light_rgb, obj, light_cols=light_cols, tile=tile,
                          chunk=chunk, clamp=bool(render["clamp_inputs"]),
                          nonnegative=bool(render["nonnegative"]))


#: G-buffer fields Eq. 9 reads, with their dtypes.
_GBUFFER_FIELDS = {"position": jnp.float32, "normal": jnp.float32, "view": jnp.float32,
                   "diffuse_albedo": jnp.float32, "specular_albedo": jnp.float32, "roughness": jnp.float32,
                   "object_id": jnp.int32, "valid": bool}


def _gbuffer_arrays(gb) -> dict:
    """The fields of ``gb`` that Eq. 9 reads, as JAX arrays of fixed dtypes (so a G-buffer from
    any source traces to the same program)."""
    return {name: jnp.asarray(getattr(gb, name), dtype) for name, dtype in _GBUFFER_FIELDS.items()}


def evaluator(params, config: dict | None = None):
    """The RRF renderer (Eq. 8, Eq. 9): ``evaluate(inputs, lights) -> (H, W, 3)`` indirect radiance.

    ``inputs`` is a ``jprt.inputs.GBuffer`` (H, W, ...) (an ``EditInputs`` for a material-editing
    model), ``lights`` a ``jprt.inputs.PointLights`` (K positions, K RGB intensities). Invalid
    pixels are 0. ``config["render"]``:

    * ``extrapolation``: lights outside the trained light box (grown by ``tolerance`` of its
      size): "error" raises ValueError (default), "clamp" moves them onto the box, "allow"
      evaluates anyway (RRFs extrapolate poorly, Ren et al. §7).
    * ``tile``, ``chunk``: the sort-free networks (``_predict_tiles``): ``tile`` x ``tile`` pixel
      tiles, ``chunk`` (leaf, tile) work items of one leaf per dense product; None: chosen for
      JAX's default backend (``render_layout``). The image does not depend on them.
    * ``clamp_inputs``: each leaf network sees its inputs clipped to the range of its training
      samples (a tanh network extrapolated outside it goes anywhere: the black line along the
      top edge of the tall box in ``make demo`` was its top face, which no training ray hit, so
      the normal's y was 0 in every training sample of that leaf and 1 there).
    * ``nonnegative``: max(Phi, 0) per light (indirect radiance is never negative).

    On concrete inputs the G-buffer and lights are checked first (``check_inputs``: empty
    G-buffer, NaN attributes at valid pixels, NaN lights, lights outside the box); under
    ``jax.jit`` / ``vmap`` the checks are skipped and NaN inputs give NaN pixels. The function is
    pure: it jits (one program per image size and light count), vmaps and exports.

    Numerics: not differentiable (builds the float32 run-time program: kd-tree traversal and per-leaf ``jprt.nn.mlp`` tanh networks, covered there; fitting is by LM on the networks).
    """
    cfg = _cfg(config)
    rc = cfg["render"]
    extrapolation = rc["extrapolation"]
    if extrapolation not in ("error", "clamp", "allow"):
        raise ValueError(f"render.extrapolation must be 'error', 'clamp' or 'allow', got {extrapolation!r}")
    material = cfg["data"]["mode"] == "material"
    params = jax.tree_util.tree_map(jnp.asarray, params)
    # params are constants of the program: kd-tree traversal unrolls over the tree's depth
    render = jax.jit(functools.partial(_render, params, attributes=cfg["model"]["attributes"], material=material,
                                       clamp=extrapolation == "clamp", render=rc))

    def evaluate(inputs, lights):
        if material != isinstance(inputs, EditInputs):
            raise TypeError("this RRF was trained for material editing: pass EditInputs(gbuffer, edit)" if material
                            else f"this RRF takes a GBuffer, got {type(inputs).__name__}")
        gb, edit = (inputs.gbuffer, inputs.edit) if material else (inputs, jnp.zeros((2,), jnp.float32))
        light_pos = jnp.asarray(lights.position, jnp.float32).reshape(-1, 3)
        light_rgb = jnp.asarray(lights.intensity, jnp.float32).reshape(-1, 3)
        if not isinstance(light_pos, jax.core.Tracer):
            check_inputs(params, gb, lights, extrapolation=extrapolation, tolerance=float(rc["tolerance"]))
        return render(_gbuffer_arrays(gb), light_pos, light_rgb, jnp.asarray(edit, jnp.float32).reshape(2))

    return evaluate


def frame_flops(params, config: dict | None, inputs, lights) -> float:
    """FLOPs one ``evaluator`` call needs (``Method.frame_flops``): per valid pixel of an object
    with networks, the light-free part of the first layer once per distinct leaf its lights reach
    (Eq. 9's sum shares it only between lights whose inputs fall in the same kd-tree cell: the
    trees split on the light position too) and, per light, the light part, the other layers and
    the colour weighting (2 per multiply-add, 1 per bias add); the input and output scaling and
    the tanh are not counted. What the networks must compute, not what the tiles execute (masked
    pixels of shared tiles, padding items).

    Numerics: not differentiable (a FLOP count).
    """
    cfg = _cfg(config)
    material = cfg["data"]["mode"] == "material"
    gb = inputs.gbuffer if material else inputs
    sizes = _sizes(params["leaves"]["layers"])
    roots = np.asarray(params["tree"]["roots"])
    obj = np.asarray(gb.object_id).reshape(-1)
    ok = np.asarray(gb.valid, bool).reshape(-1) & (obj >= 0) & (obj < roots.shape[0])
    ok &= roots[np.clip(obj, 0, roots.shape[0] - 1)] >= 0
    light_pos = np.asarray(lights.position, np.float32).reshape(-1, 3)
    k = light_pos.shape[0]
    idx = np.flatnonzero(ok)
    leaf = np.zeros((k, idx.size), np.int64)
    if idx.size:
        pixels = lambda a, c: np.asarray(a, np.float32).reshape(-1, c)[idx]  # noqa: E731 (the counted pixels)
        position, normal = pixels(gb.position, 3), pixels(gb.normal, 3)
        view = None if material else pixels(gb.view, 3)
        edit = np.broadcast_to(np.asarray(inputs.edit, np.float32), (idx.size, 2)) if material else None
        brdf = brdf_vector(pixels(gb.diffuse_albedo, 3), pixels(gb.specular_albedo, 3), pixels(gb.roughness, 1)[:, 0])
        tree = kdtree.KDTree(*(np.asarray(a) for a in _tree(params)))
        for kk in range(k):  # each light's leaf per pixel (the light is x's only per-light column)
            x = np.asarray(features(cfg["model"]["attributes"], position, view,
                                    np.broadcast_to(light_pos[kk], (idx.size, 3)), normal, brdf, edit))
            xn = _normalise(x, obj[idx], params["obj_lo"], params["obj_hi"])
            leaf[kk] = kdtree.traverse(tree, obj[idx], xn, xp=np)
    distinct = int(np.sum(1 + np.sum(np.diff(np.sort(leaf, axis=0), axis=0) != 0, axis=0))) if idx.size else 0
    shared = 2 * (sizes[0] - 3) * sizes[1]
    later = sum(2 * a * b + b for a, b in zip(sizes[1:-1], sizes[2:]))
    per_light = 2 * 3 * sizes[1] + 2 * sizes[1] + later + 2 * sizes[-1]
    return float(distinct * shared + idx.size * k * per_light)


def check_inputs(params, gbuffer, lights, *, extrapolation: str = "error", tolerance: float = 0.02) -> None:
    """Raise ValueError for an empty G-buffer, NaN attributes at valid pixels, no or NaN lights,
    or (``extrapolation="error"``) a light outside the trained box grown by ``tolerance``.

    Numerics: not differentiable (input validation).
    """
    light_pos = np.asarray(lights.position, np.float32).reshape(-1, 3)
    light_rgb = np.asarray(lights.intensity, np.float32).reshape(-1, 3)
    valid = np.asarray(gbuffer.valid, bool)
    if valid.ndim != 2 or valid.size == 0:
        raise ValueError(f"empty G-buffer (valid mask of shape {valid.shape}); need H x W > 0 pixels")
    if light_pos.shape[0] == 0:
        raise ValueError("need at least one light")
    if not (np.isfinite(light_pos).all() and np.isfinite(light_rgb).all()):
        raise ValueError("light positions or colours contain NaN or infinite values")
    for name in ("position", "view", "normal", "diffuse_albedo", "specular_albedo", "roughness"):
        a = np.asarray(getattr(gbuffer, name))
        bad = ~np.isfinite(a[valid])
        if bad.any():
            raise ValueError(f"G-buffer field {name!r} has {int(bad.reshape(bad.shape[0], -1).any(-1).sum())} "
                             f"valid pixel(s) with NaN or infinite values")
    if extrapolation == "error":
        lo, hi = light_box(params)
        margin = tolerance * (hi - lo)
        outside = np.any((light_pos < lo - margin) | (light_pos > hi + margin), axis=1)
        if outside.any():
            k = int(np.flatnonzero(outside)[0])
            raise ValueError(f"light {k} at {light_pos[k].tolist()} is outside the trained light box "
                             f"lo={lo.tolist()} hi={hi.tolist()}; RRFs do not extrapolate "
                             f"(set render.extrapolation to 'clamp' or 'allow')")


def example(data: RRFData, config: dict | None = None):
    """A held-out (inputs, lights) pair from ``data``: the validation samples' attributes laid
    out as an 8 x 8 G-buffer, lit by two lights inside the trained box (the contract tests).

    Numerics: not differentiable (a held-out input and lighting from a dataset).
    """
    cfg = _cfg(config)
    is_train = split_samples(len(data), float(cfg["data"]["val_fraction"]), int(cfg["train"]["seed"]))
    idx = np.flatnonzero(~is_train)
    idx = np.resize(idx if len(idx) else np.arange(len(data)), 64)
    grid = lambda a: np.asarray(a)[idx].reshape((8, 8) + np.shape(a)[1:])  # noqa: E731
    brdf = grid(data.brdf)
    gb = GBuffer(position=grid(data.position), normal=grid(data.normal), view=grid(data.view),
                 reflected=np.zeros((8, 8, 3), np.float32), uv=np.zeros((8, 8, 2), np.float32),
                 diffuse_albedo=brdf[..., 0:3], specular_albedo=brdf[..., 3:6], roughness=brdf[..., 6],
                 object_id=grid(data.object_id), valid=np.ones((8, 8), bool))
    lo, hi = np.asarray(data.meta["light_lo"], np.float32), np.asarray(data.meta["light_hi"], np.float32)
    lights = PointLights(position=np.stack([lo + 0.3 * (hi - lo), lo + 0.7 * (hi - lo)]).astype(np.float32),
                         intensity=np.asarray([[1.0, 0.8, 0.6], [0.3, 0.5, 1.0]], np.float32))
    if cfg["data"]["mode"] == "material":
        return EditInputs(gb, np.asarray(grid(data.edit)[0, 0], np.float32)), lights
    return gb, lights


# --------------------------------------------------------------------------------------------
# Robustness (Table 3): refit the leaves of a fixed tree


def refit_leaves(params, data: RRFData, config: dict | None, info: dict, variants: list[dict]):
    """Refit every leaf of ``params``'s kd-tree for several variants in one batched LM solve.

    Each variant is {"seed": int, "subset": float}: fresh random weights from ``seed`` and a
    random ``subset`` fraction of each leaf's training samples. The tree stays fixed (Table 3
    measures the spread due to the data subset and the initial weights). Returns a list of params.

    Numerics: not differentiable (a fitting or training procedure).
    """
    cfg = _cfg(config)
    x = data_features(data, cfg["model"]["attributes"])
    y, object_id = data.indirect, data.object_id
    xn = _normalise(x, object_id, params["obj_lo"], params["obj_hi"])
    objs, lo, hi = kdtree.leaf_cells(_tree(params))
    sizes = (x.shape[1], *cfg["model"]["hidden"], y.shape[1])
    problems = []
    for v in variants:
        rng = np.random.default_rng(int(v["seed"]) + 101)
        for i in range(len(objs)):
            p = _leaf_problem(xn, object_id, info["is_train"], objs[i], lo[i], hi[i], float(cfg["tree"]["expand"]))
            train = p.train
            if float(v.get("subset", 1.0)) < 1.0:
                train = np.sort(rng.permutation(train)[: max(1, int(round(v["subset"] * len(train))))])
            problems.append(kdtree.Problem(train, p.val, None))
    fitter = _NodeFitter(x, y, sizes, cfg, sum(int(v["seed"]) * 7919 for v in variants), lambda m: None)
    fits = fitter(problems, int(cfg["train"]["max_iters"]))
    out = []
    n = len(objs)
    for j in range(len(variants)):
        payloads = [f.payload for f in fits[j * n:(j + 1) * n]]
        new = dict(params)
        new["leaves"] = jax.tree_util.tree_map(lambda *a: jnp.asarray(np.stack([np.asarray(v) for v in a])),
                                               *payloads)
        out.append(new)
    return out


def parameter_count(params) -> int:
    """Trainable weights over all leaves.

    Numerics: not differentiable (an integer count).
    """
    return int(sum(np.asarray(leaf).size for leaf in jax.tree_util.tree_leaves(params["leaves"]["layers"])))
