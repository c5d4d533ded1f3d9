"""Content-addressed, resumable, checksummed datasets of Mitsuba renders.

A dataset is (scene, cameras, lightings, render settings, seed). Its stable hash names a folder
``$JPRT_CACHE/datasets/<hash>/`` (``JPRT_CACHE`` defaults to ``~/.cache/jprt``) holding

  spec.json                the description that was hashed
  lighting_LLLLL.npz       each lighting (so the dataset reopens without the caller's objects)
  gbuffer_VVVVV.npz        each camera's exact pixel-centre G-buffer
  item_LLLLL_VVVVV.npz     direct and indirect radiance of one (lighting, camera) pair
  <entry>.sha256           checksum of the entry, written after the entry itself

Every file is written atomically. An entry counts as present only when its checksum file exists
and matches its bytes, so a render stopped by Ctrl-C resumes at the first missing entry, and a
truncated or corrupt file is detected, reported and re-rendered, never used.
"""

from __future__ import annotations

import json
import os
import sys
import warnings
from typing import Any, Callable, NamedTuple, Sequence

import numpy as np

from jprt.hashing import stable_hash
from jprt.cache import cache_root, entry_state, load_npz, save_npz
from jprt.io import write_json
from jprt.render import cameras as cams
from jprt.render.lights import EnvMap, Lighting, PointLights, lighting_description, validate_lighting

__all__ = ["Dataset", "render_dataset", "open_dataset", "from_config", "cameras_from_config",
           "lightings_from_config", "DEFAULT_DATASET_CONFIG"]

FORMAT_VERSION = 1


class Item(NamedTuple):
    """One rendered pair: indices into the dataset's lightings and cameras."""

    lighting: int
    camera: int


class Dataset:
    """A rendered dataset on disk. Arrays are loaded lazily and verified by checksum.

    Attributes:
      folder: the content-addressed folder.
      spec: the hashed description (scene, cameras, lightings, settings).
      items: list of ``Item(lighting, camera)`` in render order.
      stats: {"rendered": entries rendered by this call, "cached": reused, "corrupt": re-rendered}.
    """

    def __init__(self, folder: str, spec: dict, stats: dict | None = None):
        self.folder = folder
        self.spec = spec
        self.items = [Item(*it) for it in spec["items"]]
        self.stats = dict(stats or {})

    def __len__(self) -> int:
        return len(self.items)

    @property
    def cameras(self) -> list[cams.Camera]:
        return [cams.Camera(**{k: tuple(v) if isinstance(v, list) else v for k, v in c.items()})
                for c in self.spec["cameras"]]

    def _load(self, name: str) -> dict:
        return load_npz(os.path.join(self.folder, name), repair="re-run render_dataset to repair it")

    def lighting(self, index: int) -> Lighting:
        data = self._load(f"lighting_{index:05d}.npz")
        kind = str(data["kind"])
        if kind == "point":
            return PointLights(data["position"], data["intensity"])
        if kind == "envmap":
            return EnvMap(data["radiance"])
        return None

    def gbuffer(self, camera: int):
        """The G-buffer of camera ``camera`` as ``jprt.render.gbuffer.GBuffer``."""
        from jprt.render.gbuffer import GBuffer

        return GBuffer(**self._load(f"gbuffer_{camera:05d}.npz"))

    def radiance(self, k: int) -> dict:
        """{"direct", "indirect"} (H, W, 3) arrays of item ``k``."""
        it = self.items[k]
        return self._load(f"item_{it.lighting:05d}_{it.camera:05d}.npz")

    def stacked(self, field: str) -> np.ndarray:
        """``field`` ("direct" or "indirect") of all items, stacked (N, H, W, 3)."""
        return np.stack([self.radiance(k)[field] for k in range(len(self))])


