"""kd-tree partition (Ren et al. 2013, §4): traversal, splitting rules and guards."""

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from jprt.methods.rrf import kdtree


def _linear_fitter(x, y):
    """fit_nodes callback: per-node least-squares affine fit (exact on affine targets)."""

    def fit(problems, stage):
        out = []
        for p in problems:
            a = np.c_[x[p.train], np.ones(len(p.train))]
            coef = np.linalg.lstsq(a, y[p.train], rcond=None)[0]

            def err(idx):
                pred = np.c_[x[idx], np.ones(len(idx))] @ coef
                return float(np.sqrt(np.sum((pred - y[idx]) ** 2) / np.sum(y[idx] ** 2)))

            tr = err(p.train)
            out.append(kdtree.NodeFit(coef, tr, err(p.val) if len(p.val) else tr))
        return out

    return fit


def _step_problem(n=4000, d=3, seed=0, step_at=0.3):
    rng = np.random.default_rng(seed)
    x = rng.random((n, d))
    y = (1.0 + 0.5 * x[:, 1] - 0.2 * x[:, 2] + np.where(x[:, 0] < step_at, 0.0, 1.0))[:, None]
    is_train = rng.random(n) < 0.7
    return x, y, is_train


def test_affine_target_stays_one_leaf():
    x, _, is_train = _step_problem()
    y = (1.0 + x @ np.array([0.3, -0.2, 0.5]))[:, None]
    tree, payloads, report = kdtree.build(x, np.zeros(len(x), int), is_train, _linear_fitter(x, y), min_samples=50)
    assert tree.n_leaves == 1 and report.levels == [] and len(payloads) == 1


def test_discontinuity_splits_only_near_it():
    x, y, is_train = _step_problem()
    tree, _, report = kdtree.build(x, np.zeros(len(x), int), is_train, _linear_fitter(x, y), min_samples=40,
                                   max_depth=5, expand=0.0)
    assert tree.n_leaves >= 4 and tree.max_depth == 5
    internal = np.flatnonzero(tree.axis >= 0)
    lo = np.where(np.isfinite(tree.cell_lo), tree.cell_lo, 0.0)
    hi = np.where(np.isfinite(tree.cell_hi), tree.cell_hi, 1.0)
    # Every split node's cell contains the discontinuity x0 = 0.3, and splits are along x0 only.
    assert np.all((lo[internal, 0] <= 0.3) & (hi[internal, 0] > 0.3))
    assert np.all(tree.axis[internal] == 0)
    # Leaves away from the step are exact (affine fit), so they were never split.
    leaf_nodes = np.flatnonzero(tree.leaf >= 0)
    far = leaf_nodes[(hi[leaf_nodes, 0] <= 0.3) | (lo[leaf_nodes, 0] > 0.3)]
    assert len(far) == tree.n_leaves - 1


def test_dims_restrict_the_split_axes():
    # The step lies along x0; barred from x0, the tree can only cut x1 / x2, which never isolates the
    # step, so it still splits (the error stays over the threshold) but on the allowed axes alone.
    x, y, is_train = _step_problem()
    tree, _, _ = kdtree.build(x, np.zeros(len(x), int), is_train, _linear_fitter(x, y), min_samples=40,
                              max_depth=3, expand=0.0, dims=[1, 2])
    internal = np.flatnonzero(tree.axis >= 0)
    assert len(internal) > 0 and set(tree.axis[internal].tolist()) <= {1, 2}
    with pytest.raises(ValueError, match="dims"):
        kdtree.build(x, np.zeros(len(x), int), is_train, _linear_fitter(x, y), dims=[3])


def test_random_axis_and_guards():
    x, y, is_train = _step_problem()
    tree, _, _ = kdtree.build(x, np.zeros(len(x), int), is_train, _linear_fitter(x, y), axis="random",
                              min_samples=40, max_depth=3, seed=1)
    assert tree.max_depth <= 3 and tree.n_leaves <= 8
    tree, _, _ = kdtree.build(x, np.zeros(len(x), int), is_train, _linear_fitter(x, y), max_leaves=3,
                              min_samples=40)
    assert tree.n_leaves <= 3
    tree, _, _ = kdtree.build(x, np.zeros(len(x), int), is_train, _linear_fitter(x, y), min_samples=5000)
    assert tree.n_leaves == 1  # no split leaves both children with enough samples


