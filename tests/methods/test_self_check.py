"""Each fit says when it is wrong (issue 45): ``Method.self_check`` scores a fit on held-out lights
or maps of its own training renders (``jprt.methods.selfcheck``). The warning rule on made-up
numbers; the scores of a zero prediction; every method's check end to end on its ``test`` preset
(sh_prt in the default suite, the others slow: their test presets together take over a minute)."""

import math
import os
import warnings

import numpy as np
import pytest

from jprt.methods import REGISTRY
from jprt.methods import selfcheck
from jprt.methods.selfcheck import FACTOR, KEYS, TRAIN_FLOOR, SelfCheckWarning, self_check_warning

CHECKED = ("rrf", "datadriven", "sg_lightfield", "wavelet_prt", "sh_prt")


# ---------------------------------------------------------------------------------------------
# The warning rule


def test_warning_rule_object_worse_than_zero():
    w = self_check_warning("m", {"floor": 0.2, "lamp": 1.3, "wall": 1.0}, 0.5, 0.3)
    assert w is not None and "\n" not in w and w.startswith("m self-check")
    assert "lamp 1.30" in w and "wall 1.00" in w and "floor" not in w
    assert w.index("lamp") < w.index("wall")  # worst first
    assert self_check_warning("m", {"floor": 0.2, "lamp": 1.3}, 0.5, None) is not None  # no training error: still
    assert "lamp" in self_check_warning("m", {"floor": 0.2, "lamp": float("nan")}, 0.5, 0.3)  # not finite: warns


def test_warning_rule_far_worse_than_training():
    per = {"floor": 0.7, "wall": 0.2}
    w = self_check_warning("m", per, 0.6, 0.1)  # 0.6 > 3 x 0.1
    assert w is not None and "\n" not in w and "floor 0.70" in w and "wall" not in w and "0.600" in w
    # the bound is FACTOR x max(train, TRAIN_FLOOR): a training error near 0 does not make 0.12 "far worse"
    assert self_check_warning("m", {"a": 0.12}, 0.12, 0.001) is None
    assert self_check_warning("m", {"a": 0.2}, 0.2, 0.001) is not None
    assert FACTOR * TRAIN_FLOOR == pytest.approx(0.15)
    # no object alone above the bound: the worst one is named
    w = self_check_warning("m", {"a": 0.2, "b": 0.25}, 0.35, 0.1)
    assert w is not None and "b 0.25" in w


def test_warning_rule_quiet_when_fine():
    assert self_check_warning("m", {"floor": 0.2, "wall": 0.3}, 0.25, 0.2) is None
    assert self_check_warning("m", {"floor": 0.9}, 0.9, 0.5) is None  # < 1 and < 3 x training
    assert self_check_warning("m", {"floor": 0.4}, 0.4, None) is None
    assert self_check_warning("m", {}, float("nan"), None) is None


def test_result_emits_the_warning_once():
    with pytest.warns(SelfCheckWarning, match="m self-check: .*lamp 1.50"):
        out = selfcheck.result("m", {"lamp": 1.5}, 1.5, 0.2, "2 held-out lights")
    assert tuple(out)[:len(KEYS)] == KEYS and out["warning"].startswith("m self-check")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        fine = selfcheck.result("m", {"lamp": 0.1}, 0.1, 0.08, "2 held-out lights")
        quiet = selfcheck.result("m", {"lamp": 1.5}, 1.5, 0.2, "x", emit=False)
    assert fine["warning"] is None and quiet["warning"] is not None


