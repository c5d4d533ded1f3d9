"""The speed-accuracy atlas: every method of ``jprt.methods.REGISTRY`` on a shared task, each swept
over its main size knob, against Mitsuba's own speed-accuracy curve measured in the same run.

    jprt atlas local_lights --preset test                       # a built-in task
    jprt atlas path/to/scene.xml --lighting point \\
        --select "indirect_rel_rmse<=0.3" --minimize frame_ms    # any scene file
    jprt run experiments/atlas.py --preset small                # both built-in tasks

A **task** is a scene, a lighting kind and a held-out set that no method trains on: views and
lightings drawn from their own seeds, rendered once by Mitsuba at ``reference_spp`` (cached by
``jprt.render.dataset``), every method scored on the same images with the same masks. The built-in
tasks (``TASKS``):

* ``local_lights``: the built-in Cornell box (no area light) lit by one white point light inside
  it (RRF's light box), views in front of its opening (RRF's view box);
* ``environment``: the glossy Cornell box with its top open, relit by environment maps held out
  from neural-wavelet PRT's training (../shared/assets), seen from views around it.

``scene_task(path, lighting)`` makes a task of any scene file (``LIGHTINGS``):

* ``point``: the file's emitters removed, white point lights drawn in the scene's light region
  (``jprt.render.sampling.scene_regions``, moved out of geometry by ``free_lights``);
* ``environment``: the file's emitters removed and its ceiling cut open
  (``jprt.render.scenes.xml``), lit by environment maps held out of neural-wavelet PRT's training;
* ``file``: the file's own emitters (the method side sees ``LightScale(1)``: the baked lighting);

seen from the file's camera and views turned about it (``views_about``).

A method takes part in a task whose lighting kind is among its ``Method.task_lightings`` (its
``task_inputs(handle, dataset, camera)`` and ``task_lighting(handle, dataset, params, config,
lighting)`` turn a task view and a task lighting into its evaluator's arguments) and that has an
entry under ``tasks.<task>.methods`` (its ``set`` items and its size knob ``grid``); otherwise
the atlas lists it as skipped, with the reason (a scene file's task also names the methods it
does not run, ``not_run``).

Every (task, method) is one ``jprt.sweep`` over the method's knob, each point a ``jprt.runner`` run
of a ``TaskExperiment`` (resumable, in ``output.dir/<task>/<method>/``); points that differ only in
run-time settings (``render.*``: wavelet PRT's K, RRF's evaluation block) share one fit. Mitsuba's
curve is the held-out set path traced at ``eval.curve_spp`` (a seed unlike the references'), its
RMSE against the references and its wall time for one frame of the timed view; each point's
equal-error spp and speedup are read off that curve (``equal_error``). ``run_atlas`` writes
``atlas.json`` (per task, per method: the points with the common summary keys, the Pareto fronts,
the Mitsuba curve), one figure per task ``atlas_<task>.png`` and ``atlas.md`` (the table); with
``eval.select``, each method's cheapest point meeting it as ``selected_<task>_<method>.json`` and
the cheapest method per task.
"""

from __future__ import annotations

import json
import math
import os
import re
import sys
import time
import traceback
import types

import numpy as np

from jprt import eval as jeval
from jprt import io
from jprt.config import apply_overrides, merge, stable_hash
from jprt.methods import REGISTRY
from jprt.render.heldout import views_about
from jprt.runner import HeldOut

__all__ = ["TASKS", "EVAL", "PRESETS", "LIGHTINGS", "dotted", "scene_task", "atlas_config", "task_cameras",
           "views_about", "task_lightings", "mitsuba_lighting", "TaskData", "task_data", "timed_camera",
           "mitsuba_curve", "equal_error", "applicability", "TaskExperiment", "run_atlas", "method_sweep",
           "select_point", "plot_task", "table"]


def dotted(overrides: dict, prefix: str = "") -> list[str]:
    """A nested override dict as ``--set`` items (``"a.b=<json>"``), leaves only."""
    out = []
    for k, v in overrides.items():
        out += dotted(v, f"{prefix}{k}.") if isinstance(v, dict) and v else [f"{prefix}{k}={json.dumps(v)}"]
    return out


def _test_sets(name: str, drop: tuple = ("scene",)) -> list[str]:
    """``--set`` items of method ``name``'s ``test`` preset, without the sections a task sets."""
    return dotted({k: v for k, v in REGISTRY[name].presets["test"].items() if k not in drop})


# --------------------------------------------------------------------------------------------
# The built-in tasks. A task's methods map a method to "set" (``--set`` items on top of its
# defaults and the task's scene) and "grid" (``--grid`` items: the size knob swept); lists, so a
# preset replaces them whole.

#: Data-driven PRT's lighting scenario on the local-lights task: the task's lights (white point
#: lights in RRF's box).
_POINT_SCENARIO = {"lights": {"kind": "point", "position_lo": [-0.6, 0.3, -0.6], "position_hi": [0.6, 0.9, 0.6],
                              "intensity": [1.0, 1.0], "saturation": 0.0, "clearance": 0.1}}

#: The Cornell box as MRT's proxy: one block spanning [-1, 1]^3, its +z side (the front) open.
_CORNELL_PROXY = {"layout": {"cells": [[0, 0]], "edges": [], "exterior": [[[0, 0], 1]]}, "origin": [-1.0, -1.0, -1.0],
                  "size": 2.0}