def test_one_tree_per_object_and_expanded_boxes():
    x, y, is_train = _step_problem(n=3000)
    obj = (np.arange(len(x)) % 2) * 2  # objects 0 and 2; object 1 has no samples
    y = np.where(obj[:, None] == 2, (1.0 + x[:, :1]), y)  # object 2 is affine
    seen = []

    def fit(problems, stage):
        seen.extend(len(p.train) for p in problems)
        return _linear_fitter(x, y)(problems, stage)

    tree, _, _ = kdtree.build(x, obj, is_train, fit, min_samples=40, max_depth=2, expand=0.1)
    assert tree.roots[1] == -1 and tree.roots[0] >= 0 and tree.roots[2] >= 0
    assert tree.axis[tree.roots[2]] == -1  # the affine object stays one leaf
    leaf = kdtree.traverse(tree, np.array([1, -1, 5]), np.full((3, 3), 0.5))
    assert np.all(np.asarray(leaf) == -1)
    # With a 10 % expansion a half box holds more than half of its parent's training samples.
    idx = np.flatnonzero((obj == 0) & is_train)
    half = kdtree.node_samples(x, np.zeros(3), np.array([0.5, 1.0, 1.0]), 0.1, idx)
    plain = kdtree.node_samples(x, np.zeros(3), np.array([0.5, 1.0, 1.0]), 0.0, idx)
    assert len(half) > len(plain)
    assert np.all(x[half, 0] <= 0.525 + 1e-12) and np.all(x[plain, 0] <= 0.5)


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 10_000), d=st.integers(1, 4), depth=st.integers(0, 5))
def test_traversal_matches_brute_force(seed, d, depth):
    """Random trees (random axes, midpoint splits): vectorised traversal == box lookup."""
    rng = np.random.default_rng(seed)
    x = rng.random((500, d))
    is_train = np.ones(len(x), bool)

    def fit(problems, stage):  # never good enough: split wherever the guards allow
        return [kdtree.NodeFit(None, 1.0, 1.0) for _ in problems]

    obj = rng.integers(0, 2, len(x))
    tree, payloads, _ = kdtree.build(x, obj, is_train, fit, axis="random", max_depth=depth, min_samples=5,
                                     seed=seed)
    assert len(payloads) == tree.n_leaves
    probe = rng.random((400, d)) * 1.2 - 0.1  # also outside the unit box
    probe_obj = rng.integers(0, 2, len(probe))
    got = np.asarray(kdtree.traverse(tree, probe_obj, probe))
    np.testing.assert_array_equal(got, kdtree.brute_force_lookup(tree, probe_obj, probe))
    assert np.all(got >= 0)


def test_bad_input():
    x, y, is_train = _step_problem(n=100)
    with pytest.raises(ValueError, match="axis"):
        kdtree.build(x, np.zeros(100, int), is_train, _linear_fitter(x, y), axis="best")
    x[3, 1] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        kdtree.build(x, np.zeros(100, int), is_train, _linear_fitter(x, y))


def test_the_leaf_budget_goes_to_nodes_that_can_split():
    """Issue 21's case: a budget smaller than the nodes over threshold, whose worst nodes cannot
    split (too few samples for ``min_samples``). Those used to take the whole budget and nothing
    split; now the budget passes to the worst nodes that can."""
    rng = np.random.default_rng(3)
    tiny, big = 60, 4000  # three tiny objects with a step (the worst errors), one big one with a milder step
    obj = np.r_[np.repeat([0, 1, 2], tiny), np.full(big, 3)]
    x = rng.random((len(obj), 2))
    y = (1.0 + np.where(x[:, 0] < 0.5, 0.0, np.where(obj == 3, 0.6, 3.0)))[:, None]
    is_train = rng.random(len(obj)) < 0.7
    tree, _, report = kdtree.build(x, obj, is_train, _linear_fitter(x, y), min_samples=200, max_leaves=6,
                                   max_depth=1)
    assert report.levels[0]["over_threshold"] == 4  # every object is over threshold; the tiny ones worst
    assert tree.n_leaves == 5 and report.levels[0]["split"] == 1  # the big object's root split
    owner, _, _ = kdtree.leaf_cells(tree)
    assert np.bincount(owner).tolist() == [1, 1, 1, 2]


def test_objects_with_one_or_no_training_sample_are_grouped_or_reported():
    """An object with a single training sample, and one with only validation samples, do not stop
    the build: with ``group_below`` they share one tree with the other small objects (every one of
    them looks it up); without a group, the sample-less one has no tree and is named."""
    rng = np.random.default_rng(4)
    obj = np.r_[np.zeros(3000, int), [1], np.full(5, 2), np.full(40, 3)]
    x = rng.random((len(obj), 2))
    y = (1.0 + x[:, :1]) * (1.0 + obj[:, None])
    is_train = np.r_[rng.random(3000) < 0.7, [True], np.zeros(5, bool), rng.random(40) < 0.7]
    tree, payloads, report = kdtree.build(x, obj, is_train, _linear_fitter(x, y), group_below=50, min_samples=40)
    assert set(report.grouped) == {1, 2, 3} and report.grouped[1] == 1 and report.grouped[2] == 0
    assert report.skipped == {}
    roots = np.asarray(tree.roots)
    assert roots[1] == roots[2] == roots[3] >= 0 and roots[0] >= 0 and roots[0] != roots[1]
    leaf = kdtree.traverse(tree, np.array([1, 2, 3]), np.full((3, 2), 0.5), xp=np)
    assert np.all(np.asarray(leaf) >= 0)

    tree, _, report = kdtree.build(x, obj, is_train, _linear_fitter(x, y), min_samples=40)
    assert report.skipped == {2: 0} and report.grouped == {}
    assert np.asarray(tree.roots)[2] == -1 and np.asarray(tree.roots)[1] >= 0
