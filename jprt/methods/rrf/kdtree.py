"""Error-driven kd-trees over an object's input box (Ren et al. 2013, §4 "Partitioning").

One kd-tree per object over its input space, normalised to the unit hypercube [0, 1]^D. Every
internal node splits its box *through the middle* of one axis (hyperplane x_axis = midpoint; the
left child is x_axis < midpoint, the right child x_axis >= midpoint). A node is fitted on the
training samples of its box expanded by ``expand`` (10 %) per dimension (Fig. 4 b: half on each
side), and split only while its training or validation (prediction) relative error exceeds
``threshold`` (5 %). The split axis is the one whose two fitted children have the smallest errors
(every axis tried, the paper's default) or a random one (``axis="random"``, ~10 % worse in the
paper), among all D axes or only those named by ``dims``. Guards: ``max_depth``, ``min_samples``
training samples per child, ``max_leaves`` in all
(the budget goes to the worst nodes that *can* split: a node whose children would be too small is
passed over, not counted against the budget). Objects with fewer than ``group_below`` training
samples (small or distant objects that the sampled rays barely reach) share one tree fitted on
their samples pooled, rather than each failing on a handful; an object with none at all, and no
group to join, has no tree (its pixels predict 0) and is named in the report.

The builder is generic: it knows boxes and sample indices, and asks a ``fit_nodes`` callback to
fit many nodes at once (the RRF trains them with the vmapped Levenberg–Marquardt solver). The
result is a flat array form (``KDTree``) whose traversal is a fixed number of vectorised gathers
(``traverse``), jit-able and exportable, with no Python loop over samples or nodes.
"""

from __future__ import annotations

from typing import Any, Callable, NamedTuple, Sequence

import jax.numpy as jnp
import numpy as np

__all__ = ["KDTree", "Problem", "NodeFit", "BuildReport", "build", "traverse", "brute_force_lookup", "node_objects",
           "leaf_cells", "leaf_stats", "node_samples", "cell_members"]


class KDTree(NamedTuple):
    """All objects' kd-trees as flat arrays (M nodes, O objects, D input dimensions).

    Fields:
      axis:      (M,) int32 split axis, -1 at leaves.
      threshold: (M,) float32 split value (normalised coordinates).
      left:      (M,) int32 child for x[axis] < threshold (self at leaves).
      right:     (M,) int32 child for x[axis] >= threshold (self at leaves).
      leaf:      (M,) int32 leaf index at leaves, -1 at internal nodes.
      roots:     (O,) int32 root node of each object, -1 for objects without a tree.
      cell_lo:   (M, D) float32 lower corner of the node's cell (-inf at the root's sides).
      cell_hi:   (M, D) float32 upper corner (+inf at the root's sides).
      depth:     (M,) int32 node depth (root 0).
    """

    axis: Any
    threshold: Any
    left: Any
    right: Any
    leaf: Any
    roots: Any
    cell_lo: Any
    cell_hi: Any
    depth: Any

    @property
    def n_leaves(self) -> int:
        """Leaves of all objects' trees together."""
        return int(np.sum(np.asarray(self.leaf) >= 0))

    @property
    def max_depth(self) -> int:
        """The deepest leaf's depth (0: a root that is a leaf)."""
        return int(np.max(np.asarray(self.depth))) if np.asarray(self.depth).size else 0


class Problem(NamedTuple):
    """One node to fit: indices (into the caller's sample arrays) of its training samples (box
    expanded) and validation samples (box itself); ``init`` is an optional warm start."""

    train: np.ndarray
    val: np.ndarray
    init: Any = None


class NodeFit(NamedTuple):
    """The callback's answer for one Problem: a payload (e.g. network weights) and the node's
    relative training and validation errors."""

    payload: Any
    train_error: float
    val_error: float


