"""Training and test data of neural-wavelet PRT (Raghavan et al. 2023, §5), rendered with
Mitsuba through ``jprt.render`` and cached by ``jprt.cache``: training maps (files or procedural)
and their rotations as cube maps, cameras on a spherical spiral and a helix, every camera under
``data.envs_per_view`` maps; G-buffer, direct and indirect per image; near / far test views under
held-out maps only; the importance maps of the four pixel-sampling strategies."""

from __future__ import annotations

import os
import time

import numpy as np

from jprt import cache
from jprt.methods.base import resolve
from jprt.methods.wavelet_prt.model import DEFAULT_CONFIG, GBUFFER_FIELDS, WaveletData
from jprt.methods.wavelet_prt.views import camera_sets, importance_maps
from jprt.sphere import cubemap, haar
from jprt.sphere.envmap import (prepare_environment, random_rotation, render_equirect, rotate_equirect, sun_skies,
                                synthetic_environments, turn_equirect)

__all__ = ["make_dataset", "add_vertex_interpolation", "gbuffer_fields", "load_environments", "self_check",
           "SHARED_ENVMAPS", "TASK_LIGHTINGS", "task_inputs", "task_lighting"]

#: The CC0 maps in ../shared/assets/envmaps (see its README), next to this checkout.
SHARED_ENVMAPS = os.path.abspath(os.path.join(os.path.dirname(__file__), "..", "..", "..", "..", "shared", "assets",
                                              "envmaps"))


def _environment_sets(ecfg: dict, seed: int, n_images: int):
    """Training lightings (E, 6, n, n, 3) with names, held-out lightings with names.

    ``envmaps.lighting = "shared"``: every training map at every rotation of ``rotations_deg``
    (§5), each lighting ``n_images / E`` images. ``"per_image"``: ``n_images`` lightings, one per
    image: a training map turned about +Y by a uniform angle (or, with probability ``tilt``, by a
    uniformly random 3D rotation: ``random_rotation``, ``turn_equirect``), mirrored left-right with
    probability 1/2 when ``mirror``, or (with probability ``procedural_fraction``) a seeded
    procedural sky (``envmaps.procedural``: broad lobes, ``synthetic_environments``, or a clear
    sky with a one-texel sun, ``sun_skies``)."""
    n = int(ecfg["face_size"])
    haar.check_face_size(n)
    rotations = [float(r) for r in ecfg["rotations_deg"]] or [0.0]
    if int(ecfg["synthetic"]) > 0:
        maps = synthetic_environments(int(ecfg["synthetic"]) + 1, n, seed)
        train = [maps[i] for i in range(len(maps) - 1)]
        names = [f"synthetic_{i}" for i in range(len(train))]
        if ecfg["lighting"] == "per_image":
            pick = np.random.default_rng([seed, 11]).integers(0, len(train), n_images)
            return np.stack([train[i] for i in pick]), [names[i] for i in pick], maps[-1:], ["synthetic_held_out"]
        return np.stack(train), names, maps[-1:], ["synthetic_held_out"]
    folder = ecfg["folder"] or SHARED_ENVMAPS
    stems = sorted(os.path.splitext(f)[0] for f in os.listdir(folder) if f.lower().endswith((".hdr", ".exr"))) \
        if os.path.isdir(folder) else []
    held = list(ecfg["held_out"])
    train_stems = list(ecfg["train"]) or [s for s in stems if s not in held]
    overlap = set(train_stems) & set(held)
    if overlap:
        raise ValueError(f"maps {sorted(overlap)} are both training and held-out maps")
    normalise = bool(ecfg["normalise"])
    tests, _ = load_environments(held, [0.0], n, normalise=normalise, folder=folder)
    if ecfg["lighting"] == "shared":
        envs, names = load_environments(train_stems, rotations, n, normalise=normalise, folder=folder)
        return envs, names, tests, held
    if ecfg["lighting"] != "per_image":
        raise ValueError(f"unknown envmaps.lighting {ecfg['lighting']!r}: use 'shared' or 'per_image'")
    from jprt.render.lights import EnvMap

    if not train_stems:
        raise ValueError("envmaps.lighting='per_image' needs at least one training map")
    radiance = {s: EnvMap.from_file(_map_file(folder, s)).radiance for s in train_stems}
    rng = np.random.default_rng([seed, 11])
    frac = float(ecfg["procedural_fraction"])
    tilt = float(ecfg["tilt"])
    if not 0.0 <= tilt <= 1.0:
        raise ValueError(f"envmaps.tilt must be in [0, 1] (a fraction of the file maps), got {tilt}")
    procedural = rng.uniform(size=n_images) < frac
    n_synth = int(procedural.sum())
    kinds = {"lobes": synthetic_environments, "sun": sun_skies}
    if ecfg["procedural"] not in kinds:
        raise ValueError(f"unknown envmaps.procedural {ecfg['procedural']!r}: use one of {sorted(kinds)}")
    synth = iter(kinds[ecfg["procedural"]](n_synth, n, seed + 1) if n_synth else ())
    envs, names = [], []
    for i in range(n_images):
        if procedural[i]:
            envs.append(next(synth))
            names.append(f"procedural_{i}")
            continue
        stem = train_stems[int(rng.integers(len(train_stems)))]
        deg = float(rng.uniform(0.0, 360.0))
        flip = bool(ecfg["mirror"]) and bool(rng.uniform() < 0.5)
        e = radiance[stem][:, ::-1] if flip else radiance[stem]
        if tilt > 0 and rng.uniform() < tilt:  # drawn only with a tilt: tilt 0 keeps the earlier draws
            r = random_rotation(rng)
            e, turn = turn_equirect(e, r), f" turned {np.round(r, 3).tolist()}"
        else:
            e, turn = rotate_equirect(e, deg), f"@{deg:.1f}"
        envs.append(prepare_environment(e, n, normalise=normalise))
        names.append(f"{stem}{turn}{' mirrored' if flip else ''}")
    if frac > 0:  # procedural maps at the mean radiance of the files' (normalised: 1)
        envs = [e if not p else e / max(_mean_radiance(e), 1e-12) for e, p in zip(envs, procedural)]
    return np.stack(envs).astype(np.float32), names, tests, held


