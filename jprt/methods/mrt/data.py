"""Held-out lightings of a block layout for Modular Radiance Transfer, rendered with Mitsuba
through ``jprt.render`` and cached by ``jprt.cache``: point lights inside random blocks, the
direct radiance at every texel centre (one shadow ray per light: exact) and the indirect
radiance there (full minus direct, equal seeds). MRT itself trains on nothing scene-specific
(its dictionary is analytic, ``model.dictionary``), so every lighting and every layout here is
held out."""

from __future__ import annotations

import time

import numpy as np

from jprt import cache, layouts
from jprt.hashing import stable_hash
from jprt.methods.base import resolve
from jprt.methods.mrt.model import DEFAULT_CONFIG, MRTData
from jprt.progress import say

__all__ = ["make_dataset", "block_frame", "texel_geometry", "random_lights", "render_texels", "TASK_LIGHTINGS",
           "task_inputs", "task_lighting"]


def block_frame(desc: dict, cfg: dict) -> tuple[dict, np.ndarray, float, float]:
    """Where the blocks are: (layout dict, world origin of cell (0, 0)'s corner, block size, inset
    fraction of the faces). A ``blocks`` scene is its own proxy; any other scene needs
    ``proxy.layout`` (§6.2: the coarse blocks an author maps onto the scene)."""
    from jprt.render.scenes import BLOCK_INSET

    proxy = cfg["proxy"]
    if desc["name"] == "blocks":
        if proxy["layout"] is not None:
            raise ValueError("a 'blocks' scene is its own proxy: leave proxy.layout null")
        return desc["layout"], np.zeros(3), float(desc["size"]), BLOCK_INSET
    if proxy["layout"] is None:
        raise ValueError(f"MRT maps a {desc['name']!r} scene onto blocks: set proxy.layout (a jprt.layouts layout, "
                         "e.g. {'cells': [[0, 0]], 'edges': [], 'exterior': [[[0, 0], 1]]} for the Cornell box), "
                         "proxy.origin and proxy.size")
    if not float(proxy["size"]) > 0:
        raise ValueError(f"proxy.size must be positive, got {proxy['size']}")
    return layouts.layout_from_dict(proxy["layout"]).as_dict(), np.asarray(proxy["origin"], np.float64), \
        float(proxy["size"]), 0.0


