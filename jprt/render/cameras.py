"""Pinhole cameras and camera trajectories (look-at, orbit, helix, random views in a box).

Cameras are plain NamedTuples of floats so they hash and serialise; ``to_sensor_dict`` turns one
into a Mitsuba ``perspective`` sensor with a box pixel filter, so a pixel's value is the average
over exactly its footprint (the G-buffer samples the pixel centre of the same footprint).
"""

from __future__ import annotations

import numpy as np

from jprt.inputs import Camera
from jprt.inputs import vec3 as _vec3

__all__ = ["Camera", "look_at", "orbit", "helix", "random_in_box", "to_sensor_dict", "camera_rays", "random_rays", "check_rays"]


def look_at(origin, target, up=(0.0, 1.0, 0.0), *, fov: float = 39.3077, width: int = 256, height: int = 256) -> Camera:
    """Validated ``Camera`` constructor."""
    origin, target, up = _vec3(origin, "camera origin"), _vec3(target, "camera target"), _vec3(up, "camera up")
    forward = np.subtract(target, origin)
    if np.linalg.norm(forward) == 0:
        raise ValueError(f"camera target must differ from its origin, got both {list(origin)}")
    if np.linalg.norm(np.cross(forward, up)) < 1e-9 * np.linalg.norm(forward) * max(np.linalg.norm(up), 1e-30):
        raise ValueError(f"camera up must not be parallel to the view direction, got up {list(up)} and view "
                         f"{forward.tolist()}")
    if not (np.isfinite(fov) and 0 < fov < 180):
        raise ValueError(f"camera fov must be in (0, 180) degrees, got {fov!r}")
    for name, v in (("width", width), ("height", height)):
        if int(v) != v or int(v) < 1:
            raise ValueError(f"camera {name} must be an integer >= 1, got {v!r}")
    return Camera(origin, target, up, float(fov), int(width), int(height))


def orbit(center, radius: float, n: int, *, elevation_deg: float = 0.0, start_deg: float = 0.0,
          arc_deg: float = 360.0, **camera_kw) -> list[Camera]:
    """``n`` cameras on a horizontal circle around ``center`` (Y up), looking at it.

    Azimuth 0 is the +Z side; with ``arc_deg=360`` the views are spread without repeating the start.
    """
    center = np.asarray(_vec3(center))
    step = arc_deg / n if abs(arc_deg - 360.0) < 1e-9 else (arc_deg / max(n - 1, 1))
    el = np.radians(elevation_deg)
    cams = []
    for k in range(n):
        az = np.radians(start_deg + k * step)
        offset = radius * np.array([np.cos(el) * np.sin(az), np.sin(el), np.cos(el) * np.cos(az)])
        cams.append(look_at(center + offset, center, **camera_kw))
    return cams


def helix(center, radius: float, n: int, *, height_range=(-0.5, 0.5), turns: float = 2.0, **camera_kw) -> list[Camera]:
    """``n`` cameras on a helix around ``center``: ``turns`` revolutions while the height goes
    through ``height_range`` (relative to the centre), each looking at the centre. Used for
    occluded scenes where one circle sees too little (Raghavan et al. 2023, §5)."""
    center = np.asarray(_vec3(center))
    t = np.linspace(0.0, 1.0, n)
    cams = []
    for tk in t:
        az = 2.0 * np.pi * turns * tk
        y = height_range[0] + (height_range[1] - height_range[0]) * tk
        cams.append(look_at(center + np.array([radius * np.sin(az), y, radius * np.cos(az)]), center, **camera_kw))
    return cams


def random_in_box(seed: int, n: int, lo, hi, target, *, jitter_target: float = 0.0, **camera_kw) -> list[Camera]:
    """``n`` cameras with origins uniform in the axis-aligned box [lo, hi], looking at ``target``
    (optionally jittered uniformly by +-``jitter_target`` per axis)."""
    rng = np.random.default_rng(seed)
    lo, hi, target = np.asarray(_vec3(lo)), np.asarray(_vec3(hi)), np.asarray(_vec3(target))
    if np.any(hi < lo):
        raise ValueError(f"box lower corner {lo} exceeds upper corner {hi}")
    origins = lo + (hi - lo) * rng.random((n, 3))
    targets = target + jitter_target * (2.0 * rng.random((n, 3)) - 1.0)
    return [look_at(o, t, **camera_kw) for o, t in zip(origins, targets)]


