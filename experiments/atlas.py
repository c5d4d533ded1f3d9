"""The speed-accuracy atlas: every method of ``jprt.methods.REGISTRY`` on shared tasks, each swept
over its main size knob, against Mitsuba's own speed-accuracy curve measured in the same run.

    jprt run experiments/atlas.py --preset small     # both tasks (python benchmarks/atlas.py records it)
    jprt run experiments/atlas.py --preset test      # seconds (tests/test_atlas.py)

A **task** is a scene, a lighting kind and a held-out set that no method trains on: views and
lightings drawn from their own seeds, rendered once by Mitsuba at ``reference_spp`` (cached by
``jprt.render.dataset``), every method scored on the same images with the same masks:

* ``local_lights``: the built-in Cornell box (no area light) lit by one white point light inside
  it (RRF's light box), views in front of its opening (RRF's view box);
* ``environment``: the glossy Cornell box with its top open, relit by environment maps held out
  from neural-wavelet PRT's training (../shared/assets), seen from views around it.

A method takes part in every task whose lighting it lists in its package's
``data.TASK_LIGHTINGS``; its ``data.task_inputs(handle, dataset, camera)`` and
``data.task_lighting(handle, dataset, params, config, lighting)`` turn a task view and a task
lighting (``PointLights``, or a ``CubeMap`` whose piecewise-constant equirect Mitsuba renders)
into its evaluator's arguments. A newly registered method appears in the atlas once it has these
and an entry under ``tasks.<task>.methods`` (its size knob); until then the atlas lists it as
skipped, with the reason.

Every (task, method) is one ``jprt.sweep`` over the method's knob (each point a ``jprt.runner``
run, resumable, in ``output.dir/<task>/<method>/``); points that differ only in run-time settings
(``render.*``: wavelet PRT's K, RRF's evaluation block) share one fit. Mitsuba's curve is the
held-out set path traced at ``eval.curve_spp`` (a seed unlike the references'), its RMSE against
the references and its wall time for one frame of the timed view; each point's equal-error spp and
speedup are read off that curve. Output (``output.dir``): ``atlas.json`` (per task, per method:
the points with the common summary keys, the Pareto fronts, the Mitsuba curve), one figure per
task ``atlas_<task>.png`` (every method's points and front, Mitsuba's curve) and ``atlas.md``
(the README's table).
"""

from __future__ import annotations

import json
import math
import os
import sys
import time
import traceback
import types

import numpy as np

from jprt import eval as jeval
from jprt import io
from jprt.config import apply_overrides, merge, stable_hash
from jprt.methods import REGISTRY
from jprt.runner import HeldOut

def _dotted(overrides: dict, prefix: str = "") -> list[str]:
    """A nested override dict as ``--set`` items (``"a.b=<json>"``), leaves only."""
    out = []
    for k, v in overrides.items():
        out += _dotted(v, f"{prefix}{k}.") if isinstance(v, dict) and v else [f"{prefix}{k}={json.dumps(v)}"]
    return out


# The methods of each task: "set" (``--set`` items on top of the method's defaults and the task's
# scene) and "grid" (``--grid`` items: the size knob swept). Lists, so a preset replaces them whole.
#: Data-driven PRT's lighting scenario on the local-lights task: the task's lights (white point lights in RRF's box).
_POINT_SCENARIO = {"lights": {"kind": "point", "position_lo": [-0.6, 0.3, -0.6], "position_hi": [0.6, 0.9, 0.6],
                              "intensity": [1.0, 1.0], "saturation": 0.0, "clearance": 0.1}}

#: The Cornell box as MRT's proxy: one block spanning [-1, 1]^3, its +z side (the front) open.
_CORNELL_PROXY = {"layout": {"cells": [[0, 0]], "edges": [], "exterior": [[[0, 0], 1]]}, "origin": [-1.0, -1.0, -1.0],
                  "size": 2.0}

