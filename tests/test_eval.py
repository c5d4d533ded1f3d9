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
    roof = jeval.roofline(f, a, b, frame_ms=0.5, peak_gflops=10.0, bandwidth_gbs=5.0)
    assert roof["frame_gflops_per_s"] == pytest.approx(2 * 64 * 32 * 48 / 0.5e-3 / 1e9, rel=0.01)
    assert roof["flops_fraction_of_peak"] == pytest.approx(roof["frame_gflops_per_s"] / 10.0)
    # nothing to count (a copy): no fraction rather than a zero
    copy = jeval.roofline(jax.jit(lambda x: x[::-1]), a, frame_ms=1.0, peak_gflops=10.0, bandwidth_gbs=5.0)
    assert copy["flops_fraction_of_peak"] is None and copy["roofline"]["fraction_of_roofline"] is None
    assert jeval.matmul_peak_gflops(n=64, repeats=2) > 0


def test_a_gathered_table_is_charged_for_the_rows_read_not_its_size():
    """A lookup of 4096 rows of 64 bytes in a 16 MiB table moves about 4096 lines, not the table
    (XLA's own figure charges the whole table); a table also read in full (a sum) keeps its full
    charge; the same holds through a float16 -> float32 cast."""
    import jax
    import jax.numpy as jnp

    table = jnp.ones((1 << 18, 16), jnp.float32)  # 16 MiB
    idx = (jnp.arange(4096) * 61) % (1 << 18)
    rows = 4096 * 64
    looked_up = jeval.xla_cost(jax.jit(lambda t, i: t[i] * 2.0), table, idx)
    assert looked_up["bytes_xla"] >= table.nbytes
    assert rows <= looked_up["bytes"] <= 4 * rows + idx.nbytes
    cast = jeval.xla_cost(jax.jit(lambda t, i: t.astype(jnp.float32)[i] * 2.0), table.astype(jnp.float16), idx)
    assert cast["bytes"] <= 4 * rows + idx.nbytes
    both = jeval.xla_cost(jax.jit(lambda t, i: t[i].sum() + t.sum()), table, idx)
    assert both["bytes"] >= table.nbytes


