"""Work killed with SIGKILL and restarted (issue 20; in a folder of its own so that pytest-xdist,
which hands out whole files, starts this long file early): what was written before the kill stays
as it was, nothing finished is redone, and the result equals an uninterrupted run (bit for
bit for training; to float rounding for Mitsuba renders, which differ by about one ulp between
processes: 2e-7 measured on values near 0.3, so 1e-6 relative is the stated tolerance)."""

import glob
import json
import os
import signal
import subprocess
import sys
import time

import jax
import numpy as np
import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def _env():
    """The worker's environment: this session's XLA compilation cache (tests/conftest.py), every
    program written to it (the workers' dozens of small eager programs too), so the killed run,
    the resumed run and this process compile each program once between them."""
    env = dict(os.environ)
    if jax.config.jax_compilation_cache_dir:
        env["JAX_COMPILATION_CACHE_DIR"] = jax.config.jax_compilation_cache_dir
        env["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] = "0"
    return env


def _start(*args):
    return subprocess.Popen([sys.executable, "-m", "tests.faults.worker", *map(str, args)], cwd=ROOT,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=_env())


def _kill_when(proc, ready, timeout_s=120.0):
    """SIGKILL ``proc`` as soon as ``ready()``; fail if it ends first (the kill must happen)."""
    t0 = time.time()
    while not ready():
        if proc.poll() is not None:
            out, err = proc.communicate()
            pytest.fail(f"the worker ended (code {proc.returncode}) before it could be killed: {err[-2000:]}")
        if time.time() - t0 > timeout_s:
            proc.kill()
            pytest.fail("the worker never reached the point to kill it at")
        time.sleep(0.02)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert proc.returncode == -signal.SIGKILL


def _run(*args):
    done = subprocess.run([sys.executable, "-m", "tests.faults.worker", *map(str, args)], cwd=ROOT,
                          capture_output=True, text=True, timeout=600, env=_env())
    assert done.returncode == 0, done.stderr[-3000:]
    return json.loads(done.stdout.strip().splitlines()[-1])


@pytest.mark.mitsuba
def test_a_killed_dataset_render_resumes_without_touching_finished_entries(tmp_path, mi):
    from tests.faults import worker as fault_worker

    cache = tmp_path / "cache"
    items = lambda: sorted(glob.glob(str(cache / "datasets" / "*" / "item_*.npz.sha256")))  # noqa: E731
    # 0.15 s after each entry: the 13 items after the third leave a 2 s window for the kill
    _kill_when(_start("render", cache, 0.15), lambda: len(items()) >= 3)
    before = {p: (os.stat(p[:-7]).st_mtime_ns, open(p[:-7], "rb").read()) for p in items()}
    assert 3 <= len(before) < 16
    resumed = fault_worker.render(str(cache))
    # the entries present at the kill were read, not rendered again, and are byte-for-byte as they were
    assert resumed.stats["cached"] >= len(before) and resumed.stats["corrupt"] == 0
    assert resumed.stats["rendered"] + resumed.stats["cached"] == 4 + 4 + 16  # lightings, G-buffers, items
    for path, (mtime, data) in before.items():
        assert os.stat(path[:-7]).st_mtime_ns == mtime and open(path[:-7], "rb").read() == data
    assert not glob.glob(str(cache / "datasets" / "*" / "*.tmp")) and not glob.glob(str(cache / "datasets" / "*" / ".*.tmp"))
    fresh = fault_worker.render(str(tmp_path / "fresh"))
    np.testing.assert_allclose(resumed.stacked("indirect"), fresh.stacked("indirect"), rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(resumed.stacked("direct"), fresh.stacked("direct"), rtol=1e-6, atol=1e-7)


def _checkpoint(path):
    """(arrays by stored tree path, header) of a ``jprt.io.save_checkpoint`` file."""
    with np.load(path, allow_pickle=False) as data:
        arrays = {k: data[k] for k in data.files}
    return arrays, json.loads(bytes(arrays.pop("__jprt_checkpoint__")).decode())


# slow (30 s of the default suite's budget): the LM fit's and the dataset render's kill tests stay in
# the default suite, and tests/solve/test_adam_losses.py resumes Adam bit-identically in-process
@pytest.mark.slow
def test_a_killed_adam_training_resumes_bit_identically(tmp_path):
    from tests.faults import worker as fault_worker

    ckpt = tmp_path / "train.npz"
    _kill_when(_start("train", ckpt, tmp_path / "unused.npz"), ckpt.exists)
    step_at_kill = _checkpoint(ckpt)[1]["step"]
    assert 0 < step_at_kill < fault_worker.TRAIN["steps"]
    info = _run("train", ckpt, tmp_path / "resumed.npz")
    # no step before the last checkpoint is repeated: the run starts where the checkpoint ends
    assert info["resumed_from"] == step_at_kill and info["step"] == fault_worker.TRAIN["steps"]
    assert info["losses"] == fault_worker.TRAIN["steps"] - step_at_kill
    # the uninterrupted run, in this process: equal bits across processes too
    fault_worker.train(str(tmp_path / "whole.npz"), str(tmp_path / "whole_out.npz"))
    a, b = _checkpoint(tmp_path / "resumed.npz")[0], _checkpoint(tmp_path / "whole_out.npz")[0]
    assert a.keys() == b.keys() and a
    for key in a:
        np.testing.assert_array_equal(a[key], b[key], err_msg=key)


@pytest.fixture(scope="module")
def tiny_wavelet_fits(tmp_path_factory):
    """(data, the bytes of a checkpoint after 4 of TINY's 12 steps, the uninterrupted fit) of the
    tiny neural-wavelet model on fake data, made once for the damaged-checkpoint tests."""
    from jprt.methods.wavelet_prt import model as wp
    from tests.methods.test_wavelet_prt import TINY, _fake_data

    data = _fake_data(n=4)
    path = tmp_path_factory.mktemp("tiny_wavelet") / "ckpt.npz"
    wp.fit(data, TINY, checkpoint_path=str(path), progress=False, stop_after=4)
    return data, path.read_bytes(), wp.fit(data, TINY, progress=False)


@pytest.mark.parametrize("damage", ["truncate", "flip_byte"])
def test_a_damaged_checkpoint_is_detected_and_training_rebuilt(tmp_path, damage, tiny_wavelet_fits):
    """A truncated or bit-flipped checkpoint is not resumed from: a warning, the file kept aside
    as .corrupt, and training from step 0 (bit-identical to a run that never had it)."""
    from jprt.methods.wavelet_prt import model as wp
    from tests.methods.test_wavelet_prt import TINY

    data, checkpoint, whole = tiny_wavelet_fits
    path = tmp_path / "ckpt.npz"
    raw = bytearray(checkpoint)
    if damage == "truncate":
        raw = raw[: len(raw) // 2]
    else:
        raw[len(raw) // 3] ^= 0x40  # inside the arrays: the zip's CRC-32 no longer matches
    path.write_bytes(bytes(raw))
    with pytest.warns(UserWarning, match="cannot read checkpoint"):
        rebuilt = wp.fit(data, TINY, checkpoint_path=str(path), progress=False)
    assert rebuilt.info["resumed_from"] == 0 and (tmp_path / "ckpt.npz.corrupt").exists()
    for a, b in zip(jax.tree_util.tree_leaves(rebuilt.params), jax.tree_util.tree_leaves(whole.params)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


@pytest.mark.mitsuba
def test_a_full_disk_fails_clearly_and_leaves_no_entry_a_later_run_trusts(tmp_path, mi):
    from jprt.cache import entry_state
    from tests.faults import worker as fault_worker

    cache = tmp_path / "cache"
    done = subprocess.run([sys.executable, "-m", "tests.faults.worker", "render-limited", str(cache), "3000"],
                          cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert done.returncode != 0
    assert "disk full or a file-size limit" in done.stderr and "File too large" in done.stderr, done.stderr[-2000:]
    folder = glob.glob(str(cache / "datasets" / "*"))
    assert folder and not glob.glob(folder[0] + "/*.tmp") and not glob.glob(folder[0] + "/.*.tmp")
    for entry in glob.glob(folder[0] + "/*.npz"):
        assert entry_state(entry) in ("ok", "missing"), entry  # a checksum only ever for a whole file
    resumed = fault_worker.render(str(cache))
    assert resumed.stats["corrupt"] == 0 and resumed.stats["rendered"] + resumed.stats["cached"] == 24
    fresh = fault_worker.render(str(tmp_path / "fresh"))
    np.testing.assert_allclose(resumed.stacked("indirect"), fresh.stacked("indirect"), rtol=1e-6, atol=1e-7)


def test_training_on_a_1e5_sun_and_a_near_black_map_stays_finite():
    """Extreme data: one map holding a texel of radiance 1e5 (its images 1e3 x brighter), one
    1e-8 x dimmer than the rest: the loss is finite at every step, the parameters too."""
    from jprt.methods.wavelet_prt import model as wp
    from tests.methods.test_wavelet_prt import TINY, _fake_data

    data = _fake_data(n=4)
    envs = np.array(data.envs)
    envs[0, 2, 1, 1] = 1e5  # a sun in one texel of the first map
    envs[1] *= 1e-8  # a near-black second map
    train = dict(data.train)
    train["indirect"] = train["indirect"] * np.array([1e3, 1e-8, 1.0], np.float32)[:, None, None, None, None]
    train["direct"] = train["direct"] * np.array([1e3, 1e-8, 1.0], np.float32)[:, None, None, None, None]
    extreme = data._replace(train=train, envs=envs)
    # TINY's 12 steps: the training program of the tests above (compiled once)
    result = wp.fit(extreme, TINY, progress=False)
    assert np.all(np.isfinite(result.info["losses"])) and len(result.info["losses"]) == TINY["train"]["steps"]
    assert all(np.all(np.isfinite(np.asarray(leaf))) for leaf in jax.tree_util.tree_leaves(result.params))


@pytest.mark.slow  # resuming a finished sweep is also checked in the default suite (tests/test_sweep.py)
def test_a_killed_sweep_resumes_without_redoing_finished_points(tmp_path, monkeypatch):
    """A sweep killed after its first point: the rerun reads the finished points, runs the rest
    (the point that was running when killed has no summary and is run again), and its table
    equals an uninterrupted sweep's (timings aside)."""
    from jprt.methods import REGISTRY
    from tests.faults import worker as fault_worker

    points = lambda: glob.glob(str(tmp_path / "a" / "sweep_*" / "points" / "*" / "summary.json"))  # noqa: E731
    _kill_when(_start("sweep", tmp_path / "a", 3.0), lambda: len(points()) >= 1)
    finished = {p: open(p).read() for p in points()}
    assert 1 <= len(finished) < 4
    import fake_method

    monkeypatch.setitem(REGISTRY, "fake", fake_method.make_fake_method())  # removed again after the test
    resumed = fault_worker.sweep(str(tmp_path / "a"))
    assert resumed["counts"] == {"done": 4 - len(finished), "cached": len(finished), "failed": 0}
    assert all(open(p).read() == text for p, text in finished.items())  # read, not rewritten
    whole = fault_worker.sweep(str(tmp_path / "b"))
    keys = ("model.bias", "data.n", "status", "indirect_rmse", "psnr_indirect")  # (the hash holds the output dir)
    got = [{k: r.get(k) for k in keys} for r in resumed["rows"]]
    want = [{k: r.get(k) for k in keys} for r in whole["rows"]]
    assert [dict(g, status="done") for g in got] == want


def test_a_killed_lm_fit_resumes_bit_identically(tmp_path):
    """An RRF kd-tree fit by LM, killed after its first batch of node fits: the rerun reads the
    finished batches (none fitted twice), fits the rest, and its params equal an uninterrupted
    fit's bit for bit. The rerun and the uninterrupted fit run in this process (the batches it
    reads were fitted by the killed one: equal bits across processes too)."""
    from tests.faults import worker as fault_worker

    batches = lambda: glob.glob(str(tmp_path / "ckpt" / "rrf_*" / "nodes_*.npz"))  # noqa: E731
    _kill_when(_start("lm", tmp_path / "ckpt", tmp_path / "unused.npz"), lambda: len(batches()) >= 1)
    finished = len(batches())
    counts = fault_worker.lm(str(tmp_path / "ckpt"), str(tmp_path / "resumed.npz"))[1]["checkpoint"]
    assert counts["loaded"] == finished >= 1 and counts["fitted"] >= 1
    total = counts["loaded"] + counts["fitted"]
    fault_worker.lm(None, str(tmp_path / "whole.npz"))  # uninterrupted, in this process, no checkpoints
    assert len(batches()) == total
    a, b = _checkpoint(tmp_path / "resumed.npz")[0], _checkpoint(tmp_path / "whole.npz")[0]
    assert a.keys() == b.keys() and a
    for key in a:
        np.testing.assert_array_equal(a[key], b[key], err_msg=key)