def _lighting_arrays(lighting: Lighting) -> dict:
    if lighting is None:
        return {"kind": np.array("scene")}
    if isinstance(lighting, PointLights):
        return {"kind": np.array("point"), "position": np.asarray(lighting.position, np.float32),
                "intensity": np.asarray(lighting.intensity, np.float32)}
    if not isinstance(lighting, EnvMap):
        raise TypeError(f"image datasets store point lights or environment maps, not {type(lighting).__name__}")
    return {"kind": np.array("envmap"), "radiance": np.asarray(lighting.radiance, np.float32)}


def render_dataset(scene, cameras: Sequence[cams.Camera], lightings: Sequence[Lighting], *, spp: int,
                   seed: int = 0, pairs: str = "product", gbuffers: bool = True, cache_dir: str | None = None,
                   progress: bool | None = None, on_entry: Callable[[str], None] | None = None,
                   ray: bool | None = None, shards: int | None = None) -> Dataset:
    """Render (or reuse from the cache) direct + indirect images for camera x lighting pairs.

    Args:
      scene: scene description or name (see ``jprt.render.scenes``).
      cameras, lightings: the views and lights; ``pairs="product"`` renders every combination,
        ``"zip"`` pairs them one to one.
      spp: samples per pixel of both the full and the direct render (indirect = full - direct
        with the same seed). Item ``k`` uses seed ``seed + k``.
      gbuffers: also store each camera's G-buffer.
      on_entry: called with each entry's name after it is written (progress hooks, tests).
      ray: render the missing entries as Ray tasks (``jprt.distributed``; default: whether
        ``JPRT_RAY_ADDRESS`` is set), ``shards`` of them (default two per CPU of the cluster),
        each writing its entries atomically into the same content-addressed folder. Every entry
        depends only on its own seed, so the dataset is the single-process one (Mitsuba's renders
        in two processes differ by about one float32 ulp).

    Returns the ``Dataset``; ``dataset.stats`` says how much was rendered vs reused.
    """
    from jprt.render.images import check_spp, direct_indirect
    from jprt.render.scenes import describe
    from jprt.render.setup import mitsuba

    spp = check_spp(spp)
    mitsuba()  # fail on a missing libLLVM before anything is written
    cameras, lightings = list(cameras), [validate_lighting(li) for li in lightings]
    if not cameras or not lightings:
        raise ValueError("a dataset needs at least one camera and one lighting")
    if pairs == "product":
        items = [(li, ci) for li in range(len(lightings)) for ci in range(len(cameras))]
    elif pairs == "zip":
        if len(cameras) != len(lightings):
            raise ValueError(f"pairs='zip' needs as many cameras as lightings, got {len(cameras)} and {len(lightings)}")
        items = [(k, k) for k in range(len(cameras))]
    else:
        raise ValueError(f"pairs must be 'product' or 'zip', got {pairs!r}")
    desc = describe(scene)
    spec = {
        "format": FORMAT_VERSION,
        "scene": desc,
        "cameras": [c.describe() for c in cameras],
        "lightings": [lighting_description(li) for li in lightings],
        "items": items,
        "render": {"spp": spp, "seed": int(seed), "integrator": "volpath" if desc.get("media") else "path",
                   "direct_max_depth": 2, "gbuffers": bool(gbuffers)},
    }
    folder = os.path.join(cache_dir or cache_root(), "datasets", stable_hash(spec))
    os.makedirs(folder, exist_ok=True)
    spec_path = os.path.join(folder, "spec.json")
    if not os.path.exists(spec_path):
        write_json(spec_path, spec)

    work: list[tuple[str, Callable[[Any], dict], Any]] = []
    stats = {"rendered": 0, "cached": 0, "corrupt": 0}

    def plan(name: str, produce: Callable[[Any], dict], needs_lighting: Any) -> None:
        state = entry_state(os.path.join(folder, name))
        if state == "ok":
            stats["cached"] += 1
            return
        if state == "corrupt":
            stats["corrupt"] += 1
            warnings.warn(f"jprt: dataset entry {os.path.join(folder, name)} failed its checksum; re-rendering it",
                          stacklevel=3)
        work.append((name, produce, needs_lighting))

    for li, lighting in enumerate(lightings):
        plan(f"lighting_{li:05d}.npz", lambda h, lighting=lighting: _lighting_arrays(lighting), "none")
    if gbuffers:
        from jprt.render.gbuffer import gbuffer

        for ci, camera in enumerate(cameras):
            plan(f"gbuffer_{ci:05d}.npz", lambda h, camera=camera: gbuffer(h, camera)._asdict(), "any")
    for k, (li, ci) in enumerate(items):
        def produce(h, camera=cameras[ci], k=k):
            r = direct_indirect(h, camera, spp=spp, seed=seed + k)
            return {"direct": r.direct, "indirect": r.indirect}

        plan(f"item_{li:05d}_{ci:05d}.npz", produce, li)

    if work:
        from jprt import distributed

        if distributed.requested(ray) and len(work) > 1:
            ray_module = distributed.connect()
            n = max(1, min(len(work), int(shards or 2 * ray_module.cluster_resources().get("CPU", 1))))
            parts = [work[i::n] for i in range(n)]  # round robin: every shard gets a mix of entry kinds

            def shard_done(_, names):
                stats["rendered"] += len(names)
                for name in names:
                    if on_entry is not None:
                        on_entry(name)

            distributed.map_tasks(_render_entries, [(desc, lightings, folder, part, False) for part in parts],
                                  on_done=shard_done)
        else:
            def counted(name: str) -> None:
                stats["rendered"] += 1
                if on_entry is not None:
                    on_entry(name)

            try:
                _render_entries(desc, lightings, folder, work, progress, counted)
            except KeyboardInterrupt:
                print(f"jprt: interrupted after {stats['rendered']} of {len(work)} entries; run again to resume "
                      f"({folder})", file=sys.stderr)
                raise
    return Dataset(folder, spec, stats)


