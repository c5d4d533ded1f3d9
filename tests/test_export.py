"""``jprt export``: the manifest, the exact parameter buffers and the round trip through
``jprt.export.load`` for every exported method, the glTF of the lightmap methods (structure with
pygltflib, 0 errors from the Khronos glTF-Validator when ``make export-deps`` installed it), the
relightable parts against the params, and the ONNX of the neural evaluators against JAX.

Each method's ``test`` preset is fitted and exported once (``_exported``) and shared by the tests.
"""

import json
import os
import shutil
import subprocess

import jax
import numpy as np
import pytest

from jprt import io
from jprt.cli import main
from jprt.export import LIGHTMAP_METHODS, ONNX_METHODS, NotAnExport, load, read_manifest
from jprt.export import bundle, gltf
from jprt.export import onnx as jonnx
from jprt.methods import REGISTRY
from jprt.runner import save_fit
from jprt.view import load_params

pytestmark = pytest.mark.mitsuba

JS = os.path.join(os.path.dirname(os.path.abspath(__file__)), "js")
_CACHE: dict = {}

#: The ONNX model's frame in these tests (the export's --size): small, so conversion is quick.
ONNX_SIZE = 8


@pytest.fixture(scope="module")
def exported(tmp_path_factory, fitted_preset):
    """``get(name) -> (run folder, export folder, method, config, FitResult, dataset)``, fitted
    (``conftest.fitted_preset``) and exported once per method for the whole module."""

    def get(name):
        if name not in _CACHE:
            m, config, dataset, result = fitted_preset(name)
            run = save_fit(str(tmp_path_factory.mktemp(f"run_{name}")), name, config, result.params)
            out = str(tmp_path_factory.mktemp(f"export_{name}"))
            assert main(["export", run, "--out", out, "--size", str(ONNX_SIZE)]) == 0
            _CACHE[name] = (run, out, m, config, result, dataset)
        return _CACHE[name]

    return get


ALL = list(LIGHTMAP_METHODS + ONNX_METHODS)
#: The parametrisations over every method: neural-wavelet PRT's and SG environment's fits and ONNX
#: conversions are the slowest of the module, so their cases run with the slow tests (`make
#: test-slow`); RRF keeps the ONNX check in the default suite.
SLOW = ("wavelet_prt", "sg_environment")
EVERY = [pytest.param(n, marks=pytest.mark.slow) if n in SLOW else n for n in ALL]


def test_every_registered_method_has_an_export():
    assert sorted(ALL) == sorted(REGISTRY)


@pytest.mark.parametrize("name", EVERY)
def test_manifest_says_what_the_model_is_and_what_each_file_holds(exported, name):
    run, out, m, config, _, _ = exported(name)
    manifest = read_manifest(out)
    assert set(manifest) <= set(bundle.MANIFEST_KEYS)
    assert manifest["method"] == name and manifest["paper"] == m.paper
    assert manifest["lighting_type"] == m.lighting.__name__ and manifest["predicts"] == m.predicts
    assert set(manifest["lighting"]) == set(m.lighting._fields)
    from jprt import __version__

    assert manifest["jprt_version"] == __version__
    with open(os.path.join(run, "summary.json")) as f:
        assert manifest["config_hash"] == json.load(f)["config_hash"]
    assert manifest["config"] == json.loads(json.dumps(config))
    assert {"radiance", "position"} <= set(manifest["units"])
    on_disk = {os.path.relpath(os.path.join(d, f), out) for d, _, fs in os.walk(out) for f in fs}
    assert on_disk == set(manifest["files"]) | {bundle.MANIFEST}
    for rel, entry in manifest["files"].items():
        assert entry["holds"] and entry["format"], rel
    assert ("lightmap" in manifest) == (name in LIGHTMAP_METHODS)
    assert ("onnx" in manifest) == (name in ONNX_METHODS)
    assert ("relight.js" in manifest["files"]) == (name in LIGHTMAP_METHODS)  # every lightmap method relights