def texel_geometry(desc: dict, t: int, cfg: dict | None = None, handle=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """World positions (on the faces the scene builds, inset for ``blocks``), inward normals and
    albedo of every texel of the scene's blocks: (B, n, 3) each. A ``blocks`` scene's albedo
    comes from its description; a proxied scene's is read from its BSDFs where each texel's
    ray meets the scene (``handle`` needed), 0 on missing faces."""
    cfg = resolve(DEFAULT_CONFIG, cfg)
    layout, origin, size, inset = block_frame(desc, cfg)
    lay = layouts.layout_from_dict(layout)
    pos, normal, face = layouts.texel_centres(t)
    shrink = 1.0 - 2.0 * inset
    p = np.stack([origin + (np.array([b.cell[0], 0.0, b.cell[1]]) + 0.5 + shrink * (pos - 0.5)) * size
                  for b in lay.blocks])
    n = np.broadcast_to(normal, p.shape).copy()
    if desc["name"] == "blocks":
        return p, n, layouts.texel_albedo(lay, t, desc["albedo"])
    from jprt.render.gbuffer import gbuffer_rays

    g = gbuffer_rays(handle, (p + 1e-3 * size * n).reshape(-1, 3), -n.reshape(-1, 3))
    albedo = np.where(np.asarray(g.valid).reshape(-1, 1), np.asarray(g.diffuse_albedo).reshape(-1, 3), 0.0)
    present = np.stack([~np.isin(face, [2 + k for k in b.open_sides]) for b in lay.blocks])
    return p, n, albedo.reshape(p.shape) * present[..., None]


def random_lights(rng: np.random.Generator, desc: dict, n: int, lights_cfg: dict, cfg: dict | None = None,
                  accept=None) -> list:
    """``n`` lightings of ``lights_cfg["count"]`` point lights, each in a block drawn uniformly,
    at least ``clearance`` (in block units) from its faces (and, with ``accept(position) ->
    bool``, in free space); intensity uniform in ``intensity`` (W/sr, max channel) times a random
    colour of saturation ``saturation``."""
    from jprt.inputs import PointLights

    layout, origin, size, _ = block_frame(desc, resolve(DEFAULT_CONFIG, cfg))
    lay = layouts.layout_from_dict(layout)
    c = float(lights_cfg["clearance"])
    if not 0 <= c < 0.5:
        raise ValueError(f"lights.clearance is a fraction of a block in [0, 0.5), got {c}")
    out = []
    for _ in range(int(n)):
        pos, power = [], []
        for _k in range(int(lights_cfg["count"])):
            for _attempt in range(1000):
                cell = lay.cells[rng.integers(len(lay.cells))]
                p = origin + (np.array([cell[0], 0.0, cell[1]]) + c + (1 - 2 * c) * rng.random(3)) * size
                if accept is None or accept(p):
                    break
            else:
                raise ValueError("no free light position in the blocks after 1000 tries")
            pos.append(p)
            colour = (1.0 - lights_cfg["saturation"]) + lights_cfg["saturation"] * rng.random(3)
            power.append(rng.uniform(*lights_cfg["intensity"]) * colour / colour.max())
        out.append(PointLights.create(np.array(pos), np.array(power)))
    return out


def render_texels(handle, positions, normals, lightings, *, spp: int, seed: int, progress: bool | None = None,
                  desc: str = "lightings") -> tuple[np.ndarray, np.ndarray]:
    """Direct (exact) and indirect (``spp``) outgoing radiance at the texels for each lighting:
    (N, B, n, 3) each. Lighting k uses seed ``seed * 100003 + k``."""
    from jprt.progress import bar as progress_bar
    from jprt.render import lightmap

    p, nrm = positions.reshape(-1, 3), normals.reshape(-1, 3)
    direct, indirect = [], []
    for k, lighting in enumerate(progress_bar(lightings, progress=progress, desc=desc)):
        direct.append(lightmap.direct_at_points(handle, lighting, p, nrm).reshape(positions.shape))
        indirect.append(lightmap.indirect_at_points(handle, p, nrm, spp=spp, seed=seed * 100003 + k)
                        .reshape(positions.shape))
    shape = (0,) + positions.shape
    return (np.stack(direct) if direct else np.zeros(shape, np.float32),
            np.stack(indirect) if indirect else np.zeros(shape, np.float32))


def make_dataset(scene=None, config: dict | None = None, *, cache_dir: str | None = None,
                 progress: bool | None = None) -> MRTData:
    """Render ``data.n_test`` held-out lightings of a ``blocks`` scene (default:
    ``config['scene']``) at its texels, cached under ``$JPRT_CACHE/mrt/<hash>.npz``."""
    from jprt.render.scenes import describe

    cfg = resolve(DEFAULT_CONFIG, config)
    desc = describe(scene if scene is not None else cfg["scene"])
    block_frame(desc, cfg)  # a clear error before any rendering
    if desc["name"] != "blocks" and (desc.get("area_light") or desc.get("keep_emitters")):
        raise ValueError("MRT's lightings are jprt point lights: use a scene without emitters of its own")
    dcfg = cfg["data"]
    if int(dcfg["n_test"]) < 1 or int(dcfg["test_spp"]) < 1:
        raise ValueError(f"data.n_test and data.test_spp must be positive, got {dcfg['n_test']}, {dcfg['test_spp']}")
    t = int(cfg["dictionary"]["texels"])
    spec = {"format": 1, "scene": desc, "texels": t, "lights": cfg["lights"], "data": dcfg}
    if desc["name"] != "blocks":
        spec["proxy"] = cfg["proxy"]

    def build() -> dict:
        from jprt.render.scenes import SceneHandle

        from jprt.render import lightmap

        t0 = time.perf_counter()
        handle = SceneHandle(desc)
        pos, nrm, alb = texel_geometry(desc, t, cfg, handle)
        accept = None if desc["name"] == "blocks" else (
            lambda p: bool(lightmap.free_positions(handle, p, clearance=0.05 * block_frame(desc, cfg)[2])[0]))
        lights = random_lights(np.random.default_rng([int(dcfg["seed"]), 7]), desc, int(dcfg["n_test"]), cfg["lights"],
                               cfg, accept)
        d, i = render_texels(handle, pos, nrm, lights, spp=int(dcfg["test_spp"]), seed=int(dcfg["seed"]),
                             progress=progress, desc="held-out lightings")
        say("mrt", progress)(f"rendered {len(lights)} lightings at {pos.shape[0] * pos.shape[1]} texels in "
                             f"{time.perf_counter() - t0:.1f} s")
        return {"positions": pos, "normals": nrm, "albedo": alb, "direct_test": d.astype(np.float32),
                "indirect_test": i.astype(np.float32),
                "lights_test_position": np.stack([l.position for l in lights]),
                "lights_test_intensity": np.stack([l.intensity for l in lights]),
                "render_s": np.array(time.perf_counter() - t0)}

    arrays, path = cache.cached("mrt", spec, build, cache_dir=cache_dir)
    meta = {"scene": desc, "render_s": float(arrays["render_s"]), "cache": path, "spec_hash": stable_hash(spec),
            "config": cfg}
    return MRTData(layout=block_frame(desc, cfg)[0], albedo=arrays["albedo"], positions=arrays["positions"],
                   normals=arrays["normals"], direct_test=arrays["direct_test"], indirect_test=arrays["indirect_test"],
                   lights_test=cache.unprefixed(arrays, "lights_test_"), meta=meta)


# --------------------------------------------------------------------------------------------
# The shared tasks of experiments/atlas.py (the Cornell box as one block, its front open)

#: The task lightings this method takes.
TASK_LIGHTINGS = ("point",)


def task_inputs(handle, dataset: MRTData, camera):
    """The camera's G-buffer with ``uv`` in the lightmap atlas (``block_atlas.proxy_uv``: each
    pixel on the face of its block that faces its way) and ``valid`` where a pixel maps to a
    block."""
    from jprt.methods.mrt.block_atlas import proxy_uv
    from jprt.render.gbuffer import gbuffer

    cfg = dataset.meta["config"]
    layout, origin, size, _ = block_frame(dataset.meta["scene"], cfg)
    g = gbuffer(handle, camera)
    uv, ok = proxy_uv(g.position, g.normal, layout, origin, size, int(cfg["dictionary"]["texels"]))
    return g._replace(uv=uv, valid=np.asarray(g.valid, bool) & ok)


def task_lighting(handle, dataset: MRTData, params, config, lighting):
    """§7.3 step 1: Mitsuba's direct light of ``lighting`` at every texel (exact, one light at a
    time: ``lightmap.direct_at_points``), a ``PointRadiance``."""
    from jprt.inputs import PointRadiance
    from jprt.render import lightmap

    direct = lightmap.direct_at_points(handle, lighting, dataset.positions.reshape(-1, 3),
                                       dataset.normals.reshape(-1, 3))
    return PointRadiance(np.asarray(direct, np.float32))
