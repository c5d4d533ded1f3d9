"""Radiance Regression Functions (Ren et al. 2013): fitting, Eq. 9 evaluation, bad input, data."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jprt.methods.rrf import data as rrf_data
from jprt.methods.rrf import features as rrf_features
from jprt.methods.rrf import fitting as rrf_fitting
from jprt.methods.rrf import kdtree
from jprt.methods.rrf import model as rrf
from jprt.methods.rrf import renderer as rrf_renderer
from jprt.render.gbuffer import GBuffer
from jprt.render.lights import PointLights

TINY = {"model": {"hidden": [6, 4]}, "train": {"max_iters": 3, "trial_iters": 1, "progress": False},
        "tree": {"threshold": 1e-6, "max_depth": 2, "min_samples": 30, "axis": "random"}}


def _fake_gbuffer(h=6, w=5, seed=0, n_objects=2):
    rng = np.random.default_rng(seed)
    unit = lambda a: a / np.linalg.norm(a, axis=-1, keepdims=True)  # noqa: E731
    valid = rng.random((h, w)) > 0.2
    return GBuffer(
        position=rng.uniform(-1, 1, (h, w, 3)).astype(np.float32),
        normal=unit(rng.normal(size=(h, w, 3))).astype(np.float32),
        view=unit(rng.normal(size=(h, w, 3))).astype(np.float32),
        reflected=np.zeros((h, w, 3), np.float32), uv=np.zeros((h, w, 2), np.float32),
        diffuse_albedo=rng.random((h, w, 3)).astype(np.float32),
        specular_albedo=np.zeros((h, w, 3), np.float32), roughness=np.ones((h, w), np.float32),
        object_id=np.where(valid, rng.integers(0, n_objects, (h, w)), -1).astype(np.int32), valid=valid)


@pytest.fixture(scope="module")
def model():
    """A (poorly trained, multi-leaf) RRF over random augmented attributes: Eq. 9 and the
    evaluator's contracts do not depend on fit quality."""
    rng = np.random.default_rng(1)
    n = 600
    x = np.concatenate([rng.uniform(-1, 1, (n, 3)), rng.normal(size=(n, 3)), rng.uniform([-0.5, 0.3, -0.5],
                        [0.5, 0.9, 0.5], (n, 3)), rng.normal(size=(n, 3)), rng.random((n, 7))], axis=1)
    y = np.abs(np.sin(x[:, :3] + x[:, 6:9]))
    obj = rng.integers(0, 2, n)
    params, info = rrf.fit_arrays(x, y, obj, TINY)
    params["light_lo"] = jnp.asarray([-0.5, 0.3, -0.5])
    params["light_hi"] = jnp.asarray([0.5, 0.9, 0.5])
    return params, info


#: One-leaf fits of 1500 samples of three inputs (the two tests below: one LM program, compiled once).
SMOOTH = {"model": {"hidden": [8, 4]}, "train": {"max_iters": 40, "progress": False}, "tree": {"min_samples": 50}}


def test_smooth_target_single_leaf():
    rng = np.random.default_rng(0)
    x = rng.random((1500, 3)).astype(np.float32)
    y = np.stack([1.0 + 0.5 * np.sin(2.0 * x[:, 0]) + 0.3 * x[:, 1] * x[:, 2]] * 3, axis=1)
    params, info = rrf.fit_arrays(x, y, np.zeros(len(x), np.int32), SMOOTH)
    assert kdtree.KDTree(**params["tree"]).n_leaves == 1
    assert info["leaf_val_error"][0] < 0.01  # stated: a smooth target is fit below 1 % relative error
    test = rng.random((500, 3)).astype(np.float32)
    ref = 1.0 + 0.5 * np.sin(2.0 * test[:, 0]) + 0.3 * test[:, 1] * test[:, 2]
    pred = _sorted(params, test, np.zeros(500, np.int32), clamp=False)
    assert rrf_fitting.relative_error(pred[:, 0], ref) < 0.01


def test_a_feature_constant_in_training_stays_constant_at_run_time():
    """The seam of ``make demo`` (the tall box's top face, which no training ray hit, so every
    training normal of its leaf had y = 0): the renderer clips each input to its leaf's training
    range, so a feature that was constant there is held at that constant instead of extrapolated."""
    rng = np.random.default_rng(3)
    x = rng.random((1500, 3)).astype(np.float32)
    x[:, 2] = 0.0
    y = np.stack([1.0 + 0.5 * np.sin(3.0 * x[:, 0]) * x[:, 1]] * 3, axis=1)
    params, _ = rrf.fit_arrays(x, y, np.zeros(len(x), np.int32), SMOOTH)
    clamped = _predictor(params)
    seen = clamped(x, np.zeros(1500, np.int32))
    x_new = x.copy()
    x_new[:, 2] = 1.0
    held = clamped(x_new, np.zeros(1500, np.int32))
    free = _sorted(params, x_new, np.zeros(1500, np.int32), clamp=False)
    np.testing.assert_allclose(held, seen, rtol=1e-5, atol=1e-6)
    assert np.abs(free - seen).max() > 1e-3  # extrapolated, the output moves


def _sorted(params, x, object_id, **kw) -> np.ndarray:
    """``rrf_renderer._predict_sorted`` compiled as one program (the trained tree closed over, as the
    evaluator does): run eagerly, each of its many small operations compiles on its own, several
    times slower in the suite."""
    return _predictor(params, **kw)(x, object_id)


def _predictor(params, **kw):
    """``_sorted`` as a function of (x, object_id): one compiled program for calls of one shape."""
    predict = jax.jit(lambda a, b: rrf_renderer._predict_sorted(params, a, b, **kw))
    return lambda x, object_id: np.asarray(predict(jnp.asarray(x), jnp.asarray(object_id)))


def _reference_phi(layers, scaling, x):
    """An independent NumPy oracle of Eq. 8 with Appendix A's scaling (tanh hidden, linear out)."""
    h = (np.asarray(x, np.float64) - scaling["in_center"]) / scaling["in_halfrange"]
    for i, layer in enumerate(layers):
        h = h @ np.asarray(layer["w"], np.float64) + np.asarray(layer["b"], np.float64)
        if i < len(layers) - 1:
            h = np.tanh(h)
    return h * scaling["out_halfrange"] + scaling["out_center"]


