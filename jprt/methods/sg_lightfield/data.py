"""The light-field texture of SG light-field textures (Currius et al. 2020 §3): the receivers'
lightmap atlas and every texel's captured incident radiance (``jprt.render.lightfield``, cached
and resumable there); and the environment-visibility texture's inputs (§5): captured visibility,
W_E (Eq. 7) and the pre-convolved environment U (Eq. 6) under a distant environment map."""

from __future__ import annotations

import os
from typing import NamedTuple

import numpy as np

from jprt.methods.sg_lightfield.model import GLOSSY_RECEIVERS, SGData, _cfg, texel_irradiance

__all__ = ["make_dataset", "TASK_LIGHTINGS", "ENV_RECEIVERS", "ENV_DEFAULTS", "EnvData", "load_environment",
           "make_environment_dataset"]

#: The shared tasks of experiments/atlas.py relight with lights the bake never saw: a light-field
#: texture is baked for its scene's own emitters, so it takes part in none of them.
TASK_LIGHTINGS: tuple = ()


def make_dataset(scene=None, config: dict | None = None, *, cache_dir: str | None = None,
                 progress: bool = True) -> SGData:
    """Capture the light field of the receivers (``objects``) of ``scene`` (default
    ``config['scene']``) under the scene's own emitters; texels inside other geometry keep their
    ``INSIDE`` flag and zero maps (the fit sees them as black, the run time never looks them up)."""
    from jprt.render.lightfield import capture_lightfield

    cfg = _cfg(config)
    c = cfg["capture"]
    if c["field"] not in ("indirect", "full"):
        raise ValueError(f"capture.field must be 'indirect' or 'full', got {c['field']!r}")
    lf = capture_lightfield(scene if scene is not None else cfg["scene"], None, objects=list(cfg["objects"]) or None,
                            resolution=int(cfg["lightmap"]["resolution"]), size=int(c["size"]), spp=int(c["spp"]),
                            seed=int(c["seed"]), block=int(c["block"]), cache_dir=cache_dir, progress=progress,
                            jitter=bool(c["jitter"]))
    images = lf.indirect if c["field"] == "indirect" else lf.full
    irradiance = np.asarray(texel_irradiance(images, lf.normal, lf.size), np.float32)
    return SGData(lf.atlas, images, lf.below, lf.normal, lf.flags, irradiance,
                  {**lf.meta, "size": lf.size, "field": c["field"]})


#: The Table 3 setting: the receivers of ``model.GLOSSY_RECEIVERS`` in the Cornell box without its
#: ceiling and light, lit by a distant environment through the open top and front.
ENV_RECEIVERS = {"name": "cornell_box", "area_light": False, "open_top": True,
                 "materials": GLOSSY_RECEIVERS["materials"]}

#: Defaults of the environment-visibility setting (``make_environment_dataset``).
ENV_DEFAULTS = {
    "map": "immenstadter_horn_1k",  # a stem of ../shared/assets/envmaps, or "synthetic" (seeded, no files)
    "folder": "",
    "seed": 0,
    "rotation": 0.0,  # degrees about +Y
    "visibility_size": 64,  # octahedral visibility / environment grid of Eq. 7's quadrature
    "samples": 4,  # jittered visibility rays per pixel
    "size": 32,  # the W_E maps the lobes fit (reflected directions)
    "u_size": 64,  # the pre-convolved environment's octahedral maps (Eq. 6)
    "u_env_size": 128,  # the environment grid Eq. 6 integrates over
    "alphas": [0.05, 0.1, 0.2, 0.3, 0.4, 0.5, 0.7, 1.0],  # GGX alpha levels of U
}


class EnvData(NamedTuple):
    """The environment-visibility texture's inputs (``make_environment_dataset``).

    Fields:
      atlas: the receivers' atlas (dict of arrays).  normal: (T, 3).  roughness: (T,) GGX alpha.
      visible: (T, m, m) captured visibility (``jprt.render.lightfield.Visibility.visible``).
      images: (T, n, n, 3) W_E over reflected directions (Eq. 7), what the lobes fit.
      below: (T, n, n) reflected directions under the surface.
      u: (A, k, k, 3) the pre-convolved environment (Eq. 6) at GGX ``alphas``.
      environment: (H, W, 3) the equirect map (what Mitsuba renders with).
      flags: (T,) capture flags.  meta: settings and seconds.
    """

    atlas: dict
    normal: np.ndarray
    roughness: np.ndarray
    visible: np.ndarray
    images: np.ndarray
    below: np.ndarray
    u: np.ndarray
    alphas: np.ndarray
    environment: np.ndarray
    flags: np.ndarray
    meta: dict


