"""Training data of Radiance Regression Functions (Ren et al. 2013, Appendix A), rendered with
Mitsuba through ``jprt.render`` and cached by ``jprt.cache``.

N_l light positions and N_v viewpoints by Latin hypercube sampling in user boxes (in a scene
file's own light box, with ``data.light_spread`` "even", lights spread evenly over its free space
instead); N_r random
primary rays per (light, view) pair; attributes at the first hit and the path-traced indirect
radiance (full minus direct, same seed). Option, not in the paper: with ``data.oversample`` > 1
the N_r rays are drawn from oversample x N_r uniform screen rays, balanced over the surfaces they
hit (``_balanced``), so that faces seen at grazing angles are in the training data too (the
``demo`` preset of experiments/rrf_cornell.py; at the ``small`` sizes uniform rays reach those
faces and were more accurate: benchmarks/results/rrf_cornell.json, ``sampling_ablation``). With
``data.min_face_rays`` > 0 every face that 16 x N_r candidate rays hit gets that many rays first
and the rest stay uniform (``_face_floor``).
Material mode (Appendix B): one viewpoint, the edited object's roughness and albedo drawn by
Latin hypercube sampling instead of views.
"""

from __future__ import annotations

import copy
import time

import numpy as np

from jprt import cache
from jprt.hashing import stable_hash
from jprt.methods.base import resolve
from jprt.methods.rrf.model import DEFAULT_CONFIG, RRFData, brdf_vector
from jprt.progress import say
from jprt.render.sampling import CORNELL_REGIONS, REGION_KEYS, free_lights, scene_regions  # noqa: F401 (re-exported)

__all__ = ["make_dataset", "edit_description", "scene_regions", "resolve_regions", "REGION_KEYS", "CORNELL_REGIONS",
           "self_check", "TASK_LIGHTINGS", "task_inputs", "task_lighting"]


def edit_description(desc: dict, obj: str, roughness: float, albedo: float) -> dict:
    """A copy of scene description ``desc`` with object ``obj``'s roughness and albedo edited (Appendix B)."""
    desc = copy.deepcopy(desc)
    material = dict(desc["materials"][obj])
    if "roughness" in material or material["type"] in ("glossy", "metal"):
        material["roughness"] = float(roughness)
    key = "specular" if material["type"] == "metal" else "albedo"
    material[key] = [float(albedo)] * 3
    desc["materials"][obj] = material
    return desc


