"""The SH PRT bake (Sloan et al. 2002 §4, as Belcour et al. 2022 §6.4's baseline): transfer
vectors of lightmap texels rendered with Mitsuba, one SH function at a time (positive and negative
parts separately), cached by ``jprt.cache``."""

from __future__ import annotations

import time

import numpy as np

from jprt import cache
from jprt.methods.base import resolve
from jprt.methods.sh_prt.model import DEFAULT_CONFIG, SHData, order_to_degree
from jprt.progress import say
from jprt.sphere import sh
from jprt.sphere.cubemap import equirect_directions

__all__ = ["bake", "bake_exit", "exit_directions", "make_dataset", "check_maps", "self_check", "TASK_LIGHTINGS",
           "task_inputs", "task_lighting"]


def bake(handle, atlas, degree: int, *, spp: int, env_height: int = 32, seed: int = 0,
         progress: bool | None = None, ray: bool | None = None) -> np.ndarray:
    """Transfer vectors (T, (degree + 1)^2, 3) of the atlas texels: the indirect radiance at
    each texel under white distant lighting Y_i, for every SH function i (one block each: in this
    process, or as Ray tasks when ``jprt.distributed.requested(ray)``; the same seeds either way)."""
    from jprt import distributed

    position = np.asarray(atlas["position"] if isinstance(atlas, dict) else atlas.position)
    normal = np.asarray(atlas["normal"] if isinstance(atlas, dict) else atlas.normal)
    n = sh.num_coeffs(int(degree))
    on_ray = distributed.requested(ray)
    args = [(handle.description if on_ray else handle, position, normal, int(degree), i, int(spp), int(env_height),
             int(seed)) for i in range(n)]
    columns = distributed.map_blocks(_bake_function, args, ray=on_ray, desc=f"SH PRT bake (degree {degree})",
                                     progress=progress)
    return np.stack(columns, axis=1).astype(np.float32)


def _bake_function(scene, position, normal, degree: int, i: int, spp: int, env_height: int, seed: int) -> np.ndarray:
    """Transfer column i (T, 3): the indirect radiance at the texels under the positive part of
    Y_i minus that under its negative part (Sloan et al. 2002 §4; Mitsuba is several times less
    noisy with two positive emitters than with one signed one). ``scene``: a ``SceneHandle``, or
    a description (a Ray task builds its own)."""
    from jprt.render import lightmap
    from jprt.render.lights import EnvMap
    from jprt.render.scenes import SceneHandle

    handle = scene if isinstance(scene, SceneHandle) else SceneHandle(scene)
    h, w = int(env_height), 2 * int(env_height)
    y = np.asarray(sh.evaluate(equirect_directions(h, w).astype(np.float32), int(degree)), np.float32)[..., i]
    out = np.zeros((len(position), 3), np.float32)
    for sign in (1.0, -1.0):
        part = np.maximum(sign * y, 0.0)
        if part.max() <= 0:
            continue
        handle.set_lighting(EnvMap.create(np.repeat(part[..., None], 3, axis=-1)))
        out += sign * lightmap.indirect_at_points(handle, position, normal, spp=spp,
                                                  seed=seed * 7919 + 2 * i + (sign < 0))
    return out