def _render_entries(desc: dict, lightings: list, folder: str, work: list, progress: bool | None,
                    on_entry: Callable[[str], None] | None = None) -> list[str]:
    """Render and write ``work`` entries (name, produce(handle) -> arrays, lighting it needs) with
    one scene handle; returns the names written. Runs in-process or as a Ray task."""
    from jprt.progress import bar as progress_bar
    from jprt.render.scenes import SceneHandle

    handle, written = None, []
    bar = progress_bar(work, progress=progress, desc=f"rendering dataset {os.path.basename(folder)}", unit="entry",
                       dynamic_ncols=True)
    try:
        for name, produce, needs in bar:
            if needs != "none":
                if handle is None:
                    handle = SceneHandle(desc, lightings[needs] if isinstance(needs, int) else lightings[0])
                elif isinstance(needs, int):
                    handle.set_lighting(lightings[needs])
            save_npz(os.path.join(folder, name), produce(handle))
            written.append(name)
            if on_entry is not None:
                on_entry(name)
    finally:
        bar.close()
    return written


def open_dataset(folder: str) -> Dataset:
    """Reopen a rendered dataset folder (entries are verified when loaded)."""
    spec_path = os.path.join(folder, "spec.json")
    if not os.path.isfile(spec_path):
        raise FileNotFoundError(f"not a jprt dataset folder (no spec.json): {folder}")
    with open(spec_path) as f:
        return Dataset(folder, json.load(f))


# --------------------------------------------------------------------------------------------
# From config dicts

