"""Sampling designs for training data: Latin hypercube samples in boxes, and the boxes a scene
suggests (``scene_regions``: where lights and views go when a config does not say).

Ren et al. 2013, Appendix A: "we uniformly subdivide the light range into N_l strata and randomly
sample the light position in each stratum" (Latin hypercube sampling, McKay et al.): along every
dimension the n samples fall one per stratum [k/n, (k+1)/n), with the strata of different
dimensions paired by independent random permutations.
"""

from __future__ import annotations

import numpy as np

__all__ = ["latin_hypercube", "check_box", "scene_regions", "free_lights", "REGION_KEYS", "CORNELL_REGIONS"]


def check_box(lo, hi, name: str = "box") -> tuple[np.ndarray, np.ndarray]:
    """``(lo, hi)`` as float64 arrays of equal shape with lo <= hi, or a one-line ValueError."""
    lo = np.asarray(lo, np.float64).reshape(-1)
    hi = np.asarray(hi, np.float64).reshape(-1)
    if lo.shape != hi.shape or lo.size == 0:
        raise ValueError(f"{name}: corners {lo.tolist()} and {hi.tolist()} need the same non-zero length")
    if not (np.isfinite(lo).all() and np.isfinite(hi).all()) or np.any(hi < lo):
        raise ValueError(f"{name}: need finite corners with lo <= hi, got lo={lo.tolist()} hi={hi.tolist()}")
    return lo, hi


def latin_hypercube(rng: np.random.Generator, n: int, lo, hi) -> np.ndarray:
    """``n`` Latin-hypercube samples (n, D) in the box [lo, hi] (D = len(lo)).

    Each coordinate has exactly one sample in each of its n equal strata; degenerate dimensions
    (lo == hi) are constant.
    """
    lo, hi = check_box(lo, hi)
    n = int(n)
    if n <= 0:
        raise ValueError(f"need at least one sample, got n={n}")
    d = lo.size
    strata = np.stack([rng.permutation(n) for _ in range(d)], axis=1)
    u = (strata + rng.random((n, d))) / n
    return lo + (hi - lo) * u


#: The sampling regions ``scene_regions`` chooses when the config leaves them None.
REGION_KEYS = ("light_lo", "light_hi", "view_lo", "view_hi", "view_target", "fov")

#: The built-in Cornell boxes' regions (tuned for them; the numbers of benchmarks/results/rrf_*).
CORNELL_REGIONS = {"light_lo": [-0.6, 0.3, -0.6], "light_hi": [0.6, 0.9, 0.6], "view_lo": [-0.6, -0.4, 2.8],
                   "view_hi": [0.6, 0.4, 3.9], "view_target": [0.0, 0.0, 0.0], "fov": 39.3077}


def scene_regions(scene) -> dict:
    """Light and view sampling regions of ``scene`` (``REGION_KEYS`` and ``source``), what the
    config's None means:

    * the built-in Cornell boxes: ``CORNELL_REGIONS`` (source "cornell");
    * any other scene (source "scene bounds"), from its bounding box B (extent e): lights in the
      upper part of the room, x and z within B shrunk by 0.2 e, y from 0.55 to 0.85 of its height
      (light samples inside geometry or within 0.02 e of a surface are drawn again:
      ``free_lights``); views from the scene file's own camera when it has one (a box of 0.1 e
      about its position, its field of view, looking where it looks: the target is the point of
      its view ray nearest B's centre), else from inside B (shrunk by 0.3 e, at 0.35-0.65 of its
      height) towards B's centre with a 60 degree field of view. Views therefore look at the
      room as the file's author framed it."""
    from jprt.render.scenes import SceneHandle, describe

    desc = describe(scene)
    if desc["name"] in ("cornell_box", "glossy_cornell"):
        return {**{k: (list(v) if isinstance(v, list) else v) for k, v in CORNELL_REGIONS.items()}, "source": "cornell"}
    handle = SceneHandle(desc)
    box = handle.scene.bbox()
    lo, hi = np.asarray(box.min, np.float64), np.asarray(box.max, np.float64)
    ext = hi - lo
    size = float(ext.max())
    light_lo = lo + 0.2 * ext
    light_hi = hi - 0.2 * ext
    light_lo[1], light_hi[1] = lo[1] + 0.55 * ext[1], lo[1] + 0.85 * ext[1]
    centre = 0.5 * (lo + hi)
    sensors = handle.scene.sensors()
    if desc["name"] == "xml" and sensors:
        cam = handle.default_camera(64, 64)
        origin = np.asarray(cam.origin, np.float64)
        forward = np.asarray(cam.target, np.float64) - origin
        forward /= max(np.linalg.norm(forward), 1e-12)
        view_lo, view_hi = origin - 0.05 * size, origin + 0.05 * size
        target = origin + max(float(np.dot(centre - origin, forward)), 0.1 * size) * forward
        fov = float(cam.fov)
    else:
        view_lo, view_hi = lo + 0.3 * ext, hi - 0.3 * ext
        view_lo[1], view_hi[1] = lo[1] + 0.35 * ext[1], lo[1] + 0.65 * ext[1]
        target, fov = centre, 60.0
    return {"light_lo": light_lo.tolist(), "light_hi": light_hi.tolist(), "view_lo": view_lo.tolist(),
            "view_hi": view_hi.tolist(), "view_target": target.tolist(), "fov": fov, "source": "scene bounds"}


def free_lights(scene, lights: np.ndarray, light_lo, light_hi, rng, tries: int = 50) -> np.ndarray:
    """Light positions outside geometry and at least 2 % of the light box's scene extent from any
    surface (``lightmap.free_positions``): each one that is not is drawn again, uniformly in the
    light box; a ValueError when the box has no free space."""
    from jprt.render.lightmap import free_positions
    from jprt.render.scenes import SceneHandle

    handle = SceneHandle(scene)
    box = handle.scene.bbox()
    clearance = 0.02 * float(np.max(np.asarray(box.max) - np.asarray(box.min)))
    lo, hi = np.asarray(light_lo, np.float64), np.asarray(light_hi, np.float64)
    lights = np.array(lights, np.float64)
    for _ in range(tries):
        bad = ~free_positions(handle, lights, clearance=clearance)
        if not bad.any():
            return lights
        lights[bad] = lo + (hi - lo) * rng.random((int(bad.sum()), 3))
    raise ValueError(f"no free space for lights in the light box {lo.tolist()} / {hi.tolist()}: set the light box")
