"""Relight a trained model interactively in the browser: ``jprt view RUN_FOLDER``.

A run folder is what ``jprt.runner`` writes (config.json, summary.json, model.npz). ``Session``
holds everything a frame needs and has no browser in it (tests use it directly):

    s = Session("results/wavelet_prt_cornell/<hash>")
    s.set(env_rotation=90.0)                      # or light=(x, y, z), colour=..., knob=..., mode=...
    frame = s.render(128)                         # evaluator (timed) + direct light + display image
    ref = s.reference(128, spp=64)                # Mitsuba's indirect of the same view and lighting

``serve`` puts a ``viser`` page on top of it: the scene's camera (orbit with the mouse, for the
methods that take a camera view), the method's lighting controls (point light position and colour
for RRF, data-driven PRT, SH-PRT and MRT; environment map and rotation for neural-wavelet PRT and
SG environment visibility (the SG light-field textures paper's §5); the bake's RGB scale for SG
light-field textures, whose run folder holds one texture atlas under its own emitters),
direct / indirect / both (a method that predicts direct light, SG environment visibility, shows
that alone), the method's run-time knob (K wavelets, MRT's feedback iterations), the
evaluator's measured frame time, and a compare mode (Mitsuba at a chosen spp, the
difference image and its RMSE). Drags render at a preview resolution and refine when they stop;
every render runs on a worker thread, so the page never waits on one (progress is shown).
"""

from __future__ import annotations

import json
import os
import re
import threading
import time
from typing import Any

import jax
import numpy as np

from jprt import io

__all__ = ["NotARunFolder", "RUN_FILES", "KNOBS", "check_run_folder", "load_params", "Session", "serve"]

#: What makes a folder a run folder (``jprt.runner.run`` writes all three).
RUN_FILES = ("config.json", "summary.json", "model.npz")

#: Each method's run-time knob: (config section, key, label, smallest value); methods not listed
#: have none (their evaluator has no setting that trades speed for accuracy without a refit).
KNOBS = {"wavelet_prt": ("render", "k", "K (wavelets)", 1), "mrt": ("runtime", "feedback", "feedback iterations", 0)}

MODES = ("direct + indirect", "indirect", "direct")


class NotARunFolder(ValueError):
    """The folder given to ``jprt view`` is not a run folder of ``jprt.runner``."""


def check_run_folder(folder: str) -> tuple[dict, dict]:
    """(summary, config) of a run folder; ``NotARunFolder`` with one line saying what is missing."""
    from jprt.methods import REGISTRY

    if not os.path.isdir(folder):
        raise NotARunFolder(f"{folder} is not a folder")
    missing = [f for f in RUN_FILES if not os.path.isfile(os.path.join(folder, f))]
    if missing:
        raise NotARunFolder(f"{folder} is not a jprt run folder (no {', '.join(missing)}; `jprt run` writes them)")
    with open(os.path.join(folder, "summary.json")) as f:
        summary = json.load(f)
    with open(os.path.join(folder, "config.json")) as f:
        config = json.load(f)
    config = config.get("config", config)  # jprt.config.save_resolved: {"hash", "config"}
    if summary.get("method") not in REGISTRY:
        raise NotARunFolder(f"{folder}: summary.json names method {summary.get('method')!r}, not one of "
                            f"{sorted(REGISTRY)}")
    return summary, config


def load_params(path: str):
    """The pytree ``jprt.io.save_checkpoint`` wrote, rebuilt from its stored tree paths
    (``jprt.io.load_tree``), without the model that made it."""
    return io.load_tree(path)[0]


