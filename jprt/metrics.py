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
* "tonemapped" means ``jprt.io.tonemap`` (sRGB transfer, clipped to [0, 1]) at exposure 0,
  reimplemented here in JAX so metrics stay differentiable and jit-able.

``valid`` masks (H, W) restrict rmse / relative_rmse / psnr to covered pixels.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["rmse", "relative_rmse", "psnr", "ssim", "tonemap", "tonemapped", "error_map"]


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
