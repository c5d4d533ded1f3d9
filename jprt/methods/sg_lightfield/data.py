"""The light-field texture of SG light-field textures (Currius et al. 2020 §3): the receivers'
lightmap atlas and every texel's captured incident radiance (``jprt.render.lightfield``, cached
and resumable there); and the environment-visibility texture's inputs (§5): captured visibility,
W_E (Eq. 7) and the pre-convolved environment U (Eq. 6) under a distant environment map."""

from __future__ import annotations

import os
from typing import NamedTuple

import numpy as np

from jprt.config import merge
from jprt.methods.base import resolve
from jprt.methods.sg_lightfield.environment import ENV_DEFAULTS, ENV_RECEIVERS  # noqa: F401 (re-exported)
from jprt.methods.sg_lightfield.model import DEFAULT_CONFIG, SGData, texel_irradiance
from jprt.progress import say

__all__ = ["make_dataset", "self_check", "check_candidates", "TASK_LIGHTINGS", "ENV_RECEIVERS", "ENV_DEFAULTS",
           "EnvData", "load_environment", "make_environment_dataset"]

#: The shared tasks of experiments/atlas.py relight with lights the bake never saw: a light-field
#: texture is baked for its scene's own emitters, so it takes part in none of them.
TASK_LIGHTINGS: tuple = ()


def make_dataset(scene=None, config: dict | None = None, *, cache_dir: str | None = None,
                 progress: bool | None = None) -> SGData:
    """Capture the light field of the receivers (``objects``) of ``scene`` (default
    ``config['scene']``) under the scene's own emitters; texels inside other geometry keep their
    ``INSIDE`` flag and zero maps (the fit sees them as black, the run time never looks them up)."""
    from jprt.render.lightfield import capture_lightfield

    cfg = resolve(DEFAULT_CONFIG, config)
    c = cfg["capture"]
    if c["field"] not in ("indirect", "full"):
        raise ValueError(f"capture.field must be 'indirect' or 'full', got {c['field']!r}")
    lf = capture_lightfield(scene if scene is not None else cfg["scene"], None, objects=list(cfg["objects"]) or None,
                            resolution=int(cfg["lightmap"]["resolution"]), size=int(c["size"]), spp=int(c["spp"]),
                            seed=int(c["seed"]), block=int(c["block"]), cache_dir=cache_dir, progress=progress,
                            jitter=bool(c["jitter"]))
    images = lf.indirect if c["field"] == "indirect" else lf.full
    irradiance = np.asarray(texel_irradiance(images, lf.normal, lf.size), np.float32)
    meta = {**lf.meta, "size": lf.size, "field": c["field"]}
    if int(c["check_texels"]) < 0:
        raise ValueError(f"capture.check_texels must be >= 0, got {c['check_texels']}")
    if int(c["check_texels"]):
        meta["check"] = _check(scene if scene is not None else cfg["scene"], lf, c, cache_dir=cache_dir,
                               progress=progress)
    return SGData(lf.atlas, images, lf.below, lf.normal, lf.flags, irradiance, meta)


#: Held-out view directions per self-check texel.
CHECK_VIEWS = 4


def check_candidates(atlas, flags) -> np.ndarray:
    """The texels a self-check may draw: captured outside geometry (``flags`` not ``INSIDE``) and
    shown by the atlas (``fill_index`` of their own pixel is themselves; a texel no view sees
    shows a seen neighbour, ``lightmap.build_atlas``'s ``seen_from``, so the evaluator never
    returns its own value)."""
    from jprt.render.lightfield import INSIDE

    shown = np.asarray(atlas["fill_index"])[np.asarray(atlas["texel_index"])] == np.arange(len(flags))
    return np.flatnonzero((np.asarray(flags) != INSIDE) & shown)


