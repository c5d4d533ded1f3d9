"""Evaluation protocol helpers: set RMSE, equal-error search, timing, report figures."""

import os

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from jprt import eval as jeval


def test_set_rmse_weights_pixels_not_images():
    a = [np.zeros((2, 2, 3)), np.zeros((1, 4, 3))]
    b = [np.ones((2, 2, 3)), np.full((1, 4, 3), 3.0)]
    assert jeval.set_rmse(a, b) == pytest.approx(np.sqrt((12 * 1 + 12 * 9) / 24))
    valid = [np.array([[True, False], [False, False]]), np.zeros((1, 4), bool)]
    assert jeval.set_rmse(a, b, valid) == pytest.approx(1.0)
    with pytest.raises(ValueError, match="differ"):
        jeval.set_rmse([np.zeros((2, 2, 3))], [np.zeros((2, 3, 3))])
    with pytest.raises(ValueError, match="equally many"):
        jeval.set_rmse([], [])
    # a (T, 3) lightmap is not an image: its "RMSE" would silently be sqrt(3) too low with a mask
    with pytest.raises(ValueError, match=r"\(H, W, C\) images"):
        jeval.set_rmse([np.zeros((10, 3))], [np.ones((10, 3))], [np.ones(10, bool)])
    with pytest.raises(ValueError, match="valid mask"):
        jeval.set_rmse(a[:1], b[:1], [np.ones((2, 3), bool)])


def test_equal_error_spp_stops_at_first_success():
    rng = np.random.default_rng(0)
    ref = [np.ones((8, 8, 3))]
    calls = []

    def render_at(spp):  # Monte Carlo-like: error ~ 1 / sqrt(spp)
        calls.append(spp)
        return [ref[0] + rng.normal(size=(8, 8, 3)) / np.sqrt(spp)]

    result = jeval.equal_error_spp(render_at, ref, 0.2, [64, 1, 4, 16, 256, 1024])
    assert result["spp"] in (16, 64) and calls == [1, 4, 16, 64][: len(calls)]
    assert all(t["rmse"] > 0.2 for t in result["tried"][:-1]) and result["tried"][-1]["rmse"] <= 0.2
    assert jeval.equal_error_spp(render_at, ref, 1e-6, [1, 2])["spp"] is None


def test_time_call_and_figures(tmp_path):
    t = jeval.time_call(lambda: np.ones(10).sum(), repeats=3, warmup=1)
    assert len(t["times_ms"]) == 3 and t["min_ms"] <= t["median_ms"]
    img = np.random.default_rng(0).random((6, 5, 3))
    jeval.side_by_side(str(tmp_path / "s.png"), [("a", img, img * 1.1), ("b", img, img)])
    jeval.plot_series(str(tmp_path / "p.png"), {"x": ([1, 2, 4], [3.0, 2.0, 1.0])}, xlabel="spp", ylabel="rmse",
                      logx=True, logy=True, hlines={"RRF": 1.5})
    assert os.path.getsize(tmp_path / "s.png") > 0 and os.path.getsize(tmp_path / "p.png") > 0


def test_write_benchmark_records_the_run(tmp_path):
    import json

    path = str(tmp_path / "b.json")
    jeval.write_benchmark(path, {"x": 1.5}, "python benchmarks/x.py", notes="n")
    with open(path) as f:
        r = json.load(f)
    assert r["x"] == 1.5 and r["context"]["command"] == "python benchmarks/x.py" and r["context"]["notes"] == "n"
    assert "cores" in r["context"]["device"] and r["context"]["date"].endswith("+00:00")


def test_benchmark_records_name_no_machine(tmp_path):
    """Absolute paths inside the checkout (or beside it) are written relative to the repository,
    paths under the home folder as ~/..., anything else as it was."""
    import json

    repo = jeval.REPOSITORY
    home = os.path.expanduser("~")
    result = {"report": os.path.join(repo, "results", "atlas"),
              "runs": [{"dir": os.path.join(os.path.dirname(repo), "shared", "assets", "scenes")}],
              "cache": os.path.join(home, ".cache", "jprt", "x.npz"), "plain": "frame_ms", "n": 3}
    path = str(tmp_path / "b.json")
    jeval.write_benchmark(path, result, "python benchmarks/x.py")
    with open(path) as f:
        r = json.load(f)
    assert r["report"] == os.path.join("results", "atlas")
    assert r["runs"][0]["dir"] == os.path.join("..", "shared", "assets", "scenes")
    assert r["plain"] == "frame_ms" and r["n"] == 3
    if home.startswith(os.path.dirname(repo) + os.sep):  # a home inside the checkout's parent
        assert not os.path.isabs(r["cache"])
    elif home not in ("", "/"):
        assert r["cache"] == os.path.join("~", ".cache", "jprt", "x.npz")
    assert repo not in json.dumps(r)


