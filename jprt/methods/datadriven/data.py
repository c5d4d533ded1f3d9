"""Training and held-out examples of data-driven PRT (Belcour et al. 2022, §4.1), rendered with
Mitsuba through ``jprt.render`` and cached by ``jprt.cache``: N random configurations of one
lighting scenario (spot lights), direct radiance at dense surface candidates (one shadow ray per
light) and indirect lightmap texels (full minus direct, equal seeds)."""

from __future__ import annotations

import time

import numpy as np

from jprt import cache
from jprt.hashing import stable_hash
from jprt.methods.base import resolve
from jprt.methods.datadriven.model import DEFAULT_CONFIG, DDData
from jprt.progress import say

__all__ = ["make_dataset", "random_lights", "render_examples", "self_check", "TASK_LIGHTINGS", "task_inputs",
           "task_lighting"]


def random_lights(rng: np.random.Generator, n: int, lights_cfg: dict, accept=None) -> list:
    """``n`` random lighting configurations of the scenario in ``lights_cfg``, one light each:
    ``kind="spot"`` (the paper's §4.1 scenario: position and target uniform in their boxes, cone
    angle uniform in ``cutoff_deg``) or ``kind="point"`` (an isotropic point light, position
    uniform in its box; the RRF task of experiments/atlas.py); intensity uniform in
    ``intensity`` times a random colour of saturation ``saturation``.
    ``accept(position) -> bool`` rejects positions (inside objects, touching walls)."""
    from jprt.render.lights import PointLights, SpotLights
    from jprt.render.sampling import check_box

    kind = lights_cfg["kind"]
    if kind not in ("spot", "point"):
        raise ValueError(f"lights.kind {kind!r}: the built-in scenarios are 'spot' and 'point' (other kinds are "
                         "evaluation-only, see experiments/datadriven.py)")
    plo, phi = check_box(lights_cfg["position_lo"], lights_cfg["position_hi"], "lights.position")
    tlo, thi = check_box(lights_cfg["target_lo"], lights_cfg["target_hi"], "lights.target")
    out = []
    for _ in range(int(n)):
        for _attempt in range(1000):
            pos = plo + (phi - plo) * rng.random(3)
            if accept is None or accept(pos):
                break
        else:
            raise ValueError(f"no acceptable {kind}-light position in lights.position_lo/hi after 1000 tries "
                             "(inside objects or closer than lights.clearance to a surface)")
        if kind == "spot":
            tgt = tlo + (thi - tlo) * rng.random(3)
            while np.linalg.norm(tgt - pos) < 1e-3:
                tgt = tlo + (thi - tlo) * rng.random(3)
            cutoff = rng.uniform(*lights_cfg["cutoff_deg"])
        colour = (1.0 - lights_cfg["saturation"]) + lights_cfg["saturation"] * rng.random(3)
        colour /= colour.max()
        power = rng.uniform(*lights_cfg["intensity"]) * colour
        out.append(SpotLights.create(pos, tgt, power, cutoff) if kind == "spot" else PointLights.create(pos, power))
    return out


def render_examples(handle, atlas, candidates, lightings, *, spp: int, seed: int = 0, first: int = 0,
                    progress: bool | None = None, desc: str = "examples") -> tuple[np.ndarray, np.ndarray]:
    """Direct at every candidate point (exact, one shadow ray per light) and indirect lightmap
    texels (``spp`` paths, full minus direct with equal seeds) for each lighting: (N, S, 3) and
    (N, T, 3). Lighting ``k`` is path traced with seed ``seed * 100003 + first + k`` (``first``:
    the index of ``lightings[0]`` in the whole set, so blocks of it render what the set does)."""
    from jprt.progress import bar as progress_bar
    from jprt.render import lightmap

    direct, indirect = [], []
    for k, lighting in enumerate(progress_bar(lightings, progress=progress, desc=desc)):
        direct.append(lightmap.direct_at_points(handle, lighting, candidates["position"], candidates["normal"]))
        indirect.append(lightmap.indirect_at_points(handle, atlas["position"], atlas["normal"], spp=spp,
                                                    seed=seed * 100003 + first + k))
    return np.stack(direct), np.stack(indirect)


#: Lighting configurations per Ray task when the examples are rendered on Ray.
BLOCK = 8


def _examples_block(desc: dict, atlas: dict, candidates: dict, lightings: list, spp: int, seed: int,
                    first: int) -> tuple[np.ndarray, np.ndarray]:
    """``render_examples`` of one block of lightings in a fresh scene (a Ray task)."""
    from jprt.render.scenes import SceneHandle

    return render_examples(SceneHandle(desc), atlas, candidates, lightings, spp=spp, seed=seed, first=first,
                           progress=False)


