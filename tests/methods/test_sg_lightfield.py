"""SG light-field textures (jprt.methods.sg_lightfield.model, Currius et al. 2020): constraints,
Appendix A's gradients, the encoder recovering a known mixture, the run-time shading against
quadrature of the GGX BRDF, and float32 at the extremes against float64."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from jprt.methods.sg_lightfield import model as M
from jprt.sphere import octahedral


#: ``constrain`` then ``to_storage`` as one program (run eagerly, each of their operations compiles
#: on its own, 40 small programs)
_CONSTRAIN_AND_STORE = jax.jit(lambda raw: (M.constrain(raw), M.to_storage(M.constrain(raw))))


@given(raw=hnp.arrays(np.float32, (5, 3, 7), elements=st.floats(-1e4, 1e4, width=32)))
@settings(max_examples=60, deadline=None)
def test_constraints_hold_for_any_raw_output(raw):
    lobes, stored = _CONSTRAIN_AND_STORE(jnp.asarray(raw))
    np.testing.assert_allclose(np.linalg.norm(np.asarray(lobes.axes), axis=-1), 1.0, rtol=1e-5)
    s = np.asarray(lobes.sharpness)
    assert (s >= 0.5 * (1 - 1e-6)).all() and (s <= 1e4 * (1 + 1e-6)).all()
    assert (np.asarray(lobes.amplitude) >= 0).all() and np.isfinite(np.asarray(lobes.amplitude)).all()
    # float16 holds every constrained sharpness (<= 1e4 < 65504)
    assert all(np.isfinite(np.asarray(a, np.float32)).all() for a in stored)
    np.testing.assert_allclose(float(_CONSTRAIN_AND_STORE(jnp.zeros((1, 7)))[0].sharpness[0]), 1.0, rtol=1e-5)


def test_appendix_a_gradients_with_the_errata():
    """Eq. 12-14 for one lobe and one pixel, as corrected: dP/dmu_jc = exp(..) (Eq. 12 writes
    mu_ic), dP/dlambda = mu exp(..) (v . u - 1), dP/du_x = mu exp(..) lambda v_x (Eq. 14 writes
    lambda x)."""
    v = jnp.array([0.3, -0.2, 0.93]) / jnp.linalg.norm(jnp.array([0.3, -0.2, 0.93]))
    u, lam, mu = jnp.array([0.1, 0.2, 0.97]), 7.0, 2.5

    def p(u, lam, mu):
        return mu * jnp.exp(lam * (jnp.dot(v, u) - 1.0))

    e = jnp.exp(lam * (jnp.dot(v, u) - 1.0))
    gu, glam, gmu = jax.grad(p, argnums=(0, 1, 2))(u, lam, mu)
    np.testing.assert_allclose(float(gmu), float(e), rtol=1e-6)
    np.testing.assert_allclose(float(glam), float(mu * e * (jnp.dot(v, u) - 1.0)), rtol=1e-5)
    np.testing.assert_allclose(np.asarray(gu), np.asarray(mu * e * lam * v), rtol=1e-5)


def _two_lobe_images(size, n_tex, brightness=1.0):
    dirs = jnp.asarray(octahedral.texel_directions(size)).reshape(-1, 3)
    images, truth = [], []
    for t in range(n_tex):
        a1 = np.array([0.2 * np.cos(t), 0.2 * np.sin(t), 1.0])
        a2 = np.array([0.8, 0.1 * t / n_tex, 0.5])
        lobes = M.Lobes(jnp.asarray(np.stack([a1 / np.linalg.norm(a1), a2 / np.linalg.norm(a2)]), jnp.float32),
                        jnp.asarray([30.0, 8.0]), brightness * jnp.asarray([[4.0, 3.0, 2.0], [0.5, 0.8, 1.0]]))
        images.append(np.asarray(M.lobe_radiance(lobes, dirs)).reshape(size, size, 3))
        truth.append(lobes)
    return np.stack(images), truth


def test_cnn_recovers_a_known_two_lobe_mixture():
    """As dim as a captured indirect light field (mean ~0.03): lobes that start far brighter than
    the data collapse to zero amplitude and maximal sharpness and never recover."""
    size, n_tex = 16, 16
    images, truth = _two_lobe_images(size, n_tex, brightness=0.05)
    config = {"model": {"n_lobes": 2, "channels": [8, 16], "min_sharpness": 0.5, "max_sharpness": 1e4,
                        "init_sharpness": 1.0},
              "train": {"steps": 500, "batch": 16, "learning_rate": 1e-2, "final_lr_fraction": 0.1, "seed": 0,
                        "jitter": False}}
    _, lobes, losses = M.fit_cnn(images, np.zeros(images.shape[:3], bool), config, progress=False)
    assert losses[-1] < 1e-3 * losses[0]
    dirs = jnp.broadcast_to(octahedral.texel_directions(size).reshape(-1, 3), (n_tex, size * size, 3))
    pred = np.asarray(M.lobe_radiance(lobes, dirs))
    target = images.reshape(n_tex, -1, 3)
    assert np.sqrt(np.mean((pred - target) ** 2)) < 0.02 * np.sqrt(np.mean(target ** 2))
    for t in range(n_tex):  # the lobes themselves, up to their order
        order = np.argsort(-np.asarray(lobes.sharpness[t]))
        np.testing.assert_allclose(np.asarray(lobes.sharpness[t])[order], [30.0, 8.0], rtol=0.1)
        cos = np.sum(np.asarray(lobes.axes[t])[order] * np.asarray(truth[t].axes), axis=-1)
        assert (cos > np.cos(np.radians(3.0))).all()


@functools.lru_cache(maxsize=None)
def _hemisphere(nt=900, npp=400):
    """Midpoint quadrature of the hemisphere of n = +z: directions w and their solid angles (float64)."""
    th = (np.arange(nt) + 0.5) / nt * np.pi / 2
    ph = (np.arange(npp) + 0.5) / npp * 2 * np.pi
    t, p = np.meshgrid(th, ph, indexing="ij")
    w = np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], -1)
    return w, np.sin(t) * (np.pi / 2 / nt) * (2 * np.pi / npp)


def _quadrature(axis, lams, n, v, alpha, f0):
    """int G(w; axis, lam, 1) f_GGX(w, v) (n . w) dw over the hemisphere of n = +z (float64), for
    each lam of ``lams`` (the BRDF-cosine computed once for them)."""
    w, d_omega = _hemisphere()
    h = w + v
    h /= np.linalg.norm(h, axis=-1, keepdims=True)
    a2 = alpha ** 2
    ndf = a2 / (np.pi * (h[..., 2] ** 2 * (a2 - 1) + 1) ** 2)
    g1 = lambda x: 2 * x / (x + np.sqrt(a2 + (1 - a2) * x * x))  # noqa: E731
    fresnel = f0 + (1 - f0) * (1 - np.clip(np.sum(w * h, -1), 0, 1)) ** 5
    brdf = ndf * g1(w[..., 2]) * g1(v[2]) * fresnel / (4 * w[..., 2] * v[2])
    weight = brdf * w[..., 2] * d_omega
    cos = w @ axis - 1
    return [float(np.sum(np.exp(lam * cos) * weight)) for lam in lams]


def test_shading_matches_quadrature_of_the_ggx_brdf():
    """One light lobe on the reflected direction, shaded by Appendix B against the exact GGX
    Cook-Torrance integral, at alpha 0.2 / 0.3 / 0.5 and views of 0 / 30 / 60 degrees (one jitted
    call for all). The SG stand-in for the GGX NDF (Eq. 17) overestimates: by at most 8 % for
    sharp lobes (lambda 300, a near-delta light), 25 % for broad ones (lambda 10), and the error
    shrinks as the lobe sharpens."""
    n, lams = np.array([0.0, 0.0, 1.0]), (10.0, 50.0, 300.0)
    cases, views, refl, lobes, args = _mirror_cases((0.2, 0.3, 0.5), (0.0, 30.0, 60.0), lams, 0.9)
    k = len(cases)
    shaded = np.asarray(jax.jit(M.shade)(lobes, *args))
    for i in range(0, k, len(lams)):  # one (alpha, view) per group of lambdas
        exact = _quadrature(refl[i], lams, n, views[i], cases[i][0], 0.9)
        ratios = [float(shaded[i + j, 0]) / exact[j] for j in range(len(lams))]
        assert all(1.0 <= q <= 1.25 for q in ratios), (cases[i][:2], ratios)
        assert ratios[-1] <= 1.08 and ratios[0] >= ratios[1] >= ratios[2], (cases[i][:2], ratios)


def _mirror_cases(alphas, degrees, lams, f0):
    """One lobe per (alpha, view angle, lambda) on the view's mirror direction about n = +z, views
    in the xz-plane: (cases, views, mirror directions, ``Lobes``, ``shade_sampled``'s arguments
    after the lobes, with specular ``f0``)."""
    n = np.array([0.0, 0.0, 1.0])
    cases = [(alpha, deg, lam) for alpha in alphas for deg in degrees for lam in lams]
    views = np.array([[np.sin(np.radians(d)), 0.0, np.cos(np.radians(d))] for _, d, _ in cases])
    refl = 2 * views[:, 2:3] * n - views
    k = len(cases)
    lobes = M.Lobes(jnp.asarray(refl[:, None], jnp.float32), jnp.asarray([[lam] for *_, lam in cases]),
                    jnp.ones((k, 1, 3)))
    args = (jnp.asarray(np.broadcast_to(n, (k, 3))), jnp.asarray(views), jnp.asarray([a for a, *_ in cases]),
            jnp.full((k, 3), f0), jnp.zeros((k, 3)), jnp.zeros((k, 3)))
    return cases, views, refl, lobes, args


def test_sampled_shading_converges_to_quadrature_of_the_ggx_brdf():
    """The same lobes and views as above through ``shade_sampled`` with every lobe's directions
    drawn from the lobe itself (``brdf_sampled`` off): at 3 x 3 directions per lobe within 1 %
    for sharp lobes (lambda 300) and within 20 % for broad ones (lambda 10, under rather than
    over), never above the exact integral by more than 1 %; at 6 x 6 within 4 % everywhere (the
    strata converge to the integral). The default shading, which takes the broad lobes here
    (lambda 10 at alpha 0.2 and 0.3) by directions drawn from the BRDF, is within 6 % on them all."""
    n, lams = np.array([0.0, 0.0, 1.0]), (10.0, 50.0, 300.0)
    cases, views, refl, lobes, args = _mirror_cases((0.2, 0.3, 0.5), (0.0, 30.0, 60.0), lams, 0.9)
    k = len(cases)
    shaded = {s: np.asarray(M.shade_sampled(lobes, *args, samples=s, brdf_sampled=False))[:, 0] for s in (3, 6)}
    default = np.asarray(M.shade_sampled(lobes, *args))[:, 0]
    for i in range(0, k, len(lams)):
        exact = np.array(_quadrature(refl[i], lams, n, views[i], cases[i][0], 0.9))
        three, six = shaded[3][i:i + len(lams)] / exact, shaded[6][i:i + len(lams)] / exact
        assert np.all((three >= 0.8) & (three <= 1.01)) and abs(three[-1] - 1) <= 0.01, (cases[i][:2], three)
        assert np.all(np.abs(six - 1) <= 0.04), (cases[i][:2], six)
        # the default (broad lobes by the BRDF's directions) within 6 % on these cases too
        assert np.all(np.abs(default[i:i + len(lams)] / exact - 1) <= 0.06), (cases[i][:2], default[i:i + len(lams)] / exact)


def test_broad_lobes_keep_their_glossy_reflection_at_grazing_views():
    """Broad lobes (lambda 0.5 / 2 / 8: an interior's bounced light) on the mirror direction of a
    plastic-like receiver (alpha 0.15 / 0.3, Schlick f0 0.04) seen at 60 / 75 / 84 degrees: the
    default shading (such lobes integrated at directions drawn from the BRDF's visible normals)
    is within 0.9-1.15 of the exact integral, where directions drawn from the lobes alone give
    under half of it in some case; the same cases turned by a rotation (normal, view and lobe
    together) shade the same to rounding (the BRDF's directions do not depend on the tangent
    frame)."""
    n, lams = np.array([0.0, 0.0, 1.0]), (0.5, 2.0, 8.0)
    cases, views, refl, lobes, args = _mirror_cases((0.15, 0.3), (60.0, 75.0, 84.0), lams, 0.04)
    k = len(cases)
    default = np.asarray(M.shade_sampled(lobes, *args))[:, 0]
    lobe_only = np.asarray(M.shade_sampled(lobes, *args, brdf_sampled=False))[:, 0]
    q, _ = np.linalg.qr(np.random.default_rng(3).normal(size=(3, 3)))
    turned = M.Lobes(jnp.asarray(refl[:, None] @ q.T, jnp.float32), lobes.sharpness, lobes.amplitude)
    np.testing.assert_allclose(
        np.asarray(M.shade_sampled(turned, jnp.asarray(np.broadcast_to(n @ q.T, (k, 3)), jnp.float32),
                                   jnp.asarray(views @ q.T, jnp.float32), *args[2:]))[:, 0], default, rtol=2e-3)
    worst_lobe_only = 1.0
    for i in range(0, k, len(lams)):
        exact = np.array(_quadrature(refl[i], lams, n, views[i], cases[i][0], 0.04))
        ratio = default[i:i + len(lams)] / exact
        assert np.all((ratio >= 0.9) & (ratio <= 1.15)), (cases[i][:2], ratio)
        worst_lobe_only = min(worst_lobe_only, float(np.min(lobe_only[i:i + len(lams)] / exact)))
    assert worst_lobe_only < 0.5


def test_evaluator_shades_by_samples_or_by_appendix_b():
    """``shading.samples`` picks the evaluator's shading: its pixel-space frame equals
    ``shade_sampled`` (or, at 0, ``shade``) of the bilinearly looked-up lobes; a negative count is
    refused."""
    rng = np.random.default_rng(3)
    res, t_count, n_lobes = 4, 16, 2
    axes = rng.normal(size=(t_count, n_lobes, 3))
    axes /= np.linalg.norm(axes, axis=-1, keepdims=True)
    params = {"axes": jnp.asarray(axes, jnp.float16),
              "sharpness": jnp.asarray(rng.uniform(1, 50, (t_count, n_lobes)), jnp.float16),
              "amplitude": jnp.asarray(rng.uniform(0, 2, (t_count, n_lobes, 3)), jnp.float16),
              "irradiance": jnp.asarray(rng.uniform(0, 1, (t_count, 3)), jnp.float32),
              "fill_index": jnp.arange(res * res, dtype=jnp.int32)}
    from jprt.methods.lightmap_lookup import atlas_inputs

    g = atlas_inputs(res, np.arange(res * res))
    normal = np.broadcast_to([0.0, 0.0, 1.0], (res, res, 3)).astype(np.float32)
    view = np.broadcast_to([0.6, 0.0, 0.8], (res, res, 3)).astype(np.float32)
    g = g._replace(normal=normal, view=view, roughness=np.full((res, res), 0.3, np.float32),
                   specular_albedo=np.full((res, res, 3), 0.9, np.float32),
                   diffuse_albedo=np.full((res, res, 3), 0.2, np.float32))
    lobes = M.lookup_lobes(params, g.uv)
    irr = np.asarray(params["irradiance"]).reshape(res, res, 3)
    pixel = (g.normal, g.view, g.roughness, g.specular_albedo, g.diffuse_albedo, irr)
    # each reference one program (eagerly, every operation of the unrolled directions compiles alone)
    sampled = jax.jit(functools.partial(M.shade_sampled, samples=2))(lobes, *pixel)
    for samples, want in ((2, sampled), (0, jax.jit(M.shade)(lobes, *pixel))):
        got = M.evaluator(params, {"shading": {"samples": samples, "space": "pixel"}})(g, np.ones(3, np.float32))
        np.testing.assert_allclose(np.asarray(got), np.asarray(want), rtol=1e-4, atol=1e-5)
    with pytest.raises(ValueError, match="shading.samples"):
        M.evaluator(params, {"shading": {"samples": -1}})


def _random_texture(rng, res: int, n_lobes: int) -> dict:
    """Random stored lobes and irradiance for every texel of a res x res atlas (no gutters)."""
    t_count = res * res
    axes = rng.normal(size=(t_count, n_lobes, 3))
    axes /= np.linalg.norm(axes, axis=-1, keepdims=True)
    return {"axes": jnp.asarray(axes, jnp.float16),
            "sharpness": jnp.asarray(rng.uniform(1, 50, (t_count, n_lobes)), jnp.float16),
            "amplitude": jnp.asarray(rng.uniform(0, 2, (t_count, n_lobes, 3)), jnp.float16),
            "irradiance": jnp.asarray(rng.uniform(0, 1, (t_count, 3)), jnp.float32),
            "fill_index": jnp.arange(t_count, dtype=jnp.int32)}


def _random_gbuffer(rng, shape, uv):
    """A G-buffer at atlas ``uv`` with per-pixel normals and views of the upper hemisphere,
    roughness, specular and diffuse albedo drawn per pixel."""
    from jprt.inputs import GBuffer

    def hemisphere(tilt):
        d = rng.normal(size=shape + (3,)) * tilt + [0.0, 0.0, 1.0]
        return (d / np.linalg.norm(d, axis=-1, keepdims=True)).astype(np.float32)

    f3 = lambda lo, hi: rng.uniform(lo, hi, shape + (3,)).astype(np.float32)  # noqa: E731
    normal, view = hemisphere(0.2), hemisphere(0.6)
    return GBuffer(position=f3(0, 1), normal=normal, view=view, reflected=view, uv=np.asarray(uv, np.float32),
                   diffuse_albedo=f3(0, 1), specular_albedo=f3(0, 1),
                   roughness=rng.uniform(0.1, 0.6, shape).astype(np.float32),
                   object_id=np.zeros(shape, np.int32), valid=np.ones(shape, bool))


def test_texel_space_equals_pixel_space_at_texel_centres():
    """Where every pixel reads one texel at its centre, shading each texel once ("texel") gives
    the pixel-space frame ("pixel", §6) exactly, whatever the pixels' normals, views and
    materials (the sampled shading; Appendix B's in the next test); a space not known is refused."""
    from jprt.methods.lightmap_lookup import atlas_inputs

    rng = np.random.default_rng(5)
    res = 4
    params = _random_texture(rng, res, 2)
    g = _random_gbuffer(rng, (res, res), atlas_inputs(res, np.arange(res * res)).uv)
    frames = [np.asarray(M.evaluator(params, {"shading": {"samples": 2, "space": space}})(g, np.ones(3)))
              for space in ("pixel", "texel")]
    assert np.abs(frames[0]).max() > 0
    np.testing.assert_allclose(frames[1], frames[0], rtol=1e-4, atol=1e-6)
    with pytest.raises(ValueError, match="shading.space"):
        M.evaluator(params, {"shading": {"space": "vertex"}})


def test_texel_space_shades_each_texel_at_its_pixels_mean_view():
    """Pixels between texels: each texel is shaded (``shade``, Fresnel's two parts at f0 1 and 0;
    the sampled shading is the same function of the same view) at the bilinear-weight mean of the
    normals, views and roughness of the valid pixels that read it, and each pixel mixes its four
    texels' shading with its bilinear weights and its own f0 and diffuse albedo; invalid pixels
    holding NaN change nothing and are 0; "auto" shades in texel space when the atlas has no more texels than
    the frame has pixels, in pixel space otherwise."""
    from jprt.methods.lightmap_lookup import texel_taps

    rng = np.random.default_rng(6)
    res, shape = 3, (5, 4)
    params = _random_texture(rng, res, 2)
    g = _random_gbuffer(rng, shape, rng.uniform(0, 1, shape + (2,)))
    index, weight = (np.asarray(a, np.float64) for a in texel_taps(params["fill_index"], g.uv))
    index = index.astype(int)
    # two invalid pixels whose fields hold NaN: they take no part in any texel's footprint
    valid = np.ones(shape, bool)
    valid[0, 0] = valid[3, 2] = False
    weight = np.where(valid[..., None], weight, 0.0)
    nan = np.where(valid[..., None], 0.0, np.nan).astype(np.float32)
    g = g._replace(valid=valid, normal=g.normal + nan, view=g.view + nan, uv=g.uv + nan[..., :2],
                   roughness=g.roughness + nan[..., 0])
    clean = lambda a: np.where(valid[..., None] if a.ndim == 3 else valid, a, 0.0)  # noqa: E731
    t_count = res * res
    w = np.zeros((t_count,) + shape)
    for k in range(4):
        for t in range(t_count):
            w[t] += np.where(index[..., k] == t, weight[..., k], 0.0)
    sums = w.reshape(t_count, -1)
    unit = lambda v: v / np.linalg.norm(v, axis=-1, keepdims=True)  # noqa: E731
    normal = unit(sums @ clean(np.asarray(g.normal, np.float64)).reshape(-1, 3))
    view = unit(sums @ clean(np.asarray(g.view, np.float64)).reshape(-1, 3))
    rough = sums @ clean(np.asarray(g.roughness, np.float64)).reshape(-1) / sums.sum(-1)
    assert (sums.sum(-1) > 0).all()  # every texel is read by some pixel here
    lobes = M.Lobes(*(jnp.asarray(params[k], jnp.float32) for k in ("axes", "sharpness", "amplitude")))
    zero = np.zeros((t_count, 3), np.float32)
    shade = jax.jit(M.shade)
    parts = [np.asarray(shade(lobes, normal.astype(np.float32), view.astype(np.float32), rough.astype(np.float32),
                              np.full((t_count, 3), f0, np.float32), zero, zero)) for f0 in (1.0, 0.0)]
    texel = np.concatenate(parts + [np.asarray(params["irradiance"])], axis=-1)  # (T, 9)
    read = sum(weight[..., k:k + 1] * texel[index[..., k]] for k in range(4))
    want = g.specular_albedo * read[..., 0:3] + (1 - g.specular_albedo) * read[..., 3:6] + \
        g.diffuse_albedo / np.pi * read[..., 6:9]
    want = clean(want)  # 0 at invalid pixels
    evaluate = {space: M.evaluator(params, {"shading": {"samples": 0, "space": space}})
                for space in ("texel", "auto", "pixel")}
    got = {space: np.asarray(f(g, np.ones(3))) for space, f in evaluate.items()}
    assert np.isfinite(got["texel"]).all()
    np.testing.assert_allclose(got["texel"], want, rtol=1e-4, atol=1e-5)
    np.testing.assert_array_equal(got["auto"], got["texel"])  # 9 texels, 20 pixels
    assert np.nanmax(np.abs(got["pixel"] - got["texel"])) > 1e-3  # between texels the spaces differ
    small = g._replace(**{f: getattr(g, f)[1:3, :2] for f in g._fields})  # 4 pixels: fewer than the texels
    np.testing.assert_allclose(np.asarray(evaluate["auto"](small, np.ones(3))), got["pixel"][1:3, :2], rtol=1e-6)


def test_float32_at_the_extremes_matches_float64():
    """Roughness 0.01, views to 89.9 degrees, sharpness up to 1e4 stored in float16: float32
    shading equals float64 shading of the same stored lobes (finite is not enough)."""
    rng = np.random.default_rng(0)
    raw = rng.normal(size=(64, 16, 7)) * 3.0
    raw[..., 3] = np.linspace(-30, 30, 64 * 16).reshape(64, 16)
    stored = _CONSTRAIN_AND_STORE(jnp.asarray(raw, jnp.float32))[1]
    assert float(jnp.max(stored.sharpness)) == pytest.approx(1e4, rel=1e-3)
    t = np.radians(np.linspace(0.0, 89.9, 64))
    view = np.stack([np.sin(t), 0 * t, np.cos(t)], -1)
    normal = np.broadcast_to([0.0, 0.0, 1.0], (64, 3))
    out = {}
    shade = jax.jit(M.shade)
    for dtype in (jnp.float32, jnp.float64):
        with jax.enable_x64(dtype == jnp.float64):
            lobes = M.Lobes(*(jnp.asarray(np.asarray(a, np.float64), dtype) for a in stored))
            for r in (0.01, 0.3):
                out[dtype, r] = np.asarray(shade(lobes, jnp.asarray(normal, dtype), jnp.asarray(view, dtype),
                                                   jnp.full((64,), r, dtype), jnp.full((64, 3), 0.9, dtype),
                                                   jnp.full((64, 3), 0.5, dtype), jnp.ones((64, 3), dtype)))
    for r in (0.01, 0.3):
        assert np.isfinite(out[jnp.float32, r]).all()
        np.testing.assert_allclose(out[jnp.float32, r], out[jnp.float64, r], rtol=1e-4, atol=1e-6)


def test_texel_irradiance_of_a_constant_sky_is_pi_l():
    size = 32
    images = np.full((2, size, size, 3), 2.0, np.float32)
    normals = np.array([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8]], np.float32)
    e = np.asarray(jax.jit(M.texel_irradiance, static_argnums=2)(images, normals, size))  # one program
    np.testing.assert_allclose(e, 2.0 * np.pi, rtol=0.01)  # cosine quadrature at pixel centres


def test_gradients_stay_finite_at_a_zero_raw_axis():
    """A raw axis of exactly 0 (a fresh network can output one) gives a unit axis and finite
    gradients (the norm must not be taken of the zero vector: inf * 0 = NaN through a where)."""
    raw = jnp.zeros((2, 7)).at[1, :3].set(jnp.array([0.3, -0.4, 1.2]))
    v = jnp.array([0.0, 0.6, 0.8])

    def loss(raw):
        lobes = M.constrain(raw)
        return jnp.sum(M.lobe_radiance(lobes, v[None]))

    g = jax.jit(jax.grad(loss))(raw)  # one program (eagerly, the gradient is ~80 small compiles)
    assert np.isfinite(np.asarray(g)).all()
    np.testing.assert_allclose(np.asarray(jax.jit(M.constrain)(raw).axes[0]), [0.0, 0.0, 1.0])


@pytest.mark.slow  # ~15 s: capture, fit and shade a tiny light-field texture end to end
@pytest.mark.mitsuba
def test_tiny_light_field_texture_end_to_end(mi, tmp_path):
    from jprt.methods.sg_lightfield import data as D
    from jprt.render import cameras, lightmap
    from jprt.render.scenes import SceneHandle

    cfg = M._cfg({"lightmap": {"resolution": 32}, "capture": {"size": 8, "spp": 8, "block": 64},
                  "model": {"n_lobes": 4, "channels": [8, 16]}, "train": {"steps": 150, "batch": 32}})
    data = D.make_dataset(None, cfg, cache_dir=str(tmp_path), progress=False)
    assert data.images.shape[1:] == (8, 8, 3) and np.isfinite(data.images).all()
    result = M.fit(data, cfg, progress=False)
    losses = result.info["losses"]
    assert np.isfinite(losses).all() and np.mean(losses[-10:]) < np.mean(losses[:10])
    # far better than black lobes (the collapse this texture once trained into), at the pixel centres
    from jprt.methods.sg_lightfield import baselines

    lobes = M.Lobes(*(np.asarray(result.params[k], np.float32) for k in ("axes", "sharpness", "amplitude")))
    black = M.Lobes(lobes.axes, lobes.sharpness, np.zeros_like(lobes.amplitude))
    assert baselines.cnn_log_l2(lobes, data.images, data.below) < 0.5 * baselines.cnn_log_l2(black, data.images,
                                                                                               data.below)
    assert result.info["bytes_per_texel"] == 4 * 7 * 2  # 4 lobes of 7 float16 numbers
    evaluate = jax.jit(M.evaluator(result.params, cfg))
    gb = lightmap.atlas_gbuffer(SceneHandle(cfg["scene"]), lightmap.Atlas(**data.atlas),
                                cameras.look_at((0.0, 0.0, 3.9), (0.0, 0.0, 0.0), width=16, height=16))
    one = np.asarray(evaluate(gb, np.ones(3, np.float32)))
    assert one.shape == (16, 16, 3) and np.isfinite(one).all() and one.max() > 0
    assert np.array_equal(one[~gb.valid], np.zeros_like(one[~gb.valid]))
    np.testing.assert_allclose(np.asarray(evaluate(gb, np.array([2.0, 1.0, 0.5], np.float32))),
                               one * np.array([2.0, 1.0, 0.5]), rtol=1e-5, atol=1e-7)  # linear in the lights


@pytest.mark.slow  # ~5 s of compilation (the experiment's test preset will run them by default)
def test_baselines_fit_the_same_texels_and_survive_a_black_one():
    """Every per-texel baseline on the known mixtures plus one black texel (a texel inside
    geometry): finite losses; the free-axis fits (GD, EM) beat the fixed bases on sharp lobes."""
    from jprt.methods.sg_lightfield import baselines

    images, _ = _two_lobe_images(16, 3)
    images = np.concatenate([images, np.zeros_like(images[:1])])
    below = np.zeros(images.shape[:3], bool)
    atlas = {"resolution": 2, "texel_index": np.arange(4), "texel_object": np.zeros(4, np.int32)}
    out = baselines.compare(images, below, atlas, 2, steps=200)
    assert set(out) == set(baselines.BASELINES)
    for name, r in out.items():
        assert np.isfinite(r["log_l2"]) and np.isfinite(r["prediction"]).all(), name
        assert np.abs(r["prediction"][3]).max() < 1e-3, name  # black stays black
    assert max(out["gd"]["log_l2"], out["em"]["log_l2"]) < min(out["fixed_axes"]["log_l2"], out["sh"]["log_l2"])
    np.testing.assert_array_equal(baselines.atlas_neighbours(atlas)[0], [0, 1, 0, 2])  # left, right, up, down