def make_dataset(scene, config: dict | None = None, *, cache_dir: str | None = None,
                 progress: bool | None = None) -> RRFData:
    """Render the RRF training samples of ``scene`` (Appendix A), cached by content hash.

    ``config`` is an RRF config (``DEFAULT_CONFIG`` layout, strict); only ``data`` matters here.
    The cache entry ``$JPRT_CACHE/rrf/<hash>.npz`` is reused when the scene description and the
    ``data`` section are unchanged.
    """
    from jprt.render.sampling import check_box
    from jprt.render.scenes import describe

    data_cfg = resolve(DEFAULT_CONFIG, config)["data"]
    desc = describe(scene)
    if desc.get("area_light") or desc.get("keep_emitters"):
        raise ValueError("RRF training needs a scene without emitters of its own (area_light=False, or "
                         "keep_emitters=False for XML): Eq. 9 is linear in the point lights only")
    mode = data_cfg["mode"]
    if mode not in ("view", "material"):
        raise ValueError(f"data.mode must be 'view' or 'material', got {mode!r}")
    data_cfg = resolve_regions(data_cfg, desc)
    check_box(data_cfg["light_lo"], data_cfg["light_hi"], "data.light_lo/light_hi")
    for key in ("n_lights", "n_views", "n_rays", "spp"):
        if int(data_cfg[key]) <= 0:
            raise ValueError(f"data.{key} must be positive, got {data_cfg[key]}")
    if data_cfg["light_spread"] not in ("even", "latin"):
        raise ValueError(f"data.light_spread must be 'even' or 'latin', got {data_cfg['light_spread']!r}")
    if int(data_cfg["check_lights"]) < 0:
        raise ValueError(f"data.check_lights must be >= 0, got {data_cfg['check_lights']}")
    if int(data_cfg["min_face_rays"]) > 0 and (int(data_cfg["oversample"]) > 1 or int(data_cfg["min_object_rays"]) > 0):
        raise ValueError("data.min_face_rays keeps the other rays uniform: it cannot be combined with "
                         "data.oversample > 1 or data.min_object_rays")
    # the regions as numbers (the cache key of the built-in boxes' data is what it was before None
    # meant "from the scene"); where they came from travels beside the spec, not in it
    regions_from = data_cfg.pop("regions_from")
    # the self-check's held-out lights are an entry of their own (``_check``): not in this key
    spec = {"format": 2, "scene": desc, "data": {k: v for k, v in data_cfg.items()
                                                 if k not in ("val_fraction", "check_lights")}}
    for key in ("min_object_rays", "min_face_rays"):  # newer keys: unset, the cache key is the old one
        if not int(data_cfg[key]):
            spec["data"].pop(key)
    # light_spread changes the data only for "even" in a box from the scene's bounds: elsewhere it
    # is left out of the key, which stays what it was before the option
    if regions_from != "scene bounds" or data_cfg["light_spread"] == "latin":
        spec["data"].pop("light_spread")
    if mode == "view":
        spec["data"].pop("material")
    if regions_from == "scene bounds":  # lights drawn by free_lights or even_lights: their rules are the data's
        from jprt.render.sampling import EVEN_RULE, LIGHT_RULE

        spec["light_rule"] = LIGHT_RULE
        if data_cfg["light_spread"] == "even":
            spec["even_rule"] = EVEN_RULE

    def build() -> dict:
        t0 = time.perf_counter()
        lights, setups, rng = _draw(desc, data_cfg, regions_from)
        arrays = _render_samples(desc, setups, lights, data_cfg, rng, progress)
        say("rrf", progress)(f"rendered {len(arrays['position'])} samples in {time.perf_counter() - t0:.1f} s")
        return arrays

    arrays, _ = cache.cached("rrf", spec, build, cache_dir=cache_dir)
    meta = _meta(spec, arrays, regions_from)
    if int(data_cfg["check_lights"]):
        meta["check"] = _check(desc, spec, data_cfg, regions_from, cache_dir=cache_dir, progress=progress)
    return RRFData(**arrays, meta=meta)


def _draw(desc: dict, data_cfg: dict, regions_from: str, *, spread: bool = True):
    """The training lights (Latin hypercube in the light box; for scene bounds the hypercube's
    lights moved off geometry, ``free_lights``, and with ``data.light_spread`` "even" replaced by
    lights spread evenly over that free space, ``even_lights``, drawn from a stream of their own
    so the views and rays are those of "latin"), the (scene, camera, edit) setups (views, or
    materials in material mode) and the generator the rays are drawn from next, in the order the
    training data draws them. For "even" the ``free_lights`` draw only advances the generator, so
    where it finds too little free space (``NoFreeSpace``) "even" goes on with its own larger
    pool; ``spread=False`` skips ``even_lights`` for a caller that wants only the setups (the
    lights returned are then "latin"'s, or the raw hypercube where ``free_lights`` gave up: not
    for use)."""
    from jprt.render import cameras as cams
    from jprt.render.sampling import NoFreeSpace, check_box, even_lights, latin_hypercube

    rng = np.random.default_rng(int(data_cfg["seed"]))
    lights = latin_hypercube(rng, data_cfg["n_lights"], data_cfg["light_lo"], data_cfg["light_hi"])
    if regions_from == "scene bounds":  # no light inside geometry or touching it
        even = data_cfg["light_spread"] == "even"
        try:
            lights = free_lights(desc, lights, data_cfg["light_lo"], data_cfg["light_hi"], rng)
        except NoFreeSpace:
            if not even:
                raise
        if even and spread:  # a stream of their own: the views and rays stay the draw's
            lights = even_lights(desc, data_cfg["n_lights"], data_cfg["light_lo"], data_cfg["light_hi"],
                                 np.random.default_rng([int(data_cfg["seed"]), 46]))
    if data_cfg["mode"] == "view":
        check_box(data_cfg["view_lo"], data_cfg["view_hi"], "data.view_lo/view_hi")
        origins = latin_hypercube(rng, data_cfg["n_views"], data_cfg["view_lo"], data_cfg["view_hi"])
        targets = np.asarray(data_cfg["view_target"]) + data_cfg["target_jitter"] * (
            2.0 * rng.random((len(origins), 3)) - 1.0)
        setups = [(desc, cams.look_at(o, t, fov=data_cfg["fov"]), None) for o, t in zip(origins, targets)]
    else:
        mat = data_cfg["material"]
        if mat["object"] not in desc.get("materials", {}):
            raise ValueError(f"data.material.object {mat['object']!r} is not an object of this scene "
                             f"({sorted(desc.get('materials', {}))})")
        edits = latin_hypercube(rng, mat["n_materials"], [mat["roughness"][0], mat["albedo"][0]],
                                [mat["roughness"][1], mat["albedo"][1]])
        camera = cams.look_at(mat["view_origin"], data_cfg["view_target"], fov=data_cfg["fov"])
        setups = [(edit_description(desc, mat["object"], r, a), camera, (r, a)) for r, a in edits]
    return lights, setups, rng


