"""Classic SH PRT's exit transfer (Sloan et al. 2002 §5, its exit form): the least-squares fit
recovers a band-limited function of the view direction from its hemisphere of directions, the
evaluator shades a view-dependent texel by sum_j Y_j(view) sum_i M_ji l_i and every other pixel
as the along-normal lightmap, and the bake's texels are exactly those of view-dependent
materials (Mitsuba's BSDF flags)."""

import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from jprt.inputs import GBuffer, SHLighting
from jprt.methods.sh_prt import data, model
from jprt.sphere import sh


@settings(max_examples=10, deadline=None)
@given(seed=st.integers(0, 2 ** 16), n=st.sampled_from([16, 32, 64]))
def test_exit_directions_cover_each_hemisphere(seed, n):
    rng = np.random.default_rng(seed)
    normal = rng.normal(size=(5, 3))
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    d = data.exit_directions(normal, n, seed)
    assert d.shape == (5, n, 3)
    np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1.0, atol=1e-9)
    cos = np.einsum("gdk,gk->gd", d, normal)
    assert np.all(cos > 0.0)
    # equal solid angles: the mean cosine over the hemisphere is 1/2
    np.testing.assert_allclose(cos.mean(axis=1), 0.5, atol=0.5 / n + 1e-9)


def test_exit_fit_recovers_a_band_limited_function_of_the_view_and_is_bounded_below_it():
    rng = np.random.default_rng(4)
    normal = np.array([[0.0, 0.0, 1.0]])
    d = data.exit_directions(normal, 64, 1)
    # a function even in the tangent plane (only Y_lm with l + |m| even about the z normal) is its
    # own mirror extension: the fit recovers it exactly
    even = np.array([(l + abs(m)) % 2 == 0 for l in range(3) for m in range(-l, l + 1)])
    truth = rng.normal(size=(1, sh.num_coeffs(2), 3)) * even[None, :, None]
    y = np.asarray(sh.evaluate(d.reshape(-1, 3).astype(np.float32), 2), np.float64).reshape(1, 64, -1)
    radiance = np.einsum("gdj,gjc->gdc", y, truth)
    fitted = data._exit_fit(d, normal, radiance, 2)
    np.testing.assert_allclose(fitted, truth, atol=1e-4)
    # any radiance: the fit below the horizon is the fit at the mirrored direction
    other = rng.uniform(0.0, 1.0, (1, 64, 3))
    fitted = data._exit_fit(d, normal, other, 3)
    below = d * np.array([1.0, 1.0, -1.0])
    f = lambda v: np.asarray(sh.evaluate(v.reshape(-1, 3).astype(np.float32), 3), np.float64) @ fitted[0]
    np.testing.assert_allclose(f(below), f(d), atol=1e-4)


def _tiny(res=4, degree=1, exit_degree=2, seed=0):
    """Params of a res x res atlas whose every pixel is a texel, texel 5 view-dependent."""
    rng = np.random.default_rng(seed)
    n, m, t = sh.num_coeffs(degree), sh.num_coeffs(exit_degree), res * res
    params = {"transfer": rng.uniform(0.0, 1.0, (t, n, 3)).astype(np.float32),
              "texel_index": np.arange(t, dtype=np.int32), "fill_index": np.arange(t, dtype=np.int32),
              "exit_transfer": rng.normal(size=(1, m, n, 3)).astype(np.float32),
              "exit_texel": np.array([5], np.int32), "exit_normal": np.array([[0.0, 0.0, 1.0]], np.float32)}
    centres = (np.arange(res, dtype=np.float32) + 0.5) / res
    uv = np.stack(np.meshgrid(centres, centres, indexing="xy"), axis=-1)
    zeros3 = np.zeros((res, res, 3), np.float32)
    inputs = GBuffer(position=zeros3, normal=zeros3, view=zeros3, reflected=zeros3, uv=uv, diffuse_albedo=zeros3,
                     specular_albedo=zeros3, roughness=np.zeros((res, res), np.float32),
                     object_id=np.zeros((res, res), np.int32), valid=np.ones((res, res), bool))
    lighting = SHLighting(rng.normal(size=(n, 3)).astype(np.float32))
    return params, inputs, lighting


