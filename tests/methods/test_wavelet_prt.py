"""Neural-wavelet PRT (Raghavan et al. 2023): wavelet relighting, selection, model, training."""

from __future__ import annotations

import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from jax.test_util import check_grads

from jprt.hashing import stable_hash
from jprt.inputs import CubeMap
from jprt.methods import REGISTRY
from jprt.methods.wavelet_prt import model as wp
from jprt.methods.wavelet_prt import views as wp_views
from jprt.nn.mlp import mlp
from jprt.solve import losses
from jprt.sphere import cubemap, envmap, haar

TINY = {
    "envmaps": {"synthetic": 4, "face_size": 4, "rotations_deg": [0]},
    "cameras": {"width": 12, "height": 12, "sphere": {"n": 4}, "helix": {"n": 4}, "near": 2, "far": 2},
    "data": {"spp": 8, "test_spp": 16, "envs_per_view": 1},
    "model": {"n_levels": 3, "features_per_level": 2, "log2_table_size": 8, "n_features": 8, "hidden": 16},
    "train": {"steps": 12, "pixels": 32, "wavelets": 24, "checkpoint_every": 4, "log_every": 4},
    "render": {"k": 16, "chunk": 50},
}


def _fake_data(seed=0, e=3, v=2, h=6, w=5, n=4) -> wp.WaveletData:
    """A random, Mitsuba-free dataset with the WaveletData layout."""
    rng = np.random.default_rng(seed)
    shape = (e, v, h, w)
    normal = rng.normal(size=shape + (3,))
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    train = {
        "position": rng.uniform(-1, 1, shape + (3,)), "normal": normal, "reflected": normal[..., ::-1].copy(),
        "diffuse_albedo": rng.uniform(0, 1, shape + (3,)), "specular_albedo": rng.uniform(0, 1, shape + (3,)),
        "roughness": rng.uniform(0, 1, shape), "valid": rng.uniform(size=shape) > 0.2,
        "direct": rng.uniform(0, 1, shape + (3,)), "indirect": rng.uniform(0, 0.5, shape + (3,)),
    }
    train = {k: np.asarray(a, np.bool_ if k == "valid" else np.float32) for k, a in train.items()}
    importance = np.stack([wp_views.importance_maps(train["indirect"][i], train["position"][i], train["valid"][i],
                                              train["specular_albedo"][i], train["roughness"][i]) for i in range(e)])
    envs = envmap.synthetic_environments(e, n, seed)
    return wp.WaveletData(train, importance, envs, {}, envs[:1], [f"e{i}" for i in range(e)], ["held"],
                          {}, {"spp": 1})


#: The unit box's corners: the bbox the model tests initialise with.
BOX = np.array([[-1, -1, -1], [1, 1, 1]], np.float32)


# -- wavelet selection and relighting ----------------------------------------------------------


@settings(deadline=None, max_examples=20)
@given(st.integers(0, 2**31 - 1), st.sampled_from([2, 4, 8]), st.integers(1, 40))
def test_select_wavelets_keeps_k_largest_area_weighted(seed, n, k):
    k = min(k, 6 * n * n)
    c = np.random.default_rng(seed).normal(size=(6, n, n, 3)).astype(np.float32)
    idx, vals = wp.select_wavelets(jnp.asarray(c), k)
    importance = np.linalg.norm(c, axis=-1) * np.asarray(haar.support_area(n))
    flat = importance.reshape(-1)
    kth = np.sort(flat)[::-1][k - 1]
    chosen = flat[np.asarray(idx)]
    assert len(set(np.asarray(idx).tolist())) == k
    assert np.all(chosen >= kth - 1e-6)  # nothing left out is larger than anything kept
    assert np.all(np.sort(flat)[::-1][:k] - np.sort(chosen)[::-1] <= 1e-6)
    np.testing.assert_array_equal(np.asarray(vals), c.reshape(-1, 3)[np.asarray(idx)])


def test_area_weighting_prefers_coarse_wavelets():
    n = 8
    c = np.zeros((6, n, n, 3), np.float32)
    c[0, 0, 0] = 1.0  # scaling coefficient, support = whole face
    c[0, 7, 7] = 3.0  # finest diagonal detail, support 1/16 of the face
    idx, _ = wp.select_wavelets(jnp.asarray(c), 1)
    assert int(idx[0]) == 0
    idx_plain, _ = haar.top_k(jnp.asarray(c), 1)
    assert int(idx_plain[0]) == 7 * n + 7


def test_evaluator_all_wavelets_with_exact_coefficients_equals_full_product():
    rng = np.random.default_rng(3)
    p, n = 37, 4
    transport = rng.normal(size=(p, 6, n, n, 3)).astype(np.float32)
    cube = rng.uniform(0, 2, (6, n, n, 3)).astype(np.float32)
    out = wp.transport_check(transport, cube, ks=(6 * n * n,), chunk=10)
    full = np.einsum("ptijc,tijc->pc", transport.astype(np.float64), cube.astype(np.float64))
    np.testing.assert_allclose(out["full"], full, rtol=1e-4, atol=1e-4)
    np.testing.assert_allclose(out["wavelet_all"], full, rtol=1e-4, atol=1e-4)
    np.testing.assert_allclose(out["by_k"][6 * n * n], full, rtol=1e-4, atol=1e-4)


