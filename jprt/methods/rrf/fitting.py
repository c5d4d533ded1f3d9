"""Fitting Radiance Regression Functions (Ren, Wang, Gong, Lin, Tong, Guo 2013, §4, Appendix A).

Each kd-tree node's network Phi_N (Eq. 8: a tanh MLP, two hidden layers) is fitted to its
samples' indirect radiance by Levenberg–Marquardt on the squared error of Eq. 6 / Eq. 10, its
inputs and outputs scaled to [-1, 1] by their ranges (Appendix A, Beale et al.'s mapminmax).
The error-driven kd-tree of §4 (``jprt.methods.rrf.kdtree``) asks for many node fits at once;
``_NodeFitter`` answers each request with one batched LM solve per padded sample count
(``jprt.solve.lm.solve_batched``), early-stopped on each node's validation samples (Beale et
al.'s trainlm, which Appendix A follows).

``fit_partitioned`` is the fit of ``model.fit_arrays`` on a resolved config; a fit with a
``checkpoint_dir`` saves each batch of node fits as it finishes and reads them back on a rerun
(``_checkpointed``). ``refit_leaf_networks`` refits the leaves of a fixed tree (Table 3).

The fitted params (``_pack``): the kd-tree's arrays, each object's input box, and the leaf
networks stacked along a leading axis, each with its scaling; ``network``, ``layer_sizes`` and
``tree_of`` read them back for the renderer.
"""

from __future__ import annotations

import functools
import hashlib
import math
import os
import time
import warnings

import jax
import jax.numpy as jnp
import numpy as np

from jprt.hashing import stable_hash
from jprt.methods.base import FitResult
from jprt.methods.rrf import kdtree
from jprt.methods.rrf.features import normalise, split_dims
from jprt.nn.mlp import MLP, constant_up_to_rounding, mlp, ranges
from jprt.progress import say as progress_say
from jprt.solve.lm import LMSettings, solve_batched

__all__ = ["network", "layer_sizes", "tree_of", "relative_error", "split_samples", "fit_partitioned",
           "refit_leaf_networks"]


@functools.lru_cache(maxsize=None)
def network(sizes: tuple) -> MLP:
    """Phi_N of Eq. 8: the tanh MLP family of layer ``sizes`` (``jprt.nn.mlp``), with Appendix A's
    [-1, 1] scaling (the node payload is exactly its params) and uniform [-1, 1] initial weights.

    Numerics: not differentiable (builds a network family; ``jprt.nn.mlp`` covers its apply).
    """
    return mlp(sizes, activation="tanh", init="rrf")


def layer_sizes(layers) -> tuple:
    """Layer sizes of a network's layers (stacked leaf networks too: the last two axes of w).

    Numerics: not differentiable (integer sizes).
    """
    return (int(np.shape(layers[0]["w"])[-2]),) + tuple(int(np.shape(layer["w"])[-1]) for layer in layers)


@functools.lru_cache(maxsize=None)
def _jitted_apply(sizes: tuple):
    return jax.jit(network(sizes).apply)


def _phi(payload, x) -> np.ndarray:
    """Phi_N(x) of one node (payload = its MLP params) for samples x (N, D), on the host: the
    jitted ``jprt.nn.mlp`` apply on rows padded to a few bucket sizes (few compiled shapes)."""
    n = len(x)
    xp = np.zeros((_bucket(n, 64), np.shape(x)[1]), np.float32)
    xp[:n] = x
    return np.asarray(_jitted_apply(layer_sizes(payload["layers"]))(payload, xp))[:n]


@functools.lru_cache(maxsize=None)
def _residual_fn(sizes: tuple):
    """Eq. 6 residual of one sample in the node's scaled space, Phi_N(x) - y, for the LM solver
    (the parameters are the layers; the scaling is the identity there)."""
    net = network(sizes)
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
            return relative_error(_phi(problem.init, self.x[idx]), self.y[idx])

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
                layers = network(self.sizes).init(self.rng)["layers"]  # uniform [-1, 1], on the host
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
            train_err = relative_error(_phi(payload, self.x[p.train]), self.y[p.train])
            val_err = train_err
            if len(p.val):
                val_err = relative_error(_phi(payload, self.x[p.val]), self.y[p.val])
            fits.append(kdtree.NodeFit(payload, train_err, val_err))
        return fits


