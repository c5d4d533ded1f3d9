"""Neural-wavelet PRT (Raghavan et al. 2023, "Neural Free-Viewpoint Relighting for Glossy
Indirect Illumination"): environment-map relighting of glossy indirect light from any view.

The indirect radiance of a pixel is a dot product in the non-standard Haar basis of a cube map
(``jprt.sphere.haar``):

    B(x, w_o) = sum_k L_k T_k(x, w_o)                                          (Eq. 3)

with L_k the wavelet coefficients of the environment (taken *without* solid-angle
premultiplication, §5: the network learns those factors) and the transport coefficients

    T_k(x, w_o) = f(h_k(x), SH4(w_r), n, rho; Theta)                            (Eq. 4)

predicted by a 2 x 128 ReLU MLP f from the CP-factored feature field

    h_k(x) = sum_m S_m[x] W_m[k] U_m                                            (Eq. 6-7)

(``jprt.nn.factor``: hash grid S over space, cube-map grid W over wavelet positions, matrix U),
the SH encoding of the reflected direction w_r (``jprt.nn.encoding.sh4``), the normal and the
GGX parameters rho = (k_d, k_s, remapped roughness log(25 sigma + 1) / log 26).

* Training (§5): each step picks a training environment, takes 300 wavelets (half the largest
  |L_k|, half uniformly among the rest), samples pixels from the images lit by that environment
  in four equal parts (uniform, view variance, high frequency, k_s (1 - sigma)), predicts
  B = sum_k L_k T_k and minimises the sign-extended mu-law tonemapped L2 loss (Eq. 8) with Adam
  (``jprt.solve.adam``, bit-identical resume). The objective is the paper's (every selected
  wavelet weight 1); ``train.objective = "unbiased"`` weights the uniform half by its inverse
  inclusion probability (as printed, the 300 wavelets' sum is fitted to an image lit by all of
  them, so T_k learns to carry the unselected wavelets' share) and ``"exact"`` sums every
  wavelet (how each scored: docs/methods/wavelet_prt.md).
  Departures, each a config switch: B is clipped at 0 in the image and the loss
  (``model.nonnegative``); each step jitters exposure and white balance of lighting and target
  alike (exact: B is linear in each colour channel of the lighting); the model is the moving
  average of the Adam iterates (``train.ema``), which moves less between two machines' runs;
  ``train.fine_penalty`` > 0 adds a penalty on the light the finest Haar levels carry (off by
  default); ``model.lighting_levels`` D reads only the scaling wavelets and the D coarsest detail
  levels of every lighting, in training and at run time (the cube map box-filtered to face 2^D;
  off, every level, by default).
* Rendering (Algorithm 1): the K largest area-weighted wavelets of the new lighting, the
  transport coefficients of all pixels in one jit-compiled pass over pixel chunks (memory bounded
  by the chunk), then the dot product; final = direct (Mitsuba) + indirect.
* Table 6's baseline (``model.spatial = "vertex"``): S_m[x] from learned features at the vertices
  of the scene mesh subdivided to a target edge length, interpolated and passed through softplus
  (``add_vertex_interpolation`` supplies the per-pixel vertices and weights).
* Ground truth for the wavelet half (``transport_check``): Mitsuba's environment-to-pixel
  transport (``jprt.render.transport``) projected onto the Haar basis and relit with the top K
  wavelets, against Mitsuba's render of the same environment.

Images are relit with environment maps that are constant over the texels of a (6, n, n) cube map
(the lighting the method represents exactly); the Mitsuba references are rendered with that
same piecewise-constant map, so the reported errors are the method's, not a resampling's.
"""

from __future__ import annotations

import math
import time
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jprt.hashing import stable_hash
from jprt.inputs import CubeMap
from jprt.methods.base import FitResult, resolve
from jprt.nn import encoding
from jprt.nn.factor import factor_field
from jprt.nn.mlp import mlp
from jprt.solve import losses
from jprt.sphere import haar

__all__ = [
    "DEFAULT_CONFIG",
    "CHUNK_ROWS",
    "auto_chunk",
    "GBUFFER_FIELDS",
    "VERTEX_FIELDS",
    "WaveletData",
    "pixel_features",
    "Model",
    "model",
    "lighting_mask",
    "training_wavelets",
    "indirect_output",
    "indirect_loss",
    "select_wavelets",
    "render_pixels",
    "exact_transport_fn",
    "transport_check",
    "run_key",
    "fit",
    "evaluator",
    "frame_flops",
    "example",
    "indirect_baseline_scale",
    "model_bytes",
]