def _examples(handle, atlas, candidates, lightings, *, spp: int, seed: int, progress: bool | None, desc: str,
              ray: bool | None):
    """``render_examples`` of every lighting: in this process, or in blocks of ``BLOCK`` as Ray
    tasks (``jprt.distributed``; the same seeds, so the same arrays)."""
    from jprt import distributed

    if not distributed.requested(ray) or not lightings:
        return render_examples(handle, atlas, candidates, lightings, spp=spp, seed=seed, progress=progress, desc=desc)
    args = [(handle.description, atlas, candidates, lightings[i:i + BLOCK], spp, seed, i)
            for i in range(0, len(lightings), BLOCK)]
    blocks = distributed.map_blocks(_examples_block, args, ray=True, desc=f"{desc} (Ray)", progress=progress)
    return np.concatenate([b[0] for b in blocks]), np.concatenate([b[1] for b in blocks])


def make_dataset(scene=None, config: dict | None = None, *, cache_dir: str | None = None,
                 progress: bool | None = None, ray: bool | None = None) -> DDData:
    """Render the training and held-out examples of ``scene`` (default: ``config['scene']``),
    cached by content hash under ``$JPRT_CACHE/datadriven/<hash>.npz`` (checksummed, atomic).
    ``ray`` (default: whether ``JPRT_RAY_ADDRESS`` is set) renders the configurations in blocks
    as Ray tasks; the entry is the same either way."""
    from jprt.render.scenes import describe

    cfg = resolve(DEFAULT_CONFIG, config)
    desc = describe(scene if scene is not None else cfg["scene"])
    if desc.get("area_light") or desc.get("keep_emitters"):
        raise ValueError("the data-driven scenario supplies the lights: use a scene without emitters of its own "
                         "(area_light=False, or keep_emitters=False for XML)")
    from jprt.render.lightmap import ATLAS_FORMAT

    dcfg = cfg["data"]
    for key in ("n_train", "n_test", "spp", "test_spp"):
        if int(dcfg[key]) < (0 if key == "n_test" else 1):
            raise ValueError(f"data.{key} must be positive, got {dcfg[key]}")
    spec = {"format": 1, "scene": desc, "objects": list(cfg["objects"]), "lightmap": cfg["lightmap"],
            "atlas_format": ATLAS_FORMAT,
            "candidates": cfg["points"]["candidates"], "seed_points": cfg["points"]["seed"],
            "point_objects": list(cfg["points"]["objects"]), "lights": cfg["lights"],
            "data": dcfg}
    if desc.get("name") == "xml":  # a file's lights must light its camera's view (sampling.free_lights' rule)
        from jprt.render.sampling import LIGHT_RULE

        spec["light_rule"] = LIGHT_RULE

    def build() -> dict:
        return _render(desc, cfg, progress, ray)

    arrays, path = cache.cached("datadriven", spec, build, cache_dir=cache_dir)
    from jprt.methods.lightmap_data import atlas_modulation

    data = _unpack(arrays, spec, path)
    return data._replace(modulation=atlas_modulation(desc, data.atlas))


def _render(desc: dict, cfg: dict, progress: bool | None, ray: bool | None = None) -> dict:
    from jprt.render import lightmap
    from jprt.render.sampling import serves_view, view_points
    from jprt.render.scenes import SceneHandle

    dcfg = cfg["data"]
    t0 = time.perf_counter()
    rng = np.random.default_rng(int(dcfg["seed"]))
    handle = SceneHandle(desc)

    view = view_points(handle)  # None for a scene without a camera of its own

    def accept(position):
        return bool(lightmap.free_positions(handle, position, clearance=float(cfg["lights"]["clearance"]))[0]
                    and serves_view(handle, position, view)[0])

    train = random_lights(rng, dcfg["n_train"], cfg["lights"], accept)
    # held-out lights from their own stream: the same test set for any n_train
    test = random_lights(np.random.default_rng([int(dcfg["seed"]), 1]), dcfg["n_test"], cfg["lights"], accept)
    objects = list(cfg["objects"]) or None
    atlas = lightmap.build_atlas(handle, objects, resolution=int(cfg["lightmap"]["resolution"]))._asdict()
    cands = lightmap.surface_samples(handle, int(cfg["points"]["candidates"]),
                                     objects=list(cfg["points"]["objects"]) or objects,
                                     seed=int(cfg["points"]["seed"]))._asdict()
    d, i = _examples(handle, atlas, cands, train, spp=int(dcfg["spp"]), seed=int(dcfg["seed"]), progress=progress,
                     desc="train configurations", ray=ray)
    t_train = time.perf_counter() - t0
    if test:
        dt, it = _examples(handle, atlas, cands, test, spp=int(dcfg["test_spp"]), seed=int(dcfg["seed"]) + 1,
                           progress=progress, desc="held-out configurations", ray=ray)
    else:
        dt, it = np.zeros((0,) + d.shape[1:], np.float32), np.zeros((0,) + i.shape[1:], np.float32)
    arrays = {f"atlas_{k}": np.asarray(v) for k, v in atlas.items()}
    arrays.update({f"cand_{k}": np.asarray(v) for k, v in cands.items()})
    arrays.update(direct=d, indirect=i, direct_test=dt, indirect_test=it,
                  object_names=np.array(handle.object_names()), render_train_s=np.array(t_train),
                  render_s=np.array(time.perf_counter() - t0))
    for name, ls in (("lights", train), ("lights_test", test)):
        for field in ("position", "target", "intensity", "cutoff_deg", "beam_deg"):
            if not ls or hasattr(ls[0], field):  # point lights have no target or cone
                arrays[f"{name}_{field}"] = np.stack([getattr(l, field)[0] for l in ls]) if ls else np.zeros((0,))
    say("datadriven", progress)(f"rendered {len(train)} + {len(test)} configurations in "
                                f"{time.perf_counter() - t0:.1f} s")
    return arrays


