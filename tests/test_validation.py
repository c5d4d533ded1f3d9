"""Every public entry refuses bad inputs in one line that names the argument, says what was
expected and what was given (issue 20). ``CASES`` and the README's table of refused inputs are
the same list: a row without a case, or a case without a row, fails."""

import os
import re

import numpy as np
import pytest

from jprt import inputs as jin
from jprt.config import ConfigError
from jprt.methods.base import checked_evaluator
from jprt.render import cameras

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _gbuffer(**override):
    h, w = 2, 3
    n = np.zeros((h, w, 3), np.float32)
    n[..., 2] = 1.0
    fields = dict(position=np.zeros((h, w, 3), np.float32), normal=n, view=n.copy(), reflected=n.copy(),
                  uv=np.zeros((h, w, 2), np.float32), diffuse_albedo=np.full((h, w, 3), 0.5, np.float32),
                  specular_albedo=np.zeros((h, w, 3), np.float32), roughness=np.ones((h, w), np.float32),
                  object_id=np.zeros((h, w), np.int32), valid=np.ones((h, w), bool))
    fields.update(override)
    return jin.GBuffer(**fields)


def _nan_at_valid():
    p = np.zeros((2, 3, 3), np.float32)
    p[1, 2, 0] = np.nan
    return p


def _method_evaluator(lighting):
    """A registered method's evaluator wrapper around a stand-in model (no fit needed)."""
    return checked_evaluator(lambda params, config=None: (lambda inputs, light: 0.0), jin.PointLights)(None)(
        _gbuffer(), lighting)


ONES = np.ones((4, 8, 3), np.float32)

#: case -> (call, exception, the words the one-line message must hold)
CASES = {
    "envmap-shape": (lambda: jin.EnvMap.create(np.ones((4, 8, 2))), ValueError, "environment map radiance must have shape (H, W, 3)"),
    "envmap-finite": (lambda: jin.EnvMap.create(np.where(ONES > 0, np.inf, 0)), ValueError, "environment map radiance must be finite"),
    "envmap-negative": (lambda: jin.EnvMap.create(-ONES), ValueError, "environment map radiance must be >= 0"),
    "wavelet-envmap": (lambda: __import__("jprt.sphere.envmap", fromlist=["x"]).prepare_environment(
        np.ones((8, 16, 2)), 4), ValueError, "environment map radiance must have shape (H, W, 3)"),
    "cubemap-shape": (lambda: jin.CubeMap.create(np.ones((6, 4, 4, 2))), ValueError, "cube map radiance must have shape (6, n, n, 3)"),
    "cubemap-finite": (lambda: jin.CubeMap.create(np.full((6, 2, 2, 3), np.nan)), ValueError, "cube map radiance must be finite"),
    "cubemap-negative": (lambda: jin.CubeMap.create(-np.ones((6, 2, 2, 3))), ValueError, "cube map radiance must be >= 0"),
    "point-shape": (lambda: jin.PointLights.create(np.zeros((2, 3)), np.ones((3, 3))), ValueError, "point light intensity must have shape (2, 3)"),
    "point-finite": (lambda: jin.PointLights.create([0, np.nan, 0], [1, 1, 1]), ValueError, "point light position must be finite"),
    "point-negative": (lambda: jin.PointLights.create([0, 0, 0], [1, -1, 1]), ValueError, "point light intensity must be >= 0"),
    "spot-axis": (lambda: jin.SpotLights.create([0, 1, 0], [0, 1, 0], [1, 1, 1]), ValueError, "spot target must differ from its position"),
    "spot-angles": (lambda: jin.SpotLights.create([0, 1, 0], [0, 0, 0], [1, 1, 1], cutoff_deg=120), ValueError, "spot angles need 0 < beam_deg <= cutoff_deg <= 90"),
    "spot-negative": (lambda: jin.SpotLights.create([0, 1, 0], [0, 0, 0], [-1, 1, 1]), ValueError, "spot intensity must be >= 0"),
    "directional-zero": (lambda: jin.DirectionalLights.create([0, 0, 0], [1, 1, 1]), ValueError, "directional light direction must be non-zero"),
    "directional-negative": (lambda: jin.DirectionalLights.create([0, -1, 0], [1, -1, 1]), ValueError, "directional light irradiance must be >= 0"),
    "sh-shape": (lambda: jin.SHLighting.create(np.ones((5, 3))), ValueError, "SH lighting coefficients must have shape ((degree + 1)^2, 3)"),
    "sh-finite": (lambda: jin.SHLighting.create(np.full((4, 3), np.inf)), ValueError, "SH lighting coefficients must be finite"),
    "point-radiance-shape": (lambda: jin.PointRadiance.create(np.ones((4, 2))), ValueError, "point radiance direct must have shape (S, 3)"),
    "point-radiance-negative": (lambda: jin.PointRadiance.create(-np.ones((4, 3))), ValueError, "point radiance direct must be >= 0"),
    "light-scale-shape": (lambda: jin.LightScale.create([1.0, 2.0]), ValueError, "light scale must have shape (3,)"),
    "light-scale-negative": (lambda: jin.LightScale.create([1.0, -2.0, 1.0]), ValueError, "light scale must be >= 0"),
    "preconvolved-alphas": (lambda: jin.PreconvolvedEnvironment.create(np.ones((2, 4, 4, 3)), [0.5, 0.2]), ValueError,
                            "alphas must increase within"),
    "gbuffer-shape": (lambda: jin.validate_gbuffer(_gbuffer(roughness=np.ones((2, 2), np.float32))), ValueError, "G-buffer roughness must have shape (2, 3)"),
    "gbuffer-finite": (lambda: jin.validate_gbuffer(_gbuffer(position=_nan_at_valid())), ValueError, "G-buffer position at valid pixels must be finite"),
    "gbuffer-unit": (lambda: jin.validate_gbuffer(_gbuffer(normal=np.full((2, 3, 3), 0.9, np.float32))), ValueError, "G-buffer normal must be unit vectors"),
    "gbuffer-roughness": (lambda: jin.validate_gbuffer(_gbuffer(roughness=np.full((2, 3), 1.5, np.float32))), ValueError, "G-buffer roughness must be in [0, 1]"),
    "camera-vector": (lambda: cameras.look_at([0, 0, np.nan], [0, 0, 0]), ValueError, "camera origin must be a finite 3-vector"),
    "camera-target": (lambda: cameras.look_at([0, 0, 1], [0, 0, 1]), ValueError, "camera target must differ from its origin"),
    "camera-up": (lambda: cameras.look_at([0, 1, 0], [0, 0, 0]), ValueError, "camera up must not be parallel to the view direction"),
    "camera-fov": (lambda: cameras.look_at([0, 0, 1], [0, 0, 0], fov=180.0), ValueError, "camera fov must be in (0, 180) degrees"),
    "camera-size": (lambda: cameras.look_at([0, 0, 1], [0, 0, 0], width=0), ValueError, "camera width must be an integer >= 1"),
    "config-key": (lambda: __import__("jprt.methods", fromlist=["x"]).REGISTRY["rrf"].resolve({"modle": {}}), ConfigError, "modle"),
    "evaluator-lighting-type": (lambda: _method_evaluator(jin.EnvMap.create(ONES)), TypeError, "lighting must be PointLights, got EnvMap"),
    "evaluator-lighting-value": (lambda: _method_evaluator(jin.PointLights(np.zeros((1, 3), np.float32), -np.ones((1, 3), np.float32))), ValueError, "point light intensity must be >= 0"),
}


