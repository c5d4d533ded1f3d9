"""Spherical-Gaussian light-field textures (Currius et al. 2020), the paper's math in pure JAX.

* **Lobes** (§4, Eq. 1): the light field T_t(v) of texel t is approximated by
  P_t(v) = sum_j mu_tj exp(lambda_tj (v . u_tj - 1)), N lobes of 7 numbers (axis, sharpness, RGB
  amplitude).
* **Constraints** (§4, "Constraints"): the paper projects gradients so that axes stay unit length
  and amplitudes and sharpnesses positive; here the network's raw outputs are reparameterised
  (``constrain``): u = r / |r|, mu = softplus(r_mu) >= 0, and log lambda = log lambda_min +
  (log lambda_max - log lambda_min) sigmoid(r_lambda), bounded so the lobes store in float16
  (lambda_max = 1e4 < 65504). Same constraints, no projection step.
* **Loss** (§4 "Loss Function" and Appendix A, Eq. 9): the log-L2 loss
  (log(T + 1) - log(P + 1))^2 per pixel and channel, weighted by each octahedral pixel's solid
  angle (the projection is not area preserving), with directions below the texel's surface
  masked out, and P evaluated at a direction jittered uniformly inside the pixel (§4
  "Optimizations"). Appendix A's derivatives (Eq. 10-14) are what ``jax.grad`` computes; the
  paper writes dmu_ic for dmu_jc in Eq. 12 and lambda_j x for lambda_j v_ix in Eq. 14 (the
  derivative of v . u w.r.t. u_x is v_x), checked against autodiff in the tests.
* **Encoder** (§4 "Encoder Network"): ``jprt.nn.cnn.sg_encoder`` maps a texel's light-field
  image to its N x 7 raw parameters; trained with Adam on all texels (``fit_cnn``). Its input is
  log(1 + T) (the paper does not say how HDR input is scaled; the loss compares logs too).
* **Run time** (§6): per pixel, the lobes of its texel (bilinear in the atlas), each integrated
  against the GGX BRDF at ``shading.samples``^2 directions drawn from it, or from the BRDF's
  visible normals where the lobe is broader than the BRDF (``shade_sampled``, the default:
  Appendix B's product lost 8 dB to the lobes' own quadrature bound on the benchmark's
  receivers), or, with ``shading.samples`` 0, by Appendix B (Eq. 15-24 with the errata of
  ``jprt.sphere.sg``, ``shade``): the GGX NDF as an SG warped to an ASG about the reflected view
  direction, each lobe convolved with it, times Smith's G (separable GGX, in the V = G / (4 n.l
  n.v) form) and Schlick's Fresnel at the reflected direction, times n.l; the diffuse term is
  albedo / pi times the texel's irradiance, integrated from the captured map.
  Eq. 17 as printed drops the 1 / (pi r^2) normalisation of the NDF; ``sg.ggx_ndf_sg`` keeps it.
  "Roughness" is GGX alpha throughout (Mitsuba's ``alpha``; Table 2 may mean perceptual
  roughness). The receivers are Mitsuba conductors with Fresnel = ``specular`` (``material
  "none"``); the shading keeps the paper's Schlick term with f0 = ``specular``, which departs
  from it only towards grazing angles.
* **Run-time layout**: ``evaluator`` packs the texture plane by plane (axis x, y, z, sharpness,
  amplitude r, g, b), fetches it with one bilinear lookup per pixel and shades on (..., N) planes
  (``_glossy_planes_product``, equal to ``shade`` to rounding, tested), tile by tile: the same
  arithmetic, laid out for XLA on CPU (``evaluator``'s docstring says why). Where the atlas has no
  more texels than the frame has pixels, each texel is shaded once (``shading.space``, texture-space
  shading) and the pixels read the shaded texels bilinearly: a departure from §6 (its cost in
  accuracy and its gain in time: docs/methods/sg_lightfield.md, "Where the lobes are shaded").
* **Environment visibility** (§5, Eq. 3-8): ``jprt.methods.sg_lightfield.environment``.
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jprt.inputs import LightScale
from jprt.sphere import octahedral
from jprt.sphere import sg

__all__ = ["DEFAULT_CONFIG", "GLOSSY_RECEIVERS", "SGData", "Lobes", "fit", "evaluator", "example", "lookup_lobes", "PARAMS_PER_LOBE", "constrain", "lobe_radiance", "jittered_directions",
           "log_l2_loss", "pixel_weights", "fit_cnn", "encode", "initial_amplitude", "texel_irradiance", "shade", "to_storage",
           "ggx_ndf", "ggx_brdf_cos", "shade_quadrature", "shade_sampled", "storage_params", "map_tiles"]

#: Raw numbers per lobe the encoder outputs: axis (3), sharpness (1), RGB amplitude (3).
PARAMS_PER_LOBE = 7

#: Receivers as Mitsuba rough conductors (so Eq. 15's BRDF is the rendered one) of GGX alpha
#: 0.2 / 0.3 / 0.4 / 0.5, lit by the Cornell box's ceiling light (the paper's Table 2 setting).
GLOSSY_RECEIVERS = {"name": "cornell_box", "area_light": True, "materials": {
    "floor": {"type": "metal", "specular": [0.9, 0.9, 0.9], "roughness": 0.2},
    "back": {"type": "metal", "specular": [0.85, 0.85, 0.9], "roughness": 0.3},
    "small-box": {"type": "metal", "specular": [0.9, 0.8, 0.6], "roughness": 0.4},
    "large-box": {"type": "metal", "specular": [0.8, 0.85, 0.9], "roughness": 0.5}}}

DEFAULT_CONFIG: dict[str, Any] = {
    "scene": GLOSSY_RECEIVERS,
    "objects": ["floor", "back", "small-box", "large-box"],  # the receivers: the light-field texture covers them
    "lightmap": {"resolution": 64},  # the lightmap atlas's size in texels per side
    "capture": {
        "size": 32,  # each texel's light field: an octahedral map of size^2 directions
        "spp": 64,  # paths per direction
        "seed": 0,  # seed of the capture's paths
        "block": 256,  # texels per capture batch (memory, not results)
        # "indirect" (paths that bounced: the evaluator then predicts indirect light, as every jprt
        # method does) or "full" (the emitters seen in the lobes too: direct + indirect, as the paper bakes)
        "field": "indirect",
        # each path along its own direction within the map pixel (box-filtered, ``jprt.render.
        # lightfield.capture_block``) instead of the pixel centre, same cost (measured on a
        # lamp-lit room: docs/methods/sg_lightfield.md)
        "jitter": False,
        # texels captured a second time (other seeds) for the self-check (data.self_check), at most
        # a tenth of the capturable ones (at the defaults ~5 % of the capture; 0: none); not part of
        # the light field's cache key
        "check_texels": 128,
    },
    "model": {
        "n_lobes": 16,  # N, spherical Gaussians per texel
        "channels": [32, 64, 128, 256],  # the encoder CNN's channels, one per stage (jprt.nn.cnn.sg_encoder)
        "min_sharpness": 0.5,  # the bounds of a lobe's sharpness lambda (``constrain``)
        "max_sharpness": 1.0e4,
        "init_sharpness": 1.0,  # the sharpness of a lobe whose raw parameters are 0 (broad lobes at the start)
    },
    "train": {
        "steps": 2000,  # Adam steps
        "batch": 64,  # texels per step
        "learning_rate": 1e-3,  # Adam's initial learning rate, decayed over the steps
        "final_lr_fraction": 0.1,  # the last step's learning rate over the first's
        "seed": 0,  # seed of the initial weights, the batches and the jitter
        "jitter": True,  # evaluate P at a direction jittered uniformly inside each octahedral pixel (§4)
    },
    # the run-time shading of the lobes: samples^2 stratified directions drawn from each lobe's SG,
    # each through the GGX BRDF (``shade_sampled``); 0: Appendix B's SG x ASG product (``shade``).
    # 3 chosen on the glossy receivers (benchmarks/results/sg_lightfield.json; docs/methods/sg_lightfield.md),
    # checked on veach-bidir (benchmarks/results/real_scenes.json: no loss there). brdf_sampling: a
    # lobe broader than the BRDF is integrated at samples^2 directions drawn from the BRDF instead
    # (its visible normals); off, every lobe is sampled itself, which loses up to 90 % of a broad
    # lobe's reflection at grazing views (``shade_sampled``). broad_bound: a lobe is broad where
    # lambda alpha^2 / 2 is below it (1: sharpness under 2 / alpha^2; chosen on
    # benchmarks/sg_shading.py's grid of single lobes)
    # space: where the lobes are shaded, "pixel" (§6: every pixel's bilinearly filtered lobes),
    # "texel" (each texel once, at its pixels' mean view, then read bilinearly) or "auto" ("texel"
    # where the atlas has no more texels than the frame has pixels; ``evaluator``)
    "shading": {"samples": 3, "brdf_sampling": True, "broad_bound": 1.0, "space": "auto"},
}


class SGData(NamedTuple):
    """A captured light-field texture (``data.make_dataset``).

    Fields:
      atlas: the lightmap atlas (dict of arrays, ``jprt.render.lightmap.Atlas``).
      images: (T, n, n, 3) the field the lobes fit (``capture.field``), one octahedral map per texel.
      below: (T, n, n) directions under each texel's surface.
      normal: (T, 3) texel normals.  flags: (T,) ``jprt.render.lightfield`` flags.
      irradiance: (T, 3) irradiance of the same field (the diffuse term's input).
      meta: capture settings and seconds.
    """

    atlas: dict
    images: np.ndarray
    below: np.ndarray
    normal: np.ndarray
    flags: np.ndarray
    irradiance: np.ndarray
    meta: dict


class Lobes(NamedTuple):
    """N SG lobes per texel: axes (..., N, 3) unit, sharpness (..., N) > 0, amplitude (..., N, 3) >= 0."""

    axes: jax.Array
    sharpness: jax.Array
    amplitude: jax.Array


@jax.custom_jvp
def _sigmoid(x):
    """The logistic function with its slope as sigmoid(x) sigmoid(-x): autodiff's s (1 - s) loses
    every digit where float32's s rounds to 1 (30 % off at x = 15.6, 0 above 17)."""
    return jax.nn.sigmoid(x)


@_sigmoid.defjvp
def _sigmoid_jvp(primals, tangents):
    (x,), (dx,) = primals, tangents
    return jax.nn.sigmoid(x), jax.nn.sigmoid(x) * jax.nn.sigmoid(-x) * dx


def constrain(raw, min_sharpness: float = 0.5, max_sharpness: float = 1.0e4, init_sharpness: float = 1.0,
              init_amplitude: float = math.log(2.0)) -> Lobes:
    """Raw encoder outputs (..., N, 7) -> constrained ``Lobes`` (module docstring). Raw zeros
    mean ``init_sharpness`` and ``init_amplitude``: lobes start broad, so every lobe's gradient
    reaches the whole image (sharp random lobes pointing away from the light die at the start),
    and as bright as the data (``fit_cnn`` sets it from the images: lobes far brighter than the
    light field are driven to zero amplitude and maximal sharpness, where they stay dead).

    Numerics:
        raw: (2, 4, 7) in [-30, 30]
        fd: off (a zero raw axis is replaced by +z, a jump, and zero raw values are always drawn)
        float32: value rtol 1e-5 atol 1e-6; grad rtol 1e-4 atol 1e-6
        (the sigmoid saturates: float32's 1 - sigmoid(x) is 0 above x = 17, where the slope is < 1e-7)
    """
    raw = jnp.asarray(raw)
    r = raw[..., :3]
    # a (near-)zero raw axis has no direction: +z stands in, chosen *before* the norm so that
    # neither value nor gradient divides by zero (a where after it would pass inf * 0 = NaN back)
    tiny = jnp.sum(r * r, axis=-1, keepdims=True) <= 1e-24
    r = jnp.where(tiny, jnp.broadcast_to(jnp.array([0.0, 0.0, 1.0], r.dtype), r.shape), r)
    axes = r / jnp.sqrt(jnp.sum(r * r, axis=-1, keepdims=True))
    lo, hi = math.log(min_sharpness), math.log(max_sharpness)
    s0 = (math.log(init_sharpness) - lo) / (hi - lo)
    sharpness = jnp.exp(lo + (hi - lo) * _sigmoid(raw[..., 3] + math.log(s0 / (1.0 - s0))))
    offset = math.log(math.expm1(max(float(init_amplitude), 1e-30)))  # softplus(offset) = init_amplitude
    return Lobes(axes, sharpness, jax.nn.softplus(raw[..., 4:7] + offset))


def lobe_radiance(lobes: Lobes, directions):
    """Eq. 1: P(v) = sum_j mu_j exp(lambda_j (v . u_j - 1)) for directions (..., M, 3) of each
    texel's lobes (..., N): (..., M, 3). v . u - 1 is evaluated as -|v - u|^2 / 2 (unit v, u): the
    dot product's float32 rounding, ~1e-7 absolute, is lambda x 1e-7 relative in the lobe (3e-3 at
    the largest sharpness, 1e4), the difference form's stays at rounding.

    Numerics:
        case: lobe_radiance (4 lobes of unit axes, sharpness in [0, 1e4], amplitude in [0, 1e5], at 16
          unit directions, aligned and antipodal ones among them)
        float32: value rtol 1e-4 atol 1e-25; grad rtol 1e-4 atol 1e-20
    """
    directions, axes = jnp.asarray(directions), jnp.asarray(lobes.axes)
    cos = -0.5 * jnp.sum(jnp.square(directions[..., :, None, :] - axes[..., None, :, :]), axis=-1)  # v . u - 1
    w = jnp.exp(lobes.sharpness[..., None, :] * cos)
    return jnp.einsum("...mn,...nc->...mc", w, lobes.amplitude)


def jittered_directions(key, size: int, shape=()):
    """Directions (*shape, size^2, 3), each uniform in its octahedral pixel's (u, v) square (§4
    "Optimizations": one jittered sample instead of the pixel's average).

    Numerics: not differentiable (random sample directions).
    """
    centres = octahedral.texel_centers(size).reshape(-1, 2)
    offsets = jax.random.uniform(key, tuple(shape) + centres.shape, minval=-1.0 / size, maxval=1.0 / size)
    return octahedral.decode(jnp.clip(jnp.broadcast_to(centres, offsets.shape) + offsets, -1.0, 1.0))


def log_l2_loss(lobes: Lobes, directions, targets, weights):
    """Eq. 9 summed over channels, weighted mean over pixels: targets (..., M, 3) at directions
    (..., M, 3) with weights (..., M) (solid angle x above-surface mask).

    Numerics:
        case: log_l2_loss (``lobe_radiance``'s domain, targets in [0, 1e5], weights in [0, 1])
        fd: off (the loss clamps the prediction at 0, a kink that zero amplitudes reach)
        float32: value rtol 1e-4 atol 1e-10; grad rtol 1e-4 atol 1e-10
    """
    return sg.log_l2(lobe_radiance(lobes, directions), targets, weights)


def pixel_weights(size: int, below):
    """Solid angle of every octahedral pixel, zero below the surface: (T, size^2).

    Numerics: not differentiable (a function of the integer size and a mask).
    """
    sa = jnp.asarray(octahedral.texel_solid_angles(size)).reshape(-1)
    return sa[None, :] * (1.0 - jnp.asarray(below, jnp.float32).reshape(below.shape[0], -1))


def initial_amplitude(images, below, n_lobes: int, init_sharpness: float) -> float:
    """The amplitude making N broad lobes' mean match the images' mean above the surfaces: a lobe
    of sharpness lambda averages (1 - exp(-2 lambda)) / (2 lambda) of its amplitude over the sphere.

    Numerics: not differentiable (a NumPy initial value).
    """
    seen = ~np.asarray(below, bool)
    mean = float(np.asarray(images, np.float64)[seen].mean()) if seen.any() else 0.0
    lam = float(init_sharpness)
    return max(mean, 1e-6) * 2.0 * lam / (-math.expm1(-2.0 * lam)) / int(n_lobes)


def encode(net_params, images, config: dict, init_amplitude: float = math.log(2.0)) -> Lobes:
    """The encoder's lobes for light-field images (T, n, n, 3) (its input is log(1 + T));
    ``init_amplitude``: the one the encoder was trained with (``fit_cnn``'s info).

    Numerics: not differentiable (covered as its parts: ``jprt.nn.cnn.sg_encoder`` and ``constrain``).
    """
    from jprt.nn.cnn import sg_encoder

    m = config["model"]
    net = sg_encoder(image_size=images.shape[1], n_lobes=int(m["n_lobes"]), params_per_lobe=PARAMS_PER_LOBE,
                     channels=tuple(m["channels"]))
    raw = net.apply(net_params, jnp.log1p(jnp.maximum(jnp.asarray(images, jnp.float32), 0.0)))
    return constrain(raw, float(m["min_sharpness"]), float(m["max_sharpness"]), float(m["init_sharpness"]),
                     init_amplitude)


def fit_cnn(images, below, config: dict, *, progress: bool | None = None):
    """Train the encoder on every texel's light-field image (T, n, n, 3), ``below`` (T, n, n)
    masking directions under the surface; Adam, minibatches of ``train.batch`` texels, cosine
    decay. Returns (net_params, lobes of every texel, losses). ``progress``: Adam's bar
    (``jprt.progress``; None: its policy).

    Numerics: not differentiable (a training loop).
    """
    import optax

    from jprt.nn.cnn import sg_encoder
    from jprt.solve import adam

    m, t = config["model"], config["train"]
    images = jnp.asarray(images, jnp.float32)
    n_tex, size = images.shape[0], images.shape[1]
    net = sg_encoder(image_size=size, n_lobes=int(m["n_lobes"]), params_per_lobe=PARAMS_PER_LOBE,
                     channels=tuple(m["channels"]))
    weights = pixel_weights(size, jnp.asarray(below))
    targets = images.reshape(n_tex, -1, 3)
    centres = octahedral.texel_directions(size).reshape(-1, 3)
    batch = min(int(t["batch"]), n_tex)
    jitter = bool(t["jitter"])

    a0 = initial_amplitude(images, below, int(m["n_lobes"]), float(m["init_sharpness"]))

    def loss_fn(params, batch):
        inputs, target, weight, dirs = batch
        raw = net.apply(params, inputs)
        lobes = constrain(raw, float(m["min_sharpness"]), float(m["max_sharpness"]), float(m["init_sharpness"]), a0)
        return log_l2_loss(lobes, dirs, target, weight)

    def sampler(key, step, data):
        logs, targets, weights = data
        k1, k2 = jax.random.split(key)
        idx = jax.random.choice(k1, n_tex, (batch,), replace=n_tex < batch)
        dirs = jittered_directions(k2, size, (batch,)) if jitter else jnp.broadcast_to(centres, (batch,) + centres.shape)
        return logs[idx], targets[idx], weights[idx], dirs

    steps = int(t["steps"])
    schedule = optax.cosine_decay_schedule(float(t["learning_rate"]), max(steps, 1), alpha=float(t["final_lr_fraction"]))
    params = net.init(jax.random.PRNGKey(int(t["seed"])))
    data = (jnp.log1p(jnp.maximum(images, 0.0)), targets, weights)  # an argument of the step, not a constant
    result = adam.train(loss_fn, params, sampler, key=jax.random.PRNGKey(int(t["seed"]) + 1), steps=steps,
                        learning_rate=schedule, eps=1e-8, progress=progress, data=data)
    trained = result.state.params
    lobes = jax.lax.map(lambda im: encode(trained, im[None], config, a0), images)
    lobes = Lobes(*(a[:, 0] for a in lobes))
    return trained, lobes, np.asarray(result.losses)


def texel_irradiance(images, normals, size: int):
    """E_t = sum_i T_t(v_i) max(n_t . v_i, 0) dOmega_i: each texel's irradiance (T, 3) from its
    captured map (the diffuse term's input), by quadrature at the pixel centres.

    Numerics:
        images: (2, 4, 4, 3) in [0, 1e5]
        normals: (2, 3) unit
        size: = 4
        fd: off (max(n . v, 0) has a kink, which axis-aligned normals hit at texel centres on the equator)
        float32: value rtol 1e-5 atol 1e-2; grad rtol 1e-5 atol 1e-6
        (a sum of 16 terms up to 1e5 x 0.8: rounding is absolute near zero)
    """
    dirs = octahedral.texel_directions(size).reshape(-1, 3)
    sa = jnp.asarray(octahedral.texel_solid_angles(size)).reshape(-1)
    cos = jnp.maximum(jnp.asarray(normals) @ dirs.T, 0.0)  # (T, M)
    return jnp.einsum("tm,tmc->tc", cos * sa[None, :], jnp.asarray(images).reshape(len(normals), -1, 3))


def _ggx_v1(m2, ndotx):
    """Separable Smith-GGX term with the 1 / (2 n.x) folded in: 1 / (n.x + sqrt(m2 + (1 - m2) n.x^2))."""
    return 1.0 / (ndotx + jnp.sqrt(m2 + (1.0 - m2) * ndotx * ndotx))


def _ggx_v1_cos(m2, ndotx):
    """n.x x ``_ggx_v1`` = 1 / (1 + sqrt(1 - m2 + m2 / n.x^2)) for n.x > 0, 0 otherwise: the product
    form's derivative at n.x = 1 is 1/2 - 1/2 plus a term of order m2, all lost in float32 for
    a mirror-like m2 (0 where float64 has 0.06 at alpha = 1e-4, against a D of 3e7)."""
    safe = jnp.where(ndotx > 0.0, ndotx, 1.0)
    return jnp.where(ndotx > 0.0, 1.0 / (1.0 + jnp.sqrt(1.0 - m2 + m2 / (safe * safe))), 0.0)


def _glossy_parts(conv, wi, normal, view, roughness):
    """``glossy_factor`` without Fresnel's f0, as (base, grazing) (``_fresnel_mix``)."""
    # clamped below only (a clip at 1 zeroes the derivative at normal incidence)
    ndotv = jnp.maximum(jnp.sum(normal * view, axis=-1), 1e-4)
    ndotl = jnp.sum(normal * wi, axis=-1)
    h = wi + view
    h = h / jnp.sqrt(jnp.maximum(jnp.sum(h * h, axis=-1, keepdims=True), 1e-20))
    m2 = jnp.square(roughness)
    vis_cos = _ggx_v1_cos(m2, ndotl) * _ggx_v1(m2, ndotv)  # V n.l
    base = conv * vis_cos[..., None]
    return base, base * jnp.power(1.0 - jnp.clip(jnp.sum(wi * h, axis=-1), 0.0, 1.0), 5.0)[..., None]


def glossy_factor(conv, wi, normal, view, roughness, specular):
    """The convolved lobes (..., 3) times Smith's G (the V = G / (4 n.l n.v) form), Schlick's
    Fresnel and n.l, all at the reflected view direction ``wi`` (Pettineo 2016)."""
    return _fresnel_mix(specular, *_glossy_parts(conv, wi, normal, view, roughness))


def _fresnel_mix(specular, base, grazing):
    """Schlick's Fresnel f0 + (1 - f0) (1 - d . h)^5 applied to shading split in its two parts:
    ``base`` (the shading without Fresnel) and ``grazing`` (with the factor (1 - d . h)^5): f0 base
    + (1 - f0) grazing. The parts do not depend on f0 (``specular``), so a texel's can be shaded
    once for every pixel that reads it (``evaluator``)."""
    f0 = jnp.asarray(specular)
    return f0 * base + (1.0 - f0) * grazing


def shade(lobes: Lobes, normal, view, roughness, specular, diffuse_albedo, irradiance):
    """Outgoing radiance (..., 3) of pixels whose texel lobes are ``lobes`` (..., N): glossy from
    the lobes (Appendix B, Eq. 15-24: NDF SG warped to an ASG, SG x ASG convolution, Smith G and
    Schlick Fresnel at the reflected direction, times n.l) plus diffuse albedo / pi x irradiance.
    ``roughness`` is GGX alpha (Mitsuba's roughconductor ``alpha``), ``specular`` the RGB
    reflectance at normal incidence.

    Numerics:
        case: shade (4 lobes as in ``lobe_radiance``; unit normals, views to 89.9 degrees from them,
          roughness in [1e-3, 1], specular and albedo in [0, 1], irradiance in [0, 1e5])
        fd: off (clamps at n . v = 1e-4 and the ASG's max(v . z, 0))
        float32: value rtol 1e-3 atol 1e-2; grad rtol 1e-3 atol 1e-2
        (the ASG's rounding, ``jprt.sphere.sg.asg_evaluate``, times amplitudes to 1e5: absolute near zero)
    """
    normal = jnp.asarray(normal)
    view = jnp.asarray(view)
    roughness = jnp.maximum(jnp.asarray(roughness), 1e-3)
    asg = sg.warp_ndf_to_asg(normal, view, roughness)
    # the pixel's warped NDF against each of its N lobes (``sg.convolve_sg_asg`` of ``asg``, with
    # the scale and sharpnesses in the fused form of ``_warped_convolution``)
    cos_v = jnp.maximum(jnp.sum(normal * view, axis=-1), 1e-4)[..., None]
    scale, sx, sy = _warped_convolution(cos_v, jnp.square(roughness)[..., None], 0.5 * lobes.sharpness)
    warped = sg.ASG(asg.x[..., None, :], asg.y[..., None, :], asg.z[..., None, :], sx, sy, 1.0)
    per_lobe = scale * sg.asg_evaluate(lobes.axes, warped)  # (..., N)
    conv = jnp.sum(per_lobe[..., None] * lobes.amplitude, axis=-2)  # (..., 3)
    return glossy_factor(conv, asg.z, normal, view, roughness, specular) + \
        jnp.asarray(diffuse_albedo) / jnp.pi * jnp.asarray(irradiance)


def ggx_ndf(cos_h, alpha):
    """GGX / Trowbridge-Reitz D(h) = alpha^2 / (pi ((n.h)^2 (alpha^2 - 1) + 1)^2), 0 for n.h <= 0.

    Numerics:
        cos_h: (32,) in [-1, 1]
        alpha: (32,) in [1e-4, 1]
        fd: off (D is 0 for n . h <= 0, a kink at 0, an end the harness draws)
        float32: value rtol 1e-5 atol 0; grad rtol 1e-4 atol 1e-30
    """
    c = jnp.maximum(cos_h, 0.0)
    return jnp.where(cos_h > 0.0, _ggx_d((1.0 - c) * (1.0 + c), jnp.square(alpha)), 0.0)


def _ggx_d(sin2, a2):
    """GGX D from sin^2 of the half-vector angle: the printed (n.h)^2 (a^2 - 1) + 1 is
    a^2 + sin^2 (1 - a^2), whose 1 - (n.h)^2 cancels to rounding (1.2e-7) near the peak, where a
    mirror-like a^2 = 1e-8 is all of it: D was wrong by orders of magnitude at alpha = 1e-4.
    Given sin^2 directly (|n x h|^2, or (1 - c)(1 + c) from an exact c), it stays at rounding,
    and so does its gradient (a separate cos^2 would carry d D / d cos^2 = -2 / (pi alpha^2)
    times the rounding of n.h's derivative at the peak: 0.5 where float64 has 0.013)."""
    d = a2 + sin2 * (1.0 - a2)
    return a2 / (jnp.pi * d * d)


def ggx_brdf_cos(normal, view, wi, roughness, specular):
    """The rendered BRDF times the cosine, f(wi, view) (n . wi), of Mitsuba's rough conductor
    with ``material="none"`` (``jprt.render.scenes`` "metal"): GGX D, separable Smith G (the
    ``_ggx_v1`` form of G / (4 n.l n.v)), Fresnel = ``specular``; 0 below the surface.

    Numerics:
        normal: (32, 3) unit
        view: (32, 3) unit within 89.9 of normal
        wi: (32, 3) unit near normal
        roughness: (32,) in [1e-4, 1]
        specular: (3,) in [0, 1]
        fd: off (0 below the surface and n . v clamped at 1e-4: kinks that the drawn ends hit)
        float32: value rtol 1e-3 atol 1e-6; grad rtol 1e-3 atol 1e-2
    """
    # clamped below only: a rounded n . v of 1 + 1e-8 is harmless, a clip at 1 would zero the
    # derivative at normal incidence (20 % off in float32 there)
    ndotl = jnp.sum(normal * wi, axis=-1)
    ndotv = jnp.maximum(jnp.sum(normal * view, axis=-1), 1e-4)
    h = wi + view
    h = h / jnp.sqrt(jnp.maximum(jnp.sum(h * h, axis=-1, keepdims=True), 1e-20))
    a2 = jnp.square(roughness)
    cos_h = jnp.sum(normal * h, axis=-1)
    nxh = jnp.cross(*jnp.broadcast_arrays(normal, h))  # sin^2 without 1 - cos^2's cancellation
    d = jnp.where(cos_h > 0.0, _ggx_d(jnp.sum(nxh * nxh, axis=-1), a2), 0.0)
    value = jnp.where(ndotl > 0.0, d * _ggx_v1_cos(a2, ndotl) * _ggx_v1(a2, ndotv), 0.0)
    f0 = jnp.asarray(specular)
    return value[..., None] * f0.reshape((1,) * (value.ndim + 1 - f0.ndim) + f0.shape)


def shade_quadrature(maps, normal, view, roughness, specular, *, sub: int = 4, key=None):
    """Glossy radiance (..., 3) of pixels from raw light-field maps (..., n, n, 3) (the captured
    texture filtered to the pixel, no lobes): sum over the map's pixels of their radiance times
    the BRDF-cosine (``ggx_brdf_cos``) integrated over the pixel by ``sub`` x ``sub`` stratified
    jittered directions (a pixel holds its directions' mean radiance). The compression-free
    upper bound of the lobes' shading.

    Numerics:
        case: shade_quadrature (2 pixels' 4 x 4 maps in [0, 1e5], unit normals, views to 89.9 degrees,
          roughness in [1e-2, 1], specular in [0, 1]; 2 x 2 jittered directions a map pixel)
        fd: off (the BRDF's clamps and the cut below the surface)
        float32: value rtol 1e-3 atol 1e-2; grad rtol 1e-3 atol 1e-2
        (a sum over 64 directions of radiance to 1e5: rounding is absolute near zero)
    """
    n = maps.shape[-2]
    key = jax.random.PRNGKey(0) if key is None else key
    grid = (jnp.arange(sub) + 0.5) / sub
    offs = jnp.stack(jnp.meshgrid(grid, grid, indexing="ij"), axis=-1).reshape(-1, 2)  # (S, 2) in (0, 1)
    # drawn in float32 whatever the precision (x64 would draw other numbers: other directions)
    jitter = jax.random.uniform(key, offs.shape, jnp.float32, minval=-0.5 / sub, maxval=0.5 / sub)
    corner = octahedral.texel_centers(n).reshape(-1, 2) - 1.0 / n  # (M, 2) lower corners
    uv = corner[:, None, :] + (offs + jitter)[None, :, :] * (2.0 / n)  # (M, S, 2)
    dirs = octahedral.decode(uv)
    sa = jnp.asarray(octahedral.texel_solid_angles(n)).reshape(-1)
    normal, view = jnp.asarray(normal), jnp.asarray(view)
    lead = normal.shape[:-1]

    def pixel(args):
        m, nrm, v, a, f0 = args
        w = ggx_brdf_cos(nrm[None, None], v[None, None], dirs, a, f0)  # (M, S, 3)
        return jnp.sum(jnp.mean(w, axis=1) * sa[:, None] * m.reshape(-1, 3), axis=0)

    maps = jnp.asarray(maps)
    flat = (maps.reshape((-1, n, n, 3)), normal.reshape(-1, 3), view.reshape(-1, 3),
            jnp.broadcast_to(jnp.maximum(jnp.asarray(roughness, maps.dtype), 1e-3), lead).reshape(-1),
            jnp.broadcast_to(jnp.asarray(specular, maps.dtype), lead + (3,)).reshape(-1, 3))
    return jax.lax.map(pixel, flat, batch_size=64).reshape(lead + (3,))


def to_storage(lobes: Lobes, dtype=jnp.float16) -> Lobes:
    """Lobes as stored at run time (the paper: 16-bit floats; 7 numbers x N lobes per texel).

    Numerics: not differentiable (quantisation to the float16 run-time storage).
    """
    return Lobes(*(jnp.asarray(a, dtype) for a in lobes))


def _cfg(config: dict | None) -> dict:
    from jprt.methods.base import resolve

    return resolve(DEFAULT_CONFIG, config)


def fit(data: SGData, config: dict | None = None, *, progress: bool | None = None):
    """Train the encoder on every captured texel (``fit_cnn``) and keep what the run time needs:
    the lobes in float16 (7 numbers per lobe: 224 bytes per texel at 16 lobes), the texels'
    irradiance and the atlas layout. Returns ``FitResult(params, info)``. ``progress``: the
    training bar (``jprt.progress``; None: its policy).

    Numerics: not differentiable (a training loop).
    """
    import time

    from jprt.methods.base import FitResult

    cfg = _cfg(config)
    t0 = time.perf_counter()
    net, lobes, losses = fit_cnn(data.images, data.below, cfg, progress=progress)
    params = storage_params(lobes, data)
    stored = sum(np.asarray(params[k]).nbytes for k in ("axes", "sharpness", "amplitude"))
    return FitResult(params, {"losses": losses, "train_s": time.perf_counter() - t0,
                              "fit_log_l2": float(losses[-1]) if len(losses) else None,
                              "bytes_per_texel": int(stored) // len(data.images)})


def storage_params(lobes: Lobes, data: SGData, dtype=jnp.float16, max_sharpness: float = 1.0e4) -> dict:
    """The evaluator's parameters for any lobes of ``data``'s texels: lobes and irradiance (when
    ``data`` has one: the environment-visibility texture has none) in ``dtype`` (float16, as the
    paper stores them), the atlas's fill index. Sharpness is clipped to ``max_sharpness`` (the
    CNN's bound; float16 overflows at 65504), which binds only for baselines fitted without it.

    Numerics: not differentiable (packing into the float16 run-time storage).
    """
    lobes = Lobes(lobes.axes, jnp.minimum(jnp.asarray(lobes.sharpness), max_sharpness), lobes.amplitude)
    stored = to_storage(lobes, dtype)
    params = {"axes": stored.axes, "sharpness": stored.sharpness, "amplitude": stored.amplitude,
              "fill_index": np.asarray(data.atlas["fill_index"], np.int32)}
    if getattr(data, "irradiance", None) is not None:
        params["irradiance"] = jnp.asarray(data.irradiance, dtype)
    return params


def lobe_table(params):
    """Every atlas pixel's texture packed plane by plane as one (R, R, 7N [+ 3]) float32 image
    (gutters filled): axis x, y, z, sharpness, amplitude r, g, b (N channels each), then the
    irradiance when ``params`` has it. One bilinear fetch reads a pixel's whole texture."""
    from jprt.methods.lightmap_lookup import atlas_image

    axes = jnp.asarray(params["axes"], jnp.float32)
    amp = jnp.asarray(params["amplitude"], jnp.float32)
    planes = [axes[..., 0], axes[..., 1], axes[..., 2], jnp.asarray(params["sharpness"], jnp.float32),
              amp[..., 0], amp[..., 1], amp[..., 2]]
    if "irradiance" in params:
        planes.append(jnp.asarray(params["irradiance"], jnp.float32))
    return atlas_image(jnp.concatenate(planes, axis=-1), jnp.asarray(params["fill_index"]))


def lobe_planes(at, n: int) -> tuple:
    """Fetched ``lobe_table`` texels (..., 7N [+ 3]) as seven (..., N) planes [and the irradiance]."""
    out = tuple(at[..., k * n:(k + 1) * n] for k in range(7))
    return out + ((at[..., 7 * n:],) if at.shape[-1] > 7 * n else ())


def lookup_lobes(params, uv) -> Lobes:
    """The lobes at atlas UVs (..., 2): each parameter bilinear between the four nearest texels
    (§6: the texture is filtered like any other), axes renormalised.

    Numerics: not differentiable (reads the float16 run-time storage; bilinear filtering in float32 by design).
    """
    return _table_lobes(lobe_table(params), uv, params["sharpness"].shape[-1])


def _table_lobes(table, uv, n: int) -> Lobes:
    """``lookup_lobes`` in a packed ``lobe_table`` of ``n`` lobes per texel."""
    from jprt.methods.lightmap_lookup import atlas_lookup

    p = lobe_planes(atlas_lookup(table, jnp.asarray(uv, jnp.float32)), n)
    axes = jnp.stack(p[0:3], axis=-1)
    axes = axes / jnp.sqrt(jnp.maximum(jnp.sum(axes * axes, axis=-1, keepdims=True), 1e-20))
    return Lobes(axes, p[3], jnp.stack(p[4:7], axis=-1))


def _warped_convolution(cos_v, r2, nu):
    """Xu et al. 2013 Eq. 12's scale pi c / sqrt((nu + lx)(nu + ly)) and convolved sharpnesses
    nu lx / (nu + lx), nu ly / (nu + ly) for the warped GGX NDF (``sg.warp_ndf_to_asg``:
    c = 1 / (pi r^2), ly = 1 / (4 r^2), lx = ly / cos_v^2), written with the roughness cancelled:
    4 cos_v / sqrt((1 + qx)(1 + qy)), nu / (1 + qx), nu / (1 + qy), qx = 4 nu cos_v^2 r^2,
    qy = 4 nu r^2. The same numbers; autodiff of the printed form cancels terms of size
    amplitude x 8 / r in d/dr (float32 kept 8 where the slope is 0, at r = 1e-3 and amplitude 1e5)."""
    qx = 4.0 * nu * cos_v * cos_v * r2
    qy = 4.0 * nu * r2
    return 4.0 * cos_v * jax.lax.rsqrt((1.0 + qx) * (1.0 + qy)), nu / (1.0 + qx), nu / (1.0 + qy)


def _glossy_planes_product(at, normal, view, roughness):
    """``shade``'s glossy part for fetched texels as planes (``lobe_planes``: seven (..., N)),
    as Fresnel's two parts (``_fresnel_mix``): the same Eq. 15-24 arithmetic (``sg.convolve_sg_asg``
    of each lobe with the warped NDF, axes renormalised after filtering), written on (..., N)
    planes; the evaluator's frame equals ``shade`` of ``lookup_lobes`` to float rounding (tested)."""
    ux, uy, uz, lam = at[:4]
    inv = jax.lax.rsqrt(jnp.maximum(ux * ux + uy * uy + uz * uz, 1e-20))
    roughness = jnp.maximum(roughness, 1e-3)
    asg = sg.warp_ndf_to_asg(normal, view, roughness)

    def dot(frame):  # lobe axes . a per-pixel frame vector: (..., N)
        return (ux * frame[..., 0:1] + uy * frame[..., 1:2] + uz * frame[..., 2:3]) * inv

    cos_v = jnp.maximum(jnp.sum(normal * view, axis=-1), 1e-4)[..., None]
    scale, sx, sy = _warped_convolution(cos_v, jnp.square(roughness)[..., None], 0.5 * lam)
    vx, vy, vz = dot(asg.x), dot(asg.y), dot(asg.z)
    per_lobe = scale * jnp.maximum(vz, 0.0) * jnp.exp(-sx * vx * vx - sy * vy * vy)
    return _glossy_parts(_amplitude_sum(per_lobe, at), asg.z, normal, view, roughness)


def _amplitude_sum(weights, at):
    """(..., 3): per channel, the sum over lobes of ``weights`` (..., N) times the lobes'
    amplitude planes (``at[4:7]`` of ``lobe_planes``)."""
    return jnp.stack([jnp.sum(weights * a, axis=-1) for a in at[4:7]], axis=-1)


def _lobe_tangents(ux, uy, uz):
    """Unit tangent and bitangent planes (three (..., N) each) about unit lobe axes given as
    planes: t = normalise(up x u) with up = z, or x where the axis is within 26 degrees of z."""
    near_z = jnp.abs(uz) >= 0.9
    tx, ty, tz = jnp.where(near_z, 0.0, -uy), jnp.where(near_z, -uz, ux), jnp.where(near_z, uy, 0.0)
    inv = jax.lax.rsqrt(jnp.maximum(tx * tx + ty * ty + tz * tz, 1e-20))
    tx, ty, tz = tx * inv, ty * inv, tz * inv
    return (tx, ty, tz), (uy * tz - uz * ty, uz * tx - ux * tz, ux * ty - uy * tx)


def _brdf_sampled(n, v, nv, m2, lobes, s: int):
    """Per lobe, the integral of exp(lambda (l . u - 1)) f(l, v) (n . l) over directions l, by
    ``s`` x ``s`` stratified directions drawn from the GGX BRDF instead of from the lobe: the
    visible normals' distribution (Heitz 2018, "Sampling the GGX Distribution of Visible
    Normals"), at (u1, u2) = ((i + 1/2) / s, (j + 1/2) / s), l the view reflected about the
    sampled normal h. With separable Smith G, f (n . l) over the density of l is F G1(l), so each
    direction carries that times the lobe's light there; the directions are the pixel's, shared by
    its lobes. Returns (plain, grazing): Fresnel's two parts as in ``_glossy_planes_sampled``,
    (..., N) each. Accurate where the lobe is smooth over the BRDF's directions (a lobe broader
    than the BRDF); a sharp lobe falls between them."""
    nx, ny, nz = n
    vx, vy, vz = v
    ux, uy, uz, lam = lobes
    # a tangent frame about the normal (Duff et al. 2017; the result does not depend on its turn)
    sign = jnp.where(nz >= 0.0, 1.0, -1.0)
    a = -1.0 / (sign + nz)
    c = nx * ny * a
    tx, ty, tz = 1.0 + sign * nx * nx * a, sign * c, -sign * nx
    bx, by, bz = c, sign + ny * ny * a, -ny
    # the view in that frame, stretched to the hemisphere configuration (alpha = 1)
    alpha = jnp.sqrt(m2)
    vt, vb = vx * tx + vy * ty + vz * tz, vx * bx + vy * by + vz * bz
    nvc = jnp.maximum(nv, 1e-4)
    sx, sy = alpha * vt, alpha * vb
    inv = jax.lax.rsqrt(sx * sx + sy * sy + nvc * nvc)
    sx, sy, sz = sx * inv, sy * inv, nvc * inv
    lensq = sx * sx + sy * sy
    far = lensq > 1e-12
    il = jax.lax.rsqrt(jnp.where(far, lensq, 1.0))
    t1x, t1y = jnp.where(far, -sy * il, 1.0), jnp.where(far, sx * il, 0.0)  # T1 = (t1x, t1y, 0)
    t2x, t2y, t2z = -sz * t1y, sz * t1x, sx * t1y - sy * t1x  # T2 = S x T1
    half = 0.5 * (1.0 + sz)
    plain, grazing = 0.0, 0.0
    for i in range(s):
        r = math.sqrt((i + 0.5) / s)
        for j in range(s):
            phi = 2.0 * math.pi * (j + 0.5) / s
            p1 = r * math.cos(phi)
            p2 = (1.0 - half) * math.sqrt(max(1.0 - p1 * p1, 0.0)) + half * (r * math.sin(phi))
            p3 = jnp.sqrt(jnp.maximum(1.0 - p1 * p1 - p2 * p2, 0.0))
            # the visible normal in the stretched frame, then back to the ellipsoid's
            mx, my, mz = p1 * t1x + p2 * t2x + p3 * sx, p1 * t1y + p2 * t2y + p3 * sy, p2 * t2z + p3 * sz
            mx, my, mz = alpha * mx, alpha * my, jnp.maximum(mz, 0.0)
            im = jax.lax.rsqrt(jnp.maximum(mx * mx + my * my + mz * mz, 1e-20))
            mx, my, mz = mx * im, my * im, mz * im
            vh = vt * mx + vb * my + nvc * mz
            nl = 2.0 * vh * mz - nvc  # n . l for l = 2 (v . h) h - v
            hx, hy, hz = mx * tx + my * bx + mz * nx, mx * ty + my * by + mz * ny, mx * tz + my * bz + mz * nz
            lx, ly, lz = 2.0 * vh * hx - vx, 2.0 * vh * hy - vy, 2.0 * vh * hz - vz
            # unit again: vh and nl use the clamped n . v, the view itself may face away
            il = jax.lax.rsqrt(jnp.maximum(lx * lx + ly * ly + lz * lz, 1e-20))
            lx, ly, lz = lx * il, ly * il, lz * il
            w = 2.0 * _ggx_v1_cos(m2, nl)  # G1(l), 0 below the surface
            # l . u - 1 as -|l - u|^2 / 2: no cancellation near the lobe's axis (``lobe_radiance``)
            cos1 = -0.5 * (jnp.square(lx - ux) + jnp.square(ly - uy) + jnp.square(lz - uz))
            light = jnp.exp(lam * cos1) * w
            fw = 1.0 - jnp.clip(vh, 0.0, 1.0)
            fw2 = fw * fw
            plain = plain + light
            grazing = grazing + light * (fw2 * fw2 * fw)
    return plain / (s * s), grazing / (s * s)


def _glossy_planes_sampled(at, normal, view, roughness, samples: int, brdf_sampled: bool = True,
                           broad_bound: float = 1.0):
    """``shade_sampled``'s glossy part for fetched texels as planes (``lobe_planes``), as
    Fresnel's two parts (``_fresnel_mix``), the layout of ``_glossy_planes_product``."""
    ux, uy, uz, lam = at[:4]
    inv = jax.lax.rsqrt(jnp.maximum(ux * ux + uy * uy + uz * uz, 1e-20))
    ux, uy, uz = ux * inv, uy * inv, uz * inv
    (tx, ty, tz), (bx, by, bz) = _lobe_tangents(ux, uy, uz)
    s = int(samples)
    lam_drawn = jnp.maximum(lam, 1e-6)  # the lobe-drawn directions' sharpness, finite at lambda 0
    nx, ny, nz = (normal[..., k:k + 1] for k in range(3))
    vx, vy, vz = (view[..., k:k + 1] for k in range(3))
    nv = nx * vx + ny * vy + nz * vz
    ndotv = jnp.maximum(nv, 1e-4)
    a2 = jnp.square(jnp.maximum(roughness, 1e-3))[..., None] + 1.0 / (lam_drawn * (s * s))  # widened per lobe
    tail = 1.0 - jnp.exp(-2.0 * lam_drawn)  # the SG's mass in the cosine's range
    gv = _ggx_v1(a2, ndotv)
    # a direction d = cx t + cy b + cos u enters only through n . d and v . d (both linear in its
    # frame coordinates), and h = (d + v) / |d + v| with |d + v|^2 = 2 + 2 v . d
    nt, nb, nu = nx * tx + ny * ty + nz * tz, nx * bx + ny * by + nz * bz, nx * ux + ny * uy + nz * uz
    vt, vb, vu = vx * tx + vy * ty + vz * tz, vx * bx + vy * by + vz * bz, vx * ux + vy * uy + vz * uz
    plain, grazing = 0.0, 0.0
    for i in range(s):
        # 1 - cos of the stratum's direction, from the SG's inverse CDF (no 1 - cos cancellation)
        t = -jnp.log1p(-((i + 0.5) / s) * tail) / lam_drawn
        cos = 1.0 - t
        sin = jnp.sqrt(jnp.maximum(t * (2.0 - t), 0.0))
        for j in range(s):
            phi = 2.0 * math.pi * (j + 0.5) / s
            cx, cy = sin * math.cos(phi), sin * math.sin(phi)
            ndotl = cx * nt + cy * nb + cos * nu
            vdotl = cx * vt + cy * vb + cos * vu
            hinv = jax.lax.rsqrt(jnp.maximum(2.0 + 2.0 * vdotl, 1e-20))
            c = (ndotl + nv) * hinv  # n . h
            dd = a2 + jnp.maximum((1.0 - c) * (1.0 + c), 0.0) * (1.0 - a2)  # GGX D = a2 / (pi dd^2)
            lit = (c > 0.0) & (ndotl > 0.0)
            safe = jnp.where(lit, ndotl, 1.0)
            # D x n.l x _ggx_v1(n.l) in one division: n.l / (n.l + sqrt(a2 + (1 - a2) n.l^2))
            value = jnp.where(lit, a2 * safe / (math.pi * dd * dd * (safe + jnp.sqrt(a2 + (1.0 - a2) * safe * safe))),
                              0.0) * gv
            w = 1.0 - jnp.clip((1.0 + vdotl) * hinv, 0.0, 1.0)  # 1 - d . h
            w2 = w * w
            plain = plain + value
            grazing = grazing + value * (w2 * w2 * w)
    energy = (2.0 * math.pi / (s * s)) * tail / lam_drawn  # each direction's share of the SG's integral
    plain, grazing = plain * energy, grazing * energy
    if brdf_sampled:
        # a lobe broader than the BRDF: its light is smooth over the BRDF's directions, so those
        # are drawn instead (``_brdf_sampled``); broader: sharpness lambda below 2 / alpha^2, the
        # sharpness of the SG that stands for the GGX NDF (Appendix B, Eq. 17; ``shade_sampled``
        # says how that bound was chosen)
        m2 = jnp.square(jnp.maximum(roughness, 1e-3))[..., None]
        by_brdf = _brdf_sampled((nx, ny, nz), (vx, vy, vz), nv, m2, (ux, uy, uz, lam), s)
        broad = lam * (0.5 * m2) < broad_bound
        plain, grazing = jnp.where(broad, by_brdf[0], plain), jnp.where(broad, by_brdf[1], grazing)
    return _amplitude_sum(plain, at), _amplitude_sum(grazing, at)


def shade_sampled(lobes: Lobes, normal, view, roughness, specular, diffuse_albedo, irradiance, samples: int = 3,
                  brdf_sampled: bool = True, broad_bound: float = 1.0):
    """Outgoing radiance (..., 3) like ``shade``, with each lobe integrated against the GGX BRDF
    by ``samples`` x ``samples`` stratified directions drawn from the lobe itself instead of
    Appendix B's SG x ASG product.

    Each lobe's light, mu exp(lambda (w . u - 1)), has the integral 2 pi mu (1 - e^(-2 lambda)) /
    lambda; its directions are drawn by the SG's inverse CDF, 1 - cos theta = -log(1 - x (1 -
    e^(-2 lambda))) / lambda at x = (i + 1/2) / samples, and phi = 2 pi (j + 1/2) / samples, each
    carrying an equal share of the integral through f(w, v) (n . w): GGX D, separable Smith G and
    Schlick's Fresnel with f0 = ``specular``, the terms of ``shade``. Each direction stands for a
    stratum of the lobe, angular variance about 1 / (lambda samples^2) per axis; a light spread of
    variance s^2 spreads the half vector by s^2 / 4, which GGX's peak (variance alpha^2 / 4) absorbs
    as alpha^2 + 1 / (lambda samples^2): that widened alpha is used (derived, not fitted). At 3 x 3
    it reaches the lobes' own quadrature bound on the benchmark's receivers (docs/methods/
    sg_lightfield.md); the cost is samples^2 BRDF evaluations per lobe and pixel.

    That holds for a lobe sharper than the BRDF. A broad lobe's strata are wide, and their
    centres miss a glossy BRDF's peak: against a brute-force integral (400k directions) of one
    lobe (lambda 0.5-300, on and off the mirror direction) through GGX (alpha 0.05-0.6, Schlick
    f0 0.04, views 0-84 degrees from the normal), the lobe-drawn directions alone give 9-60 % of
    a broad lobe's reflection at grazing views (``python benchmarks/sg_shading_grid.py``). With
    ``brdf_sampled`` (default) a lobe of sharpness lambda < 2 / alpha^2 (that of the SG standing
    for the GGX NDF, Appendix B's Eq. 17) is integrated instead at ``samples`` x ``samples``
    directions drawn from the BRDF (``_brdf_sampled``, its visible normals): on that grid the
    median relative error 0.18 -> 0.035, the 90th percentile 0.71 -> 0.14, the summed absolute
    error over the summed integral 0.59 -> 0.044 (f0 0.9: 0.32 -> 0.035). The bound was chosen on
    that grid, no scene: lambda alpha^2 / 2 below ``broad_bound`` = 1/4, 1, 2 or 4 gave 0.089, 0.044, 0.043, 0.042
    summed and 0.16, 0.14, 0.17, 0.23 at the 90th percentile; 2 x 2 BRDF directions instead of
    3 x 3 doubled the error (0.098). The cost: both integrals for every lobe, about twice the
    shading's time.

    Numerics:
        case: shade_sampled (4 lobes as in ``lobe_radiance``; unit normals, views to 89.9 degrees
          from them, roughness in [1e-3, 1], specular and albedo in [0, 1], irradiance in [0, 1e5])
        fd: off (clamps at n . v = 1e-4, n . l = 0 and n . h = 0; the switch to BRDF-drawn directions at
          lambda alpha^2 / 2 = 1 and their frame's turn with the view's azimuth at normal incidence)
        float32: value rtol 1e-3 atol 1e-2; grad rtol 1e-3 atol 1e-2
        (sums of samples^2 x 4 terms with amplitudes to 1e5: absolute rounding near zero)
    """
    planes = (lobes.axes[..., 0], lobes.axes[..., 1], lobes.axes[..., 2], lobes.sharpness,
              lobes.amplitude[..., 0], lobes.amplitude[..., 1], lobes.amplitude[..., 2], jnp.asarray(irradiance))
    parts = _glossy_planes_sampled(planes, jnp.asarray(normal), jnp.asarray(view), jnp.asarray(roughness), samples,
                                   brdf_sampled, broad_bound)
    return _fresnel_mix(specular, *parts) + jnp.asarray(diffuse_albedo) / jnp.pi * planes[7]


#: Pixels (or texels) per tile of the evaluator's loop (see ``evaluator``).
TILE = 4096

#: Where ``evaluator`` shades the lobes (``shading.space``).
SHADING_SPACES = ("auto", "pixel", "texel")


def map_tiles(fn, fields, tile: int):
    """``fn`` over the pixels of image-shaped ``fields`` (each (..., C) or (...) with the leading
    shape of the first, the uv), ``tile`` pixels at a time (a ``lax.map``): each field flattened
    to pixels, zero-padded to whole tiles (a zero normal shades to a finite value, discarded),
    ``fn(*tile_fields) -> (tile, C)``; returns (..., C). A tile's working set stays in cache,
    where XLA would otherwise stream the whole frame through each fusion (the evaluators' timings).

    Numerics: not differentiable (the run-time tiling; the arithmetic is ``fn``'s).
    """
    shape = jnp.shape(fields[0])[:-1]
    count = math.prod(shape)
    tiles, size = max(1, -(-count // int(tile))), min(int(tile), count)

    def flat(a):
        a = jnp.asarray(a, jnp.float32)
        a = a.reshape((count,) + a.shape[len(shape):])
        if tiles * size > count:
            a = jnp.concatenate([a, jnp.zeros((tiles * size - count,) + a.shape[1:], a.dtype)])
        return a.reshape((tiles, size) + a.shape[1:])

    out = jax.lax.map(lambda t: fn(*t), tuple(flat(a) for a in fields))
    return out.reshape((tiles * size, -1))[:count].reshape(shape + (out.shape[-1],))


def evaluator(params, config: dict | None = None, *, tile: int = TILE):
    """``evaluate(inputs, lighting) -> (H, W, 3)``: a G-buffer with atlas ``uv`` (``jprt.render.
    lightmap.atlas_gbuffer``) shaded from its texels' lobes (``shade_sampled`` at ``shading.samples``
    directions per lobe and side; ``shade``, Appendix B's product, where that is 0); ``lighting`` is a
    ``jprt.inputs.LightScale`` (or its (3,) array): the baked lighting scaled per channel (light
    transport is linear in the emitters' power: the only relighting a baked light field allows).
    Invalid pixels are 0.

    ``shading.space`` says where the lobes are shaded:

    * "pixel" (§6 of the paper): each pixel's lobes bilinear between its four texels (every
      parameter filtered, axes renormalised), shaded at the pixel's normal, view and roughness. The
      texture (lobes and irradiance of every atlas pixel, float32 from the float16 storage) is
      packed once here, as a renderer uploads its textures once. Pixels are shaded in tiles of
      ``tile`` (a ``lax.map``, one program): one bilinear fetch of the packed texture per pixel,
      then the shading on (..., N) planes: on a CPU several times faster than the same program
      untiled or ``shade`` on (..., N, 3) vectors (XLA fuses the fetch into every use of its
      result and streams the whole frame through each fusion; a tile stays in cache).
    * "texel" (texture-space shading, as engines do for costly shading: Baker 2016, "Object Space
      Lighting"; Hillesland and Yang 2016, "Texel Shading"): each texel's own lobes are shaded
      once, at the mean normal, view and roughness of the valid pixels that read it (weighted by
      their bilinear weights, ``lightmap_lookup.texel_taps``), as Fresnel's two parts, which do not
      depend on f0 (``_fresnel_mix``); each pixel then reads the shaded texels bilinearly and
      applies its own specular and diffuse albedo. The work is per texel, not per pixel. It
      differs from "pixel" in two ways: the light between texels is the bilinear mix of their
      lobes' shading, not the shading of bilinearly mixed lobes, and the view and normal are
      constant over a texel's footprint. At texel centres the two are equal (tested). A G-buffer
      whose pixels see one texel from several directions at once (the self-check's) needs "pixel".
    * "auto" (the default): "texel" where the atlas has no more texels than the frame has pixels,
      "pixel" otherwise (the shading's work is then the smaller of the two).

    Numerics: not differentiable (builds the float32 run-time program; ``shade_sampled`` and ``shade`` are covered).
    """
    from jprt.methods.lightmap_lookup import atlas_lookup, texel_taps

    shading = _cfg(config)["shading"]
    samples, brdf_sampling, broad_bound = int(shading["samples"]), bool(shading["brdf_sampling"]), \
        float(shading["broad_bound"])
    space = str(shading["space"])
    n = params["sharpness"].shape[-1]
    if samples < 0:
        raise ValueError(f"shading.samples must be >= 0 (0: Appendix B's product), got {samples}")
    if space not in SHADING_SPACES:
        raise ValueError(f"shading.space must be one of {', '.join(SHADING_SPACES)}, got {space!r}")
    tile = int(tile)
    fill = jnp.asarray(params["fill_index"], jnp.int32)
    axes = jnp.asarray(params["axes"], jnp.float32)
    amp = jnp.asarray(params["amplitude"], jnp.float32)
    texels = (axes[..., 0], axes[..., 1], axes[..., 2], jnp.asarray(params["sharpness"], jnp.float32),
              amp[..., 0], amp[..., 1], amp[..., 2])
    count = texels[0].shape[0]
    irradiance = jnp.asarray(params["irradiance"], jnp.float32)
    # the packed atlas image of "pixel" (built here, outside any caller's trace)
    table = None if space == "texel" else lobe_table(params)

    def glossy(at, normal, view, roughness):
        if samples:
            return _glossy_planes_sampled(at, normal, view, roughness, samples, brdf_sampling, broad_bound)
        return _glossy_planes_product(at, normal, view, roughness)

    @jax.jit
    def _pixels(table, inputs, scale):
        def shade_tile(uv, normal, view, roughness, specular, diffuse):
            at = lobe_planes(atlas_lookup(table, uv), n)
            return _fresnel_mix(specular, *glossy(at, normal, view, roughness)) + diffuse / jnp.pi * at[7]

        out = map_tiles(shade_tile, (inputs.uv, inputs.normal, inputs.view, inputs.roughness, inputs.specular_albedo,
                                     inputs.diffuse_albedo), tile)
        out = out * jnp.asarray(scale, jnp.float32).reshape((1,) * (out.ndim - 1) + (3,))
        return jnp.where(jnp.asarray(inputs.valid, bool)[..., None], out, 0.0)

    @jax.jit
    def _texels(texels, irradiance, fill, inputs, scale):
        valid = jnp.asarray(inputs.valid, bool)
        # an invalid pixel's fields may hold anything (NaN included): zeroed, not multiplied by 0
        index, weight = texel_taps(fill, jnp.where(valid[..., None], jnp.asarray(inputs.uv, jnp.float32), 0.0))
        weight = jnp.where(valid[..., None], weight, 0.0)
        # each texel's footprint: the weighted sums of its pixels' normal, view and roughness
        attrs = jnp.concatenate([jnp.asarray(inputs.normal, jnp.float32), jnp.asarray(inputs.view, jnp.float32),
                                 jnp.asarray(inputs.roughness, jnp.float32)[..., None],
                                 jnp.ones(valid.shape + (1,), jnp.float32)], axis=-1)
        attrs = jnp.where(valid[..., None], attrs, 0.0)
        sums = jnp.zeros((count, 8), jnp.float32).at[index.reshape(-1)].add(
            (weight[..., None] * attrs[..., None, :]).reshape(-1, 8))
        seen = sums[:, 7] > 0.0  # a texel no pixel reads is shaded at a placeholder and read with weight 0

        def unit(v):
            norm = jnp.sqrt(jnp.sum(v * v, axis=-1, keepdims=True))
            ok = seen[:, None] & (norm > 0.0)
            return jnp.where(ok, v / jnp.where(ok, norm, 1.0), jnp.asarray([0.0, 0.0, 1.0], jnp.float32))

        roughness = jnp.where(seen, sums[:, 6] / jnp.where(seen, sums[:, 7], 1.0), 1.0)

        def shade_tile(*fields):
            return jnp.concatenate(glossy(fields[:7], *fields[7:]), axis=-1)

        parts = map_tiles(shade_tile, (*texels, unit(sums[:, 0:3]), unit(sums[:, 3:6]), roughness), tile)
        table = jnp.concatenate([parts, irradiance], axis=-1)  # (T, 9): base, grazing, irradiance
        read = sum(weight[..., k:k + 1] * table[index[..., k]] for k in range(4))
        out = _fresnel_mix(jnp.asarray(inputs.specular_albedo, jnp.float32), read[..., 0:3], read[..., 3:6]) + \
            jnp.asarray(inputs.diffuse_albedo, jnp.float32) / jnp.pi * read[..., 6:9]
        out = out * jnp.asarray(scale, jnp.float32).reshape((1,) * (out.ndim - 1) + (3,))
        return jnp.where(valid[..., None], out, 0.0)

    def evaluate(inputs, lighting):
        scale = lighting.scale if hasattr(lighting, "scale") else lighting
        pixels = math.prod(jnp.shape(inputs.uv)[:-1])
        if space == "texel" or (space == "auto" and count <= pixels):
            return _texels(texels, irradiance, fill, inputs, scale)
        return _pixels(table, inputs, scale)

    return evaluate


def example(data: SGData, config: dict | None = None):
    """The atlas seen head-on: every texel shaded along its own normal (roughness 0.3, specular
    0.9), at the bake's lighting (scale 1).

    Numerics: not differentiable (a held-out input and lighting from a dataset).
    """
    from jprt.methods.lightmap_lookup import atlas_inputs

    _cfg(config)
    r = int(data.atlas["resolution"])
    g = atlas_inputs(r, data.atlas["texel_index"])
    normal = np.zeros((r * r, 3), np.float32)
    normal[:, 2] = 1.0
    normal[np.asarray(data.atlas["texel_index"])] = np.asarray(data.normal, np.float32)
    normal = normal.reshape(r, r, 3)
    g = g._replace(normal=normal, view=normal, reflected=normal, roughness=np.full((r, r), 0.3, np.float32),
                   specular_albedo=np.full((r, r, 3), 0.9, np.float32))
    return g, LightScale(np.ones(3, np.float32))