@pytest.mark.parametrize("name", EVERY)
def test_params_buffers_are_the_fitted_params_bit_for_bit(exported, name):
    run, out, *_ = exported(name)
    manifest = read_manifest(out)
    got = bundle.read_params(out, manifest["params"])
    want = load_params(os.path.join(run, "model.npz"))
    assert jax.tree_util.tree_structure(got) == jax.tree_util.tree_structure(want)
    for a, b in zip(jax.tree_util.tree_leaves(got), jax.tree_util.tree_leaves(want)):
        assert a.dtype == np.asarray(b).dtype and a.shape == np.shape(b)
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("name", EVERY)
def test_load_gives_an_evaluator_equal_to_the_original(exported, name):
    _, out, m, config, result, dataset = exported(name)
    back = load(out)
    assert back.method.name == name and back.config == config
    inputs, lighting = m.example(dataset, config)
    want = np.asarray(jax.jit(m.evaluator(result.params, config))(inputs, lighting))
    np.testing.assert_array_equal(np.asarray(jax.jit(back.evaluate)(inputs, lighting)), want)


def test_load_refuses_a_folder_that_is_not_an_export(tmp_path):
    with pytest.raises(NotAnExport, match="not a jprt export"):
        load(str(tmp_path))
    (tmp_path / bundle.MANIFEST).write_text(json.dumps({"format": "jprt-export", "format_version": 99}))
    with pytest.raises(NotAnExport, match="version 99"):
        load(str(tmp_path))