def _unpack(arrays: dict, spec: dict, path: str) -> DDData:
    meta = {"scene": spec["scene"], "object_names": [str(s) for s in arrays["object_names"]],
            "render_s": float(arrays["render_s"]), "render_train_s": float(arrays["render_train_s"]),
            "cache": path, "spec_hash": stable_hash(spec)}
    return DDData(atlas=cache.unprefixed(arrays, "atlas_"), candidates=cache.unprefixed(arrays, "cand_"),
                  direct=arrays["direct"], indirect=arrays["indirect"], direct_test=arrays["direct_test"],
                  indirect_test=arrays["indirect_test"],
                  lights=cache.unprefixed(arrays, "lights_", exclude="lights_test_"),
                  lights_test=cache.unprefixed(arrays, "lights_test_"), meta=meta)


# --------------------------------------------------------------------------------------------
# Self-check (``jprt.methods.selfcheck``)

#: Training configurations scored for the self-check's training error (evenly spaced, at most).
CHECK_TRAIN = 32


def self_check(dataset: DDData, result, config: dict | None = None) -> dict:
    """The fit scored on the dataset's held-out configurations (``data.n_test`` lights drawn from
    their own stream, never fitted): the lightmap (``model.lightmap``) of each one's direct radiance
    at the fine measurement points against its rendered indirect lightmap (``data.test_spp``), per
    object (the atlas texels' objects); the training error the same way on up to ``CHECK_TRAIN``
    training configurations. No Mitsuba."""
    from jprt.methods import selfcheck
    from jprt.methods.datadriven.model import lightmap

    cfg = resolve(DEFAULT_CONFIG, config)
    names = list(dataset.meta["object_names"])
    ids = np.asarray(dataset.atlas["texel_object"])
    fine = np.asarray(result.params["fine_index"])
    n_test, texels = len(dataset.indirect_test), int(ids.shape[0])
    kind = cfg["lights"]["kind"]

    def score(direct, indirect):
        pred = np.asarray(lightmap(result.params, np.asarray(direct)[:, fine], cfg))
        return selfcheck.scores(list(pred), list(np.asarray(indirect)), ids, names)

    pick = np.unique(np.linspace(0, len(dataset.indirect) - 1, min(CHECK_TRAIN, len(dataset.indirect))).round()
                     .astype(int))
    train, _ = score(dataset.direct[pick], dataset.indirect[pick])
    if not n_test:
        return selfcheck.result("datadriven", {}, float("nan"), train,
                                "nothing held out (data.n_test = 0): no self-check")
    rel, per = score(dataset.direct_test, dataset.indirect_test)
    return selfcheck.result("datadriven", per, rel, train,
                            f"{n_test} held-out {kind}-light configurations at {texels} lightmap texels, "
                            f"{int(cfg['data']['test_spp'])} spp (data.n_test, data.test_spp); training error on "
                            f"{len(pick)} training configurations")


# --------------------------------------------------------------------------------------------
# The shared tasks of experiments/atlas.py: how this method sees a task's camera view and lighting
# (a task lighting is ``PointLights`` for "point" tasks, a ``CubeMap`` for "environment" tasks)

#: The task lightings this method takes.
TASK_LIGHTINGS = ("point",)


def task_inputs(handle, dataset: DDData, camera):
    """The atlas G-buffer (lightmap ``uv`` per pixel) of ``camera`` over the dataset's atlas."""
    from jprt.render import lightmap

    return lightmap.atlas_gbuffer(handle, lightmap.Atlas(**dataset.atlas), camera)


def task_lighting(handle, dataset: DDData, params, config, lighting):
    """§4.3 at run time: the direct radiance of ``lighting`` at the fine measurement points
    (Mitsuba, one shadow ray per light, as in training: ``lightmap.direct_at_points``), a
    ``PointRadiance``."""
    from jprt.inputs import PointRadiance
    from jprt.render import lightmap

    fine = np.asarray(params["fine_index"])
    direct = lightmap.direct_at_points(handle, lighting, np.asarray(dataset.candidates["position"])[fine],
                                       np.asarray(dataset.candidates["normal"])[fine])
    return PointRadiance(np.asarray(direct, np.float32))