def test_relighting_error_falls_with_k():
    rng = np.random.default_rng(4)
    p, n = 20, 8
    transport = np.abs(rng.normal(size=(p, 6, n, n, 3))).astype(np.float32)
    cube = np.asarray(envmap.synthetic_environments(1, n, 5)[0])
    out = wp.transport_check(transport, cube, ks=(8, 32, 128, 6 * n * n))
    errs = [np.linalg.norm(out["by_k"][k] - out["full"]) for k in (8, 32, 128, 6 * n * n)]
    assert errs[-1] < 1e-3 * np.linalg.norm(out["full"])
    assert errs[2] < errs[0]


def _exact_pixels(seed, p=23):
    """(transport_fn, g, light) of p pixels with random exact transport on 2^2 cube faces."""
    rng = np.random.default_rng(seed)
    t_hat = jnp.asarray(rng.normal(size=(p, 6, 2, 2, 3)).astype(np.float32))
    light = jnp.asarray(rng.normal(size=(6, 2, 2, 3)).astype(np.float32))
    return wp.exact_transport_fn(t_hat), {"pixel": jnp.arange(p, dtype=jnp.int32)}, light


def test_render_pixels_chunking_is_exact():
    fn, g, light = _exact_pixels(5)
    a = wp.render_pixels(fn, g, light, 10, chunk=23)
    b = wp.render_pixels(fn, g, light, 10, chunk=4)  # padded last chunk
    np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-6, atol=1e-6)


def test_render_pixels_skips_chunks_without_valid_pixels():
    fn, g, light = _exact_pixels(7)
    valid = np.ones(23, bool)
    valid[4:12] = False  # chunks 1 and 2 of 4 pixels hold no valid pixel; chunk 3 a partial one
    valid[12:15] = False
    full = np.asarray(wp.render_pixels(fn, g, light, 10, chunk=4))
    out = np.asarray(wp.render_pixels(fn, g, light, 10, chunk=4, valid=jnp.asarray(valid)))
    assert np.all(out[4:12] == 0) and np.any(full[4:12] != 0)
    np.testing.assert_array_equal(out[12:], full[12:])  # a chunk with a valid pixel is computed whole
    np.testing.assert_array_equal(out[:4], full[:4])


def test_auto_chunk_by_backend():
    """render.chunk 0: rows per step by backend (GPU's for backends not listed), at least one pixel."""
    assert wp.auto_chunk(64, "cpu") == 8192 // 64
    assert wp.auto_chunk(64, "gpu") == 2 ** 22 // 64 == wp.auto_chunk(64, "tpu")
    assert wp.auto_chunk(10 ** 6, "cpu") == 1
    assert wp.auto_chunk(16) == wp.auto_chunk(16, jax.default_backend())


@pytest.mark.parametrize("overrides", [{}, pytest.param({"model": {"null_transport": "free"}}, marks=pytest.mark.slow),
                                       pytest.param({"model": {"layers": 3, "hidden": 64},
                                                     "render": {"k": 32}},
                                                    marks=pytest.mark.slow)])  # the last two for the suite's budget
def test_frame_flops_is_xla_count_of_one_chunk(overrides):
    """The method's own FLOP count (XLA counts a loop body once) against XLA's cost analysis of
    a render done in one chunk: within 1 % (XLA also counts the encodings and the Haar transform)."""
    cfg = {"model": {"hidden": 128, **overrides.get("model", {})},
           "render": {"k": 64, "chunk": 8 * 8, **overrides.get("render", {})}}
    data = _fake_data(h=8, w=8, n=16)
    m = wp.model(cfg)
    params = jax.jit(m.init)(jax.random.PRNGKey(0), BOX)  # one program (eagerly, each random draw compiles)
    g = {f: jnp.asarray(data.train[f][0, 0]) for f in wp.GBUFFER_FIELDS}
    g["valid"] = jnp.ones_like(g["valid"])  # XLA counts every pixel of the one chunk
    lighting = CubeMap(data.envs[0])
    from jprt import eval as jeval

    xla = jeval.xla_flops(wp.evaluator(params, cfg), g, lighting)
    ours = wp.frame_flops(params, cfg, g, lighting)
    assert xla is not None and abs(ours / xla - 1) < 0.01, (ours, xla)
    half = dict(g, valid=g["valid"].at[:4].set(False))
    assert wp.frame_flops(params, cfg, half, lighting) == pytest.approx(ours / 2)  # valid pixels only


def test_training_wavelets_half_largest_half_uniform():
    rng = np.random.default_rng(6)
    c = jnp.asarray(rng.normal(size=(96, 3)).astype(np.float32))
    mag = np.linalg.norm(np.asarray(c), axis=-1)
    top = set(np.argsort(mag)[::-1][:10].tolist())
    seen = set()
    for s in range(30):
        idx, vals, w = wp.training_wavelets(jax.random.PRNGKey(s), c, 20)
        idx = np.asarray(idx)
        assert len(set(idx.tolist())) == 20
        assert set(idx[:10].tolist()) == top
        assert not (set(idx[10:].tolist()) & top)
        np.testing.assert_array_equal(np.asarray(vals), np.asarray(c)[idx])
        np.testing.assert_array_equal(np.asarray(w), 1.0)  # the paper's objective: no weights
        seen |= set(idx[10:].tolist())
    assert len(seen) > 60  # the uniform half reaches most of the other 86 wavelets