def _mean_radiance(cube) -> float:
    omega = np.asarray(cubemap.texel_solid_angles(np.asarray(cube).shape[1]))
    return float(np.sum(np.asarray(cube).mean(axis=-1) * omega) / (4.0 * np.pi))


def _map_file(folder: str, stem: str) -> str:
    for f in os.listdir(folder):
        if os.path.splitext(f)[0] == stem:
            return os.path.join(folder, f)
    raise FileNotFoundError(f"environment map {stem!r} not in {folder}")


def load_environments(stems, rotations, face_size: int, *, normalise: bool = True,
                      folder: str = "") -> tuple[np.ndarray, list[str]]:
    """The maps ``stems`` of ``folder`` (default ../shared/assets/envmaps), each at every rotation
    about +Y, as (E, 6, n, n, 3) cube maps (``prepare_environment``) and their names "stem@deg"."""
    from jprt.render.lights import EnvMap

    folder = folder or SHARED_ENVMAPS
    if not os.path.isdir(folder):
        raise FileNotFoundError(f"environment maps not found at {folder} (set envmaps.folder, or "
                                f"envmaps.synthetic > 0 for procedural maps)")
    files = {os.path.splitext(f)[0]: os.path.join(folder, f) for f in os.listdir(folder)}
    missing = [s for s in stems if s not in files]
    if missing:
        available = sorted(os.path.splitext(f)[0] for f in os.listdir(folder) if f.lower().endswith((".hdr", ".exr")))
        raise FileNotFoundError(f"environment maps {missing} not in {folder}; available: {available}")
    envs, names = [], []
    for stem in stems:
        radiance = EnvMap.from_file(files[stem]).radiance
        for r in rotations:
            envs.append(prepare_environment(rotate_equirect(radiance, float(r)), face_size, normalise=normalise))
            names.append(f"{stem}@{float(r):g}")
    return (np.stack(envs) if envs else np.zeros((0, 6, face_size, face_size, 3), np.float32)), names