def load_environment(spec: dict) -> np.ndarray:
    """The equirect radiance (H, W, 3) of ``spec`` (``ENV_DEFAULTS`` keys): a file of
    ``spec['folder']`` (default ../shared/assets/envmaps) or a seeded procedural sky with suns
    (``"synthetic"``: no files needed), rotated by ``spec['rotation']`` degrees about +Y."""
    from jprt.methods.wavelet_prt.data import SHARED_ENVMAPS
    from jprt.methods.wavelet_prt.model import render_equirect, rotate_equirect, synthetic_environments
    from jprt.render.lights import EnvMap

    s = {**ENV_DEFAULTS, **spec}
    if s["map"] == "synthetic":
        radiance = render_equirect(synthetic_environments(1, 16, int(s["seed"]))[0], scale=8)
    else:
        folder = s["folder"] or SHARED_ENVMAPS
        path = next((os.path.join(folder, s["map"] + ext) for ext in (".hdr", ".exr")
                     if os.path.exists(os.path.join(folder, s["map"] + ext))), None)
        if path is None:
            raise FileNotFoundError(f"environment map {s['map']!r} not found in {folder} (set environment.folder, "
                                    f"or environment.map = 'synthetic' for a procedural sky)")
        radiance = EnvMap.from_file(path).radiance
    return np.asarray(rotate_equirect(radiance, float(s["rotation"])) if float(s["rotation"]) else radiance,
                      np.float32)


def make_environment_dataset(config: dict | None = None, environment: dict | None = None, *,
                             scene=None, cache_dir: str | None = None, progress: bool = True) -> EnvData:
    """§5's inputs for the receivers (``config['objects']``, atlas at ``lightmap.resolution``) of
    ``scene`` (default ``ENV_RECEIVERS``) under the environment ``environment`` (``ENV_DEFAULTS``
    keys): the captured visibility (cached), W_E by Eq. 7 with each texel's own roughness, and U by
    Eq. 6."""
    import time

    from jprt.methods.sg_lightfield import environment as env_model
    from jprt.render.lightfield import capture_visibility
    from jprt.render.scenes import SceneHandle, describe

    cfg = _cfg(config)
    e = {**ENV_DEFAULTS, **(environment or {})}
    desc = describe(scene if scene is not None else ENV_RECEIVERS)
    radiance = load_environment(e)
    vis = capture_visibility(desc, objects=list(cfg["objects"]) or None, resolution=int(cfg["lightmap"]["resolution"]),
                             size=int(e["visibility_size"]), samples=int(e["samples"]), seed=int(e["seed"]),
                             block=int(cfg["capture"]["block"]), cache_dir=cache_dir, progress=progress)
    names = SceneHandle(desc).object_names()
    materials = desc.get("materials", {})
    rough = []
    for obj in np.asarray(vis.atlas["texel_object"]):
        mat = materials.get(names[int(obj)], {})
        if "roughness" not in mat:
            raise ValueError(f"receiver {names[int(obj)]!r} has no GGX roughness (make it 'metal' or 'glossy')")
        rough.append(float(mat["roughness"]))
    roughness = np.asarray(rough, np.float32)
    t0 = time.perf_counter()
    grid = env_model.octahedral_environment(radiance, int(e["visibility_size"]))
    w, below = env_model.weighted_visibility(vis.visible, vis.normal, roughness, grid, int(e["size"]))
    u = env_model.preconvolve(env_model.octahedral_environment(radiance, int(e["u_env_size"])), e["alphas"],
                              int(e["u_size"]))
    return EnvData(vis.atlas, vis.normal, roughness, vis.visible, np.asarray(w, np.float32), np.asarray(below, bool),
                   np.asarray(u, np.float32), np.asarray(e["alphas"], np.float32), radiance, vis.flags,
                   {**vis.meta, "quadrature_s": time.perf_counter() - t0, "environment": dict(e)})