def test_rescale_is_exact():
    rng = np.random.default_rng(0)
    layers = [{"w": rng.normal(size=(3, 5)), "b": rng.normal(size=5)}, {"w": rng.normal(size=(5, 2)),
                                                                     "b": rng.normal(size=2)}]
    src = {"in_center": rng.normal(size=3), "in_halfrange": rng.random(3) + 0.5,
           "out_center": rng.normal(size=2), "out_halfrange": rng.random(2) + 0.5}
    dst = {"in_center": rng.normal(size=3), "in_halfrange": rng.random(3) + 0.5,
           "out_center": rng.normal(size=2), "out_halfrange": rng.random(2) + 0.5}
    x = rng.normal(size=(20, 3))
    np.testing.assert_allclose(_reference_phi(rrf_fitting._rescale(layers, src, dst), dst, x), _reference_phi(layers, src, x),
                               rtol=1e-10, atol=1e-10)


def test_eq9_linearity(model):
    params, _ = model
    assert kdtree.KDTree(**params["tree"]).n_leaves > 2
    evaluate = rrf.evaluator(params)
    gb = _fake_gbuffer()
    a = PointLights.create([[0.1, 0.5, 0.0]], [1.0, 0.5, 2.0])
    b = PointLights.create([[-0.3, 0.8, 0.2]], [0.3, 1.0, 0.7])
    both = PointLights.create([[0.1, 0.5, 0.0], [-0.3, 0.8, 0.2]], [[1.0, 0.5, 2.0], [0.3, 1.0, 0.7]])
    ia, ib, iab = (np.asarray(evaluate(gb, lights)) for lights in (a, b, both))
    np.testing.assert_allclose(iab, ia + ib, rtol=1e-5, atol=1e-6)
    assert np.abs(ia).max() > 0
    twice = PointLights.create([[0.1, 0.5, 0.0]], [2.0, 1.0, 4.0])
    np.testing.assert_allclose(np.asarray(evaluate(gb, twice)), 2 * ia, rtol=1e-5, atol=1e-6)
    assert np.all(ia[~gb.valid] == 0)


def test_gradient_evaluator_is_the_evaluator_and_reverse_mode_goes_through_it(model):
    """``gradient_evaluator`` (``render_dense``): the tiled renderer's image, pixel for pixel, for
    one and three lights; ``jax.grad`` of an image objective through it equals ``jax.jacfwd``
    through the tiled renderer (the same function, away from the leaves' boundaries) and a
    central difference of it."""
    params, _ = model
    gb = _fake_gbuffer(h=12, w=10)
    tiled, dense = rrf.evaluator(params), rrf.gradient_evaluator(params)
    pos = np.asarray([[0.1, 0.5, 0.0], [-0.3, 0.8, 0.2], [0.35, 0.42, -0.31]], np.float32)
    rgb = np.asarray([[1.0, 0.5, 2.0], [0.3, 1.0, 0.7], [0.6, 0.6, 0.2]], np.float32)
    for k in (1, 3):
        lights = PointLights.create(pos[:k], rgb[:k])
        want = np.asarray(tiled(gb, lights))
        assert np.abs(want).max() > 0
        np.testing.assert_allclose(np.asarray(dense(gb, lights)), want, rtol=2e-5, atol=1e-6)
    weights = jnp.asarray(np.random.default_rng(5).normal(size=(12, 10, 3)), jnp.float32)

    def objective(evaluate):
        return lambda p: jnp.sum(weights * evaluate(gb, PointLights(p, jnp.asarray(rgb)))) ** 2

    g_rev = np.asarray(jax.jit(jax.grad(objective(dense)))(jnp.asarray(pos)))
    g_fwd = np.asarray(jax.jit(jax.jacfwd(objective(tiled)))(jnp.asarray(pos)))
    assert np.abs(g_rev).max() > 0
    np.testing.assert_allclose(g_rev, g_fwd, rtol=1e-3, atol=1e-4 * np.abs(g_fwd).max())
    f = jax.jit(objective(dense))
    h, e = 1e-3, np.zeros_like(pos)
    e[1, 2] = h
    fd = (float(f(jnp.asarray(pos + e, jnp.float32))) - float(f(jnp.asarray(pos - e, jnp.float32)))) / (2 * h)
    np.testing.assert_allclose(g_rev[1, 2], fd, rtol=2e-2, atol=1e-3 * np.abs(g_rev).max())


def test_no_recompile_for_same_light_count(model):
    params, _ = model
    pure = rrf.evaluator(params)
    traces = []

    def traced(gb, lights):  # runs once per trace, not per call
        traces.append(1)
        return pure(gb, lights)

    evaluate = jax.jit(traced)
    gb = _fake_gbuffer()
    for k in range(3):
        evaluate(gb, PointLights.create([[0.1 * k, 0.5, 0.0], [0.0, 0.6, 0.1 * k]], [1.0, 1.0, 1.0]))
    assert len(traces) == 1
    evaluate(gb, PointLights.create([[0.0, 0.5, 0.0]], [1.0, 1.0, 1.0]))  # another light count: one more program
    assert len(traces) == 2


