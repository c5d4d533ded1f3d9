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
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jprt import eval as jeval
from jprt.inputs import GBuffer, PointLights
from jprt.methods.base import FitResult, resolve
from jprt.methods.rrf import fitting, kdtree, renderer
from jprt.methods.rrf.features import (ATTRIBUTE_SETS, RRFData, brdf_vector, data_features, features, input_size,
                                       normalise, split_dims)
from jprt.methods.rrf.fitting import layer_sizes, split_samples, tree_of
from jprt.methods.rrf.renderer import RENDER_LAYOUTS, raw_thresholds, render_layout

__all__ = ["DEFAULT_CONFIG", "gradient_evaluator", "ATTRIBUTE_SETS", "RRFData", "EditInputs", "features", "brdf_vector", "data_features",
           "split_samples", "split_dims", "input_size", "fit", "fit_arrays", "evaluator", "frame_flops", "frame_work",
           "network_flops", "network_rate_gflops", "frame_roofline", "check_inputs", "example",
           "refit_leaves", "parameter_count", "light_box", "raw_thresholds", "RENDER_LAYOUTS", "render_layout"]

DEFAULT_CONFIG: dict = {
    # the scene rendered for training: a built-in name (jprt.render.scenes) or a file, with its options
    "scene": {"name": "cornell_box", "area_light": False},
    "data": {
        "mode": "view",  # "view" (x_p, v, l, ...) or "material" (Appendix B: v replaced by an edit)
        # sampling regions of lights and views, world-space boxes [x, y, z]; None: from the scene
        # (data.scene_regions: the built-in boxes' tuned regions, else the scene's bounds and free space)
        "light_lo": None,
        "light_hi": None,
        "view_lo": None,
        "view_hi": None,
        "view_target": None,  # the point every training camera looks at (world units; None: from the scene)
        "target_jitter": 0.15,  # each camera's target moved by up to this much per axis (world units, uniform)
        "fov": None,  # camera field of view in degrees; None: from the scene, as the regions above
        "n_lights": 20,  # N_l training light positions (Latin hypercube in the light box; see light_spread)
        # how training lights fill a light box that comes from a scene file's bounds: "latin" (the
        # Latin hypercube, each light off geometry drawn again at random) or "even"
        # (``sampling.even_lights``: k-means centres over the free space that lights the file's
        # view, fewer gaps; what it was measured to do: docs/own-scene.md); where
        # the config sets every region key (and for the built-in scenes' tuned boxes) the lights
        # are the Latin hypercube as it is
        "light_spread": "latin",
        "n_views": 20,  # N_v training viewpoints (Latin hypercube in the view box)
        "n_rays": 100,  # N_r primary rays (samples) per (light, view) pair
        # > 1: n_rays drawn from oversample x n_rays screen rays, balanced over the surfaces they hit
        # (data.py): for small budgets, where uniform rays miss faces seen at grazing angles
        "oversample": 1,
        # at least this many of each view-light pair's rays on every object the candidate rays hit
        # (drawn first; 0: none), so small objects get samples that uniform rays may all miss
        "min_object_rays": 0,
        # at least this many of each view-light pair's rays on every face (object x signed dominant
        # normal axis) that 16 x n_rays candidate screen rays hit, drawn first, the rest uniform
        # (0: none): a face seen only at grazing angles (the tall box's top) gets samples
        "min_face_rays": 0,
        "spp": 512,  # path-traced samples per training ray (the indirect radiance's Monte Carlo budget)
        "seed": 0,  # seed of the light, view and ray draws and of the renders
        "val_fraction": 0.3,  # fraction of the samples held out for validation (Appendix A: 70/30)
        # held-out point lights (their own seed stream, never fitted) rendered from every view (or
        # material) at n_rays / 2 rays each for the self-check (data.self_check; at the defaults
        # 5 % of the training render; 0: none). Not part of the training data's cache key
        "check_lights": 2,
        # material mode (Appendix B): the edited object, its GGX roughness and albedo ranges,
        # n_materials edits by Latin hypercube, all seen from view_origin (world units)
        "material": {"object": "floor", "roughness": [0.05, 0.5], "albedo": [0.1, 0.8], "n_materials": 8,
                     "view_origin": [0.0, 0.0, 3.9]},
    },
    # hidden: the widths of Phi's tanh hidden layers (Eq. 8: 20 and 10); attributes: Phi's inputs,
    # an ATTRIBUTE_SETS name (Fig. 3)
    "model": {"hidden": [20, 10], "attributes": "augmented"},
    "tree": {
        "threshold": 0.05,  # a node splits while its training or validation relative error exceeds this (§4: 5 %)
        "axis": "all",  # split axis: "all" (try every axis, keep the best pair of children) or "random"
        "expand": 0.1,  # a node trains on its cell grown by this fraction of its width (half per side)
        "max_depth": 6,  # splits from an object's root to a leaf, at most
        "min_samples": 1500,  # training samples each child of a split needs, at least
        "max_leaves": 64,  # leaves over all objects, at most
        "group_below": 32,  # objects with fewer training samples share one tree
        # the attributes (ATTRIBUTE_SETS names) whose axes a node may split; None, every axis, is
        # the paper's. Without "light" every leaf serves every light, so a frame's lights share each
        # pixel's traversal and the light-free part of the first layer (experiments/rrf_cornell.py's
        # `small` config bars it; docs/methods/rrf.md has its measured cost and accuracy)
        "split_on": None,
    },
    "train": {
        "max_iters": 40,  # LM iterations per node fit (a chosen candidate's trial iterations count towards them)
        "trial_iters": 10,  # LM iterations of each candidate pair when every axis is tried (tree.axis "all")
        "trial_samples": 1024,  # candidates are compared on at most this many of their training samples (0: all)
        "max_fail": 6,  # accepted LM steps without a better validation error before a fit stops (0: no early stop)
        "rtol": 1e-6,  # an LM fit stops when an accepted step lowers the squared error by less than this fraction
        "damping": 1e-3,  # initial LM damping mu, relative to diag(J^T J)
        "chunk_size": 1024,  # samples per Jacobian chunk (memory, not results)
        "seed": 0,  # seed of the initial weights, the 70/30 split and the subsets
        "subset": 1.0,  # fraction of the training samples kept (Table 3, Fig. 6)
        # the fit's messages on stderr; None follows jprt.progress (JPRT_PROGRESS, else whether
        # stderr is a terminal), as every fit does; fit's progress= argument wins over it
        "progress": None,
    },
    "render": {
        # lights outside the trained box (grown by `tolerance` of its size per axis): "error"
        # raises, "clamp" moves them onto the box, "allow" evaluates anyway
        "extrapolation": "error",
        "tolerance": 0.02,
        # the renderer's pixel tiles (tile x tile pixels) and (leaf, tile) items per dense product;
        # None: by JAX's default backend (``RENDER_LAYOUTS``). The image does not depend on them
        "tile": None,
        "chunk": None,
        "clamp_inputs": True,  # each leaf network's inputs clipped to the range of its training samples
        "nonnegative": True,  # max(Phi, 0) per light (indirect radiance is never negative)
    },
}