def relative_error(pred, ref) -> float:
    """sqrt(sum ||pred - ref||^2 / sum ||ref||^2) (§4: the 5 % relative error).

    Numerics: not differentiable (a host-side error measure of the kd-tree build).
    """
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


def fit_partitioned(x, y, object_id, cfg: dict, *, is_train=None, checkpoint_dir: str | None = None,
                    progress: bool | None = None) -> FitResult:
    """``model.fit_arrays`` on a resolved config ``cfg`` (every key of ``model.DEFAULT_CONFIG``):
    the per-object input boxes, the kd-tree of §4 grown by batched LM node fits, the packed
    params and the per-leaf errors. Returns ``FitResult(params, info)``; ``params`` has no light
    box. ``is_train``, ``checkpoint_dir`` and ``progress``: see ``model.fit_arrays``.

    Numerics: not differentiable (a fitting or training procedure).
    """
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
    # ``unit`` keeps it at x - lo ~ 1e-7 instead of stretching its rounding to [0, 1]: the tree
    # split the floor, the ceiling and both side walls at their root on that noise (two leaves per
    # wall, each fitted on a random half of its samples, alternating pixel by pixel in a frame)
    obj_hi = np.where(constant_up_to_rounding(obj_lo, obj_hi), obj_lo, obj_hi)
    xn = normalise(x, object_id, obj_lo, obj_hi)

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


def _pack(tree: kdtree.KDTree, obj_lo, obj_hi, payloads) -> dict:
    """The fitted params: the kd-tree's arrays, each object's input box and the leaf payloads
    stacked along a leading leaf axis (float32)."""
    stack = lambda *a: jnp.asarray(np.stack([np.asarray(v) for v in a]), jnp.float32)  # noqa: E731
    leaves = jax.tree_util.tree_map(stack, *payloads)
    return {"tree": {k: jnp.asarray(v) for k, v in tree._asdict().items()},
            "obj_lo": jnp.asarray(obj_lo), "obj_hi": jnp.asarray(obj_hi), "leaves": leaves}


def tree_of(params) -> kdtree.KDTree:
    """The kd-tree of fitted ``params`` (its arrays as stored, NumPy or JAX).

    Numerics: not differentiable (integer tree arrays and split values).
    """
    return kdtree.KDTree(**params["tree"])


def _leaf_errors(params, xn, x, y, object_id, is_train):
    """Per-leaf relative errors on the samples routed to each leaf (training / validation)."""
    tree = kdtree.KDTree(*(np.asarray(a) for a in tree_of(params)))
    leaf = kdtree.traverse(tree, object_id, xn, xp=np)
    leaves = jax.tree_util.tree_map(np.asarray, params["leaves"])
    n_leaves = leaves["layers"][0]["w"].shape[0]
    tr, va = np.full(n_leaves, np.nan), np.full(n_leaves, np.nan)
    for i in range(n_leaves):
        payload = jax.tree_util.tree_map(lambda v: v[i], leaves)
        for out, sel in ((tr, (leaf == i) & is_train), (va, (leaf == i) & ~is_train)):
            if sel.any():
                out[i] = relative_error(_phi(payload, x[sel]), y[sel])
    return tr, va


def refit_leaf_networks(params, x, y, object_id, is_train, cfg: dict, variants: list[dict]) -> list:
    """Refit every leaf network of ``params``'s kd-tree to samples x (N, D), y (N, R) of objects
    ``object_id`` for several variants in one batched LM solve (``model.refit_leaves`` on a
    resolved config ``cfg``; ``is_train`` the fit's training mask).

    Each variant is {"seed": int, "subset": float}: fresh random weights from ``seed`` and a
    random ``subset`` fraction of each leaf's training samples; the tree stays fixed. Returns a
    list of params, one per variant.

    Numerics: not differentiable (a fitting or training procedure).
    """
    xn = normalise(x, object_id, params["obj_lo"], params["obj_hi"])
    objs, lo, hi = kdtree.leaf_cells(tree_of(params))
    sizes = (x.shape[1], *cfg["model"]["hidden"], y.shape[1])
    problems = []
    for v in variants:
        rng = np.random.default_rng(int(v["seed"]) + 101)
        for i in range(len(objs)):
            p = _leaf_problem(xn, object_id, is_train, objs[i], lo[i], hi[i], float(cfg["tree"]["expand"]))
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