_PROXY_SETS = [f"proxy.{k}={json.dumps(v)}" for k, v in _CORNELL_PROXY.items()]

#: The glossy Cornell box's meshes (the metal sphere is an analytic shape: SH PRT's lightmap
#: leaves it out, its pixels predicted 0; a diffuse transfer could not reflect the environment there).
_GLOSSY_MESHES = ["floor", "back", "green-wall", "red-wall", "small-box"]

TASKS = {
    "local_lights": {
        "title": "local lights: Cornell box, one point light",
        "scene": {"name": "cornell_box", "area_light": False},
        "lighting": "point",
        "lights": {"n": 3, "lo": [-0.6, 0.3, -0.6], "hi": [0.6, 0.9, 0.6], "intensity": [1.0, 1.0, 1.0], "seed": 3101},
        "views": {"n": 3, "lo": [-0.6, -0.4, 2.8], "hi": [0.6, 0.4, 3.9], "target": [0.0, 0.0, 0.0],
                  "fov": 39.3077, "seed": 3102},
        "resolution": 64,
        "reference_spp": 4096,
        "methods": {
            # Ren et al. 2013 §4 at the method's default sizes: leaves split until the error threshold
            # is met; networks of 20-10 (the paper's) or 8-4
            "rrf": {"set": ["train.progress=false"],
                    "grid": ["model.hidden=[[8, 4], [20, 10]]", "tree.threshold=[0.02, 0.1]"]},
            # Belcour et al. 2022 §4.1, the task's lights as its scenario
            "datadriven": {"set": dotted({**_POINT_SCENARIO, "data": {"n_test": 0}}),
                           "grid": ["basis.n=[4, 16, 64]", "points.count=[64, 256]"]},
            "sh_prt": {"set": [], "grid": ["sh.order=[2, 3, 5]"]},
            # Loos et al. 2011 §7.2: the box as one block of the dictionary, its front open to the
            # camera; one held-out lighting of its own (it fits nothing to it)
            "mrt": {"set": _PROXY_SETS + dotted({"data": {"n_test": 1, "test_spp": 16}}),
                    "grid": ["dictionary.k_b=[8, 32]"]},
        },
    },
    "environment": {
        "title": "environment relighting: glossy open Cornell box, held-out maps",
        "scene": {"name": "glossy_cornell", "open_top": True, "floor_roughness": 0.1, "sphere_roughness": 0.05},
        "lighting": "environment",
        # the maps neural-wavelet PRT holds out of training (its envmaps.held_out), unrotated and turned
        "envmaps": {"names": ["st_fagans_interior_1k", "venice_sunset_1k"], "rotations_deg": [0.0, 90.0],
                    "face_size": 16, "normalise": True, "synthetic": 0, "seed": 3103},
        # views off the training trajectories (radius, azimuth, elevation about the target)
        "views": {"n": 3, "radius": [2.6, 3.4], "azimuth": [-40.0, 40.0], "elevation": [0.0, 40.0],
                  "target": [0.0, -0.1, 0.0], "fov": 39.3077, "seed": 3104},
        "resolution": 64,
        "reference_spp": 2048,
        "methods": {
            # Raghavan et al. 2023 at the method's sizes: K is run-time only (one fit per MLP width);
            # none of the method's own near / far test views (the task has its own)
            "wavelet_prt": {"set": ["cameras.near=0", "cameras.far=0"],
                            "grid": ["model.hidden=[64, 128]", "render.k=[16, 32, 64]"]},
            "sh_prt": {"set": [f"objects={json.dumps(_GLOSSY_MESHES)}"], "grid": ["sh.order=[2, 3, 5]"]},
        },
    },
}

EVAL = {
    "curve_spp": [1, 2, 4, 8, 16, 32, 64, 128, 256, 512, 1024],  # Mitsuba's curve
    "curve_seed": 7777,
    "timing_resolution": 128,  # every method's frame and Mitsuba's frame are timed at this size
    "timing_repeats": 5,
    "exposure": 0.0,
    "images": 2,  # side-by-side rows per point
    "tasks": [],  # run only these tasks ([] = all)
    "methods": [],  # run only these methods ([] = all that apply)
    # model only what the scene needs: per task, each method's cheapest point meeting `select`
    # ("indirect_rel_rmse<=0.3", comma-separated constraints, as `jprt sweep --select`) by
    # `minimize`, and the cheapest over all methods; each written as a config that runs that point
    "select": "",
    "minimize": "frame_ms",
}

#: The evaluation at test sizes (every task).
_TEST_EVAL = {"curve_spp": [1, 4, 16], "timing_resolution": 16, "timing_repeats": 2, "images": 1}