DEFAULT_CONFIG = {
    # the glossy Cornell box opened at the top so the environment lights it from above and the front
    "scene": {"name": "glossy_cornell", "open_top": True, "floor_roughness": 0.1, "sphere_roughness": 0.05},
    "envmaps": {
        "folder": "",  # "" -> ../shared/assets/envmaps
        "train": [],  # file stems; [] -> every map in the folder that is not held out
        # held out by category (never in training, in any rotation or jitter); the first two are the
        # benchmark's original pair
        "held_out": ["st_fagans_interior_1k", "venice_sunset_1k", "lebombo_1k", "potsdamer_platz_1k",
                     "rooitou_park_1k", "kiara_1_dawn_1k"],
        # [stem, category] pairs (a list, so a config may name maps of its own); sorted by looking at
        # the maps: lebombo is a room with windows, potsdamer_platz an overcast square, rooitou_park a
        # clear sky whose sun holds 69 % of the energy in 0.1 % of the texels, kiara_1_dawn a sun on
        # the horizon
        "categories": [["st_fagans_interior_1k", "indoor"], ["lebombo_1k", "indoor"],
                       ["potsdamer_platz_1k", "overcast"], ["rooitou_park_1k", "clear sky with sun"],
                       ["venice_sunset_1k", "sunset"], ["kiara_1_dawn_1k", "sunset"],
                       ["adams_place_bridge_1k", "overcast"], ["dikhololo_night_1k", "dusk"],
                       ["empty_warehouse_01_1k", "indoor"], ["forest_slope_1k", "clear sky with sun"],
                       ["immenstadter_horn_1k", "overcast"], ["studio_small_03_1k", "indoor"]],
        # "per_image": every training image its own lighting (a training map at a uniform rotation,
        # mirrored half the time, or a procedural sky); "shared": maps x rotations_deg (§5)
        "lighting": "per_image",
        "mirror": True,  # "per_image": each file map mirrored left-right with probability 1/2
        "procedural_fraction": 0.2,  # "per_image": the fraction of training lightings that are procedural skies
        # "per_image" only: the fraction of the file maps turned by a uniformly random 3D rotation
        # instead of about +Y. Turned about +Y only, every training lighting is bright above and dark
        # below in much the same ratio, so the light of the sky and of the ground are hard to tell
        # apart; 0 (no tilted maps) scored better on a held-out sun in validation (CHANGELOG.md)
        "tilt": 0.0,
        # the procedural lightings: "lobes" (synthetic_environments: a sky and one or two broad lobes)
        # or "sun" (sun_skies: a clear sky whose sun holds 20-80 % of the energy in one texel)
        "procedural": "lobes",
        "rotations_deg": [0.0, 120.0, 240.0],  # "shared": §5's each map and its 120 / 240 degree rotations
        "synthetic": 0,  # > 0: that many seeded procedural maps instead of files (tests)
        "face_size": 16,  # cube-map face size n (paper: 64)
        "normalise": True,  # scale every map to mean radiance 1 (equal exposure across maps)
    },
    "cameras": {
        "width": 64,  # image size in pixels
        "height": 64,
        "fov": 39.3077,  # field of view in degrees (with target set; else the scene's)
        # the orbits' centre; None: views from the scene instead (a file's own camera and field of
        # view, jittered in a box about it: jprt.render.sampling.scene_regions), for interiors
        "target": [0.0, -0.1, 0.0],
        # spherical trajectory: a spiral of n training views over a cap of the sphere of `radius`
        # (world units) about the target (azimuth / elevation ranges, degrees)
        "sphere": {"n": 45, "radius": 3.9, "azimuth": [-35.0, 35.0], "elevation": [-5.0, 45.0]},
        # helix for occluded regions: n views sweeping the azimuth range `turns` times while rising
        "helix": {"n": 30, "radius": 3.0, "azimuth": [-30.0, 30.0], "elevation": [0.0, 40.0], "turns": 2.0},
        "near": 6,  # held-out views on the training trajectories
        "far": 6,  # held-out views away from them, drawn in the ranges below
        "far_radius": [2.4, 2.8],  # world units from the target
        "far_azimuth": [-45.0, 45.0],  # degrees
        "far_elevation": [-10.0, 55.0],  # degrees
    },
    "data": {
        "spp": 128,  # path-traced samples per pixel of a training image
        "test_spp": 1024,  # samples per pixel of a held-out reference
        "envs_per_view": 2,  # training lightings each training camera is rendered under
        "seed": 0,  # seed of the cameras, lightings and renders
        "max_depth": -1,  # Mitsuba's path depth of the full render (-1: unbounded)
        # "all" -> every near / far view under every held-out map; "cycle" -> view i under map i
        "test_pairs": "all",
        # "image" renders each pixel over its footprint (Mitsuba's box-filtered image, as the
        # paper's training images); "centre" traces the pixel-centre rays the G-buffer reads
        # (jprt.render.images.centre_rays), so a target is the radiance of the one point the model sees
        "rays": "image",
    },
    "model": {
        # the hash grid S of Eq. 6: M = n_levels x features_per_level features per point (paper: 64)
        "n_levels": 8,
        "features_per_level": 2,
        "log2_table_size": 14,  # log2 of the hash table's entries per level (paper: 19)
        "base_resolution": 4,  # the coarsest level's grid cells per axis
        "per_level_scale": 1.6,  # each level's resolution over the previous one's
        "n_features": 32,  # L, the width of h_k (paper: 64)
        "hidden": 128,  # f: the width of its ReLU hidden layers (paper: 128)
        "layers": 2,  # f: its number of hidden layers (paper: 2)
        "reflection": "sh4",  # "sh4" | "raw" (w_r as 3 numbers) | "none"   (Table 4)
        # S_m[x]: "hashgrid" (the paper), or "vertex": learned features at the vertices of the scene
        # mesh subdivided to edges <= vertex_edge, interpolated, softplus (Table 6's baseline)
        "spatial": "hashgrid",
        "vertex_edge": 0.1,  # "vertex": the longest mesh edge after subdivision (world units)
        # B = max(sum_k L_k T_k, 0) in the image and in the loss (indirect radiance is never negative);
        # the loss also penalises the clipped negative part, so a negative B still gets a gradient
        "nonnegative": True,
        # W[k] ~ N(0, w_init^2) at the start (standard deviation): a row whose wavelet no training
        # lighting excites keeps about its initial value, so it starts near zero (see null_transport)
        "w_init": 0.01,
        # what a wavelet whose features are zero (h_k = 0) transports: "free" is Eq. 4 as written,
        # f(0, pixel) (the same for every such wavelet, whatever training left it); "zero" subtracts
        # it, T_k = f(h_k, pixel) - f(0, pixel), so a wavelet no training lighting excited carries
        # nearly nothing instead of the pixel's average transport times L_k. Under a sun the top-K
        # Haar details at the sun all have the sun's sign, and with "free" their sum lit the scene
        # several times too bright (measured: docs/methods/wavelet_prt.md)
        "null_transport": "zero",
        # the Haar detail levels of the lighting the model reads, coarsest first; None: every level
        # (the paper). An integer D keeps the scaling wavelets and the D coarsest detail levels (each
        # face's top-left 2^D x 2^D block of coefficients) and drops the finer ones at training and at
        # run time: the lighting is then exactly the cube map box-filtered to face 2^D (energy kept),
        # the targets stay rendered under the full map. Indirect light is smooth in the light's
        # direction, and 6 x 4^D transport functions are learnt instead of 6 n^2 from the same
        # training lightings (``lighting_mask``)
        "lighting_levels": None,
    },
    "train": {
        "steps": 1500,  # Adam steps
        "learning_rate": 1e-2,  # Adam's initial learning rate, decayed exponentially over the steps
        "final_lr_fraction": 0.1,  # the last step's learning rate over the first's
        "pixels": 256,  # training pixels per step (paper: 2048; fewer keep a CPU step short)
        "wavelets": 300,  # wavelets per step (§5: half the largest |L_k|, half uniform among the rest)
        "seed": 0,  # seed of the initial parameters and of every step's draws
        "checkpoint_every": 250,  # steps between checkpoints (fit's checkpoint_path)
        "log_every": 50,  # steps between loss log lines
        "mu": 10.0,  # mu-law constant (eps = 1)
        # "unbiased": the uniformly drawn half of the wavelets weighted by (N - n/2) / (n - n/2), so the
        # step's sum is an unbiased estimate of sum over all N wavelets and T_k is not rewarded for
        # carrying the share of wavelets it was not shown; "paper": every selected wavelet weight 1 (§5);
        # "exact": every wavelet of the lighting (B itself, no estimate), on pixels * wavelets / N
        # pixels per step (the same number of (pixel, wavelet) products; at least 4). "paper" scored
        # best on the held-out maps (docs/methods/wavelet_prt.md)
        "objective": "paper",
        # per-step lighting jitter, exact by linearity (lighting and target scaled per channel alike):
        # exposure 2^U(-s, s) with s = exposure_stops (stops), and a white balance exp(N(0, wb^2))
        # per channel (mean log 0) with wb = white_balance
        "exposure_stops": 1.0,
        "white_balance": 0.2,
        # > 0: the model is the exponential moving average of the parameters with this decay
        # (``jprt.solve.adam``; 0.99: about the last 100 steps), not the last Adam iterate (0); two
        # trainings on different machine code agree more closely on it (docs/methods/wavelet_prt.md)
        "ema": 0.99,
        # > 0: a penalty on the light the finest ``fine_levels`` Haar detail levels carry, added to
        # the loss: fine_penalty x sum over pixels and selected fine wavelets of |L_k T_k|^2 over the
        # sum of |target|^2 (dimensionless, so exposure jitter leaves it alone): against a fit that
        # puts more light in the finest levels than Mitsuba's transport has (CHANGELOG.md);
        # 0: off (the paper's loss, Eq. 8)
        "fine_penalty": 0.0,
        "fine_levels": 2,  # how many of the finest Haar detail levels fine_penalty counts
    },
    "render": {
        # K: the largest area-weighted wavelets of a lighting the evaluator sums (Algorithm 1); 32, not
        # the paper's 64 (its faces are 16x larger): chosen and validated by measurement (docs/methods/wavelet_prt.md)
        "k": 32,
        # pixels per step of the render loop; 0 -> ``auto_chunk``: 8192 // K on a CPU, about 8192
        # (pixel, wavelet) rows per product, which keeps a 2 x 128 MLP's activations in cache;
        # 2^22 // K on a GPU (each the fastest measured on its kind of device, ``CHUNK_ROWS``)
        "chunk": 0,
    },
}