def test_a_view_dependent_texel_is_shaded_along_the_view_and_the_rest_as_the_lightmap():
    params, inputs, lighting = _tiny()
    evaluate = model.evaluator(params)
    flat = model.lightmap(params["transfer"], lighting.coefficients)  # (T, 3) along the normals
    view = np.zeros((16, 3), np.float32)
    view[5] = [0.3, -0.4, np.sqrt(1.0 - 0.25)]  # in front of texel 5
    view[6] = [0.0, 0.0, 1.0]  # a diffuse texel: its view changes nothing
    image = np.asarray(evaluate(inputs._replace(view=view.reshape(4, 4, 3)), lighting)).reshape(-1, 3)
    coeff = np.einsum("jic,ic->jc", params["exit_transfer"][0].astype(np.float64), lighting.coefficients)
    expect = np.asarray(sh.evaluate(view[5:6], 2), np.float64)[0] @ coeff
    np.testing.assert_allclose(image[5], expect, rtol=1e-4, atol=1e-5)
    others = np.arange(16) != 5
    np.testing.assert_allclose(image[others], flat[others], rtol=1e-5, atol=1e-6)
    # no view (an atlas G-buffer) or a view behind the texel: the radiance along its normal
    behind = view.copy()
    behind[5] = [0.0, 0.6, -0.8]
    for v in (np.zeros((16, 3), np.float32), behind):
        image = np.asarray(evaluate(inputs._replace(view=v.reshape(4, 4, 3)), lighting)).reshape(-1, 3)
        np.testing.assert_allclose(image, flat, rtol=1e-5, atol=1e-6)


def test_texel_lookup_is_the_atlas_image_lookup():
    """Reading each bilinear corner through the fill index is the lookup of the built atlas image,
    to the bit, at texel centres, between them and clamped past the atlas's edges."""
    from jprt.methods.lightmap_lookup import atlas_image, atlas_lookup, texel_lookup, texel_taps

    rng = np.random.default_rng(3)
    texels = rng.normal(size=(7, 5)).astype(np.float32)
    fill = rng.integers(0, 7, 36).astype(np.int32)  # a 6 x 6 atlas, texels repeated as the fill does
    uv = rng.uniform(-0.1, 1.1, (9, 11, 2)).astype(np.float32)
    expect = np.asarray(atlas_lookup(atlas_image(jnp.asarray(texels), jnp.asarray(fill)), jnp.asarray(uv)))
    got = np.asarray(texel_lookup(jnp.asarray(texels), jnp.asarray(fill), jnp.asarray(uv)))
    assert got.shape == (9, 11, 5) and np.array_equal(got, expect)
    # the same corners as texel indices and weights (texel-space shading reads through them)
    index, weight = (np.asarray(a) for a in texel_taps(jnp.asarray(fill), jnp.asarray(uv)))
    np.testing.assert_allclose(weight.sum(-1), 1.0, rtol=1e-6)
    np.testing.assert_allclose(np.einsum("...k,...kc->...c", weight, texels[index]), expect, rtol=1e-5, atol=1e-6)


def test_without_exit_transfer_the_evaluator_is_the_lightmap():
    params, inputs, lighting = _tiny()
    params.update(exit_transfer=np.zeros((0, 1, 1, 3), np.float32), exit_texel=np.zeros(0, np.int32),
                  exit_normal=np.zeros((0, 3), np.float32))
    view = np.tile(np.array([0.0, 0.0, 1.0], np.float32), (4, 4, 1))
    image = np.asarray(model.evaluator(params)(inputs._replace(view=view), lighting)).reshape(-1, 3)
    np.testing.assert_allclose(image, model.lightmap(params["transfer"], lighting.coefficients), rtol=1e-5, atol=1e-6)


