"""Data-driven PRT (Belcour et al. 2022): linear algebra, measurement points, evaluator."""

import warnings

import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp
from scipy.spatial.distance import pdist

import jax

from jprt.inputs import PointRadiance
from jprt.methods.datadriven import model as dd
from jprt.methods.lightmap_lookup import atlas_inputs, shown_texels, texel_modulation


def _layout(params, texels, res=8):
    """Attach a trivial lightmap layout (texel t at flat atlas index t) so the evaluator runs."""
    params = dict(params)
    params["texel_index"] = np.arange(texels, dtype=np.int32)
    fill = np.minimum(np.arange(res * res), texels - 1).astype(np.int32)
    params["fill_index"] = fill
    params["fine_index"] = np.arange(len(params["group"]), dtype=np.int32)
    return params


def _linear_transport(rng, p=12, t=60, n=40, colour_mix=False):
    """Known transport: indirect = M_true direct per channel (or mixing channels)."""
    m_true = rng.random((t, p)) * (rng.random((t, p)) < 0.5)
    direct = rng.random((n, p, 3)) + 0.05
    if colour_mix:
        big = rng.random((3 * t, 3 * p))
        indirect = (direct.reshape(n, -1) @ big.T).reshape(n, t, 3)
        return big, direct, indirect
    return m_true, direct, np.einsum("tp,npc->ntc", m_true, direct)


# ---------------------------------------------------------------------------------------------
# Exact recovery of a known linear transport (noise free, full rank)


@pytest.mark.parametrize("channels", ["mono", "multi"])
def test_recovers_known_linear_transport_exactly(channels):
    rng = np.random.default_rng(0)
    p, t = 10, 50
    n = 40 if channels == "mono" else 80  # multi needs N >= 3P examples for a full-rank D
    m_true, direct, indirect = _linear_transport(rng, p, t, n, colour_mix=channels == "multi")
    rank = p if channels == "mono" else 3 * p
    cfg = {"basis": {"n": rank, "center": False, "channels": channels}, "transfer": {"lam": 0.0}}
    params = dd.fit_arrays(direct, indirect, np.arange(p), cfg).params
    # effective operator U_n M_n equals the true transport
    u, m = params["basis"].astype(np.float64), params["transfer"].astype(np.float64)
    if channels == "mono":
        for c in range(3):
            np.testing.assert_allclose(u @ m[c], m_true, atol=2e-5 * np.abs(m_true).max())
    else:
        np.testing.assert_allclose(u @ m, m_true, atol=2e-5 * np.abs(m_true).max())
    # and held-out lighting is reproduced through the jitted lightmap
    fresh = rng.random((4, p, 3))
    if channels == "mono":
        expected = np.einsum("tp,npc->ntc", m_true, fresh)
    else:
        expected = (fresh.reshape(4, -1) @ m_true.T).reshape(4, t, 3)
    got = np.asarray(dd.lightmap(params, fresh, cfg))
    np.testing.assert_allclose(got, expected, rtol=1e-4, atol=1e-4 * np.abs(expected).max())


def test_centred_basis_interpolates_training_examples():
    """With the mean (scaled by |x|, §4.2) and P >= N the fit reproduces every training example."""
    rng = np.random.default_rng(1)
    p, t, n = 30, 80, 20
    _, direct, indirect = _linear_transport(rng, p, t, n)
    params = dd.fit_arrays(direct, indirect, np.arange(p), {"basis": {"n": p + 1}, "transfer": {"lam": 0.0}}).params
    got = np.asarray(dd.lightmap(params, direct))
    np.testing.assert_allclose(got, indirect, rtol=1e-4, atol=1e-4 * np.abs(indirect).max())
    # the projection of the training set onto its own full basis is exact too
    np.testing.assert_allclose(dd.project(params, direct, indirect), indirect, atol=1e-5 * np.abs(indirect).max())


def test_intensity_scaling_is_linear():
    """Normalising by |x| and scaling the mean back makes the output homogeneous of degree 1."""
    rng = np.random.default_rng(2)
    _, direct, indirect = _linear_transport(rng, 8, 30, 50)
    cfg = {"basis": {"n": 5}}
    params = dd.fit_arrays(direct, indirect + 0.01 * rng.random(indirect.shape), np.arange(8), cfg).params
    x = rng.random((8, 3))
    np.testing.assert_allclose(np.asarray(dd.lightmap(params, 7.5 * x, cfg)), 7.5 * np.asarray(dd.lightmap(params, x, cfg)),
                               rtol=1e-5, atol=1e-6)