def test_frame_flops_count_the_shared_layer_once_per_distinct_leaf(model):
    """Eq. 9 shares the light-free part of the first layer between lights only within one kd-tree
    cell: the count has it once per (pixel, distinct leaf), found here by the brute-force lookup,
    and every light's own part once per pixel. The tree (two of the fixture's leaf networks)
    splits on the light's x."""
    fitted, _ = model
    d = 19
    lo, hi = np.full((3, d), -np.inf, np.float32), np.full((3, d), np.inf, np.float32)  # root, left, right cells
    hi[1, 6], lo[2, 6] = 0.5, 0.5
    tree = kdtree.KDTree(axis=np.asarray([6, -1, -1], np.int32), threshold=np.asarray([0.5, 0, 0], np.float32),
                         left=np.asarray([1, 1, 2], np.int32), right=np.asarray([2, 1, 2], np.int32),
                         leaf=np.asarray([-1, 0, 1], np.int32), roots=np.asarray([0], np.int32), cell_lo=lo,
                         cell_hi=hi, depth=np.asarray([0, 1, 1], np.int32))
    params = {**fitted, "tree": {k: jnp.asarray(v) for k, v in tree._asdict().items()},
              "obj_lo": fitted["obj_lo"][:1], "obj_hi": fitted["obj_hi"][:1],
              "leaves": jax.tree_util.tree_map(lambda a: a[:2], fitted["leaves"])}
    gb = _fake_gbuffer(h=8, w=9, seed=2, n_objects=1)
    lights = PointLights.create([[0.2, 0.5, 0.0], [0.2, 0.5, 0.0], [-0.3, 0.8, 0.3]], np.ones((3, 3)))
    obj = np.where(gb.valid, gb.object_id, -1).reshape(-1)
    o_lo, o_hi = np.asarray(params["obj_lo"])[0], np.asarray(params["obj_hi"])[0]
    leaves = []
    for p in np.asarray(lights.position):
        x = np.asarray(rrf.features("augmented", gb.position, gb.view, np.broadcast_to(p, gb.position.shape), gb.normal,
                                    rrf.brdf_vector(gb.diffuse_albedo, gb.specular_albedo, gb.roughness))).reshape(-1, d)
        leaves.append(kdtree.brute_force_lookup(tree, obj, (x - o_lo) / np.where(o_hi - o_lo > 1e-8, o_hi - o_lo, 1.0)))
    leaves = np.stack(leaves)
    live = leaves[0] >= 0
    distinct = sum(len(set(leaves[:, i])) for i in np.flatnonzero(live))
    assert distinct == 2 * live.sum()  # the third light is in the other leaf at every pixel
    h1, h2 = 6, 4
    shared, per_light = 2 * 16 * h1, 2 * 3 * h1 + 2 * h1 + (2 * h1 * h2 + h2) + (2 * h2 * 3 + 3) + 2 * 3
    assert rrf.frame_flops(params, None, gb, lights) == distinct * shared + live.sum() * 3 * per_light


def test_frame_work_counts_the_tiles_slots(model):
    """With one-pixel tiles and one-item chunks every slot is one needed pixel-leaf network, so
    one light executes exactly what it needs; larger tiles and chunks only add masked slots
    (occupancy <= 1), in whole tiles and chunks. The network rate is measured and positive, and
    the method contract's frame report takes it as RRF's roof."""
    from jprt.methods.rrf import METHOD

    params, _ = model
    gb = _fake_gbuffer(h=12, w=10, seed=4, n_objects=2)
    one = PointLights.create([[0.1, 0.5, 0.0]], np.ones((1, 3)))
    exact = rrf.frame_work(params, {"render": {"tile": 1, "chunk": 1}}, gb, one)
    assert exact["slots"] == exact["pixels"] == exact["items"] > 0
    assert exact["executed_flops"] == exact["useful_flops"] and exact["occupancy"] == 1.0
    tiled = rrf.frame_work(params, {"render": {"tile": 4, "chunk": 3}}, gb, one)
    assert tiled["useful_flops"] == exact["useful_flops"] == rrf.frame_flops(params, None, gb, one)
    assert tiled["slots"] % (4 * 4 * 3) == 0 and tiled["executed_flops"] >= exact["executed_flops"]
    assert 0 < tiled["occupancy"] <= 1 and tiled["bytes"] > 0
    cfg = {"render": {"tile": 4, "chunk": 3}}
    roof = rrf.frame_roofline(params, cfg, gb, one, frame_ms=1.0, repeats=2, bandwidth_gbs=5.0)
    detail = roof["detail"]
    assert detail["network_gflops"] > 0 and roof["roofline"]["matmul_gflops"] == detail["network_gflops"]
    assert roof["roofline"]["frame_flops"] == tiled["executed_flops"]
    assert 0 < detail["useful_over_executed"] <= 1
    # the contract's report takes RRF's own roof and keeps the generic one beside it
    report = METHOD.frame_report(params, cfg, jax.jit(rrf.evaluator(params, cfg)), gb, one, 1.0, peak_gflops=100.0,
                                 bandwidth_gbs=5.0, repeats=2)
    own, matmul = report["roofline"], report["roofline_matmul"]
    assert own["roof"] == "networks" and own["matmul_gflops"] == report["roofline_detail"]["network_gflops"]
    assert own["frame_flops"] == tiled["executed_flops"]
    assert report["roofline_detail"]["work"]["slots"] == tiled["slots"]
    assert matmul["roof"] == "matmul" and matmul["matmul_gflops"] == 100.0
    assert own["bandwidth_gbs"] == matmul["bandwidth_gbs"] == 5.0
    assert report["frame_flops"] == matmul["frame_flops"] == rrf.frame_flops(params, cfg, gb, one)
    assert report["frame_flops_source"] == "method"


def test_traversal_in_evaluator_matches_brute_force(model):
    params, _ = model
    rng = np.random.default_rng(3)
    x = rng.random((300, 19)).astype(np.float32)
    obj = rng.integers(-1, 3, 300)  # includes no-tree and out-of-range objects
    tree = kdtree.KDTree(**{k: np.asarray(v) for k, v in params["tree"].items()})
    np.testing.assert_array_equal(np.asarray(kdtree.traverse(tree, obj, x)), kdtree.brute_force_lookup(tree, obj, x))


def test_raw_thresholds_traverse_raw_inputs_as_the_tree_does_normalised(model):
    """``raw_thresholds``: the renderer's traversal of raw inputs against split values mapped back
    through each object's box finds the leaf that the normalised traversal finds."""
    params, _ = model
    rng = np.random.default_rng(4)
    lo, hi = np.asarray(params["obj_lo"]), np.asarray(params["obj_hi"])
    obj = rng.integers(0, lo.shape[0], 2000)
    x = (lo[obj] + rng.uniform(-0.1, 1.1, (2000, lo.shape[1])) * (hi - lo)[obj]).astype(np.float32)
    tree = kdtree.KDTree(**{k: np.asarray(v) for k, v in params["tree"].items()})
    want = kdtree.traverse(tree, obj, rrf_features.normalise(x, obj, lo, hi), xp=np)
    got = kdtree.traverse(tree._replace(threshold=rrf.raw_thresholds(params)), obj, x, xp=np)
    assert len(np.unique(want)) > 2
    np.testing.assert_array_equal(got, want)