#: G-buffer arrays the model reads, with their trailing shapes.
GBUFFER_FIELDS = {"position": (3,), "normal": (3,), "reflected": (3,), "diffuse_albedo": (3,),
                  "specular_albedo": (3,), "roughness": (), "valid": ()}
#: Extra per-pixel arrays of the per-vertex variant (``add_vertex_interpolation``).
VERTEX_FIELDS = {"vertex_index": (4,), "vertex_weight": (4,)}


def _cfg(config: dict | None) -> dict:
    """``DEFAULT_CONFIG`` merged strictly with ``config`` (an unknown key raises ConfigError)."""
    return resolve(DEFAULT_CONFIG, config)


# --------------------------------------------------------------------------------------------
# Dataset (§5)
# --------------------------------------------------------------------------------------------


class WaveletData(NamedTuple):
    """Rendered training and test data (NumPy).

    Fields:
      train:      dict of (E, V, H, W, ...) arrays: the GBUFFER_FIELDS, "direct", "indirect";
                  images grouped by their training environment (V images each).
      importance: (E, 4, V * H * W) pixel-sampling distributions (``importance_maps``).
      envs:       (E, 6, n, n, 3) training environments (cube maps).
      tests:      {"near": dict, "far": dict} of (N, H, W, ...) arrays (GBUFFER_FIELDS, "direct",
                  "indirect", "env" (N,) index into ``test_envs``).
      test_envs:  (Eh, 6, n, n, 3) held-out environments, never used in training.
      env_names:  names of the training environments ("map@rotation").
      test_env_names: names of the held-out environments.
      cameras:    {"train": (C, 3), "near": ..., "far": ...} camera origins.
      stats:      {"render_s": ..., "spp": ..., "test_spp": ...}.
    """

    train: dict
    importance: np.ndarray
    envs: np.ndarray
    tests: dict
    test_envs: np.ndarray
    env_names: list
    test_env_names: list
    cameras: dict
    stats: dict


# --------------------------------------------------------------------------------------------
# Model (§4, Eq. 4-7)
# --------------------------------------------------------------------------------------------


def _reflection_size(kind: str) -> int:
    sizes = {"sh4": 16, "raw": 3, "none": 0}
    if kind not in sizes:
        raise ValueError(f"unknown reflection encoding {kind!r}: use one of {sorted(sizes)}")
    return sizes[kind]


def pixel_features(g: dict, reflection: str = "sh4"):
    """Per-pixel inputs of f besides h_k: encoded w_r, n, k_d, k_s, remapped roughness (..., D).

    Numerics:
        case: wavelet_pixel_features (unit reflected directions and normals, albedos in [0, 1],
          roughness in [0, 1])
        fd: off (the roughness is clipped to [0, 1], the domain's ends)
        float32: value rtol 1e-5 atol 1e-6; grad rtol 1e-4 atol 1e-5
    """
    parts = []
    if reflection == "sh4":
        parts.append(encoding.sh4(g["reflected"]))
    elif reflection == "raw":
        parts.append(jnp.asarray(g["reflected"]))
    elif reflection != "none":
        _reflection_size(reflection)
    rough = encoding.roughness_remap(jnp.clip(jnp.asarray(g["roughness"]), 0.0, 1.0))[..., None]
    parts += [jnp.asarray(g["normal"]), jnp.asarray(g["diffuse_albedo"]), jnp.asarray(g["specular_albedo"]), rough]
    return jnp.concatenate(parts, axis=-1)


class Model(NamedTuple):
    """``init(key, bbox) -> params``; ``transport(params, g, k) -> (P, K, 3)`` for a batch of
    pixels (dict of (P, ...) arrays named in ``fields``) and wavelet flat indices k (K,)."""

    init: Callable
    transport: Callable
    face_size: int
    fields: tuple
    prepare: Callable
    head: Callable


def _relu_delta(neg, low, dz):
    """relu(z + dz) - relu(z) from neg = -z and low = min(z, 0): max(dz, -z) + min(z, 0), which is
    dz itself where z and z + dz are both positive (no rounding of z enters) and exactly 0 where
    both are negative; as cheap as the ReLU it replaces (a max and an add)."""
    return jnp.maximum(dz, neg) + low