def to_sensor_dict(camera: Camera, spp: int, mi) -> dict:
    """Mitsuba sensor dict for ``camera`` with an independent sampler of ``spp`` samples."""
    return {
        "type": "perspective",
        "fov": camera.fov,
        "fov_axis": "smaller",
        "near_clip": 1e-3,
        "far_clip": 1e4,
        "to_world": mi.ScalarTransform4f().look_at(origin=camera.origin, target=camera.target, up=camera.up),
        "sampler": {"type": "independent", "sample_count": int(spp)},
        "film": {
            "type": "hdrfilm",
            "width": camera.width,
            "height": camera.height,
            "rfilter": {"type": "box"},
            "pixel_format": "rgb",
            "component_format": "float32",
        },
    }


def _film_directions(camera: Camera, px, py) -> np.ndarray:
    """Unit directions through film positions (px, py) in pixels (x right, y down, origin at the
    top-left corner), same geometry as Mitsuba's perspective sensor with ``fov_axis='smaller'``."""
    o = np.asarray(camera.origin, np.float64)
    f = np.asarray(camera.target, np.float64) - o
    f /= np.linalg.norm(f)
    left = np.cross(np.asarray(camera.up, np.float64), f)
    left /= np.linalg.norm(left)
    up = np.cross(f, left)
    w, h = camera.width, camera.height
    half = np.tan(np.radians(camera.fov) / 2.0) / min(w, h)
    xs = (np.asarray(px, np.float64) - w / 2.0) * 2.0 * half
    ys = (np.asarray(py, np.float64) - h / 2.0) * 2.0 * half
    d = f - xs[..., None] * left - ys[..., None] * up
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def camera_rays(camera: Camera, offset=None) -> tuple[np.ndarray, np.ndarray]:
    """Primary rays (origins, unit directions), each (H, W, 3), in NumPy.

    ``offset`` is the position inside each pixel in [0, 1)^2 (x right, y down): None for the
    pixel centre (0.5, 0.5), or an (H, W, 2) array (e.g. uniform jitter, which makes the mean
    over many offsets the box-filtered pixel value). Same geometry as Mitsuba's perspective
    sensor with ``fov_axis='smaller'``: row 0 is the top of the image, column 0 its left.
    """
    w, h = camera.width, camera.height
    off = np.full((h, w, 2), 0.5) if offset is None else np.broadcast_to(np.asarray(offset, np.float64), (h, w, 2))
    d = _film_directions(camera, np.arange(w)[None, :] + off[..., 0], np.arange(h)[:, None] + off[..., 1])
    return np.broadcast_to(np.asarray(camera.origin, np.float64), d.shape).copy(), d


def check_rays(origins, directions) -> tuple[np.ndarray, np.ndarray]:
    """Ray batches as float32 (N, 3) origins and unit directions, or a one-line ValueError
    (shape mismatch, non-finite values, zero directions)."""
    o = np.asarray(origins, np.float32).reshape(-1, 3)
    d = np.asarray(directions, np.float32).reshape(-1, 3)
    if o.shape != d.shape:
        raise ValueError(f"origins {o.shape} and directions {d.shape} differ")
    norms = np.linalg.norm(d, axis=1, keepdims=True)
    if not (np.isfinite(o).all() and np.isfinite(d).all()) or np.any(norms == 0):
        raise ValueError("ray origins/directions must be finite with non-zero directions")
    return o, d / norms


def random_rays(camera: Camera, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """``n`` primary rays (origins, unit directions), each (n, 3), through uniformly random film
    positions of ``camera`` (Ren et al. 2013, Appendix A: "randomly shoot N_r rays from the
    viewpoint")."""
    if int(n) < 0:
        raise ValueError(f"number of rays must be >= 0, got {n}")
    px = rng.random(int(n)) * camera.width
    py = rng.random(int(n)) * camera.height
    d = _film_directions(camera, px, py)
    return np.broadcast_to(np.asarray(camera.origin, np.float64), d.shape).copy(), d