#: Named presets of an atlas config over the built-in tasks: ``small`` (the defaults) and
#: ``test`` (seconds: tiny sizes, each method's own ``test`` preset).
PRESETS = {
    "small": {},
    "test": {
        "tasks": {
            "local_lights": {
                "lights": {"n": 1}, "views": {"n": 1}, "resolution": 12, "reference_spp": 16,
                "methods": {
                    "rrf": {"set": _test_sets("rrf"), "grid": ["model.hidden=[[4, 2], [6, 4]]"]},
                    "datadriven": {"set": dotted(merge(REGISTRY["datadriven"].presets["test"], {"data": {"n_test": 0}}))
                                   + dotted(_POINT_SCENARIO), "grid": ["basis.n=[2, 4]"]},
                    "sh_prt": {"set": _test_sets("sh_prt"), "grid": ["sh.order=[2]"]},
                    "mrt": {"set": _test_sets("mrt", ("scene", "data")) + dotted({"data": {"n_test": 1, "test_spp": 4}})
                            + _PROXY_SETS, "grid": ["dictionary.k_b=[4, 12]"]},
                },
            },
            "environment": {
                "envmaps": {"synthetic": 1, "rotations_deg": [0.0], "face_size": 4}, "views": {"n": 1},
                "resolution": 12, "reference_spp": 16,
                "methods": {
                    "wavelet_prt": {"set": _test_sets("wavelet_prt") + ["cameras.near=0", "cameras.far=0"],
                                    "grid": ["render.k=[8, 16]"]},
                    "sh_prt": {"set": _test_sets("sh_prt") + [f"objects={json.dumps(_GLOSSY_MESHES)}"],
                               "grid": ["sh.order=[2]"]},
                },
            },
        },
        "eval": _TEST_EVAL,
    },
}


# --------------------------------------------------------------------------------------------
# Tasks of scene files

#: The lighting kinds of a scene file's task (``scene_task``).
LIGHTINGS = ("point", "environment", "file")

#: The environment maps a scene file's environment task is lit by: one indoor, one overcast, one
#: clear sky with sun, all held out of neural-wavelet PRT's training maps.
_HELD_OUT_MAPS = ["st_fagans_interior_1k", "potsdamer_platz_1k", "rooitou_park_1k"]

#: Per lighting kind, each method's entry on a scene file at default sizes ("set", "grid"): the
#: methods' defaults read the scene's regions from the file, so only the knobs and the task's
#: lighting are set here.
_SCENE_METHODS = {
    "point": {"rrf": {"set": ["train.progress=false"], "grid": ["model.hidden=[[8, 4], [20, 10]]"]},
              "datadriven": {"set": ["data.n_test=0"], "grid": ["basis.n=[4, 16, 64]"]},
              "sh_prt": {"set": [], "grid": ["sh.order=[2, 3, 5]"]}},
    # views about the file's camera (target None); none of the method's own test views
    "environment": {"wavelet_prt": {"set": ["cameras.target=null", "cameras.near=0", "cameras.far=0"],
                                    "grid": ["render.k=[16, 32, 64]"]},
                    "sh_prt": {"set": [], "grid": ["sh.order=[2, 3, 5]"]}},
    # a method baked under the file's own emitters (every object a receiver); it takes part once
    # its task adapter lists "file"
    "file": {"sg_lightfield": {"set": ["objects=[]"], "grid": ["model.n_lobes=[4, 8]"]}},
}
#: The same at test sizes (each method's own ``test`` preset; one point where a second would be
#: a second fit of seconds: RRF's networks compile per width).
_SCENE_TEST_METHODS = {
    "point": {"rrf": {"set": _test_sets("rrf"), "grid": ["model.hidden=[[6, 4]]"]},
              "datadriven": {"set": _test_sets("datadriven", ("scene", "data")) + ["data.n_test=0"],
                             "grid": ["basis.n=[2, 4]"]},
              "sh_prt": {"set": _test_sets("sh_prt"), "grid": ["sh.order=[2]"]}},
    "environment": {"wavelet_prt": {"set": _test_sets("wavelet_prt") + ["cameras.target=null", "cameras.near=0",
                                                                        "cameras.far=0"],
                                    "grid": ["render.k=[8, 16]"]},
                    "sh_prt": {"set": _test_sets("sh_prt"), "grid": ["sh.order=[2]"]}},
    "file": {"sg_lightfield": {"set": _test_sets("sg_lightfield", ("scene", "objects")) + ["objects=[]"],
                               "grid": ["model.n_lobes=[2]"]}},
}
#: Registered methods a scene file's task does not run, and why.
_SCENE_NOT_RUN = {"mrt": "MRT relights a block layout (its proxy.*), which a scene file does not give"}


def scene_task(path: str, lighting: str = "point", preset: str | None = None) -> dict:
    """The task of scene file ``path`` under ``lighting`` (one of ``LIGHTINGS``; module
    docstring): its held-out views (the file's camera and two turned about it), three held-out
    lightings, references at 1024 spp, each applicable method at default sizes; ``preset`` "test":
    one view, one lighting, 12^2 pixels, 16 spp, each method's ``test`` preset (procedural
    environment maps: no shared assets needed)."""
    from jprt.render.sampling import scene_regions

    if lighting not in LIGHTINGS:
        raise ValueError(f"lighting {lighting!r}: one of {', '.join(LIGHTINGS)}")
    if preset not in (None, "small", "test"):
        raise ValueError(f"unknown preset {preset!r}; a scene file's atlas has 'small' (default) and 'test'")
    path = os.path.abspath(path)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"scene file not found: {path}")
    test = preset == "test"
    stem = os.path.splitext(os.path.basename(path))[0]
    scene = {"name": "xml", "path": path, "keep_emitters": lighting == "file",
             "opening": "ceiling" if lighting == "environment" else ""}
    methods = json.loads(json.dumps((_SCENE_TEST_METHODS if test else _SCENE_METHODS)[lighting]))
    task = {"title": f"{stem}: {lighting} lighting", "scene": scene, "lighting": lighting,
            "views": {"n": 1 if test else 3, "about": "file camera", "yaw_deg": [10.0, 25.0], "pitch_deg": 5.0,
                      "seed": 3102},
            "resolution": 12 if test else 64, "reference_spp": 16 if test else 1024, "methods": methods,
            "not_run": dict(_SCENE_NOT_RUN)}
    if lighting == "point":
        regions = scene_regions(scene)
        lo, hi = regions["light_lo"], regions["light_hi"]
        task["lights"] = {"n": 1 if test else 3, "lo": lo, "hi": hi, "intensity": [1.0, 1.0, 1.0], "seed": 3101,
                          "free": True}
        if "datadriven" in methods:  # its lighting scenario: the task's lights, 2 % of the box from surfaces
            scenario = {"kind": "point", "position_lo": lo, "position_hi": hi, "intensity": [1.0, 1.0],
                        "saturation": 0.0, "clearance": 0.02 * float(np.max(np.subtract(hi, lo)))}
            methods["datadriven"]["set"] += dotted({"lights": scenario})
    elif lighting == "environment":
        task["envmaps"] = {"names": list(_HELD_OUT_MAPS), "rotations_deg": [0.0], "face_size": 4 if test else 16,
                           "normalise": True, "synthetic": 1 if test else 0, "seed": 3103}
    return task


