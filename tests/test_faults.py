"""Work killed with SIGKILL and restarted (issue 20): what was written before the kill stays
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

import numpy as np
import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _start(*args):
    return subprocess.Popen([sys.executable, "-m", "tests.fault_worker", *map(str, args)], cwd=ROOT,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


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
    done = subprocess.run([sys.executable, "-m", "tests.fault_worker", *map(str, args)], cwd=ROOT,
                          capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    return json.loads(done.stdout.strip().splitlines()[-1])


@pytest.mark.mitsuba
def test_a_killed_dataset_render_resumes_without_touching_finished_entries(tmp_path, mi):
    from tests import fault_worker

    cache = tmp_path / "cache"
    items = lambda: sorted(glob.glob(str(cache / "datasets" / "*" / "item_*.npz.sha256")))  # noqa: E731
    _kill_when(_start("render", cache, 0.4), lambda: len(items()) >= 3)
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


def test_a_killed_adam_training_resumes_bit_identically(tmp_path):
    from tests import fault_worker

    ckpt = tmp_path / "train.npz"
    _kill_when(_start("train", ckpt, tmp_path / "unused.npz"), ckpt.exists)
    step_at_kill = _checkpoint(ckpt)[1]["step"]
    assert 0 < step_at_kill < fault_worker.TRAIN["steps"]
    info = _run("train", ckpt, tmp_path / "resumed.npz")
    # no step before the last checkpoint is repeated: the run starts where the checkpoint ends
    assert info["resumed_from"] == step_at_kill and info["step"] == fault_worker.TRAIN["steps"]
    assert info["losses"] == fault_worker.TRAIN["steps"] - step_at_kill
    whole = _run("train", tmp_path / "whole.npz", tmp_path / "whole_out.npz")
    assert whole["resumed_from"] == 0
    a, b = _checkpoint(tmp_path / "resumed.npz")[0], _checkpoint(tmp_path / "whole_out.npz")[0]
    assert a.keys() == b.keys() and a
    for key in a:
        np.testing.assert_array_equal(a[key], b[key], err_msg=key)