def test_unbiased_training_wavelets_estimate_the_full_sum():
    """sum_k w_k L_k T_k over the drawn wavelets is an unbiased estimate of the sum over all of
    them (train.objective = "unbiased"); the paper's unweighted sum misses the others' share."""
    rng = np.random.default_rng(8)
    n_all, n = 96, 20
    c = jnp.asarray(rng.normal(size=(n_all, 3)).astype(np.float32))
    t = rng.uniform(0.5, 1.5, (n_all, 3))  # a positive "transport" per wavelet and channel
    full = np.sum(np.asarray(c) * t, axis=0)
    # 2000 draws (keys 0..1999) as one vmapped program: 2000 eager calls took 12 s of dispatch
    idx, vals, w = jax.jit(jax.vmap(lambda s: wp.training_wavelets(jax.random.PRNGKey(s), c, n, unbiased=True)))(
        jnp.arange(2000))
    idx, vals, w = np.asarray(idx), np.asarray(vals), np.asarray(w)
    np.testing.assert_allclose(w[:, 10:], (n_all - 10) / 10)
    assert all(len(set(row)) == n for row in idx)  # distinct wavelets in every draw
    draws = np.sum(w[..., None] * vals * t[idx], axis=1)
    plain = np.sum(vals * t[idx], axis=1)
    se = draws.std(axis=0) / np.sqrt(len(draws))
    assert np.all(np.abs(draws.mean(axis=0) - full) < 4 * se)
    assert np.any(np.abs(np.mean(plain, axis=0) - full) > 10 * se)


def test_indirect_loss_sees_the_clipped_image_and_pushes_negatives_up():
    target = jnp.array([[0.2, 0.1, 0.0], [0.5, 0.5, 0.5]])
    pos = jnp.array([[0.3, 0.0, 0.1], [0.4, 0.6, 0.5]])
    assert float(wp.indirect_loss(pos, target, 10.0)) == pytest.approx(float(losses.mu_law_l2(pos, target, 10.0)))
    neg = pos.at[0, 0].set(-0.3)
    shown = wp.indirect_output(neg)
    assert float(shown[0, 0]) == 0.0 and bool(jnp.all(shown >= 0))
    # the clipped image's loss plus the hidden negative part's, so the gradient stays
    g = jax.grad(lambda p: wp.indirect_loss(p, target, 10.0))(neg)
    assert float(g[0, 0]) < 0  # raising the negative prediction lowers the loss
    assert float(wp.indirect_loss(neg, target, 10.0)) > float(losses.mu_law_l2(shown, target, 10.0))
    np.testing.assert_array_equal(np.asarray(wp.indirect_output(neg, False)), np.asarray(neg))


# -- loss --------------------------------------------------------------------------------------


def test_mu_law_loss_sign_extension_handles_negative_predictions():
    x = jnp.array([0.3, 2.0, 50.0])
    np.testing.assert_allclose(np.asarray(losses.mu_law(-x)), -np.asarray(losses.mu_law(x)), rtol=1e-6)
    assert float(losses.mu_law(jnp.array(0.0))) == 0.0
    target = jnp.array([[0.5, 0.2, 0.1]])
    neg = jnp.array([[-0.5, -0.2, -0.1]])
    # a negative prediction is further from a positive target than zero is, and the gradient pushes it up
    assert float(losses.mu_law_l2(neg, target)) > float(losses.mu_law_l2(jnp.zeros_like(target), target)) > 0
    grad = jax.grad(lambda p: losses.mu_law_l2(p, target))(neg)
    assert np.all(np.isfinite(np.asarray(grad))) and np.all(np.asarray(grad) < 0)
    check_grads(lambda p: losses.mu_law_l2(p, target), (neg,), order=1, modes=["rev"], eps=1e-3, atol=2e-2,
                rtol=2e-2)


# -- model -------------------------------------------------------------------------------------


def test_split_first_layer_matches_the_plain_mlp():
    free = {**TINY, "model": {**TINY["model"], "null_transport": "free"}}  # Eq. 4 as written
    m = wp.model(free)
    params = m.init(jax.random.PRNGKey(0), np.array([[-1, -1, -1], [1, 1, 1]], np.float32))
    data = _fake_data(n=4)
    g = {f: jnp.asarray(data.train[f][0, 0].reshape((-1,) + data.train[f].shape[4:])) for f in wp.GBUFFER_FIELDS}
    idx = jnp.array([0, 5, 17, 90], jnp.int32)
    t = jax.jit(m.transport)(params, g, idx)  # each side one program (eagerly, ~100 small compiles)
    mc = REGISTRY["wavelet_prt"].resolve(free)["model"]
    from jprt.nn.factor import factor_field

    field = factor_field(face_size=4, n_features=mc["n_features"], n_levels=mc["n_levels"],
                         features_per_level=mc["features_per_level"], log2_table_size=mc["log2_table_size"],
                         base_resolution=mc["base_resolution"], per_level_scale=mc["per_level_scale"])

    @jax.jit
    def plain(params, g, idx):  # the field, then one MLP over [h_k, pixel features]
        x = (g["position"] - params["bbox"][0][None]) / (params["bbox"][1] - params["bbox"][0])[None]
        h = field.apply(params["field"], jnp.clip(x, 0, 1), idx)
        pix = wp.pixel_features(g, "sh4")
        inp = jnp.concatenate([h, jnp.broadcast_to(pix[:, None], h.shape[:2] + pix.shape[-1:])], axis=-1)
        f = mlp((inp.shape[-1], mc["hidden"], mc["hidden"], 3), activation="relu", init="he")
        return f.apply(params["f"], inp) * (4 * np.pi / (6 * 16))

    np.testing.assert_allclose(np.asarray(t), np.asarray(plain(params, g, idx)), rtol=1e-4, atol=1e-6)