def model(config: dict | None = None, *, n_vertices: int | None = None) -> Model:
    """The transport network T_k(x, w_o) = f(h_k(x), enc(w_r), n, rho) of Eq. 4 with the CP
    feature field of Eq. 7 (``jprt.nn.factor``), less f(0, pixel) with ``model.null_transport =
    "zero"`` (the default; "free" is Eq. 4 as written). With ``model.spatial = "vertex"`` S_m[x] is
    softplus of per-vertex features interpolated over the subdivided scene mesh instead
    (``n_vertices`` needed for ``init``).

    Numerics:
        case: wavelet_model (face size 4, 8 features, 4 x 2 hash-grid components, a 2 x 16 ReLU f as
          ``init`` draws them; pixels in the unit box with unit normals and reflected directions,
          albedos and roughness in [0, 1], every wavelet index; gradients w.r.t. the parameters)
        fd: off (ReLU and the hash grid's trilinear interpolation have kinks)
        float32: value rtol 1e-4 atol 1e-6; grad rtol 1e-4 atol 1e-5
        (sums of the factor field's products of both signs: rounding is absolute near zero)
    """
    cfg = _cfg(config)
    mc, n = cfg["model"], int(cfg["envmaps"]["face_size"])
    field = factor_field(face_size=n, n_features=int(mc["n_features"]), n_levels=int(mc["n_levels"]),
                         features_per_level=int(mc["features_per_level"]),
                         log2_table_size=int(mc["log2_table_size"]), base_resolution=int(mc["base_resolution"]),
                         per_level_scale=float(mc["per_level_scale"]), w_init=float(mc["w_init"]))
    spatial = mc["spatial"]
    if spatial not in ("hashgrid", "vertex"):
        raise ValueError(f"unknown model.spatial {spatial!r}: use 'hashgrid' or 'vertex'")
    fields = tuple(GBUFFER_FIELDS) + (tuple(VERTEX_FIELDS) if spatial == "vertex" else ())
    reflection = mc["reflection"]
    null = mc["null_transport"]
    if null not in ("free", "zero"):
        raise ValueError(f"unknown model.null_transport {null!r}: use 'free' (Eq. 4) or 'zero'")
    d_pix = _reflection_size(reflection) + 10
    n_in = int(mc["n_features"]) + d_pix
    f = mlp((n_in,) + (int(mc["hidden"]),) * int(mc["layers"]) + (3,), activation="relu", init="he")
    # Fixed output scale: the mean texel solid angle 4 pi / (6 n^2). Without premultiplication T_k
    # carries the solid-angle factors (§5); this puts f's outputs at O(1) for an O(1) transport.
    out_scale = 4.0 * math.pi / (6 * n * n)

    def init(key, bbox):
        kf, km, kv = jax.random.split(key, 3)
        fp = field.init(kf)
        if spatial == "vertex":
            if not n_vertices:
                raise ValueError("model.spatial='vertex' needs n_vertices (see add_vertex_interpolation)")
            fp["S"] = {"vertex": jax.random.uniform(kv, (int(n_vertices), field.n_components), jnp.float32,
                                                    -1e-4, 1e-4)}
        return {"field": fp, "f": f.init(km), "bbox": jnp.asarray(bbox, jnp.float32)}

    def factors(params, g, k):
        """S[x] (P, M) and W[k] (K, M) of Eq. 7 (h_k(x) = (S[x] * W[k]) U)."""
        if spatial == "hashgrid":
            bbox = jax.lax.stop_gradient(params["bbox"])
            x = jnp.clip((jnp.asarray(g["position"]) - bbox[0][None, :]) / (bbox[1] - bbox[0])[None, :], 0.0, 1.0)
            return field.parts(params["field"], x, k)
        fv = params["field"]["S"]["vertex"][jnp.asarray(g["vertex_index"])]  # (P, 4, M)
        s = jax.nn.softplus(jnp.einsum("pv,pvm->pm", jnp.asarray(g["vertex_weight"]), fv))
        return s, params["field"]["W"][jnp.asarray(k, jnp.int32)]

    def prepare(params, g, *, exact: bool = True):
        """The per-pixel part of f (P pixels): S[x] (P, M) of Eq. 7 and the pixel inputs' share
        of the first layer (P, hidden), computed once per pixel whatever K is. With
        ``null_transport = "zero"`` also f(0, pixel): with ``exact`` the pre-activations z of its
        hidden layers as (-z, min(z, 0)) for ``head``'s difference form, else its output."""
        s, _ = factors(params, g, jnp.zeros((1,), jnp.int32))
        layers = params["f"]["layers"]
        n_h = params["field"]["U"].shape[-1]
        pix = pixel_features(g, reflection)  # (P, D)
        pre = {"s": s, "z0": pix @ layers[0]["w"][n_h:] + layers[0]["b"][None, :]}
        if null == "zero" and exact:
            z, kinks = pre["z0"], []
            for layer in layers[1:]:
                kinks.append((-z, jnp.minimum(z, 0.0)))
                z = jax.nn.relu(z) @ layer["w"] + layer["b"][None, :]
            pre["kinks"] = kinks
        elif null == "zero":
            pre["t0"] = _rest(layers, jax.nn.relu(pre["z0"]))
        return pre

    def _rest(layers, z):
        """f's layers after the first on first-layer activations z (..., hidden), times the output scale."""
        lead = (1,) * (z.ndim - 1)  # the biases broadcast over z's leading axes
        for layer in layers[1:-1]:
            z = jax.nn.relu(z @ layer["w"] + layer["b"].reshape(lead + (-1,)))
        return (z @ layers[-1]["w"] + layers[-1]["b"].reshape(lead + (-1,))) * out_scale

    def head(params, pre, k):
        """T_k for prepared pixels (``prepare``) and wavelets k (K,) -> (P, K, 3).

        With ``null_transport = "zero"`` and ``prepare(exact=True)`` (``transport``, training)
        T_k = f(h_k, pixel) - f(0, pixel) is carried through the layers as a difference of
        activations: relative precision for any T_k, and the gradients of a T_k near 0 (every
        T_k at initialisation) are not rounding noise (the numerics harness's case for ``model``
        checks it). With ``exact=False`` (the run-time ``evaluator``) it is f(h_k, pixel) less the
        prepared f(0, pixel): absolute rounding of f's output, ~1e-7 of |f(0, pixel)| (out_scale
        units), and faster than the difference form on a CPU."""
        layers = params["f"]["layers"]
        n_h = params["field"]["U"].shape[-1]
        w = params["field"]["W"][jnp.asarray(k, jnp.int32)]  # (K, M)
        # The first layer on concat(h_k, pix) split in two: the pixel part once per pixel
        # (``prepare``), and h_k(x) W0_h = (S[x] * W[k]) (U W0_h) with U folded into the layer
        # (Eq. 7 is linear in U): 2 M hidden FLOPs per (pixel, wavelet) instead of 2 (M + hidden) L.
        v = params["field"]["U"] @ layers[0]["w"][:n_h]  # (M, hidden)
        dz = (pre["s"][:, None, :] * w[None, :, :]) @ v  # (P, K, hidden): h_k's share of the first layer
        if "kinks" not in pre:
            t = _rest(layers, jax.nn.relu(dz + pre["z0"][:, None, :]))
            return t - pre["t0"][:, None, :] if "t0" in pre else t
        # f(h_k, pixel) - f(0, pixel) layer by layer as differences of activations, never as the
        # difference of two O(1) outputs: T_k near 0 keeps its relative precision (and so do its
        # gradients; the output bias cancels exactly instead of to rounding)
        d = dz
        for i, (neg, low) in enumerate(pre["kinks"]):
            d = _relu_delta(neg[:, None, :], low[:, None, :], d)
            d = d @ layers[i + 1]["w"]
        return d * out_scale

    def transport(params, g, k):
        return head(params, prepare(params, g), k)

    return Model(init, transport, n, fields, prepare, head)


