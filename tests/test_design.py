"""Lighting design (``jprt.design``): the objective file's validation, the analytic direct term of
point lights and its visibility, gradients at the light region's faces, convergence to a known
optimum on a synthetic model, and ``jprt design`` end to end on a test-preset RRF."""

import json
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jprt import design
from jprt.inputs import GBuffer

NAMES = ["floor", "ceiling", "back", "large-box"]


def _write(tmp_path, spec, name="objective.json"):
    path = tmp_path / name
    path.write_text(json.dumps(spec))
    return str(path)


@pytest.mark.parametrize("spec, message", [
    ({"objects": [{"name": "flor", "min": 1.0}]}, "'flor' is not an object of the scene (did you mean floor?)"),
    ({"objects": [{"name": "desk", "min": 1.0}]}, "'desk' is not an object of the scene (it has 4"),
    ({"objects": [{"name": "floor", "min": 2.0, "max": 1.0}]}, "min 2.0 is above max 1.0"),
    ({"objects": [{"name": "floor", "min": -1.0}]}, "objects[0].min must be >= 0"),
    ({"objects": [{"name": "floor", "max": 0}]}, "objects[0].max must be > 0"),
    ({"objects": [{"name": "floor", "max": float("nan")}]}, "must be a finite number"),
    ({"objects": [{"name": "floor"}]}, "needs a 'min' or a 'max'"),
    ({"objects": [{"name": "floor", "min": 1.0, "quantity": "flux"}]}, "quantity must be one of irradiance, radiance"),
    ({"objects": [{"name": "floor", "mn": 1.0}]}, "unknown key 'mn'"),
    ({"objects": [{"name": "floor", "min": 1.0}, {"name": "back", "max": 2.0}, {"name": "floor", "max": 3.0}]},
     "objects[2] repeats objects[0] (floor, irradiance): give its min and max in one entry"),
    ({"object": []}, "unknown key 'object'"),
    ({}, "nothing to optimise"),
    ({"image": {"quantity": "full"}}, "needs a 'path'"),
    ({"image": {"path": "missing.exr"}}, "no such file"),
    ({"objects": [{"name": "floor", "min": 1.0}], "power_penalty": -1}, "power_penalty must be >= 0"),
])
def test_a_bad_objective_is_refused_in_one_line(tmp_path, spec, message):
    with pytest.raises(design.ObjectiveError) as e:
        design.load_objective(_write(tmp_path, spec), NAMES)
    assert message in str(e.value) and "\n" not in str(e.value) and "objective.json" in str(e.value)


def test_a_good_objective_loads_with_its_image_and_mask(tmp_path):
    np.save(tmp_path / "target.npy", np.ones((4, 4, 3), np.float32))
    mask = np.zeros((4, 4), np.float32)
    mask[1:3] = 1.0
    np.save(tmp_path / "mask.npy", mask)
    spec = {"image": {"path": "target.npy", "mask": "mask.npy", "quantity": "indirect"},
            "objects": [{"name": "floor", "min": 0.5, "max": 2}, {"name": "back", "max": 1, "quantity": "radiance"}],
            "power_penalty": 0.1}
    obj = design.load_objective(_write(tmp_path, spec), NAMES, shape=(4, 4))
    assert obj.image.quantity == "indirect" and obj.image.mask.sum() == 8
    assert [t.name for t in obj.objects] == ["floor", "back"] and obj.objects[1].min is None
    with pytest.raises(design.ObjectiveError, match="the frame is 8 x 8"):
        design.load_objective(_write(tmp_path, spec), NAMES, shape=(8, 8))


def _floor(n=12, size=2.0, albedo=0.5):
    """A square diffuse floor (y = 0) of n x n pixels seen from straight above."""
    c = (np.arange(n) + 0.5) / n * size - size / 2
    x, z = np.meshgrid(c, c, indexing="xy")
    pos = np.stack([x, np.zeros_like(x), z], -1).astype(np.float32)
    up = np.broadcast_to(np.array([0, 1, 0], np.float32), pos.shape).copy()
    return GBuffer(pos, up, up, up, np.zeros((n, n, 2), np.float32), np.full((n, n, 3), albedo, np.float32),
                   np.zeros((n, n, 3), np.float32), np.ones((n, n), np.float32), np.zeros((n, n), np.int32),
                   np.ones((n, n), bool))


def test_direct_light_of_a_point_light_is_the_inverse_square_law():
    gb = _floor(n=3, size=2.0)
    h, inten = 1.5, np.array([[2.0, 1.0, 0.5]])
    radiance, irradiance = design.point_direct(gb, np.array([[0.0, h, 0.0]]), inten, np.ones((3, 3, 1)))
    np.testing.assert_allclose(irradiance[1, 1], inten[0] / h ** 2, rtol=1e-6)  # straight below the light
    d2 = (2.0 / 3) ** 2 + h ** 2  # the pixel beside it: cos / r^2 = h / r^3
    np.testing.assert_allclose(irradiance[1, 0], inten[0] * h / d2 ** 1.5, rtol=1e-5)
    np.testing.assert_allclose(radiance, 0.5 / np.pi * np.asarray(irradiance), rtol=1e-6)
    _, shadowed = design.point_direct(gb, np.array([[0.0, h, 0.0]]), inten, np.zeros((3, 3, 1)))
    assert np.all(np.asarray(shadowed) == 0)


def test_gradients_are_finite_at_the_light_regions_faces():
    gb = _floor()
    lo, hi = np.array([-1.0, 0.5, -1.0]), np.array([1.0, 2.0, 1.0])
    obj = design.load_objective({"objects": [{"name": "floor", "min": 10.0}]}, NAMES)
    masks = design.object_masks(obj, gb.object_id, NAMES)
    def loss(p):
        pos, inten = design.from_params(p, lo, hi)
        _, irr = design.point_direct(gb, pos, inten, jnp.ones((12, 12, 1)))
        return sum(design.objective_terms(obj, masks, irr, irr, irr, inten, 1.0).values())

    grad = jax.jit(jax.grad(loss))
    for corner in (lo, hi, np.array([lo[0], hi[1], lo[2]])):
        params = design.to_params(corner[None], np.ones((1, 3)), lo, hi)
        pos, _ = design.from_params(params, lo, hi)
        np.testing.assert_allclose(pos[0], corner, atol=2e-4 * 2.0)  # EDGE inside the face
        g = grad(params)
        assert all(np.all(np.isfinite(np.asarray(a))) for a in g)
        assert np.abs(np.asarray(g.log_intensity)).max() > 0  # the floor is below its bound: more light helps


