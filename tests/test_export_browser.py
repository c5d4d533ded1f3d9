"""The browser side of ``jprt export``: each relightable export's ``scene.glb`` drawn by a pinned
three.js in headless Chromium (Playwright) with its ``relight.js`` material, at the run's camera
under a lighting that was not in training, read back from a float render target and compared with
jprt's evaluator on the same view and lighting; RRF's GLSL (``rrf.glsl`` through ``rrf_pass.js``)
evaluated over the run camera's G-buffer the same way (slow: ``make export-deps`` installs Chromium,
Playwright and the npm packages; ``make test-slow`` runs it)."""

import http.server
import json
import os
import shutil
import socketserver
import threading

import numpy as np
import pytest

from jprt import io
from jprt.cli import main
from jprt.config import merge
from jprt.methods import REGISTRY
from jprt.runner import save_fit

pytestmark = [pytest.mark.slow, pytest.mark.mitsuba]

JS = os.path.join(os.path.dirname(os.path.abspath(__file__)), "js")
SCREENSHOTS = os.environ.get("JPRT_SCREENSHOTS")

#: The frame compared (square, pixels a side).
SIZE = 256


def _browser_ready() -> str | None:
    if shutil.which("chromium") is None and shutil.which("chromium-browser") is None:
        return "chromium is not installed (make export-deps)"
    if not os.path.isdir(os.path.join(JS, "node_modules", "three")):
        return "the npm package three is not installed in tests/js (make export-deps)"
    try:
        import playwright.sync_api  # noqa: F401
    except ImportError:
        return "playwright is not installed (make export-deps)"
    return None


class _Quiet(http.server.SimpleHTTPRequestHandler):
    def log_message(self, *args):
        pass


def _serve(root: str):
    handler = lambda *a, **k: _Quiet(*a, directory=root, **k)  # noqa: E731
    server = socketserver.TCPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    return server


def _in_page(root, size: int, calls: list) -> list:
    """Serve the folder ``root`` (its ``index.html`` a test page), open it in headless Chromium
    (SwiftShader WebGL2) at ``size`` x ``size``, wait for ``window.ready``, and return what each
    ``(script, argument)`` of ``calls`` evaluates to, in order."""
    from playwright.sync_api import sync_playwright

    server = _serve(str(root))
    try:
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=shutil.which("chromium") or shutil.which("chromium-browser"),
                                        args=["--use-gl=angle", "--use-angle=swiftshader",
                                              "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist"])
            page = browser.new_page(viewport={"width": size, "height": size})
            page.goto(f"http://127.0.0.1:{server.server_address[1]}/index.html")
            page.wait_for_function("window.ready !== undefined", timeout=60_000)
            assert page.evaluate("window.ready") == "ok", page.evaluate("window.ready")
            results = [page.evaluate(script, argument) for script, argument in calls]
            browser.close()
    finally:
        server.shutdown()
        server.server_close()
    return results


def _site(tmp_path, export: str, page: str):
    """A folder to serve: /three (the npm package), /export (``export``), index.html (``page`` of
    tests/js) and the pages' readback module."""
    root = tmp_path / "site"
    root.mkdir(exist_ok=True)
    os.symlink(os.path.join(JS, "node_modules", "three"), root / "three")
    os.symlink(export, root / "export")
    shutil.copy(os.path.join(JS, page), root / "index.html")
    shutil.copy(os.path.join(JS, "float_target.js"), root / "float_target.js")
    return root


def _browser_frame(export: str, lighting: dict, camera: dict, size: int, tmp_path):
    """((size, size, 4) radiance and coverage (alpha 1 where a mesh is drawn), (size, size, 2) the
    atlas UV the browser drew at each pixel), float32."""
    rows, uv = _in_page(_site(tmp_path, export, "relight.html"), size,
                        [("([l, c, s]) => window.render(l, c, s)", [lighting, camera, size]),
                         ("([c, s]) => window.renderUv(c, s)", [camera, size])])
    return np.asarray(rows, np.float32).reshape(size, size, 4), np.asarray(uv, np.float32).reshape(size, size, 4)[..., :2]