def test_lights_share_each_pixels_leaf_without_light_splits():
    """With ``tree.split_on`` barring the light, the renderer traverses once for all of a frame's
    lights; Eq. 9 stays linear in the lights and equals the per-light frames."""
    rng = np.random.default_rng(2)
    n = 600
    x = np.concatenate([rng.uniform(-1, 1, (n, 3)), rng.normal(size=(n, 3)), rng.uniform([-0.5, 0.3, -0.5],
                        [0.5, 0.9, 0.5], (n, 3)), rng.normal(size=(n, 3)), rng.random((n, 7))], axis=1)
    y = np.abs(np.sin(x[:, :3] + x[:, 6:9]))
    config = {**TINY, "tree": {**TINY["tree"], "split_on": ["position", "view", "normal", "brdf"]}}
    params, _ = rrf.fit_arrays(x, y, rng.integers(0, 2, n), config)
    params["light_lo"], params["light_hi"] = jnp.asarray([-0.5, 0.3, -0.5]), jnp.asarray([0.5, 0.9, 0.5])
    axes = np.asarray(params["tree"]["axis"])
    assert kdtree.KDTree(**params["tree"]).n_leaves > 2 and not np.isin(axes, [6, 7, 8]).any()
    evaluate, gb = rrf.evaluator(params, config), _fake_gbuffer()
    spots, colours = [[0.1, 0.5, 0.0], [-0.3, 0.8, 0.2], [0.4, 0.4, -0.4]], [[1.0, 0.5, 2.0], [0.3, 1.0, 0.7], [1, 1, 1]]
    each = [np.asarray(evaluate(gb, PointLights.create([p], [c]))) for p, c in zip(spots, colours)]
    np.testing.assert_allclose(np.asarray(evaluate(gb, PointLights.create(spots, colours))), sum(each),
                               rtol=1e-5, atol=1e-6)
    assert np.abs(each[0]).max() > 0


def test_bad_input(model):
    params, _ = model
    evaluate = rrf.evaluator(params)
    gb = _fake_gbuffer()
    inside = PointLights.create([[0.5, 0.9, 0.5]], [1.0, 1.0, 1.0])
    outside = PointLights.create([[2.0, 0.5, 0.0]], [1.0, 1.0, 1.0])
    with pytest.raises(ValueError, match="outside the trained light box"):
        evaluate(gb, outside)
    clamped = rrf.evaluator(params, {"render": {"extrapolation": "clamp"}})(gb, outside)
    np.testing.assert_allclose(np.asarray(clamped), np.asarray(evaluate(gb, PointLights.create(
        [[0.5, 0.5, 0.0]], [1.0, 1.0, 1.0]))), rtol=1e-6, atol=1e-7)
    rrf.evaluator(params, {"render": {"extrapolation": "allow"}})(gb, outside)  # documented: evaluates anyway
    empty = GBuffer(*(np.asarray(a)[:0] for a in gb))
    with pytest.raises(ValueError, match="empty G-buffer"):
        evaluate(empty, inside)
    none_valid = gb._replace(valid=np.zeros_like(gb.valid), object_id=np.full_like(gb.object_id, -1))
    assert np.all(np.asarray(evaluate(none_valid, inside)) == 0)  # documented: all-invalid -> zeros
    bad = gb._replace(normal=np.where(gb.valid[..., None], np.nan, gb.normal))
    with pytest.raises(ValueError, match="'normal' has .* NaN"):
        evaluate(bad, inside)
    ok_nan = gb._replace(normal=np.where(~gb.valid[..., None], np.nan, gb.normal))  # NaN at invalid pixels only
    assert np.all(np.isfinite(np.asarray(evaluate(ok_nan, inside))))
    with pytest.raises(ValueError, match="extrapolation"):
        rrf.evaluator(params, {"render": {"extrapolation": "extrapolate"}})
    with pytest.raises(ValueError, match="NaN"):
        rrf.fit_arrays(np.full((10, 3), np.nan), np.ones((10, 3)), np.zeros(10, int), TINY)


def test_export_roundtrip(model):
    from jprt.export import export_function, load_function

    params, _ = model
    evaluate = rrf.evaluator(params)
    gb = _fake_gbuffer()
    lights = PointLights.create([[0.1, 0.5, 0.0], [0.2, 0.7, -0.1]], [[1.0, 0.5, 2.0], [1, 1, 1]])
    blob = export_function(evaluate, gb, lights)
    loaded = load_function(blob)
    np.testing.assert_allclose(np.asarray(loaded(gb, lights)), np.asarray(evaluate(gb, lights)), rtol=1e-6, atol=1e-7)


def test_refit_leaves_variants(model):
    params, info = model
    rng = np.random.default_rng(1)
    n = info["n_samples"]
    data = rrf.RRFData(position=rng.uniform(-1, 1, (n, 3)), view=rng.normal(size=(n, 3)),
                       light=rng.uniform([-0.5, 0.3, -0.5], [0.5, 0.9, 0.5], (n, 3)), normal=rng.normal(size=(n, 3)),
                       brdf=rng.random((n, 7)), edit=np.zeros((n, 0)), object_id=rng.integers(0, 2, n),
                       direct=np.zeros((n, 3)), indirect=rng.random((n, 3)), pair=np.zeros(n, int),
                       meta={"mode": "view"})
    variants = rrf.refit_leaves(params, data, TINY, info, [{"seed": 1, "subset": 0.7}, {"seed": 2, "subset": 1.0}])
    assert len(variants) == 2
    for v in variants:
        assert v["tree"] is params["tree"]
        assert v["leaves"]["layers"][0]["w"].shape == params["leaves"]["layers"][0]["w"].shape
    assert not np.allclose(variants[0]["leaves"]["layers"][0]["w"], variants[1]["leaves"]["layers"][0]["w"])