_LOCAL_METHODS = {
    "rrf": {
        # Ren et al. 2013 §4 at the method's default (`small`) sizes: leaves split until the error
        # threshold is met; networks of 20-10 (the paper's) or 8-4
        "set": ["train.progress=false"],
        "grid": ["model.hidden=[[8, 4], [20, 10]]", "tree.threshold=[0.02, 0.1]"],
    },
    "datadriven": {
        # Belcour et al. 2022 §4.1, the task's lights as its scenario
        "set": _dotted({**_POINT_SCENARIO, "data": {"n_test": 0}}),
        "grid": ["basis.n=[4, 16, 64]", "points.count=[64, 256]"],
    },
    "sh_prt": {"set": [], "grid": ["sh.order=[2, 3, 5]"]},
    "mrt": {
        # Loos et al. 2011 §7.2: the box as one block of the dictionary, its front open to the camera;
        # one held-out lighting of its own (it fits nothing to it)
        "set": [f"proxy.{k}={json.dumps(v)}" for k, v in _CORNELL_PROXY.items()] + _dotted({"data": {"n_test": 1,
                                                                                                "test_spp": 16}}),
        "grid": ["dictionary.k_b=[8, 32]"],
    },
}

_GLOSSY_MESHES = ["floor", "back", "green-wall", "red-wall", "small-box"]

_ENV_METHODS = {
    "wavelet_prt": {
        # Raghavan et al. 2023 at the method's `small` sizes: K is run-time only (one fit per MLP
        # width); none of the method's own near / far test views (the task has its own)
        "set": ["cameras.near=0", "cameras.far=0"],
        "grid": ["model.hidden=[64, 128]", "render.k=[16, 32, 64]"],
    },
    # the lightmap covers the meshes (the metal sphere is an analytic shape: its pixels are predicted 0,
    # and a diffuse transfer could not reflect the environment there anyway)
    "sh_prt": {"set": [f"objects={json.dumps(_GLOSSY_MESHES)}"], "grid": ["sh.order=[2, 3, 5]"]},
}

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
        "methods": _LOCAL_METHODS,
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
        "methods": _ENV_METHODS,
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
    # `minimize`, and the cheapest over all methods; each written as a config `jprt run --config` runs
    "select": "",
    "minimize": "frame_ms",
}

CONFIG = {"tasks": TASKS, "eval": EVAL, "output": {"dir": "results/atlas"}}

PRESETS = {
    "small": {},
    "test": {
        "tasks": {
            "local_lights": {
                "lights": {"n": 1}, "views": {"n": 1}, "resolution": 12, "reference_spp": 16,
                "methods": {
                    "rrf": {"set": _dotted(REGISTRY["rrf"].presets["test"]), "grid": ["model.hidden=[[4, 2], [6, 4]]"]},
                    "datadriven": {"set": _dotted(merge(REGISTRY["datadriven"].presets["test"], {"data": {"n_test": 0}}))
                                   + _dotted(_POINT_SCENARIO),
                                   "grid": ["basis.n=[2, 4]"]},
                    "sh_prt": {"set": _dotted(REGISTRY["sh_prt"].presets["test"]), "grid": ["sh.order=[2]"]},
                    "mrt": {"set": _dotted({**{k: v for k, v in REGISTRY["mrt"].presets["test"].items()
                                                if k not in ("scene", "data")}, "data": {"n_test": 1, "test_spp": 4}})
                            + [f"proxy.{k}={json.dumps(v)}" for k, v in _CORNELL_PROXY.items()],
                        "grid": ["dictionary.k_b=[4, 12]"]},
                },
            },
            "environment": {
                "envmaps": {"synthetic": 1, "rotations_deg": [0.0], "face_size": 4}, "views": {"n": 1},
                "resolution": 12, "reference_spp": 16,
                "methods": {
                    "wavelet_prt": {"set": _dotted(REGISTRY["wavelet_prt"].presets["test"]) + ["cameras.near=0",
                                                                                               "cameras.far=0"],
                                    "grid": ["render.k=[8, 16]"]},
                    "sh_prt": {"set": _dotted(REGISTRY["sh_prt"].presets["test"]) + [
                        f"objects={json.dumps(_GLOSSY_MESHES)}"], "grid": ["sh.order=[2]"]},
                },
            },
        },
        "eval": {"curve_spp": [1, 4, 16], "timing_resolution": 16, "timing_repeats": 2, "images": 1},
    },
}

