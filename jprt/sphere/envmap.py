"""Environment maps as lighting: equirect maps turned and resampled onto cube maps, and
seeded procedural skies.

* ``prepare_environment``: an (H, W, 3) equirect map as a (6, n, n, 3) cube map (area-weighted
  resampling, ``jprt.sphere.cubemap``), optionally scaled to mean radiance 1;
  ``render_equirect`` the inverse view, an equirect map whose texels take their cube-map texel's
  value (piecewise-constant lighting a path tracer can render with).
* ``rotate_equirect`` turns a map about +Y (a column roll), ``turn_equirect`` by any rotation,
  ``random_rotation`` draws one uniformly on SO(3) (Shoemake 1992).
* ``synthetic_environments`` (a sky gradient and one or two broad lobes) and ``sun_skies`` (a
  clear sky whose sun holds a fraction of the energy in one texel): seeded maps for tests and
  training lightings without assets.

NumPy in, NumPy out (the resampling runs through ``jprt.sphere.cubemap``'s JAX functions).
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from jprt.sphere import cubemap

__all__ = ["check_equirect", "prepare_environment", "render_equirect", "rotate_equirect", "turn_equirect",
           "random_rotation", "synthetic_environments", "sun_skies"]


def check_equirect(radiance, *, signed: bool = False) -> np.ndarray:
    """``radiance`` as a float32 (H, W, 3) equirect map, or a one-line ValueError: the shape
    (H, W >= 2), finite values, and every value >= 0 unless ``signed``.

    Numerics: not differentiable (input validation).
    """
    e = np.asarray(radiance, dtype=np.float32)
    if e.ndim != 3 or e.shape[2] != 3 or min(e.shape[:2]) < 2:
        raise ValueError(f"environment map radiance must have shape (H, W, 3) with H, W >= 2, got shape {e.shape}")
    checks = [(~np.isfinite(e), "be finite", "NaN/inf")] + (
        [] if signed else [(e < 0, "be >= 0 (pass signed=True for signed lighting)", "negative")])
    for bad, rule, what in checks:
        if bad.any():
            where = tuple(int(i) for i in np.argwhere(bad)[0])
            raise ValueError(f"environment map radiance must {rule}, got {int(bad.sum())} {what} entries "
                             f"(first at {where}: {e[where]})")
    return e


def rotate_equirect(equirect, degrees: float) -> np.ndarray:
    """The map rotated about +Y by ``degrees`` (a column roll; exact when degrees * W / 360 is
    an integer, nearest column otherwise).

    Numerics: not differentiable (a column roll of a NumPy map).
    """
    e = np.asarray(equirect)
    return np.roll(e, int(round(degrees / 360.0 * e.shape[1])), axis=1)


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    """A rotation matrix (3, 3) uniform on SO(3): a uniform unit quaternion (Shoemake 1992, four
    normal numbers normalised).

    Numerics: not differentiable (a seeded random draw).
    """
    w, x, y, z = (q := rng.normal(size=4)) / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def turn_equirect(equirect, rotation) -> np.ndarray:
    """The map turned by the rotation matrix ``rotation`` (3, 3): the new map's radiance in
    direction d is the old map's in R^T d (nearest texel of the source, at its own resolution).

    Numerics: not differentiable (a nearest-texel NumPy resampling).
    """
    e = np.asarray(equirect)
    d = np.asarray(cubemap.equirect_directions(e.shape[0], e.shape[1]), np.float64)
    src = d @ np.asarray(rotation, np.float64)  # rows d^T R = (R^T d)^T
    return np.asarray(cubemap.sample_equirect_nearest(e, jnp.asarray(src, jnp.float32)))


def _downsample_equirect(e: np.ndarray, max_height: int) -> np.ndarray:
    """Solid-angle weighted block averages down to at most ``max_height`` rows (energy kept)."""
    h, w = e.shape[:2]
    f = 1
    while h // (2 * f) >= max_height and h % (2 * f) == 0 and w % (2 * f) == 0:
        f *= 2
    if f == 1:
        return e
    omega = np.asarray(cubemap.equirect_solid_angles(h, w))[..., None]
    num = (e * omega).reshape(h // f, f, w // f, f, -1).sum(axis=(1, 3))
    den = omega.reshape(h // f, f, w // f, f, 1).sum(axis=(1, 3))
    return num / den


def prepare_environment(equirect, face_size: int, *, normalise: bool = True) -> np.ndarray:
    """An (H, W, 3) equirect map as the (6, n, n, 3) cube map the method relights with
    (area-weighted resampling, ``jprt.sphere.cubemap``), optionally scaled to mean radiance 1.
    The map is checked first (``check_equirect``).

    Numerics: not differentiable (NumPy resampling of a map, through ``jprt.sphere.cubemap``).
    """
    e = _downsample_equirect(check_equirect(equirect), max(8, 4 * face_size))
    cube = np.asarray(cubemap.equirect_to_cubemap(jnp.asarray(e), face_size), np.float32)
    cube = np.maximum(cube, 0.0)
    if normalise:
        omega = np.asarray(cubemap.texel_solid_angles(face_size))
        mean = float(np.sum(cube.mean(axis=-1) * omega) / (4.0 * np.pi))
        if mean <= 0:
            raise ValueError("environment map has no positive radiance")
        cube = cube / mean
    return cube.astype(np.float32)


def synthetic_environments(n_maps: int, face_size: int, seed: int = 0) -> np.ndarray:
    """``n_maps`` seeded procedural cube maps (E, 6, n, n, 3): a coloured sky gradient plus one
    or two sharp lobes ("suns" and windows), mean radiance about 1 (tests, demos without assets).

    Numerics: not differentiable (seeded procedural maps).
    """
    rng = np.random.default_rng(seed)
    d = np.asarray(cubemap.texel_directions(face_size))
    out = []
    for _ in range(n_maps):
        sky = rng.uniform(0.2, 1.0, 3) * (0.6 + 0.4 * d[..., 1:2]) + rng.uniform(0.0, 0.3, 3) * (1 - d[..., 1:2]) / 2
        for _ in range(int(rng.integers(1, 3))):
            axis = rng.normal(size=3)
            axis[1] = abs(axis[1])
            axis /= np.linalg.norm(axis)
            sharp = rng.uniform(10.0, 80.0)
            lobe = np.exp(sharp * (d @ axis - 1.0))[..., None] * rng.uniform(0.5, 1.0, 3)
            sky = sky + rng.uniform(2.0, 8.0) * lobe
        out.append(sky)
    return np.stack(out).astype(np.float32)


def sun_skies(n_maps: int, face_size: int, seed: int = 0) -> np.ndarray:
    """``n_maps`` seeded clear skies with a sun (E, 6, n, n, 3), mean radiance 1: a sky gradient
    (bluer towards the zenith), a dim ground, and a sun holding a fraction U(0.2, 0.8) of the
    map's energy (real clear skies: 20-70 %) in the one texel that contains its direction, which
    is uniform on the upper hemisphere. A sun this small puts large coefficients on the finest
    Haar wavelets at its position (neural-wavelet PRT's ``envmaps.procedural = "sun"`` trains on
    such skies).

    Numerics: not differentiable (seeded procedural maps).
    """
    rng = np.random.default_rng(seed)
    d = np.asarray(cubemap.texel_directions(face_size))
    omega = np.asarray(cubemap.texel_solid_angles(face_size))
    out = []
    for _ in range(n_maps):
        up = np.clip(d[..., 1:2], 0.0, 1.0)
        zenith, horizon = rng.uniform([0.15, 0.3, 0.6], [0.4, 0.6, 1.0]), rng.uniform(0.6, 1.0, 3)
        sky = np.where(d[..., 1:2] >= 0, horizon + (zenith - horizon) * up ** 0.5,
                       rng.uniform(0.05, 0.3) * rng.uniform([0.6, 0.5, 0.3], [1.0, 0.8, 0.6]))
        sky = sky / (np.sum(sky.mean(-1) * omega) / (4 * np.pi))
        y = rng.uniform(0.0, 1.0)  # uniform on the hemisphere: the height is uniform
        phi = rng.uniform(0.0, 2 * np.pi)
        axis = np.array([np.sqrt(1 - y * y) * np.cos(phi), y, np.sqrt(1 - y * y) * np.sin(phi)])
        texel = np.unravel_index(np.argmax(d @ axis), d.shape[:3])
        frac = rng.uniform(0.2, 0.8)
        colour = rng.uniform([1.0, 0.85, 0.6], [1.0, 1.0, 1.0])
        sun = np.zeros_like(sky)
        # sky: 1 - frac of the energy, the sun frac: 4 pi frac / (1 - frac) over the texel's solid angle
        sun[texel] = colour / colour.mean() * 4 * np.pi * frac / (1 - frac) / omega[texel]
        out.append((sky + sun) * (1 - frac))
    return np.stack(out).astype(np.float32)


def render_equirect(cube, scale: int = 8) -> np.ndarray:
    """The (scale n, 2 scale n, 3) equirect map whose texels take the value of the cube-map texel
    containing their centre: what Mitsuba renders with, so references see the same piecewise
    constant lighting as the wavelet relighting (up to the equirect's bilinear lookup).

    Numerics: not differentiable (a nearest-texel NumPy view of a cube map).
    """
    n = np.asarray(cube).shape[1]
    d = cubemap.equirect_directions(scale * n, 2 * scale * n)
    return np.asarray(cubemap.sample_cubemap_nearest(jnp.asarray(cube), d), np.float32)
