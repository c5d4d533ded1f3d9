"""The per-texel baselines Currius et al. 2020 compare the CNN with (§7), on the same texels and the
same lobe budget, scored by the same loss (``model.log_l2_loss`` at the pixel centres, solid-angle
weighted, below-surface directions masked):

* ``gd``: every texel's lobes fitted independently by Adam on the log-L2 loss (``sg.fit_gd``),
  axes initialised by matching pursuit on the texel's image (``sg.peak_axes``);
* ``gd_aligned``: the same with the axis-alignment regulariser between texels adjacent in the
  atlas (the "explicit alignment" of [GKMD06; HSRG07] the paper argues against);
* ``em``: EM on a von Mises-Fisher mixture per texel (``sg.fit_em``, vmapped), amplitudes refitted
  by least squares;
* ``fixed_axes``: N axes fixed on a Fibonacci sphere with one sharpness, amplitudes by weighted
  non-negative least squares (the classic precomputed SG basis);
* ``sh``: real spherical harmonics with about as many numbers per texel as the lobes (7 N), fitted
  by weighted least squares over the texel's hemisphere.

``compare(images, below, atlas, n_lobes)`` runs them all and returns each one's loss, seconds and
per-texel predictions.
"""

from __future__ import annotations

import math
import time

import jax
import jax.numpy as jnp
import numpy as np

from jprt.methods.sg_lightfield.model import Lobes, lobe_radiance, log_l2_loss, pixel_weights
from jprt.sphere import octahedral, sg, sh

__all__ = ["fibonacci_axes", "atlas_neighbours", "fit_per_texel", "fit_fixed_axes", "fit_sh", "sh_radiance",
           "interpolate_lobes", "compare", "BASELINES"]

#: The baselines, in the order the report lists them.
BASELINES = ("gd", "gd_aligned", "em", "fixed_axes", "sh")


def fibonacci_axes(n: int) -> np.ndarray:
    """``n`` near-uniform unit directions (n, 3) (the Fibonacci sphere)."""
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    r = np.sqrt(np.maximum(1.0 - z * z, 0.0))
    phi = math.pi * (3.0 - math.sqrt(5.0)) * i
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=-1).astype(np.float32)


def atlas_neighbours(atlas: dict) -> np.ndarray:
    """(T, 4) indices of each texel's left / right / up / down neighbours in the atlas (itself where
    the neighbour is not a covered texel of the same object)."""
    r = int(atlas["resolution"])
    index = np.asarray(atlas["texel_index"])
    obj = np.asarray(atlas["texel_object"])
    where = np.full(r * r, -1, np.int64)
    where[index] = np.arange(len(index))
    row, col = index // r, index % r
    out = np.repeat(np.arange(len(index))[:, None], 4, axis=1)
    for k, (dr, dc) in enumerate(((0, -1), (0, 1), (-1, 0), (1, 0))):
        rr, cc = row + dr, col + dc
        inside = (rr >= 0) & (rr < r) & (cc >= 0) & (cc < r)
        nb = np.where(inside, where[np.clip(rr, 0, r - 1) * r + np.clip(cc, 0, r - 1)], -1)
        ok = (nb >= 0) & (obj[np.maximum(nb, 0)] == obj)
        out[ok, k] = nb[ok]
    return out


def _init_axes(images, n_lobes: int) -> np.ndarray:
    dirs = np.asarray(octahedral.texel_directions(images.shape[1])).reshape(-1, 3)
    return np.stack([sg.peak_axes(dirs, im.reshape(-1, 3), n_lobes) for im in np.asarray(images)])