_FITS: dict = {}  # fits shared by points that differ only in run-time settings (this process)
_TASK_DATA: dict = {}  # each task's held-out set, loaded once


# --------------------------------------------------------------------------------------------
# Tasks: held-out views and lightings, their references, Mitsuba's curve


def task_cameras(task: dict, resolution: int | None = None) -> list:
    """The task's held-out cameras (seeded), at ``resolution`` (default the task's)."""
    from jprt.render import cameras as cams
    from jprt.render.sampling import latin_hypercube

    v, res = task["views"], int(resolution or task["resolution"])
    rng = np.random.default_rng(int(v["seed"]))
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
    """The task's held-out lightings as methods see them: ``PointLights`` or ``CubeMap``."""
    from jprt.inputs import CubeMap, PointLights
    from jprt.render.sampling import latin_hypercube

    if task["lighting"] == "point":
        lt = task["lights"]
        positions = latin_hypercube(np.random.default_rng(int(lt["seed"])), int(lt["n"]), lt["lo"], lt["hi"])
        return [PointLights.create([p], lt["intensity"]) for p in positions]
    if task["lighting"] != "environment":
        raise ValueError(f"task lighting {task['lighting']!r}: 'point' or 'environment'")
    from jprt.methods.wavelet_prt import data as wp_data
    from jprt.methods.wavelet_prt import model as wp

    e = task["envmaps"]
    n = int(e["face_size"])
    if int(e["synthetic"]) > 0:
        return [CubeMap(c) for c in wp.synthetic_environments(int(e["synthetic"]), n, int(e["seed"]))]
    cubes, _ = wp_data.load_environments(e["names"], e["rotations_deg"], n, normalise=bool(e["normalise"]))
    return [CubeMap(c) for c in cubes]


def mitsuba_lighting(lighting):
    """What Mitsuba renders for a task lighting: point lights as they are, a cube map as the
    equirect map of its texels (``wavelet_prt.model.render_equirect``)."""
    from jprt.inputs import CubeMap
    from jprt.methods.wavelet_prt import model as wp
    from jprt.render.lights import EnvMap

    return EnvMap.create(wp.render_equirect(lighting.radiance)) if isinstance(lighting, CubeMap) else lighting


class TaskData(types.SimpleNamespace):
    """A task's held-out set: ``cameras``, ``lightings`` (method side), ``mitsuba`` (lightings as
    rendered), ``dataset`` (``jprt.render.dataset.Dataset`` of every camera x lighting),
    ``references`` / ``direct`` / ``valid`` (per item), ``labels``."""


def task_data(task: dict, progress: bool = True) -> TaskData:
    """Render (or read from the cache) the task's held-out references at ``reference_spp``."""
    from jprt.render.dataset import render_dataset

    key = stable_hash({k: v for k, v in task.items() if k != "methods"})
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
    return cams.look_at(c0.origin, c0.target, fov=c0.fov, width=int(resolution), height=int(resolution))