def _readme_cases() -> list[str]:
    text = open(os.path.join(ROOT, "README.md"), encoding="utf-8").read()
    table = text.split("<!-- refused-inputs -->")[1]
    return re.findall(r"^\| `([a-z0-9-]+)` \|", table, re.M)


def test_the_readme_table_lists_exactly_the_tested_cases():
    rows = _readme_cases()
    assert len(rows) == len(set(rows)), "a case is listed twice in the README"
    assert set(rows) == set(CASES), (f"README rows without a test: {sorted(set(rows) - set(CASES))}; "
                                     f"tests without a README row: {sorted(set(CASES) - set(rows))}")


@pytest.mark.parametrize("case", sorted(CASES))
def test_refused_in_one_line_naming_the_argument(case):
    call, error, words = CASES[case]
    with pytest.raises(error) as info:
        call()
    message = str(info.value)
    assert words in message and "\n" not in message, message
    if case != "config-key":  # ConfigError names the key and the nearest valid one instead
        assert "got" in message, message


def test_signed_lighting_is_accepted_when_asked_for():
    """Basis lightings (Haar wavelets, SH lobes) are signed: ``signed=True`` lets them through."""
    assert jin.EnvMap.create(-ONES, signed=True).radiance.min() == -1.0
    assert jin.PointLights.create([0, 0, 0], [1, -1, 1], signed=True).intensity[0, 1] == -1.0
    assert jin.validate_lighting(jin.CubeMap(-np.ones((6, 2, 2, 3), np.float32)), signed=True) is not None


def test_every_registered_method_checks_its_evaluator_arguments():
    from jprt.methods import REGISTRY

    for name, m in REGISTRY.items():
        assert m.evaluator.__name__ == "evaluator" and m.evaluator.__wrapped__ is not None, name
        assert m.evaluator.__module__ == f"jprt.methods.{name}.model", name