def test_make_dataset_tiny(mi, tmp_path):
    from jprt.render.images import RENDER_STATS

    cfg = {"data": {"n_lights": 3, "n_views": 2, "n_rays": 24, "spp": 4}}
    data = rrf_data.make_dataset({"name": "cornell_box", "area_light": False}, cfg, cache_dir=str(tmp_path),
                            progress=False)
    assert 0.8 * 3 * 2 * 24 <= len(data) <= 3 * 2 * 24
    assert data.brdf.shape == (len(data), 7) and data.edit.shape == (len(data), 0)
    np.testing.assert_allclose(np.linalg.norm(data.normal, axis=1), 1.0, atol=1e-4)
    np.testing.assert_allclose(np.linalg.norm(data.view, axis=1), 1.0, atol=1e-4)
    assert np.all(np.abs(data.position) <= 1.0 + 1e-3)  # first hits inside the Cornell box
    assert data.indirect.min() > -1e-4 and data.indirect.mean() > 0
    # Latin hypercube: one light per stratum along every axis of the light box.
    lights = np.unique(data.light, axis=0)
    lo, hi = np.array(rrf_data.CORNELL_REGIONS["light_lo"]), np.array(rrf_data.CORNELL_REGIONS["light_hi"])
    assert data.meta["regions"]["source"] == "cornell" and data.meta["light_lo"] == rrf_data.CORNELL_REGIONS["light_lo"]
    strata = np.floor((lights - lo) / (hi - lo) * 3).astype(int)
    assert all(sorted(strata[:, a]) == [0, 1, 2] for a in range(3))
    before = dict(RENDER_STATS)
    again = rrf_data.make_dataset({"name": "cornell_box", "area_light": False}, cfg, cache_dir=str(tmp_path),
                             progress=False)
    assert dict(RENDER_STATS) == before
    np.testing.assert_array_equal(again.indirect, data.indirect)
    x = rrf.data_features(data, "augmented")
    assert x.shape == (len(data), rrf.input_size("augmented")) and rrf.input_size("basic") == 9
    # "diffuse" is "augmented" without the view's three columns
    np.testing.assert_array_equal(rrf.data_features(data, "diffuse"), np.delete(x, [3, 4, 5], axis=1))
    assert rrf.input_size("diffuse") == 16


def test_make_dataset_material_mode(mi, tmp_path):
    cfg = {"data": {"mode": "material", "n_lights": 2, "n_rays": 16, "spp": 2,
                    "material": {"object": "floor", "n_materials": 2}}}
    data = rrf_data.make_dataset("glossy_cornell", cfg, cache_dir=str(tmp_path), progress=False)
    assert data.edit.shape == (len(data), 2)
    assert len(np.unique(data.edit[:, 0])) == 2
    assert rrf.data_features(data, "augmented").shape[1] == rrf.input_size("augmented", "material")
    with pytest.raises(ValueError, match="has no view"):  # the edit parameters take the view's place
        rrf.fit(data, {"data": {"mode": "material"}, "model": {"attributes": "diffuse"}})
    with pytest.raises(ValueError, match="without emitters"):
        rrf_data.make_dataset("cornell_box", cfg, cache_dir=str(tmp_path), progress=False)  # has its area light
    with pytest.raises(ValueError, match="not an object"):
        rrf_data.make_dataset("glossy_cornell", {"data": {"mode": "material", "material": {"object": "teapot"}}},
                         cache_dir=str(tmp_path), progress=False)


def test_blocked_prediction_matches_per_leaf_numpy(model):
    """The sorted-block evaluation equals evaluating each sample's own leaf network directly, with
    and without the inputs clipped to each leaf's trained range; the tiled, sort-free evaluation
    of the renderer equals it (and takes the sorted path past its capacity)."""
    params, _ = model
    rng = np.random.default_rng(7)
    n = 1000
    x = np.concatenate([rng.uniform(-1, 1, (n, 3)), rng.normal(size=(n, 3)), rng.uniform([-0.5, 0.3, -0.5],
                        [0.5, 0.9, 0.5], (n, 3)), rng.normal(size=(n, 3)), rng.random((n, 7))], axis=1).astype(np.float32)
    obj = rng.integers(-1, 3, n)  # -1 and 2: no tree -> 0
    got = _sorted(params, x, obj, block=16, clamp=False)
    tree = kdtree.KDTree(**{k: np.asarray(v) for k, v in params["tree"].items()})
    safe = np.clip(obj, 0, 1)
    lo, hi = np.asarray(params["obj_lo"])[safe], np.asarray(params["obj_hi"])[safe]
    leaf = kdtree.brute_force_lookup(tree, obj, (x - lo) / np.where(hi - lo > 1e-8, hi - lo, 1.0))
    leaves = jax.tree_util.tree_map(np.asarray, params["leaves"])
    want, want_c = np.zeros((n, 3), np.float32), np.zeros((n, 3), np.float32)
    for i in np.flatnonzero(leaf >= 0):
        s = {k: v[leaf[i]] for k, v in leaves["scaling"].items()}
        layers = [{k: v[leaf[i]] for k, v in layer.items()} for layer in leaves["layers"]]
        want[i] = _reference_phi(layers, s, x[i][None])[0]
        clipped = np.clip(x[i], s["in_min"], s["in_max"])  # the leaf's training range
        want_c[i] = _reference_phi(layers, s, clipped[None])[0]
    assert np.any(leaf < 0) and np.all(got[leaf < 0] == 0)
    np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-5)
    clamped = _predictor(params, block=16, clamp=True)
    got_c = clamped(x, obj)
    np.testing.assert_allclose(got_c, want_c, rtol=1e-4, atol=1e-5)
    assert np.abs(want_c - want).max() > 1e-2  # the normals drawn from N(0, 1) leave the trained range
    # the renderer's form: one light for every sample, the other columns shared; sorted by object and
    # position so that runs of samples share leaves as image rows do
    x[:, 6:9] = [0.1, 0.5, -0.2]
    order = np.lexsort((x[:, 0], obj))
    x, obj = x[order], obj[order]
    shared = np.delete(x, [6, 7, 8], axis=1)
    ref = clamped(x, obj)
    for tile, chunk in ((4, 3), (16, 1)):  # a chunk that does not divide the tiles, and one chunk
        tiles = jax.jit(lambda a, b, light, o: rrf_renderer._predict_tiles(  # noqa: B023 (called at once)
            params, [a, b], light, jnp.ones((1, 3)), o, light_cols=(6, 7, 8), tile=tile, chunk=chunk, clamp=True,
            nonnegative=False))
        tiled = tiles(jnp.asarray(shared[:, :6].reshape(40, 25, -1)), jnp.asarray(shared[:, 6:].reshape(40, 25, -1)),
                      jnp.asarray(x[:1, 6:9]), jnp.asarray(obj.reshape(40, 25)))
        np.testing.assert_allclose(np.asarray(tiled).reshape(n, 3), ref, rtol=1e-4, atol=1e-5)