def fit_per_texel(images, below, n_lobes: int, *, steps: int = 500, learning_rate: float = 0.05,
                  neighbours=None, align_weight: float = 0.0) -> Lobes:
    """``gd`` (and ``gd_aligned`` with ``neighbours`` and ``align_weight``): Adam on every texel's
    lobes at once (``sg.fit_gd``), masked by ``below``."""
    size = images.shape[1]
    dirs = octahedral.texel_directions(size).reshape(-1, 3)
    fit = sg.fit_gd(dirs, pixel_weights(size, below), jnp.asarray(images).reshape(len(images), -1, 3),
                    _init_axes(images, n_lobes), steps=steps, learning_rate=learning_rate, neighbours=neighbours,
                    align_weight=align_weight)
    return Lobes(fit.axes, fit.sharpness, fit.amplitudes)


def fit_em_lobes(images, below, n_lobes: int, *, iterations: int = 100, max_sharpness: float = 1e4) -> Lobes:
    """``em``: ``sg.fit_em`` on every texel (vmapped), weights masked by ``below``; sharpness
    bounded like the CNN's lobes (float16 storage)."""
    size = images.shape[1]
    dirs = octahedral.texel_directions(size).reshape(-1, 3)
    fit = jax.vmap(lambda w, v, a: sg.fit_em(dirs, w, v, a, iterations=iterations,
                                                        max_sharpness=max_sharpness))(
        pixel_weights(size, below), jnp.asarray(images).reshape(len(images), -1, 3), jnp.asarray(_init_axes(images, n_lobes)))
    return Lobes(fit.axes, fit.sharpness, fit.amplitudes)


def _nnls_rows(basis, weights, values, iterations: int = 200):
    """Weighted non-negative least squares per texel by projected gradient on the normal equations:
    basis (M, K), weights (T, M), values (T, M, 3) -> (T, K, 3)."""
    gram = jnp.einsum("mk,tm,ml->tkl", basis, weights, basis)
    rhs = jnp.einsum("mk,tm,tmc->tkc", basis, weights, values)
    step = 1.0 / jnp.maximum(jnp.linalg.eigvalsh(gram)[:, -1], 1e-20)  # (T,)
    x = jnp.maximum(jnp.linalg.solve(gram + 1e-9 * jnp.eye(gram.shape[-1])[None], rhs), 0.0)

    def body(x, _):
        return jnp.maximum(x - step[:, None, None] * (jnp.einsum("tkl,tlc->tkc", gram, x) - rhs), 0.0), None

    x, _ = jax.lax.scan(body, x, None, length=iterations)
    return x


def fit_fixed_axes(images, below, n_lobes: int) -> Lobes:
    """``fixed_axes``: Fibonacci axes, one sharpness making neighbouring lobes cross at half their
    peak (lambda = ln 2 / (1 - cos theta_nn), theta_nn ~ sqrt(4 pi / N)), amplitudes >= 0 by NNLS."""
    size = images.shape[1]
    dirs = octahedral.texel_directions(size).reshape(-1, 3)
    axes = jnp.asarray(fibonacci_axes(n_lobes))
    lam = math.log(2.0) / (1.0 - math.cos(math.sqrt(4.0 * math.pi / n_lobes)))
    basis = jnp.exp(lam * (dirs @ axes.T - 1.0))  # (M, K)
    amp = _nnls_rows(basis, pixel_weights(size, below), jnp.asarray(images).reshape(len(images), -1, 3))
    t = len(images)
    return Lobes(jnp.broadcast_to(axes, (t, n_lobes, 3)), jnp.full((t, n_lobes), lam, jnp.float32), amp)


def sh_degree_for(n_lobes: int) -> int:
    """The SH degree whose RGB coefficients (3 (l + 1)^2) come closest to, not over, 7 N numbers."""
    return max(0, int(math.floor(math.sqrt(7.0 * n_lobes / 3.0))) - 1)


def fit_sh(images, below, degree: int):
    """``sh``: SH coefficients (T, (l+1)^2, 3) per texel by weighted least squares over the visible
    hemisphere (``sh_radiance`` evaluates them)."""
    size = images.shape[1]
    dirs = octahedral.texel_directions(size).reshape(-1, 3)
    y = sh.evaluate(dirs, int(degree))  # (M, K)
    w = pixel_weights(size, below)
    gram = jnp.einsum("mk,tm,ml->tkl", y, w, y) + 1e-6 * jnp.eye(y.shape[-1])[None]
    rhs = jnp.einsum("mk,tm,tmc->tkc", y, w, jnp.asarray(images).reshape(len(images), -1, 3))
    return jnp.linalg.solve(gram, rhs)