def _task_name(path: str) -> str:
    """A task name of a scene file: its stem, word characters only."""
    return re.sub(r"\W", "_", os.path.splitext(os.path.basename(path))[0]) or "scene"


def atlas_config(target: str, lighting: str | None = None, preset: str | None = None, *, out: str | None = None,
                 select: str = "", minimize: str = "frame_ms", overrides: list[str] = ()) -> dict:
    """The atlas config (``{"tasks", "eval", "output"}``) of one task: ``target`` a built-in task
    name (``TASKS``; ``lighting`` must be its own or None) or a scene file (``scene_task``,
    ``lighting`` default "point"); ``preset`` as ``PRESETS``; ``out`` the output folder (default
    results/atlas/<task>); ``select`` / ``minimize`` as ``eval.select`` / ``eval.minimize``;
    ``overrides`` ``--set`` items applied last."""
    lighting = {"env": "environment"}.get(lighting, lighting)
    if target in TASKS:
        if preset not in (None, *PRESETS):
            raise ValueError(f"unknown preset {preset!r}; the atlas has {sorted(PRESETS)}")
        p = PRESETS[preset] if preset else {}
        name, task = target, merge(TASKS[target], p.get("tasks", {}).get(target, {}))
        if lighting not in (None, task["lighting"]):
            raise ValueError(f"task {target} is lit by {task['lighting']} lighting, not {lighting}")
        e = merge(EVAL, p.get("eval", {}))
    elif os.path.isfile(target) or target.endswith(".xml"):
        name, task = _task_name(target), scene_task(target, lighting or "point", preset)
        e = merge(EVAL, _TEST_EVAL if preset == "test" else {})
    else:
        raise ValueError(f"{target!r} is neither a built-in task ({', '.join(TASKS)}) nor a scene file")
    e = merge(e, {"select": select or "", "minimize": minimize})
    config = {"tasks": {name: task}, "eval": e, "output": {"dir": out or os.path.join("results", "atlas", name)}}
    return apply_overrides(config, list(overrides))


_FITS: dict = {}  # fits shared by points that differ only in run-time settings (this process)
_TASK_DATA: dict = {}  # each task's held-out set, loaded once per process


# --------------------------------------------------------------------------------------------
# Tasks: held-out views and lightings, their references, Mitsuba's curve


def task_cameras(task: dict, resolution: int | None = None) -> list:
    """The task's held-out cameras (seeded), at ``resolution`` (default the task's): from a box of
    origins (``views.lo`` / ``hi``) or spherical coordinates (``radius`` / ``azimuth`` /
    ``elevation``) about ``views.target``, or (``views.about`` "file camera") the scene file's
    camera and views turned about it (``views_about``)."""
    from jprt.render import cameras as cams
    from jprt.render.sampling import latin_hypercube

    v, res = task["views"], int(resolution or task["resolution"])
    rng = np.random.default_rng(int(v["seed"]))
    if v.get("about") == "file camera":
        from jprt.render.scenes import SceneHandle

        first = SceneHandle(task["scene"]).default_camera(res, res)
        return [first] + views_about(first, int(v["n"]) - 1, int(v["seed"]), v["yaw_deg"], float(v["pitch_deg"]))
    if "lo" in v:  # a box of origins, all looking at the target
        origins = latin_hypercube(rng, int(v["n"]), v["lo"], v["hi"])
    else:  # spherical coordinates about the target
        r, az, el = (latin_hypercube(rng, int(v["n"]), [v[k][0] for k in ("radius", "azimuth", "elevation")],
                                     [v[k][1] for k in ("radius", "azimuth", "elevation")]).T)
        az, el = np.radians(az), np.radians(el)
        origins = np.asarray(v["target"]) + np.stack([r * np.sin(az) * np.cos(el), r * np.sin(el),
                                                      r * np.cos(az) * np.cos(el)], axis=-1)
    return [cams.look_at(o, v["target"], fov=float(v["fov"]), width=res, height=res) for o in origins]