class BuildReport(NamedTuple):
    """What the builder did: per level, the nodes tried and split; candidate fits performed; the
    objects pooled into one shared tree (``grouped``) and those left without a tree
    (``skipped``), each as {object: training samples}."""

    levels: list
    n_fits: int
    grouped: dict = {}
    skipped: dict = {}


def traverse(tree: KDTree, object_id, x, *, xp=jnp, column: Callable | None = None):
    """Leaf index for each sample, -1 where the object has no tree (or object_id < 0).

    Args:
      tree: a ``KDTree`` (NumPy or JAX arrays).
      object_id: (...,) int object of each sample.
      x: (..., D) normalised inputs (None with ``column``).
      xp: ``jax.numpy`` (default; jit/vmap-able) or ``numpy`` (host-side, no compilation).
      column: instead of ``x``, ``column(axis) -> (...,)``: each sample's normalised input on
        the axis ``axis`` (...,) its current node splits (so x need never exist as one array).

    A fixed number of steps (the tree's depth, static) of vectorised gathers.
    """
    depth = int(np.max(np.asarray(tree.depth))) if np.asarray(tree.depth).size else 0
    axis, thr = xp.asarray(tree.axis), xp.asarray(tree.threshold)
    left, right = xp.asarray(tree.left), xp.asarray(tree.right)
    roots = xp.asarray(tree.roots)
    object_id = xp.asarray(object_id)
    n_obj = roots.shape[0]
    ok = (object_id >= 0) & (object_id < n_obj)
    node = xp.where(ok, roots[xp.clip(object_id, 0, n_obj - 1)], -1)
    has = node >= 0
    node = xp.maximum(node, 0)
    for _ in range(depth):
        a = axis[node]
        if column is None:
            value = xp.take_along_axis(x, xp.maximum(a, 0)[..., None], axis=-1)[..., 0]
        else:
            value = column(xp.maximum(a, 0))
        child = xp.where(value >= thr[node], right[node], left[node])
        node = xp.where(a >= 0, child, node)
    return xp.where(has, xp.asarray(tree.leaf)[node], -1)


def brute_force_lookup(tree: KDTree, object_id, x) -> np.ndarray:
    """Reference for ``traverse``: the leaf whose half-open cell [lo, hi) contains x, found by
    testing every leaf of the sample's object (NumPy, O(samples x leaves); for tests)."""
    tree = KDTree(*map(np.asarray, tree))
    x = np.asarray(x)
    object_id = np.asarray(object_id)
    owner = node_objects(tree)
    out = np.full(object_id.shape, -1, np.int32)
    for node in np.flatnonzero(tree.leaf >= 0):
        inside = np.all((x >= tree.cell_lo[node]) & (x < tree.cell_hi[node]), axis=-1) & (object_id == owner[node])
        if np.any(out[inside] >= 0):
            raise AssertionError("leaf cells overlap")
        out[inside] = tree.leaf[node]
    return out


def node_objects(tree: KDTree) -> np.ndarray:
    """The object each node belongs to (M,) int64, -1 for nodes of no object's tree.

    Numerics: not differentiable (integer tree structure).
    """
    tree = KDTree(*(np.asarray(a) for a in tree))
    owner = np.full(tree.axis.shape, -1, np.int64)
    for obj, root in enumerate(tree.roots):
        if root < 0:
            continue
        stack = [int(root)]
        while stack:
            node = stack.pop()
            owner[node] = obj
            if tree.axis[node] >= 0:
                stack += [int(tree.left[node]), int(tree.right[node])]
    return owner