@pytest.mark.parametrize("k", [1, 2, 3, 4])
def test_the_compiled_direct_light_of_the_designs_lights_equals_the_eager_one(k):
    """The design's step is one compiled program from its parameters (``_light_map``: position
    and power, the colour held) to the direct light; compiled, it must give the numbers the
    operations give one by one. For two white lights, XLA:CPU (jax 0.10.2) compiled the power (a
    mean over RGB broadcast back) times the lights' sum wrongly: about half the light, or NaN."""
    n = 64  # the miscompilation needed a frame this large (32 and 64 showed it, 16 not) and white lights
    gb = _floor(n=n)
    gb = gb._replace(specular_albedo=np.full((n, n, 3), 0.2, np.float32), roughness=np.full((n, n), 0.4, np.float32))
    lo, hi = np.array([-0.8, 0.6, -0.8]), np.array([0.8, 1.6, 0.8])
    rng = np.random.default_rng(k)
    p0 = design.to_params(lo + (hi - lo) * rng.uniform(0.2, 0.8, (k, 3)), np.full((k, 3), 0.25), lo, hi)
    lights = design._light_map(p0, ("position", "power"), lo, hi)
    params = p0._replace(log_intensity=p0.log_intensity + 0.3)
    vis = jnp.asarray(rng.uniform(0, 1, (n, n, k)) > 0.3, jnp.float32)
    for glossy in (False, True):
        for part in (0, 1):  # radiance, irradiance: one scalar per program, as a design's objective is
            def light(params, glossy=glossy, part=part):
                return jnp.sum(design.point_direct(gb, *lights(params), vis, glossy=glossy)[part])

            np.testing.assert_allclose(float(jax.jit(light)(params)), float(light(params)), rtol=1e-5)


def test_reverse_mode_gradient_of_the_direct_light_is_finite_beside_empty_pixels():
    """Pixels that see no surface carry zero normal, view and roughness (GGX's D is 0 / 0 there):
    their value is masked to 0, and so must be their part of a reverse-mode gradient, which
    sums every pixel's cotangent (one NaN pixel made the whole gradient NaN). The gradient
    equals forward mode's, which never mixed pixels."""
    gb = _floor(n=6)
    empty = np.zeros((6, 6), bool)
    empty[:, :2] = True
    zero = lambda a: np.where(empty.reshape(empty.shape + (1,) * (a.ndim - 2)), 0, a).astype(a.dtype)  # noqa: E731
    gb = gb._replace(normal=zero(gb.normal), view=zero(gb.view), roughness=zero(gb.roughness),
                     specular_albedo=np.full((6, 6, 3), 0.3, np.float32), valid=~empty)
    pos, inten = jnp.asarray([[0.2, 1.5, -0.1]]), jnp.ones((1, 3))

    def loss(p):
        radiance, irradiance = design.point_direct(gb, p, inten, jnp.ones((6, 6, 1)))
        return jnp.sum(radiance) + jnp.sum(irradiance)

    g_rev, g_fwd = np.asarray(jax.jit(jax.grad(loss))(pos)), np.asarray(jax.jit(jax.jacfwd(loss))(pos))
    assert np.all(np.isfinite(g_rev)) and np.abs(g_rev).max() > 0
    np.testing.assert_allclose(g_rev, g_fwd, rtol=1e-5, atol=1e-7)


def test_design_finds_the_known_optimum_of_a_synthetic_linear_model():
    """Direct light of one point light on a floor plus an indirect term linear in its intensity
    (a fixed pattern): the target is this model's image under a known light; from another start
    in the region, the design recovers its position and intensity."""
    gb = _floor(n=16)
    pattern = jnp.asarray(0.05 + 0.05 * np.linspace(0, 1, 16)[None, :, None] * np.ones((16, 16, 3)), jnp.float32)

    def indirect(position, intensity, visibility):
        return pattern * jnp.mean(intensity)

    frame = design.design_frame(gb, indirect, glossy=False)
    lo, hi = np.array([-0.8, 0.6, -0.8]), np.array([0.8, 1.6, 0.8])
    true_pos, true_int = np.array([[0.3, 1.1, -0.25]]), np.array([[3.0, 3.0, 3.0]])
    target, _, _ = frame(true_pos, true_int, {"pixels": jnp.ones((16, 16, 1))})
    obj = design.Objective(design.ImageTarget(np.asarray(target), None, "full", 1.0), (), 0.0, "synthetic")
    result = design.design(frame, obj, np.zeros((0, 16, 16)), np.array([[-0.4, 0.8, 0.4]]), np.ones((1, 3)), lo, hi,
                           steps=400, learning_rate=0.05, progress=False)
    assert result.history[-1] < 1e-5 * result.history[0]
    np.testing.assert_allclose(result.position, true_pos, atol=0.01 * np.linalg.norm(hi - lo))
    np.testing.assert_allclose(result.intensity, true_int, rtol=0.02)
    assert np.all(result.position >= lo) and np.all(result.position <= hi)
    # one step's count for the benchmark's roofline: a 16 x 16 frame's forward and backward pass
    # and the update do more than one multiply-add per pixel, and read more than the frame once
    assert result.step_cost["flops"] > 16 * 16 * 3 and result.step_cost["bytes"] > 16 * 16 * 3 * 4