def _cfg(config: dict | None) -> dict:
    """``DEFAULT_CONFIG`` merged strictly with ``config`` (an unknown key raises ConfigError)."""
    return resolve(DEFAULT_CONFIG, config)


# --------------------------------------------------------------------------------------------
# Fitting (Eq. 6, Eq. 10, §4; ``jprt.methods.rrf.fitting``)


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
    return fitting.fit_partitioned(x, y, object_id, _cfg(config), is_train=is_train, checkpoint_dir=checkpoint_dir,
                                   progress=progress)


def refit_leaves(params, data: RRFData, config: dict | None, info: dict, variants: list[dict]):
    """Refit every leaf of ``params``'s kd-tree for several variants in one batched LM solve.

    Each variant is {"seed": int, "subset": float}: fresh random weights from ``seed`` and a
    random ``subset`` fraction of each leaf's training samples. The tree stays fixed (Table 3
    measures the spread due to the data subset and the initial weights). Returns a list of params.

    Numerics: not differentiable (a fitting or training procedure).
    """
    cfg = _cfg(config)
    x = data_features(data, cfg["model"]["attributes"])
    return fitting.refit_leaf_networks(params, x, data.indirect, data.object_id, info["is_train"], cfg, variants)


# --------------------------------------------------------------------------------------------
# Evaluation (Eq. 8, Eq. 9; ``jprt.methods.rrf.renderer``)


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