def exit_directions(normal, n: int, seed: int) -> np.ndarray:
    """(G, n, 3) view directions about each unit ``normal`` (G, 3): a spherical Fibonacci set of
    ``n`` directions over the hemisphere (equal solid angle each, from the normal down to the
    horizon), turned about each normal by its own random angle (``seed``) so that neighbouring
    texels do not share their gaps."""
    normal = np.asarray(normal, np.float64).reshape(-1, 3)
    i = np.arange(int(n)) + 0.5
    z = 1.0 - i / int(n)
    phi = np.pi * (1.0 + np.sqrt(5.0)) * i
    r = np.sqrt(np.maximum(1.0 - z * z, 0.0))
    helper = np.where(np.abs(normal[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    t = np.cross(normal, helper)
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    b = np.cross(normal, t)
    spin = np.random.default_rng(int(seed)).uniform(0.0, 2.0 * np.pi, len(normal))[:, None]
    x, y = r[None] * np.cos(phi[None] + spin), r[None] * np.sin(phi[None] + spin)
    return x[..., None] * t[:, None] + y[..., None] * b[:, None] + z[None, :, None] * normal[:, None]


#: Ridge of the exit transfer's least-squares fit, relative to the number of directions: only
#: keeps the solve defined (the mirrored directions below make the fit a full-sphere one).
EXIT_RIDGE = 1e-6


def _exit_fit(directions: np.ndarray, normal: np.ndarray, radiance: np.ndarray, exit_degree: int) -> np.ndarray:
    """Least-squares SH coefficients (G, m, 3) of ``radiance`` (G, D, 3) along ``directions``
    (G, D, 3) over each point's hemisphere about ``normal`` (G, 3), extended to the whole sphere
    by its mirror image in the tangent plane. SH restricted to a hemisphere are nearly dependent
    (the Gram matrix's smallest eigenvalue is 1e-4 of its largest at order 4): a hemisphere-only
    fit may carry large combinations that vanish on it and blow up just below it, where a
    bilinear lookup between texels of different normals can evaluate it; the mirrored fit is
    bounded there (it returns the mirrored view's radiance)."""
    g, d = directions.shape[:2]
    normal = np.asarray(normal, np.float64).reshape(g, 1, 3)
    mirrored = directions - 2.0 * np.sum(directions * normal, axis=-1, keepdims=True) * normal
    both = np.concatenate([directions, mirrored], axis=1)
    y = np.asarray(sh.evaluate(both.reshape(-1, 3).astype(np.float32), int(exit_degree)),
                   np.float64).reshape(g, 2 * d, -1)
    gram = np.einsum("gdi,gdj->gij", y, y) + EXIT_RIDGE * 2 * d * np.eye(y.shape[-1])
    radiance = np.asarray(radiance, np.float64)
    return np.linalg.solve(gram, np.einsum("gdi,gdc->gic", y, np.concatenate([radiance, radiance], axis=1)))


def bake_exit(handle, position, normal, degree: int, exit_degree: int, *, n_directions: int, spp: int,
              env_height: int = 32, seed: int = 0, progress: bool | None = None,
              ray: bool | None = None) -> np.ndarray:
    """Exit transfer (G, (exit_degree + 1)^2, (degree + 1)^2, 3) of surface points (texels of a
    view-dependent material): under each white distant light Y_i, the indirect radiance leaving
    each point along ``n_directions`` directions over its hemisphere (``exit_directions``, ``spp``
    samples each, positive and negative parts of Y_i apart as ``bake``), fitted by least squares
    to SH of the view direction (Sloan et al. 2002 §5's glossy transfer, its exit form)."""
    from jprt import distributed

    position = np.asarray(position, np.float64).reshape(-1, 3)
    normal = np.asarray(normal, np.float64).reshape(-1, 3)
    directions = exit_directions(normal, int(n_directions), int(seed) * 7919 + 31)
    n = sh.num_coeffs(int(degree))
    on_ray = distributed.requested(ray)
    args = [(handle.description if on_ray else handle, position, normal, directions, int(degree), i, int(spp),
             int(env_height), int(seed)) for i in range(n)]
    radiance = distributed.map_blocks(_bake_exit_function, args, ray=on_ray,
                                      desc=f"SH PRT exit bake ({len(position)} texels x {int(n_directions)} views)",
                                      progress=progress)
    return np.stack([_exit_fit(directions, normal, r, int(exit_degree)) for r in radiance], axis=2).astype(np.float32)


def _bake_exit_function(scene, position, normal, directions, degree: int, i: int, spp: int, env_height: int,
                        seed: int) -> np.ndarray:
    """(G, D, 3): the indirect radiance leaving each point along each of its ``directions`` under
    Y_i's positive part minus that under its negative part."""
    from jprt.render import lightmap
    from jprt.render.images import indirect_rays
    from jprt.render.lights import EnvMap
    from jprt.render.scenes import SceneHandle

    handle = scene if isinstance(scene, SceneHandle) else SceneHandle(scene)
    h, w = int(env_height), 2 * int(env_height)
    y = np.asarray(sh.evaluate(equirect_directions(h, w).astype(np.float32), int(degree)), np.float32)[..., i]
    g, d = directions.shape[:2]
    # each ray starts ``ray_offset`` above the surface along its own direction (further out at
    # grazing ones) and is traced back onto the point
    cos = np.einsum("gdk,gk->gd", directions, normal)[..., None]
    reach = lightmap.ray_offset(handle) / np.maximum(cos, 0.05)
    origin = (position[:, None] + reach * directions).reshape(-1, 3)
    toward = -directions.reshape(-1, 3)
    out = np.zeros((g * d, 3), np.float32)
    for sign in (1.0, -1.0):
        part = np.maximum(sign * y, 0.0)
        if part.max() <= 0:
            continue
        handle.set_lighting(EnvMap.create(np.repeat(part[..., None], 3, axis=-1)))
        seed_i = seed * 7919 + 2 * i + (sign < 0) + 500_009
        out += sign * indirect_rays(handle, origin, toward, spp=spp, seed=seed_i).indirect
    return out.reshape(g, d, 3)


def make_dataset(scene=None, config: dict | None = None, *, cache_dir: str | None = None,
                 progress: bool | None = None, ray: bool | None = None) -> SHData:
    """Build the lightmap atlas of ``scene`` (default ``config['scene']``) and bake its transfer
    vectors up to ``sh.order``; cached under ``$JPRT_CACHE/sh_prt/<hash>.npz``. ``ray`` (default:
    whether ``JPRT_RAY_ADDRESS`` is set) bakes the SH functions as Ray tasks."""
    from jprt.render import lightmap
    from jprt.render.scenes import SceneHandle, describe

    cfg = resolve(DEFAULT_CONFIG, config)
    desc = describe(scene if scene is not None else cfg["scene"])
    degree = order_to_degree(cfg["sh"]["order"])
    n_check = int(cfg["sh"]["check_maps"])
    if n_check < 0:
        raise ValueError(f"sh.check_maps must be >= 0, got {n_check}")
    # the self-check's maps are an entry of their own (``_check``): the bake's key is what it was
    exit_keys = ("exit_order", "exit_directions", "exit_spp")
    spec = {"format": 1, "scene": desc, "objects": list(cfg["objects"]), "lightmap": cfg["lightmap"],
            "sh": {k: v for k, v in cfg["sh"].items() if k != "check_maps" and k not in exit_keys},
            "atlas_format": lightmap.ATLAS_FORMAT}

    def build() -> dict:
        t0 = time.perf_counter()
        handle = SceneHandle(desc)
        atlas = lightmap.build_atlas(handle, list(cfg["objects"]) or None,
                                     resolution=int(cfg["lightmap"]["resolution"]))._asdict()
        s = cfg["sh"]
        transfer = bake(handle, atlas, degree, spp=int(s["spp"]), env_height=int(s["env_height"]), seed=int(s["seed"]),
                        progress=progress, ray=ray)
        arrays = {f"atlas_{k}": np.asarray(v) for k, v in atlas.items()}
        arrays.update(transfer=transfer, bake_s=np.array(time.perf_counter() - t0))
        return arrays

    arrays, _ = cache.cached("sh_prt", spec, build, cache_dir=cache_dir)
    atlas = cache.unprefixed(arrays, "atlas_")
    meta = {"bake_s": float(arrays["bake_s"]), "degree": degree, "exit_degree": -1}
    exit_transfer, exit_texel = np.zeros((0, 1, 1, 3), np.float32), np.zeros(0, np.int32)
    exit_order = int(cfg["sh"]["exit_order"])
    if exit_order < 0:
        raise ValueError(f"sh.exit_order must be >= 0, got {exit_order}")
    if exit_order:
        exit_spec = {"format": 1, "bake": spec, **{k: int(cfg["sh"][k]) for k in exit_keys}}

        def build_exit() -> dict:
            from jprt.render.gbuffer import view_dependent_objects

            t0 = time.perf_counter()
            handle = SceneHandle(desc)
            texel = np.flatnonzero(np.isin(atlas["texel_object"], view_dependent_objects(handle))).astype(np.int32)
            m = sh.num_coeffs(order_to_degree(exit_order))
            out = np.zeros((0, m, sh.num_coeffs(degree), 3), np.float32)
            if texel.size:
                s = cfg["sh"]
                out = bake_exit(handle, atlas["position"][texel], atlas["normal"][texel], degree,
                                order_to_degree(exit_order), n_directions=int(s["exit_directions"]),
                                spp=int(s["exit_spp"]), env_height=int(s["env_height"]), seed=int(s["seed"]),
                                progress=progress, ray=ray)
            return {"exit_transfer": out, "exit_texel": texel, "bake_s": np.array(time.perf_counter() - t0)}

        exit_arrays, _ = cache.cached("sh_prt_exit", exit_spec, build_exit, cache_dir=cache_dir)
        exit_transfer, exit_texel = exit_arrays["exit_transfer"], exit_arrays["exit_texel"]
        meta.update(exit_degree=order_to_degree(exit_order), exit_bake_s=float(exit_arrays["bake_s"]))
    if n_check:
        meta["check"] = _check(desc, spec, atlas, n_check, cache_dir=cache_dir, progress=progress)
    from jprt.methods.lightmap_data import atlas_modulation

    return SHData(atlas, arrays["transfer"], meta, exit_transfer, exit_texel, atlas_modulation(desc, atlas))


#: Cube-map face size of the self-check's procedural maps.
CHECK_FACE = 16


def check_maps(n: int, seed: int) -> np.ndarray:
    """The self-check's held-out lightings: ``n`` procedural skies with one or two broad lobes
    (``jprt.sphere.envmap.synthetic_environments``, (n, 6, 16, 16, 3) cube maps), a
    seed stream of their own."""
    from jprt.sphere.envmap import synthetic_environments

    return np.asarray(synthetic_environments(int(n), CHECK_FACE, 45_000 + int(seed)), np.float32)


def _check(desc: dict, spec: dict, atlas: dict, n: int, *, cache_dir: str | None, progress: bool | None) -> dict:
    """The self-check's held-out set, cached apart from the bake (``$JPRT_CACHE/sh_prt_check``):
    the indirect light at every atlas texel under each of ``check_maps(n)``, rendered as the bake
    renders (``indirect_at_points`` at ``sh.spp``, other seeds), their cube maps and the scene's
    object names."""
    s = spec["sh"]

    def build() -> dict:
        from jprt.sphere.envmap import render_equirect
        from jprt.render import lightmap
        from jprt.render.lights import EnvMap
        from jprt.render.scenes import SceneHandle

        t0 = time.perf_counter()
        handle = SceneHandle(desc)
        cubes = check_maps(n, int(s["seed"]))
        indirect = []
        for k, cube in enumerate(cubes):
            handle.set_lighting(EnvMap.create(render_equirect(cube)))
            indirect.append(lightmap.indirect_at_points(handle, atlas["position"], atlas["normal"], spp=int(s["spp"]),
                                                        seed=int(s["seed"]) * 7919 + 100_003 + k))
        say("sh_prt", progress)(f"self-check set ({n} held-out map(s)) rendered in {time.perf_counter() - t0:.1f} s")
        return {"cubes": cubes, "indirect": np.stack(indirect).astype(np.float32),
                "object_names": np.array(handle.object_names())}

    arrays, _ = cache.cached("sh_prt_check", {"format": 1, "bake": spec, "maps": int(n), "face": CHECK_FACE}, build,
                             cache_dir=cache_dir)
    return arrays


def self_check(dataset: SHData, result, config: dict | None = None) -> dict:
    """The bake scored on ``sh.check_maps`` held-out procedural environment maps (``_check``): the
    lightmap sum_i l_i t_i (``model.lightmap``) of each map's SH projection at the bake's degree
    against the indirect light rendered at every texel, per object. The bake is the fit (a texel's
    training renders are its transfer vector itself), so there is no training error to compare
    with (``train_rel_rmse`` None): the check measures what the band limit and the bake's noise
    cost under a lighting the bake never saw. No Mitsuba."""
    from jprt.methods import selfcheck
    from jprt.methods.sh_prt.model import lightmap

    cfg = resolve(DEFAULT_CONFIG, config)
    check = dataset.meta.get("check")
    if check is None or not len(check["indirect"]):
        return selfcheck.result("sh_prt", {}, float("nan"), None,
                                "nothing held out (sh.check_maps = 0): no self-check")
    degree = int(dataset.meta["degree"])
    preds = [lightmap(result.params["transfer"], sh.project_cubemap(np.asarray(c, np.float32), degree))
             for c in check["cubes"]]
    ids = np.asarray(dataset.atlas["texel_object"])
    rel, per = selfcheck.scores(preds, list(check["indirect"]), ids, [str(x) for x in check["object_names"]])
    n = len(check["indirect"])
    return selfcheck.result("sh_prt", per, rel, None,
                            f"{n} held-out procedural environment map(s) at {len(ids)} lightmap texels, "
                            f"{int(cfg['sh']['spp'])} spp (sh.check_maps); no training error (the bake is the fit)")


# --------------------------------------------------------------------------------------------
# The shared tasks of experiments/atlas.py: how this method sees a task's camera view and lighting
# (a task lighting is ``PointLights`` for "point" tasks, a ``CubeMap`` for "environment" tasks)

#: The task lightings this method takes.
TASK_LIGHTINGS = ("point", "environment")


def task_inputs(handle, dataset: SHData, camera):
    """The atlas G-buffer (lightmap ``uv`` per pixel) of ``camera`` over the baked atlas."""
    from jprt.render import lightmap

    return lightmap.atlas_gbuffer(handle, lightmap.Atlas(**dataset.atlas), camera)


def task_lighting(handle, dataset: SHData, params, config, lighting):
    """``SHLighting`` of a task lighting at the bake's degree: a cube map projected with exact
    texel solid angles (``jprt.sphere.sh.project_cubemap``); local lights as deltas of their
    unoccluded irradiance seen from the atlas centre (the distant-lighting assumption of SH PRT,
    as in Belcour et al. 2022 §6.4)."""
    from jprt.inputs import CubeMap, SHLighting
    from jprt.methods.sh_prt.model import delta_light_coefficients
    from jprt.render import lightmap

    degree = int(dataset.meta["degree"])
    if isinstance(lighting, CubeMap):
        coefficients = np.asarray(sh.project_cubemap(np.asarray(lighting.radiance, np.float32), degree))
    else:
        center = np.asarray(dataset.atlas["position"]).mean(axis=0)
        coefficients = delta_light_coefficients(*lightmap.incident_delta_lights(handle, center, lighting), degree)
    return SHLighting(np.asarray(coefficients, np.float32))