def test_search_start_then_design_recovers_a_light_whose_shadow_moves_with_it():
    """A point light over a floor casting a shadow edge that moves with it (a blade: a pixel more
    than 0.4 left of the light is shadowed), plus an indirect term linear in the total power: the
    target is this model's image under a known light. The search among traced candidates puts the
    light near it, and the design from there recovers it; with two lights the search returns two
    lights in the region."""
    from scipy.optimize import linear_sum_assignment

    gb = _floor(n=16)
    pattern = jnp.asarray(0.05 + 0.05 * np.linspace(0, 1, 16)[None, :, None] * np.ones((16, 16, 3)), jnp.float32)

    def indirect(position, intensity, visibility):
        return pattern * jnp.sum(intensity) / 3.0  # a sum over the lights, as transport is

    def visibility(position):
        x = np.asarray(gb.position)[..., 0]
        lights = np.asarray(position, np.float64).reshape(-1, 3)
        return {"pixels": (x[..., None] > lights[None, None, :, 0] - 0.4).astype(np.float32)}

    frame = design.design_frame(gb, indirect, glossy=False)
    lo, hi = np.array([-0.8, 0.6, -0.8]), np.array([0.8, 1.6, 0.8])
    true_pos, true_int = np.array([[0.3, 1.1, -0.25]]), np.full((1, 3), 3.0)
    target, _, _ = frame(true_pos, true_int, {k: jnp.asarray(v) for k, v in visibility(true_pos).items()})
    obj = design.Objective(design.ImageTarget(np.asarray(target), None, "full", 1.0), (), 0.0, "synthetic")
    masks = np.zeros((0, 16, 16))
    diagonal = float(np.linalg.norm(hi - lo))

    def errors(found):
        cost = np.linalg.norm(found[:, None] - true_pos[None], axis=-1)
        rows, cols = linear_sum_assignment(cost)
        return cost[rows, cols] / diagonal

    pos0, int0 = design.search_start(frame, obj, masks, lo, hi, 1, visibility_fn=visibility, candidates=64,
                                     progress=False)
    assert pos0.shape == (1, 3) and int0.shape == (1, 3)
    assert errors(pos0)[0] < 0.15  # 64 candidates in the box: about 0.1 of its diagonal apart
    two = design.search_start(frame, obj, masks, lo, hi, 2, visibility_fn=visibility, candidates=16, refine=0,
                              progress=False)
    assert two[0].shape == (2, 3) and np.all(two[0] >= lo) and np.all(two[0] <= hi) and np.all(two[1] > 0)
    result = design.design(frame, obj, masks, pos0, int0, lo, hi, visibility_fn=visibility, steps=300,
                           learning_rate=0.05, progress=False)
    assert errors(result.position)[0] < 0.01
    np.testing.assert_allclose(result.intensity, true_int, rtol=0.03)
    with pytest.raises(ValueError, match="lights >= 1"):
        design.search_start(frame, obj, masks, lo, hi, 0)


def test_refinement_splits_a_light_that_explains_two_nearby_ones():
    """Two lights 0.2 apart over a floor, each casting two shadow edges (x and z blades) that move
    with it: the start explains both with one light of their summed power at their midpoint and
    puts the second light far away and dim (what a coarse candidate grid gives). The traced local
    search splits the bright light: both hidden lights are found within 2 % of the region's
    diagonal, with their powers, and the objective falls a hundredfold."""
    from scipy.optimize import linear_sum_assignment

    n = 32
    gb = _floor(n=n)
    pattern = jnp.asarray(0.05 + 0.05 * np.linspace(0, 1, n)[None, :, None] * np.ones((n, n, 3)), jnp.float32)

    def indirect(position, intensity, visibility):
        return pattern * jnp.sum(intensity) / 3.0

    def visibility(position):
        x, z = np.asarray(gb.position)[..., 0, None], np.asarray(gb.position)[..., 2, None]
        p = np.asarray(position, np.float64).reshape(-1, 3)
        return {"pixels": jnp.asarray(((x > p[:, 0] - 0.4) & (z > p[:, 2] - 0.4)).astype(np.float32))}

    frame = design.design_frame(gb, indirect, glossy=False)

    def render(p):
        out = [frame(jnp.asarray(p[c:c + 1], jnp.float32), jnp.ones((1, 3), jnp.float32), visibility(p[c:c + 1]))
               for c in range(len(p))]
        return [jnp.stack([u[i] for u in out]) for i in range(3)]

    lo, hi = np.array([-0.8, 1.0, -0.8]), np.array([0.8, 1.2, 0.8])
    true_pos = np.array([[0.3, 1.1, -0.25], [0.1, 1.1, -0.25]])
    target, _, _ = frame(true_pos, np.ones((2, 3)), visibility(true_pos))
    obj = design.Objective(design.ImageTarget(np.asarray(target), None, "full", 1.0), (), 0.0, "synthetic")
    masks = np.zeros((0, n, n))
    mid, far = true_pos.mean(axis=0), np.array([-0.6, 1.1, 0.6])
    units = render(np.stack([mid, far]))
    start = [(mid, 2.0, [2.0 * u[0] for u in units]), (far, 0.05, [0.05 * u[1] for u in units])]

    def value(lights):
        frames = [sum(light[2][i] for light in lights) for i in range(3)]
        return float(sum(design.objective_terms(obj, masks, *frames, jnp.ones((1, 3)), 6.0).values()))

    found = design._refine_lights(render, obj, masks, start, lo, hi, 6.0, refine=4, radius=(hi - lo) / 8, seed=0)
    pos, power = np.stack([f[0] for f in found]), np.array([f[1] for f in found])
    cost = np.linalg.norm(pos[:, None] - true_pos[None], axis=-1)
    rows, cols = linear_sum_assignment(cost)
    assert np.all(cost[rows, cols] < 0.02 * np.linalg.norm(hi - lo))
    np.testing.assert_allclose(power[rows], 1.0, rtol=0.03)
    assert np.all(pos >= lo) and np.all(pos <= hi)
    assert value(found) < 0.01 * value(start)


def test_visibility_is_traced_by_mitsuba(mi):
    """In the Cornell box, a light just under the ceiling sees the floor's centre; one behind the
    back wall sees no pixel."""
    from jprt.render.gbuffer import gbuffer
    from jprt.render.scenes import SceneHandle

    handle = SceneHandle("cornell_box")
    gb = gbuffer(handle, handle.default_camera(16, 16))
    names = handle.object_names()
    floor = np.asarray(gb.object_id) == names.index("floor")
    vis = design.point_visibility(handle, gb, np.array([[0.0, 0.9, 0.0], [0.0, 0.0, -5.0]]))
    assert vis.shape == (16, 16, 2)
    assert vis[..., 0][floor].mean() > 0.5 and vis[..., 1].max() == 0.0
    assert np.all(vis[~np.asarray(gb.valid, bool)] == 0)


