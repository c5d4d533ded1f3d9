"""Where neural-wavelet PRT's training pixels come from (Raghavan et al. 2023, §5): the camera
trajectories of the training and held-out views, and the four importance maps the training
steps draw pixels from (Fig. 2).

* ``trajectory``: camera origins on a spherical spiral or a helix about the scene's centre;
  ``camera_sets`` the training, "near" (on the training curves, between their samples) and
  "far" (away from them) views.
* ``importance_maps``: per environment, the uniform, view-variance, high-frequency and
  k_s (1 - sigma) distributions over the valid pixels of its images.

Pure NumPy / SciPy; ``data.make_dataset`` uses them while rendering the training set.
"""

from __future__ import annotations

import numpy as np

from jprt.nn import encoding
from jprt.solve import losses

__all__ = ["trajectory", "camera_sets", "importance_maps"]


def _on_sphere(radius, az_deg, el_deg, target):
    """Points at ``radius`` from ``target`` at azimuth / elevation (degrees; azimuth 0 on +Z,
    elevation 90 on +Y)."""
    az, el = np.radians(az_deg), np.radians(el_deg)
    return np.asarray(target) + np.stack([radius * np.cos(el) * np.sin(az), radius * np.sin(el),
                                          radius * np.cos(el) * np.cos(az)], axis=-1)


def trajectory(kind: str, n: int, spec: dict, target, *, phase: float = 0.0) -> np.ndarray:
    """Camera origins (n, 3) on a training trajectory (§5).

    ``"sphere"``: a Fibonacci-like spiral covering the azimuth x elevation cap of a sphere of
    ``spec["radius"]`` around ``target``. ``"helix"``: the azimuth range swept back and forth
    ``spec["turns"]`` times while the elevation rises through its range. ``phase`` in [0, 1)
    shifts the samples along the curve (held-out "near" views use phase 0.5: between the
    training positions, on the same curve).

    Numerics: not differentiable (camera positions).
    """
    t = (np.arange(n) + 0.5 + phase) / max(n, 1)
    t = np.clip(t, 0.0, 1.0)
    a0, a1 = spec["azimuth"]
    e0, e1 = spec["elevation"]
    if kind == "sphere":
        golden = (np.sqrt(5.0) - 1.0) / 2.0
        u = np.mod((np.arange(n) + phase) * golden, 1.0)
        az = a0 + (a1 - a0) * u
        el = e0 + (e1 - e0) * t
    elif kind == "helix":
        s = 0.5 - 0.5 * np.cos(2.0 * np.pi * float(spec["turns"]) * t)
        az = a0 + (a1 - a0) * s
        el = e0 + (e1 - e0) * t
    else:
        raise ValueError(f"unknown trajectory {kind!r}: use 'sphere' or 'helix'")
    return _on_sphere(float(spec["radius"]), az, el, target)


def camera_sets(ccfg: dict, seed: int):
    """Origins of the training, near and far views.

    Numerics: not differentiable (camera positions).
    """
    target = np.asarray(ccfg["target"], np.float64)
    train, near = [], []
    for kind in ("sphere", "helix"):
        spec = ccfg[kind]
        if int(spec["n"]) > 0:
            train.append(trajectory(kind, int(spec["n"]), spec, target))
    train = np.concatenate(train) if train else np.zeros((0, 3))
    n_near = int(ccfg["near"])
    if n_near:
        spec = ccfg["sphere"]
        near = trajectory("sphere", int(spec["n"]), spec, target, phase=0.5)
        near = near[np.linspace(0, len(near) - 1, n_near).round().astype(int)]
    rng = np.random.default_rng([seed, 7])
    n_far = int(ccfg["far"])
    far = _on_sphere(rng.uniform(*ccfg["far_radius"], n_far), rng.uniform(*ccfg["far_azimuth"], n_far),
                     rng.uniform(*ccfg["far_elevation"], n_far), target)
    return train, np.asarray(near).reshape(-1, 3), far


def _luminance(x):
    """Rec. 709 luminance of linear RGB (..., 3)."""
    return x @ np.array([0.2126, 0.7152, 0.0722], np.float32)


def _blur(img: np.ndarray, mask: np.ndarray, sigma: float = 1.5) -> np.ndarray:
    """Gaussian blur of (..., H, W) images over the pixels in ``mask`` only (normalised
    convolution: invalid pixels neither contribute nor darken their neighbours)."""
    from scipy.ndimage import gaussian_filter

    sig = (0,) * (img.ndim - 2) + (sigma, sigma)
    m = mask.astype(np.float64)
    num = gaussian_filter(np.where(mask, img, 0.0), sig, mode="constant")
    den = gaussian_filter(m, sig, mode="constant")
    return np.where(den > 1e-12, num / np.maximum(den, 1e-12), 0.0)


def importance_maps(indirect, position, valid, specular, roughness, *, mu: float = 10.0, grid: int = 24):
    """The four pixel-sampling distributions of §5 for the V images lit by one environment.

    Args: (V, H, W, ...) arrays of one environment's images.
    Returns (4, V * H * W) probabilities, each summing to 1 over valid pixels:
      0 uniform;
      1 view variance: the variance across views of the mu-law tonemapped indirect luminance of
        each surface voxel (a ``grid``^3 voxelisation of the hit points), per pixel;
      2 high frequency: |TM(I) - blur(TM(I))|;
      3 k_s (1 - sigma): mean specular albedo times the complement of the remapped roughness.
    A strategy with no mass (e.g. no glossy pixel) falls back on uniform.

    Numerics: not differentiable (NumPy sampling distributions).
    """
    valid = np.asarray(valid, bool)
    tm = np.asarray(losses.mu_law(_luminance(np.asarray(indirect, np.float32)), mu))
    v = valid.reshape(-1)
    lo = position[valid].min(axis=0) if valid.any() else np.zeros(3)
    hi = position[valid].max(axis=0) if valid.any() else np.ones(3)
    cell = np.clip(((position - lo) / np.maximum(hi - lo, 1e-9) * grid).astype(int), 0, grid - 1)
    voxel = ((cell[..., 0] * grid + cell[..., 1]) * grid + cell[..., 2]).reshape(len(indirect), -1)
    n_vox = grid**3
    means = []
    for i in range(len(indirect)):  # per-view mean of each voxel, then the variance across views
        m = valid[i].reshape(-1)
        s = np.bincount(voxel[i][m], tm[i].reshape(-1)[m], n_vox)
        c = np.bincount(voxel[i][m], None, n_vox)
        means.append((s / np.maximum(c, 1), c > 0))
    s1 = sum(np.where(seen, mean, 0.0) for mean, seen in means)
    s2 = sum(np.where(seen, mean**2, 0.0) for mean, seen in means)
    cnt = sum(seen.astype(float) for _, seen in means)
    var = np.where(cnt > 1, s2 / np.maximum(cnt, 1) - (s1 / np.maximum(cnt, 1)) ** 2, 0.0)
    view_var = np.maximum(var[voxel.reshape(-1)], 0.0)
    high = np.abs(tm - _blur(tm, valid)).reshape(-1)
    gloss = (np.asarray(specular).mean(axis=-1)
             * (1.0 - np.asarray(encoding.roughness_remap(np.clip(roughness, 0.0, 1.0))))).reshape(-1)
    out = []
    for w in (np.ones_like(high), view_var, high, gloss):
        w = np.where(v, np.maximum(w, 0.0), 0.0)
        if w.sum() <= 0:
            w = v.astype(float)
        out.append(w / w.sum())
    return np.stack(out).astype(np.float32)