def _render_view(handle, camera, cube, spp: int, seed: int, max_depth: int, rays: str):
    """(direct, indirect) of one view under one cube map: rendered over each pixel's footprint
    (``rays="image"``) or along the pixel-centre rays (``"centre"``, ``images.centre_rays``)."""
    from jprt.render import images
    from jprt.render.lights import EnvMap

    handle.set_lighting(EnvMap.create(render_equirect(cube)))
    render = images.centre_rays if rays == "centre" else images.direct_indirect
    r = render(handle, camera, spp=spp, seed=seed, max_depth=max_depth)
    return r.direct, r.indirect


def gbuffer_fields(handle, camera) -> dict:
    """The ``GBUFFER_FIELDS`` of a camera's exact pixel-centre G-buffer, as the model reads them."""
    from jprt.render.gbuffer import gbuffer

    g = gbuffer(handle, camera)
    return {k: np.asarray(getattr(g, k)) for k in GBUFFER_FIELDS}


def make_dataset(scene=None, config: dict | None = None, *, cache_dir: str | None = None,
                 progress: bool | None = None) -> WaveletData:
    """Render the training images (§5) and held-out near / far test views of ``scene``
    (default ``config['scene']``) lit by environment maps; cached by content hash under
    ``$JPRT_CACHE/wavelet_prt/<hash>.npz`` (checksummed, atomic).

    Each training camera is rendered under ``data.envs_per_view`` training environments, assigned
    so that every environment lights the same number V of images; each image has its G-buffer
    (exact pixel-centre rays), direct (Mitsuba ``max_depth=2``) and indirect (full minus direct,
    same seed) radiance, over each pixel's footprint or along its centre ray (``data.rays``).
    Test views are lit by held-out maps only and rendered at ``test_spp``.
    """
    from jprt.render.scenes import describe

    cfg = resolve(DEFAULT_CONFIG, config)
    desc = describe(scene if scene is not None else cfg["scene"])
    if desc.get("area_light") or desc.get("keep_emitters"):
        raise ValueError("wavelet PRT relights with environment maps only: use a scene without emitters of its own")
    ecfg, ccfg, dcfg = cfg["envmaps"], cfg["cameras"], cfg["data"]
    files_key = None
    if int(ecfg["synthetic"]) <= 0:
        folder = ecfg["folder"] or SHARED_ENVMAPS
        files_key = sorted((f, os.path.getsize(os.path.join(folder, f))) for f in os.listdir(folder)) \
            if os.path.isdir(folder) else None
    if dcfg["rays"] not in ("image", "centre"):
        raise ValueError(f"unknown data.rays {dcfg['rays']!r}: use 'image' (pixel footprints) or 'centre' "
                         "(pixel-centre rays)")
    # the default "image" is left out of the key, so datasets cached before the key existed stay valid
    spec = {"format": 1, "scene": desc, "envmaps": {k: v for k, v in ecfg.items() if k != "folder"},
            "files": files_key, "cameras": ccfg,
            "data": {k: v for k, v in dcfg.items() if not (k == "rays" and v == "image")}}
    arrays, _ = cache.cached("wavelet_prt", spec, lambda: _render(desc, cfg, progress), cache_dir=cache_dir)
    data = _unpack(arrays)
    return data._replace(stats=dict(data.stats, check=_test_objects(desc, cfg, spec, data, cache_dir=cache_dir)))


def _test_objects(desc: dict, cfg: dict, spec: dict, data: WaveletData, *, cache_dir: str | None) -> dict:
    """The object id of every pixel of the held-out near / far test images (their cameras' exact
    G-buffers, one per view, repeated per held-out map as the images are; -1 where invalid) and
    the scene's object names, for the self-check's per-object scores: a G-buffer pass per test
    view, cached apart from the images (``$JPRT_CACHE/wavelet_prt_check``)."""
    def build() -> dict:
        from jprt.render.cameras import look_at
        from jprt.render.gbuffer import gbuffer
        from jprt.render.scenes import SceneHandle

        ccfg, dcfg = cfg["cameras"], cfg["data"]
        _, near_o, far_o, target, fov = _cameras(desc, ccfg, int(dcfg["seed"]))
        handle = SceneHandle(desc)
        repeat = len(data.test_envs) if dcfg["test_pairs"] == "all" else 1
        out = {"object_names": np.array(handle.object_names())}
        for name, origins in (("near", near_o), ("far", far_o)):
            ids = [gbuffer(handle, look_at(o, target, fov=fov, width=int(ccfg["width"]),
                                           height=int(ccfg["height"]))).object_id for o in origins]
            out[f"{name}_object_id"] = (np.repeat(np.stack(ids), repeat, axis=0).astype(np.int32) if ids
                                        else np.zeros((0, int(ccfg["height"]), int(ccfg["width"])), np.int32))
        return out

    arrays, _ = cache.cached("wavelet_prt_check", {"format": 1, "data": spec}, build, cache_dir=cache_dir)
    return arrays