def test_render_layout_by_backend_and_config():
    """None: the backend's measured layout (the GPU's for backends not listed); set values win;
    sizes below 1 are refused."""
    assert rrf.render_layout({"tile": None, "chunk": None}, "cpu") == rrf.RENDER_LAYOUTS["cpu"]
    assert rrf.render_layout({"tile": None, "chunk": None}, "tpu") == rrf.RENDER_LAYOUTS["gpu"]
    assert rrf.render_layout({"tile": 4, "chunk": None}, "cpu") == (4, rrf.RENDER_LAYOUTS["cpu"][1])
    assert rrf.render_layout({"tile": None, "chunk": 3}, "gpu") == (rrf.RENDER_LAYOUTS["gpu"][0], 3)
    with pytest.raises(ValueError, match="render.tile and render.chunk"):
        rrf.render_layout({"tile": 0, "chunk": 8})


def test_split_on_names_the_attribute_axes():
    """``tree.split_on``: None leaves every axis to the tree (the paper's); a list of attribute
    names gives exactly their columns of ``features``' layout (view is 2 wide in material mode)
    (the fit splits those columns only: ``test_the_fit_splits_only_the_axes_split_on_names``)."""
    cfg = lambda split_on, mode="view", attributes="augmented": {  # noqa: E731
        "tree": {"split_on": split_on}, "model": {"attributes": attributes}, "data": {"mode": mode}}
    assert rrf.split_dims(cfg(None)) is None
    assert rrf.split_dims(cfg(["light"])) == [6, 7, 8]
    assert rrf.split_dims(cfg(["position", "view", "normal", "brdf"])) == [0, 1, 2, 3, 4, 5, *range(9, 19)]
    assert rrf.split_dims(cfg(["light"], mode="material")) == [5, 6, 7]
    assert rrf.split_dims(cfg(["brdf"], attributes="basic+a")) == list(range(9, 16))
    for bad in (["normal"], [], "light"):
        with pytest.raises(ValueError, match="split_on"):
            rrf.split_dims(cfg(bad, attributes="basic"))


@pytest.mark.slow  # 16 s of LM fits over every candidate axis
def test_the_fit_splits_only_the_axes_split_on_names():
    """Free, this tiny fit's root splits a non-light axis (5 when written); barred from all but
    the light, it splits a light column."""
    rng = np.random.default_rng(3)
    n = 600
    x = np.concatenate([rng.uniform(-1, 1, (n, 6)), rng.uniform(-1, 1, (n, 3)), rng.normal(size=(n, 3)),
                        rng.random((n, 7))], axis=1).astype(np.float32)
    y = np.abs(np.sin(3 * x[:, 6:9])) + 0.1
    axes = {}
    for split_on in (None, ["light"]):
        config = {**TINY, "tree": {**TINY["tree"], "axis": "all", "max_depth": 1, "split_on": split_on}}
        params, _ = rrf.fit_arrays(x, y, np.zeros(n, np.int32), config)
        a = np.asarray(params["tree"]["axis"])
        axes[str(split_on)] = set(a[a >= 0].tolist())
    assert axes["None"] - {6, 7, 8} and axes["['light']"] and axes["['light']"] <= {6, 7, 8}


def test_discontinuity_splits_only_near_it():
    """An affine target with a step at x0 = 0.3: the RRF kd-tree splits only cells that contain
    the step (along x0), and the other leaves fit below the 1 % threshold."""
    rng = np.random.default_rng(0)
    x = rng.random((2000, 2)).astype(np.float32)
    y = (1 + 0.3 * x[:, 0] + 0.2 * x[:, 1] + np.where(x[:, 0] < 0.3, 0.0, 1.0))[:, None]
    cfg = {"model": {"hidden": [3]}, "tree": {"min_samples": 40, "max_depth": 3, "threshold": 0.01, "expand": 0.0},
           "train": {"max_iters": 30, "trial_iters": 30, "progress": False}}
    params, info = rrf.fit_arrays(x, y, np.zeros(len(x), np.int32), cfg)
    tree = kdtree.KDTree(**{k: np.asarray(v) for k, v in params["tree"].items()})
    internal = np.flatnonzero(tree.axis >= 0)
    assert len(internal) >= 2
    assert np.all(tree.axis[internal] == 0)
    lo = np.where(np.isfinite(tree.cell_lo), tree.cell_lo, 0.0)[internal, 0]
    hi = np.where(np.isfinite(tree.cell_hi), tree.cell_hi, 1.0)[internal, 0]
    assert np.all((lo <= 0.3) & (hi > 0.3))
    _, leaf_lo, leaf_hi = kdtree.leaf_cells(tree)
    away = (np.nan_to_num(leaf_hi[:, 0], posinf=1.0) <= 0.3) | (np.nan_to_num(leaf_lo[:, 0], neginf=0.0) > 0.3)
    assert away.sum() == tree.n_leaves - 1 and np.all(info["leaf_val_error"][away] < 0.01)


def test_a_wall_coordinate_constant_up_to_rounding_is_never_split():
    """A wall's constant coordinate carries float32 rounding from the ray intersections (x = -1
    and the next float up). The object's kd-tree box must not stretch that to [0, 1]: the tree
    split the Cornell box's floor, ceiling and side walls on it at their roots (each leaf a
    random half of the wall, the leaves alternating pixel by pixel). Here the target does not
    depend on that coordinate at all, and a split on it halves each child's samples."""
    rng = np.random.default_rng(5)
    n = 2000
    wall = np.where(rng.random(n) < 0.5, np.float32(-1.0), np.nextafter(np.float32(-1.0), np.float32(0.0)))
    x = np.concatenate([wall[:, None], rng.uniform(-1, 1, (n, 2))], axis=1).astype(np.float32)
    y = (1.0 + np.where(x[:, 1] < 0.0, 0.0, 1.0) + 0.2 * x[:, 2])[:, None]  # a step in x1
    cfg = {"model": {"hidden": [3]}, "tree": {"min_samples": 100, "max_depth": 2, "threshold": 0.01, "axis": "all"},
           "train": {"max_iters": 10, "trial_iters": 10, "progress": False}}
    params, _ = rrf.fit_arrays(x, y, np.zeros(n, np.int32), cfg)
    axes = np.asarray(params["tree"]["axis"])
    assert (axes >= 0).any() and not (axes == 0).any()
    assert float(params["obj_hi"][0, 0] - params["obj_lo"][0, 0]) == 0.0  # the box is flat there
    # both roundings of the wall go through the same leaf
    probe = np.array([[-1.0, 0.5, 0.3], [np.nextafter(np.float32(-1.0), np.float32(0.0)), 0.5, 0.3]], np.float32)
    leaf = np.asarray(rrf_renderer._leaf_of(params, jnp.asarray(probe), jnp.zeros(2, jnp.int32)))
    assert leaf[0] == leaf[1]


