"""The method contract (``jprt.methods.base``), for every method in ``REGISTRY`` on its ``test``
preset: make_dataset -> fit -> evaluator; the evaluator jits without retracing, gives finite
(H, W, 3) output, vmaps over a batch of lightings and round-trips through ``jax.export``; an
unknown config key raises; ``model.py`` imports with Mitsuba and Dr.Jit unimportable."""

import importlib
import subprocess
import sys

import jax
import numpy as np
import pytest

from jprt.config import ConfigError
from jprt.methods import REGISTRY, FitResult
from jprt.methods.base import LIGHTING_KINDS, PREDICTS, check_params

NAMES = sorted(REGISTRY)


@pytest.fixture(scope="module")
def fitted(fitted_preset):
    """{name: (method, config, dataset, FitResult)} on each test preset (``conftest.fitted_preset``)."""
    return {name: fitted_preset(name) for name in NAMES}


@pytest.mark.mitsuba
@pytest.mark.parametrize("name", NAMES)
def test_method_contract(mi, fitted, name):
    m, config, dataset, result = fitted[name]
    assert isinstance(result, FitResult) and isinstance(result.info, dict)
    check_params(result.params)
    evaluate = m.evaluator(result.params, config)
    for attribute in ("core", "jitted", "traces", "lightmap", "transfer"):  # module functions now
        assert not hasattr(evaluate, attribute), attribute
    inputs, lighting = m.example(dataset, config)
    assert isinstance(lighting, m.lighting)

    image = np.asarray(evaluate(inputs, lighting))
    assert image.ndim == 3 and image.shape[-1] == 3 and np.isfinite(image).all()
    assert np.abs(image).max() > 0
    if m.frame_flops is not None:  # the method's own FLOP count of a frame (the runner's roofline)
        flops = m.frame_flops(result.params, config, inputs, lighting)
        assert np.isfinite(flops) and flops > 0

    traces = []

    def traced(inputs, lighting):  # runs once per trace, not per call
        traces.append(1)
        return evaluate(inputs, lighting)

    jitted = jax.jit(traced)
    np.testing.assert_allclose(np.asarray(jitted(inputs, lighting)), image, rtol=1e-5, atol=1e-6)
    # another lighting of the same type and shapes: each array pulled a quarter of the way to its
    # mean over the first axis (stays inside an RRF's light box, stays a valid radiance)
    scaled = jax.tree_util.tree_map(
        lambda a: (0.75 * np.asarray(a) + 0.25 * np.asarray(a).mean(axis=0, keepdims=True)).astype(np.asarray(a).dtype),
        lighting)
    jitted(inputs, scaled)  # equal shapes, other values: no second trace
    assert len(traces) == 1

    batch = jax.tree_util.tree_map(lambda a, b: np.stack([np.asarray(a), np.asarray(b)]), lighting, scaled)
    batched = np.asarray(jax.vmap(evaluate, in_axes=(None, 0))(inputs, batch))
    assert batched.shape == (2,) + image.shape
    np.testing.assert_allclose(batched[0], image, rtol=1e-4, atol=1e-5)
    single_scaled = np.asarray(evaluate(inputs, scaled))
    np.testing.assert_allclose(batched[1], single_scaled, rtol=1e-4, atol=1e-5)

    exported = jax.export.export(jax.jit(evaluate))(inputs, lighting)
    restored = jax.export.deserialize(exported.serialize())
    np.testing.assert_allclose(np.asarray(restored.call(inputs, lighting)), image, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("name", NAMES)
def test_unknown_config_key_raises(name):
    m = REGISTRY[name]
    section = next(k for k, v in m.default_config.items() if isinstance(v, dict) and len(v) > 1)
    key = sorted(m.default_config[section])[0]
    with pytest.raises(ConfigError, match=f"did you mean '{section}.{key}'"):
        m.resolve({section: {key + "x": 1}})
    with pytest.raises(ConfigError):
        m.resolve({"no_such_section": {}})
    with pytest.raises(ConfigError):
        m.evaluator({}, {"no_such_section": {}})


def test_models_import_without_mitsuba():
    """Every registered method's model.py is the paper's math in pure JAX: importing it (and the
    contract's modules) never needs Mitsuba or Dr.Jit (one subprocess for all of them)."""
    imports = ", ".join(f"jprt.methods.{name}.model" for name in NAMES)
    code = (
        "import sys\n"
        "class Block:\n"
        "    def find_spec(self, fullname, path=None, target=None):\n"
        "        if fullname.split('.')[0] in ('mitsuba', 'drjit'):\n"
        "            raise ImportError('blocked ' + fullname)\n"
        "sys.meta_path.insert(0, Block())\n"
        f"import jprt.inputs, jprt.methods.base, {imports}\n"
        "assert 'mitsuba' not in sys.modules and 'drjit' not in sys.modules\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True)


def test_registry_names_match_packages():
    for name, m in REGISTRY.items():
        assert m.name == name
        assert importlib.import_module(f"jprt.methods.{name}").METHOD is m
        assert "test" in m.presets
        m.resolve(m.presets["test"])  # every preset is valid for its method


@pytest.mark.parametrize("name", NAMES)
def test_method_declares_its_adapters(name):
    """What a package's ``data.py`` exposes to the atlas and the viewer is a field of its
    ``Method`` (filled by ``Method.of_package``), so no caller needs the module itself."""
    m = REGISTRY[name]
    data = importlib.import_module(f"jprt.methods.{name}.data")
    assert m.task_lightings == tuple(getattr(data, "TASK_LIGHTINGS", ()))
    assert m.view_lightings == tuple(getattr(data, "VIEW_LIGHTINGS", None) or m.task_lightings)
    assert m.predicts == getattr(data, "PREDICTS", "indirect") and m.predicts in PREDICTS
    assert set(m.task_lightings + m.view_lightings) <= set(LIGHTING_KINDS)
    assert m.task_inputs is getattr(data, "task_inputs", None)
    assert m.task_lighting is getattr(data, "task_lighting", None)
    assert m.view_environments is getattr(data, "view_environments", None)
    if m.task_lightings or m.view_lightings:
        assert callable(m.task_inputs) and callable(m.task_lighting)


def test_of_package_refuses_lightings_without_an_adapter():
    import types

    from jprt.inputs import PointLights
    from jprt.methods.base import Method

    model = types.SimpleNamespace(DEFAULT_CONFIG={}, fit=None, evaluator=lambda p, c=None: None, example=None)
    data = types.SimpleNamespace(make_dataset=None, TASK_LIGHTINGS=("point",))
    with pytest.raises(TypeError, match="task_inputs"):
        Method.of_package("x", "", PointLights, model, data, {})
    with pytest.raises(TypeError, match="unknown lighting kinds"):
        Method.of_package("x", "", PointLights, model, types.SimpleNamespace(make_dataset=None, TASK_LIGHTINGS=("area",),
                          task_inputs=len, task_lighting=len), {})
    with pytest.raises(TypeError, match="PREDICTS"):
        Method.of_package("x", "", PointLights, model, types.SimpleNamespace(make_dataset=None, PREDICTS="both"), {})
    bare = Method.of_package("x", "", PointLights, model, types.SimpleNamespace(make_dataset=None), {})
    assert (bare.task_lightings, bare.view_lightings, bare.predicts) == ((), (), "indirect")


@pytest.mark.mitsuba
@pytest.mark.parametrize("name", NAMES)
def test_task_adapter(mi, fitted, name):
    """The task adapter (``Method.task_lightings``, ``task_inputs``, ``task_lighting``) turns an 8 x 8
    view and every task lighting the method takes into evaluator arguments: finite (8, 8, 3) light."""
    from jprt.inputs import CubeMap, PointLights
    from jprt.sphere.envmap import render_equirect, synthetic_environments
    from jprt.render.cameras import look_at
    from jprt.render.lights import EnvMap
    from jprt.render.scenes import SceneHandle

    m, config, dataset, result = fitted[name]
    assert set(m.task_lightings) <= {"point", "environment"}
    if not m.task_lightings:  # baked for its own lights (SG light-field textures): no task adapter to check
        return
    camera = look_at((0.0, 0.0, 3.9), (0.0, 0.0, 0.0), width=8, height=8)
    face = int(config.get("envmaps", {}).get("face_size", 4))
    lightings = {"point": PointLights.create([[0.0, 0.6, 0.0]], [1.0, 1.0, 1.0]),
                 "environment": CubeMap(synthetic_environments(1, face, seed=3)[0])}
    evaluate = m.evaluator(result.params, config)
    for kind in m.task_lightings:
        task_lighting = lightings[kind]
        rendered = EnvMap.create(render_equirect(task_lighting.radiance)) if kind == "environment" else task_lighting
        handle = SceneHandle(config["scene"], rendered)
        inputs = m.task_inputs(handle, dataset, camera)
        lighting = m.task_lighting(handle, dataset, result.params, config, task_lighting)
        assert isinstance(lighting, m.lighting), kind
        image = np.asarray(evaluate(inputs, lighting))
        assert image.shape == (8, 8, 3) and np.isfinite(image).all(), kind
        assert np.abs(image).max() > 0, kind


@pytest.mark.mitsuba
def test_wavelet_prt_is_nonnegative_under_a_lighting_it_never_saw(mi, fitted):
    """Issue 18: the test preset's model under one bright sun-like lobe on a near-black sky (far
    from its procedural training maps) gives indirect radiance >= 0 at every pixel."""
    from jprt.inputs import CubeMap
    from jprt.sphere import cubemap

    m, config, dataset, result = fitted["wavelet_prt"]
    n = int(config["envmaps"]["face_size"])
    d = np.asarray(cubemap.texel_directions(n))
    sun = np.array([0.3, 0.25, -0.92]) / np.linalg.norm([0.3, 0.25, -0.92])
    cube = 1e-3 + 5e3 * np.exp(2000.0 * (d @ sun - 1.0))[..., None] * np.array([1.0, 0.9, 0.7])
    inputs, _ = m.example(dataset, config)
    image = np.asarray(m.evaluator(result.params, config)(inputs, CubeMap(cube.astype(np.float32))))
    assert np.isfinite(image).all() and image.min() >= 0.0
    raw = m.evaluator(result.params, dict(config, model=dict(config["model"], nonnegative=False)))
    raw = np.asarray(raw(inputs, CubeMap(cube.astype(np.float32))))
    np.testing.assert_allclose(image, np.maximum(raw, 0.0), rtol=1e-6, atol=1e-7)  # the clip, nothing else