def test_scores_measure_what_they_say():
    """A zero prediction scores 1 on every lit object and pooled; a perfect one 0; an object dark
    against the items is judged on their scale (below 1 for zero); unlabelled entries are ignored."""
    rng = np.random.default_rng(0)
    ids = np.array([0] * 40 + [1] * 30 + [2] * 20 + [-1] * 10)
    refs = [rng.uniform(0.5, 2.0, (100, 3)) * (np.where(ids == 2, 1e-4, 1.0))[:, None] for _ in range(3)]
    names = ["floor", "wall", "dark"]
    rel, per = selfcheck.scores([np.zeros_like(r) for r in refs], refs, ids, names)
    assert rel == pytest.approx(1.0) and per["floor"] == pytest.approx(1.0) and per["wall"] == pytest.approx(1.0)
    assert per["dark"] < 0.01
    rel, per = selfcheck.scores(refs, refs, ids, names)
    assert rel == 0.0 and all(v == 0.0 for v in per.values())
    noisy = [r + np.where(ids[:, None] < 0, 1e3, 0.0) for r in refs]  # unlabelled entries do not count
    assert selfcheck.scores(noisy, refs, ids, names)[0] == 0.0
    assert math.isnan(selfcheck.scores(refs, refs, np.full(100, -1), names)[0])


def test_registered_methods_have_self_check():
    for name in CHECKED:
        m = REGISTRY[name]
        data = __import__(f"jprt.methods.{name}.data", fromlist=["data"])
        assert m.self_check is data.self_check, name
    assert REGISTRY["mrt"].self_check is None and REGISTRY["sg_environment"].self_check is None


# ---------------------------------------------------------------------------------------------
# End to end on the test presets


@pytest.fixture(scope="module")
def fitted(fitted_preset):
    """``get(name) -> (method, config, dataset, FitResult)`` on the method's test preset
    (``conftest.fitted_preset``: fitted once for the session)."""
    return fitted_preset


def _params(name):
    return pytest.param(name, marks=[] if name == "sh_prt" else [pytest.mark.slow])


@pytest.mark.mitsuba
@pytest.mark.parametrize("name", [_params(n) for n in CHECKED])
def test_self_check_end_to_end(mi, fitted, name):
    from jprt.render.scenes import SceneHandle

    m, config, dataset, result = fitted(name)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", SelfCheckWarning)
        check = m.self_check(dataset, result, config)
    assert set(KEYS) <= set(check)
    assert math.isfinite(check["rel_rmse"]) and check["rel_rmse"] >= 0.0
    scene_names = set(SceneHandle(config["scene"]).object_names())
    assert check["per_object"] and set(check["per_object"]) <= scene_names
    assert all(math.isfinite(v) and v >= 0.0 for v in check["per_object"].values())
    if name == "sh_prt":
        assert check["train_rel_rmse"] is None  # the bake is the fit
    else:
        assert math.isfinite(check["train_rel_rmse"]) and check["train_rel_rmse"] >= 0.0
    assert isinstance(check["held_out"], str) and check["held_out"]
    expected = self_check_warning(name, check["per_object"], check["rel_rmse"], check["train_rel_rmse"])
    assert check["warning"] == expected
    emitted = [str(w.message) for w in caught if issubclass(w.category, SelfCheckWarning)]
    assert emitted == ([expected] if expected else [])
    if expected:
        assert "\n" not in expected and expected.startswith(f"{name} self-check")


def _zero(name, params):
    """``params`` whose prediction is 0 everywhere (methods linear in their parameters' outputs)."""
    import jax

    if name == "sh_prt":
        return {**params, "transfer": np.zeros_like(params["transfer"])}
    if name == "datadriven":
        return {**params, **{k: np.zeros_like(params[k]) for k in ("mean", "basis", "transfer")}}
    if name == "sg_lightfield":
        return {**params, "amplitude": np.zeros_like(params["amplitude"]),
                "irradiance": np.zeros_like(params["irradiance"])}
    return jax.tree_util.tree_map(np.zeros_like, params)