# ---------------------------------------------------------------------------------------------
# Ridge regression and its limit


@pytest.mark.parametrize("rank_deficient", [False, True])
def test_ridge_tends_to_the_pseudo_inverse(rank_deficient):
    rng = np.random.default_rng(3)
    d = rng.normal(size=(12, 20))
    if rank_deficient:
        d[5] = d[2]  # duplicate measurement point
        d[:, 7] = 0.0  # a light that reaches no point
    target = np.linalg.pinv(d, rcond=1e-12)
    errors = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", dd.IllConditionedWarning)
        for lam in (1e-1, 1e-3, 1e-5, 1e-7, 1e-9):
            pinv, _ = dd.ridge_pinv(d, lam)
            errors.append(np.abs(pinv - target).max())
        exact, _ = dd.ridge_pinv(d, 0.0)
    assert all(b < a for a, b in zip(errors, errors[1:])), errors
    assert errors[-1] < 1e-6
    np.testing.assert_allclose(exact, target, atol=1e-10)


def test_both_gram_orientations_agree_for_positive_lambda():
    """Erratum of Eq. 13-14: (D^T D + lam)^-1 D^T == D^T (D D^T + lam)^-1 == ridge_pinv."""
    rng = np.random.default_rng(4)
    d = rng.normal(size=(9, 15))
    lam = 0.3
    a = np.linalg.solve(d.T @ d + lam * np.eye(15), d.T)
    b = d.T @ np.linalg.inv(d @ d.T + lam * np.eye(9))
    c, _ = dd.ridge_pinv(d, lam)
    np.testing.assert_allclose(a, b, atol=1e-10)
    np.testing.assert_allclose(c, a, atol=1e-10)


def test_ill_conditioned_direct_matrix_warns_and_stays_finite():
    rng = np.random.default_rng(5)
    p, t, n = 10, 40, 30
    _, direct, indirect = _linear_transport(rng, p, t, n)
    direct[:, 3] = direct[:, 2]  # duplicate measurement points
    direct[4] = 0.0  # a configuration whose light reaches no measurement point
    with pytest.warns(dd.IllConditionedWarning) as record:
        params = dd.fit_arrays(direct, indirect, np.arange(p), {"basis": {"n": 8}, "transfer": {"lam": 0.0}}).params
    messages = " ".join(str(w.message) for w in record)
    assert "condition number" in messages and "zero direct vector" in messages
    for key in ("mean", "basis", "transfer"):
        assert np.isfinite(params[key]).all(), key
    assert np.isfinite(np.asarray(dd.lightmap(params, direct[0]))).all()
    assert np.isfinite(np.asarray(dd.lightmap(params, np.zeros((p, 3))))).all()  # zero light -> finite (zero)
    np.testing.assert_allclose(np.asarray(dd.lightmap(params, np.zeros((p, 3)))), 0.0)


def test_all_zero_direct_is_an_error():
    with pytest.raises(ValueError, match="no light reaches"):
        dd.fit_arrays(np.zeros((4, 3, 3)), np.ones((4, 5, 3)), np.arange(3))


# ---------------------------------------------------------------------------------------------
# Gamma space (§5.3)


@settings(max_examples=50, deadline=None)
@given(hnp.arrays(np.float64, st.integers(1, 30), elements=st.floats(-1e4, 1e4, allow_nan=False)),
       st.floats(1.0, 3.0))
def test_gamma_round_trip(values, gamma):
    np.testing.assert_allclose(dd.gamma_decode(dd.gamma_encode(values, gamma), gamma), values, rtol=1e-9, atol=1e-9)
    # float32 in JAX on the values padded to the longest draw: the maps are elementwise, and one
    # shape compiles their operations once instead of once per drawn length
    padded = jnp.asarray(np.pad(values, (0, 30 - len(values))), jnp.float32)
    got = np.asarray(dd.gamma_decode(dd.gamma_encode(padded, gamma), gamma))[:len(values)]
    np.testing.assert_allclose(got, values, rtol=2e-5, atol=1e-4)
    assert np.all(np.sign(dd.gamma_encode(values, gamma)) == np.sign(values))