DEFAULT_DATASET_CONFIG: dict = {
    "scene": {"name": "cornell_box", "area_light": False},
    "cameras": {
        "kind": "orbit",  # orbit | helix | random | list | file (the scene file's own sensor)
        "n": 3,
        "center": [0.0, 0.0, 0.0],
        "radius": 3.9,
        "elevation_deg": 0.0,
        "start_deg": -20.0,
        "arc_deg": 40.0,
        "height_range": [-0.5, 0.5],
        "turns": 1.0,
        "box_lo": [-0.5, -0.5, 3.0],
        "box_hi": [0.5, 0.5, 3.9],
        "origins": [],
        "fov": 39.3077,
        "width": 256,
        "height": 256,
        "seed": 0,
    },
    "lights": {
        "kind": "point",  # point | envmap | scene
        "positions": [[0.0, 0.8, 0.0], [-0.5, 0.6, 0.4]],
        "intensity": [4.0, 4.0, 4.0],
        "per_config": 1,  # point lights per lighting configuration
        "envmaps": [],
    },
    "spp": 64,
    "seed": 0,
    "pairs": "product",
    "gbuffers": True,
}


def cameras_from_config(cfg: dict, scene=None) -> list[cams.Camera]:
    """Cameras from the ``cameras`` section of a dataset config (see DEFAULT_DATASET_CONFIG);
    ``file`` is the first sensor of ``scene`` (an xml scene; the Cornell box's camera for the
    built-in boxes) at ``width`` x ``height``, its field of view kept along the smaller axis."""
    kw = {"fov": cfg["fov"], "width": cfg["width"], "height": cfg["height"]}
    kind = cfg["kind"]
    if kind == "file":
        if scene is None:
            raise ValueError("cameras.kind='file' needs the scene (the file's sensor)")
        from jprt.render.scenes import SceneHandle

        return [SceneHandle(scene).default_camera(int(cfg["width"]), int(cfg["height"]))]
    if kind == "orbit":
        return cams.orbit(cfg["center"], cfg["radius"], cfg["n"], elevation_deg=cfg["elevation_deg"],
                          start_deg=cfg["start_deg"], arc_deg=cfg["arc_deg"], **kw)
    if kind == "helix":
        return cams.helix(cfg["center"], cfg["radius"], cfg["n"], height_range=cfg["height_range"],
                          turns=cfg["turns"], **kw)
    if kind == "random":
        return cams.random_in_box(cfg["seed"], cfg["n"], cfg["box_lo"], cfg["box_hi"], cfg["center"], **kw)
    if kind == "list":
        return [cams.look_at(o, cfg["center"], **kw) for o in cfg["origins"]]
    raise ValueError(f"unknown camera kind {kind!r} (use orbit, helix, random, list or file)")


def lightings_from_config(cfg: dict) -> list[Lighting]:
    """Lightings from the ``lights`` section of a dataset config."""
    kind = cfg["kind"]
    if kind == "point":
        positions = np.asarray(cfg["positions"], np.float32).reshape(-1, 3)
        per = int(cfg["per_config"])
        if per <= 0 or len(positions) % per:
            raise ValueError(f"{len(positions)} light positions do not split into groups of per_config={per}")
        return [PointLights.create(positions[i:i + per], cfg["intensity"]) for i in range(0, len(positions), per)]
    if kind == "envmap":
        if not cfg["envmaps"]:
            raise ValueError("lights.kind='envmap' needs lights.envmaps (a list of .hdr/.exr paths)")
        return [EnvMap.from_file(p) for p in cfg["envmaps"]]
    if kind == "scene":
        return [None]
    raise ValueError(f"unknown lights kind {kind!r} (use point, envmap or scene)")


def from_config(cfg: dict, *, cache_dir: str | None = None, progress: bool | None = None) -> Dataset:
    """Render (or reuse) the dataset a config's ``dataset`` section describes."""
    return render_dataset(cfg["scene"], cameras_from_config(cfg["cameras"], cfg["scene"]),
                          lightings_from_config(cfg["lights"]),
                          spp=cfg["spp"], seed=cfg["seed"], pairs=cfg["pairs"], gbuffers=cfg["gbuffers"],
                          cache_dir=cache_dir, progress=progress)