#: Training images scored for the self-check's training error (one view of evenly spaced lightings).
CHECK_TRAIN = 8


def self_check(dataset: WaveletData, result, config: dict | None = None) -> dict:
    """The fit scored on the held-out near and far test views (``cameras.near`` / ``far``) under
    the held-out maps (``envmaps.held_out``, never in training; rendered at ``data.test_spp``): the
    evaluator's image of each against its rendered indirect light, per object (``_test_objects``).
    The training error the same way, pooled, on up to ``CHECK_TRAIN`` training images (the first
    view of evenly spaced training lightings) under their own maps. No Mitsuba."""
    from jprt.inputs import CubeMap
    from jprt.methods import selfcheck
    from jprt.methods.wavelet_prt.model import evaluator, model

    cfg = resolve(DEFAULT_CONFIG, config)
    check = dataset.stats.get("check")
    if check is None:
        return selfcheck.result("wavelet_prt", {}, float("nan"), None,
                                "no held-out object ids (a dataset not from make_dataset): no self-check")
    fields = model(cfg, n_vertices=dataset.stats.get("n_vertices")).fields
    evaluate = evaluator(result.params, cfg)
    preds, refs, ids, maps = [], [], [], set()
    for name in ("near", "far"):
        views = dataset.tests.get(name) or {}
        for i in range(len(views.get("valid", ()))):
            inputs = {f: views[f][i] for f in fields}
            preds.append(np.asarray(evaluate(inputs, CubeMap(np.asarray(dataset.test_envs[int(views["env"][i])])))))
            refs.append(np.asarray(views["indirect"][i]))
            ids.append(np.where(np.asarray(views["valid"][i], bool), check[f"{name}_object_id"][i], -1))
            maps.add(int(views["env"][i]))
    n_env = len(dataset.envs)
    lightings = np.unique(np.linspace(0, n_env - 1, min(CHECK_TRAIN, n_env)).round().astype(int))
    train_p, train_r, train_ids = [], [], []
    for e in lightings:
        inputs = {f: dataset.train[f][e, 0] for f in fields}
        train_p.append(np.asarray(evaluate(inputs, CubeMap(np.asarray(dataset.envs[e])))))
        train_r.append(np.asarray(dataset.train["indirect"][e, 0]))
        train_ids.append(np.where(np.asarray(dataset.train["valid"][e, 0], bool), 0, -1))
    train, _ = selfcheck.scores(train_p, train_r, train_ids, ["all"])
    if not preds:
        return selfcheck.result("wavelet_prt", {}, float("nan"), train,
                                "nothing held out (cameras.near = cameras.far = 0): no self-check")
    rel, per = selfcheck.scores(preds, refs, ids, [str(x) for x in check["object_names"]])
    h, w = preds[0].shape[:2]
    return selfcheck.result(
        "wavelet_prt", per, rel, train,
        f"{len(preds)} held-out (near / far view, held-out map) images ({len(maps)} map(s)), {h} x {w} pixels, "
        f"{int(dataset.stats['test_spp'])} spp (cameras.near / far, envmaps.held_out); training error on "
        f"{len(train_p)} training images")