def model_bytes(params) -> int:
    """Bytes of the learned parameters (float32), the bounding box excluded (for the per-vertex
    variant the unused hash grid is not counted either).

    Numerics: not differentiable (an integer size).
    """
    return int(sum(np.asarray(leaf).nbytes for leaf in jax.tree_util.tree_leaves(
        {"field": params["field"], "f": params["f"]["layers"]})))


# --------------------------------------------------------------------------------------------
# Wavelet selection and the dot product (Algorithm 1)
# --------------------------------------------------------------------------------------------


def lighting_mask(face_size: int, levels: int | None) -> np.ndarray:
    """The flat Haar coefficients (``haar.flat_index`` order, (6 n^2,) bool) a model with
    ``model.lighting_levels`` = ``levels`` reads: each face's scaling wavelet and its ``levels``
    coarsest detail levels (in the Mallat layout, rows and columns below 2^levels); every
    coefficient when ``levels`` is None. ValueError unless 0 <= levels <= log2(face_size).

    Numerics: not differentiable (a boolean mask).
    """
    n_levels = haar.check_face_size(int(face_size))
    if levels is None:
        return np.ones(6 * face_size * face_size, bool)
    if isinstance(levels, bool) or not isinstance(levels, (int, np.integer)) or not 0 <= int(levels) <= n_levels:
        raise ValueError(f"model.lighting_levels must be None or an integer in [0, {n_levels}] (log2 of the face "
                         f"size {face_size}), got {levels!r}")
    block = np.arange(face_size) < 2 ** int(levels)
    return np.broadcast_to(block[:, None] & block[None, :], (6, face_size, face_size)).reshape(-1).copy()


def training_wavelets(key, coeffs, n: int, *, unbiased: bool = False, allowed=None):
    """§5's training selection from flat coefficients (N, 3): the n // 2 largest |L_k| (no area
    weighting) and n - n // 2 distinct others uniformly at random. Returns (indices (n,), values
    (n, 3), weights (n,)): weights 1, or with ``unbiased`` (N - n // 2) / (n - n // 2) for the
    uniform half, which makes sum_k w_k L_k T_k an unbiased estimate of the sum over all N
    wavelets (each of the other wavelets is drawn with that inverse probability). ``allowed`` (N,)
    bool restricts both halves to those wavelets (``lighting_mask``; N then counts them only, and
    n must not exceed it).

    Numerics: not differentiable (a random selection of wavelet indices).
    """
    coeffs = jnp.asarray(coeffs)
    mag = jnp.sqrt(jnp.sum(jnp.square(coeffs), axis=-1))
    allowed = np.ones(mag.shape[0], bool) if allowed is None else np.asarray(allowed, bool)
    total = int(allowed.sum())
    if n > total:
        raise ValueError(f"cannot select {n} training wavelets of {total}")
    half = n // 2
    _, top = jax.lax.top_k(jnp.where(allowed, mag, -1.0), half)
    rest = jnp.asarray(allowed).at[top].set(False)
    others = jax.random.choice(key, mag.shape[0], (n - half,), replace=False, p=rest / jnp.sum(rest))
    idx = jnp.concatenate([top, others]).astype(jnp.int32)
    scale = (total - half) / max(n - half, 1) if unbiased else 1.0
    weights = jnp.concatenate([jnp.ones(half, coeffs.dtype), jnp.full(n - half, scale, coeffs.dtype)])
    return idx, coeffs[idx], weights


def indirect_output(b, nonnegative: bool = True):
    """The image the method shows: max(B, 0) with ``nonnegative`` (model.nonnegative), else B.

    Numerics:
        b: (32, 3) in [-1e5, 1e5]
        nonnegative: = True
        fd: off (max(B, 0) has a kink at 0, drawn)
        float32: value rtol 0 atol 0; grad rtol 0 atol 0
    """
    return jnp.maximum(b, 0.0) if nonnegative else b


def indirect_loss(pred, target, mu: float, nonnegative: bool = True):
    """The training loss on B (Eq. 8): the mu-law L2 of what the image shows
    (``indirect_output``), plus, with ``nonnegative``, the mu-law square of the clipped negative
    part (zero where B >= 0), which keeps a gradient on negative predictions.

    Numerics:
        pred: (32, 3) in [-1e5, 1e5]
        target: (32, 3) in [0, 1e5]
        mu: = 10.0
        fd: off (the clip at B = 0 is a kink, drawn)
        float32: value rtol 1e-5 atol 1e-12; grad rtol 1e-5 atol 1e-12
    """
    if not nonnegative:
        return losses.mu_law_l2(pred, target, mu)
    neg = jnp.minimum(pred, 0.0)
    return losses.mu_law_l2(jnp.maximum(pred, 0.0), target, mu) + jnp.mean(jnp.square(losses.mu_law(neg, mu)))


def select_wavelets(light_coeffs, k: int):
    """Algorithm 1, line 3: the ``k`` largest area-weighted coefficients of a (6, n, n, 3)
    wavelet cube map -> (flat indices (k,), values (k, 3)).

    Numerics:
        light_coeffs: (6, 4, 4, 3) in [-1e5, 1e5]
        k: = 8
        fd: off (the selected set changes where importances tie)
        float32: value rtol 0 atol 0; grad rtol 0 atol 0
        (a selection: the values are gathered, exact)
    """
    return haar.top_k(light_coeffs, int(k), area_weighted=True)