def test_view_dependent_objects_are_read_from_the_bsdf_flags(mi, tmp_path):
    from jprt.render.gbuffer import view_dependent_objects
    from jprt.render.scenes import SceneHandle, xml

    shapes = {"matte": '<bsdf type="diffuse"/>',
              "twosided_matte": '<bsdf type="twosided"><bsdf type="diffuse"/></bsdf>',
              "varnish": '<bsdf type="twosided"><bsdf type="roughplastic"><float name="alpha" value="0.15"/>'
                         '</bsdf></bsdf>',
              "mirror": '<bsdf type="conductor"/>', "glass": '<bsdf type="dielectric"/>'}
    body = "".join(f'<shape type="rectangle" id="{k}"><transform name="to_world"><translate x="{3 * i}"/></transform>'
                   f"{b}</shape>" for i, (k, b) in enumerate(shapes.items()))
    path = tmp_path / "materials.xml"
    path.write_text(f'<scene version="3.0.0">{body}</scene>')
    handle = SceneHandle(xml(str(path)))
    names = handle.object_names()
    assert sorted(names[k] for k in view_dependent_objects(handle)) == ["glass", "mirror", "varnish"]


def test_a_negative_exit_order_is_refused():
    with pytest.raises(ValueError, match="sh.exit_order must be >= 0"):
        data.make_dataset("cornell_box", {"sh": {"exit_order": -1}})


def test_demodulated_lookup_shades_a_texture_finer_than_a_texel():
    """A Lambertian object whose light is its albedo a times E, E the same at every texel: with
    ``texel_modulation`` a pixel between two texels is shaded a_pixel E (the plain lookup blends
    its neighbours' a E); the atlas G-buffer (no albedo) still reads the texels' own light."""
    from jprt.methods.lightmap_lookup import atlas_inputs, texel_modulation

    rng = np.random.default_rng(4)
    t, res = 64, 8
    albedo = rng.uniform(0.1, 0.9, (t, 3)).astype(np.float32)
    energy = np.array([2.0, 1.5, 1.0], np.float32)
    params = {"transfer": (albedo * energy)[:, None, :], "texel_index": np.arange(t, dtype=np.int32),
              "fill_index": np.arange(res * res, dtype=np.int32),
              **dict(zip(("texel_modulation", "object_albedo"),
                         texel_modulation(albedo, np.zeros_like(albedo), np.zeros(t, int), np.zeros(t, int), 1)))}
    light = SHLighting(np.ones((1, 3), np.float32))
    evaluate = model.evaluator(params)
    atlas = np.asarray(evaluate(atlas_inputs(res, np.arange(t)), light)).reshape(-1, 3)
    np.testing.assert_allclose(atlas, albedo * energy, rtol=1e-5)
    rows, cols = np.meshgrid(np.arange(res), np.arange(res - 1), indexing="ij")
    uv = np.stack([(cols + 1.0) / res, (rows + 0.5) / res], axis=-1).astype(np.float32)
    pixel = rng.uniform(0.1, 0.9, uv.shape[:-1] + (3,)).astype(np.float32)
    gb = atlas_inputs(res, np.arange(t))._replace(uv=uv, valid=np.ones(uv.shape[:-1], bool), diffuse_albedo=pixel,
                                                   specular_albedo=np.zeros_like(pixel), view=np.zeros_like(pixel),
                                                   object_id=np.zeros(uv.shape[:-1], np.int32))
    np.testing.assert_allclose(np.asarray(evaluate(gb, light)), pixel * energy, rtol=1e-5)
    plain = {k: v for k, v in params.items() if k not in ("texel_modulation", "object_albedo")}
    blend = np.asarray(model.evaluator(plain)(gb, light))
    assert np.abs(blend - pixel * energy).max() > 0.1