def evaluator(params, config: dict | None = None):
    """The RRF renderer (Eq. 8, Eq. 9): ``evaluate(inputs, lights) -> (H, W, 3)`` indirect radiance.

    ``inputs`` is a ``jprt.inputs.GBuffer`` (H, W, ...) (an ``EditInputs`` for a material-editing
    model), ``lights`` a ``jprt.inputs.PointLights`` (K positions, K RGB intensities). Invalid
    pixels are 0. ``config["render"]``:

    * ``extrapolation``: lights outside the trained light box (grown by ``tolerance`` of its
      size): "error" raises ValueError (default), "clamp" moves them onto the box, "allow"
      evaluates anyway (RRFs extrapolate poorly, Ren et al. §7).
    * ``tile``, ``chunk``: the sort-free networks (``renderer.render_frame``): ``tile`` x ``tile`` pixel
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
    return _evaluator(params, config, renderer.render_frame)


def gradient_evaluator(params, config: dict | None = None):
    """``evaluator``'s function (same arguments, checks and image) by ``renderer.render_dense``,
    which reverse-mode differentiation goes through (``Method.gradient_evaluator``): for
    ``jax.grad`` of an objective of the image in the lights (``jprt.design``). A few times slower
    per frame than ``evaluator``, which is for display.

    The image is differentiable in the lights' positions and intensities, in reverse and forward
    mode (a pixel's kd-tree leaf is piecewise constant in the light; its gradient is stopped).

    Numerics: not differentiable (builds the float32 program; its gradient is checked against forward mode and a central difference in tests/methods/test_rrf.py).
    """
    return _evaluator(params, config, renderer.render_dense)


def _evaluator(params, config: dict | None, frame: Callable):
    """``evaluator`` with the frame program ``frame`` (``renderer.render_frame`` or ``render_dense``)."""
    cfg = _cfg(config)
    rc = cfg["render"]
    extrapolation = rc["extrapolation"]
    if extrapolation not in ("error", "clamp", "allow"):
        raise ValueError(f"render.extrapolation must be 'error', 'clamp' or 'allow', got {extrapolation!r}")
    material = cfg["data"]["mode"] == "material"
    params = jax.tree_util.tree_map(jnp.asarray, params)
    # params are constants of the program: kd-tree traversal unrolls over the tree's depth
    render = jax.jit(functools.partial(frame, params, attributes=cfg["model"]["attributes"],
                                       material=material, clamp=extrapolation == "clamp", render=rc))

    def evaluate(inputs, lights):
        if material != isinstance(inputs, EditInputs):
            raise TypeError("this RRF was trained for material editing: pass EditInputs(gbuffer, edit)" if material
                            else f"this RRF takes a GBuffer, got {type(inputs).__name__}")
        gb, edit = (inputs.gbuffer, inputs.edit) if material else (inputs, jnp.zeros((2,), jnp.float32))
        light_pos = jnp.asarray(lights.position, jnp.float32).reshape(-1, 3)
        light_rgb = jnp.asarray(lights.intensity, jnp.float32).reshape(-1, 3)
        if not isinstance(light_pos, jax.core.Tracer):
            check_inputs(params, gb, lights, extrapolation=extrapolation, tolerance=float(rc["tolerance"]))
        return render(renderer.gbuffer_arrays(gb), light_pos, light_rgb, jnp.asarray(edit, jnp.float32).reshape(2))

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
    sizes = layer_sizes(params["leaves"]["layers"])
    _, leaf, k = _pixel_leaves(params, config, inputs, lights)
    distinct = _distinct_leaves(leaf)
    shared, per_light = network_flops(sizes)
    return float(distinct * shared + leaf.shape[1] * k * per_light)


def network_flops(sizes) -> tuple[int, int]:
    """FLOPs of one pixel's network of layer ``sizes`` (``frame_flops``'s count): the light-free
    part of the first layer, and what each light adds (its part of the first layer, the other
    layers, the colour).

    Numerics: not differentiable (a count).
    """
    shared = 2 * (sizes[0] - 3) * sizes[1]
    later = sum(2 * a * b + b for a, b in zip(sizes[1:-1], sizes[2:]))
    return shared, 2 * 3 * sizes[1] + 2 * sizes[1] + later + 2 * sizes[-1]


def _distinct_leaves(leaf) -> int:
    """The (pixel, distinct leaf) pairs of a (K, pixels) leaf array: each pixel's first layer runs
    once per distinct leaf its lights reach."""
    return int(np.sum(1 + np.sum(np.diff(np.sort(leaf, axis=0), axis=0) != 0, axis=0))) if leaf.size else 0


def _pixel_leaves(params, config: dict | None, inputs, lights):
    """The pixels with networks, flat indices into the (H, W) image, and each one's kd-tree leaf
    under each light, (K, pixels); and K."""
    cfg = _cfg(config)
    material = cfg["data"]["mode"] == "material"
    gb = inputs.gbuffer if material else inputs
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
        tree = kdtree.KDTree(*(np.asarray(a) for a in tree_of(params)))
        for kk in range(k):  # each light's leaf per pixel (the light is x's only per-light column)
            x = np.asarray(features(cfg["model"]["attributes"], position, view,
                                    np.broadcast_to(light_pos[kk], (idx.size, 3)), normal, brdf, edit))
            xn = normalise(x, obj[idx], params["obj_lo"], params["obj_hi"])
            leaf[kk] = kdtree.traverse(tree, obj[idx], xn, xp=np)
    return idx, leaf, k


def frame_work(params, config: dict | None, inputs, lights) -> dict:
    """What one ``evaluator`` call executes (``renderer.render_frame``'s tiled layout), beside what
    it needs (``frame_flops``): every (leaf, tile) pair some pixel needs is a work item of
    tile^2 pixel slots, each leaf's items padded to whole chunks, and every slot of an item runs
    its leaf's network (masked afterwards). Returns {"useful_flops" (``frame_flops``),
    "executed_flops" (slots x the network's FLOPs, every light counted on every slot: exact for
    one light or trees that do not split on the light, an upper bound otherwise), "pixels" (with
    networks), "items", "slots", "occupancy" (pixel-leaf evaluations needed / slots), "tile",
    "chunk", "bytes" (a stated model of the memory traffic: the G-buffer's fields read once, each
    slot's inputs gathered and its output added into the image planes, read and written; the
    networks' weights, a few kB per leaf, stay in cache)}.

    Numerics: not differentiable (a count).
    """
    cfg = _cfg(config)
    material = cfg["data"]["mode"] == "material"
    gb = inputs.gbuffer if material else inputs
    h, w = np.asarray(gb.object_id).shape
    tile, chunk = renderer.render_layout(cfg["render"])
    sizes = layer_sizes(params["leaves"]["layers"])
    n_leaves = int(np.asarray(params["leaves"]["layers"][0]["w"]).shape[0])
    idx, leaf, k = _pixel_leaves(params, config, inputs, lights)
    tw = -(-w // tile)
    n_tiles = -(-h // tile) * tw
    tiles = (idx // w) // tile * tw + (idx % w) // tile
    pairs = np.unique((leaf * n_tiles + tiles[None, :]).reshape(-1))  # (leaf, tile) items
    count = np.bincount(pairs // n_tiles, minlength=n_leaves)
    items = int(count.sum())
    slots = int(np.sum(-(-count // chunk) * chunk)) * tile * tile
    shared, per_light = network_flops(sizes)
    needed = _distinct_leaves(leaf)
    inputs_per_pixel = sizes[0] - 3  # x's columns but the light's, float32
    fields = 4 * (3 + 3 + 3 + 3 + 3 + 1 + 1) + 1  # GBUFFER_FIELDS: six float vectors / scalars, id, valid
    moved = h * w * fields + slots * 4 * (inputs_per_pixel + 2 * sizes[-1]) + h * w * 4 * sizes[-1]
    return {"useful_flops": float(needed * shared + leaf.shape[1] * k * per_light),  # frame_flops, one traversal
            "executed_flops": float(slots * (shared + k * per_light)), "pixels": int(idx.size), "items": items,
            "slots": slots, "occupancy": needed / slots if slots else None, "tile": tile, "chunk": chunk,
            "bytes": float(moved)}


def network_rate_gflops(params, config: dict | None, slots: int, repeats: int = 10) -> float:
    """The rate (GFLOP/s, ``model.frame_flops``'s count) at which this process runs the evaluator's
    networks by themselves: leaf 0's network, as the tiled renderer applies it (features x pixels
    products of ``chunk`` x tile^2 columns, the rational tanh, one light), over ``slots`` pixel
    slots (16 chunks at least) in a loop of chunks, without the tiles' gathers, masks and indexed
    adds. What the frame's products would attain if they were all it did: RRF's compute roof
    (``frame_work``).

    Numerics: not differentiable (a timing).
    """
    tile, chunk = renderer.render_layout(_cfg(config)["render"])
    n = chunk * tile * tile
    layers = [{"w": jnp.asarray(layer["w"][0]), "b": jnp.asarray(layer["b"][0])}
              for layer in params["leaves"]["layers"]]
    sizes = layer_sizes(params["leaves"]["layers"])
    steps = max(16, -(-int(slots) // n))  # at least 16 chunks: the products' rate, not one call's overhead
    z = jnp.asarray(np.random.default_rng(0).uniform(-1, 1, (sizes[0] - 3, n)), jnp.float32)

    @jax.jit
    def run(layers, z):
        def body(i, acc):
            # acc enters the product's operand, so XLA cannot hoist the product out of the loop
            h = layers[0]["w"][:-3].T @ (z + acc[:1, :1] * 0.0) + layers[0]["b"][:, None]
            h = renderer.rational_tanh(h)
            for j, layer in enumerate(layers[1:], start=1):
                h = layer["w"].T @ h + layer["b"][:, None]
                h = renderer.rational_tanh(h) if j < len(layers) - 1 else h
            return acc + h
        return jax.lax.fori_loop(0, steps, body, jnp.zeros((sizes[-1], n), jnp.float32))

    ms = jeval.time_call(run, layers, z, repeats=repeats)["median_ms"]
    shared, per_light = network_flops(sizes)
    return steps * n * (shared + per_light) / (ms * 1e-3) / 1e9


def frame_roofline(params, config: dict | None, inputs, lights, frame_ms: float, *, repeats: int = 10,
                   bandwidth_gbs: float | None = None) -> dict:
    """RRF's frame against what bounds it (``Method.frame_roofline``): its networks' products.
    ``frame_work`` counts what the tiled frame executes; ``network_rate_gflops`` measures, in this
    process, the rate of those products by themselves; the roofline (``jprt.eval.roofline_of``)
    takes that rate as its compute roof, the executed FLOPs and the work's stated byte model
    (``bandwidth_gbs``: the triad's, measured now unless given). Returns {"roofline" (its "roof"
    is "networks": ``matmul_gflops`` there is the networks' rate, ``frame_flops`` the executed
    FLOPs), "detail": {"work", "network_gflops", "useful_over_executed"}, "frame_flops"}: the
    share of the executed network work the image needs (``frame_flops`` / executed; masked slots
    of shared tiles and padding items are the rest), and ``frame_flops``' count (the work's
    "useful_flops", from the same traversal).

    Numerics: not differentiable (a timing).
    """
    work = frame_work(params, config, inputs, lights)
    rate = network_rate_gflops(params, config, work["slots"], repeats=repeats)
    roof = jeval.roofline_of(work["executed_flops"], work["bytes"], frame_ms=frame_ms, peak_gflops=rate,
                             bandwidth_gbs=bandwidth_gbs)["roofline"]
    roof["roof"] = "networks"  # matmul_gflops is network_gflops, frame_flops the executed FLOPs
    return {"roofline": roof, "frame_flops": work["useful_flops"],
            "detail": {"work": work, "network_gflops": rate,
                       "useful_over_executed": work["useful_flops"] / work["executed_flops"]
                       if work["executed_flops"] else None}}


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


def parameter_count(params) -> int:
    """Trainable weights over all leaves.

    Numerics: not differentiable (an integer count).
    """
    return int(sum(np.asarray(leaf).size for leaf in jax.tree_util.tree_leaves(params["leaves"]["layers"])))