def leaf_cells(tree: KDTree) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(object (L,), cell_lo (L, D), cell_hi (L, D)) of every leaf, in leaf-index order."""
    tree = KDTree(*map(np.asarray, tree))
    nodes = np.flatnonzero(tree.leaf >= 0)
    order = np.argsort(tree.leaf[nodes])
    nodes = nodes[order]
    return node_objects(tree)[nodes], tree.cell_lo[nodes], tree.cell_hi[nodes]


def node_samples(x, lo, hi, expand: float, candidates: np.ndarray) -> np.ndarray:
    """Indices among ``candidates`` whose x lies in the box [lo, hi] grown by ``expand`` of its
    width per dimension (half on each side; the box is clipped to the unit cube first)."""
    lo = np.clip(lo, 0.0, 1.0)
    hi = np.clip(hi, 0.0, 1.0)
    margin = 0.5 * expand * (hi - lo)
    sub = x[candidates]
    inside = np.all((sub >= lo - margin) & (sub <= hi + margin), axis=1)
    return candidates[inside]


class _Node:
    __slots__ = ("obj", "depth", "lo", "hi", "fit", "axis", "threshold", "children", "train", "val")

    def __init__(self, obj, depth, lo, hi):
        self.obj, self.depth, self.lo, self.hi = obj, depth, lo, hi
        self.fit = None
        self.axis, self.threshold, self.children = -1, 0.0, None


def cell_members(x, lo, hi, candidates: np.ndarray) -> np.ndarray:
    """Indices among ``candidates`` whose x lies in the half-open cell [lo, hi)."""
    sub = x[candidates]
    return candidates[np.all((sub >= lo) & (sub < hi), axis=1)]


def build(x, object_id, is_train, fit_nodes: Callable[[Sequence[Problem], str], Sequence[NodeFit]], *,
          threshold: float = 0.05, axis: str = "all", expand: float = 0.1, max_depth: int = 8,
          min_samples: int = 200, max_leaves: int = 256, seed: int = 0, objects: Sequence[int] | None = None,
          group_below: int = 0, dims: Sequence[int] | None = None,
          progress: Callable[[str], None] | None = None):
    """Build one error-driven kd-tree per object (module docstring) and fit its leaves.

    Args:
      x: (N, D) inputs normalised per object to [0, 1]^D.
      object_id: (N,) int object of each sample.
      is_train: (N,) bool, True for training samples (70 %), False for validation (30 %).
      fit_nodes: ``fit_nodes(problems, stage)`` fits a batch of ``Problem``s at once and returns one
        ``NodeFit`` each; ``stage`` is "root" (the objects' roots), "candidate" (children of every
        tried axis) or "refine" (the chosen children, warm-started from their candidate fit, before
        their own split decision; the callback may return the candidate fits unchanged).
      threshold: relative error above which a node splits (training OR validation error).
      axis: "all" (try every axis, keep the best pair of children) or "random".
      expand: fraction of the box width added to a node's training box (half per side).
      max_depth, min_samples, max_leaves: guards (a split needs both children to have at least
        ``min_samples`` training samples).
      objects: the objects to build trees for (default: every object with samples).
      group_below: objects with fewer training samples than this share one tree (their samples
        pooled; module docstring); 0 groups none. Objects with no training sample always join the
        group when there is one, and are skipped (no tree, reported) otherwise.
      dims: the input axes a node may split (default: all D, the paper's).
      progress: optional callback for one-line progress messages.

    Returns:
      (tree, payloads, report): the flat ``KDTree``, the list of leaf payloads in leaf-index
      order, and a ``BuildReport``.
    """
    x = np.asarray(x, np.float64)
    object_id = np.asarray(object_id)
    is_train = np.asarray(is_train, bool)
    if x.ndim != 2 or object_id.shape != (x.shape[0],) or is_train.shape != (x.shape[0],):
        raise ValueError(f"need x (N, D), object_id (N,), is_train (N,); got {x.shape}, {object_id.shape}, "
                         f"{is_train.shape}")
    if axis not in ("all", "random"):
        raise ValueError(f"axis must be 'all' or 'random', got {axis!r}")
    if not (threshold > 0):
        raise ValueError(f"threshold must be > 0, got {threshold}")
    if not np.all(np.isfinite(x)):
        raise ValueError("kd-tree inputs contain NaN or infinite values")
    d = x.shape[1]
    allowed = list(range(d)) if dims is None else sorted({int(a) for a in dims})
    if any(a < 0 or a >= d for a in allowed):
        raise ValueError(f"dims must be axes in [0, {d}), got {list(dims)}")
    rng = np.random.default_rng(seed)
    say = progress or (lambda msg: None)
    if objects is None:
        objects = sorted(int(o) for o in np.unique(object_id) if o >= 0)
    n_objects = int(max([*objects, int(object_id.max(initial=-1))]) + 1) if len(objects) else 0
    by_object = {o: np.flatnonzero(object_id == o) for o in objects}
    counts = {o: int(is_train[by_object[o]].sum()) for o in objects}
    small = [o for o in objects if counts[o] < int(group_below) or counts[o] == 0]
    grouped, skipped, aliases = {}, {}, {}
    if small and sum(counts[o] for o in small) > 0 and (len(small) > 1 or counts[small[0]] > 0):
        key = small[0]
        by_object[key] = np.sort(np.concatenate([by_object[o] for o in small]))
        grouped = {o: counts[o] for o in small}
        aliases = {o: key for o in small[1:]}
        objects = [o for o in objects if o not in aliases]
        say(f"kd-tree: {len(small)} object(s) with fewer than {int(group_below)} training samples share one tree "
            f"({sum(grouped.values())} samples): {sorted(grouped)}")
    else:
        skipped = {o: counts[o] for o in small if counts[o] == 0}
        objects = [o for o in objects if o not in skipped]
    if skipped:
        say(f"kd-tree: object(s) {sorted(skipped)} have no training samples: no tree, their pixels predict 0")

    def problem(obj, lo, hi, init=None):
        idx = by_object[obj]
        train = node_samples(x, lo, hi, expand, idx[is_train[idx]])
        val = cell_members(x, lo, hi, idx[~is_train[idx]])
        return Problem(train, val, init)

    roots = []
    for obj in objects:
        lo, hi = np.full(d, -np.inf), np.full(d, np.inf)
        roots.append(_Node(obj, 0, lo, hi))
    root_problems = [problem(n.obj, n.lo, n.hi) for n in roots]
    fits = fit_nodes(root_problems, "root") if root_problems else []
    n_fits = len(fits)
    for n, f, p in zip(roots, fits, root_problems):
        n.fit, n.train, n.val = f, len(p.train), len(p.val)
    n_leaves = len(roots)
    frontier = list(roots)
    levels = []
    while frontier:
        want = [n for n in frontier if max(n.fit.train_error, n.fit.val_error) > threshold and n.depth < max_depth]
        want.sort(key=lambda n: -max(n.fit.train_error, n.fit.val_error))
        if not want or n_leaves >= max_leaves:
            break
        # Candidate children: (node, axis, side) for every tried axis, of the worst nodes that have
        # a split with enough samples on both sides, until the leaf budget is covered
        candidates, problems, splittable = [], [], 0
        for n in want:
            if splittable >= max_leaves - n_leaves:
                break
            before = len(candidates)
            idx = by_object[n.obj]
            sub = x[cell_members(x, n.lo, n.hi, idx)]
            box_lo = np.where(np.isfinite(n.lo), n.lo, 0.0)
            box_hi = np.where(np.isfinite(n.hi), n.hi, 1.0)
            axes = [a for a in allowed if sub.size and np.ptp(sub[:, a]) > 1e-9]
            if axis == "random" and axes:
                axes = [int(rng.choice(axes))]
            for a in axes:
                mid = 0.5 * (box_lo[a] + box_hi[a])
                lo_r, hi_l = n.lo.copy(), n.hi.copy()
                hi_l[a] = mid
                lo_r[a] = mid
                pl = problem(n.obj, n.lo, hi_l, n.fit.payload)
                pr = problem(n.obj, lo_r, n.hi, n.fit.payload)
                if min(len(pl.train), len(pr.train)) < min_samples:
                    continue
                candidates.append((n, a, mid, (n.lo, hi_l), (lo_r, n.hi)))
                problems += [pl, pr]
            splittable += len(candidates) > before
        if not candidates:
            break
        say(f"kd-tree level {len(levels) + 1}: {len(want)} node(s) over threshold, fitting {len(problems)} "
            f"candidate children")
        fits = fit_nodes(problems, "candidate")
        n_fits += len(fits)
        best: dict[int, tuple] = {}
        for c, (node, a, mid, box_l, box_r) in enumerate(candidates):
            fl, fr = fits[2 * c], fits[2 * c + 1]
            pl, pr = problems[2 * c], problems[2 * c + 1]
            weights = np.array([max(len(pl.val), 1), max(len(pr.val), 1)], np.float64)
            score = float(np.dot(weights, [fl.train_error + fl.val_error, fr.train_error + fr.val_error])
                          / weights.sum())
            if id(node) not in best or score < best[id(node)][0]:
                best[id(node)] = (score, node, a, mid, (box_l, fl, pl), (box_r, fr, pr))
        chosen = [n for n in want if id(n) in best][: max_leaves - n_leaves]
        refine = [Problem(p.train, p.val, f.payload) for n in chosen for (_, f, p) in best[id(n)][4:]]
        refined = fit_nodes(refine, "refine") if refine else []
        new_frontier = []
        for c, n in enumerate(chosen):
            _, _, a, mid, *kids = best[id(n)]
            n.axis, n.threshold = a, mid
            n.children = []
            for side, ((lo, hi), _, p) in enumerate(kids):
                child = _Node(n.obj, n.depth + 1, lo, hi)
                child.fit, child.train, child.val = refined[2 * c + side], len(p.train), len(p.val)
                n.children.append(child)
            n.fit = None
            new_frontier += n.children
        n_leaves += len(chosen)
        split = len(chosen)
        levels.append({"level": len(levels) + 1, "over_threshold": len(want), "candidates": len(problems),
                       "split": split, "leaves": n_leaves})
        frontier = new_frontier
    return _flatten(roots, n_objects, d, aliases) + (BuildReport(levels, n_fits, grouped, skipped),)


def _flatten(roots, n_objects: int, d: int, aliases: dict | None = None):
    axis, thr, left, right, leaf, lo, hi, depth, payloads = [], [], [], [], [], [], [], [], []
    root_index = np.full(n_objects, -1, np.int32)

    def add(node) -> int:
        i = len(axis)
        axis.append(node.axis)
        thr.append(node.threshold)
        left.append(i)
        right.append(i)
        lo.append(node.lo)
        hi.append(node.hi)
        depth.append(node.depth)
        if node.children is None:
            leaf.append(len(payloads))
            payloads.append(node.fit.payload)
        else:
            leaf.append(-1)
            left[i] = add(node.children[0])
            right[i] = add(node.children[1])
        return i

    for root in roots:
        root_index[root.obj] = add(root)
    for obj, key in (aliases or {}).items():  # objects pooled into another's tree
        root_index[obj] = root_index[key]
    tree = KDTree(
        axis=np.asarray(axis, np.int32), threshold=np.asarray(thr, np.float32),
        left=np.asarray(left, np.int32), right=np.asarray(right, np.int32), leaf=np.asarray(leaf, np.int32),
        roots=root_index, cell_lo=np.asarray(lo, np.float32).reshape(-1, d),
        cell_hi=np.asarray(hi, np.float32).reshape(-1, d), depth=np.asarray(depth, np.int32))
    return tree, payloads


def leaf_stats(tree: KDTree) -> dict:
    """Leaves per object and depth histogram (for reports)."""
    owner, _, _ = leaf_cells(tree)
    return {"n_leaves": int(len(owner)), "leaves_per_object": np.bincount(owner[owner >= 0]).tolist(),
            "max_depth": KDTree(*map(np.asarray, tree)).max_depth}