def test_gamma_transfer_reproduces_data_linear_in_gamma_space():
    """Data that is linear between gamma-mapped direct and indirect is recovered exactly."""
    rng = np.random.default_rng(6)
    p, t, n, gamma = 8, 30, 40, 2.2
    m_true, direct_g, indirect_g = _linear_transport(rng, p, t, n)
    direct, indirect = dd.gamma_decode(direct_g, gamma), dd.gamma_decode(indirect_g, gamma)
    cfg = {"basis": {"n": p, "center": False, "gamma": gamma}, "transfer": {"lam": 0.0}}
    params = dd.fit_arrays(direct, indirect, np.arange(p), cfg).params
    fresh_g = rng.random((3, p, 3))
    expected = dd.gamma_decode(np.einsum("tp,npc->ntc", m_true, fresh_g), gamma)
    got = np.asarray(dd.lightmap(params, dd.gamma_decode(fresh_g, gamma), cfg))
    np.testing.assert_allclose(got, expected, rtol=2e-4, atol=2e-4 * np.abs(expected).max())


# ---------------------------------------------------------------------------------------------
# SVD through the Gram matrix (§4.2)


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 10_000), st.integers(2, 12), st.integers(0, 12))
def test_gram_svd_equals_direct_svd(seed, cols, rank_drop):
    rng = np.random.default_rng(seed)
    rows = 5 * cols + 7
    rank = max(1, cols - rank_drop)
    a = rng.normal(size=(rows, rank)) @ rng.normal(size=(rank, cols))
    u, s = dd.gram_svd(a, cols)
    u_ref, s_ref, _ = np.linalg.svd(a, full_matrices=False)
    assert np.isfinite(u).all()
    np.testing.assert_allclose(s, s_ref, atol=1e-6 * s_ref[0])  # tiny ones come back as exact zeros
    for j in range(rank):  # singular vectors up to sign (the rank-deficient tail is a zero column)
        if s_ref[j] > 1e-6 * s_ref[0] and (j + 1 >= cols or s_ref[j] - s_ref[j + 1] > 1e-6 * s_ref[0]):
            np.testing.assert_allclose(np.abs(u[:, j] @ u_ref[:, j]), 1.0, atol=1e-6)
    np.testing.assert_allclose(u.T @ u, np.diag((s > 1e-8 * s[0]).astype(float)), atol=1e-8)


# ---------------------------------------------------------------------------------------------
# Measurement points (§4.1, §5.1)


@pytest.mark.parametrize("seed", range(8))
def test_sample_elimination_beats_random_subsets(seed):
    rng = np.random.default_rng(seed)
    candidates = rng.random((1500, 2))
    n = 150
    keep = dd.sample_elimination(candidates, n, area=1.0)
    assert keep.shape == (n,) and len(set(keep.tolist())) == n
    d_elim = pdist(candidates[keep]).min()
    d_random = [pdist(candidates[rng.choice(1500, n, replace=False)]).min() for _ in range(20)]
    assert d_elim >= max(d_random), (d_elim, max(d_random))