def test_renderer_tanh_matches_float64():
    """The renderer's rational tanh against numpy's float64 tanh, over the float32 range that
    matters and past its clamp (+-7.9: exactly +-1 in float32), including 0 and denormal-small."""
    x = np.concatenate([np.linspace(-20, 20, 200001), [0.0, 1e-30, -1e-30, 7.9053111, -7.9053111, 1e4, -1e4]])
    x = x.astype(np.float32)
    got = np.asarray(rrf_renderer.rational_tanh(jnp.asarray(x)), np.float64)
    want = np.tanh(x.astype(np.float64))
    assert np.abs(got - want).max() <= 3.2e-7  # measured 3.13e-7 (jnp.tanh: 2.6e-7)
    assert np.all(np.abs(got) <= 1.0) and np.all(np.sign(got) == np.sign(want))


def test_every_object_the_rays_hit_gets_its_floor_of_samples():
    """``data.min_object_rays``: a tiny object hit by 3 of 1000 candidate rays keeps 2 of the 50
    drawn (uniform drawing keeps none most of the time); without a floor the draw is unchanged."""
    from types import SimpleNamespace

    n = 1000
    obj = np.zeros(n, np.int32)
    obj[[10, 500, 900]] = 7
    normal = np.tile([0.0, 1.0, 0.0], (n, 1))
    gb = SimpleNamespace(valid=np.ones(n, bool), object_id=obj, normal=normal)
    o, d = np.arange(n, dtype=np.float64)[:, None].repeat(3, 1), np.zeros((n, 3))
    kept, _ = rrf_data._balanced(gb, o, d, 50, np.random.default_rng(0), floor=2)
    assert len(kept) == 50 and len(np.unique(kept[:, 0])) == 50
    assert np.isin(kept[:, 0], [10, 500, 900]).sum() >= 2
    a, _ = rrf_data._balanced(gb, o, d, 50, np.random.default_rng(1))
    b, _ = rrf_data._balanced(gb, o, d, 50, np.random.default_rng(1), floor=0)
    np.testing.assert_array_equal(a, b)


def test_every_face_the_rays_hit_gets_its_floor_and_the_rest_stays_uniform():
    """``data.min_face_rays``: a face (same object, another normal axis) hit by 2 of 1600
    candidates keeps both of the 100 drawn with a floor of 2; the other faces keep their screen
    share (no reweighting: a face with 3 / 4 of the candidates keeps 3 / 4 of the rays not forced)."""
    from types import SimpleNamespace

    n = 1600
    normal = np.tile([0.0, 0.0, 1.0], (n, 1))
    normal[:1200] = [1.0, 0.0, 0.0]  # three quarters on the +x face
    normal[[7, 800]] = [0.0, 1.0, 0.0]  # the grazing top face
    gb = SimpleNamespace(valid=np.ones(n, bool), object_id=np.zeros(n, np.int32), normal=normal)
    o, d = np.arange(n, dtype=np.float64)[:, None].repeat(3, 1), np.zeros((n, 3))
    shares = []
    for seed in range(200):
        kept, _ = rrf_data._face_floor(gb, o, d, 100, np.random.default_rng(seed), floor=2)
        idx = kept[:, 0].astype(int)
        assert len(idx) == 100 and len(np.unique(idx)) == 100 and np.isin([7, 800], idx).all()
        shares.append(np.mean(normal[idx, 0] == 1.0))
    want = (2 + 94 * 1196 / 1594) / 100  # 2 forced, 94 uniform among the 1594 others (std of the mean 0.003)
    assert abs(np.mean(shares) - want) < 0.012, (np.mean(shares), want)


def test_face_floor_refuses_the_balanced_draws():
    with pytest.raises(ValueError, match="min_face_rays"):
        rrf_data.make_dataset({"name": "cornell_box", "area_light": False},
                              {"data": {"min_face_rays": 1, "oversample": 4}}, progress=False)


@pytest.mark.mitsuba
def test_regions_come_from_the_scene_file(mi, tmp_path):
    """Left None, the light and view regions of a scene file come from its bounds and its own
    camera: lights in the upper part of the room and outside geometry, views about the file's
    camera looking where it looks; the built-in box keeps its tuned regions."""
    from jprt.render.lightmap import free_positions
    from jprt.render.scenes import SceneHandle

    room = tmp_path / "room.xml"
    room.write_text("""<scene version="3.0.0">
  <sensor type="perspective"><float name="fov" value="50"/>
    <transform name="to_world"><lookat origin="0, 1, 3.5" target="0, 1, 0" up="0, 1, 0"/></transform></sensor>
  <shape type="cube" id="room"><transform name="to_world"><scale x="4" y="2" z="4"/>
    <translate y="2"/></transform><bsdf type="diffuse"/><boolean name="flip_normals" value="true"/></shape>
  <shape type="cube" id="pillar"><transform name="to_world"><scale x="0.6" y="2" z="0.6"/><translate y="2"/>
    </transform><bsdf type="diffuse"/></shape>
</scene>""")
    desc = {"name": "xml", "path": str(room), "keep_emitters": False}
    regions = rrf_data.scene_regions(desc)
    assert regions["source"] == "scene bounds"
    lo, hi = np.array(regions["light_lo"]), np.array(regions["light_hi"])
    np.testing.assert_allclose([lo[1], hi[1]], [0.55 * 4, 0.85 * 4], atol=1e-4)  # the room's upper part
    assert np.all(np.array(regions["view_lo"]) <= [0, 1, 3.5]) and np.all([0, 1, 3.5] <= np.array(regions["view_hi"]))
    np.testing.assert_allclose(regions["view_target"], [0, 1, 0], atol=1e-4)
    cfg = {**rrf.DEFAULT_CONFIG["data"], "n_lights": 12}
    box = rrf_data.resolve_regions(cfg, desc)
    lights = rrf_data.free_lights(desc, np.tile([0.0, 3.0, 0.0], (12, 1)), box["light_lo"], box["light_hi"],
                                  np.random.default_rng(0))  # all inside the pillar to start with
    assert free_positions(SceneHandle(desc), lights, clearance=0.1).all()
    assert rrf_data.scene_regions({"name": "cornell_box", "area_light": False})["light_lo"] == [-0.6, 0.3, -0.6]