def mitsuba_curve(task: dict, e: dict, say=print) -> list[dict]:
    """Mitsuba's speed-accuracy curve on the task: for every spp of ``e["curve_spp"]``, the
    indirect RMSE of the held-out set path traced at that spp (full minus direct, seed
    ``curve_seed``) against the references, and the wall time (ms) of one frame of the first
    held-out view and lighting at ``timing_resolution`` (both renders)."""
    from jprt.render.images import direct_indirect
    from jprt.render.scenes import SceneHandle

    td = task_data(task)
    handle = SceneHandle(task["scene"], td.mitsuba[0])
    tr = int(e["timing_resolution"])
    timed = timed_camera(td, tr)
    curve = []
    for spp in e["curve_spp"]:
        images = []
        for it in td.dataset.items:
            handle.set_lighting(td.mitsuba[it.lighting])
            images.append(direct_indirect(handle, td.cameras[it.camera], spp=int(spp), seed=int(e["curve_seed"])).indirect)
        handle.set_lighting(td.mitsuba[0])
        direct_indirect(handle, timed, spp=1, seed=3)  # warm-up: Dr.Jit compiles for this film size
        ms = jeval.time_call(lambda: direct_indirect(handle, timed, spp=int(spp), seed=3), repeats=1, warmup=0)
        curve.append({"spp": int(spp), "ms": ms["median_ms"], "rmse": jeval.set_rmse(images, td.references, td.valid)})
        say(f"Mitsuba {spp} spp: RMSE {curve[-1]['rmse']:.5f}, {curve[-1]['ms']:.0f} ms at {tr}x{tr}")
    return curve


def equal_error(curve: list[dict], rmse: float | None, frame_ms: float | None) -> dict:
    """A point's equal-error numbers read off Mitsuba's curve: the smallest spp whose RMSE is at
    most ``rmse``, its frame time and the speedup; when no spp reaches it, spp None and the time
    of the largest spp (a lower bound, ``reached`` False)."""
    if rmse is None or not curve:
        return {"equal_error_spp": None, "pathtrace_ms_equal_error": None, "speedup_equal_error": None,
                "equal_error_reached": None}
    hit = next((c for c in sorted(curve, key=lambda c: c["spp"]) if c["rmse"] <= rmse), None)
    ms = (hit or max(curve, key=lambda c: c["spp"]))["ms"]
    return {"equal_error_spp": hit["spp"] if hit else None, "pathtrace_ms_equal_error": ms,
            "speedup_equal_error": ms / frame_ms if frame_ms else None, "equal_error_reached": hit is not None}


# --------------------------------------------------------------------------------------------
# One (task, method) as a jprt.runner experiment


def _package_data(method):
    """The ``data`` module of a method's package (where its task adapter lives)."""
    return sys.modules[method.make_dataset.__module__]


def applicability(task: dict, name: str) -> str | None:
    """None when method ``name`` runs on ``task``, else why not."""
    data = _package_data(REGISTRY[name])
    kinds = getattr(data, "TASK_LIGHTINGS", None)
    if kinds is None or (kinds and not hasattr(data, "task_inputs")):
        return f"{name} has no task adapter (data.TASK_LIGHTINGS / task_inputs / task_lighting)"
    if not kinds:
        return f"{name} is baked for its scene's own emitters and relights none of the tasks' lightings"
    if task["lighting"] not in kinds:
        return f"{name} takes {', '.join(kinds)} lighting, the task is {task['lighting']}"
    if name not in task["methods"]:
        return f"no size knob for {name} under this task's methods"
    return None


