"""SG environment visibility (Currius et al. 2020 §5, Eq. 3-8), the run time in pure JAX.

Glossy reflection of a distant environment L_E with visibility V (Eq. 3) is approximated by
Eq. 8, L_o = U(w_r) W_E(w_r) G F / (4 n.v) (n . w_o) at the reflected view direction w_r:

* U (Eq. 6) is the environment pre-convolved with the GGX NDF at a few alphas, once per
  environment: ``preconvolved`` makes the ``jprt.inputs.PreconvolvedEnvironment`` the evaluator
  takes (the "3D texture" of §5; bilinear in direction, linear in alpha).
* W_E (Eq. 7), the illumination-weighted environment visibility, is stored per lightmap texel as
  N spherical Gaussians (7 numbers each, float16) predicted by the light-field CNN of §4 (the same
  encoder, loss and training as ``jprt.methods.sg_lightfield``; §5: "the same network can be used
  to create the SGs describing this function").
* The shading (``jprt.methods.sg_lightfield.environment.shade_environment``) keeps the Jacobian
  factor n . w_o that Eq. 8 as printed lacks, and evaluates W_E and U at w_r (errata in
  ../shared/papers/README.md).

W_E is weighted by the environment it was computed under (``environment`` in the config). Another
map changes U exactly and W_E not at all: for a different map the weighting is an approximation
(exact where the lobe is fully visible or fully blocked, and for a constant environment up to the
weighting). The viewer (``jprt view``) relights with any map and rotation, and its compare mode
shows what the approximation costs against Mitsuba.

The prediction is *direct* light: the environment reflected once by the glossy receivers (the
paper adds it to the light-field texture's indirect light). This module imports no Mitsuba.
"""

from __future__ import annotations

import copy
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from jprt.inputs import PreconvolvedEnvironment
from jprt.methods.base import FitResult, resolve
from jprt.methods.sg_lightfield import environment as env
from jprt.methods.sg_lightfield.environment import ENV_DEFAULTS, ENV_RECEIVERS
from jprt.methods.sg_lightfield import model as sgm

__all__ = ["DEFAULT_CONFIG", "fit", "evaluator", "example", "preconvolved"]

DEFAULT_CONFIG: dict[str, Any] = {
    "scene": ENV_RECEIVERS,  # the glossy receivers in the Cornell box without ceiling and light
    "objects": ["floor", "back", "small-box", "large-box"],  # the receivers: the texture covers them
    "lightmap": {"resolution": 64},  # the lightmap atlas's size in texels per side
    "capture": {"block": 256},  # texels per visibility-capture batch
    # the environment W_E is weighted by, and the sizes of Eq. 6-7's quadrature
    # (jprt.methods.sg_lightfield.environment.ENV_DEFAULTS)
    "environment": dict(ENV_DEFAULTS),
    # the per-texel lobes and their training: SG light-field textures' (jprt.methods.sg_lightfield.model)
    "model": copy.deepcopy(sgm.DEFAULT_CONFIG["model"]),
    "train": copy.deepcopy(sgm.DEFAULT_CONFIG["train"]),
}


def _cfg(config: dict | None) -> dict:
    return resolve(DEFAULT_CONFIG, config)