@pytest.mark.mitsuba
@pytest.mark.parametrize("name", [_params(n) for n in ("sh_prt", "datadriven", "sg_lightfield")])
def test_zero_prediction_scores_one(mi, fitted, name):
    """The check measures what it says: a zero prediction scores 1 pooled and on every object
    whose held-out reference is lit (``object_scores``' own scale), at most 1 on dark ones."""
    from jprt.methods.base import FitResult

    m, config, dataset, result = fitted(name)
    check = m.self_check(dataset, FitResult(_zero(name, result.params), result.info), config)
    assert check["rel_rmse"] == pytest.approx(1.0, abs=1e-6)
    values = list(check["per_object"].values())
    assert values and max(values) == pytest.approx(1.0, abs=1e-6) and min(values) >= 0.0
    assert check["warning"] is not None  # worse than nothing is "wrong"


@pytest.mark.mitsuba
def test_sh_prt_check_keeps_the_bake_cache_key(mi, fitted):
    """The held-out maps are an entry of their own (and so is the exit transfer): the bake's entry
    is the one of the spec before ``sh.check_maps`` and the ``sh.exit_*`` keys existed, shared by
    check_maps 0 and 1, and check_maps 0 renders no check."""
    from jprt import cache
    from jprt.render.lightmap import ATLAS_FORMAT
    from jprt.render.scenes import describe

    m, config, dataset, _ = fitted("sh_prt")
    sh = {k: v for k, v in config["sh"].items() if k != "check_maps" and not k.startswith("exit_")}
    old = {"format": 1, "scene": describe(config["scene"]), "objects": list(config["objects"]),
           "lightmap": config["lightmap"], "sh": sh, "atlas_format": ATLAS_FORMAT}
    assert int(config["sh"]["check_maps"]) >= 1 and "check" in dataset.meta
    bare = m.make_dataset(config["scene"], m.resolve({**m.presets["test"], "sh": {**m.presets["test"]["sh"],
                                                                                 "check_maps": 0}}),
                          progress=False)
    assert "check" not in bare.meta
    assert os.path.exists(cache.entry_path("sh_prt", old))
    np.testing.assert_array_equal(bare.transfer, dataset.transfer)
    # check_maps 1 in this worker's cache reads the same bake entry and adds only the check's entry
    bakes = os.path.dirname(cache.entry_path("sh_prt", old))
    before = sorted(os.listdir(bakes))
    again = m.make_dataset(config["scene"], config, progress=False)
    assert sorted(os.listdir(bakes)) == before
    np.testing.assert_array_equal(again.transfer, dataset.transfer)
    assert "check" in again.meta
    assert m.self_check(bare, m.fit(bare, config), config)["warning"] is None


@pytest.mark.mitsuba
@pytest.mark.slow
def test_sg_lightfield_checks_texels_the_atlas_shows(mi, fitted):
    """The evaluator reads a texel through the atlas, where a texel no view sees shows a seen
    neighbour's value (``build_atlas``'s ``seen_from``): the self-check draws its texels among those
    the atlas shows, so its training error is the fit's, not the neighbour's difference."""
    _, _, dataset, _ = fitted("sg_lightfield")
    a = dataset.atlas
    shows = np.asarray(a["fill_index"])[np.asarray(a["texel_index"])] == np.arange(len(a["texel_index"]))
    assert not shows.all()  # the preset's atlas hides some texels (under the boxes), so this can fail
    idx = np.asarray(dataset.meta["check"]["index"])
    assert len(idx) and shows[idx].all()


def test_sg_lightfield_check_candidates_are_shown_and_outside():
    """Texels inside geometry or hidden by the atlas (their pixel shows another texel) are never
    drawn for the self-check."""
    from jprt.methods.sg_lightfield.data import check_candidates
    from jprt.render.lightfield import INSIDE, OK, PUSHED

    # a 4 x 4 atlas of 5 texels: texel 3's pixel shows texel 2 (hidden), texel 4 is inside geometry
    texel_index = np.array([0, 1, 2, 3, 4])
    fill = np.array([0, 1, 2, 2] + [4] * 12)
    flags = np.array([OK, PUSHED, OK, OK, INSIDE], np.int8)
    got = check_candidates({"fill_index": fill, "texel_index": texel_index}, flags)
    np.testing.assert_array_equal(got, [0, 1, 2])