def test_a_loop_is_counted_as_many_times_as_it_runs():
    """XLA's own analysis counts a while body once: a ``lax.map`` over 16 tiles reported 1/16 of
    the FLOPs. ``xla_cost`` counts each body its trip count times, in nested loops too, so a tiled
    program costs what the untiled one does (FLOPs and transcendentals); its bytes charge the
    loop's carried arrays once (inputs read, output written), not each tile's intermediates."""
    import jax
    import jax.numpy as jnp

    def body(t):
        return jnp.sin(t) * t + t * t  # 3 FLOPs and 1 transcendental an element

    n = 1 << 16
    flat = jeval.xla_cost(jax.jit(body), jnp.ones((n,), jnp.float32))
    assert flat["loops"] == [] and flat["flops"] == pytest.approx(3 * n)
    for tiles in (4, 16):
        tiled = jeval.xla_cost(jax.jit(lambda x: jax.lax.map(body, x)), jnp.ones((tiles, n // tiles), jnp.float32))
        assert tiled["loops"] == [tiles]
        assert tiled["flops"] == pytest.approx(3 * n, rel=1e-3)
        assert tiled["transcendentals"] == pytest.approx(n)
        # the input read and the output written once each (and at most one copy XLA makes
        # outside the loop), however many tiles
        assert 2 * 4 * n <= tiled["bytes"] <= 3.5 * 4 * n and tiled["bytes"] <= tiled["bytes_xla"]
    nested = jeval.xla_cost(jax.jit(lambda x: jax.lax.map(lambda t: jax.lax.map(body, t), x)),
                            jnp.ones((4, 8, n // 32), jnp.float32))
    assert sorted(nested["loops"]) == [4, 8] and nested["flops"] == pytest.approx(3 * n, rel=1e-3)
    steps = jeval.xla_cost(jax.jit(lambda a: jax.lax.fori_loop(0, 5, lambda i, a: body(a), a)),
                           jnp.ones((n,), jnp.float32))
    assert steps["flops"] == pytest.approx(5 * 3 * n, rel=1e-3)
    assert steps["bytes"] < steps["bytes_xla"] / 2  # the state carried once, not read and written 5 times
    # a loop that runs until a condition holds has no trip count: counted once, and said so; a
    # loop of known count inside it still counts its iterations
    until = jeval.xla_cost(jax.jit(lambda a: jax.lax.while_loop(
        lambda c: c.sum() < 1e30, lambda c: jax.lax.fori_loop(0, 8, lambda i, x: body(x), c), a)),
        jnp.ones((n,), jnp.float32))
    assert until["loops_unknown"] == 1 and until["loops"] == [8]
    assert until["flops"] >= 8 * 3 * n
    # a loop inside a conditional's branch: XLA costs the larger branch, so it stays once, said so
    branch = jeval.xla_cost(jax.jit(lambda a, p: jax.lax.cond(
        p, lambda x: jax.lax.fori_loop(0, 8, lambda i, y: body(y), x), body, a)), jnp.ones((n,), jnp.float32), True)
    assert branch["loops_unknown"] == 1 and branch["flops"] < 8 * 3 * n


def test_roofline_is_the_lower_of_the_peak_and_intensity_times_bandwidth():
    """attainable = min(peak, FLOP/byte x bandwidth); the bound names the smaller; the fraction is
    the achieved rate over it. XLA's bytes of a matmul are at least its operands and result."""
    import jax
    import jax.numpy as jnp

    f = jax.jit(lambda a, b: a @ b)
    a, b = jnp.ones((64, 32), jnp.float32), jnp.ones((32, 48), jnp.float32)
    assert jeval.xla_cost(f, a, b)["bytes"] >= 4 * (64 * 32 + 32 * 48 + 64 * 48)
    # memory-bound: 1 FLOP per byte at 5 GB/s attains 5 of a 100 GFLOP/s peak
    r = jeval.roofline(f, a, b, frame_ms=1.0, peak_gflops=100.0, bandwidth_gbs=5.0, flops=2e6, frame_bytes=2e6)["roofline"]
    assert r["intensity"] == 1.0 and r["attainable_gflops"] == 5.0 and r["bound"] == "memory"
    assert r["fraction_of_roofline"] == pytest.approx(2.0 / 5.0)  # 2e6 FLOP in 1 ms = 2 GFLOP/s
    # compute-bound: 100 FLOP per byte would attain 500, more than the peak
    r = jeval.roofline(f, a, b, frame_ms=1.0, peak_gflops=100.0, bandwidth_gbs=5.0, flops=2e6, frame_bytes=2e4)["roofline"]
    assert r["attainable_gflops"] == 100.0 and r["bound"] == "compute"
    assert r["fraction_of_roofline"] == pytest.approx(0.02)
    assert set(r) >= {"matmul_gflops", "bandwidth_gbs", "frame_flops", "frame_bytes", "attainable_gflops",
                      "fraction_of_roofline"}


def test_stream_bandwidth_moves_three_arrays():
    """The triad's rate is finite and positive, and measured once per argument set; it writes into
    its donated input's buffer (no fresh pages to fault in) and computes b + 3 c."""
    import jax.numpy as jnp

    first = jeval.stream_bandwidth_gbs(n_bytes=1 << 20, repeats=2)
    assert 0 < first < 1e5 and jeval.stream_bandwidth_gbs(n_bytes=1 << 20, repeats=2) == first
    a, b, c = jnp.zeros(256), jnp.ones(256), jnp.full(256, 0.5)
    assert "input_output_alias={ {}: (0," in jeval._triad().lower(a, b, c).compile().as_text()
    assert np.allclose(np.asarray(jeval._triad()(a, b, c)), 2.5)


def test_a_roofline_carries_the_stream_of_its_own_size():
    """``roofline_of`` measures the triad at the frame's bytes (``stream_at_size``: four arrays of
    a quarter each, rounded up to 64 KiB, so nearby sizes share one measurement) and reports its
    rate over the bandwidth it was given; without a byte count (none, zero, not finite) there is
    no size to measure."""
    sized = jeval.stream_at_size(3e5, 10.0)
    assert sized["stream_gbs_at_frame_bytes"] == jeval.stream_bandwidth_gbs(
        n_bytes=128 << 10, repeats=jeval.SIZED_STREAM_REPEATS) > 0  # 75 000 bytes an array -> 128 KiB
    assert sized["stream_fraction_at_frame_bytes"] == pytest.approx(sized["stream_gbs_at_frame_bytes"] / 10.0)
    assert jeval.stream_at_size(3.1e5, 10.0) == sized
    r = jeval.roofline_of(1e6, 3e5, frame_ms=1.0, peak_gflops=100.0, bandwidth_gbs=10.0)["roofline"]
    assert r["stream_gbs_at_frame_bytes"] == sized["stream_gbs_at_frame_bytes"]
    assert jeval.stream_at_size(1.0, 10.0)["stream_gbs_at_frame_bytes"] == jeval.stream_bandwidth_gbs(
        n_bytes=64 << 10, repeats=jeval.SIZED_STREAM_REPEATS)  # never below 64 KiB an array
    for moved in (None, 0.0, float("nan")):
        r = jeval.roofline_of(1e6, moved, frame_ms=1.0, peak_gflops=100.0, bandwidth_gbs=10.0)["roofline"]
        assert r["stream_gbs_at_frame_bytes"] is None and r["stream_fraction_at_frame_bytes"] is None


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



def test_score_images_is_the_held_out_protocol():
    """One definition of the held-out scores: RMSE over every valid pixel and channel of all images,
    relative to the references' RMS, the 99.9th percentile of |error|, tonemapped PSNR / SSIM per
    image averaged; SSIM None under its window; unknown names refused; a subset computes only it."""
    from jprt import metrics

    rng = np.random.default_rng(1)
    refs = [rng.random((12, 12, 3)) for _ in range(2)]
    preds = [r + 0.05 * rng.standard_normal(r.shape) for r in refs]
    valid = [np.ones((12, 12), bool), rng.random((12, 12)) > 0.3]
    direct = [rng.random((12, 12, 3)) for _ in range(2)]
    s = jeval.score_images(preds, refs, valid, direct, scores=jeval.SCORES[:7] + ("ssim_full", "image_rmse_mean"))
    assert s["indirect_rmse"] == pytest.approx(jeval.set_rmse(preds, refs, valid))
    ref_rms = np.sqrt(sum(float(np.sum(r[m] ** 2)) for r, m in zip(refs, valid)) / (3 * sum(m.sum() for m in valid)))
    assert s["indirect_rel_rmse"] == pytest.approx(s["indirect_rmse"] / ref_rms)
    err = np.concatenate([np.abs(p - r)[m].ravel() for p, r, m in zip(preds, refs, valid)])
    assert s["p999_abs_error"] == pytest.approx(np.percentile(err, 99.9))
    assert s["psnr_indirect"] == pytest.approx(np.mean([metrics.tonemapped(metrics.psnr, p, r) for p, r in zip(preds, refs)]))
    assert s["psnr_full"] == pytest.approx(np.mean([metrics.tonemapped(metrics.psnr, d + p, d + r)
                                                    for p, r, d in zip(preds, refs, direct)]))
    assert s["ssim_indirect"] is not None and s["ssim_full"] is not None
    assert s["image_rmse_mean"] == pytest.approx(np.mean([metrics.rmse(p, r, m) for p, r, m in zip(preds, refs, valid)]),
                                                 rel=1e-5)
    small = jeval.score_images([p[:8, :8] for p in preds], [r[:8, :8] for r in refs],
                               scores=("ssim_indirect", "psnr_full"))
    assert small == {"ssim_indirect": None, "psnr_full": None}  # under SSIM's window; no direct images
    masked = jeval.score_images(preds, refs, valid, scores=("psnr_indirect",), psnr_valid=True)["psnr_indirect"]
    assert masked == pytest.approx(np.mean([metrics.tonemapped(metrics.psnr, p, r, valid=m)
                                            for p, r, m in zip(preds, refs, valid)]))
    held = jeval.HeldOut(preds, refs, valid, direct)
    assert jeval.score_held_out(held, scores=("indirect_rmse",)) == {"indirect_rmse": s["indirect_rmse"]}
    with pytest.raises(ValueError, match="unknown scores"):
        jeval.score_images(preds, refs, scores=("psnr",))


def test_per_image_relative_rmse_finds_the_pair_a_set_hides():
    """Each image's relative RMSE is its own error over its own reference's RMS on its own valid
    pixels; the worst of them is reported beside the set's score, which a bright, well-predicted
    image can pull under a dark, badly predicted one's; a black reference scores 0 when matched
    and inf when not (never a division by zero)."""
    rng = np.random.default_rng(2)
    bright = 10 * rng.random((12, 12, 3)) + 1
    dark = 0.1 * rng.random((12, 12, 3)) + 0.01
    valid = [np.ones((12, 12), bool), rng.random((12, 12)) > 0.3]
    preds = [1.01 * bright, 0 * dark]  # 1 % off, and black
    s = jeval.score_images(preds, [bright, dark], valid,
                           scores=("indirect_rel_rmse", "indirect_rel_rmse_by_image", "indirect_rel_rmse_worst_image"))
    assert s["indirect_rel_rmse_by_image"] == pytest.approx([0.01, 1.0])
    assert s["indirect_rel_rmse_worst_image"] == pytest.approx(1.0)
    assert s["indirect_rel_rmse"] < 0.02  # the set's score hides the black image
    black = np.zeros((4, 4, 3))
    per = jeval.score_images([black, black + 1], [black, black], scores=("indirect_rel_rmse_by_image",))
    assert per["indirect_rel_rmse_by_image"] == [0.0, float("inf")]


def test_equal_error_curve_measures_and_reads():
    """The curve measures ascending spp until one reaches the target (each timed), reads a model's
    error off it (the smallest spp at or under it; the largest spp's time as a lower bound when none
    is), and a later, smaller error extends it with larger spp only."""
    ref = [np.zeros((4, 4, 3))]
    rendered, timed = [], []

    def render_at(spp):
        rendered.append(spp)
        return [np.full((4, 4, 3), 1.0 / spp)]  # RMSE 1 / spp

    def time_at(spp):
        timed.append(spp)
        return 10.0 * spp

    tracer = jeval.PathTracer(render_at, time_at, "fake")
    curve = jeval.EqualErrorCurve().measure(tracer, ref, None, [8, 1, 2, 4, 16], target=0.3)
    assert rendered == timed == [1, 2, 4] and [p["ms"] for p in curve.points] == [10.0, 20.0, 40.0]
    assert curve.read(0.3, frame_ms=2.0) == {"equal_error_spp": 4, "pathtrace_ms_equal_error": 40.0,
                                             "speedup_equal_error": 20.0, "equal_error_reached": True}
    assert curve.read(0.6)["equal_error_spp"] == 2  # read off the measured points, nothing rendered
    assert curve.read(0.01) == {"equal_error_spp": None, "pathtrace_ms_equal_error": 40.0,
                                "speedup_equal_error": None, "equal_error_reached": False}
    curve.measure(tracer, ref, None, [1, 2, 4, 8, 16, 32], target=0.1)
    assert rendered == [1, 2, 4, 8, 16] and curve.read(0.1)["equal_error_spp"] == 16
    assert curve.tried == [{"spp": s, "rmse": pytest.approx(1.0 / s)} for s in (1, 2, 4, 8, 16)]
    assert jeval.EqualErrorCurve().read(0.1)["equal_error_spp"] is None  # nothing measured: nothing to read


def test_interleaved_times_time_every_pair():
    calls = []
    out = jeval.interleaved_times({"a": lambda x, l: calls.append(("a", l)), "b": lambda x, l: calls.append(("b", l))},
                                  None, {1: 1, 4: 4}, repeats=2)
    assert set(out) == {("a", 1), ("a", 4), ("b", 1), ("b", 4)}
    assert calls[:4] == [("a", 1), ("a", 1), ("a", 4), ("a", 4)]  # one warm-up call each in the first round
    assert all(v["min_ms"] <= v["median_ms"] for v in out.values())
