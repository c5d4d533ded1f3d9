"""Illumination-weighted environment visibility (jprt.methods.sg_lightfield.environment, Currius
et al. 2020 §5): W_E is 1 with nothing in the way and near 0 under a plate, U's normalisation
(Eq. 6), Eq. 8 against quadrature of the rendered BRDF, the energy of the environment's
resampling, and the fast evaluator against the reference shading."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jprt.methods.sg_lightfield import environment as E
from jprt.methods.sg_lightfield import model as M
from jprt.sphere import octahedral


def _sky(size=16, value=1.0):
    return np.full((size, size, 3), value, np.float32)


def test_weighted_visibility_is_one_in_the_open_and_zero_when_blocked():
    """Eq. 7 is a weighted mean of V: exactly 1 (to rounding) with every direction open, exactly 0
    with every direction blocked, for any normal and roughness; below-surface r are masked."""
    rng = np.random.default_rng(0)
    normal = rng.normal(size=(5, 3))
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    rough = np.array([0.01, 0.1, 0.3, 0.6, 1.0])
    env = np.exp(rng.normal(size=(16, 16, 3))).astype(np.float32)  # any positive environment
    w, below = E.weighted_visibility(np.ones((5, 16, 16)), normal, rough, env, 8)
    np.testing.assert_allclose(np.asarray(w)[~np.asarray(below)], 1.0, rtol=1e-5)
    w0, _ = E.weighted_visibility(np.zeros((5, 16, 16)), normal, rough, env, 8)
    assert float(jnp.max(jnp.abs(w0))) == 0.0
    dirs = np.asarray(octahedral.texel_directions(8)).reshape(-1, 3)
    np.testing.assert_array_equal(np.asarray(below).reshape(5, -1), normal @ dirs.T <= 0.0)


@pytest.mark.slow  # ~3 s; the open / blocked and plate tests cover Eq. 7 by default
def test_weighted_visibility_weighs_by_the_light_in_the_lobe():
    """Half of the sky blocked: W_E follows where the light is, not the blocked fraction. With all
    light in the open half, a lobe pointing there sees W_E ~ 1; with all light in the blocked half, ~ 0."""
    dirs = np.asarray(octahedral.texel_directions(32)).reshape(32, 32, 3)
    open_half = (dirs[..., 0] > 0).astype(np.float32)  # +x half of the sky open
    lit_open = np.where((dirs[..., 0] > 0)[..., None], 1.0, 1e-3).astype(np.float32) * np.ones(3, np.float32)
    lit_blocked = np.where((dirs[..., 0] <= 0)[..., None], 1.0, 1e-3).astype(np.float32) * np.ones(3, np.float32)
    n = np.array([[0.0, 0.0, 1.0]])
    r = np.array([0.5, 0.0, 0.866])  # reflected direction tilted into the open half
    for env, lo, hi in ((lit_open, 0.95, 1.0), (lit_blocked, 0.0, 0.05)):
        w, _ = E.weighted_visibility(open_half[None], n, np.array([0.3]), env, 16)
        value = np.asarray(E.octahedral_lookup(w[0], jnp.asarray(r)))
        assert (lo <= value).all() and (value <= hi).all(), value


def test_preconvolved_constant_sky_has_the_closed_form_normalisation():
    """Eq. 6 with L = 1 and n = w_o: int D(h) dw_i = 4 int D (h.n) dh over h within 45 degrees of n:
    -> 4 as alpha -> 0; exactly 2 for alpha = 1 (D = 1 / pi over the hemisphere)."""
    u = np.asarray(E.preconvolve(_sky(64), [0.05, 1.0], 8))
    np.testing.assert_allclose(u[1], 2.0, rtol=2e-3)
    np.testing.assert_allclose(u[0], 4.0 * (1.0 - 0.05**2 / (1.0 + 0.05**2)), rtol=0.03)


def test_eq8_matches_quadrature_of_the_rendered_brdf_under_an_open_sky():
    """A constant sky, nothing in the way (W_E = 1): Eq. 8's split (U x G F / (4 n.v)) against the
    full integral of the rendered BRDF (``model.shade_quadrature``) at normal and oblique views.
    Eq. 8 is an approximation: within 4 % at alpha 0.2 up to 45 degrees."""
    n = np.array([0.0, 0.0, 1.0], np.float32)
    alphas = [0.1, 0.2, 0.3]
    u = E.preconvolve(_sky(32), alphas, 16)

    @jax.jit  # one program for both sides, compiled once for both views (eagerly, ~160 small compiles)
    def split_and_exact(v, r):
        split = E.shade_environment(E.lookup_preconvolved(u, alphas, r, 0.2), 1.0, n, v, 0.2,
                                    np.full(3, 0.9, np.float32))
        return split, M.shade_quadrature(_sky(32), n, v, 0.2, np.full(3, 0.9, np.float32), sub=4)

    for deg in (0.0, 45.0):
        t = np.radians(deg)
        v = np.array([np.sin(t), 0.0, np.cos(t)], np.float32)
        r = 2 * v @ n * n - v
        split, exact = (np.asarray(a) for a in split_and_exact(jnp.asarray(v), jnp.asarray(r)))
        np.testing.assert_allclose(split, exact, rtol=0.04)


def test_octahedral_environment_keeps_constant_maps_and_a_suns_energy():
    h, w = 128, 256
    const = E.octahedral_environment(np.full((h, w, 3), 0.7, np.float32), 16)
    np.testing.assert_allclose(const, 0.7, rtol=1e-5)
    sun = np.zeros((h, w, 3), np.float32)
    sun[40, 100] = 1e4  # one texel: it must land whole in one pixel, with its energy
    from jprt.sphere import cubemap

    energy = 1e4 * float(np.asarray(cubemap.equirect_solid_angles(h, w))[40, 100])
    grid = E.octahedral_environment(sun, 16)
    sa = np.asarray(octahedral.texel_solid_angles(16))
    assert (grid[..., 0] > 0).sum() == 1
    assert float((grid[..., 0] * sa).sum()) == pytest.approx(energy, rel=0.1)
    with pytest.raises(ValueError, match="too coarse"):
        E.octahedral_environment(np.ones((8, 16, 3), np.float32), 32)


def test_fast_evaluator_equals_the_reference_shading_of_its_fetched_lobes():
    """The evaluator's planar pixel-space path (one packed fetch, (..., N) planes) with Appendix
    B's shading (``shading.samples`` 0) against ``shade`` of ``lookup_lobes``: the same numbers to float
    rounding (the sampled shading's planar path: test_sg_lightfield)."""
    from jprt.inputs import GBuffer, LightScale
    from jprt.methods.lightmap_lookup import atlas_image, atlas_lookup

    rng = np.random.default_rng(1)
    t, r, n, h = 40, 8, 5, 12
    axes = rng.normal(size=(t, n, 3))
    axes /= np.linalg.norm(axes, axis=-1, keepdims=True)
    params = {"axes": jnp.asarray(axes, jnp.float16), "sharpness": jnp.asarray(rng.uniform(0.5, 1e4, (t, n)), jnp.float16),
              "amplitude": jnp.asarray(rng.uniform(0, 2, (t, n, 3)), jnp.float16),
              "irradiance": jnp.asarray(rng.uniform(0, 1, (t, 3)), jnp.float16),
              "fill_index": rng.integers(0, t, r * r).astype(np.int32)}
    normal = rng.normal(size=(h, h, 3))
    normal[..., 2] = np.abs(normal[..., 2]) + 0.1
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    view = rng.normal(size=(h, h, 3))
    view[..., 2] = np.abs(view[..., 2]) + 0.1
    view /= np.linalg.norm(view, axis=-1, keepdims=True)
    f32 = lambda x: np.asarray(x, np.float32)  # noqa: E731
    g = GBuffer(position=f32(np.zeros((h, h, 3))), normal=f32(normal), view=f32(view), reflected=f32(view),
                uv=f32(rng.uniform(0, 1, (h, h, 2))), diffuse_albedo=f32(rng.uniform(0, 1, (h, h, 3))),
                specular_albedo=f32(rng.uniform(0, 1, (h, h, 3))), roughness=f32(rng.uniform(0.01, 1, (h, h))),
                object_id=np.zeros((h, h), np.int32), valid=rng.uniform(size=(h, h)) > 0.2)
    got = np.asarray(M.evaluator(params, {"shading": {"samples": 0, "space": "pixel"}})(
        g, LightScale(np.ones(3, np.float32))))

    @jax.jit  # one program for the reference (eagerly, each operation compiles on its own)
    def reference(p, g):
        irr = atlas_lookup(atlas_image(jnp.asarray(p["irradiance"], jnp.float32), jnp.asarray(p["fill_index"])),
                           jnp.asarray(g.uv))
        return M.shade(M.lookup_lobes(p, g.uv), g.normal, g.view, g.roughness, g.specular_albedo, g.diffuse_albedo, irr)

    want = np.asarray(reference(params, g))
    want = np.where(g.valid[..., None], want, 0.0)
    np.testing.assert_allclose(got, want, rtol=2e-5, atol=1e-6)


def test_the_environment_methods_evaluator_is_eq8_of_its_lobes_and_lighting():
    """``jprt.methods.sg_environment``'s tiled evaluator on (..., N) planes against Eq. 8 composed
    from ``lookup_lobes``, ``evaluate_lobes`` and ``lookup_preconvolved``: the same numbers to
    float rounding, tiles of a size that does not divide the frame included; and the one-fetch
    lookup of all alpha levels equals looking up each level's map on its own."""
    from jprt.inputs import GBuffer, PreconvolvedEnvironment
    from jprt.methods.sg_environment import model as SE

    rng = np.random.default_rng(2)
    t, r, n, h = 30, 8, 4, 11
    axes = rng.normal(size=(t, n, 3))
    params = {"axes": jnp.asarray(axes / np.linalg.norm(axes, axis=-1, keepdims=True), jnp.float16),
              "sharpness": jnp.asarray(rng.uniform(0.5, 50, (t, n)), jnp.float16),
              "amplitude": jnp.asarray(rng.uniform(0, 1, (t, n, 3)), jnp.float16),
              "fill_index": rng.integers(0, t, r * r).astype(np.int32)}
    normal = rng.normal(size=(h, h, 3))
    normal[..., 2] = np.abs(normal[..., 2]) + 0.2
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    view = normal + 0.5 * rng.normal(size=(h, h, 3))
    view /= np.linalg.norm(view, axis=-1, keepdims=True)
    f32 = lambda x: np.asarray(x, np.float32)  # noqa: E731
    g = GBuffer(position=f32(np.zeros((h, h, 3))), normal=f32(normal), view=f32(view), reflected=f32(view),
                uv=f32(rng.uniform(0, 1, (h, h, 2))), diffuse_albedo=f32(np.zeros((h, h, 3))),
                specular_albedo=f32(rng.uniform(0, 1, (h, h, 3))), roughness=f32(rng.uniform(0.01, 1, (h, h))),
                object_id=np.zeros((h, h), np.int32), valid=rng.uniform(size=(h, h)) > 0.2)
    lit = PreconvolvedEnvironment.create(rng.uniform(0, 3, (4, 8, 8, 3)), [0.05, 0.2, 0.5, 1.0])
    got = np.asarray(SE.evaluator(params, tile=50)(g, lit))
    refl = f32(2.0 * np.sum(normal * view, axis=-1, keepdims=True) * normal - view)

    @jax.jit  # one program for the reference composition (eager, each op compiles on its own)
    def reference(params, g, lit, refl):
        u_r = E.lookup_preconvolved(lit.u, lit.alphas, refl, g.roughness)
        w = E.evaluate_lobes(M.lookup_lobes(params, g.uv), refl)
        levels = jnp.stack([E.octahedral_lookup(lit.u[k], refl) for k in range(4)])
        return u_r, E.shade_environment(u_r, w, g.normal, g.view, g.roughness, g.specular_albedo), levels

    u_r, want, levels = (np.asarray(x) for x in reference(params, g, lit, refl))
    np.testing.assert_allclose(got, np.where(g.valid[..., None], want, 0.0), rtol=2e-5, atol=1e-6)
    a = np.clip(g.roughness, 0.05, 1.0)
    hi = np.clip(np.searchsorted(lit.alphas, a, side="right"), 1, 3)
    t_ = ((a - lit.alphas[hi - 1]) / (lit.alphas[hi] - lit.alphas[hi - 1]))[..., None]
    pick = lambda i: np.take_along_axis(levels, i[None, ..., None], axis=0)[0]  # noqa: E731
    np.testing.assert_allclose(np.asarray(u_r), pick(hi - 1) * (1 - t_) + pick(hi) * t_, rtol=1e-5, atol=1e-6)


@pytest.mark.mitsuba
def test_we_from_a_capture_is_near_zero_under_a_plate_and_high_under_the_open_sky(mi, tmp_path):
    """Cornell floor texels away from the open front (z <= 0.25) and half a texel or more from
    the walls, W_E at r = n (straight up, alpha 0.05, a constant sky): with the ceiling on (a
    plate over the floor) near 0; with it removed, high (the opening above spans about 27 degrees
    around the normal, so the lobe's GGX tails still meet the walls: not exactly 1)."""
    from jprt.render import lightfield

    values = {}
    for name, scene in (("plate", {"name": "cornell_box", "area_light": False}),
                        ("open", {"name": "cornell_box", "area_light": False, "open_top": True})):
        vis = lightfield.capture_visibility(scene, objects=["floor"], resolution=8, size=32, samples=2,
                                           cache_dir=str(tmp_path), progress=False)
        assert vis.visible.shape[1:] == (32, 32) and np.isfinite(vis.visible).all()
        assert ((0 <= vis.visible) & (vis.visible <= 1)).all()
        w, _ = E.weighted_visibility(vis.visible, vis.normal, np.full(len(vis.normal), 0.05), _sky(32), 16)
        # each texel's own map at its normal, one program for all of them
        up = np.asarray(jax.jit(jax.vmap(E.octahedral_lookup))(w, jnp.asarray(vis.normal)))[:, 0]
        values[name] = up
        # texel centres: the conservative texels at the floor's rim sit within a quarter texel of
        # the walls, whose feet block the lobe's tails far more there
        half = 0.5 * float(vis.atlas["texel_size"])
        inner = (np.abs(vis.position[:, 0]) <= 1.0 - half) & (vis.position[:, 2] >= -1.0 + half)
        keep = (vis.flags == lightfield.OK) & (vis.position[:, 2] <= 0.25) & inner
    assert keep.sum() >= 6
    assert (values["plate"][keep] < 0.05).all(), values["plate"][keep]
    assert (values["open"][keep] > 0.6).all() and values["open"][keep].mean() > 0.75, values["open"][keep]


def test_turning_the_preconvolved_map_is_preconvolving_the_turned_map():
    """A lighting design turns SG environment visibility's U (Eq. 6) instead of pre-convolving
    the turned map again (``rotate_preconvolved_y``): on a procedural sky with suns, U turned by
    0.7 rad matches the pre-convolution of the map turned by ``rotate_cubemap_y`` to a few
    percent (the two grids' resampling), far closer than the unturned U does; no turn is no
    change."""
    from jprt.sphere import cubemap
    from jprt.sphere.envmap import render_equirect, synthetic_environments

    cube = synthetic_environments(1, 16, seed=3)[0]
    alphas = [0.3, 0.6]

    def u_of(c):
        grid = E.octahedral_environment(render_equirect(np.asarray(c, np.float32)), 32)
        return np.asarray(E.preconvolve(grid, alphas, 16))

    angle = 0.7
    rotate = jax.jit(E.rotate_preconvolved_y)  # one program (eagerly each operation dispatches alone)
    ref, unturned = u_of(cubemap.rotate_cubemap_y(cube, angle)), u_of(cube)
    turned = np.asarray(rotate(unturned, angle))
    assert turned.shape == unturned.shape == (2, 16, 16, 3)
    err = np.abs(turned - ref).mean() / np.abs(ref).mean()
    base = np.abs(unturned - ref).mean() / np.abs(ref).mean()
    assert err < 0.05 and err < 0.25 * base, (err, base)
    np.testing.assert_allclose(np.asarray(rotate(unturned, 0.0)), unturned, rtol=1e-4,
                               atol=1e-4 * float(unturned.max()))
    # differentiable in the angle: the design's gradient is finite and moves U
    g = jax.jit(jax.grad(lambda a: jnp.sum(E.rotate_preconvolved_y(unturned, a) * ref)))(jnp.float32(angle))
    assert np.isfinite(float(g)) and float(g) != 0.0