def fit(data, config: dict | None = None, *, progress: bool | None = None) -> FitResult:
    """Train the §4 encoder on every texel's W_E map (``data``: a
    ``jprt.methods.sg_lightfield.data.EnvData``) and keep what the run time needs: the lobes in
    float16 and the atlas's fill index. Returns ``FitResult(params, info)``. ``progress``: the
    training bar (``jprt.progress``; None: its policy).

    Numerics: not differentiable (a training loop).
    """
    import time

    cfg = _cfg(config)
    t0 = time.perf_counter()
    _, lobes, losses = sgm.fit_cnn(data.images, data.below, cfg, progress=progress)
    params = sgm.storage_params(lobes, data, max_sharpness=float(cfg["model"]["max_sharpness"]))
    nbytes = sum(np.asarray(params[k]).nbytes for k in ("axes", "sharpness", "amplitude"))
    return FitResult(params, {"losses": losses, "train_s": time.perf_counter() - t0,
                              "fit_log_l2": float(losses[-1]) if len(losses) else None,
                              "bytes_per_texel": int(nbytes) // len(data.images)})


def preconvolved(radiance, config: dict | None = None) -> PreconvolvedEnvironment:
    """Eq. 6 for an equirect environment ``radiance`` (H, W, 3) (``jprt.render.lights`` layout):
    U at the config's GGX ``environment.alphas`` on ``environment.u_size``^2 octahedral maps,
    integrated over a ``environment.u_env_size``^2 octahedral grid of the map (energy kept:
    ``environment.octahedral_environment``). What a renderer computes once when its environment
    changes; the evaluator only looks it up.

    Numerics: not differentiable (a per-environment precomputation; NumPy splatting, then Eq. 6's
    quadrature in float32).
    """
    e = _cfg(config)["environment"]
    grid = env.octahedral_environment(np.asarray(radiance, np.float32), int(e["u_env_size"]))
    u = env.preconvolve(grid, e["alphas"], int(e["u_size"]))
    return PreconvolvedEnvironment.create(np.asarray(u), np.asarray(e["alphas"], np.float32))


def evaluator(params, config: dict | None = None, *, tile: int = sgm.TILE):
    """``evaluate(inputs, lighting) -> (H, W, 3)``: a G-buffer with atlas ``uv``
    (``jprt.render.lightmap.atlas_gbuffer``) shaded by Eq. 8: at each pixel the reflected view
    direction w_r, W_E(w_r) from the texel's lobes (bilinear in the atlas, axes renormalised), U(w_r)
    from ``lighting`` (a ``PreconvolvedEnvironment``) at the pixel's GGX alpha, times Smith's G,
    Schlick's Fresnel with f0 = ``specular_albedo`` and n . w_o. Invalid pixels are 0. The texture
    is packed once here (one bilinear fetch reads a pixel's lobes, one more all of U's alpha
    levels); pixels are shaded in tiles of ``tile`` (a ``lax.map``: a tile's (pixels, N) planes
    stay in cache), several times faster on a CPU than one fetch per level with the lobes as
    (..., N, 3) vectors.

    Numerics: not differentiable (builds the float32 run-time program from
    ``sg_lightfield.model``'s lobe fetch and ``environment``'s Eq. 8).
    """
    _cfg(config)
    n = params["sharpness"].shape[-1]
    table = sgm.lobe_table(params)
    tile = int(tile)

    def shade(table, u, alphas, uv, normal, view, roughness, specular):
        from jprt.methods.lightmap_lookup import atlas_lookup

        r = 2.0 * jnp.sum(normal * view, axis=-1, keepdims=True) * normal - view
        # Eq. 1 at w_r on the fetched (..., N) planes (``environment.evaluate_lobes`` on (..., N, 3)
        # vectors is the same sum; planes keep XLA's fusions per tile, as in the light-field run time)
        ux, uy, uz, lam, *amp = sgm.lobe_planes(atlas_lookup(table, uv), n)
        cos = (ux * r[..., 0:1] + uy * r[..., 1:2] + uz * r[..., 2:3]) * jax.lax.rsqrt(
            jnp.maximum(ux * ux + uy * uy + uz * uz, 1e-20))
        weight = jnp.exp(lam * (cos - 1.0))
        w = jnp.stack([jnp.sum(weight * a, axis=-1) for a in amp[:3]], axis=-1)
        u_r = env.lookup_preconvolved(u, alphas, r, roughness)
        return env.shade_environment(u_r, w, normal, view, roughness, specular)

    @jax.jit
    def _evaluate(table, inputs, u, alphas):
        out = sgm.map_tiles(lambda *f: shade(table, u, alphas, *f),
                            (inputs.uv, inputs.normal, inputs.view, inputs.roughness, inputs.specular_albedo), tile)
        return jnp.where(jnp.asarray(inputs.valid, bool)[..., None], out, 0.0)

    def evaluate(inputs, lighting: PreconvolvedEnvironment):
        return _evaluate(table, inputs, lighting.u, lighting.alphas)

    return evaluate


def example(data, config: dict | None = None):
    """The atlas seen head-on (every texel along its own normal, its own roughness, specular 0.9)
    under the environment W_E was computed for.

    Numerics: not differentiable (a held-out input and lighting from a dataset).
    """
    from jprt.methods.lightmap_lookup import atlas_inputs

    _cfg(config)
    r = int(data.atlas["resolution"])
    index = np.asarray(data.atlas["texel_index"])
    g = atlas_inputs(r, index)
    normal = np.zeros((r * r, 3), np.float32)
    normal[:, 2] = 1.0
    normal[index] = np.asarray(data.normal, np.float32)
    rough = np.full(r * r, 0.3, np.float32)
    rough[index] = np.asarray(data.roughness, np.float32)
    normal = normal.reshape(r, r, 3)
    g = g._replace(normal=normal, view=normal, reflected=normal, roughness=rough.reshape(r, r),
                   specular_albedo=np.full((r, r, 3), 0.9, np.float32))
    return g, PreconvolvedEnvironment.create(data.u, data.alphas)
