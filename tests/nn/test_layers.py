"""MLP scaling and init, the factored feature field, encodings, the SG encoder CNN."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jprt.nn import count_parameters, factor_field, mlp, one_blob, roughness_remap, sg_encoder, sh4, with_scaling


def test_rrf_init_is_uniform_in_unit_interval():
    params = mlp((12, 20, 10, 3), init="rrf").init(jax.random.PRNGKey(0))
    leaves = jax.tree_util.tree_leaves(params["layers"])
    values = np.concatenate([np.asarray(v).ravel() for v in leaves])
    assert values.min() >= -1 and values.max() <= 1 and abs(values.mean()) < 0.1 and values.std() > 0.5
    assert count_parameters(params) == 12 * 20 + 20 + 20 * 10 + 10 + 10 * 3 + 3


def test_scaling_maps_ranges_to_unit_interval_and_is_not_trained():
    rng = np.random.default_rng(0)
    x = rng.uniform([0, -50, 3], [10, 50, 3], size=(200, 3)).astype(np.float32)  # last feature constant
    y = rng.uniform(100, 300, size=(200, 2)).astype(np.float32)
    net = mlp((3, 2), activation="linear", output_activation="linear", init="glorot")
    params = with_scaling(net.init(jax.random.PRNGKey(0)), x, y)
    s = params["scaling"]
    scaled = (x - np.asarray(s["in_center"])) / np.asarray(s["in_halfrange"])
    np.testing.assert_allclose(scaled[:, :2].min(axis=0), -1, atol=1e-6)
    np.testing.assert_allclose(scaled[:, :2].max(axis=0), 1, atol=1e-6)
    np.testing.assert_allclose(scaled[:, 2], 0, atol=1e-6)
    # Identity weights: output = out_center + out_halfrange * scaled input.
    params["layers"][0] = {"w": jnp.eye(3, 2), "b": jnp.zeros(2)}
    out = np.asarray(net.apply(params, x))
    np.testing.assert_allclose(out, np.asarray(s["out_center"]) + np.asarray(s["out_halfrange"]) * scaled[:, :2],
                               rtol=1e-5)
    grads = jax.grad(lambda p: jnp.sum(net.apply(p, x)))(params)
    assert all(float(jnp.abs(g).max()) == 0 for g in jax.tree_util.tree_leaves(grads["scaling"]))


def test_mlp_errors():
    with pytest.raises(ValueError, match="unknown activation"):
        mlp((2, 2), activation="gelu2")
    with pytest.raises(ValueError, match="expects inputs with 3 features"):
        net = mlp((3, 1))
        net.apply(net.init(jax.random.PRNGKey(0)), jnp.ones((2, 4)))


def test_factor_field_is_equation_7_and_chunking_is_exact():
    kw = dict(face_size=4, n_features=5, n_levels=3, features_per_level=2, log2_table_size=8, base_resolution=4,
              per_level_scale=1.5)
    field = factor_field(**kw)
    params = field.init(jax.random.PRNGKey(0))
    params["S"] = {"tables": [jax.random.normal(jax.random.PRNGKey(i), t.shape) for i, t in enumerate(params["S"]["tables"])]}
    x = jax.random.uniform(jax.random.PRNGKey(1), (9, 3))
    k = jnp.array([0, 5, 95])
    out = np.asarray(field.apply(params, x, k))
    from jprt.nn.hashgrid import hashgrid

    s = np.asarray(hashgrid(n_levels=3, n_features=2, log2_table_size=8, base_resolution=4, per_level_scale=1.5)
                   .apply(params["S"], x))  # (B, M)
    w, u = np.asarray(params["W"]), np.asarray(params["U"])
    expected = np.zeros((9, 3, 5))
    for b in range(9):
        for j, kk in enumerate(np.asarray(k)):
            for m in range(s.shape[1]):  # h_k(x) = sum_m S_m[x] W_m[k] U_m
                expected[b, j] += s[b, m] * w[kk, m] * u[m]
    np.testing.assert_allclose(out, expected, rtol=1e-4, atol=1e-6)
    chunked = factor_field(**kw, chunk=4)
    np.testing.assert_allclose(np.asarray(chunked.apply(params, x, k)), out, rtol=1e-6, atol=1e-7)
    small = factor_field(**kw, w_init=0.01).init(jax.random.PRNGKey(0))  # W ~ N(0, w_init^2), the rest as before
    np.testing.assert_allclose(np.asarray(small["W"]), 0.01 * np.asarray(field.init(jax.random.PRNGKey(0))["W"]),
                               rtol=1e-6)
    np.testing.assert_array_equal(np.asarray(small["U"]), np.asarray(field.init(jax.random.PRNGKey(0))["U"]))


def test_encodings():
    d = jnp.array([[0.0, 0.0, 1.0], [0.6, 0.8, 0.0]])
    assert sh4(d).shape == (2, 16)
    blob = one_blob(jnp.array([0.0, 0.5, 1.0]), bins=8)
    assert blob.shape == (3, 8) and int(jnp.argmax(blob[1])) in (3, 4)
    np.testing.assert_allclose(roughness_remap(jnp.array([0.0, 1.0])), [0.0, 1.0], atol=1e-7)
    r = jnp.linspace(0, 1, 50)
    assert bool(jnp.all(jnp.diff(roughness_remap(r)) > 0))
    assert float(roughness_remap(0.1)) > 3 * 0.1  # stretched near 0: more resolution at low roughness


def test_sg_encoder_matches_the_paper_layout():
    cnn = sg_encoder(image_size=128, n_lobes=16, params_per_lobe=7)
    params = jax.eval_shape(cnn.init, jax.random.PRNGKey(0))
    assert [c["w"].shape for c in params["convs"]] == [(3, 3, 3, 32), (3, 3, 32, 64), (3, 3, 64, 128), (3, 3, 128, 256)]
    assert params["dense"]["w"].shape == (8 * 8 * 256, 16 * 7)  # 8x8x256 features after four blocks
    out = jax.eval_shape(cnn.apply, params, jax.ShapeDtypeStruct((2, 128, 128, 3), jnp.float32))
    assert out.shape == (2, 16, 7)
    with pytest.raises(ValueError, match="divisible"):
        sg_encoder(image_size=100)


def test_mlp_host_init_and_ranges():
    """``init`` takes a NumPy Generator too (RRF draws thousands of tiny networks on the host):
    same shapes and distribution as the JAX path, reproducible from the seed; ``ranges`` is the
    one mapminmax (NumPy in, NumPy out) that ``with_scaling`` uses."""
    import numpy as np

    from jprt.nn.mlp import mlp, ranges, with_scaling

    net = mlp((4, 6, 2), activation="tanh", init="rrf")
    a, b = net.init(np.random.default_rng(3)), net.init(np.random.default_rng(3))
    jax_params = net.init(jax.random.PRNGKey(0))
    for la, lb, lj in zip(a["layers"], b["layers"], jax_params["layers"]):
        for k in ("w", "b"):
            assert isinstance(la[k], np.ndarray) and la[k].dtype == np.float32 and la[k].shape == lj[k].shape
            np.testing.assert_array_equal(la[k], lb[k])
            assert np.all(np.abs(la[k]) <= 1.0)
    x = np.random.default_rng(1).normal(size=(50, 4)).astype(np.float32)
    x[:, 2] = 7.0  # a constant feature maps to 0 with half-range 1
    centre, half = ranges(x)
    assert isinstance(centre, np.ndarray) and half[2] == 1.0 and centre[2] == 7.0
    scaled = with_scaling(a, x)["scaling"]
    np.testing.assert_array_equal(np.asarray(scaled["in_center"]), centre)
    np.testing.assert_array_equal(np.asarray(scaled["in_halfrange"]), half)
    np.testing.assert_allclose(np.asarray(net.apply(a, x)), np.asarray(net.apply(b, x)))
    # constant up to float32 rounding (a wall's coordinate from ray hits) is constant too
    x[:, 3] = np.float32(-1.0) + np.random.default_rng(2).integers(-2, 3, 50) * np.spacing(np.float32(1.0))
    assert ranges(x)[1][3] == 1.0 and ranges(x * 1e3)[1][3] == 1.0
    assert ranges(x)[1][0] != 1.0
    # the rule on its own (the RRF's kd-tree boxes), NumPy and JAX alike
    from jprt.nn.mlp import constant_up_to_rounding

    lo, hi = x.min(axis=0), x.max(axis=0)
    np.testing.assert_array_equal(constant_up_to_rounding(lo, hi), [False, False, True, True])
    np.testing.assert_array_equal(np.asarray(constant_up_to_rounding(jnp.asarray(lo), jnp.asarray(hi))),
                                  [False, False, True, True])
    assert not constant_up_to_rounding(np.float32(0.0), np.float32(1e-3))  # a small real spread is kept