def _rrf_run(tmp_path, fitted_preset):
    from jprt.runner import save_fit

    m, config, dataset, result = fitted_preset("rrf")
    return save_fit(str(tmp_path / "run"), "rrf", config, result.params)


def test_jprt_design_refuses_a_bad_objective_in_one_line(tmp_path, capsys):
    """The objective is checked against the scene's object names before the run's model is used
    (``jprt.design.load_problem``), so the run folder (the RRF test preset's config) holds a
    placeholder model rather than a fit."""
    from jprt.cli import main
    from jprt.methods import REGISTRY
    from jprt.runner import save_fit

    m = REGISTRY["rrf"]
    run = save_fit(str(tmp_path / "run"), "rrf", m.resolve(m.presets["test"]), {"placeholder": np.zeros(1, np.float32)})
    bad = _write(tmp_path, {"objects": [{"name": "desk", "min": 1}]}, "bad.json")
    assert main(["design", run, "--objective", bad]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "'desk' is not an object of the scene" in err


@pytest.mark.slow
def test_jprt_design_on_a_test_preset_rrf_writes_a_verified_report(tmp_path, fitted_preset):
    from jprt.cli import main

    run = _rrf_run(tmp_path, fitted_preset)
    objective = _write(tmp_path, {"objects": [{"name": "floor", "min": 0.2}, {"name": "back", "max": 5.0}]})
    out = str(tmp_path / "design.json")
    assert main(["design", run, "--objective", objective, "--size", "12", "--steps", "6",
                 "--verify-spp", "4", "--out", out]) == 0
    with open(out) as f:
        report = json.load(f)
    lo, hi = np.asarray(report["light_region"]["lo"]), np.asarray(report["light_region"]["hi"])
    pos = np.asarray(report["found"]["position"])
    assert pos.shape == (1, 3) and np.all(pos >= lo) and np.all(pos <= hi)
    assert len(report["history"]) == 6 and np.all(np.isfinite(report["history"]))
    assert set(report["verified_terms"]) == set(report["model_terms"]) == {"floor.irradiance", "back.irradiance"}
    assert np.isfinite(report["verified_objective"]) and report["visibility_updates"] >= 1
    # each bound beside the objects' means: the hinge terms recomputed from the reported means
    for side in ("model", "verified"):
        for key, b in report["bounds"].items():
            low = (max(b["min"] - b[f"{side}_mean"], 0.0) / b["min"]) ** 2 if b["min"] is not None else 0.0
            high = (max(b[f"{side}_mean"] - b["max"], 0.0) / b["max"]) ** 2 if b["max"] is not None else 0.0
            assert low + high == pytest.approx(report[f"{side}_terms"][key], rel=1e-4, abs=1e-9)
            assert b[f"met_{side}" if side == "verified" else "met_on_model"] == (low + high == 0.0)
    assert report["bounds_met_verified"] == all(b["met_verified"] for b in report["bounds"].values())
    # the correction (one pass by default) ran from the design's lights, said whether it kept its
    # lights, and the report's lights are either its own or those before it
    assert report["correction"]["passes"] == 1 and len(report["correction"]["kept"]) == 1
    assert len(report["correction"]["moved"]) == 1
    assert report["correction"]["seconds"] > 0 and report["reference_power"] == pytest.approx(3.0)
    if not report["correction"]["kept"][0]:
        assert report["found"]["position"] == report["uncorrected"]["position"]
    # from the search's lights: two white lights inside the region, the search timed in design_s
    assert main(["design", run, "--objective", objective, "--size", "12", "--steps", "6", "--lights", "2",
                 "--start", "search", "--verify-spp", "4", "--out", out]) == 0
    with open(out) as f:
        report = json.load(f)
    start = np.asarray(report["start"]["position"])
    assert start.shape == (2, 3) and np.all(start >= lo) and np.all(start <= hi)
    assert np.all(np.asarray(report["start"]["intensity"]) > 0)
    assert 0.0 < report["search_s"] < report["design_s"]


@pytest.mark.slow
def test_the_design_experiment_writes_its_report_and_figure(tmp_path, fitted_preset):
    """``experiments/design.py`` at its test preset through a given run folder: the report, the
    figure and the objective it ran are written, and the report is the one it returns."""
    from jprt.cli import main

    run = _rrf_run(tmp_path, fitted_preset)
    out = tmp_path / "out"
    assert main(["run", "experiments/design.py", "--preset", "test", "--set", f"run={run}",
                 "--set", f"output.dir={out}"]) == 0
    (folder,) = os.listdir(out)
    for name in ("config.json", "objective.json", "design.json", "design.png"):
        assert (out / folder / name).is_file(), name
    with open(out / folder / "design.json") as f:
        report = json.load(f)
    assert set(report["bounds"]) == {"back.irradiance", "green-wall.irradiance"}  # the demo's objective
    assert len(report["history"]) == 6 and np.isfinite(report["verified_objective"])
    # an objective file of one's own, named by path: run as written, and copied beside the report
    mine = _write(tmp_path, {"objects": [{"name": "floor", "min": 0.5}]}, "mine.json")
    out2 = tmp_path / "out2"
    assert main(["run", "experiments/design.py", "--preset", "test", "--set", f"run={run}",
                 "--set", f"objective={mine}", "--set", f"output.dir={out2}"]) == 0
    (folder,) = os.listdir(out2)
    with open(out2 / folder / "design.json") as f:
        assert set(json.load(f)["bounds"]) == {"floor.irradiance"}
    with open(out2 / folder / "objective.json") as f:
        assert json.load(f) == {"objects": [{"name": "floor", "min": 0.5}]}


@pytest.mark.parametrize("name", ["datadriven", "mrt"])
def test_the_analytic_direct_light_at_measurement_points_is_mitsubas(name, fitted_preset, tmp_path):
    """Data-driven PRT and MRT take the direct radiance at their points; the design computes it
    with ``point_direct`` and traced visibility, which must be what the method's own task adapter
    gets from Mitsuba (one shadow ray per light) for the same lights."""
    from jprt.inputs import PointLights
    from jprt.runner import save_fit
    from jprt.view import Session

    m, config, dataset, result = fitted_preset(name)
    s = Session(save_fit(str(tmp_path / "run"), name, config, result.params))
    points = design.measurement_points(s)
    lo, hi = design._region(s)
    rng = np.random.default_rng(3)
    pos = lo + (hi - lo) * rng.uniform(0.2, 0.8, (2, 3))
    inten = np.array([[1.0, 0.8, 0.6], [0.5, 0.5, 1.0]])
    want = np.asarray(m.task_lighting(s.handle, dataset, result.params, config,
                                      PointLights.create(pos, inten)).direct)
    got, _ = design.point_direct(points, pos, inten, design.point_visibility(s.handle, points, pos), glossy=False)
    valid = np.asarray(points.valid, bool)  # MRT: texels of faces that exist (the rest are masked out)
    got, want = np.asarray(got)[valid], want[valid]
    assert want.shape == got.shape and np.abs(want).max() > 0
    # the same light at every point but a few on a shadow's edge (the two shadow rays start differently)
    close = np.abs(got - want) <= 1e-4 * np.abs(want).max() + 1e-3 * np.abs(want)
    assert close.all(axis=-1).mean() >= 0.98, close.all(axis=-1).mean()


@pytest.mark.parametrize("name", ["datadriven", "mrt"])
def test_a_design_through_a_measurement_point_model_takes_finite_reverse_mode_steps(name, fitted_preset, tmp_path):
    """The design's step is ``jax.value_and_grad`` through the method's evaluator of the direct
    radiance at its points: finite, and the objective it reports is the model's at the end."""
    from jprt.runner import save_fit

    m, config, dataset, result = fitted_preset(name)
    run = save_fit(str(tmp_path / "run"), name, config, result.params)
    from jprt.render.scenes import SceneHandle
    from jprt.runner import method_config

    names = list(SceneHandle(method_config(m, config)["scene"]).object_names())
    obj = _write(tmp_path, {"objects": [{"name": names[0], "min": 5.0}]}, "first.json")
    pb = design.load_problem(run, obj, size=8, progress=False)
    pos0 = pb.lo + (pb.hi - pb.lo) * 0.5
    res = design.design(pb.frame, pb.objective, pb.masks, pos0[None], np.full((1, 3), 0.1), pb.lo, pb.hi,
                        visibility_fn=pb.visibility, steps=4, progress=False)
    assert np.all(np.isfinite(res.history)) and np.all(np.isfinite(res.position))
    assert res.history[-1] < res.history[0]  # 4 steps of Adam up a hinge below its bound lower it


def _sky(face):
    """A smooth, asymmetric sky: brighter above and towards +X, warm (its rotation is visible)."""
    from jprt.sphere import cubemap

    d = np.asarray(cubemap.texel_directions(face))
    return ((0.5 + 2.0 * np.maximum(d[..., 1:2], 0) ** 2 + 0.8 * np.maximum(d[..., 0:1], 0))
            * np.array([1.0, 0.9, 0.8])).astype(np.float32)


def test_environment_design_finds_the_known_turn_and_scale_of_a_synthetic_model():
    """Pixels that each see a lobe of directions about their own axis (azimuths all round, so a turn
    of the sky moves the image) plus an indirect term linear in the map: the target is the frame
    under the sky turned 0.5 rad and scaled 2; from no turn and scale 1 the design recovers both."""
    from jprt.sphere import cubemap

    face, n = 4, 8
    d = np.asarray(cubemap.texel_directions(face)).reshape(-1, 3)
    omega = np.asarray(cubemap.texel_solid_angles(face)).reshape(-1)
    azimuth, elevation = np.linspace(0, 2 * np.pi, n * n, endpoint=False), np.tile(np.linspace(-0.3, 0.8, n), n)
    axes = np.stack([np.cos(azimuth) * np.cos(elevation), np.sin(elevation), np.sin(azimuth) * np.cos(elevation)], -1)
    transfer = (np.maximum(axes @ d.T, 0) ** 4 * omega).reshape(n, n, -1).astype(np.float32)
    frame = design.environment_frame(_floor(n=n), lambda cube, angle, scale: 0.05 * jnp.mean(cube) * jnp.ones((n, n, 3)),
                                     transfer)
    sky = _sky(face)
    target, _, _ = frame(2.0 * cubemap.rotate_cubemap_y(sky, 0.5), 0.5, jnp.full((3,), 2.0))
    obj = design.Objective(design.ImageTarget(np.asarray(target), None, "full", 1.0), (), 0.0, "synthetic")
    result = design.design_environment(frame, obj, np.zeros((0, n, n)), sky, steps=200, learning_rate=0.05,
                                       progress=False)
    assert result.history[-1] < 1e-6 * result.history[0]
    assert abs(result.angle - 0.5) < 1e-3 and np.allclose(result.scale, 2.0, rtol=1e-3), (result.angle, result.scale)


def test_the_environment_transfer_gives_mitsubas_direct_light(mi):
    """The design's direct light of an environment (its traced transfer at the cube's texels) against
    Mitsuba's direct render of the same map on the Cornell box's diffuse pixels (lit through its open
    front), along the G-buffer's pixel-centre rays: the same mean, and per pixel within what one
    visibility ray per texel allows."""
    from jprt.render import images
    from jprt.render.gbuffer import gbuffer
    from jprt.render.lights import EnvMap
    from jprt.render.scenes import SceneHandle
    from jprt.sphere.envmap import render_equirect

    handle = SceneHandle({"name": "cornell_box", "area_light": False})
    camera = handle.default_camera(24, 24)
    gb = gbuffer(handle, camera)
    sky = _sky(8)
    e = np.einsum("hwj,jc->hwc", design.environment_transfer(handle, gb, 8), sky.reshape(-1, 3))
    pred = np.asarray(gb.diffuse_albedo) / np.pi * e
    handle.set_lighting(EnvMap.create(render_equirect(sky)))
    ref = np.asarray(images.centre_rays(handle, camera, spp=512, seed=1).direct)  # along the G-buffer's rays
    diffuse = np.asarray(gb.valid, bool) & (np.asarray(gb.specular_albedo).max(axis=-1) == 0)
    assert diffuse.sum() > 100
    ratio = pred[diffuse].mean() / ref[diffuse].mean()
    rel = np.sqrt(np.mean((pred[diffuse] - ref[diffuse]) ** 2) / np.mean(ref[diffuse] ** 2))
    assert abs(ratio - 1.0) < 0.05 and rel < 0.25, (ratio, rel)


@pytest.mark.slow
@pytest.mark.parametrize("name", ["sh_prt", "sg_environment"])
def test_jprt_design_turns_and_scales_an_environment(name, tmp_path, fitted_preset, assets, capsys):
    """SH PRT (its SH projection of the turned map) and SG environment visibility (its U, turned)
    through ``jprt design`` with an environment-map file: a finite turn, a positive scale, every
    step, and the objective verified on Mitsuba's render."""
    import glob

    from jprt.cli import main
    from jprt.runner import save_fit

    m, config, dataset, result = fitted_preset(name)
    run = save_fit(str(tmp_path / "run"), name, config, result.params)
    hdr = sorted(glob.glob(os.path.join(assets, "envmaps", "*.hdr")))[0]
    # an object the run's frame shows; SG environment's by its radiance, which reads the model's
    # glossy term (its irradiance is the direct light's alone)
    seen, quantity = {"sh_prt": ("back", "irradiance"), "sg_environment": ("floor", "radiance")}[name]
    objective = _write(tmp_path, {"objects": [{"name": seen, "quantity": quantity, "min": 5.0}]})
    out = str(tmp_path / "design.json")
    assert main(["design", run, "--objective", objective, "--env", hdr, "--size", "12", "--steps", "8",
                 "--verify-spp", "4", "--out", out]) == 0
    with open(out) as f:
        report = json.load(f)
    assert report["environment"] == os.path.basename(hdr) and np.isfinite(report["found"]["rotation_deg"])
    assert np.all(np.asarray(report["found"]["scale"]) > 0) and len(report["history"]) == 8
    assert set(report["verified_terms"]) == {f"{seen}.{quantity}"} and np.isfinite(report["verified_objective"])
    if name == "sg_environment":  # a model of direct light is not designed for an indirect image
        np.save(tmp_path / "target.npy", np.zeros((12, 12, 3), np.float32))
        bad = _write(tmp_path, {"image": {"path": "target.npy", "quantity": "indirect"}}, "indirect.json")
        assert main(["design", run, "--objective", bad, "--env", hdr, "--size", "12", "--steps", "2",
                     "--verify-spp", "4"]) == 2
        assert "predicts the environment's direct light" in capsys.readouterr().err


def test_what_is_not_optimised_keeps_its_starting_value():
    """Colour alone moves the RGB ratios and leaves each light's power (its mean log intensity) and
    position as they started; power alone leaves the colour."""
    gb = _floor(n=8)
    frame = design.design_frame(gb, lambda p, i, v: jnp.zeros((8, 8, 3)), glossy=False)
    lo, hi = np.array([-0.8, 0.6, -0.8]), np.array([0.8, 1.6, 0.8])
    target, _, _ = frame(np.array([[0.1, 1.0, 0.0]]), np.array([[2.0, 1.0, 0.5]]), {"pixels": jnp.ones((8, 8, 1))})
    obj = design.Objective(design.ImageTarget(np.asarray(target), None, "full", 1.0), (), 0.0, "synthetic")
    start_p, start_i = np.array([[-0.2, 1.2, 0.3]]), np.array([[1.0, 1.0, 1.0]])
    colour = design.design(frame, obj, np.zeros((0, 8, 8)), start_p, start_i, lo, hi, steps=100, optimise=["colour"],
                           progress=False)
    np.testing.assert_allclose(np.mean(np.log(colour.intensity)), 0.0, atol=1e-5)
    np.testing.assert_allclose(colour.position, start_p, atol=1e-5)
    assert colour.intensity[0, 0] > colour.intensity[0, 1] > colour.intensity[0, 2]  # it took the target's tint
    power = design.design(frame, obj, np.zeros((0, 8, 8)), start_p, start_i, lo, hi, steps=50, optimise=["power"],
                          progress=False)
    np.testing.assert_allclose(power.intensity[0] / power.intensity[0, 0], 1.0, rtol=1e-5)


def test_the_peers_adam_loop_walks_its_gradients_to_their_optimum():
    """``mitsuba_design``'s loop (Adam on the same parameters, the renderer's gradients in
    position and intensity pulled back through the light map), with a peer whose objective is a
    known quadratic in the light's position and log power: it ends at that optimum, keeps what is
    not optimised (the colour), and checkpoints every ``every`` steps."""
    target_pos, target_level = np.array([0.3, 1.1, -0.2]), np.log(2.0)

    class Quadratic:
        def loss_and_grad(self, pos, inten, seed):
            level = np.log(inten).mean(axis=-1)
            value = float(np.sum((pos - target_pos) ** 2) + np.sum((level - target_level) ** 2))
            d_pos = 2.0 * (pos - target_pos)
            d_inten = (2.0 * (level - target_level))[:, None] / (3.0 * inten)  # d value / d intensity
            return value, d_pos, d_inten

    lo, hi = np.array([-0.8, 0.6, -0.8]), np.array([0.8, 1.6, 0.8])
    start_i = np.array([[1.0, 0.5, 0.25]])
    out = design.mitsuba_design(Quadratic(), np.array([[-0.4, 0.9, 0.5]]), start_i, lo, hi, steps=300,
                                learning_rate=0.05, every=100, progress=False)
    np.testing.assert_allclose(out.position[0], target_pos, atol=2e-2)
    np.testing.assert_allclose(np.log(out.intensity[0]).mean(), target_level, atol=2e-2)
    np.testing.assert_allclose(out.intensity[0] / out.intensity[0, 0], start_i[0] / start_i[0, 0], rtol=1e-4)
    assert out.history[-1] < 1e-2 * out.history[0]
    assert [c["step"] for c in out.checkpoints] == [100, 200, 300]


def test_a_program_compiled_before_the_start_serves_every_start():
    """``design_run`` compiles the design's step while the start is searched (``_warm_design``),
    so the held starting values are arguments of the program, not its constants: one program,
    compiled at the region's centre, designs from two other starts exactly as a program built
    for each, and what is not optimised stays at each start's own value."""
    gb = _floor(n=8)
    frame = design.design_frame(gb, lambda p, i, v: jnp.zeros((8, 8, 3)), glossy=False)
    lo, hi = np.array([-0.8, 0.6, -0.8]), np.array([0.8, 1.6, 0.8])
    target, _, _ = frame(np.array([[0.1, 1.0, 0.0]]), np.array([[2.0, 1.0, 0.5]]), {"pixels": jnp.ones((8, 8, 1))})
    obj = design.Objective(design.ImageTarget(np.asarray(target), None, "full", 1.0), (), 0.0, "synthetic")
    masks = np.zeros((0, 8, 8))
    program = design._warm_design(design._design_program(frame, obj, masks, lo, hi, optimise=["colour"],
                                                         reference=3.0, steps=40, learning_rate=0.05),
                                  None, 1, lo, hi)
    for start_p in (np.array([[-0.2, 1.2, 0.3]]), np.array([[0.5, 0.9, -0.6]])):
        start_i = np.ones((1, 3))
        shared = design.design(frame, obj, masks, start_p, start_i, lo, hi, steps=40, optimise=["colour"],
                               reference_power=3.0, program=program, progress=False)
        own = design.design(frame, obj, masks, start_p, start_i, lo, hi, steps=40, optimise=["colour"],
                            reference_power=3.0, progress=False)
        np.testing.assert_allclose(shared.position, start_p, atol=1e-5)
        np.testing.assert_allclose(shared.position, own.position, rtol=1e-6)
        np.testing.assert_allclose(shared.intensity, own.intensity, rtol=1e-5)
        np.testing.assert_allclose(shared.history, own.history, rtol=1e-5)
    with pytest.raises(ValueError, match="built for another"):
        design.design(frame, obj, masks, start_p, np.ones((1, 3)), lo, hi, steps=40, optimise=["power"],
                      reference_power=3.0, program=program, progress=False)


def test_a_design_corrected_by_the_truths_error_recovers_what_a_biased_model_misses():
    """The correction's principle (``design``'s ``offset``; ``design_run`` measures it on a render,
    ``model_offset``), here with the truth's exact error: the truth's indirect light is a bump
    under the light; the model's bump sits 0.15 beside it, so the model's own optimum lies off the
    light that made the target. Holding the truth's error at the design's result as ``offset``
    and designing again from there (three times) moves the light at least halfway back to the truth's,
    and lowers the objective measured on the truth; a zero offset changes nothing."""
    gb = _floor(n=16)
    x = jnp.asarray(np.asarray(gb.position)[..., 0:1])

    def bump(shift):
        def indirect(position, intensity, visibility):
            return 0.4 * jnp.exp(-4.0 * (x - position[0, 0] - shift) ** 2) * jnp.mean(intensity) * jnp.ones((1, 1, 3))
        return indirect

    truth = design.design_frame(gb, bump(0.0), glossy=False)
    model = design.design_frame(gb, bump(0.15), glossy=False)
    lo, hi = np.array([-0.8, 0.6, -0.8]), np.array([0.8, 1.6, 0.8])
    vis = {"pixels": jnp.ones((16, 16, 1))}
    true_pos, ones = np.array([[0.2, 1.1, -0.1]]), np.ones((1, 3))
    target, _, _ = truth(true_pos, ones, vis)
    obj = design.Objective(design.ImageTarget(np.asarray(target), None, "full", 1.0), (), 0.0, "synthetic")
    masks = np.zeros((0, 16, 16))
    program = design._design_program(model, obj, masks, lo, hi, optimise=["position", "power"], reference=3.0,
                                     steps=300, learning_rate=0.05)

    def run(p, i, offset):
        return design.design(model, obj, masks, p, i, lo, hi, steps=300, reference_power=3.0, offset=offset,
                             program=program, progress=False)

    def on_truth(r):
        return float(sum(design.objective_terms(obj, masks, *truth(r.position, r.intensity, vis), r.intensity,
                                                3.0).values()))

    first = result = run(np.array([[-0.3, 0.9, 0.3]]), ones, None)
    miss = np.linalg.norm(first.position - true_pos)
    assert miss > 0.02  # the model's bias moves its optimum
    unchanged = run(first.position, first.intensity, design._zero_offset((16, 16)))
    np.testing.assert_allclose(unchanged.position, first.position, atol=2e-3)
    for _ in range(3):
        offset = tuple(np.asarray(t) - np.asarray(m) for t, m in zip(truth(result.position, result.intensity, vis),
                                                                     model(result.position, result.intensity, vis)))
        result = run(result.position, result.intensity, offset)
    assert np.linalg.norm(result.position - true_pos) < 0.5 * miss
    assert on_truth(result) < on_truth(first)
    with pytest.raises(ValueError, match="offset is three"):
        run(first.position, first.intensity, (np.zeros((8, 8, 3)),) * 3)


def test_model_offset_is_the_render_minus_the_model_at_the_same_lights(mi):
    """``model_offset`` in the Cornell box, of a model with the analytic direct light and a wrong
    indirect light (a constant): the full and indirect errors are the render's minus the model's
    (the same seed renders the same image), invalid pixels carry none, and the model plus the
    offset scores what the render scores (``rendered_terms``, the same seed) on an image term and
    an irradiance bound alike: ``design_run`` reads the render's objective there."""
    from jprt.inputs import PointLights
    from jprt.render.gbuffer import gbuffer
    from jprt.render.scenes import SceneHandle

    handle = SceneHandle("cornell_box")
    camera = handle.default_camera(8, 8)
    gb = gbuffer(handle, camera)
    frame = design.design_frame(gb, lambda p, i, v: jnp.full((8, 8, 3), 0.05) * jnp.sum(i), glossy=False)
    pos, inten = np.array([[0.1, 0.8, -0.1], [-0.3, 0.7, 0.2]]), np.array([[2.0, 1.5, 1.0], [1.0, 1.0, 1.0]])

    def visibility(p):
        return {"pixels": design.point_visibility(handle, gb, p)}

    full, ind, irr = design.model_offset(handle, camera, gb, frame, pos, inten, visibility_fn=visibility, spp=16,
                                         seed=3)
    r_full, r_ind = design._render_frames(handle, camera, gb, PointLights.create(pos.astype(np.float32),
                                                                                 inten.astype(np.float32)),
                                          spp=16, seed=3)
    valid = np.asarray(gb.valid, bool)[..., None]
    m_full, m_ind, m_irr = (np.asarray(a) for a in frame(pos, inten, visibility(pos)))
    assert np.max(r_ind) > 0 and np.max(m_ind) > 0
    np.testing.assert_allclose(ind, np.where(valid, r_ind - m_ind, 0.0), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(full, np.where(valid, r_full - m_full, 0.0), rtol=1e-5, atol=1e-6)
    assert np.all(np.asarray([full, ind, irr])[:, ~valid[..., 0]] == 0)
    names = list(handle.object_names())
    target = np.where(valid, 1.3 * r_full, 0.0).astype(np.float32)
    obj = design._on_valid(design.Objective(design.ImageTarget(target, None, "full", 1.0),
                                            (design.ObjectTarget("floor", "irradiance", 1e3, None, 1.0),), 0.0,
                                            "synthetic"), gb.valid)  # as load_problem gives it
    masks = design.object_masks(obj, gb.object_id, names, gb.valid)
    corrected = design.objective_terms(obj, masks, *(m + o for m, o in zip((m_full, m_ind, m_irr), (full, ind, irr))),
                                       inten, 3.0)
    rendered = design.rendered_terms(handle, camera, gb, obj, masks, pos, inten, spp=16, seed=3, reference_power=3.0)
    assert set(corrected) == set(rendered) and all(float(v) > 0 for v in rendered.values())
    for key in rendered:
        assert float(corrected[key]) == pytest.approx(rendered[key], rel=1e-4)


def test_merge_candidates_makes_one_light_of_neighbours_that_share_its_weight():
    """Weight spread over three neighbouring candidates and over two far from them: K = 2 gives
    one group per cluster; a K beyond the candidates with weight gives one group each; no weight
    anywhere: no group."""
    x = np.array([[0.1, 0.1, 0.1], [0.15, 0.1, 0.1], [0.1, 0.16, 0.1], [0.9, 0.9, 0.8], [0.85, 0.9, 0.8],
                  [0.5, 0.5, 0.5]])
    w = np.array([1.0, 0.5, 0.5, 2.0, 0.1, 0.0])
    groups = design._merge_candidates(x, w, 2)
    assert sorted(sorted(g.tolist()) for g in groups) == [[0, 1, 2], [3, 4]]
    assert len(design._merge_candidates(x, w, 9)) == 5  # one group per candidate with weight at most
    assert design._merge_candidates(x, np.zeros(6), 2) == []


def test_candidate_weights_recover_the_lights_that_made_the_target():
    """Four candidates with independent unit frames; the target is 2 x the first plus 0.5 x the
    third: the non-negative weights that minimise the image objective are (2, 0, 0.5, 0)."""
    rng = np.random.default_rng(3)
    unit = rng.uniform(0.0, 1.0, (4, 8, 8, 3)).astype(np.float32)
    units = [jnp.asarray(unit), jnp.asarray(unit), jnp.asarray(unit)]
    target = 2.0 * unit[0] + 0.5 * unit[2]
    obj = design.Objective(design.ImageTarget(target, None, "full", 1.0), (), 0.0, "synthetic")
    w = design._candidate_weights(units, obj, np.zeros((0, 8, 8)), 1.0, 2.0 ** np.linspace(-6, 6, 49) / 4)
    np.testing.assert_allclose(w, [2.0, 0.0, 0.5, 0.0], atol=0.02)


def test_design_keeps_its_best_traced_point_and_stops_when_converged():
    """A light over a floor whose shadow edge moves with it (the blade of the search test), started
    beside the light that made the target: with ``keep_best`` the design never ends worse than where
    it started (the objective with visibility traced at the result), and with ``tol`` it stops
    before its step budget once the traces stop improving; without ``tol`` it runs every step."""
    gb = _floor(n=16)

    def visibility(position):
        x = np.asarray(gb.position)[..., 0]
        lights = np.asarray(position, np.float64).reshape(-1, 3)
        return {"pixels": (x[..., None] > lights[None, None, :, 0] - 0.4).astype(np.float32)}

    frame = design.design_frame(gb, lambda p, i, v: 0.02 * jnp.sum(i) * jnp.ones((16, 16, 3)), glossy=False)
    lo, hi = np.array([-0.8, 0.6, -0.8]), np.array([0.8, 1.6, 0.8])
    true_pos, true_int = np.array([[0.3, 1.1, -0.25]]), np.full((1, 3), 3.0)

    def traced(position, intensity):
        frames = frame(position, intensity, {k: jnp.asarray(v) for k, v in visibility(position).items()})
        return float(sum(design.objective_terms(obj, np.zeros((0, 16, 16)), *frames, jnp.asarray(intensity),
                                                3.0).values()))

    target = np.asarray(frame(true_pos, true_int, {k: jnp.asarray(v) for k, v in visibility(true_pos).items()})[0])
    obj = design.Objective(design.ImageTarget(target, None, "full", 1.0), (), 0.0, "synthetic")
    start_pos, start_int = true_pos + np.array([[0.05, 0.0, 0.0]]), np.full((1, 3), 2.5)
    kept = design.design(frame, obj, np.zeros((0, 16, 16)), start_pos, start_int, lo, hi, visibility_fn=visibility,
                         steps=400, learning_rate=0.02, tol=1e-3, progress=False)
    assert traced(kept.position, kept.intensity) <= traced(start_pos, start_int)
    assert len(kept.history) < 400
    full = design.design(frame, obj, np.zeros((0, 16, 16)), start_pos, start_int, lo, hi, visibility_fn=visibility,
                         steps=40, learning_rate=0.02, tol=0.0, progress=False)
    assert len(full.history) == 40
