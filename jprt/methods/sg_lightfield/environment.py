"""Illumination-weighted environment visibility (Currius et al. 2020 §5, Eq. 3-8), pure JAX.

Glossy reflection of a distant environment L_E with visibility V (Eq. 3) is approximated as

    L_o(w_o) = U(w_r) W_E(w_r) G(w_r, w_o) F / (4 |w_o . n| |w_r . n|) |w_r . n|        (Eq. 8)

* ``preconvolve`` (Eq. 6): U(r) = int D(h) L_E(w_i) dw_i for a surface facing r (n = w_o = r),
  one octahedral map per GGX alpha of ``alphas`` (the paper's "3D texture"; looked up bilinearly
  in direction and linearly in alpha, ``lookup_preconvolved``).
* ``weighted_visibility`` (Eq. 7): per texel, W_E = int D L_E V dw_i / int D L_E dw_i with the
  texel's own normal and roughness, by quadrature over the captured visibility
  (``jprt.render.lightfield.capture_visibility``) and the environment splatted onto the same
  octahedral grid (``octahedral_environment``). W_E is a weighted mean of V, in [0, 1]: 1 where
  nothing is in the way.
* The map of W_E is parameterised by the *reflected* direction r (the view is w_o = reflect(r, n)):
  the paper writes W_E(w_o) in Eq. 7-8 but its shader (§6, step 3) evaluates the SGs at the
  reflected direction, and so does Eq. 8's U (errata in ../shared/papers/README.md). As a function
  of r, W_E follows the visibility's own shape (for a mirror it is V(r)), which lobes fit well.
  Directions r below the surface (so is w_o) are masked like the light field's.
* ``shade_environment``: Eq. 8 with the same G, F and n.l factor as the light-field shading
  (``model.glossy_factor``) and the Jacobian factor n . w_o that Eq. 8 as printed lacks (its
  docstring; an erratum found here), W_E from SG lobes (``model.Lobes``, fitted by the same CNN) or any
  other estimate of the visibility term: ``reflected_visibility`` (visibility tested along w_r
  alone, the paper's Fig. 4 leak) and 1 (no visibility) are the comparisons.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from jprt.methods.sg_lightfield.model import GLOSSY_RECEIVERS, ggx_ndf, glossy_factor
from jprt.sphere import octahedral
from jprt.sphere.cubemap import turned_back_y

__all__ = ["ENV_RECEIVERS", "ENV_DEFAULTS", "ggx_ndf", "octahedral_environment", "preconvolve", "weighted_visibility",
           "lookup_preconvolved", "octahedral_lookup", "rotate_preconvolved_y", "evaluate_lobes", "shade_environment"]

#: The Table 3 setting: the receivers of ``model.GLOSSY_RECEIVERS`` in the Cornell box without its
#: ceiling and light, lit by a distant environment through the open top and front.
ENV_RECEIVERS = {"name": "cornell_box", "area_light": False, "open_top": True,
                 "materials": GLOSSY_RECEIVERS["materials"]}

#: Defaults of the environment-visibility setting
#: (``jprt.methods.sg_lightfield.data.make_environment_dataset``).
ENV_DEFAULTS = {
    "map": "immenstadter_horn_1k",  # a stem of ../shared/assets/envmaps, or "synthetic" (seeded, no files)
    "folder": "",
    "seed": 0,
    "rotation": 0.0,  # degrees about +Y
    "visibility_size": 64,  # octahedral visibility / environment grid of Eq. 7's quadrature
    "samples": 4,  # jittered visibility rays per pixel
    "size": 32,  # the W_E maps the lobes fit (reflected directions)
    "u_size": 64,  # the pre-convolved environment's octahedral maps (Eq. 6)
    "u_env_size": 128,  # the environment grid Eq. 6 integrates over
    "alphas": [0.05, 0.1, 0.2, 0.3, 0.4, 0.5, 0.7, 1.0],  # GGX alpha levels of U
}


def octahedral_environment(radiance, size: int) -> np.ndarray:
    """An equirect environment (H, W, 3) (``jprt.render.lights`` layout) as an (n, n, 3)
    octahedral map that keeps its energy: every equirect texel's radiance x solid angle is added
    to the octahedral pixel holding its centre, then divided by the solid angle of the texels it
    received (exact for a constant map; the pixel's own solid angle would alias with the texel
    count); a sun of a few texels lands whole in one pixel instead of being missed by point
    sampling.
    Needs the equirect finer than the octahedral map (every pixel receives texels)."""
    from jprt.sphere import cubemap

    radiance = np.asarray(radiance, np.float64)
    h, w = radiance.shape[:2]
    d = np.asarray(cubemap.equirect_directions(h, w), np.float64).reshape(-1, 3)
    sa = np.asarray(cubemap.equirect_solid_angles(h, w), np.float64).reshape(-1)
    row, col = (np.asarray(a) for a in octahedral.direction_to_texel(jnp.asarray(d, jnp.float32), int(size)))
    flat = row.reshape(-1) * int(size) + col.reshape(-1)
    energy = np.zeros((int(size) ** 2, 3))
    np.add.at(energy, flat, radiance.reshape(-1, 3) * sa[:, None])
    area = np.bincount(flat, weights=sa, minlength=int(size) ** 2)
    if (area == 0).any():
        raise ValueError(f"the {h}x{w} environment is too coarse for a {size}^2 octahedral map "
                         f"({int((area == 0).sum())} pixels receive no texel)")
    return (energy / area[:, None]).reshape(int(size), int(size), 3).astype(np.float32)


def _grid(size: int):
    return (jnp.asarray(octahedral.texel_directions(size)).reshape(-1, 3),
            jnp.asarray(octahedral.texel_solid_angles(size)).reshape(-1))


@functools.partial(jax.jit, static_argnames=("size", "chunk"))  # one program (eager, ~100 small compiles)
def preconvolve(env, alphas, size: int, *, chunk: int = 512) -> jax.Array:
    """Eq. 6: U(r) = sum_i D(h_i; n = r) L_E(w_i) dOmega_i over w_i . r > 0, h_i = (w_i + r) /
    |w_i + r|, for the octahedral environment ``env`` (m, m, 3), at the centres of a ``size``^2
    octahedral map, for every GGX alpha of ``alphas``: (A, size, size, 3)."""
    dirs, sa = _grid(env.shape[0])
    light = jnp.asarray(env, jnp.float32).reshape(-1, 3) * sa[:, None]
    out_dirs = jnp.asarray(octahedral.texel_directions(size)).reshape(-1, 3)

    def one(alpha):
        def rows(r):  # (c, 3) -> (c, 3)
            h = dirs[None, :, :] + r[:, None, :]
            h = h / jnp.sqrt(jnp.maximum(jnp.sum(h * h, axis=-1, keepdims=True), 1e-20))
            k = ggx_ndf(jnp.sum(h * r[:, None, :], axis=-1), alpha) * (r @ dirs.T > 0.0)
            return k @ light

        pad = (-out_dirs.shape[0]) % chunk
        r = jnp.concatenate([out_dirs, jnp.broadcast_to(out_dirs[:1], (pad, 3))]).reshape(-1, chunk, 3)
        return jax.lax.map(rows, r).reshape(-1, 3)[:out_dirs.shape[0]]

    return jnp.stack([one(jnp.float32(a)) for a in alphas]).reshape(len(alphas), size, size, 3)


@functools.partial(jax.jit, static_argnames=("size", "chunk"))
def weighted_visibility(visible, normal, roughness, env, size: int, *, chunk: int = 8):
    """Eq. 7 for every texel: W_E(r) = sum_i D V L dOmega / sum_i D L dOmega with D the texel's
    GGX NDF (its ``normal`` (T, 3), ``roughness`` (T,)) at the half vector of w_i and the view
    w_o = reflect(r, n), over w_i . n > 0, for r at the centres of a ``size``^2 octahedral map.
    ``visible`` (T, m, m) and ``env`` (m, m, 3) share one grid. Returns (W (T, size, size, 3),
    below (T, size, size)); W = 1 where the environment gives the lobe no light at all."""
    m = env.shape[0]
    if visible.shape[1:] != (m, m):
        raise ValueError(f"visibility maps {visible.shape[1:]} and environment {env.shape[:2]} differ in size")
    dirs, sa = _grid(m)
    light = jnp.asarray(env, jnp.float32).reshape(-1, 3) * sa[:, None]  # (M, 3)
    r = jnp.asarray(octahedral.texel_directions(size)).reshape(-1, 3)  # (P, 3)
    vis = jnp.asarray(visible, jnp.float32).reshape(visible.shape[0], -1)
    normal = jnp.asarray(normal, jnp.float32)
    alpha = jnp.maximum(jnp.asarray(roughness, jnp.float32), 1e-3)

    def texel(args):
        v, n, a = args
        wo = 2.0 * (r @ n)[:, None] * n[None, :] - r  # (P, 3)
        h = dirs[None, :, :] + wo[:, None, :]
        h = h / jnp.sqrt(jnp.maximum(jnp.sum(h * h, axis=-1, keepdims=True), 1e-20))
        k = ggx_ndf(h @ n, a) * (dirs @ n > 0.0)[None, :]  # (P, M)
        num, den = k @ (light * v[:, None]), k @ light
        return jnp.where(den > 0.0, num / jnp.where(den > 0.0, den, 1.0), 1.0)

    t = vis.shape[0]
    pad = (-t) % chunk
    padded = [jnp.concatenate([x, jnp.repeat(x[:1], pad, axis=0)]) if pad else x for x in (vis, normal, alpha)]
    out = jax.lax.map(lambda b: jax.vmap(texel)(b), tuple(x.reshape((-1, chunk) + x.shape[1:]) for x in padded))
    w = out.reshape((-1,) + out.shape[2:])[:t].reshape(t, size, size, 3)
    below = (normal @ r.T <= 0.0).reshape(t, size, size)
    return jnp.where(below[..., None], 0.0, w), below


def octahedral_lookup(image, d):
    """Bilinear lookup of one octahedral map (n, n, C) at unit directions d (..., 3): (..., C).
    Texel centres as ``octahedral.texel_centers`` (the atlas lookup's convention on the square
    mapped to [0, 1]^2); clamped at the square's border (the octahedral fold is not wrapped, a
    half-texel approximation there)."""
    from jprt.methods.lightmap_lookup import atlas_lookup

    return atlas_lookup(image, (octahedral.encode(d) + 1.0) * 0.5)


def rotate_preconvolved_y(u, angle):
    """The pre-convolved maps ``u`` (A, n, n, 3) (``preconvolve``) of the environment turned by
    ``angle`` radians about +Y: a direction d of the result sees what R(-angle) d saw (the
    convention of ``jprt.sphere.cubemap.rotate_cubemap_y``), every octahedral texel centre
    bilinear in the original (``octahedral_lookup``). Eq. 6 turns with the map (the GGX NDF about
    r turns with r), so this is the pre-convolution of the turned map, up to the resampling:
    a lighting design turns U instead of pre-convolving again. Differentiable in ``angle`` and
    ``u`` (the bilinear weights have kinks where a turned centre crosses a texel centre)."""
    u = jnp.asarray(u, jnp.float32)
    n_levels, n = u.shape[0], u.shape[1]
    src = turned_back_y(jnp.asarray(octahedral.texel_directions(n), jnp.float32), angle)
    stacked = jnp.moveaxis(u, 0, 2).reshape(n, n, 3 * n_levels)  # every level in one bilinear fetch
    return jnp.moveaxis(octahedral_lookup(stacked, src).reshape(n, n, n_levels, 3), 2, 0)


def lookup_preconvolved(u, alphas, r, roughness):
    """U at reflected directions r (..., 3) and GGX alphas (...): bilinear in the octahedral maps
    ``u`` (A, n, n, 3) of ``preconvolve``, linear in alpha between the two nearest levels of the
    increasing ``alphas`` (clamped at the ends)."""
    alphas = jnp.asarray(alphas, jnp.float32)
    u = jnp.asarray(u, jnp.float32)
    n_levels = u.shape[0]
    a = jnp.clip(jnp.asarray(roughness, jnp.float32), alphas[0], alphas[-1])
    hi = jnp.clip(jnp.searchsorted(alphas, a, side="right"), 1, n_levels - 1)
    lo = hi - 1
    t = ((a - alphas[lo]) / jnp.maximum(alphas[hi] - alphas[lo], 1e-12))[..., None]
    # every level in one bilinear fetch: the maps stacked along channels, (n, n, 3A)
    stacked = jnp.moveaxis(u, 0, 2).reshape(u.shape[1], u.shape[2], 3 * n_levels)
    levels = octahedral_lookup(stacked, r).reshape(jnp.shape(r)[:-1] + (n_levels, 3))  # (..., A, 3)
    pick = lambda idx: jnp.take_along_axis(levels, idx[..., None, None], axis=-2)[..., 0, :]  # noqa: E731
    return pick(lo) * (1.0 - t) + pick(hi) * t


def evaluate_lobes(lobes, d):
    """Eq. 1 at one direction per pixel: sum_j mu_j exp(lambda_j (d . u_j - 1)) for lobes
    (..., N) and directions d (..., 3): (..., 3)."""
    cos = jnp.sum(lobes.axes * d[..., None, :], axis=-1)
    return jnp.sum(jnp.exp(lobes.sharpness * (cos - 1.0))[..., None] * lobes.amplitude, axis=-2)


def shade_environment(u_r, visibility, normal, view, roughness, specular):
    """Eq. 8 with its Jacobian restored: U(w_r) (n . w_o) x the visibility term (W_E(w_r) from
    lobes, V(w_r) along the reflected ray, or 1) x G F / (4 n.v) at w_r = reflect(-view, n), as in
    the light-field shading.

    The factor n . w_o: Eq. 3's integral over w_i of D(h) carries dw_i = 4 (h . w_o) dw_h, so for
    a sharp lobe int D(h) dw_i ~ 4 (n . w_o); U (Eq. 6) is integrated for a surface facing w_o,
    where that factor is 4. Eq. 8 as printed therefore overestimates by 1 / (n . w_o) at oblique
    views (measured against quadrature of the rendered BRDF under a constant sky, alpha 0.2:
    1.45x at 45 degrees, 1.01x at normal view; with the factor, within 3 %, tested)."""
    normal, view = jnp.asarray(normal), jnp.asarray(view)
    ndotv = jnp.sum(normal * view, axis=-1, keepdims=True)
    r = 2.0 * ndotv * normal - view
    return glossy_factor(jnp.asarray(u_r) * jnp.clip(ndotv, 0.0, 1.0) * jnp.asarray(visibility), r, normal, view,
                          jnp.maximum(jnp.asarray(roughness), 1e-3), specular)