def test_roofline_counts_a_matmul_and_judges_it_against_the_peak():
    import jax
    import jax.numpy as jnp

    f = jax.jit(lambda a, b: a @ b)
    a, b = jnp.ones((64, 32), jnp.float32), jnp.ones((32, 48), jnp.float32)
    assert jeval.xla_flops(f, a, b) == pytest.approx(2 * 64 * 32 * 48, rel=0.01)
    roof = jeval.roofline(f, a, b, frame_ms=0.5, peak_gflops=10.0)
    assert roof["frame_gflops_per_s"] == pytest.approx(2 * 64 * 32 * 48 / 0.5e-3 / 1e9, rel=0.01)
    assert roof["flops_fraction_of_peak"] == pytest.approx(roof["frame_gflops_per_s"] / 10.0)
    # nothing to count (a copy): no fraction rather than a zero
    assert jeval.roofline(jax.jit(lambda x: x[::-1]), a, frame_ms=1.0, peak_gflops=10.0)["flops_fraction_of_peak"] is None
    assert jeval.matmul_peak_gflops(n=64, repeats=2) > 0


def test_object_scores_relative_rmse_on_lit_objects():
    """On a lit object the score is ||p - r|| / ||r||: predicting zero scores 1, a 10 % error 0.1."""
    ref = np.ones((4, 4, 3))
    ids = np.zeros((4, 4), int)
    ids[:, 2:] = 1
    ref[:, 2:] *= 3.0
    pred = ref.copy()
    pred[:, :2] = 0.0
    pred[:, 2:] *= 1.1
    out = jeval.object_scores([pred], [ref], ids, ["a", "b"])
    assert out["a"]["rel_rmse"] == pytest.approx(1.0) and out["a"]["scale"] == "object"
    assert out["b"]["rel_rmse"] == pytest.approx(0.1) and out["b"]["mean_ratio"] == pytest.approx(1.1)
    assert out["a"]["fraction"] == 0.5 and out["a"]["pixels"] == 8


@settings(max_examples=40, deadline=None)
@given(st.floats(0.0, 1e-30), st.one_of(st.just(0.0), st.floats(1e-6, 10.0)), st.integers(0, 2**31 - 1))
def test_object_scores_a_black_reference_never_gives_a_huge_number(dark, error, seed):
    """An object whose reference is black (or nearly) is judged on its image's scale: its score is
    the error over a tenth of the image's RMS, never infinite or astronomically large; a black
    image everywhere scores 0 for a black prediction and 1 otherwise."""
    rng = np.random.default_rng(seed)
    ref = rng.uniform(0.5, 2.0, (6, 6, 3))
    ids = np.zeros((6, 6), int)
    ids[:2] = 1
    ref[:2] = dark
    pred = ref.copy()
    pred[:2] += error
    out = jeval.object_scores([pred], [ref], ids, ["lit", "dark"])
    image_rms = np.sqrt(np.mean(ref ** 2))
    assert out["dark"]["scale"] == "image" and out["dark"]["mean_ratio"] is None
    assert np.isfinite(out["dark"]["rel_rmse"])
    assert out["dark"]["rel_rmse"] == pytest.approx(error / (jeval.DARK_OBJECT_SCALE * image_rms), rel=1e-6, abs=1e-12)
    black = jeval.object_scores([np.zeros((2, 2, 3)), np.full((2, 2, 3), error)], [np.zeros((2, 2, 3))] * 2,
                                np.zeros((2, 2), int), ["x"])
    assert black["x"]["scale"] == "none" and black["x"]["rel_rmse"] == (0.0 if error == 0 else 1.0)


def test_object_scores_checks_shapes_and_takes_ids_per_item():
    ref = [np.ones((2, 2, 3)), np.ones((3, 3))[..., None] * np.ones(3)]
    ids = [np.zeros((2, 2), int), np.full((3, 3), -1)]
    ids[1][0, 0] = 0
    out = jeval.object_scores(ref, ref, ids, ["a"])
    assert out["a"]["rel_rmse"] == 0.0 and len(out["a"]["rel_rmse_by_lighting"]) == 2
    with pytest.raises(ValueError, match="do not match"):
        jeval.object_scores([np.ones((2, 2, 3))], [np.ones((2, 2, 3))], np.zeros((3, 2), int), ["a"])
    with pytest.raises(ValueError, match="equally many"):
        jeval.object_scores([], [], np.zeros(1), [])


def test_noise_removed_takes_half_the_floor_out():
    assert jeval.noise_removed(0.5, 0.0) == 0.5
    assert jeval.noise_removed(0.5, np.sqrt(2) * 0.3) == pytest.approx(0.4)
    assert jeval.noise_removed(0.1, 1.0) == 0.0

