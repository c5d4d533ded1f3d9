"""The runner (jprt.runner) on a fake method: the pipeline's order, the summary schema, the report
folder, equal error against a fake path tracer, strict method configs."""

import json
import os
import types

import jax.numpy as jnp
import numpy as np
import pytest

from jprt import runner
from jprt.config import ConfigError
from jprt.inputs import GBuffer, PointLights
from jprt.methods import REGISTRY
from jprt.methods.base import FitResult, Method

H, W = 12, 12


def _gbuffer(seed: int) -> GBuffer:
    rng = np.random.default_rng(seed)
    z3 = np.zeros((H, W, 3), np.float32)
    valid = rng.random((H, W)) > 0.1
    return GBuffer(position=rng.random((H, W, 3)).astype(np.float32), normal=z3, view=z3, reflected=z3,
                   uv=np.zeros((H, W, 2), np.float32), diffuse_albedo=rng.random((H, W, 3)).astype(np.float32),
                   specular_albedo=z3, roughness=np.zeros((H, W), np.float32),
                   object_id=valid.astype(np.int32) - 1, valid=valid)


def _truth(gb, lights):
    """The fake scene's 'path-traced' indirect: albedo times the sum of the light intensities."""
    return np.where(gb.valid[..., None], gb.diffuse_albedo * np.asarray(lights.intensity).sum(0), 0.0)


def _make_fake_method() -> Method:
    """Indirect = gain * albedo * sum of intensities; fit learns the gain (truth: 1) by least squares."""
    default = {"scene": {"name": "fake"}, "model": {"bias": 0.0}, "data": {"n": 3, "seed": 0}}

    def make_dataset(scene, config):
        cfg = REGISTRY["fake"].resolve(config)
        rng = np.random.default_rng(cfg["data"]["seed"])
        items = []
        for k in range(cfg["data"]["n"]):
            gb = _gbuffer(k)
            lights = PointLights.create(rng.random((1, 3)), rng.random((1, 3)) + 0.5)
            items.append((gb, lights, _truth(gb, lights)))
        return items

    def fit(dataset, config):
        num = sum(float(np.sum(gb.diffuse_albedo * l.intensity.sum(0) * y)) for gb, l, y in dataset)
        den = sum(float(np.sum((gb.diffuse_albedo * l.intensity.sum(0)) ** 2 * gb.valid[..., None]))
                  for gb, l, y in dataset)
        return FitResult({"gain": np.asarray(num / den, np.float32)}, {"train_s": 0.25})

    def evaluator(params, config):
        bias = REGISTRY["fake"].resolve(config)["model"]["bias"]

        def evaluate(inputs, lighting):
            out = jnp.asarray(params["gain"]) * inputs.diffuse_albedo * jnp.sum(lighting.intensity, axis=0)[None, None] + bias
            return jnp.where(inputs.valid[..., None], out, 0.0)

        return evaluate

    def example(dataset, config):
        return dataset[0][0], dataset[0][1]

    return Method("fake", "nobody 2026", PointLights, default, {"test": {}}, make_dataset, fit, evaluator, example)


@pytest.fixture
def fake(monkeypatch, tmp_path):
    monkeypatch.setitem(REGISTRY, "fake", _make_fake_method())
    calls = []

    def held_out(run):
        calls.append("held_out")
        gb = _gbuffer(100)
        lights = PointLights.create([[0.5, 0.5, 0.5]], [[1.0, 2.0, 0.5]])
        ref = _truth(gb, lights)
        run.state["test"] = (gb, lights, ref)
        return runner.HeldOut([np.asarray(run.evaluate(gb, lights))], [ref], [gb.valid], [0.5 * ref])

    def pathtracer(run):
        gb, lights, ref = run.state["test"]
        noise = np.random.default_rng(0).normal(size=ref.shape)
        return runner.PathTracer(lambda spp: [ref + 0.5 * noise / np.sqrt(spp)], lambda spp: 2.0 * spp, "fake")

    def stage(run):
        calls.append("stage")
        assert run.summary["indirect_rmse"] is not None  # stages run after the common summary
        return {"gain": float(run.result.params["gain"])}

    module = types.SimpleNamespace(
        METHOD="fake", CONFIG={**REGISTRY["fake"].default_config, "eval": {"equal_error_spp": [1, 4, 16, 64, 256],
                                                                          "images": 1, "timing_repeats": 2},
                               "output": {"dir": str(tmp_path / "out")}},
        held_out=held_out, pathtracer=pathtracer, STAGES=[stage])
    return module, calls


def test_run_writes_the_common_summary(fake):
    module, calls = fake
    s = runner.run(module, {})
    assert list(s)[:len(runner.SUMMARY_SCHEMA)] == list(runner.SUMMARY_SCHEMA)  # schema keys first, in order
    assert calls == ["held_out", "stage"]
    assert s["method"] == "fake" and s["scene"] == {"name": "fake"}
    assert s["indirect_rmse"] < 1e-5 and s["extra"]["gain"] == pytest.approx(1.0, rel=1e-5)
    assert s["psnr_full"] is not None and s["ssim_indirect"] is not None
    assert s["train_s"] == 0.25 and s["model_bytes"] == 4 and s["frame_resolution"] == [H, W]
    # a method this exact is never reached by the noisy path tracer: stated, timed at the largest spp
    assert s["equal_error_spp"] is None and s["pathtrace_ms_equal_error"] == 512.0
    assert "NOT reached" in s["extra"]["pathtrace_note"]
    assert s["speedup_equal_error"] == pytest.approx(512.0 / s["frame_ms"])
    folder = s["output"]
    with open(os.path.join(folder, "config.json")) as f:
        assert json.load(f)["hash"] == s["config_hash"] == os.path.basename(folder)
    for name in ("summary.json", "model.npz", "side_by_side.png", "equal_error.png"):
        assert os.path.isfile(os.path.join(folder, name)), name


def test_equal_error_is_found_for_a_biased_method(fake):
    module, _ = fake
    s = runner.run(module, {"model": {"bias": 0.05}})
    assert s["indirect_rmse"] == pytest.approx(0.05, rel=1e-4)
    assert s["equal_error_spp"] in (1, 4, 16, 64, 256)
    tried = s["extra"]["pathtrace_rmse_by_spp"]
    assert tried[-1]["rmse"] <= s["indirect_rmse"] < min(t["rmse"] for t in tried[:-1])
    assert s["pathtrace_ms_equal_error"] == 2.0 * s["equal_error_spp"]


def test_configs_are_strict(fake):
    module, _ = fake
    with pytest.raises(ConfigError, match="model.bias"):
        runner.run(module, {"model": {"bais": 1.0}})
    with pytest.raises(ValueError, match="lacks the fake sections"):
        runner.method_config(REGISTRY["fake"], {"scene": {"name": "fake"}})


def test_common_summary_refuses_lightmaps_and_handles_small_images():
    ref = np.ones((8, 8, 3))
    held = runner.HeldOut([ref * 1.1], [ref], [np.ones((8, 8), bool)])
    s = runner.common_summary(held)
    assert s["indirect_rmse"] == pytest.approx(0.1) and s["indirect_rel_rmse"] == pytest.approx(0.1)
    assert s["ssim_indirect"] is None and s["psnr_full"] is None  # 8 x 8 < SSIM window; no direct given
    with pytest.raises(ValueError, match=r"\(H, W, C\) images"):
        runner.common_summary(runner.HeldOut([np.ones((10, 3))], [np.ones((10, 3))], [np.ones(10, bool)]))