@pytest.mark.parametrize("name", ["sh_prt", "datadriven", "mrt", "sg_lightfield"])
def test_browser_relighting_equals_the_evaluator(name, tmp_path):
    """Relative RMSE <= 0.01 over the pixels both cover, the browser rendering to a float target."""
    why = _browser_ready()
    if why:
        pytest.skip(why)
    from jprt.inputs import LightScale
    from jprt.render import lightmap
    from jprt.view import Session

    m = REGISTRY[name]
    config = m.resolve(m.presets["test"])
    result = m.fit(m.make_dataset(config["scene"], config), config)
    run = save_fit(str(tmp_path / "run"), name, config, result.params)
    out = str(tmp_path / "export")
    assert main(["export", run, "--out", out, "--no-onnx"]) == 0
    with open(os.path.join(out, "export.json")) as f:
        manifest = json.load(f)
    s = Session(run)
    if s.kind == "scale":  # SG light-field textures: the bake's emitters, tinted and brighter (a light scale)
        gb = lightmap.atlas_gbuffer(s.handle, lightmap.Atlas(**s.dataset.atlas), s.camera(SIZE))
        light = LightScale(np.asarray([1.6, 0.9, 0.5], np.float32))
        # relight.js shades every fragment's filtered lobes: jprt's pixel space (§6)
        want = np.asarray(m.evaluator(s.params, merge(s.method_config, {"shading": {"space": "pixel"}}))(gb, light))
    else:  # a light the model never saw: the view's default light moved and tinted
        s.set(light=tuple(np.asarray(s.state["light"]) + [0.25, -0.2, 0.15]), colour=(1.0, 0.8, 0.6), power=2.0,
              mode="indirect")
        gb, light = s.inputs(SIZE), s.method_lighting()
        want = s.prediction(SIZE)
    valid = np.asarray(gb.valid, bool)
    assert np.abs(want[valid]).max() > 0
    lighting = {k: np.asarray(v, np.float64).tolist() for k, v in light._asdict().items()}
    frame, uv = _browser_frame(out, lighting, manifest["camera"], SIZE, tmp_path)
    # the pixels where both see the same surface point: drawn by the browser, valid in jprt's
    # G-buffer, and the browser's atlas UV within a tenth of a texel of jprt's (a rasteriser's
    # sub-pixel precision moves a pixel's point by about 1 / 256 pixel; at an object's edge the
    # two may see different objects)
    res = manifest["lightmap"]["resolution"]
    same = np.abs(uv - np.asarray(gb.uv)).max(axis=-1) * res < 0.1
    covered = valid & (frame[..., 3] > 0.5) & same
    assert covered.sum() >= 0.9 * valid.sum(), (covered.sum(), valid.sum())
    got, ref = frame[..., :3][covered], want[covered]
    rel = float(np.sqrt(np.mean((got - ref) ** 2) / np.mean(ref ** 2)))
    print(f"{name}: relative RMSE {rel:.2e} over {covered.sum()} of {valid.sum()} valid pixels (float target)")
    # browser | jprt | 10 x |difference|, one exposure ($JPRT_SCREENSHOTS=docs/images keeps it)
    both = np.where(covered[..., None], frame[..., :3], 0.0)
    exposure = float(np.log2(0.7 / max(np.percentile(np.abs(want[valid]), 99), 1e-6)))
    io.write_png(os.path.join(SCREENSHOTS or str(tmp_path), f"export_{name}.png"),
                 np.concatenate([both, np.where(covered[..., None], want, 0.0), 10.0 * np.abs(both - want)], axis=1),
                 exposure=exposure)
    assert rel <= 0.01


def _rgba(a) -> np.ndarray:
    """(H, W, c <= 4) -> (H, W, 4) float32 (missing channels 0)."""
    a = np.asarray(a, np.float32)
    a = a[..., None] if a.ndim == 2 else a
    return np.concatenate([a, np.zeros(a.shape[:2] + (4 - a.shape[-1],), np.float32)], axis=-1)


def test_browser_rrf_glsl_equals_the_evaluator(tmp_path):
    """RRF's exported GLSL in WebGL2 over the run camera's G-buffer, under a light moved and
    tinted from the view's default (not a training light): relative RMSE <= 0.01 over the valid
    pixels, the browser rendering to a float target."""
    why = _browser_ready()
    if why:
        pytest.skip(why)
    from jprt.view import Session

    m = REGISTRY["rrf"]
    config = m.resolve(m.presets["test"])
    result = m.fit(m.make_dataset(config["scene"], config), config)
    run = save_fit(str(tmp_path / "run"), "rrf", config, result.params)
    out = str(tmp_path / "export")
    assert main(["export", run, "--out", out, "--no-onnx"]) == 0
    s = Session(run)
    s.set(light=tuple(np.asarray(s.state["light"]) + [0.2, -0.15, 0.1]), colour=(1.0, 0.8, 0.6), power=2.0,
          mode="indirect")
    want = s.prediction(SIZE)
    gb = s.inputs(SIZE)
    valid = np.asarray(gb.valid, bool)
    root = _site(tmp_path, out, "rrf.html")
    (root / "gbuffer").mkdir()
    fields = {"position": gb.position, "normal": gb.normal, "view": gb.view, "diffuse": gb.diffuse_albedo,
              "specular": np.concatenate([np.asarray(gb.specular_albedo), np.asarray(gb.roughness)[..., None]], -1),
              "object": np.where(valid, np.asarray(gb.object_id), -1)}
    for name, values in fields.items():
        _rgba(values).astype("<f4").tofile(str(root / "gbuffer" / f"{name}.bin"))
    lighting = {k: np.asarray(v, np.float64).tolist() for k, v in s.method_lighting()._asdict().items()}
    pixels, = _in_page(root, SIZE, [("([l, w, h]) => window.render(l, w, h)", [lighting, SIZE, SIZE])])
    frame = np.asarray(pixels, np.float32).reshape(SIZE, SIZE, 4)
    assert (frame[..., 3][valid] > 0.5).all() and (frame[..., 3][~valid] == 0).all()
    got, ref = frame[..., :3][valid], want[valid]
    assert np.abs(ref).max() > 0
    rel = float(np.sqrt(np.mean((got - ref) ** 2) / np.mean(ref ** 2)))
    print(f"rrf GLSL: relative RMSE {rel:.2e} over {valid.sum()} valid pixels (float target)")
    exposure = float(np.log2(0.7 / max(np.percentile(np.abs(want[valid]), 99), 1e-6)))
    io.write_png(os.path.join(SCREENSHOTS or str(tmp_path), "export_rrf_glsl.png"),
                 np.concatenate([frame[..., :3], want, 10.0 * np.abs(frame[..., :3] - want)], axis=1),
                 exposure=exposure)
    assert rel <= 0.01