def experiment(task_name: str, task: dict, name: str, e: dict, out: str) -> types.ModuleType:
    """The ``jprt.runner`` experiment of method ``name`` on ``task``: the method's defaults, the
    task's scene and the task entry's ``set``; held-out = the task's references."""
    method = REGISTRY[name]
    adapter = _package_data(method)
    entry = task["methods"][name]
    config = apply_overrides(merge(method.default_config, {"scene": task["scene"]}), entry["set"])
    config.update(task={k: v for k, v in task.items() if k != "methods"} | {"name": task_name},
                  eval={"equal_error_spp": [], "timing_repeats": int(e["timing_repeats"]),
                        "timing_resolution": int(e["timing_resolution"]), "exposure": float(e["exposure"]),
                        "images": int(e["images"])},
                  output={"dir": os.path.join(out, task_name, name)})

    def handle(run):
        from jprt.render.scenes import SceneHandle

        if "handle" not in run.state:
            run.state["handle"] = SceneHandle(task["scene"], task_data(task).mitsuba[0])
        return run.state["handle"]

    def arguments(run, camera, lighting):
        h = handle(run)
        return (adapter.task_inputs(h, run.dataset, camera),
                adapter.task_lighting(h, run.dataset, run.result.params, run.method_config, lighting))

    def held_out(run) -> HeldOut:
        td = task_data(task)
        inputs = {}
        preds = []
        for it, valid in zip(td.dataset.items, td.valid):
            if it.camera not in inputs:
                inputs[it.camera] = adapter.task_inputs(handle(run), run.dataset, td.cameras[it.camera])
            lighting = adapter.task_lighting(handle(run), run.dataset, run.result.params, run.method_config,
                                             td.lightings[it.lighting])
            preds.append(np.where(valid[..., None], np.asarray(run.evaluate(inputs[it.camera], lighting)), 0.0))
        return HeldOut(preds, td.references, td.valid, td.direct, td.labels)

    def frame(run):
        td = task_data(task)
        return arguments(run, timed_camera(td, e["timing_resolution"]), td.lightings[0])

    def fit(run):
        key = (name, stable_hash({k: v for k, v in run.method_config.items() if k != "render"}))
        if key not in _FITS:
            t0 = time.perf_counter()
            result = method.fit(run.dataset, run.method_config)
            result.info.setdefault("train_s", time.perf_counter() - t0)
            _FITS[key] = result
        return _FITS[key]

    module = types.ModuleType(f"atlas_{task_name}_{name}")
    module.__dict__.update(METHOD=name, LABEL=f"atlas {task_name}/{name}", CONFIG=config, held_out=held_out,
                           frame=frame, fit=fit)
    return module


# --------------------------------------------------------------------------------------------
# The atlas


def main(config: dict) -> dict:
    """Run every applicable (task, method) sweep and Mitsuba's curve per task; write atlas.json,
    the figures and the table to ``output.dir``; return the record."""
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
                entry["methods"][name] = _method_sweep(config, task_name, task, name, curve, out, say)
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


def _method_sweep(config: dict, task_name: str, task: dict, name: str, curve: list, out: str, say) -> dict:
    """One method's sweep on a task: its points (with the equal-error reading off Mitsuba's
    ``curve``), front and, with ``eval.select``, the selected point."""
    from jprt.sweep import parse_grid, run_sweep

    e = config["eval"]
    module = experiment(task_name, task, name, e, out)
    grid = parse_grid(task["methods"][name]["grid"])
    sweep = run_sweep(module, module.CONFIG, grid, label=f"{task_name}/{name}")
    rows = []
    for r in sweep["rows"]:
        row = {k: v for k, v in r.items() if k != "pathtrace_curve"}
        row.update(equal_error(curve, r.get("indirect_rmse"), r.get("frame_ms")))
        rows.append(row)
    result = {"status": "done", "knobs": list(grid), "points": rows, "pareto": sweep["pareto"],
              "sweep_folder": sweep["folder"], "counts": sweep["counts"]}
    if e["select"]:
        result["selected"] = _select(config, task_name, name, rows, grid, out, say)
    return result


def _select(config: dict, task_name: str, name: str, rows: list, grid: dict, out: str, say) -> dict:
    """``jprt.sweep.select`` over one method's points: the chosen point (its knob values, the
    minimised value) and ``selected_<task>_<method>.json``, the atlas config that runs just that
    point (``jprt run experiments/atlas.py --config ...``); or the error naming the best reached."""
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
    io.write_json(path, {"experiment": os.path.abspath(__file__), "select": e["select"], "minimize": e["minimize"],
                         "point": point, "config": chosen})
    say(f"{name}: selected {point} ({e['minimize']} = {row[e['minimize']]:.4g}); run it with: jprt run "
        f"experiments/atlas.py --config {path}")
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
    ax.legend(fontsize=7)
    fig.tight_layout()
    with io.atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)


def _fmt(v, spec: str) -> str:
    return "-" if v is None or (isinstance(v, float) and math.isnan(v)) else format(v, spec)


def table(record: dict) -> str:
    """The README's table: per task, every method's points on its frame-time front (and the
    most accurate point), with the common metrics and the equal-error speedup."""
    lines = []
    for task_name, t in record["tasks"].items():
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