def _render(desc: dict, cfg: dict, progress: bool | None) -> dict:
    from jprt.progress import bar as progress_bar
    from jprt.render.cameras import look_at
    from jprt.render.scenes import SceneHandle

    ecfg, ccfg, dcfg = cfg["envmaps"], cfg["cameras"], cfg["data"]
    seed = int(dcfg["seed"])
    t0 = time.perf_counter()
    train_o, near_o, far_o, target, fov = _cameras(desc, ccfg, seed)
    per_view = int(dcfg["envs_per_view"])
    n_img = len(train_o) * per_view
    envs, names, test_envs, test_names = _environment_sets(ecfg, seed, n_img)
    n_env = len(envs)
    if n_img % n_env:
        raise ValueError(f"{len(train_o)} training cameras x {per_view} environments each = {n_img} images do not "
                         f"split evenly over {n_env} environments: change cameras.sphere.n / cameras.helix.n")
    rng = np.random.default_rng(seed)
    # image j (of camera j // per_view) gets environment perm[j] % n_env: every environment equally often
    assign = rng.permutation(n_img) % n_env
    cam_kw = {"fov": fov, "width": int(ccfg["width"]), "height": int(ccfg["height"])}
    handle = SceneHandle(desc)
    spp, max_depth = int(dcfg["spp"]), int(dcfg["max_depth"])
    groups: list[list[dict]] = [[] for _ in range(n_env)]
    if dcfg["test_pairs"] not in ("cycle", "all"):
        raise ValueError(f"unknown data.test_pairs {dcfg['test_pairs']!r}: use 'cycle' or 'all'")
    n_test = (len(near_o) + len(far_o)) * (len(test_envs) if dcfg["test_pairs"] == "all" else 1)
    bar = progress_bar(total=n_img + n_test, progress=progress, desc="wavelet PRT images")
    for c, origin in enumerate(train_o):
        cam = look_at(origin, target, **cam_kw)
        g = gbuffer_fields(handle, cam)
        for j in range(per_view):
            e = int(assign[c * per_view + j])
            direct, indirect = _render_view(handle, cam, envs[e], spp, seed * 100003 + c * per_view + j, max_depth,
                                            dcfg["rays"])
            groups[e].append(dict(g, direct=direct, indirect=indirect))
            bar.update(1)
    train = {k: np.stack([np.stack([img[k] for img in grp]) for grp in groups])
             for k in list(GBUFFER_FIELDS) + ["direct", "indirect"]}
    mu = float(cfg["train"]["mu"])
    if train["valid"].shape[1] > 1:  # each lighting lights several views: §5's per-lighting maps
        importance = np.stack([importance_maps(train["indirect"][e], train["position"][e], train["valid"][e],
                                               train["specular_albedo"][e], train["roughness"][e], mu=mu)
                               for e in range(n_env)])
    else:  # one view per lighting: the view variance is taken over all images, then split per image
        flat = {k: train[k][:, 0] for k in ("indirect", "position", "valid", "specular_albedo", "roughness")}
        imp = importance_maps(flat["indirect"], flat["position"], flat["valid"], flat["specular_albedo"],
                              flat["roughness"], mu=mu).reshape(4, n_env, -1).transpose(1, 0, 2)
        imp = imp.astype(np.float64)
        imp = np.where(imp.sum(-1, keepdims=True) > 0, imp, flat["valid"].reshape(n_env, 1, -1))
        importance = (imp / np.maximum(imp.sum(-1, keepdims=True), 1e-30)).astype(np.float32)
    t_train = time.perf_counter() - t0
    tests = {}
    for name, origins in (("near", near_o), ("far", far_o)):
        views = []
        for i, origin in enumerate(origins):
            cam = look_at(origin, target, **cam_kw)
            g = gbuffer_fields(handle, cam)
            # "cycle": view i under held-out map i mod count; "all": every view under every held-out map
            lightings = range(len(test_envs)) if dcfg["test_pairs"] == "all" else [i % max(len(test_envs), 1)]
            for e in lightings:
                direct, indirect = _render_view(handle, cam, test_envs[e], int(dcfg["test_spp"]),
                                                seed * 7 + 1000003 + i + (0 if name == "near" else 5003)
                                                + 100 * e * (dcfg["test_pairs"] == "all"), max_depth,
                                                dcfg["rays"])
                views.append(dict(g, direct=direct, indirect=indirect, env=np.int32(e)))
                bar.update(1)
        tests[name] = {k: np.stack([v[k] for v in views]) for k in views[0]} if views else {}
    bar.close()
    arrays = {f"train_{k}": v for k, v in train.items()}
    for name, t in tests.items():
        arrays.update({f"{name}_{k}": v for k, v in t.items()})
    arrays.update(importance=importance, envs=envs, test_envs=test_envs, env_names=np.array(names),
                  test_env_names=np.array(test_names), cam_train=train_o, cam_near=near_o, cam_far=far_o,
                  render_train_s=np.array(t_train), render_s=np.array(time.perf_counter() - t0),
                  spp=np.array(spp), test_spp=np.array(int(dcfg["test_spp"])))
    return arrays