def _check(desc: dict, spec: dict, data_cfg: dict, regions_from: str, *, cache_dir: str | None,
           progress: bool | None) -> dict:
    """The self-check's held-out samples, cached apart from the training data
    (``$JPRT_CACHE/rrf_check``): ``data.check_lights`` point lights drawn in the light box from a
    seed stream of their own (never fitted), each rendered from every training view (or material)
    as the training pairs are (``_render_samples``: fresh random rays, ``n_rays / 2`` per pair,
    ``data.spp``, other path seeds); the sample arrays, ``lights`` (L, 3) and the scene's object
    names. For a box from a scene's bounds the lights are moved off geometry as the training
    draw's are (``free_lights``); with "even", where that gives up, they are drawn uniformly over
    the same space from a larger pool (``uniform_free_lights``), as the training lights go on."""
    from jprt.render.sampling import NoFreeSpace, latin_hypercube, uniform_free_lights
    from jprt.render.scenes import SceneHandle

    n = int(data_cfg["check_lights"])
    seed = int(data_cfg["seed"])

    def build() -> dict:
        t0 = time.perf_counter()
        _, setups, _ = _draw(desc, data_cfg, regions_from, spread=False)
        rng = np.random.default_rng([seed, 45])
        lights = latin_hypercube(rng, n, data_cfg["light_lo"], data_cfg["light_hi"])
        if regions_from == "scene bounds":
            try:
                lights = free_lights(desc, lights, data_cfg["light_lo"], data_cfg["light_hi"], rng)
            except NoFreeSpace:
                if data_cfg["light_spread"] != "even":
                    raise
                lights = uniform_free_lights(desc, n, data_cfg["light_lo"], data_cfg["light_hi"], rng)
        cfg = {**data_cfg, "n_rays": max(1, int(data_cfg["n_rays"]) // 2), "seed": seed + 104_729}
        arrays = _render_samples(desc, setups, lights, cfg, rng, False)
        say("rrf", progress)(f"self-check set ({n} held-out lights, {len(arrays['position'])} samples) rendered in "
                             f"{time.perf_counter() - t0:.1f} s")
        return {**arrays, "lights": np.asarray(lights, np.float32),
                "object_names": np.array(SceneHandle(desc).object_names())}

    arrays, _ = cache.cached("rrf_check", {"format": 1, "data": spec, "regions_from": regions_from, "check_lights": n},
                             build, cache_dir=cache_dir)
    return arrays


def self_check(dataset: RRFData, result, config: dict | None = None) -> dict:
    """The fit scored on held-out lights (``_check``: ``data.check_lights`` point lights never
    fitted, from every training view or material): the evaluator (Eq. 9, one unit white light) at
    each held-out light's ray samples against their rendered indirect radiance, per object; one
    item per light (per (material, light) pair in material mode). The training error the same way
    on the fitted samples (the training split, ``data.val_fraction``) of up to as many training
    lights (at least 2). No Mitsuba."""
    from jprt.inputs import GBuffer, PointLights
    from jprt.methods import selfcheck
    from jprt.methods.rrf.model import EditInputs, evaluator, split_samples

    cfg = resolve(DEFAULT_CONFIG, config)
    check = dataset.meta.get("check")
    if check is None or not len(check["lights"]):
        return selfcheck.result("rrf", {}, float("nan"), None,
                                "nothing held out (data.check_lights = 0): no self-check")
    material = cfg["data"]["mode"] == "material"
    names = [str(x) for x in check["object_names"]]
    n_check = len(check["lights"])
    held_key = check["pair"] if material else check["pair"] % n_check
    held = [np.flatnonzero(held_key == g) for g in np.unique(held_key)]
    train = dataset._asdict()
    is_train = result.info.get("is_train")
    if is_train is None or len(is_train) != len(dataset):  # train.subset < 1 fits a subset: the split it drew from
        is_train = split_samples(len(dataset), float(cfg["data"]["val_fraction"]), int(cfg["train"]["seed"]))
    is_train = np.asarray(is_train, bool)
    train_key = dataset.pair if material else dataset.pair % int(cfg["data"]["n_lights"])
    keys = np.unique(train_key[is_train])
    keys = keys[np.unique(np.linspace(0, len(keys) - 1, min(len(keys), max(2, len(held)))).round().astype(int))]
    fitted = [np.flatnonzero((train_key == g) & is_train) for g in keys]
    size = max(len(g) for g in held + fitted)  # one shape: the evaluator compiles once
    evaluate = evaluator(result.params, cfg)

    def items(arrays, groups):
        preds, refs, ids = [], [], []
        for g in groups:
            def pad(name, fill=0):
                a = np.asarray(arrays[name])[g]
                return np.concatenate([a, np.full((size - len(g),) + a.shape[1:], fill, a.dtype)])

            brdf = pad("brdf")[:, None]
            valid = np.arange(size) < len(g)
            gb = GBuffer(position=pad("position")[:, None], normal=pad("normal")[:, None], view=pad("view")[:, None],
                         reflected=np.zeros((size, 1, 3), np.float32), uv=np.zeros((size, 1, 2), np.float32),
                         diffuse_albedo=brdf[..., 0:3], specular_albedo=brdf[..., 3:6], roughness=brdf[..., 6],
                         object_id=pad("object_id", -1)[:, None], valid=valid[:, None])
            light = PointLights(position=np.asarray(arrays["light"][g[0]], np.float32)[None],
                                intensity=np.ones((1, 3), np.float32))
            inputs = EditInputs(gb, np.asarray(arrays["edit"][g[0]], np.float32)) if material else gb
            preds.append(np.asarray(evaluate(inputs, light))[:, 0])
            refs.append(pad("indirect"))
            ids.append(pad("object_id", -1))
        return preds, refs, ids

    rel, per = selfcheck.scores(*items(check, held), names)
    train_rel, _ = selfcheck.scores(*items(train, fitted), names)
    setups = len(np.unique(check["pair"] // n_check))
    return selfcheck.result(
        "rrf", per, rel, train_rel,
        f"{n_check} held-out point lights x {setups} {'materials' if material else 'views'}: "
        f"{sum(len(g) for g in held)} ray samples, {int(cfg['data']['spp'])} spp (data.check_lights); training "
        f"error on the fitted samples of {len(fitted)} training {'pairs' if material else 'lights'}")


def resolve_regions(data_cfg: dict, scene) -> dict:
    """``data_cfg`` (an RRF config's ``data`` section) with the regions it leaves None filled in
    from ``scene_regions(scene)``, and ``regions_from``: "config" when it sets all of them, else
    the regions' source ("cornell" or "scene bounds")."""
    def number(v):
        return float(v) if np.ndim(v) == 0 else [float(x) for x in v]

    if all(data_cfg[k] is not None for k in REGION_KEYS):
        return {**data_cfg, **{k: number(data_cfg[k]) for k in REGION_KEYS}, "regions_from": "config"}
    regions = scene_regions(scene)
    return {**data_cfg, **{k: number(regions[k] if data_cfg[k] is None else data_cfg[k]) for k in REGION_KEYS},
            "regions_from": regions["source"]}


def _meta(spec: dict, arrays: dict, regions_from: str = "config") -> dict:
    data = spec["data"]
    return {"light_lo": list(map(float, data["light_lo"])), "light_hi": list(map(float, data["light_hi"])),
            "regions": {**{k: data[k] for k in REGION_KEYS if data.get(k) is not None},
                        "source": regions_from},
            "spp": int(data["spp"]), "mode": data["mode"], "scene": spec["scene"], "hash": stable_hash(spec),
            "material_object": data.get("material", {}).get("object")}


def _faces(gb, idx):
    """Face group of candidate rays ``idx``: object x 6 + signed dominant normal axis."""
    normal = np.asarray(gb.normal)[idx]
    axis = np.argmax(np.abs(normal), axis=1)
    side = np.take_along_axis(normal, axis[:, None], axis=1)[:, 0] > 0
    return np.asarray(gb.object_id)[idx] * 6 + axis * 2 + side


def _floor_first(valid, group, floor: int, n: int, rng):
    """Up to ``floor`` of the candidates ``valid`` of every ``group`` (uniformly within each), in
    random order, at most ``n`` in all: the rays a floor draws before the rest."""
    first = np.concatenate([rng.choice(valid[group == g], size=min(int(floor), int((group == g).sum())), replace=False)
                            for g in np.unique(group)])
    return first[rng.permutation(len(first))[:n]]


def _face_floor(gb, origins, directions, n: int, rng, floor: int):
    """``n`` of the candidate rays: up to ``floor`` rays of every face group the candidates hit
    (``_faces``), drawn first, the rest uniformly among the other candidates that hit the scene,
    so that outside the floor the rays stay uniform over the screen."""
    valid = np.flatnonzero(np.asarray(gb.valid))
    if len(valid) <= n:
        return origins[valid], directions[valid]
    first = _floor_first(valid, _faces(gb, valid), floor, n, rng)
    rest = np.setdiff1d(valid, first)
    keep = np.sort(np.concatenate([first, rng.choice(rest, size=n - len(first), replace=False)]))
    return origins[keep], directions[keep]


def _balanced(gb, origins, directions, n: int, rng, floor: int = 0):
    """``n`` of the candidate rays (origins, directions), drawn without replacement with weights
    1 / sqrt(candidates hitting the same object with the same signed dominant normal axis).
    Every surface a view sees gets samples, however small it is on screen: a face seen at a
    grazing angle that uniform screen rays miss leaves its leaf's network without a single sample
    of its normal, which the renderer then extrapolates (the black line along the top edge of the
    tall box in ``make demo``). Large surfaces keep more than an equal share: weights 1 / count
    starved the walls (demo RMSE 0.0288 against 0.0255 with 1 / sqrt, measured before the
    ``jprt.nn.ranges`` fix). Rays that miss the scene are never drawn. With ``floor``, up to
    ``floor`` rays of every object the candidates hit are drawn first (uniformly among that
    object's candidates), the rest as above: a small or distant object that a view sees gets
    samples rather than one ray or none."""
    valid = np.flatnonzero(np.asarray(gb.valid))
    if len(valid) <= n:
        keep = valid
    else:
        first = np.zeros(0, np.int64)
        if floor > 0:
            first = _floor_first(valid, np.asarray(gb.object_id)[valid], floor, n, rng)
        rest = np.setdiff1d(valid, first)
        group = _faces(gb, rest)
        _, inverse, counts = np.unique(group, return_inverse=True, return_counts=True)
        w = 1.0 / np.sqrt(counts[inverse])
        keep = np.sort(np.concatenate([first, rng.choice(rest, size=n - len(first), replace=False, p=w / w.sum())]))
    return origins[keep], directions[keep]


def _gbuffers(handle, batches) -> list:
    """``gbuffer_rays`` of each (origins, directions) batch, traced as one batch (a G-buffer reads
    each shape's material once per call: in a file of many meshes, one call per light cost
    seconds each)."""
    from jprt.render.gbuffer import gbuffer_rays

    g = gbuffer_rays(handle, np.concatenate([o for o, _ in batches]), np.concatenate([d for _, d in batches]))
    ends = np.cumsum([len(o) for o, _ in batches])
    return [type(g)(*(a[e - len(o):e] for a in g)) for (o, _), e in zip(batches, ends)]


def _render_samples(base_desc, setups, lights, data_cfg, rng, progress) -> dict:
    from jprt.progress import bar as progress_bar
    from jprt.render import cameras as cams
    from jprt.render.gbuffer import gbuffer_rays
    from jprt.render.images import indirect_rays
    from jprt.render.lights import PointLights
    from jprt.render.scenes import SceneHandle

    n_rays, spp, seed = int(data_cfg["n_rays"]), int(data_cfg["spp"]), int(data_cfg["seed"])
    over, floor = int(data_cfg["oversample"]), int(data_cfg.get("min_object_rays", 0))
    face_floor = int(data_cfg.get("min_face_rays", 0))
    if floor > 0 and over == 1:  # a floor needs candidates to choose from
        over = 4
    if face_floor > 0:
        over = 16
    base = SceneHandle(base_desc, PointLights.create([lights[0]], [1.0, 1.0, 1.0]))
    # The same rays for each setup's G-buffer pass; fresh random rays for every (light, setup) pair.
    rays = [[cams.random_rays(cam, n_rays * over, rng) for _ in lights] for _, cam, _ in setups]
    if face_floor > 0:  # every face the candidates see first, the rest uniform
        rays = [[_face_floor(g, o, d, n_rays, rng, face_floor)
                 for (o, d), g in zip(per_setup, _gbuffers(base, per_setup))] for per_setup in rays]
    elif over > 1:  # keep n_rays of the candidates, balanced over the surfaces they hit
        rays = [[_balanced(g, o, d, n_rays, rng, floor)
                 for (o, d), g in zip(per_setup, _gbuffers(base, per_setup))] for per_setup in rays]
    out: dict[str, list] = {k: [] for k in ("position", "view", "light", "normal", "brdf", "edit", "object_id",
                                            "direct", "indirect", "pair")}
    bar = progress_bar(total=len(setups) * len(lights), progress=progress, desc="rrf samples", unit="pair", leave=False)
    for s, (desc, _, edit) in enumerate(setups):
        handle = base if edit is None else SceneHandle(desc, PointLights.create([lights[0]], [1.0, 1.0, 1.0]))
        o = np.concatenate([r[0] for r in rays[s]])
        d = np.concatenate([r[1] for r in rays[s]])
        ends = np.cumsum([len(r[0]) for r in rays[s]])
        gb = gbuffer_rays(handle, o, d)
        gb_attr = gb if edit is None else gbuffer_rays(base, o, d)  # material mode: a from the base scene
        brdf = brdf_vector(gb_attr.diffuse_albedo, gb_attr.specular_albedo, gb_attr.roughness)
        for li, light in enumerate(lights):
            sl = slice(ends[li] - len(rays[s][li][0]), ends[li])
            keep = gb.valid[sl]
            handle.set_lighting(PointLights.create([light], [1.0, 1.0, 1.0]))
            rad = indirect_rays(handle, o[sl][keep], d[sl][keep], spp=spp, seed=seed * 100003 + s * 1009 + li)
            out["position"].append(gb.position[sl][keep])
            out["view"].append(gb.view[sl][keep])
            out["normal"].append(gb.normal[sl][keep])
            out["brdf"].append(brdf[sl][keep])
            out["object_id"].append(gb.object_id[sl][keep])
            out["light"].append(np.broadcast_to(light, (int(keep.sum()), 3)))
            out["edit"].append(np.broadcast_to(np.asarray(edit if edit is not None else [], np.float32),
                                               (int(keep.sum()), 0 if edit is None else 2)))
            out["direct"].append(rad.direct)
            out["indirect"].append(rad.indirect)
            out["pair"].append(np.full(int(keep.sum()), s * len(lights) + li, np.int32))
            bar.update(1)
    bar.close()
    arrays = {k: np.concatenate(v).astype(np.int32 if k in ("object_id", "pair") else np.float32)
              for k, v in out.items()}
    if len(arrays["position"]) == 0:
        raise ValueError("no training ray hit the scene: check data.view_lo/view_hi and view_target")
    return arrays


# --------------------------------------------------------------------------------------------
# The shared tasks of experiments/atlas.py: how this method sees a task's camera view and lighting
# (a task lighting is ``PointLights`` for "point" tasks, a ``CubeMap`` for "environment" tasks)

#: The task lightings this method takes.
TASK_LIGHTINGS = ("point",)


def task_inputs(handle, dataset, camera):
    """The exact pixel-centre ``GBuffer`` of ``camera`` in the scene of ``handle``."""
    from jprt.render.gbuffer import gbuffer

    return gbuffer(handle, camera)


def task_lighting(handle, dataset, params, config, lighting):
    """Point lights are RRF's own lighting (Eq. 9 sums one network output per light)."""
    return lighting