def test_null_transport_zero_subtracts_what_zero_features_transport():
    """``model.null_transport = "zero"``: T_k = f(h_k, pixel) - f(0, pixel), so a wavelet whose
    row of W is zero transports nothing (with "free", Eq. 4, it transports f(0, pixel)): exactly
    nothing in training's difference form, to f's rounding in the run-time form, which otherwise
    agrees with it."""
    data = _fake_data(n=4)
    g = {f: jnp.asarray(data.train[f][0, 0].reshape((-1,) + data.train[f].shape[4:])) for f in wp.GBUFFER_FIELDS}
    idx = jnp.array([0, 5, 17, 90], jnp.int32)
    free = wp.model({**TINY, "model": {**TINY["model"], "null_transport": "free"}})
    zero = wp.model({**TINY, "model": {**TINY["model"], "null_transport": "zero"}})
    params = free.init(jax.random.PRNGKey(0), np.array([[-1, -1, -1], [1, 1, 1]], np.float32))
    silent = dict(params, field=dict(params["field"], W=params["field"]["W"].at[idx[:2]].set(0.0)))

    @jax.jit
    def both(p):
        run_time = zero.head(p, zero.prepare(p, g, exact=False), idx)
        return free.transport(p, g, idx), zero.transport(p, g, idx), run_time

    t_free, t_zero, t_run = both(silent)
    null = t_free[:, :1]  # f(0, pixel): what the zeroed wavelet 0 transports under Eq. 4
    assert float(jnp.min(jnp.abs(null).sum(-1))) > 0  # Eq. 4 transports something for h_k = 0
    np.testing.assert_allclose(np.asarray(t_zero), np.asarray(t_free - null), rtol=1e-4, atol=1e-6)
    assert not np.any(np.asarray(t_zero[:, :2]))
    assert float(jnp.abs(t_run[:, :2]).max()) < 1e-6 * float(jnp.abs(null).max())
    np.testing.assert_allclose(np.asarray(t_run), np.asarray(t_zero), rtol=1e-4, atol=1e-6)
    with pytest.raises(ValueError, match="null_transport"):
        wp.model({**TINY, "model": {**TINY["model"], "null_transport": "mean"}})


@pytest.mark.parametrize("reflection, size", [("sh4", 16), ("raw", 3), ("none", 0)])
def test_pixel_features_reflection_encodings(reflection, size):
    g = {"reflected": jnp.array([[0.0, 1.0, 0.0]]), "normal": jnp.array([[0.0, 0.0, 1.0]]),
         "diffuse_albedo": jnp.ones((1, 3)), "specular_albedo": jnp.ones((1, 3)), "roughness": jnp.array([1.0])}
    assert wp.pixel_features(g, reflection).shape == (1, size + 10)
    with pytest.raises(ValueError, match="reflection"):
        wp.model({"model": {"reflection": "dce"}})


@pytest.mark.slow  # ~10 s (suite budget): float64 check_grads of the whole model; training tests run its gradients
def test_model_gradients():
    """Reverse-mode gradients of T_k w.r.t. every parameter (float64, so finite differences
    with a small step do not cross ReLU kinks)."""
    m = wp.model(TINY)
    data = _fake_data(n=4)
    with jax.enable_x64(True):
        params = m.init(jax.random.PRNGKey(1), np.array([[-1, -1, -1], [1, 1, 1]], np.float32))
        params = jax.tree_util.tree_map(lambda a: jnp.asarray(a, jnp.float64), params)
        params["field"]["S"]["tables"] = [t * 1e3 for t in params["field"]["S"]["tables"]]  # away from ~0
        g = {f: jnp.asarray(data.train[f][0, 0].reshape((-1,) + data.train[f].shape[4:]))[:6].astype(
            jnp.float64 if f != "valid" else bool) for f in wp.GBUFFER_FIELDS}
        idx = jnp.array([1, 2, 40], jnp.int32)
        trainable = {"field": params["field"], "f": params["f"]}

        def fn(p):
            return jnp.sum(m.transport(dict(params, **p), g, idx) ** 2)

        check_grads(fn, (trainable,), order=1, modes=["rev"], eps=1e-5, atol=1e-4, rtol=1e-4)


# -- data helpers ------------------------------------------------------------------------------


def test_importance_maps_are_distributions_over_valid_pixels():
    data = _fake_data()
    for e in range(data.importance.shape[0]):
        p = data.importance[e]
        valid = data.train["valid"][e].reshape(-1)
        np.testing.assert_allclose(p.sum(axis=1), 1.0, rtol=1e-5)
        assert np.all(p[:, ~valid] == 0)
        np.testing.assert_allclose(p[0, valid], 1.0 / valid.sum(), rtol=1e-5)