def task_lightings(task: dict) -> list:
    """The task's held-out lightings as methods see them: ``PointLights`` (drawn in ``lights.lo`` /
    ``hi``; with ``lights.free``, moved out of geometry), ``CubeMap`` (``envmaps``: held-out maps,
    or procedural ones) or, for the file's own emitters, ``LightScale(1)``."""
    from jprt.inputs import CubeMap, LightScale, PointLights
    from jprt.render.sampling import free_lights, latin_hypercube

    if task["lighting"] == "point":
        lt = task["lights"]
        rng = np.random.default_rng(int(lt["seed"]))
        positions = latin_hypercube(rng, int(lt["n"]), lt["lo"], lt["hi"])
        if lt.get("free"):
            positions = free_lights(task["scene"], positions, lt["lo"], lt["hi"], rng)
        return [PointLights.create([p], lt["intensity"]) for p in positions]
    if task["lighting"] == "file":
        return [LightScale.create(np.ones(3, np.float32))]
    if task["lighting"] != "environment":
        raise ValueError(f"task lighting {task['lighting']!r}: one of {', '.join(LIGHTINGS)}")
    from jprt.methods.wavelet_prt import data as wp_data
    from jprt.sphere.envmap import synthetic_environments

    e = task["envmaps"]
    n = int(e["face_size"])
    if int(e["synthetic"]) > 0:
        return [CubeMap(c) for c in synthetic_environments(int(e["synthetic"]), n, int(e["seed"]))]
    cubes, _ = wp_data.load_environments(e["names"], e["rotations_deg"], n, normalise=bool(e["normalise"]))
    return [CubeMap(c) for c in cubes]


def mitsuba_lighting(lighting):
    """What Mitsuba renders for a task lighting: point lights as they are, a cube map as the
    equirect map of its texels (``jprt.sphere.envmap.render_equirect``), a ``LightScale`` as the
    file's own emitters (None)."""
    from jprt.inputs import CubeMap, LightScale
    from jprt.render.lights import EnvMap
    from jprt.sphere.envmap import render_equirect

    if isinstance(lighting, LightScale):
        return None
    return EnvMap.create(render_equirect(lighting.radiance)) if isinstance(lighting, CubeMap) else lighting


class TaskData(types.SimpleNamespace):
    """A task's held-out set: ``cameras``, ``lightings`` (method side), ``mitsuba`` (lightings as
    rendered), ``dataset`` (``jprt.render.dataset.Dataset`` of every camera x lighting),
    ``references`` / ``direct`` / ``valid`` (per item), ``labels``."""


def _held_out_key(task: dict) -> str:
    return stable_hash({k: v for k, v in task.items() if k not in ("methods", "not_run")})


def task_data(task: dict, progress: bool = True) -> TaskData:
    """Render (or read from the cache) the task's held-out references at ``reference_spp``."""
    from jprt.render.dataset import render_dataset

    key = _held_out_key(task)
    if key not in _TASK_DATA:
        cameras, lightings = task_cameras(task), task_lightings(task)
        mitsuba = [mitsuba_lighting(li) for li in lightings]
        ds = render_dataset(task["scene"], cameras, mitsuba, spp=int(task["reference_spp"]), seed=5000, gbuffers=True,
                            progress=progress)
        rad = [ds.radiance(k) for k in range(len(ds))]
        valid = [np.asarray(ds.gbuffer(it.camera).valid) for it in ds.items]
        _TASK_DATA[key] = TaskData(cameras=cameras, lightings=lightings, mitsuba=mitsuba, dataset=ds,
                                   references=[r["indirect"] for r in rad], direct=[r["direct"] for r in rad],
                                   valid=valid, labels=[f"view {it.camera}, light {it.lighting}" for it in ds.items])
    return _TASK_DATA[key]


def timed_camera(td: TaskData, resolution: int):
    """The first held-out view at ``resolution``: the frame every method and Mitsuba are timed on."""
    from jprt.render import cameras as cams

    c0 = td.cameras[0]
    return cams.look_at(c0.origin, c0.target, c0.up, fov=c0.fov, width=int(resolution), height=int(resolution))


def mitsuba_curve(task: dict, e: dict, say=print) -> list[dict]:
    """Mitsuba's speed-accuracy curve on the task: for every spp of ``e["curve_spp"]``, the
    indirect RMSE of the held-out set path traced at that spp (full minus direct, seed
    ``curve_seed``) against the references (``jprt.eval.equal_error_spp`` with no target: every
    spp measured), and the wall time (ms) of one frame of the first held-out view and lighting at
    ``timing_resolution`` (both renders)."""
    from jprt.render.images import direct_indirect
    from jprt.render.scenes import SceneHandle

    td = task_data(task)
    handle = SceneHandle(task["scene"], td.mitsuba[0])
    tr = int(e["timing_resolution"])
    timed = timed_camera(td, tr)

    def render_at(spp: int) -> list:
        images = []
        for it in td.dataset.items:
            handle.set_lighting(td.mitsuba[it.lighting])
            images.append(direct_indirect(handle, td.cameras[it.camera], spp=spp, seed=int(e["curve_seed"])).indirect)
        return images

    measured = jeval.equal_error_spp(render_at, td.references, -math.inf, e["curve_spp"], td.valid)["tried"]
    handle.set_lighting(td.mitsuba[0])
    direct_indirect(handle, timed, spp=1, seed=3)  # warm-up: Dr.Jit compiles for this film size
    curve = []
    for point in measured:
        spp = point["spp"]
        ms = jeval.time_call(lambda: direct_indirect(handle, timed, spp=spp, seed=3), repeats=1, warmup=0)
        curve.append({"spp": spp, "ms": ms["median_ms"], "rmse": point["rmse"]})
        say(f"Mitsuba {spp} spp: RMSE {point['rmse']:.5f}, {ms['median_ms']:.0f} ms at {tr}x{tr}")
    return curve