def _check(scene, lf, c: dict, *, cache_dir: str | None, progress: bool | None) -> dict:
    """The self-check's held-out set, cached apart from the light field
    (``$JPRT_CACHE/sg_lightfield_check``): ``capture.check_texels`` texels (at most a tenth of those
    not inside geometry that the atlas shows, ``check_candidates``; drawn with a seed of their own)
    captured again as the light field is (``capture_block``: same points, size, spp and jitter,
    other seeds), their materials (the G-buffer of a ray from the capture point down the normal:
    ``ok`` where it hits the texel's own object), ``CHECK_VIEWS`` held-out view directions each
    (uniform over the hemisphere at up to 78 degrees from the normal) and the scene's object names."""
    import time

    from jprt import cache
    from jprt.render.lightfield import atlas_digest, capture_block
    from jprt.render.scenes import SceneHandle, describe

    desc = describe(scene)
    a = lf.atlas
    seed, size, spp, jitter = int(c["seed"]), int(lf.size), int(c["spp"]), bool(c["jitter"])
    free = check_candidates(a, lf.flags)
    n = min(int(c["check_texels"]), max(1, len(free) // 10), len(free))
    spec = {"format": 2, "scene": desc, "atlas": atlas_digest(a["position"], a["normal"]), "size": size, "spp": spp,
            "seed": seed, "jitter": jitter, "texels": n, "views": CHECK_VIEWS}

    def build() -> dict:
        from jprt.render.gbuffer import gbuffer_rays

        t0 = time.perf_counter()
        rng = np.random.default_rng([seed, 45])
        idx = np.sort(rng.choice(free, n, replace=False))
        handle = SceneHandle(desc)
        points, normal = np.asarray(lf.position, np.float64)[idx], np.asarray(lf.normal, np.float64)[idx]
        maps = capture_block(handle, points, normal, np.asarray(lf.flags)[idx], size, spp=spp,
                             seed=seed * 1000003 + 999_983, jitter=jitter)
        g = gbuffer_rays(handle, points, -normal)
        ok = np.asarray(g.valid, bool) & (np.asarray(g.object_id) == np.asarray(a["texel_object"])[idx])
        # views: uniform in solid angle over cos(theta) in [0.2, 1] about each texel's normal
        cos = rng.uniform(0.2, 1.0, (n, CHECK_VIEWS))
        phi = rng.uniform(0.0, 2.0 * np.pi, (n, CHECK_VIEWS))
        helper = np.where(np.abs(normal[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
        t1 = np.cross(normal, helper)
        t1 /= np.linalg.norm(t1, axis=-1, keepdims=True)
        t2 = np.cross(normal, t1)
        sin = np.sqrt(1.0 - cos * cos)
        views = (cos[..., None] * normal[:, None] + (sin * np.cos(phi))[..., None] * t1[:, None]
                 + (sin * np.sin(phi))[..., None] * t2[:, None])
        say("sg_lightfield", progress)(f"self-check set ({n} texels captured again) in {time.perf_counter() - t0:.1f} s")
        return {"index": idx.astype(np.int64), "full": maps["full"], "indirect": maps["indirect"],
                "below": maps["below"], "views": views.astype(np.float32), "ok": ok,
                "diffuse_albedo": np.asarray(g.diffuse_albedo, np.float32),
                "specular_albedo": np.asarray(g.specular_albedo, np.float32),
                "roughness": np.asarray(g.roughness, np.float32), "object_names": np.array(handle.object_names())}

    arrays, _ = cache.cached("sg_lightfield_check", spec, build, cache_dir=cache_dir)
    return arrays


def self_check(dataset: SGData, result, config: dict | None = None) -> dict:
    """The fit scored on the texels captured again (``_check``), at held-out views: the evaluator
    (the lobes of each texel, looked up at its centre, shaded with its own material along each
    held-out view, plus albedo / pi x its irradiance) against the same shading of the second
    capture, without lobes (``model.shade_quadrature``, the GGX BRDF integrated over the captured
    map, plus albedo / pi x the second capture's irradiance), per object; one item per view. The
    training error the same way against the training capture of the same texels and views. No
    Mitsuba."""
    import jax.numpy as jnp

    from jprt.inputs import GBuffer
    from jprt.methods import selfcheck
    from jprt.methods.lightmap_lookup import atlas_inputs
    from jprt.methods.sg_lightfield.model import evaluator, shade_quadrature

    cfg = resolve(DEFAULT_CONFIG, config)
    check = dataset.meta.get("check")
    if check is None or not len(check["index"]):
        return selfcheck.result("sg_lightfield", {}, float("nan"), None,
                                "nothing held out (capture.check_texels = 0): no self-check")
    idx, ok, views = np.asarray(check["index"]), np.asarray(check["ok"], bool), np.asarray(check["views"])
    k, v = views.shape[:2]
    a = dataset.atlas
    r = int(a["resolution"])
    uv = np.asarray(atlas_inputs(r, a["texel_index"]).uv).reshape(-1, 2)[np.asarray(a["texel_index"])[idx]]
    normal = np.asarray(dataset.normal, np.float32)[idx]

    def per_view(x):  # (k, ...) -> (k, v, ...)
        x = np.asarray(x, np.float32)
        return np.broadcast_to(x[:, None], (k, v) + x.shape[1:])

    diffuse, specular, rough = check["diffuse_albedo"], check["specular_albedo"], check["roughness"]
    gb = GBuffer(position=np.zeros((k, v, 3), np.float32), normal=per_view(normal), view=views,
                 reflected=per_view(normal), uv=per_view(uv), diffuse_albedo=per_view(diffuse),
                 specular_albedo=per_view(specular), roughness=per_view(rough),
                 object_id=np.broadcast_to(np.asarray(a["texel_object"], np.int32)[idx][:, None], (k, v)),
                 valid=np.broadcast_to(ok[:, None], (k, v)))
    # each check texel is seen along several views at its centre: shaded per pixel, not per texel
    pixel = merge(cfg, {"shading": {"space": "pixel"}})
    pred = np.asarray(evaluator(result.params, pixel)(gb, np.ones(3, np.float32)))

    def reference(maps, irradiance):
        maps = np.asarray(maps, np.float32)
        glossy = shade_quadrature(jnp.asarray(np.broadcast_to(maps[:, None], (k, v) + maps.shape[1:])),
                                  per_view(normal), views, per_view(rough), per_view(specular))
        return np.asarray(glossy) + per_view(np.asarray(diffuse) / np.pi * np.asarray(irradiance))

    field = dataset.meta["field"]
    held = reference(check[field], texel_irradiance(check[field], normal, int(dataset.meta["size"])))
    fitted = reference(dataset.images[idx], dataset.irradiance[idx])
    ids = np.where(ok, np.asarray(a["texel_object"])[idx], -1)
    names = [str(x) for x in check["object_names"]]
    rel, per = selfcheck.scores([pred[:, j] for j in range(v)], [held[:, j] for j in range(v)], ids, names)
    train, _ = selfcheck.scores([pred[:, j] for j in range(v)], [fitted[:, j] for j in range(v)], ids, names)
    return selfcheck.result(
        "sg_lightfield", per, rel, train,
        f"{int(ok.sum())} texels captured again ({field} field, {int(cfg['capture']['spp'])} spp, other seeds; "
        f"capture.check_texels) x {v} held-out views, shaded with their materials; training error against the "
        "training capture of the same texels and views")


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
    from jprt.sphere.envmap import render_equirect, rotate_equirect, synthetic_environments
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
                             scene=None, cache_dir: str | None = None, progress: bool | None = None) -> EnvData:
    """§5's inputs for the receivers (``config['objects']``, atlas at ``lightmap.resolution``) of
    ``scene`` (default ``ENV_RECEIVERS``) under the environment ``environment`` (``ENV_DEFAULTS``
    keys): the captured visibility (cached), W_E by Eq. 7 with each texel's own roughness, and U by
    Eq. 6."""
    import time

    from jprt.methods.sg_lightfield import environment as env_model
    from jprt.render.lightfield import capture_visibility
    from jprt.render.scenes import SceneHandle, describe

    cfg = resolve(DEFAULT_CONFIG, config)
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