def test_cli_refuses_a_folder_that_is_not_a_run(tmp_path, capsys):
    assert main(["export", str(tmp_path), "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("jprt: error:") and "not a jprt run folder" in err and "\n" not in err


# --------------------------------------------------------------------------------------------
# Lightmap methods: glTF, lightmaps, relightable parts


def test_rgbm_round_trips_within_its_quantisation():
    rng = np.random.default_rng(0)
    x = rng.uniform(0.0, 8.0, (16, 16, 3)) * rng.uniform(0.0, 1.0, (16, 16, 1)) ** 3
    back = gltf.rgbm_decode(gltf.rgbm_encode(x, 8.0), 8.0)
    step = (np.max(x, axis=-1, keepdims=True) + 8.0 / 255.0) / 255.0
    assert np.all(np.abs(back - x) <= 0.5 * step * (1 + 1e-5))


def _accessor(doc, blob, index):
    acc = doc.accessors[index]
    view = doc.bufferViews[acc.bufferView]
    width = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4}[acc.type]
    assert acc.componentType == 5126 and view.byteLength == acc.count * width * 4
    start = (view.byteOffset or 0) + (acc.byteOffset or 0)
    return np.frombuffer(blob[start:start + view.byteLength], "<f4").reshape(acc.count, width)


@pytest.mark.parametrize("name", LIGHTMAP_METHODS)
def test_gltf_holds_the_atlas_meshes_and_references_the_lightmap(exported, name):
    import pygltflib

    _, out, m, config, result, dataset = exported(name)
    manifest = read_manifest(out)
    doc = pygltflib.GLTF2().load(os.path.join(out, "scene.glb"))
    blob = doc.binary_blob()
    assert doc.asset.version == "2.0" and gltf.EXTENSION in doc.extensionsUsed
    assert len(doc.meshes) == len(doc.nodes) == len(doc.materials) >= 1
    assert doc.buffers[0].byteLength == len(blob)
    for mesh in doc.meshes:
        prim = mesh.primitives[0]
        pos = _accessor(doc, blob, prim.attributes.POSITION)
        acc = doc.accessors[prim.attributes.POSITION]
        np.testing.assert_array_equal(acc.min, pos.min(axis=0))
        np.testing.assert_array_equal(acc.max, pos.max(axis=0))
        normal = _accessor(doc, blob, prim.attributes.NORMAL)
        uv1 = _accessor(doc, blob, prim.attributes.TEXCOORD_1)
        assert len(pos) == len(normal) == len(uv1) == len(_accessor(doc, blob, prim.attributes.TEXCOORD_0))
        assert len(pos) % 3 == 0 and prim.mode == 4
        np.testing.assert_allclose(np.linalg.norm(normal, axis=1), 1.0, atol=1e-5)
        assert uv1.min() >= 0.0 and uv1.max() <= 1.0
        ext = doc.materials[prim.material].extensions[gltf.EXTENSION]
        assert ext["index"] == 0 and ext["texCoord"] == 1 and ext["encoding"] == "RGBM"
        assert ext["rgbmRange"] == manifest["lightmap"]["rgbm_range"]
    # the embedded image is the RGBM PNG beside it, and decodes to lightmap.exr
    view = doc.bufferViews[doc.images[0].bufferView]
    png = blob[view.byteOffset:view.byteOffset + view.byteLength]
    with open(os.path.join(out, "lightmap_rgbm.png"), "rb") as f:
        assert png == f.read()
    from PIL import Image
    import io as pyio

    rgbm = np.asarray(Image.open(pyio.BytesIO(png)))
    exr = io.read_exr(os.path.join(out, "lightmap.exr"))
    res = manifest["lightmap"]["resolution"]
    assert rgbm.shape == (res, res, 4) and exr.shape == (res, res, 3)
    r = manifest["lightmap"]["rgbm_range"]
    assert exr.min() >= 0.0
    # RGBM's rounding: half a step of the pixel's scale a x range / 255^2, a >= its peak / range
    step = (np.max(exr, axis=-1, keepdims=True) + r / 255.0) / 255.0
    assert np.all(np.abs(gltf.rgbm_decode(rgbm, r) - exr) <= 0.5 * step * (1 + 1e-5))


@pytest.mark.parametrize("name", ["datadriven", "sh_prt", "mrt"])
def test_lightmap_radiance_is_the_evaluator_at_the_texels(exported, name):
    """lightmap_radiance.exr is the evaluator on the atlas under the manifest's lighting, and
    lightmap.exr is pi x it / albedo where the albedo reflects."""
    from jprt import inputs as jin

    _, out, m, config, result, dataset = exported(name)
    manifest = read_manifest(out)
    baked = manifest["lightmap"]["lighting"]
    lighting = getattr(jin, baked.pop("type"))(**{k: np.asarray(v, np.float32) for k, v in baked.items()})
    atlas = m.example(dataset, config)[0]
    want = np.asarray(jax.jit(m.evaluator(result.params, config))(atlas, lighting))
    got = io.read_exr(os.path.join(out, "lightmap_radiance.exr"))
    valid = np.asarray(atlas.valid, bool)
    np.testing.assert_array_equal(got[valid], want[valid])
    e = io.read_exr(os.path.join(out, "lightmap.exr"))
    assert np.all(np.isfinite(e)) and e.min() >= 0.0 and e[valid].max() > 0.0


def test_relightable_parts_are_the_params(exported):
    """Each method's textures and buffers hold its params at the atlas's texels, as the atlas shows
    them (``fill_index``: a texel no view sees shows the nearest seen texel of its object)."""
    from jprt.export.engine import texel_materials
    from jprt.view import Session

    for name in LIGHTMAP_METHODS:
        run, out, m, config, result, dataset = exported(name)
        p = result.params
        res = int(round(np.sqrt(np.asarray(p["fill_index"]).size)))
        texels = np.asarray(p["texel_index"] if "texel_index" in p else dataset.atlas["texel_index"])
        row, col = texels // res, texels % res
        shown = np.asarray(p["fill_index"])[texels]  # the texel each texel's atlas pixel shows
        if name == "datadriven":
            channels = io.read_exr(os.path.join(out, "basis.exr"), None)
            basis = np.asarray(p["basis"])
            for i in range(basis.shape[1]):
                np.testing.assert_array_equal(channels[f"b{i:02d}"][row, col], basis[shown, i])
            np.testing.assert_array_equal(channels["mean"][row, col], np.asarray(p["mean"])[shown])
            pts = np.fromfile(os.path.join(out, "measurement_points.bin"), "<f4").reshape(-1, 6)
            fine = np.asarray(p["fine_index"])
            np.testing.assert_array_equal(pts[:, :3], np.asarray(dataset.candidates["position"])[fine])
        elif name == "sh_prt":
            channels = io.read_exr(os.path.join(out, "sh_transfer.exr"), None)
            t = np.asarray(p["transfer"])
            for i in range(t.shape[1]):
                for c, ch in enumerate("RGB"):
                    np.testing.assert_array_equal(channels[f"c{i:02d}.{ch}"][row, col], t[shown, i, c])
        elif name == "sg_lightfield":
            channels = io.read_exr(os.path.join(out, "sg_lobes.exr"), None, dtype=np.float16)
            for j in range(np.shape(p["sharpness"])[1]):
                np.testing.assert_array_equal(channels[f"lobe{j:02d}.S"][row, col],
                                              np.asarray(p["sharpness"])[shown, j])
                for c, ch in enumerate("XYZ"):
                    np.testing.assert_array_equal(channels[f"lobe{j:02d}.{ch}"][row, col],
                                                  np.asarray(p["axes"])[shown, j, c])
                for c, ch in enumerate("RGB"):
                    np.testing.assert_array_equal(channels[f"lobe{j:02d}.{ch}"][row, col],
                                                  np.asarray(p["amplitude"])[shown, j, c])
            # the shading's material at each texel: what the G-buffer reads there (diffuse, specular, roughness)
            mats = np.fromfile(os.path.join(out, "sg_materials.bin"), "<f4").reshape(-1, 7)
            want = texel_materials(Session(run), texels)
            np.testing.assert_array_equal(mats, np.concatenate([want["diffuse"], want["specular"],
                                                                want["roughness"][:, None]], axis=1))
        else:  # MRT: the operators are the params buffers themselves
            files = read_manifest(out)["files"]
            assert {"params/T_db.bin", "params/U_b.bin", "params/rec_T.bin"} <= set(files)
            assert "T_d->b" in files["params/T_db.bin"]["holds"]


def _validator_ready() -> str | None:
    """Why the glTF-Validator cannot run here, or None."""
    if shutil.which("node") is None:
        return "node is not installed (make export-deps installs it)"
    if not os.path.isdir(os.path.join(JS, "node_modules", "gltf-validator")):
        return "the npm package gltf-validator is not installed in tests/js (make export-deps)"
    return None


def test_gltf_validator_reports_no_errors(exported):
    """The Khronos glTF-Validator on every exported .glb: 0 errors (warnings are printed)."""
    why = _validator_ready()
    if why:
        pytest.skip(why)
    files = [os.path.join(exported(name)[1], "scene.glb") for name in LIGHTMAP_METHODS]
    done = subprocess.run(["node", os.path.join(JS, "validate_gltf.mjs"), *files], capture_output=True, text=True,
                          timeout=120, check=True)
    for report in json.loads(done.stdout):
        for msg in report["messages"]:
            if msg["severity"] <= 1:
                print(f"{report['file']}: {msg['code']} {msg['pointer']}: {msg['message']}")
        assert report["errors"] == 0, report["messages"]


# --------------------------------------------------------------------------------------------
# Neural evaluators: ONNX


def _feeds(out):
    with np.load(os.path.join(out, "reference_inputs.npz")) as data:
        return {k: data[k] for k in data.files}


@pytest.mark.parametrize("name", ["rrf", pytest.param("sg_environment", marks=pytest.mark.slow)])
def test_onnx_equals_the_jax_evaluator(exported, name):
    """onnxruntime on the exported model and the view's frame equals the JAX evaluator (the
    reference frame written beside it, and recomputed from the run) to relative 1e-5."""
    _, out, m, config, result, _ = exported(name)
    manifest = read_manifest(out)
    feeds = _feeds(out)
    assert [i["name"] for i in manifest["onnx"]["inputs"]] == list(feeds)
    got = jonnx.run_onnx(os.path.join(out, "evaluator.onnx"), feeds)
    want = np.load(os.path.join(out, "reference_output.npy"))
    assert got.shape == want.shape == (ONNX_SIZE, ONNX_SIZE, 3) and np.abs(want).max() > 0
    assert np.abs(got - want).max() <= 1e-5 * np.abs(want).max()
    assert set(manifest["onnx"]["hand_written"]) <= set(jonnx.HAND_WRITTEN)


@pytest.mark.slow
def test_onnx_of_neural_wavelet_prt_is_the_same_function(exported):
    """Neural-wavelet PRT's test-preset model predicts about 1e-3 as a sum of terms of order 1, so
    float32 rounding alone moves its output by about 1e-3 relative (JAX jitted against JAX
    op by op differs as much): the graph is checked in float64, where ONNX equals JAX to 1e-5,
    and in float32 against that rounding."""
    run, out, m, config, result, dataset = exported("wavelet_prt")
    inputs, lighting = m.example(dataset, config)
    to64 = lambda t: jax.tree_util.tree_map(  # noqa: E731
        lambda a: np.asarray(a, np.float64) if np.asarray(a).dtype == np.float32 else np.asarray(a), t)
    with jax.enable_x64(True):
        evaluate = m.evaluator(to64(result.params), config)
        i64, l64 = to64(inputs), type(lighting)(*to64(tuple(lighting)))
        want = np.asarray(jax.jit(evaluate)(i64, l64))
        model, _ = jonnx.to_onnx(evaluate, i64, l64, double=True)
    leaves = [np.asarray(x) for x in jax.tree_util.tree_leaves((i64, l64))]
    got = jonnx.run_onnx(model, dict(zip(jonnx.input_names(i64, l64), leaves)))
    assert got.dtype == np.float64 and np.abs(got - want).max() <= 1e-5 * np.abs(want).max()
    # float32: within twice JAX's own jitted-against-op-by-op difference on the same frame
    feeds = _feeds(out)
    got32 = jonnx.run_onnx(os.path.join(out, "evaluator.onnx"), feeds)
    want32 = np.load(os.path.join(out, "reference_output.npy"))
    back = load(out)
    from jprt.view import Session

    s = Session(run)
    with jax.disable_jit():
        eager = np.asarray(back.evaluate(s.inputs(ONNX_SIZE), s.method_lighting()))
    floor = max(np.abs(eager - want32).max(), 1e-5 * np.abs(want32).max())
    assert np.abs(got32 - want32).max() <= 2.0 * floor


def _glsl_program(source: str) -> tuple[dict, dict, dict]:
    """The constants a generated RRF shader declares: ints, int arrays, bools."""
    import re

    ints = {k: int(v) for k, v in re.findall(r"const int (RRF_\w+) = (-?\d+);", source)}
    arrays = {k: [int(v) for v in body.split(",")]
              for k, body in re.findall(r"const int (RRF_\w+)\[\d+\] = int\[\]\(([^)]*)\);", source)}
    flags = {k: v == "true" for k, v in re.findall(r"const bool (RRF_\w+) = (true|false);", source)}
    return ints, arrays, flags


def _run_glsl(source: str, data: np.ndarray, inputs: list, gb, lights) -> np.ndarray:
    """rrf.glsl's functions, statement by statement, in NumPy float32 over the data texture: what a
    fragment shader computes per pixel (rrfInputs, rrfLeaf, rrfNetwork, rrfIndirect)."""
    c, arrays, flags = _glsl_program(source)
    at = data.ravel().astype(np.float32)
    fields = {"position": np.asarray(gb.position), "view": np.asarray(gb.view), "normal": np.asarray(gb.normal),
              "brdf": np.concatenate([np.asarray(gb.diffuse_albedo), np.asarray(gb.specular_albedo),
                                      np.asarray(gb.roughness)[..., None]], axis=-1)}
    h, w = np.shape(gb.object_id)
    out = np.zeros((h, w, 3), np.float32)
    lo, hi = at[c["RRF_LIGHT_LO"]:c["RRF_LIGHT_LO"] + 3], at[c["RRF_LIGHT_HI"]:c["RRF_LIGHT_HI"] + 3]
    d = c["RRF_D"]
    for y in range(h):
        for x_ in range(w):
            obj = int(gb.object_id[y, x_]) if bool(gb.valid[y, x_]) else -1
            if obj < 0 or obj >= c["RRF_OBJECTS"]:
                continue
            x = np.zeros(d, np.float32)
            for name, first, end in inputs:
                if name != "light":
                    x[first:end] = fields[name][y, x_]
            for p, rgb in zip(np.asarray(lights.position, np.float32), np.asarray(lights.intensity, np.float32)):
                x[c["RRF_LIGHT"]:c["RRF_LIGHT"] + 3] = np.clip(p, lo, hi) if flags["RRF_CLAMP_LIGHTS"] else p
                node = int(at[c["RRF_ROOTS"] + obj])
                if node < 0:
                    continue
                for _ in range(c["RRF_DEPTH"]):
                    axis = int(at[c["RRF_AXIS"] + node])
                    if axis < 0:
                        break
                    side = "RRF_RIGHT" if x[axis] >= at[c["RRF_THRESHOLD"] + node] else "RRF_LEFT"
                    node = int(at[c[side] + node])
                leaf = int(at[c["RRF_LEAF"] + node])
                row = slice(leaf * d, (leaf + 1) * d)
                v = x
                if flags["RRF_CLAMP_INPUTS"]:
                    v = np.clip(v, at[c["RRF_IN_MIN"]:][row], at[c["RRF_IN_MAX"]:][row])
                a = (v - at[c["RRF_IN_CENTER"]:][row]) / at[c["RRF_IN_HALF"]:][row]
                sizes = arrays["RRF_SIZES"]
                for li in range(c["RRF_LAYERS"]):
                    n_in, n_out = sizes[li], sizes[li + 1]
                    wts = at[arrays["RRF_W"][li] + leaf * n_in * n_out:][:n_in * n_out].reshape(n_in, n_out)
                    a = a @ wts + at[arrays["RRF_B"][li] + leaf * n_out:][:n_out]
                    a = np.tanh(np.clip(a, -9.0, 9.0)) if li < c["RRF_LAYERS"] - 1 else a  # rrfTanh
                yv = a * at[c["RRF_OUT_HALF"] + 3 * leaf:][:3] + at[c["RRF_OUT_CENTER"] + 3 * leaf:][:3]
                out[y, x_] += (np.maximum(yv, 0) if flags["RRF_NONNEGATIVE"] else yv) * rgb
    return out


def test_rrf_glsl_computes_the_evaluator(exported):
    """rrf.glsl with rrf_data.bin, executed as written (``_run_glsl``: its constants parsed from
    the source, every number read from the data texture by its offsets), equals the JAX evaluator
    at the view's frame under one light and under two lights, the second moved and tinted (and
    outside the trained box when it lands there: a shader cannot refuse it, so it evaluates as
    ``render.extrapolation`` "allow" does unless the config clamps). The browser test runs the
    same source in WebGL2."""
    from jprt.inputs import PointLights
    from jprt.view import Session

    run, out, m, config, result, _ = exported("rrf")
    manifest = read_manifest(out)
    g = manifest["glsl"]
    with open(os.path.join(out, g["source"])) as f:
        source = f.read()
    data = np.fromfile(os.path.join(out, g["data"]), "<f4").reshape(g["data_height"], g["data_width"])
    assert "uniform highp sampler2D rrfData;" in source and g["max_lights"] >= 2
    s = Session(run)
    gb = s.inputs(12)
    one = s.method_lighting()
    p0 = np.asarray(one.position, np.float32)[0]
    two = PointLights.create(np.stack([p0, p0 + [0.3, -0.2, 0.1]]), [[1.0, 0.8, 0.6], [0.5, 0.5, 1.0]])
    clamps = config["render"]["extrapolation"] == "clamp"
    cfg = {**config, "render": {**config["render"], "extrapolation": "clamp" if clamps else "allow"}}
    for lights in (one, two):
        want = np.asarray(m.evaluator(result.params, cfg)(gb, lights))
        got = _run_glsl(source, data, g["inputs"], gb, lights)
        assert np.abs(want).max() > 0
        assert np.abs(got - want).max() <= 1e-5 * np.abs(want).max(), np.abs(got - want).max()