def render_pixels(transport_fn: Callable, g: dict, light_coeffs, k: int, *, chunk: int = 2048, valid=None):
    """B = sum_{k in K} L_k T_k for P pixels (Algorithm 1, lines 3-10), in chunks of ``chunk``
    pixels so memory stays O(chunk x K x width) (``jax.lax.map``). ``g`` is a dict of (P, ...)
    arrays, ``transport_fn(g_chunk, idx) -> (chunk, K, 3)``. With ``valid`` (P,) a chunk with no
    valid pixel is skipped (its pixels are 0). Returns (P, 3).

    Numerics:
        case: wavelet_render (exact transport coefficients (P = 8, face size 2) in [-1e3, 1e3], light
          coefficients in [-1e5, 1e5], K = 8 of 24 wavelets, chunks of 3 pixels)
        fd: off (the top-K set changes where importances tie)
        float32: value rtol 1e-5 atol 1e2; grad rtol 1e-5 atol 1e-3
        (a sum of K = 8 products to 1e8 of both signs: rounding is absolute near zero)
    """
    idx, vals = select_wavelets(light_coeffs, k)
    p = jax.tree_util.tree_leaves(g)[0].shape[0]
    c = max(1, min(int(chunk), p))
    pad = (-p) % c

    def chunks(a):
        return jnp.pad(a, [(0, pad)] + [(0, 0)] * (a.ndim - 1), mode="edge").reshape((-1, c) + a.shape[1:])

    def one(gc):
        return jnp.einsum("pkc,kc->pc", transport_fn(gc, idx), vals)

    gp = jax.tree_util.tree_map(chunks, g)
    if valid is None:
        out = jax.lax.map(one, gp)
    else:
        live = jnp.any(chunks(jnp.asarray(valid) > 0), axis=1)
        out = jax.lax.map(lambda a: jax.lax.cond(a[1], one, lambda gc: jnp.zeros((c, 3), vals.dtype), a[0]),
                          (gp, live))
    return out.reshape(-1, 3)[:p]


def exact_transport_fn(transport_coeffs):
    """A ``transport_fn`` reading exact transport coefficients (P, 6, n, n, 3) by pixel index
    (the G-buffer dict must carry "pixel" (P,) int32): for tests and the ground-truth check.

    Numerics: not differentiable (builds a transport function; covered through ``render_pixels``).
    """
    t = jnp.asarray(transport_coeffs)
    flat = t.reshape(t.shape[0], -1, 3)

    def fn(g, idx):
        return flat[g["pixel"]][:, idx]

    return fn


def transport_check(transport, cube, ks=(32, 64, 128, 300), *, chunk: int = 1024) -> dict:
    """Relight with Mitsuba's ground-truth transport (``jprt.render.transport``) in the Haar basis.

    Args:
      transport: (P, 6, n, n, 3) texel-domain transport T (solid angles included).
      cube: (6, n, n, 3) environment.
    Returns {"full": (P, 3) sum_t T_t L_t, "wavelet_all": (P, 3) the same through the Haar
    basis with every wavelet, "by_k": {K: (P, 3) with the top-K area-weighted wavelets}}.

    Numerics: not differentiable (a ground-truth check from Mitsuba's transport).
    """
    t = jnp.asarray(transport)
    p, n = t.shape[0], t.shape[2]
    # Haar transform over the texel axes: (6, n, n, P, 3) -> coefficients T_hat (P, 6, n, n, 3)
    t_hat = jnp.moveaxis(haar.forward(jnp.moveaxis(t, 0, 3)), 3, 0)
    l_hat = haar.forward(jnp.asarray(cube))
    g = {"pixel": jnp.arange(p, dtype=jnp.int32)}
    fn = exact_transport_fn(t_hat)
    full = jnp.einsum("ptijc,tijc->pc", t, jnp.asarray(cube))
    out = {"full": np.asarray(full),
           "wavelet_all": np.asarray(render_pixels(fn, g, l_hat, 6 * n * n, chunk=chunk)), "by_k": {}}
    for k in ks:
        out["by_k"][int(k)] = np.asarray(render_pixels(fn, g, l_hat, min(int(k), 6 * n * n), chunk=chunk))
    return out


# --------------------------------------------------------------------------------------------
# Training (§5)
# --------------------------------------------------------------------------------------------


def indirect_baseline_scale(direct, indirect, valid) -> np.ndarray:
    """The best RGB scale c (least squares over valid pixels) of indirect ~ c * direct: the
    baseline of the acceptance targets.

    Numerics: not differentiable (a NumPy least-squares baseline).
    """
    d = np.asarray(direct, np.float64)[np.asarray(valid, bool)]
    i = np.asarray(indirect, np.float64)[np.asarray(valid, bool)]
    return (np.sum(d * i, axis=0) / np.maximum(np.sum(d * d, axis=0), 1e-30)).astype(np.float32)


def _device_data(data: WaveletData) -> dict:
    t = data.train
    e, v, h, w = t["valid"].shape
    names = [k for k in list(GBUFFER_FIELDS) + list(VERTEX_FIELDS) if k in t] + ["indirect"]
    flat = {k: jnp.asarray(t[k].reshape((e, v * h * w) + t[k].shape[4:])) for k in names}
    coeffs = haar.forward(jnp.moveaxis(jnp.asarray(data.envs), 0, 3))  # (6, n, n, E, 3)
    flat["coeffs"] = jnp.moveaxis(coeffs, 3, 0).reshape(e, -1, 3)
    flat["log_importance"] = jnp.log(jnp.asarray(data.importance))
    return flat


def _bbox(data: WaveletData, margin: float = 0.02) -> np.ndarray:
    p = data.train["position"][data.train["valid"].astype(bool)]
    lo, hi = p.min(axis=0), p.max(axis=0)
    pad = margin * (hi - lo).max()
    return np.stack([lo - pad, hi + pad]).astype(np.float32)


def run_key(config: dict | None = None) -> str:
    """Content hash of everything a trained model depends on (scene, maps, cameras, data, model,
    training): names checkpoint folders so an interrupted run resumes and a finished one is reused.

    Numerics: not differentiable (a content hash).
    """
    cfg = _cfg(config)
    train = cfg["train"]
    if not float(train["fine_penalty"]):  # off: left out, so models trained before the keys existed keep their key
        train = {k: v for k, v in train.items() if k not in ("fine_penalty", "fine_levels")}
    model_cfg = cfg["model"]
    if model_cfg["lighting_levels"] is None:  # every level: left out, as above
        model_cfg = {k: v for k, v in model_cfg.items() if k != "lighting_levels"}
    return stable_hash({**{k: cfg[k] for k in ("scene", "envmaps", "cameras", "data")}, "model": model_cfg,
                        "train": train})