def equal_error(curve: list[dict], rmse: float | None, frame_ms: float | None) -> dict:
    """A point's equal-error numbers read off Mitsuba's curve: the smallest spp whose RMSE is at
    most ``rmse``, its frame time and the speedup; when no spp reaches it, spp None and the time
    of the largest spp (a lower bound, ``reached`` False): ``jprt.eval.EqualErrorCurve.read``."""
    return jeval.EqualErrorCurve(curve).read(rmse, frame_ms)


# --------------------------------------------------------------------------------------------
# One (task, method) as a jprt.runner experiment


def applicability(task: dict, name: str) -> str | None:
    """None when method ``name`` runs on ``task``, else why not."""
    if name in task.get("not_run", {}):
        return task["not_run"][name]
    kinds = REGISTRY[name].task_lightings
    if not kinds:
        return (f"{name} has no task adapter for the file's own emitters (Method.task_lightings is empty)"
                if task["lighting"] == "file" else
                f"{name} is baked for its scene's own emitters and relights none of the tasks' lightings")
    if task["lighting"] not in kinds:
        return f"{name} takes {', '.join(kinds)} lighting, the task is {task['lighting']}"
    if name not in task["methods"]:
        return f"no size knob for {name} under this task's methods"
    return None


class TaskExperiment:
    """Method ``name`` on ``task`` as the experiment ``jprt.runner.run`` and ``jprt.sweep`` run:
    ``METHOD``, ``LABEL``, ``CONFIG`` (the method's defaults, the task's scene and the task entry's
    ``set``, the evaluation of ``e``, the report folder ``out/<task>/<method>``) and the runner's
    hooks ``fit`` (shared by points that differ only in ``render.*``), ``held_out`` (the task's
    references and the method's predictions of them) and ``frame`` (the timed view and first
    lighting)."""

    def __init__(self, task_name: str, task: dict, name: str, e: dict, out: str):
        self.task, self.method = task, REGISTRY[name]
        self.timing_resolution = int(e["timing_resolution"])
        self.METHOD = name
        self.LABEL = f"atlas {task_name}/{name}"
        entry = task["methods"][name]
        config = apply_overrides(merge(self.method.default_config, {"scene": task["scene"]}), entry["set"])
        config.update(task={k: v for k, v in task.items() if k != "methods"} | {"name": task_name},
                      eval={"equal_error_spp": [], "timing_repeats": int(e["timing_repeats"]),
                            "timing_resolution": self.timing_resolution, "exposure": float(e["exposure"]),
                            "images": int(e["images"])},
                      output={"dir": os.path.join(out, task_name, name)})
        self.CONFIG = config

    def _handle(self, run):
        from jprt.render.scenes import SceneHandle

        if "handle" not in run.state:
            run.state["handle"] = SceneHandle(self.task["scene"], task_data(self.task).mitsuba[0])
        return run.state["handle"]

    def _lighting(self, run, lighting):
        return self.method.task_lighting(self._handle(run), run.dataset, run.result.params, run.method_config,
                                         lighting)

    def fit(self, run):
        """The method's fit of the point's config, once per process for configs that differ only
        in run-time settings (``render.*``)."""
        key = (self.METHOD, stable_hash({k: v for k, v in run.method_config.items() if k != "render"}))
        if key not in _FITS:
            t0 = time.perf_counter()
            result = self.method.fit(run.dataset, run.method_config)
            result.info.setdefault("train_s", time.perf_counter() - t0)
            _FITS[key] = result
        return _FITS[key]

    def held_out(self, run) -> HeldOut:
        """The method's predictions of every held-out item (masked to the valid pixels) beside the
        task's references."""
        td = task_data(self.task)
        inputs = {}
        preds = []
        for it, valid in zip(td.dataset.items, td.valid):
            if it.camera not in inputs:
                inputs[it.camera] = self.method.task_inputs(self._handle(run), run.dataset, td.cameras[it.camera])
            lighting = self._lighting(run, td.lightings[it.lighting])
            preds.append(np.where(valid[..., None], np.asarray(run.evaluate(inputs[it.camera], lighting)), 0.0))
        return HeldOut(preds, td.references, td.valid, td.direct, td.labels)

    def frame(self, run):
        """The timed frame's arguments: the first held-out view at the timing resolution, the
        first held-out lighting."""
        td = task_data(self.task)
        camera = timed_camera(td, self.timing_resolution)
        return self.method.task_inputs(self._handle(run), run.dataset, camera), self._lighting(run, td.lightings[0])


# --------------------------------------------------------------------------------------------
# The atlas