def _cameras(desc: dict, ccfg: dict, seed: int):
    """(training, near, far origins, target, fov): the orbits of ``camera_sets`` about
    ``cameras.target``, or, when it is None, views from the scene itself
    (``jprt.render.sampling.scene_regions``: about a scene file's own camera, looking where it
    looks, at its field of view; ``sphere.n + helix.n`` training views, ``near`` and ``far``
    held-out views, each set Latin-hypercube sampled in the region's box with its own seed)."""
    if ccfg["target"] is not None:
        train_o, near_o, far_o = camera_sets(ccfg, seed)
        return train_o, near_o, far_o, tuple(ccfg["target"]), float(ccfg["fov"])
    from jprt.render.sampling import latin_hypercube, scene_regions

    regions = scene_regions(desc)
    counts = (int(ccfg["sphere"]["n"]) + int(ccfg["helix"]["n"]), int(ccfg["near"]), int(ccfg["far"]))
    sets = [latin_hypercube(np.random.default_rng([seed, 11, i]), n, regions["view_lo"], regions["view_hi"])
            if n else np.zeros((0, 3)) for i, n in enumerate(counts)]
    return sets[0], sets[1], sets[2], tuple(regions["view_target"]), float(regions["fov"])


def _unpack(a: dict) -> WaveletData:
    fields = list(GBUFFER_FIELDS) + ["direct", "indirect"]
    tests = {name: {k: a[f"{name}_{k}"] for k in fields + ["env"] if f"{name}_{k}" in a} for name in ("near", "far")}
    return WaveletData(
        train={k: a[f"train_{k}"] for k in fields}, importance=a["importance"], envs=a["envs"], tests=tests,
        test_envs=a["test_envs"], env_names=[str(s) for s in a["env_names"]],
        test_env_names=[str(s) for s in a["test_env_names"]],
        cameras={"train": a["cam_train"], "near": a["cam_near"], "far": a["cam_far"]},
        stats={"render_train_s": float(a["render_train_s"]), "render_s": float(a["render_s"]),
               "spp": int(a["spp"]), "test_spp": int(a["test_spp"])})




def add_vertex_interpolation(data: WaveletData, scene, edge: float = 0.1) -> WaveletData:
    """``data`` with the VERTEX_FIELDS of every training and test pixel
    (``jprt.render.lightmap.vertex_interpolation`` on ``scene``); ``stats["n_vertices"]``."""
    from jprt.render.lightmap import vertex_interpolation
    from jprt.render.scenes import SceneHandle

    handle = SceneHandle(scene)
    _, _, verts = vertex_interpolation(handle, np.zeros((1, 3)), edge=edge)

    def add(arrays: dict) -> dict:
        if not arrays:
            return arrays
        idx, w, _ = vertex_interpolation(handle, arrays["position"], edge=edge)
        return dict(arrays, vertex_index=idx, vertex_weight=w)

    return data._replace(train=add(data.train), tests={k: add(v) for k, v in data.tests.items()},
                         stats=dict(data.stats, n_vertices=int(len(verts))))


# --------------------------------------------------------------------------------------------
# The shared tasks of experiments/atlas.py: how this method sees a task's camera view and lighting
# (a task lighting is ``PointLights`` for "point" tasks, a ``CubeMap`` for "environment" tasks)

#: The task lightings this method takes.
TASK_LIGHTINGS = ("environment",)


def task_inputs(handle, dataset: WaveletData, camera) -> dict:
    """The ``GBUFFER_FIELDS`` of ``camera`` (``gbuffer_fields``)."""
    return gbuffer_fields(handle, camera)


def task_lighting(handle, dataset: WaveletData, params, config, lighting):
    """A cube map is the method's own lighting (Algorithm 1 takes its top-K Haar wavelets)."""
    return lighting
