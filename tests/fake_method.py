"""A fake method for the runner and sweep tests: pure NumPy/JAX, no Mitsuba, milliseconds.

Indirect = gain * albedo * sum of the light intensities (+ ``model.bias``); ``fit`` learns the
gain (truth: 1) by least squares and refuses ``model.bias < 0`` (a failing sweep point). ``CALLS``
counts make_dataset and fit calls (a re-run of a finished sweep must make none).
"""

import collections

import jax.numpy as jnp
import numpy as np

from jprt import runner
from jprt.inputs import GBuffer, PointLights
from jprt.methods import REGISTRY
from jprt.methods.base import FitResult, Method

CALLS = collections.Counter()

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


def make_fake_method() -> Method:
    """Indirect = gain * albedo * sum of intensities; fit learns the gain (truth: 1) by least squares."""
    default = {"scene": {"name": "fake"}, "model": {"bias": 0.0}, "data": {"n": 3, "seed": 0}}

    def make_dataset(scene, config):
        CALLS["make_dataset"] += 1
        cfg = REGISTRY["fake"].resolve(config)
        rng = np.random.default_rng(cfg["data"]["seed"])
        items = []
        for k in range(cfg["data"]["n"]):
            gb = _gbuffer(k)
            lights = PointLights.create(rng.random((1, 3)), rng.random((1, 3)) + 0.5)
            items.append((gb, lights, _truth(gb, lights)))
        return items

    def fit(dataset, config):
        CALLS["fit"] += 1
        if REGISTRY["fake"].resolve(config)["model"]["bias"] < 0:
            raise ValueError("the fake method refuses a negative bias")
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




def held_out(run):
    """One held-out view: predictions, references, valid pixels, direct (half the indirect)."""
    gb = _gbuffer(100)
    lights = PointLights.create([[0.5, 0.5, 0.5]], [[1.0, 2.0, 0.5]])
    ref = _truth(gb, lights)
    run.state["test"] = (gb, lights, ref)
    return runner.HeldOut([np.asarray(run.evaluate(gb, lights))], [ref], [gb.valid], [0.5 * ref])


def pathtracer(run):
    """Noise ~ 0.5 / sqrt(spp) around the reference; 2 ms per spp."""
    gb, lights, ref = run.state["test"]
    noise = np.random.default_rng(0).normal(size=ref.shape)
    return runner.PathTracer(lambda spp: [ref + 0.5 * noise / np.sqrt(spp)], lambda spp: 2.0 * spp, "fake")


def config(output_dir: str) -> dict:
    """A fake experiment's CONFIG."""
    return {**REGISTRY["fake"].default_config, "eval": {"equal_error_spp": [1, 4, 16, 64, 256], "images": 1,
                                                       "timing_repeats": 2}, "output": {"dir": output_dir}}