def sh_radiance(coeffs, directions):
    """SH coefficients (..., K, 3) at directions (M, 3): (..., M, 3)."""
    degree = int(round(math.sqrt(coeffs.shape[-2]))) - 1
    return jnp.einsum("mk,...kc->...mc", sh.evaluate(jnp.asarray(directions), degree), jnp.asarray(coeffs))


def interpolate_lobes(a: Lobes, b: Lobes, t: float = 0.5) -> Lobes:
    """Lobes as the run time filters them between two texels: every parameter linear, axes
    renormalised (``model.lookup_lobes``)."""
    axes = (1.0 - t) * jnp.asarray(a.axes) + t * jnp.asarray(b.axes)
    axes = axes / jnp.sqrt(jnp.maximum(jnp.sum(axes * axes, axis=-1, keepdims=True), 1e-20))
    return Lobes(axes, (1.0 - t) * jnp.asarray(a.sharpness) + t * jnp.asarray(b.sharpness),
                 (1.0 - t) * jnp.asarray(a.amplitude) + t * jnp.asarray(b.amplitude))


def compare(images, below, atlas: dict, n_lobes: int, *, steps: int = 500, align_weight: float = 0.1,
            em_iterations: int = 100, max_sharpness: float = 1e4, methods=BASELINES) -> dict:
    """Every baseline on the same texels: {name: {"log_l2", "fit_s", "prediction" (T, M, 3), and
    "lobes" (``Lobes``, float32) or "sh" (T, K, 3) coefficients}}."""
    size = images.shape[1]
    dirs = octahedral.texel_directions(size).reshape(-1, 3)
    t = len(images)
    targets = jnp.asarray(images).reshape(t, -1, 3)
    weights = pixel_weights(size, below)
    at_centres = jnp.broadcast_to(dirs, (t,) + dirs.shape)
    out = {}
    for name in methods:
        t0 = time.perf_counter()
        lobes, coeffs = None, None
        if name == "gd":
            lobes = fit_per_texel(images, below, n_lobes, steps=steps)
        elif name == "gd_aligned":
            lobes = fit_per_texel(images, below, n_lobes, steps=steps, neighbours=atlas_neighbours(atlas),
                                  align_weight=align_weight)
        elif name == "em":
            lobes = fit_em_lobes(images, below, n_lobes, iterations=em_iterations, max_sharpness=max_sharpness)
        elif name == "fixed_axes":
            lobes = fit_fixed_axes(images, below, n_lobes)
        elif name == "sh":
            coeffs = fit_sh(images, below, sh_degree_for(n_lobes))
        else:
            raise ValueError(f"unknown baseline {name!r}; baselines are {BASELINES}")
        pred = lobe_radiance(lobes, at_centres) if lobes is not None else sh_radiance(coeffs, dirs)
        pred = jax.block_until_ready(pred)
        out[name] = {"log_l2": float(sg.log_l2(pred, targets, weights)), "fit_s": time.perf_counter() - t0,
                     "prediction": np.asarray(pred)}
        if lobes is not None:
            out[name]["lobes"] = Lobes(*(np.asarray(a, np.float32) for a in lobes))
        else:
            out[name]["sh"] = np.asarray(coeffs, np.float32)
    return out


def cnn_log_l2(lobes: Lobes, images, below) -> float:
    """The CNN's lobes scored like the baselines (pixel centres, no jitter)."""
    size = images.shape[1]
    dirs = octahedral.texel_directions(size).reshape(-1, 3)
    t = len(images)
    return float(log_l2_loss(lobes, jnp.broadcast_to(dirs, (t,) + dirs.shape), jnp.asarray(images).reshape(t, -1, 3),
                             pixel_weights(size, below)))