def test_sample_elimination_on_a_sphere_surface():
    rng = np.random.default_rng(11)
    v = rng.normal(size=(3000, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    keep = dd.sample_elimination(v, 200, area=4 * np.pi)
    d = pdist(v[keep]).min()
    assert d >= max(pdist(v[rng.choice(3000, 200, replace=False)]).min() for _ in range(20))
    # close to the Poisson-disk radius: a blue-noise set, not merely better than random
    r_max = np.sqrt(4 * np.pi / (2 * np.sqrt(3) * 200))
    assert d > 0.6 * r_max


def test_select_points_groups():
    rng = np.random.default_rng(7)
    pts = rng.random((2000, 2))
    mp = dd.select_points(pts, 40, supersample=4, area=1.0)
    assert mp.fine_index.shape == (160,) and mp.counts.shape == (40,)
    assert mp.counts.min() >= 1 and mp.counts.sum() == 160
    assert set(mp.coarse_index.tolist()) <= set(mp.fine_index.tolist())
    # every fine point is averaged into its nearest coarse point
    fine, coarse = pts[mp.fine_index], pts[mp.coarse_index]
    nearest = np.argmin(np.linalg.norm(fine[:, None] - coarse[None], axis=-1), axis=1)
    assert np.mean(nearest == mp.group) > 0.97  # ties and the "coarse point in its own group" rule aside
    with pytest.raises(ValueError, match="candidates"):
        dd.select_points(pts[:100], 40, supersample=4)


# ---------------------------------------------------------------------------------------------
# Evaluator


def test_image_lookup_at_texel_centres_returns_texels():
    rng = np.random.default_rng(8)
    p, t, res = 6, 64, 8
    _, direct, indirect = _linear_transport(rng, p, t, 30)
    params = _layout(dd.fit_arrays(direct, indirect, np.arange(p), {"basis": {"n": 6}}).params, t, res)
    params["fill_index"] = np.arange(res * res, dtype=np.int32)
    evaluate = dd.evaluator(params)
    rows, cols = np.divmod(np.arange(t), res)
    uv = np.stack([(cols + 0.5) / res, (rows + 0.5) / res], axis=-1).reshape(8, 8, 2).astype(np.float32)

    class GB:  # the evaluator reads only uv and valid
        pass

    gb = GB()
    gb.uv, gb.valid = uv, np.ones((8, 8), bool)
    gb.valid[0, 0] = False
    x = direct[3]
    image = np.asarray(evaluate(gb, PointRadiance(x)))
    lm = np.asarray(dd.lightmap(params, x))
    np.testing.assert_allclose(image.reshape(-1, 3)[1:], lm[1:], rtol=1e-5, atol=1e-6)
    assert np.all(image[0, 0] == 0)
    with pytest.raises(ValueError, match="fine measurement points"):
        evaluate(gb, PointRadiance(np.zeros((p + 1, 3))))
    # transfer alone = M_n x
    coeffs = np.asarray(dd.transfer_coefficients(params, x))
    np.testing.assert_allclose(coeffs, np.einsum("cnp,pc->nc", params["transfer"], x), rtol=1e-5, atol=1e-6)


def test_fit_input_errors():
    with pytest.raises(ValueError, match="examples"):
        dd.fit_arrays(np.ones((3, 4, 3)), np.ones((2, 5, 3)), np.arange(4))
    with pytest.raises(ValueError, match="NaN"):
        bad = np.ones((3, 4, 3))
        bad[0, 0, 0] = np.nan
        dd.fit_arrays(bad, np.ones((3, 5, 3)), np.arange(4))
    with pytest.raises(ValueError, match="channels"):
        dd.fit_arrays(np.ones((3, 4, 3)), np.ones((3, 5, 3)), np.arange(4), {"basis": {"channels": "rgb"}})


def test_batched_lightmap_matches_the_evaluator_and_cv_picks_a_candidate():
    rng = np.random.default_rng(9)
    p, t = 8, 40
    _, direct, indirect = _linear_transport(rng, p, t, 40)
    noisy = indirect + 0.05 * rng.normal(size=indirect.shape)
    atlas = atlas_inputs(8, np.arange(t))
    for channels, gamma in (("mono", 0.0), ("multi", 0.0), ("mono", 2.2)):
        cfg = {"basis": {"n": 6, "channels": channels, "gamma": gamma}}
        params = _layout(dd.fit_arrays(direct, noisy, np.arange(p), cfg).params, t)
        params["fill_index"] = np.arange(64, dtype=np.int32) % t
        evaluate = dd.evaluator(params, cfg)
        batch = np.asarray(dd.lightmap(params, direct[:5], cfg))  # one call over a batch of lightings
        images = np.stack([np.asarray(evaluate(atlas, PointRadiance(d))) for d in direct[:5]])
        np.testing.assert_allclose(images.reshape(5, -1, 3)[:, :t], batch, rtol=1e-5, atol=1e-6)
    cv = dd.cross_validate_lambda(direct, noisy, np.arange(p), {"basis": {"n": 6}}, [1e-6, 1e-2, 1e3], folds=4)
    assert cv["best"] in (1e-6, 1e-2, 1e3) and len(cv["rmse"]) == 3
    assert cv["rmse"][2] > min(cv["rmse"][:2])  # a huge lambda shrinks the transfer to zero: clearly worse


def test_linear_mean_recovers_known_transport_with_centring():
    """basis.mean = "linear": the mean is a regressed basis vector, so the centred model is
    exactly linear and held-out lighting is recovered (the paper's |x|-scaled mean is not)."""
    rng = np.random.default_rng(10)
    p, t = 10, 50
    m_true, direct, indirect = _linear_transport(rng, p, t, 40)
    cfg = {"basis": {"n": p + 1, "mean": "linear"}, "transfer": {"lam": 0.0}}
    params = dd.fit_arrays(direct, indirect, np.arange(p), cfg).params
    np.testing.assert_allclose(params["mean"], 0.0)
    fresh = rng.random((4, p, 3))
    expected = np.einsum("tp,npc->ntc", m_true, fresh)
    paper_cfg = {"basis": {"n": p + 1, "mean": "norm"}, "transfer": {"lam": 0.0}}
    paper = dd.fit_arrays(direct, indirect, np.arange(p), paper_cfg).params
    with jax.enable_x64(True):  # the lightmap in float64: exact recovery is checked at 1e-6
        f64 = lambda ps: {k: np.asarray(v, np.float64) if np.asarray(v).dtype.kind == "f" else v  # noqa: E731
                          for k, v in ps.items()}
        got = np.asarray(dd.lightmap(f64(params), fresh, cfg))
        paper_got = np.asarray(dd.lightmap(f64(paper), fresh, paper_cfg))
    np.testing.assert_allclose(got, expected, rtol=1e-6, atol=1e-6 * np.abs(expected).max())
    assert np.abs(paper_got - expected).max() > 1e-3 * np.abs(expected).max()


def test_random_lights_point_scenario():
    """``lights.kind="point"``: isotropic lights inside the position box, white at saturation 0,
    the intensity inside its range; an unknown kind is refused by name."""
    from jprt.inputs import PointLights
    from jprt.methods.datadriven.data import random_lights

    cfg = dd.DEFAULT_CONFIG["lights"] | {"kind": "point", "intensity": [0.5, 2.0], "saturation": 0.0}
    lights = random_lights(np.random.default_rng(0), 16, cfg)
    assert len(lights) == 16 and all(isinstance(li, PointLights) for li in lights)
    pos = np.concatenate([li.position for li in lights])
    assert (pos >= np.asarray(cfg["position_lo"])).all() and (pos <= np.asarray(cfg["position_hi"])).all()
    power = np.concatenate([li.intensity for li in lights])
    assert np.allclose(power, power[:, :1]) and (power >= 0.5).all() and (power <= 2.0).all()
    with pytest.raises(ValueError, match="'area'"):
        random_lights(np.random.default_rng(0), 1, cfg | {"kind": "area"})


@pytest.mark.parametrize("demodulate", [True, False])
def test_demodulated_fit_shades_texture_finer_than_a_texel(demodulate):
    """Indirect light a(x) E on a Lambertian surface: E linear in the lights and the same over the
    surface, a a texture that changes from texel to texel. A demodulated fit
    (``shading.demodulate``) shades a pixel between two texels with its own albedo times E,
    exactly; the plain lookup blends its neighbours' a E. Both give the texels' own light at
    texel centres and on the atlas G-buffer (no albedo); a glossy pixel keeps the lookup."""
    rng = np.random.default_rng(3)
    s, t, res, n = 6, 64, 8, 12
    direct = rng.random((n, s, 3)) + 0.1
    energy = direct.sum(axis=1)  # (n, 3): E of each configuration, the same at every texel
    albedo = rng.uniform(0.1, 0.9, (t, 3)).astype(np.float32)
    indirect = albedo[None] * energy[:, None]
    empty = np.zeros((0, s, 3))
    data = dd.DDData(atlas={"texel_index": np.arange(t), "fill_index": np.arange(res * res), "resolution": res},
                     candidates={"position": rng.random((s, 3)), "area": 1.0}, direct=direct, indirect=indirect,
                     direct_test=empty, indirect_test=np.zeros((0, t, 3)), lights={}, lights_test={}, meta={},
                     modulation=texel_modulation(albedo, np.zeros_like(albedo), np.zeros(t, int), np.zeros(t, int), 1))
    cfg = {"points": {"count": s, "supersample": 1}, "basis": {"n": 3},
           "transfer": {"lam_cv": [], "lam": 1e-9}, "shading": {"demodulate": demodulate}}
    params = dd.fit(data, cfg).params
    assert ("texel_modulation" in params) == demodulate
    evaluate = dd.evaluator(params, cfg)
    x = PointRadiance(direct[0][params["fine_index"]].astype(np.float32))
    lightmap = np.asarray(dd.lightmap(params, x.direct, cfg))
    np.testing.assert_allclose(lightmap, indirect[0], rtol=1e-4)
    # batched over lightings, as the self-check calls it: the texture goes back on every one
    batch = np.asarray(dd.lightmap(params, direct[:2][:, params["fine_index"]].astype(np.float32), cfg))
    np.testing.assert_allclose(batch, indirect[:2], rtol=1e-4)
    atlas = np.asarray(evaluate(atlas_inputs(res, np.arange(t)), x)).reshape(-1, 3)
    np.testing.assert_allclose(atlas, indirect[0], rtol=1e-4)
    # pixels halfway between texel columns c and c + 1 of each row, with albedos of their own
    rows, cols = np.meshgrid(np.arange(res), np.arange(res - 1), indexing="ij")
    uv = np.stack([(cols + 1.0) / res, (rows + 0.5) / res], axis=-1).astype(np.float32)
    pixel_albedo = rng.uniform(0.1, 0.9, uv.shape[:-1] + (3,)).astype(np.float32)
    gb = atlas_inputs(res, np.arange(t))._replace(uv=uv, valid=np.ones(uv.shape[:-1], bool),
                                                   diffuse_albedo=pixel_albedo, specular_albedo=np.zeros_like(pixel_albedo),
                                                   object_id=np.zeros(uv.shape[:-1], np.int32))
    image = np.asarray(evaluate(gb, x))
    exact = pixel_albedo * energy[0]
    blend = 0.5 * (indirect[0].reshape(res, res, 3)[:, :-1] + indirect[0].reshape(res, res, 3)[:, 1:])
    glossy = np.asarray(evaluate(gb._replace(specular_albedo=np.full_like(pixel_albedo, 0.04)), x))
    np.testing.assert_allclose(glossy, blend, rtol=1e-4)
    if demodulate:
        np.testing.assert_allclose(image, exact, rtol=1e-4)
    else:
        np.testing.assert_allclose(image, blend, rtol=1e-4)
        assert np.abs(image - exact).max() > 0.1 * np.abs(exact).max()


def test_texel_modulation_divides_out_texture_only():
    """An untextured Lambertian object's texels keep their light (relative modulation 1, the mean
    its albedo); a textured one's are divided by their albedo over the object's mean; glossy
    texels (a specular albedo), texels without a diffuse albedo, and texels whose material was
    read on another object keep theirs, and no mean is taken over them."""
    diffuse = np.array([[0.5, 0.4, 0.3], [0.5, 0.4, 0.3], [0.2, 0.2, 0.2], [0.6, 0.6, 0.6], [0.7, 0.1, 0.1],
                        [0.0, 0.0, 0.0], [0.9, 0.9, 0.9]], np.float32)
    specular = np.zeros_like(diffuse)
    specular[4] = 0.04
    obj = np.array([0, 0, 1, 1, 2, 3, 0])
    hit = np.array([0, 0, 1, 1, 2, 3, 5])
    rel, mean = texel_modulation(diffuse, specular, obj, hit, 6)
    np.testing.assert_allclose(rel[:2], 1.0)
    np.testing.assert_allclose(mean[0], diffuse[0], rtol=1e-6)
    np.testing.assert_allclose(rel[2:4], diffuse[2:4] / 0.4, rtol=1e-6)
    np.testing.assert_allclose(rel[4:], 1.0)
    np.testing.assert_allclose(mean[2:], 0.0)


def test_atlas_inputs_leave_out_texels_whose_pixel_shows_another():
    """An unseen texel's atlas pixel shows a seen neighbour (``build_atlas``' fill): given the
    fill, ``atlas_inputs`` marks only the texels that show themselves valid, so an atlas-image
    score compares each valid pixel with its own texel."""
    texel_index = np.array([0, 1, 2, 5])
    fill = np.array([0, 1, 1, 1, 2, 3, 3, 3, 2])  # texel 2's pixel (2) shows texel 1
    g = atlas_inputs(3, texel_index, fill)
    assert np.flatnonzero(np.asarray(g.valid).reshape(-1)).tolist() == [0, 1, 5]
    assert np.flatnonzero(np.asarray(atlas_inputs(3, texel_index).valid).reshape(-1)).tolist() == [0, 1, 2, 5]
    # the same texels by index, as the fit report's rmse_shown selects them
    assert shown_texels(texel_index, fill).tolist() == [True, True, False, True]