#: A closed room with a camera of its own, nothing in it: a scene file's regions, cheaply.
_EMPTY_ROOM = """<scene version="3.0.0">
  <sensor type="perspective"><transform name="to_world"><lookat origin="0, 1, 3.5" target="0, 1, 0" up="0, 1, 0"/>
    </transform></sensor>
  <shape type="cube"><transform name="to_world"><scale x="4" y="2" z="4"/><translate y="2"/></transform>
    <bsdf type="diffuse"/><boolean name="flip_normals" value="true"/></shape>
</scene>"""


@pytest.mark.mitsuba
def test_light_spread_is_checked_and_keys_the_scene_files_data(mi, tmp_path, monkeypatch):
    """``data.light_spread``: a bad value is refused in one line; for a scene file "even" and
    "latin" are different data (cache keys), "latin" keeping the key from before the option; for
    the built-in box, whose lights are its tuned hypercube either way, the key does not change."""
    from jprt.methods.rrf import data as rrf_data

    with pytest.raises(ValueError, match="light_spread must be 'even' or 'latin'"):
        rrf_data.make_dataset({"name": "cornell_box", "area_light": False}, {"data": {"light_spread": "blue"}},
                              cache_dir=str(tmp_path), progress=False)
    specs = []

    class Captured(Exception):
        pass

    def capture(name, spec, build, **kw):
        specs.append(spec)
        raise Captured

    monkeypatch.setattr(rrf_data.cache, "cached", capture)
    room = tmp_path / "room.xml"
    room.write_text(_EMPTY_ROOM)
    for scene in ({"name": "xml", "path": str(room), "keep_emitters": False}, {"name": "cornell_box", "area_light": False}):
        for spread in ("even", "latin"):
            with pytest.raises(Captured):
                rrf_data.make_dataset(scene, {"data": {"light_spread": spread}}, cache_dir=str(tmp_path), progress=False)
    even, latin, box_even, box_latin = specs
    assert even != latin and even["data"]["light_spread"] == "even" and "even_rule" in even
    assert "light_spread" not in latin["data"] and "even_rule" not in latin and "light_rule" in latin
    assert box_even == box_latin and "light_spread" not in box_even["data"]


@pytest.mark.mitsuba
def test_even_lights_keep_the_views_and_latin_keeps_the_old_draw(mi, tmp_path):
    """``_draw`` for a scene file: "latin" is the hypercube moved off geometry by ``free_lights``
    (the draw before ``data.light_spread``); "even" changes the lights only, the views (and the
    generator the rays come from next) are "latin"'s."""
    from jprt.render.sampling import free_lights, latin_hypercube

    room = tmp_path / "room.xml"
    room.write_text(_EMPTY_ROOM)
    desc = {"name": "xml", "path": str(room), "keep_emitters": False}
    draws = {}
    for spread in ("latin", "even"):
        cfg = rrf_data.resolve_regions({**rrf.DEFAULT_CONFIG["data"], "n_lights": 6, "n_views": 3,
                                        "light_spread": spread}, desc)
        regions_from = cfg.pop("regions_from")
        assert regions_from == "scene bounds"
        draws[spread] = rrf_data._draw(desc, cfg, regions_from)
    rng = np.random.default_rng(int(cfg["seed"]))
    old = free_lights(desc, latin_hypercube(rng, 6, cfg["light_lo"], cfg["light_hi"]), cfg["light_lo"], cfg["light_hi"], rng)
    np.testing.assert_array_equal(draws["latin"][0], old)
    assert not np.array_equal(draws["even"][0], old)
    assert [s[1] for s in draws["even"][1]] == [s[1] for s in draws["latin"][1]]
    assert draws["even"][2].random() == draws["latin"][2].random()
    setups_only = rrf_data._draw(desc, cfg, regions_from, spread=False)
    np.testing.assert_array_equal(setups_only[0], old)  # even_lights skipped: the hypercube's lights
    assert [s[1] for s in setups_only[1]] == [s[1] for s in draws["even"][1]]


@pytest.mark.mitsuba
def test_even_lights_go_on_where_the_latin_draw_finds_too_little_space(mi, tmp_path):
    """A light box about 150 times the room's volume: most of it serves no view, so ``free_lights``
    gives up on some light ("latin" raises ``NoFreeSpace``), while "even", whose pool is larger,
    spreads its lights over the room (with a warning that the pool is short), and its self-check
    set draws its held-out lights in the room too (``uniform_free_lights``)."""
    from jprt.render.sampling import NoFreeSpace

    room = tmp_path / "room.xml"
    room.write_text(_EMPTY_ROOM)
    desc = {"name": "xml", "path": str(room), "keep_emitters": False}
    box = {"light_lo": [-20.0, -10.0, -20.0], "light_hi": [20.0, 14.0, 20.0]}

    def in_room(lights):
        return (np.abs(lights[:, [0, 2]]) < 4).all() and ((lights[:, 1] > 0) & (lights[:, 1] < 4)).all()

    for spread in ("latin", "even"):
        cfg = rrf_data.resolve_regions({**rrf.DEFAULT_CONFIG["data"], "n_lights": 6, "n_views": 2, "n_rays": 8,
                                        "spp": 4, "check_lights": 2, "light_spread": spread}, desc)
        cfg.pop("regions_from")
        cfg.update(box)
        if spread == "latin":
            with pytest.raises(NoFreeSpace, match="no free space for lights"):
                rrf_data._draw(desc, cfg, "scene bounds")
            continue
        with pytest.warns(UserWarning, match="acceptable candidates"):
            lights = rrf_data._draw(desc, cfg, "scene bounds")[0]
        assert lights.shape == (6, 3) and in_room(lights)
        check = rrf_data._check(desc, {"test": spread}, cfg, "scene bounds", cache_dir=str(tmp_path), progress=False)
        assert check["lights"].shape == (2, 3) and in_room(check["lights"])
        assert len(check["position"]) > 0