class Session:
    """A trained model of a run folder and what the page can change: the camera, the lighting,
    the display mode and the run-time knob (``set``); ``render`` / ``reference`` make frames.

    ``kind`` is "point" (a point light), "environment" (an environment map and its rotation about
    +Y) or "scale" (the bake's lighting times an RGB factor: SG light-field textures, shown as
    their texture atlas, which has no camera): the method's ``Method.view_lightings``. ``predicts``
    is what the evaluator returns, "indirect" (every method but one) or "direct" (SG environment
    visibility: the environment reflected once; ``Method.predicts``); ``modes`` the display modes
    that make sense for it. Camera views and lightings become the evaluator's arguments through
    the method's task adapter (``Method.task_inputs``, ``Method.task_lighting``)."""

    def __init__(self, folder: str, *, progress: bool | None = None):
        from jprt.methods import REGISTRY
        from jprt.render.scenes import SceneHandle
        from jprt.runner import method_config

        self.folder = folder
        self.summary, self.config = check_run_folder(folder)
        self.method = REGISTRY[self.summary["method"]]
        self.method_config = method_config(self.method, self.config)
        self.params = jax.tree_util.tree_map(jax.numpy.asarray, load_params(os.path.join(folder, "model.npz")))
        import inspect

        kw = {"progress": progress} if "progress" in inspect.signature(self.method.make_dataset).parameters else {}
        self.dataset = self.method.make_dataset(self.method_config["scene"], self.method_config, **kw)
        kinds = self.method.view_lightings
        self.kind = "point" if "point" in kinds else "environment" if "environment" in kinds else "scale"
        self.predicts = self.method.predicts
        self.modes = MODES if self.predicts == "indirect" else ("direct",)
        self.handle = SceneHandle(self.method_config["scene"])
        self.knob = KNOBS.get(self.method.name)
        self._evaluators: dict = {}
        self.environments = self._environments() if self.kind == "environment" else {}
        self.state = {"mode": self.modes[0], "exposure": 0.0, "env": next(iter(self.environments), None),
                      "env_rotation": 0.0, "scale": (1.0, 1.0, 1.0),
                      "knob": (int(self.method_config[self.knob[0]][self.knob[1]]) if self.knob else None),
                      **self._default_light()}
        self.state.update(self._default_camera(self.state["light"]))
        self._inputs_key, self._inputs = None, None
        self._lighting_key, self._lighting = None, None

    # -- what the run folder holds -------------------------------------------------------------
    def _environments(self) -> dict:
        """{name: (6, n, n, 3) cube map}: the method's ``Method.view_environments`` where it has
        one; else the run's held-out maps, then its training maps that appear unrotated ("stem@0";
        per-image lightings are turned by random angles)."""
        if self.method.view_environments is not None:
            return dict(self.method.view_environments(self.dataset, self.method_config))
        names = list(getattr(self.dataset, "test_env_names", []))
        cubes = list(np.asarray(getattr(self.dataset, "test_envs", np.zeros((0,)))))
        for name, cube in zip(getattr(self.dataset, "env_names", []), np.asarray(getattr(self.dataset, "envs", []))):
            stem = name.split("@")[0]
            if re.fullmatch(r"[^@]+@0(\.0)?", name) and stem not in names:
                names.append(stem)
                cubes.append(cube)
        if not names:
            raise ValueError(f"{self.folder}: the run's dataset has no environment maps to relight with")
        return dict(zip(names, cubes))

    def _default_light(self) -> dict:
        """{"light", "colour", "power"}: RRF's the middle of its trained light box (white, 1); else
        the run's first held-out light (its position, colour and power); else above the middle of
        the scene (white, 1)."""
        white = {"colour": (1.0, 1.0, 1.0), "power": 1.0}
        meta = getattr(self.dataset, "meta", None)
        if isinstance(meta, dict) and "light_lo" in meta:
            return dict(white, light=tuple(float(v) for v in (np.asarray(meta["light_lo"])
                                                              + np.asarray(meta["light_hi"])) / 2))
        held = getattr(self.dataset, "lights_test", None)
        if isinstance(held, dict) and len(np.asarray(held.get("position", []))):
            i = np.asarray(held["intensity"], np.float64).reshape(-1, 3)[0]
            return {"light": tuple(float(v) for v in np.asarray(held["position"]).reshape(-1, 3)[0]),
                    "power": float(i.max()), "colour": tuple(float(v) for v in i / max(i.max(), 1e-12))}
        box = self.handle.scene.bbox()
        lo, hi = np.asarray(box.min, np.float64), np.asarray(box.max, np.float64)
        c = (lo + hi) / 2
        return dict(white, light=(float(c[0]), float(c[1] + 0.3 * (hi[1] - lo[1])), float(c[2])))

    def _default_camera(self, light) -> dict:
        if self.handle.description["name"] in ("cornell_box", "glossy_cornell", "xml"):
            cam = self.handle.default_camera(64, 64)
            return {"origin": tuple(cam.origin), "target": tuple(cam.target), "up": tuple(cam.up), "fov": cam.fov,
                    "aspect": 1.0}
        # other scenes (MRT's block layouts): from the default light (inside the lit space) towards
        # the middle of the scene, wide
        box = self.handle.scene.bbox()
        c = (np.asarray(box.min, np.float64) + np.asarray(box.max, np.float64)) / 2
        origin = np.asarray(light, np.float64)
        if np.linalg.norm(origin - c) < 1e-3:
            c = c + np.array([0.0, 0.0, -1.0])
        return {"origin": tuple(origin), "target": tuple(c), "up": (0.0, 1.0, 0.0), "fov": 80.0, "aspect": 1.0}

    # -- state ---------------------------------------------------------------------------------
    def set(self, **changes) -> None:
        """Change the state: origin / target / up / fov / aspect (the camera; frames are ``size``
        high and ``size * aspect`` wide), light / colour / power (the point light), env /
        env_rotation (degrees), scale (RGB), mode, knob, exposure. Raises on an unknown key or
        value."""
        unknown = sorted(set(changes) - set(self.state))
        if unknown:
            raise KeyError(f"unknown view settings {unknown}; known: {sorted(self.state)}")
        if "mode" in changes and changes["mode"] not in self.modes:
            raise ValueError(f"mode must be one of {self.modes}, got {changes['mode']!r}")
        if "env" in changes and changes["env"] not in self.environments:
            raise ValueError(f"unknown environment {changes['env']!r}; known: {list(self.environments)}")
        if changes.get("knob") is not None and self.knob and int(changes["knob"]) < self.knob[3]:
            raise ValueError(f"{self.knob[2]} must be >= {self.knob[3]}, got {changes['knob']}")
        self.state.update(changes)

    def camera(self, size: int):
        from jprt.render.cameras import look_at

        s = self.state
        return look_at(s["origin"], s["target"], s["up"], fov=float(s["fov"]),
                       width=max(1, round(size * float(s["aspect"]))), height=size)

    def _lightings(self):
        """(Mitsuba's lighting or None, the evaluator's lighting) of the current state, made once
        per lighting state (the map's rotation resamples it; data-driven PRT and MRT measure
        direct light with Mitsuba in their task adapter)."""
        from jprt.inputs import CubeMap, LightScale, PointLights
        from jprt.render.lights import EnvMap
        from jprt.sphere.envmap import prepare_environment, render_equirect, rotate_equirect

        s = self.state
        key = {"point": ("light", "colour", "power"), "environment": ("env", "env_rotation"),
               "scale": ("scale",)}[self.kind]
        key = tuple(s[k] for k in key)
        if key == self._lighting_key:
            return self._lighting
        if self.kind == "scale":
            scene, task = None, LightScale(np.asarray(s["scale"], np.float32))
        else:
            if self.kind == "point":
                scene = task = PointLights.create([s["light"]], [np.asarray(s["colour"], np.float32) * float(s["power"])])
            else:  # the chosen map turned about +Y (through its equirect, back at the face size)
                cube = np.asarray(self.environments[s["env"]], np.float32)
                if float(s["env_rotation"]) % 360.0 != 0.0:
                    e = rotate_equirect(render_equirect(cube), float(s["env_rotation"]))
                    cube = prepare_environment(e, int(cube.shape[1]), normalise=False)
                scene = EnvMap.create(render_equirect(cube))
                task = CubeMap(cube)
            self.handle.set_lighting(scene)
            task = self.method.task_lighting(self.handle, self.dataset, self.params, self.method_config, task)
        self._lighting_key, self._lighting = key, (scene, task)
        return self._lighting

    def scene_lighting(self):
        """The lighting Mitsuba renders with (``jprt.inputs``), or None for the scene's own emitters."""
        return self._lightings()[0]

    def method_lighting(self):
        """The lighting the evaluator takes, from the state (the method's task adapter)."""
        return self._lightings()[1]

    def inputs(self, size: int):
        """The evaluator's inputs for the camera at ``size`` x ``size`` (cached per camera)."""
        s = self.state
        key = (size, s["origin"], s["target"], s["up"], s["fov"], s["aspect"])
        if key != self._inputs_key:
            if self.kind == "scale":
                self._inputs = self.method.example(self.dataset, self.method_config)[0]
            else:
                self._inputs = self.method.task_inputs(self.handle, self.dataset, self.camera(size))
            self._inputs_key = key
        return self._inputs

    def evaluator(self, *, gradient: bool = False):
        """The jitted evaluator at the current knob (one per knob value, kept); with ``gradient``
        the method's ``gradient_evaluator`` where it has one (the same image by a program that
        reverse-mode differentiation goes through), not jitted (it is traced inside the caller's
        gradient program)."""
        from jprt.config import merge

        k = self.state["knob"]
        key = ("gradient", k) if gradient else k
        if key not in self._evaluators:
            config = self.method_config
            if self.knob:
                config = self.method.resolve(merge(config, {self.knob[0]: {self.knob[1]: int(k)}}))
            if gradient:
                self._evaluators[key] = (self.method.gradient_evaluator or self.method.evaluator)(self.params, config)
            else:
                self._evaluators[key] = jax.jit(self.method.evaluator(self.params, config))
        return self._evaluators[key]

    # -- frames --------------------------------------------------------------------------------
    def prediction(self, size: int) -> np.ndarray:
        """The evaluator's radiance (H, W, 3) for the current state (indirect light, or direct
        light where ``predicts`` says so)."""
        return np.asarray(self.evaluator()(self.inputs(size), self.method_lighting()))

    def frame_ms(self, size: int, repeats: int = 15, block_ms: float = 40.0) -> float:
        """Time of one evaluator call at ``size`` (compiled, inputs and lighting ready), in ms: the
        fastest of ``repeats`` blocks, each block ``n`` frames in one jitted loop (``n`` chosen so
        a block takes at least ``block_ms``), divided by ``n``. The loop keeps Python's dispatch
        (about 0.1 ms a call here, and at the mercy of every other thread holding the GIL: a
        server's event loop, a browser's driver) out of the number, so it is the evaluator's own
        cost; each frame's lighting is scaled by 1 + 1e-30 x the last frame's mean, a dependency
        XLA cannot drop, at the cost of one reduction per frame."""
        evaluate, inputs, lighting = self.evaluator(), self.inputs(size), self.method_lighting()
        key = ("loop", self.state["knob"], size, self.state["aspect"], float(block_ms))
        if key not in self._evaluators:  # n frames a block, fixed per frame shape (one compile)
            jax.block_until_ready(evaluate(inputs, lighting))
            t0 = time.perf_counter()
            jax.block_until_ready(evaluate(inputs, lighting))
            n = max(1, int(np.ceil(block_ms / max(1e3 * (time.perf_counter() - t0), 1e-3))))
            loop = _frame_loop(evaluate, n)
            jax.block_until_ready(loop(inputs, lighting))
            t0 = time.perf_counter()
            jax.block_until_ready(loop(inputs, lighting))
            block = 1e3 * (time.perf_counter() - t0)
            if block < 0.5 * block_ms:  # a call was mostly dispatch: size the block by the loop itself
                n = int(np.ceil(n * block_ms / max(block, 1e-3)))
                loop = _frame_loop(evaluate, n)
            self._evaluators[key] = (loop, n)
        loop, n = self._evaluators[key]
        # warm-up of about 0.3 s: measured here, the first 0.6 s of a freshly compiled loop ran
        # 1.8x slower than the rest
        for _ in range(max(2, int(np.ceil(300.0 / block_ms)))):
            jax.block_until_ready(loop(inputs, lighting))
        times = []
        for _ in range(max(1, int(repeats))):
            t0 = time.perf_counter()
            jax.block_until_ready(loop(inputs, lighting))
            times.append(1e3 * (time.perf_counter() - t0) / n)
        return float(np.min(times))

    def direct(self, size: int, spp: int = 4) -> np.ndarray:
        """Direct light: Mitsuba (``max_depth = 2``) at ``spp``, the source every method here uses
        for its direct term; zero for the SG texture atlas (no camera view to render it from)."""
        from jprt.render import images

        if self.kind == "scale":
            return np.zeros(np.shape(self.inputs(size).valid) + (3,), np.float32)
        self.handle.set_lighting(self.scene_lighting())
        return np.asarray(images.render(self.handle, self.camera(size), spp=spp, max_depth=2, seed=7), np.float32)

    def reference(self, size: int, spp: int, *, seed: int = 11, passes: int = 1, progress=None) -> np.ndarray:
        """Mitsuba's counterpart of the prediction for the same view and lighting: its indirect
        (full minus direct, same seed), or its direct light (``max_depth = 2``) where the method
        predicts direct light; the mean of ``passes`` renders of ``spp / passes`` each
        (``progress(i, passes)`` after each). Pixels outside the model's G-buffer (``valid``:
        geometry a lightmap atlas does not cover, the environment seen directly) are 0, as in the
        prediction."""
        from jprt.render import images

        if self.kind == "scale":
            raise ValueError("compare needs a camera view: the SG texture atlas has none")
        self.handle.set_lighting(self.scene_lighting())
        passes = max(1, min(int(passes), int(spp)))
        acc = 0.0
        for i in range(passes):
            n = max(1, int(spp) // passes)
            if self.predicts == "direct":
                r = images.render(self.handle, self.camera(size), spp=n, max_depth=2, seed=seed + i)
            else:
                r = images.direct_indirect(self.handle, self.camera(size), spp=n, seed=seed + i).indirect
            acc = acc + np.asarray(r, np.float32)
            if progress is not None:
                progress(i + 1, passes)
        valid = getattr(self.inputs(size), "valid", None)
        return acc / passes if valid is None else np.where(np.asarray(valid, bool)[..., None], acc / passes, 0.0)

    def render(self, size: int, *, direct_spp: int = 4, time_repeats: int = 0) -> dict:
        """One frame: {"prediction" (the evaluator's output), "indirect", "direct", "image"
        (linear, by mode), "display" (uint8 sRGB), "eval_ms" (this call of the evaluator),
        "frame_ms" (``frame_ms`` over ``time_repeats`` blocks, None for 0), "stats" (of the
        prediction)}. A method that predicts direct light has no indirect term here (zeros)."""
        inputs, lighting = self.inputs(size), self.method_lighting()
        evaluate = self.evaluator()
        t0 = time.perf_counter()
        predicted = np.asarray(jax.block_until_ready(evaluate(inputs, lighting)))
        eval_ms = 1e3 * (time.perf_counter() - t0)
        frame_ms = self.frame_ms(size, time_repeats) if time_repeats else None
        mode = self.state["mode"]
        if self.predicts == "direct":
            direct, indirect = predicted, np.zeros_like(predicted)
        else:
            indirect = predicted
            direct = self.direct(size, direct_spp) if mode != "indirect" else np.zeros_like(indirect)
        image = {"indirect": indirect, "direct": direct, "direct + indirect": direct + indirect}[mode]
        return {"prediction": predicted, "indirect": indirect, "direct": direct, "image": image, "eval_ms": eval_ms,
                "frame_ms": frame_ms, "display": io.preview_pixels(image, exposure=float(self.state["exposure"])),
                "stats": image_stats(predicted)}


def _frame_loop(evaluate, n: int):
    """``n`` evaluator calls in one jitted ``fori_loop`` (``Session.frame_ms``)."""
    import jax.numpy as jnp

    @jax.jit
    def loop(inputs, lighting):
        def body(_, carry):
            scale = 1.0 + 1e-30 * carry
            lit = jax.tree_util.tree_map(
                lambda a: a * scale.astype(a.dtype) if jnp.issubdtype(a.dtype, jnp.floating) else a, lighting)
            return jnp.mean(evaluate(inputs, lit)).astype(jnp.float32)

        return jax.lax.fori_loop(0, n, body, jnp.float32(0.0))

    return loop


def image_stats(image) -> dict:
    """Mean / max per channel and the mean over pixels of the channel sum of an image: what the
    page prints, so a test can check the shown frame against the evaluator."""
    a = np.asarray(image, np.float64).reshape(-1, 3)
    return {"mean": [float(v) for v in a.mean(0)], "max": [float(v) for v in a.max(0)],
            "sum_mean": float(a.sum(1).mean())}


def _fmt(v) -> str:
    return ",".join(f"{x:.7g}" for x in v) if isinstance(v, (list, tuple)) else f"{v:.7g}"


def serve(folder: str, *, host: str = "127.0.0.1", port: int = 8080, preview: int = 48, size: int = 128,
          refine_after_s: float = 0.3, timing_after_s: float = 1.0, stop_event: threading.Event | None = None) -> None:
    """Serve the viewer of ``folder`` on http://host:port until Ctrl-C (or ``stop_event``)."""
    import viser

    session = Session(folder, progress=True)
    server = viser.ViserServer(host=host, port=port, verbose=False)
    m = session.method
    gui = server.gui
    gui.add_markdown(f"**{m.name}** — {m.paper}\n\nrun `{os.path.basename(os.path.abspath(folder))}`; "
                     + ("the texture atlas seen head-on: indirect only (no camera view to render direct light from)"
                        if session.kind == "scale" else
                        "the prediction is direct light (the environment reflected once); compare renders Mitsuba's "
                        "direct light" if session.predicts == "direct" else
                        "direct light: Mitsuba at low spp (the source the method uses)"))
    status = gui.add_markdown("status: loading")
    stats_md = gui.add_markdown("stats: -")
    view_md = gui.add_markdown("state: -")
    timing = gui.add_markdown("frame: -")
    bar = gui.add_progress_bar(0.0)
    image = gui.add_image(np.zeros((size, size, 3), np.uint8), label="frame", format="png")
    mode = gui.add_dropdown("mode", session.modes, initial_value=session.state["mode"])
    exposure = gui.add_number("exposure", 0.0, step=0.5)
    controls: dict[str, Any] = {}
    if session.kind == "point":
        for i, axis in enumerate("xyz"):
            controls[f"light {axis}"] = gui.add_number(f"light {axis}", round(session.state["light"][i], 4), step=0.05)
        controls["colour"] = gui.add_rgb("light colour", tuple(int(round(255 * c)) for c in session.state["colour"]))
        controls["power"] = gui.add_number("light power", round(session.state["power"], 4), min=0.0, step=0.1)
    elif session.kind == "environment":
        controls["env"] = gui.add_dropdown("environment", list(session.environments), initial_value=session.state["env"])
        controls["rotation"] = gui.add_number("map rotation", 0.0, step=15.0)
    else:
        for i, c in enumerate("rgb"):
            controls[f"scale {c}"] = gui.add_number(f"scale {c}", 1.0, min=0.0, step=0.1)
    knob = gui.add_number(session.knob[2], session.state["knob"], min=session.knob[3], step=1) if session.knob else None
    compare = gui.add_checkbox("compare with Mitsuba", False, disabled=session.kind == "scale")
    spp = gui.add_number("Mitsuba spp", 64, min=1, step=16)

    lock = threading.Condition()
    request = {"generation": 0, "done": -1}

    def schedule(_=None):
        with lock:
            request["generation"] += 1
            lock.notify()

    def read_controls():
        changes = {"mode": mode.value, "exposure": float(exposure.value)}
        if session.kind == "point":
            changes["light"] = tuple(float(controls[f"light {a}"].value) for a in "xyz")
            changes["colour"] = tuple(c / 255.0 for c in controls["colour"].value)
            changes["power"] = float(controls["power"].value)
        elif session.kind == "environment":
            changes["env"], changes["env_rotation"] = controls["env"].value, float(controls["rotation"].value)
        else:
            changes["scale"] = tuple(float(controls[f"scale {c}"].value) for c in "rgb")
        if knob is not None:
            changes["knob"] = int(knob.value)
        return changes

    for handle in [mode, exposure, knob, compare, spp, *controls.values()]:
        if handle is not None:
            handle.on_update(schedule)

    @server.on_client_connect
    def _(client):
        if session.kind == "scale":
            return
        s = session.state
        client.camera.position, client.camera.look_at = s["origin"], s["target"]
        client.camera.up_direction, client.camera.fov = s["up"], np.radians(float(s["fov"]))

        @client.camera.on_update
        def _(cam):
            with lock:  # viser's fov is vertical, ours along the smaller axis: equal when wider than high
                request["camera"] = dict(origin=tuple(float(v) for v in cam.position),
                                         target=tuple(float(v) for v in cam.look_at),
                                         up=tuple(float(v) for v in cam.up_direction), fov=float(np.degrees(cam.fov)),
                                         aspect=max(1.0, float(cam.aspect)))
            schedule()

    def show(frame, res, generation, state, note=""):
        image.image = frame.get("panels", frame["display"])
        server.scene.set_background_image(frame["display"], format="png")
        h, w = frame["prediction"].shape[:2]
        keys = ["exposure"] + ([] if session.kind == "scale" else ["origin", "target", "up", "fov", "aspect"]) \
            + {"point": ["light", "colour", "power"], "environment": ["env_rotation"], "scale": ["scale"]}[session.kind] \
            + (["knob"] if session.knob else [])
        view_md.content = "state: " + " ".join(  # what the frame was rendered with, at full precision
            f"{k}={','.join(repr(float(v)) for v in np.ravel(state[k]))}" for k in keys) \
            + (f" env={state['env']}" if session.kind == "environment" else "")
        stats_md.content = (f"stats ({session.predicts}, {w}x{h}, generation {generation}): mean={_fmt(frame['stats']['mean'])} "
                            f"max={_fmt(frame['stats']['max'])} sum_mean={_fmt(frame['stats']['sum_mean'])}{note}")

    stop = stop_event or threading.Event()

    def worker():
        while not stop.is_set():
            with lock:
                if request["generation"] == request["done"]:
                    lock.wait(timeout=0.2)
                    continue
                generation = request["generation"]
            try:
                with lock:
                    session.set(**read_controls(), **request.pop("camera", {}))
                    state = dict(session.state)
                status.content = f"status: rendering preview {preview}x{preview}"
                show(session.render(preview), preview, generation, state)
                time.sleep(refine_after_s)  # still dragging? then the next request wins
                with lock:
                    if request["generation"] != generation:
                        continue
                status.content = f"status: refining {size}x{size}"
                bar.value = 0.0
                frame = session.render(size)
                note = ""
                if compare.value and session.kind != "scale":
                    def progress(i, n):
                        bar.value = 100.0 * i / n
                        status.content = f"status: Mitsuba {int(spp.value)} spp, pass {i} of {n}"
                    ref = session.reference(size, int(spp.value), passes=4, progress=progress)
                    diff = frame["prediction"] - ref
                    rmse = float(np.sqrt(np.mean(np.square(diff))))
                    exposure_now = float(session.state["exposure"])
                    shown = ref if session.predicts == "direct" else ref + frame["direct"]
                    frame["panels"] = np.concatenate([frame["display"], io.preview_pixels(shown, exposure=exposure_now),
                                                      io.preview_pixels(np.abs(diff) * 4.0, exposure=exposure_now)], axis=1)
                    note = (f" | compare: model / Mitsuba {int(spp.value)} spp / 4x |difference|; "
                            f"{session.predicts} RMSE={rmse:.6g}")
                with lock:
                    if request["generation"] != generation:
                        continue
                show(frame, size, generation, state, note)
                bar.value = 100.0
                status.content = f"status: ready (generation {generation})"
                request["done"] = generation
                # the frame time, once the browser has drawn the frame: timed at once it read 1.2-2x
                # slower than in another process (software WebGL drawing, other work on 2 cores)
                stop.wait(timing_after_s)
                with lock:
                    if request["generation"] != generation or stop.is_set():
                        continue
                # three measurements, the fastest: this VM has transient slow spells (one whole
                # measurement came out 2x slower than the others)
                ms = min(session.frame_ms(size) for _ in range(3))
                timing.content = (f"frame: evaluator {ms:.4g} ms at {frame['prediction'].shape[1]}x{size} (generation "
                                  f"{generation}; fastest of 3 x 15 jitted loops of >= 40 ms; the method's lighting "
                                  f"transform and direct light not included)")
            except Exception as e:  # keep serving: show the error on the page
                status.content = f"status: error: {type(e).__name__}: {e}"
                request["done"] = generation

    thread = threading.Thread(target=worker, daemon=True)
    thread.start()
    schedule()
    print(f"jprt view: {m.name} run at http://{host}:{server.get_port()} (Ctrl-C stops)", flush=True)
    try:
        while not stop.is_set():
            time.sleep(0.2)
    except KeyboardInterrupt:
        pass
    finally:  # let the worker finish its render (a thread inside XLA at exit can crash the interpreter)
        stop.set()
        with lock:
            lock.notify()
        thread.join(timeout=60)
        server.stop()
        print("jprt view: stopped", flush=True)