def run_atlas(config: dict, *, experiment: str | None = None) -> dict:
    """Run every applicable (task, method) sweep and Mitsuba's curve per task of ``config``
    (``atlas_config``, or an experiment's CONFIG); write atlas.json, the figures, the table and,
    with ``eval.select``, the selections to ``output.dir``; return the record. ``experiment``: the
    experiment file the selections re-run through (``jprt run FILE --config ...``; default
    ``jprt atlas --config ...``)."""
    from jprt.sweep import PARETO_AXES, pareto_front

    t_start = time.perf_counter()
    e, out = config["eval"], os.path.abspath(config["output"]["dir"])
    os.makedirs(out, exist_ok=True)
    record = {"tasks": {}, "eval": e, "methods": {n: m.paper for n, m in REGISTRY.items()}}
    for task_name, task in config["tasks"].items():
        if e["tasks"] and task_name not in e["tasks"]:
            continue
        say = lambda msg, t=task_name: print(f"[atlas {t}] {msg}", file=sys.stderr, flush=True)  # noqa: E731
        t0 = time.perf_counter()
        td = task_data(task)
        say(f"{len(td.dataset)} held-out images ({len(td.cameras)} views x {len(td.lightings)} lightings) at "
            f"{task['resolution']}^2, references {task['reference_spp']} spp")
        curve = mitsuba_curve(task, e, say)
        entry = {"title": task["title"], "scene": task["scene"], "lighting": task["lighting"],
                 "n_images": len(td.dataset), "resolution": int(task["resolution"]),
                 "reference_spp": int(task["reference_spp"]), "mitsuba_curve": curve, "methods": {}}
        for name in REGISTRY:
            if e["methods"] and name not in e["methods"]:
                continue
            why = applicability(task, name)
            if why:
                entry["methods"][name] = {"status": "skipped", "reason": why}
                say(f"{name}: skipped ({why})")
                continue
            try:  # one method failing never loses the others: its error and traceback go in the record
                entry["methods"][name] = method_sweep(config, task_name, name, curve, out, say,
                                                      experiment=experiment)
            except Exception as err:
                entry["methods"][name] = {"status": "failed", "error": f"{type(err).__name__}: {err}",
                                          "traceback": traceback.format_exc()}
                say(f"{name}: FAILED: {type(err).__name__}: {err}")
        # the front over every method of the task (frame time against error)
        pts = [(n, i, r) for n, m in entry["methods"].items() if m["status"] == "done"
               for i, r in enumerate(m["points"]) if r["status"] != "failed"]
        on = pareto_front([r["frame_ms"] for _, _, r in pts], [r["indirect_rmse"] for _, _, r in pts])
        entry["front_frame_ms"] = [{"method": n, "point": i} for (n, i, _), o in zip(pts, on) if o]
        if e["select"]:
            chosen = [(m["selected"][e["minimize"]], n) for n, m in entry["methods"].items()
                      if "config" in m.get("selected", {})]
            entry["selected"] = {"select": e["select"], "minimize": e["minimize"],
                                 "method": min(chosen)[1] if chosen else None}
            say(f"cheapest method meeting {e['select']}: {entry['selected']['method']}")
        entry["seconds"] = time.perf_counter() - t0
        record["tasks"][task_name] = entry
        plot_task(os.path.join(out, f"atlas_{task_name}.png"), entry)
        say(f"done in {entry['seconds'] / 60:.1f} min")
    record["pareto_axes"] = list(PARETO_AXES)
    record["total_s"] = time.perf_counter() - t_start
    io.write_json(os.path.join(out, "atlas.json"), record)
    with open(os.path.join(out, "atlas.md"), "w") as f:
        f.write(table(record))
    print(f"atlas (atlas.json, atlas_<task>.png, atlas.md) written to {out}")
    return record


def method_sweep(config: dict, task_name: str, name: str, curve: list, out: str, say=print, *,
                 experiment: str | None = None) -> dict:
    """Method ``name``'s sweep on task ``task_name`` of ``config``: its points (with the
    equal-error reading off Mitsuba's ``curve``), fronts and, with ``eval.select``, the selected
    point (``select_point``)."""
    from jprt.sweep import parse_grid, run_sweep

    e, task = config["eval"], config["tasks"][task_name]
    target = TaskExperiment(task_name, task, name, e, out)
    grid = parse_grid(task["methods"][name]["grid"])
    sweep = run_sweep(target, target.CONFIG, grid, label=f"{task_name}/{name}")
    rows = []
    for r in sweep["rows"]:
        row = {k: v for k, v in r.items() if k != "pathtrace_curve"}
        row.update(equal_error(curve, r.get("indirect_rmse"), r.get("frame_ms")))
        rows.append(row)
    result = {"status": "done", "knobs": list(grid), "points": rows, "pareto": sweep["pareto"],
              "sweep_folder": sweep["folder"], "counts": sweep["counts"]}
    if e["select"]:
        result["selected"] = select_point(config, task_name, name, rows, grid, out, say, experiment=experiment)
    return result


def select_point(config: dict, task_name: str, name: str, rows: list, grid: dict, out: str, say=print, *,
                 experiment: str | None = None) -> dict:
    """``jprt.sweep.select`` over one method's points: the chosen point (its knob values, the
    minimised value) and ``selected_<task>_<method>.json``, the atlas config that runs just that
    point (``jprt atlas --config FILE``, or ``jprt run EXPERIMENT --config FILE``); or the error
    naming the best reached."""
    from jprt.sweep import select

    e = config["eval"]
    try:
        row = select(rows, e["select"], e["minimize"])
    except ValueError as err:
        say(f"{name}: {err}")
        return {"error": str(err)}
    point = {k: row[k] for k in grid}
    chosen = json.loads(json.dumps(config))
    entry = chosen["tasks"][task_name]["methods"][name]
    entry["set"] = list(entry["set"]) + [f"{k}={json.dumps(v)}" for k, v in point.items()]
    entry["grid"] = []
    chosen["eval"].update(tasks=[task_name], methods=[name], select="")
    chosen["output"]["dir"] = os.path.join(out, f"selected_{task_name}_{name}")  # not over the whole atlas
    path = os.path.join(out, f"selected_{task_name}_{name}.json")
    command = f"jprt run {os.path.relpath(experiment)} --config {path}" if experiment else f"jprt atlas --config {path}"
    io.write_json(path, {"experiment": os.path.abspath(experiment) if experiment else None, "command": command,
                         "select": e["select"], "minimize": e["minimize"], "point": point, "config": chosen})
    say(f"{name}: selected {point} ({e['minimize']} = {row[e['minimize']]:.4g}); run it with: {command}")
    return {"point": point, e["minimize"]: row[e["minimize"]], "indirect_rmse": row["indirect_rmse"],
            "config": path}