def fit(data: WaveletData, config: dict | None = None, *, checkpoint_path: str | None = None,
        log_path: str | None = None, progress: bool | None = None, stop_after: int | None = None) -> FitResult:
    """Train the transport network on ``data`` (§5) with Adam; resumes bit-identically from
    ``checkpoint_path`` when it exists. Returns ``FitResult(params, info)``, info {"losses",
    "train_s", "resumed_from", "step"}. ``progress``: the training bar (``jprt.progress``; None:
    its policy).

    Numerics: not differentiable (a fitting or training procedure).
    """
    from jprt.solve.adam import train
    import optax

    cfg = _cfg(config)
    tc = cfg["train"]
    if int(data.envs.shape[2]) != int(cfg["envmaps"]["face_size"]):
        raise ValueError(f"data has face size {data.envs.shape[2]}, config envmaps.face_size is "
                         f"{cfg['envmaps']['face_size']}")
    m = model(cfg, n_vertices=data.stats.get("n_vertices"))
    missing = [f for f in m.fields if f not in data.train]
    if missing:
        raise ValueError(f"data lacks {missing} (model.spatial='vertex' needs add_vertex_interpolation)")
    kept = lighting_mask(m.face_size, cfg["model"]["lighting_levels"])
    n_kept = int(kept.sum())
    n_wav = min(int(tc["wavelets"]), n_kept)
    n_pix = int(tc["pixels"])
    if n_pix % 4:
        raise ValueError(f"train.pixels must be a multiple of 4 (four sampling strategies), got {n_pix}")
    mu = float(tc["mu"])
    if tc["objective"] not in ("unbiased", "paper", "exact"):
        raise ValueError(f"unknown train.objective {tc['objective']!r}: use 'unbiased', 'paper' or 'exact'")
    unbiased, exact = tc["objective"] == "unbiased", tc["objective"] == "exact"
    if exact:  # all N wavelets per pixel: as many (pixel, wavelet) products per step as n_wav wavelets
        n_wav = n_kept
        n_pix = max(4, 4 * round(n_pix * min(int(tc["wavelets"]), n_wav) / n_wav / 4))
    kept_idx = jnp.asarray(np.flatnonzero(kept), jnp.int32)
    nonneg = bool(cfg["model"]["nonnegative"])
    fine, n_fine, levels = float(tc["fine_penalty"]), int(tc["fine_levels"]), haar.check_face_size(m.face_size)
    if fine < 0 or not 0 <= n_fine <= levels:
        raise ValueError(f"train.fine_penalty must be >= 0 and train.fine_levels in [0, log2(face_size)], got "
                         f"{fine} and {n_fine}")
    first_fine = levels - n_fine  # the coarsest penalised detail level
    stops, wb = float(tc["exposure_stops"]), float(tc["white_balance"])
    if stops < 0 or wb < 0:
        raise ValueError(f"train.exposure_stops and train.white_balance must be >= 0, got {stops} and {wb}")
    dev = _device_data(data)
    n_env = dev["coeffs"].shape[0]
    key = jax.random.PRNGKey(int(tc["seed"]))
    params = m.init(jax.random.fold_in(key, 1), _bbox(data))

    def sampler(k, step, d):
        ke, kw, kp, kj, kb = jax.random.split(k, 5)
        e = jax.random.randint(ke, (), 0, n_env)
        if exact:
            idx, vals, weights = kept_idx, d["coeffs"][e][kept_idx], jnp.ones(n_wav)
        else:
            idx, vals, weights = training_wavelets(kw, d["coeffs"][e], n_wav, unbiased=unbiased, allowed=kept)
        logits = d["log_importance"][e]  # (4, V H W)
        pix = jax.vmap(lambda kk, lg: jax.random.categorical(kk, lg, shape=(n_pix // 4,)))(
            jax.random.split(kp, 4), logits).reshape(-1)
        g = {f: d[f][e][pix] for f in m.fields}
        # exposure and white balance: B is linear in each colour channel of the lighting, so scaling
        # the lighting's channels scales the target's alike (no render needed)
        log_wb = wb * jax.random.normal(kb, (3,))
        gain = jnp.exp2(jax.random.uniform(kj, (), minval=-stops, maxval=stops)) * jnp.exp(log_wb - jnp.mean(log_wb))
        return {"g": g, "idx": idx, "vals": vals * weights[:, None] * gain[None, :],
                "target": d["indirect"][e][pix] * gain[None, :]}

    def loss_fn(p, batch):
        t = m.transport(p, batch["g"], batch["idx"])  # (P, K, 3)
        if not fine:
            return indirect_loss(jnp.einsum("pkc,kc->pc", t, batch["vals"]), batch["target"], mu, nonneg)
        light = t * batch["vals"][None, :, :]  # (P, K, 3): each wavelet's share of B
        w = haar.unflatten_index(batch["idx"], m.face_size)
        is_fine = (w.level >= first_fine) & (w.band != haar.BAND_SCALING)
        carried = jnp.sum(jnp.where(is_fine[None, :, None], jnp.square(light), 0.0))
        return (indirect_loss(jnp.sum(light, axis=1), batch["target"], mu, nonneg)
                + fine * carried / (jnp.sum(jnp.square(batch["target"])) + 1e-12))

    steps = int(tc["steps"])
    lr = optax.exponential_decay(float(tc["learning_rate"]), max(steps, 1), float(tc["final_lr_fraction"]))
    t0 = time.perf_counter()
    result = train(loss_fn, params, sampler, key=key, steps=steps, learning_rate=lr,
                   checkpoint_path=checkpoint_path, checkpoint_every=int(tc["checkpoint_every"]),
                   log_path=log_path, log_every=int(tc["log_every"]), progress=progress, stop_after=stop_after,
                   data=dev, ema_decay=float(tc["ema"]))
    final = result.state.params if result.state.ema is None else result.state.ema
    params = jax.tree_util.tree_map(jnp.asarray, final)  # a resumed state is NumPy
    return FitResult(params, {"losses": result.losses, "train_s": time.perf_counter() - t0,
                              "resumed_from": result.resumed_from, "step": int(result.state.step),
                              "model_bytes": model_bytes(params)})


# --------------------------------------------------------------------------------------------
# Rendering (Algorithm 1)
# --------------------------------------------------------------------------------------------


#: Rows (pixels x K) per ``render_pixels`` step when ``render.chunk`` is 0, by JAX backend: on a
#: CPU 8192 rows keep a step's activations in cache; on a GPU a step is a few kernel launches, and
#: 2^22 rows (65536 pixels at K = 64, the whole 256^2 frame in one step, 2 GiB per 128-wide
#: activation) run faster than smaller steps (frame times: the docs' "Evaluators on a GPU"
#: benchmark page, from benchmarks/results/device_evaluators.json).
CHUNK_ROWS = {"cpu": 8192, "gpu": 2 ** 22}


def auto_chunk(k: int, backend: str | None = None) -> int:
    """Pixels per rendering step for K = ``k`` wavelets when ``render.chunk`` is 0: ``CHUNK_ROWS``
    of ``backend`` (default: JAX's default backend; others take the GPU's) over K.

    Numerics: not differentiable (a chunk size; every chunk size gives the same image).
    """
    return max(1, CHUNK_ROWS.get(backend or jax.default_backend(), CHUNK_ROWS["gpu"]) // int(k))


def evaluator(params, config: dict | None = None):
    """``evaluate(inputs, lighting) -> (H, W, 3)`` indirect radiance (Algorithm 1).

    ``inputs`` is a G-buffer dict of (H, W, ...) ``GBUFFER_FIELDS`` arrays (plus
    ``VERTEX_FIELDS`` for the per-vertex variant); ``lighting`` a ``CubeMap`` (6, n, n, 3).
    Haar transform (Eq. 3), the top-K area-weighted wavelets (K = ``render.k``, the one place K is
    set), T_k of every pixel in chunks of ``render.chunk`` pixels (0: ``auto_chunk``), the dot product. Pixels whose
    primary ray missed are 0. Pure and jitted. T_k is ``head``'s run-time form, checked against
    ``transport`` in tests/methods/test_wavelet_prt.py.

    Numerics: not differentiable (builds the float32 run-time program: ``render_pixels`` of ``model``, covered).
    """
    cfg = _cfg(config)
    m = model(cfg)
    params = jax.tree_util.tree_map(jnp.asarray, params)
    k, chunk = int(cfg["render"]["k"]), int(cfg["render"]["chunk"])
    kept = lighting_mask(m.face_size, cfg["model"]["lighting_levels"])
    n_kept = int(kept.sum())
    if not 1 <= k <= n_kept:
        raise ValueError(f"render.k must be in [1, {n_kept}] (the wavelets of model.lighting_levels "
                         f"{cfg['model']['lighting_levels']}), got {k}")
    band = None if kept.all() else jnp.asarray(kept.reshape(6, m.face_size, m.face_size, 1), jnp.float32)
    if chunk < 0:
        raise ValueError(f"render.chunk must be >= 0 (0: automatic), got {chunk}")
    chunk = chunk or auto_chunk(k)

    @jax.jit
    def evaluate(inputs, lighting):
        shape = jnp.asarray(inputs["valid"]).shape
        flat = {f: jnp.asarray(inputs[f]).reshape((-1,) + jnp.asarray(inputs[f]).shape[len(shape):])
                for f in m.fields}
        light = haar.forward(jnp.asarray(lighting.radiance))
        if band is not None:  # model.lighting_levels: the finer detail levels are not read
            light = light * band
        b = render_pixels(lambda pc, idx: m.head(params, pc, idx), m.prepare(params, flat, exact=False), light, k,
                          chunk=chunk, valid=flat["valid"])
        b = indirect_output(b, bool(cfg["model"]["nonnegative"]))
        return jnp.where(flat["valid"][:, None] > 0, b, 0.0).reshape(shape + (3,))

    return evaluate


def frame_flops(params, config: dict | None, inputs, lighting) -> float:
    """FLOPs one ``evaluator`` call needs (``Method.frame_flops``; 2 per multiply-add, 1 per add
    or product): per valid pixel the pixel inputs' share of the first layer and the hash grid's
    trilinear weights (8 corners x M); per (valid pixel, wavelet) S[x] * W[k], the folded first
    layer (2 M hidden), the other layers with their biases and ReLUs, the output layer and the
    dot product with L_k. Encodings, the Haar transform and the top-K selection are not counted
    (XLA's cost analysis counts a loop body once, so the method counts for itself).

    Numerics: not differentiable (a FLOP count).
    """
    cfg = _cfg(config)
    mc = cfg["model"]
    k = int(cfg["render"]["k"])
    layers = params["f"]["layers"]
    sizes = [int(np.shape(layers[0]["w"])[0])] + [int(np.shape(layer["w"])[1]) for layer in layers]
    m = int(np.shape(params["field"]["U"])[0])
    n_h = int(np.shape(params["field"]["U"])[1])
    hidden = sizes[1]
    pixels = int(np.sum(np.asarray(inputs["valid"]) > 0))
    per_pixel = 2 * (sizes[0] - n_h) * hidden + hidden + (2 * 8 * m if mc["spatial"] == "hashgrid" else 0)
    if mc["null_transport"] == "zero":  # f(0, pixel): the layers after the first, once per pixel
        per_pixel += sum(2 * a * b + 2 * b for a, b in zip(sizes[1:-2], sizes[2:-1])) + 2 * sizes[-2] * sizes[-1] \
            + 2 * sizes[-1]
    per_pair = m + 2 * m * hidden + 2 * hidden  # S * W, folded first layer, + pixel part, ReLU
    per_pair += sum(2 * a * b + 2 * b for a, b in zip(sizes[1:-2], sizes[2:-1]))  # hidden layers, bias, ReLU
    per_pair += 2 * sizes[-2] * sizes[-1] + 2 * sizes[-1] + 2 * sizes[-1]  # output, bias, scale; dot with L_k
    return float(pixels * (per_pixel + k * per_pair))


def example(data: WaveletData, config: dict | None = None):
    """A held-out (inputs, lighting) pair: the first far test view's G-buffer under its held-out
    map (the near views, or a training view, when there is none).

    Numerics: not differentiable (a held-out input and lighting from a dataset).
    """
    cfg = _cfg(config)
    fields = model(cfg).fields
    for name in ("far", "near"):
        views = data.tests.get(name) or {}
        if views and len(views["valid"]):
            return {f: views[f][0] for f in fields}, CubeMap(np.asarray(data.test_envs[int(views["env"][0])]))
    return {f: data.train[f][0, 0] for f in fields}, CubeMap(np.asarray(data.envs[0]))