def test_importance_view_variance_finds_view_dependent_voxels():
    v, h, w = 4, 8, 8
    pos = np.zeros((v, h, w, 3), np.float32)
    pos[:, :, :4] = [0.1, 0.1, 0.1]
    pos[:, :, 4:] = [0.9, 0.9, 0.9]
    ind = np.ones((v, h, w, 3), np.float32)
    ind[:, :, 4:] *= np.arange(1, v + 1)[:, None, None, None]  # right half changes with the view
    p = wp_views.importance_maps(ind, pos, np.ones((v, h, w), bool), np.zeros((v, h, w, 3)), np.ones((v, h, w)))
    view = p[1].reshape(v, h, w)
    assert view[:, :, :4].sum() == 0 and view[:, :, 4:].sum() == pytest.approx(1.0, rel=1e-5)


def test_environment_preparation():
    rng = np.random.default_rng(0)
    eq = rng.uniform(0.5, 2.0, (32, 64, 3)).astype(np.float32)
    cube = envmap.prepare_environment(eq, 8)
    omega = np.asarray(cubemap.texel_solid_angles(8))
    assert cube.shape == (6, 8, 8, 3)
    assert np.sum(cube.mean(-1) * omega) / (4 * np.pi) == pytest.approx(1.0, rel=1e-4)
    np.testing.assert_array_equal(envmap.rotate_equirect(eq, 360.0 / 64 * 3), np.roll(eq, 3, axis=1))
    re = envmap.render_equirect(cube, scale=4)
    d = np.asarray(cubemap.equirect_directions(*re.shape[:2]))
    np.testing.assert_array_equal(re, np.asarray(cubemap.sample_cubemap_nearest(jnp.asarray(cube), d)))


def test_trajectories():
    spec = {"radius": 2.0, "azimuth": [-30.0, 30.0], "elevation": [0.0, 40.0], "turns": 2.0}
    for kind in ("sphere", "helix"):
        o = wp_views.trajectory(kind, 10, spec, [0, 0, 0])
        np.testing.assert_allclose(np.linalg.norm(o, axis=-1), 2.0, rtol=1e-6)
        el = np.degrees(np.arcsin(o[:, 1] / 2.0))
        assert el.min() >= -1e-6 and el.max() <= 40 + 1e-6
    with pytest.raises(ValueError, match="trajectory"):
        wp_views.trajectory("spiral", 3, spec, [0, 0, 0])


def test_indirect_baseline_scale_is_least_squares():
    rng = np.random.default_rng(1)
    d = rng.uniform(0, 1, (5, 4, 4, 3)).astype(np.float32)
    c = np.array([0.2, 0.5, 0.1], np.float32)
    valid = rng.uniform(size=(5, 4, 4)) > 0.3
    np.testing.assert_allclose(wp.indirect_baseline_scale(d, d * c, valid), c, rtol=1e-5)


# -- training ----------------------------------------------------------------------------------