def _label(row: dict, knobs: list) -> str:
    return ", ".join(f"{k.split('.')[-1]}={row[k]}".replace(" ", "") for k in knobs)


def plot_task(path: str, entry: dict) -> None:
    """One task's figure: indirect RMSE against frame time, every method's points (its Pareto
    front joined) and Mitsuba's curve labelled by spp; log-log."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5))
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for c, (name, m) in zip(colours, ((n, m) for n, m in entry["methods"].items() if m["status"] == "done")):
        ok = [(i, r) for i, r in enumerate(m["points"]) if r["status"] != "failed" and r["frame_ms"] is not None]
        ax.scatter([r["frame_ms"] for _, r in ok], [r["indirect_rmse"] for _, r in ok], color=c, s=18, label=name)
        for i in m["pareto"]["frame_ms"]:  # the front's points named (all of them would overlap)
            r = m["points"][i]
            ax.annotate(_label(r, m["knobs"]), (r["frame_ms"], r["indirect_rmse"]), fontsize=5, xytext=(3, 3),
                        textcoords="offset points", color=c)
        front = sorted((m["points"][i]["frame_ms"], m["points"][i]["indirect_rmse"]) for i in m["pareto"]["frame_ms"])
        if front:
            ax.step([p[0] for p in front], [p[1] for p in front], where="post", color=c, alpha=0.7)
    curve = entry["mitsuba_curve"]
    if curve:
        ax.plot([p["ms"] for p in curve], [p["rmse"] for p in curve], "k--o", markersize=3, label="Mitsuba path tracing")
        for p in curve:
            ax.annotate(f"{p['spp']}", (p["ms"], p["rmse"]), fontsize=5, xytext=(2, -7), textcoords="offset points")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("frame time (ms, this CPU; methods: JAX evaluator, Mitsuba: full + direct render)")
    ax.set_ylabel("indirect RMSE (held-out set)")
    ax.set_title(entry["title"], fontsize=9)
    ax.grid(True, which="both", alpha=0.2)
    if ax.get_legend_handles_labels()[0]:  # a task where nothing ran has nothing to label
        ax.legend(fontsize=7)
    fig.tight_layout()
    with io.atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)


def _fmt(v, spec: str) -> str:
    return "-" if v is None or (isinstance(v, float) and math.isnan(v)) else format(v, spec)


def table(record: dict) -> str:
    """The atlas as a Markdown table: per task, every method's points on its frame-time front (and
    the most accurate point), with the common metrics and the equal-error speedup."""
    lines = []
    for t in record["tasks"].values():
        lines += [f"**{t['title']}** ({t['n_images']} held-out images at {t['resolution']}^2, references "
                  f"{t['reference_spp']} spp)", "",
                  "| method | point | RMSE | PSNR | SSIM | FLIP | LPIPS | frame ms | model KB | train s | "
                  "equal-error spp | speedup |", "|---|---|---|---|---|---|---|---|---|---|---|---|"]
        skipped = [f"{name} ({m['reason'] if m['status'] == 'skipped' else 'failed: ' + m['error']})"
                   for name, m in t["methods"].items() if m["status"] != "done"]
        for name, m in t["methods"].items():
            if m["status"] != "done":
                continue
            ok = [i for i, r in enumerate(m["points"]) if r["status"] != "failed"]
            best = min(ok, key=lambda i: m["points"][i]["indirect_rmse"], default=None)
            show = sorted(set(m["pareto"]["frame_ms"]) | ({best} if best is not None else set()),
                          key=lambda i: m["points"][i]["frame_ms"])
            for i in show:
                r = m["points"][i]
                eq = _fmt(r["equal_error_spp"], "d") if r["equal_error_reached"] else \
                    f"> {max(c['spp'] for c in t['mitsuba_curve'])}"
                lines.append(f"| {name} | {_label(r, m['knobs'])} | {_fmt(r['indirect_rmse'], '.4f')} | "
                             f"{_fmt(r['psnr_indirect'], '.1f')} | {_fmt(r['ssim_indirect'], '.3f')} | "
                             f"{_fmt(r['flip_indirect'], '.3f')} | {_fmt(r['lpips_indirect'], '.3f')} | "
                             f"{_fmt(r['frame_ms'], '.3g')} | {_fmt((r['model_bytes'] or 0) / 1024, '.0f')} | "
                             f"{_fmt(r['train_s'], '.0f')} | {eq} | {_fmt(r['speedup_equal_error'], '.1f')} |")
        c = t["mitsuba_curve"]
        lines += ["", "Not run: " + "; ".join(skipped) + "." if skipped else ""]
        lines += ["", "Mitsuba: " + ", ".join(f"{p['spp']} spp {p['rmse']:.4f} in {p['ms']:.0f} ms" for p in c), ""]
    return "\n".join(lines) + "\n"