@pytest.mark.slow  # make test runs the stronger tests/faults/: the same resume after a SIGKILL
def test_training_resumes_bit_identically(tmp_path):
    data = _fake_data(n=4)
    full = wp.fit(data, TINY, checkpoint_path=str(tmp_path / "a.npz"), progress=False)
    part = wp.fit(data, TINY, checkpoint_path=str(tmp_path / "b.npz"), progress=False, stop_after=5)
    assert part.info["step"] == 5
    rest = wp.fit(data, TINY, checkpoint_path=str(tmp_path / "b.npz"), progress=False)
    assert rest.info["resumed_from"] == 5 and rest.info["step"] == TINY["train"]["steps"]
    for a, b in zip(jax.tree_util.tree_leaves(full.params), jax.tree_util.tree_leaves(rest.params)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    np.testing.assert_array_equal(full.info["losses"][5:], rest.info["losses"])


def test_exact_objective_trains_on_every_wavelet_and_unknown_objectives_raise():
    data = _fake_data(n=4)
    cfg = dict(TINY, train=dict(TINY["train"], steps=3, objective="exact"))
    res = wp.fit(data, cfg, progress=False)
    assert len(res.info["losses"]) == 3 and np.all(np.isfinite(res.info["losses"]))
    with pytest.raises(ValueError, match="unknown train.objective 'all'"):
        wp.fit(data, dict(TINY, train=dict(TINY["train"], objective="all")), progress=False)


def _fine_share(params, data, cfg, first_fine: int) -> float:
    """The share of sum |L_k T_k|^2 over every training pixel and wavelet that the detail levels
    >= ``first_fine`` carry, under the training lightings."""
    m = wp.model(cfg)
    n = m.face_size
    idx = jnp.arange(6 * n * n, dtype=jnp.int32)
    w = haar.unflatten_index(idx, n)
    fine = np.asarray((w.level >= first_fine) & (w.band != haar.BAND_SCALING))
    dev = wp._device_data(data)
    total = carried = 0.0
    for e in range(dev["coeffs"].shape[0]):
        g = {f: dev[f][e] for f in m.fields}
        light = np.square(np.asarray(m.transport(params, g, idx)) * np.asarray(dev["coeffs"][e])[None])
        light = light[np.asarray(dev["valid"][e], bool)]
        total, carried = total + light.sum(), carried + light[:, fine].sum()
    return carried / total


@pytest.mark.slow  # ~10 s: two 100-step fits (the switch is off by default; its key and checks are below)
def test_fine_penalty_moves_light_out_of_the_fine_levels():
    """``train.fine_penalty``: the finest level's share of the light falls to under a quarter of
    what the same fit without it puts there."""
    data = _fake_data(n=4)
    base = dict(TINY, train=dict(TINY["train"], steps=100))
    shares = {}
    for penalty in (0.0, 30.0):
        cfg = dict(base, train=dict(base["train"], fine_penalty=penalty, fine_levels=1))
        shares[penalty] = _fine_share(wp.fit(data, cfg, progress=False).params, data, cfg, first_fine=1)
    assert shares[0.0] > 0.02 and shares[30.0] < 0.25 * shares[0.0], shares  # measured 0.042 and 0.0023


def test_fine_penalty_off_keeps_the_run_key_and_bad_values_raise():
    """``train.fine_penalty`` 0 (the default) leaves ``run_key`` as it was before the switch
    existed (whatever ``fine_levels`` says); negative penalties and more levels than the face has
    raise before training."""
    base = dict(TINY, train=dict(TINY["train"], steps=100))
    cfg = wp._cfg(base)
    before = {**{k: cfg[k] for k in ("scene", "envmaps", "cameras", "data")},  # the key's old content
              "model": {k: v for k, v in cfg["model"].items() if k != "lighting_levels"},
              "train": {k: v for k, v in cfg["train"].items() if k not in ("fine_penalty", "fine_levels")}}
    assert wp.run_key(base) == stable_hash(before) == wp.run_key(dict(base, train=dict(base["train"], fine_levels=1)))
    assert wp.run_key(base) != wp.run_key(dict(base, train=dict(base["train"], fine_penalty=1.0)))
    for bad in ({"fine_penalty": -1.0}, {"fine_levels": 3}):
        with pytest.raises(ValueError, match="fine_"):
            wp.fit(_fake_data(n=4), dict(base, train=dict(base["train"], **bad)), progress=False)


def _box_filtered(cube, face: int):
    """A (6, n, n, 3) cube map box-filtered to face size ``face`` and repeated back to n."""
    n = cube.shape[1]
    r = n // face
    means = cube.reshape(6, face, r, face, r, 3).mean(axis=(2, 4))
    return np.repeat(np.repeat(means, r, axis=1), r, axis=2)


def test_lighting_levels_read_the_box_filtered_map():
    """``model.lighting_levels`` D: the kept coefficients are each face's 2^D x 2^D Mallat block
    (6 x 4^D of them), and zeroing the others is the cube map box-filtered to face 2^D (energy
    kept), so the evaluator gives the same image under a map and under its box-filtered copy;
    training draws only kept wavelets; None keeps the run key; bad values raise."""
    n = 8
    assert [int(wp.lighting_mask(n, d).sum()) for d in (0, 1, 2, 3, None)] == [6, 24, 96, 384, 384]
    rng = np.random.default_rng(4)
    cube = rng.lognormal(size=(6, n, n, 3)).astype(np.float32)
    mask = wp.lighting_mask(n, 1).reshape(6, n, n, 1)
    kept = np.asarray(haar.inverse(haar.forward(jnp.asarray(cube)) * mask))
    np.testing.assert_allclose(kept, _box_filtered(cube, 2), rtol=1e-5, atol=1e-6)
    allowed = wp.lighting_mask(n, 2)
    idx, _, _ = wp.training_wavelets(jax.random.PRNGKey(0), jnp.asarray(cube.reshape(-1, 3)), 40, allowed=allowed)
    assert allowed[np.asarray(idx)].all() and len(set(np.asarray(idx).tolist())) == 40
    with pytest.raises(ValueError, match="cannot select 97"):
        wp.training_wavelets(jax.random.PRNGKey(0), jnp.asarray(cube.reshape(-1, 3)), 97, allowed=allowed)
    data = _fake_data(n=4)
    cfg = dict(TINY, model=dict(TINY["model"], lighting_levels=1), train=dict(TINY["train"], steps=3))
    res = wp.fit(data, cfg, progress=False)
    g = {f: data.train[f][0, 0] for f in wp.GBUFFER_FIELDS}
    env = data.envs[0]
    ev = wp.evaluator(res.params, cfg)
    out, out_box = np.asarray(ev(g, CubeMap(env))), np.asarray(ev(g, CubeMap(_box_filtered(env, 2))))
    assert np.abs(out).max() > 0
    np.testing.assert_allclose(out, out_box, rtol=1e-4, atol=1e-6 * np.abs(out).max())
    assert wp.run_key(TINY) == wp.run_key(dict(TINY, model=dict(TINY["model"], lighting_levels=None)))
    assert wp.run_key(TINY) != wp.run_key(cfg)
    with pytest.raises(ValueError, match="render.k must be in \\[1, 24\\]"):  # 6 x 4^1 wavelets to choose from
        wp.evaluator(res.params, dict(cfg, render={"k": 25}))
    for bad in (3, -1, 1.5, True):
        with pytest.raises(ValueError, match="lighting_levels"):
            wp.lighting_mask(4, bad)


def test_sun_skies_hold_a_sun_in_one_texel():
    """Mean radiance 1; the brightest texel (above the horizon) holds 20-80 % of the energy; seeded."""
    from jprt.sphere import cubemap

    maps = envmap.sun_skies(6, 8, seed=3)
    omega = np.asarray(cubemap.texel_solid_angles(8))
    d = np.asarray(cubemap.texel_directions(8))
    for m in maps:
        energy = m.mean(-1) * omega
        assert energy.sum() / (4 * np.pi) == pytest.approx(1.0, rel=1e-5)
        sun = np.unravel_index(np.argmax(energy), energy.shape)
        assert 0.2 <= energy[sun] / energy.sum() <= 0.81 and d[sun][1] >= -0.2  # 0.8 + the sky in that texel
    np.testing.assert_array_equal(maps, envmap.sun_skies(6, 8, seed=3))


def test_fit_rejects_mismatched_face_size():
    with pytest.raises(ValueError, match="face size"):
        wp.fit(_fake_data(n=4), {"envmaps": {"face_size": 8}}, progress=False)


def test_evaluator_masks_invalid_pixels_and_checks_k():
    """On the model as ``init`` draws it: masking and the k check do not depend on training (the
    module's fits and the contract test evaluate trained models)."""
    data = _fake_data(n=4)
    params = wp.model(TINY).init(jax.random.PRNGKey(0), BOX)  # eagerly, as fit does: compiled once for the module
    ev = wp.evaluator(params, TINY)
    g = {f: data.train[f][0, 0] for f in wp.GBUFFER_FIELDS}
    out = np.asarray(ev(g, CubeMap(data.envs[0])))
    assert out.shape == g["valid"].shape + (3,)
    assert np.all(out[~g["valid"]] == 0) and np.all(np.isfinite(out))
    assert np.abs(out[g["valid"]]).max() > 0  # the valid pixels are lit: the zeros are the mask's
    with pytest.raises(ValueError, match="render.k must be"):
        wp.evaluator(params, dict(TINY, render={"k": 6 * 16 + 1}))


def test_per_vertex_variant_trains_and_renders():
    """Table 6's baseline: features at mesh vertices, interpolated (weights over 4 slots), softplus."""
    data = _fake_data(n=4)
    rng = np.random.default_rng(0)
    n_vertices = 50
    extra = {"vertex_index": rng.integers(0, n_vertices, data.train["valid"].shape + (4,)).astype(np.int32),
             "vertex_weight": rng.dirichlet(np.ones(4), data.train["valid"].shape).astype(np.float32)}
    cfg = dict(TINY, model=dict(TINY["model"], spatial="vertex"), train=dict(TINY["train"], steps=3))
    with pytest.raises(ValueError, match="vertex"):
        wp.fit(data, cfg, progress=False)
    data = data._replace(train={**data.train, **extra}, stats={"n_vertices": n_vertices})
    res = wp.fit(data, cfg, progress=False)
    assert res.params["field"]["S"]["vertex"].shape[0] == n_vertices
    g = {f: data.train[f][0, 0] for f in list(wp.GBUFFER_FIELDS) + list(wp.VERTEX_FIELDS)}
    out = np.asarray(wp.evaluator(res.params, cfg)(g, CubeMap(data.envs[0])))
    assert out.shape == g["valid"].shape + (3,) and np.all(np.isfinite(out))


def test_turned_maps_follow_the_rotation():
    """turn_equirect: the identity keeps the map; a turn about +Y is rotate_equirect's column roll;
    a seeded random_rotation is a rotation, and turns a sun to R times its direction; the
    rotations are uniform (the mean matrix of many is near 0)."""
    rng = np.random.default_rng(0)
    eq = rng.uniform(0.5, 2.0, (32, 64, 3)).astype(np.float32)
    np.testing.assert_array_equal(envmap.turn_equirect(eq, np.eye(3)), eq)
    a = np.radians(90.0)
    about_y = np.array([[np.cos(a), 0.0, -np.sin(a)], [0.0, 1.0, 0.0], [np.sin(a), 0.0, np.cos(a)]])
    np.testing.assert_array_equal(envmap.turn_equirect(eq, about_y), envmap.rotate_equirect(eq, 90.0))
    rs = np.stack([envmap.random_rotation(np.random.default_rng([5, i])) for i in range(500)])
    np.testing.assert_allclose(rs @ np.swapaxes(rs, 1, 2), np.broadcast_to(np.eye(3), rs.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(rs), 1.0, atol=1e-12)
    assert np.abs(rs.mean(axis=0)).max() < 0.1  # E[R] = 0 for the uniform (Haar) measure; 500 draws
    sun = np.zeros((64, 128, 3), np.float32)
    d = np.asarray(cubemap.equirect_directions(64, 128))
    sun[20, 30] = 1.0
    turned = envmap.turn_equirect(sun, rs[0])
    hit = np.unravel_index(np.argmax(turned[..., 0]), turned.shape[:2])
    assert np.dot(d[hit], rs[0] @ d[20, 30]) > np.cos(np.radians(4.0))  # within a texel or so


@pytest.fixture(scope="module")
def maps_decoded_once():
    """``jprt.io.read_hdr`` remembering what it decoded, for this module: each lighting set below
    reads all twelve 1k maps of the assets folder, and decoding them was most of these tests' time.
    Each call gets its own copy."""
    from jprt import io as jio

    read, decoded = jio.read_hdr, {}

    def read_hdr(path, *args, **kwargs):
        key = (os.path.abspath(path), args, tuple(sorted(kwargs.items())))
        if key not in decoded:
            decoded[key] = read(path, *args, **kwargs)
        return np.array(decoded[key], copy=True)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(jio, "read_hdr", read_hdr)
        yield


@pytest.mark.mitsuba
# the plain file maps (0.0, 0.0) with the slow tests: the per-image and tilted cases hold them too
@pytest.mark.parametrize("fraction, tilt", [pytest.param(0.0, 0.0, marks=pytest.mark.slow), (0.5, 0.0), (0.0, 1.0)])
def test_per_image_lightings_never_use_a_held_out_map(mi, assets, maps_decoded_once, fraction, tilt):
    from jprt.methods.wavelet_prt import data as wp_data

    ecfg = dict(wp.DEFAULT_CONFIG["envmaps"], folder=os.path.join(assets, "envmaps"), face_size=4,
                procedural_fraction=fraction, tilt=tilt)
    envs, names, tests, held = wp_data._environment_sets(ecfg, 0, 12)
    assert envs.shape == (12, 6, 4, 4, 3) and len(names) == 12 and np.all(envs >= 0)
    assert tests.shape[0] == len(held) == 6
    assert not any(name.split("@")[0].split(" turned")[0] in held for name in names)
    n_proc = sum(name.startswith("procedural") for name in names)
    assert (n_proc == 0) == (fraction == 0.0)
    assert len(set(names)) == 12  # twelve distinct lightings (uniform angles), not maps x 3 rotations
    assert all((" turned " in name) == (tilt == 1.0) for name in names)
    if tilt:  # turned in 3D, the sky is no longer always above: the +Y face's share of the light varies
        omega = np.asarray(cubemap.texel_solid_angles(4))
        energy = envs.mean(-1) * omega  # (E, 6, n, n)
        up = energy[:, 2].sum(axis=(1, 2)) / energy.sum(axis=(1, 2, 3))
        assert up.min() < 0.1 < 0.3 < up.max()
    with pytest.raises(ValueError, match="envmaps.tilt"):
        wp_data._environment_sets(dict(ecfg, tilt=1.5), 0, 12)


@pytest.mark.mitsuba
def test_cameras_without_a_target_come_from_the_scene_file(mi, tmp_path):
    """cameras.target None: views about the file's own camera (scene_regions), every set its size."""
    from jprt.methods.wavelet_prt import data as wp_data
    from jprt.render.sampling import scene_regions

    path = tmp_path / "room.xml"
    path.write_text("""<scene version="3.0.0"><sensor type="perspective"><float name="fov" value="50"/>
      <transform name="to_world"><lookat origin="0, 0, 4" target="0, 0, 0" up="0, 1, 0"/></transform></sensor>
      <shape type="cube"><bsdf type="diffuse"/></shape></scene>""")
    desc = {"name": "xml", "path": str(path), "keep_emitters": False}
    ccfg = dict(wp.DEFAULT_CONFIG["cameras"], target=None, sphere={"n": 5}, helix={"n": 2}, near=3, far=0)
    train, near, far, target, fov = wp_data._cameras(desc, ccfg, seed=0)
    regions = scene_regions(desc)
    assert (train.shape, near.shape, far.shape) == ((7, 3), (3, 3), (0, 3))
    for origins in (train, near):
        assert np.all(origins >= np.asarray(regions["view_lo"]) - 1e-9)
        assert np.all(origins <= np.asarray(regions["view_hi"]) + 1e-9)
    assert not np.allclose(train[:3], near)  # each set its own seed
    np.testing.assert_allclose(target, regions["view_target"])
    assert fov == pytest.approx(regions["fov"])
    orbit = wp_data._cameras(desc, wp.DEFAULT_CONFIG["cameras"], seed=0)  # a target: the orbits, as before
    np.testing.assert_array_equal(orbit[0], wp_views.camera_sets(wp.DEFAULT_CONFIG["cameras"], 0)[0])


@pytest.mark.mitsuba
def test_centre_ray_targets_are_the_radiance_at_the_gbuffers_points(mi):
    """``data.rays = "centre"``: every training and test target is traced along the pixel-centre
    ray the G-buffer reads, so where that ray misses the scene the indirect light is exactly 0;
    the default rendered images ("image") average each pixel's footprint and light some of those
    pixels from the surfaces beside them. Unknown values are refused."""
    from jprt.methods.wavelet_prt import data as wp_data

    preset = REGISTRY["wavelet_prt"].presets["test"]
    small = {**preset, "cameras": {**preset["cameras"], "width": 8, "height": 8, "sphere": {"n": 2}, "helix": {"n": 1},
                                   "near": 1, "far": 1}, "data": {**preset["data"], "spp": 4, "test_spp": 4}}
    sets = {}
    for rays in ("image", "centre"):
        cfg = REGISTRY["wavelet_prt"].resolve({**small, "data": {**small["data"], "rays": rays}})
        sets[rays] = wp_data.make_dataset(cfg["scene"], cfg, progress=False)
    for rays, data in sets.items():
        views = [data.train] + [data.tests[n] for n in ("near", "far")]
        missed = np.concatenate([np.abs(v["indirect"][~v["valid"].astype(bool)]).max(-1).ravel() for v in views])
        assert missed.size > 0  # the open top and the box's outline: some pixels' centre rays miss
        if rays == "centre":
            assert not np.any(missed)
        else:
            assert np.sum(missed > 0) > 0
    np.testing.assert_array_equal(sets["image"].train["position"], sets["centre"].train["position"])  # same views
    with pytest.raises(ValueError, match="data.rays"):
        cfg = REGISTRY["wavelet_prt"].resolve({**small, "data": {**small["data"], "rays": "jittered"}})
        wp_data.make_dataset(cfg["scene"], cfg, progress=False)
