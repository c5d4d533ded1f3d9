"""The jprt command: info, run, render, and one-line errors."""

import json
import os
import subprocess
import sys

import pytest

from jprt.cli import main

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def test_info_prints_variant_and_llvm():
    proc = subprocess.run([sys.executable, "-m", "jprt.cli", "info"], capture_output=True, text=True, cwd=ROOT,
                          timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert "mitsuba variant: llvm_ad_rgb" in proc.stdout
    line = next(li for li in proc.stdout.splitlines() if li.startswith("llvm library:"))
    path = line.split(":", 1)[1].strip().split(" ")[0]
    assert os.path.exists(path) and "libLLVM" in path
    assert "jax devices:" in proc.stdout


def test_run_and_render_demo_experiment(tmp_path, capsys, mi):
    out = tmp_path / "results"
    args = ["experiments/cornell_gt.py", "--preset", "test", "--set", f"output.dir={out}"]
    cwd = os.getcwd()
    os.chdir(ROOT)
    try:
        assert main(["run", *args]) == 0
        assert main(["render", *args]) == 0
    finally:
        os.chdir(cwd)
    printed = capsys.readouterr().out
    assert "rendered 0 entries, reused 8" in printed  # the run's dataset is reused by render
    (folder,) = list(out.iterdir())
    summary = json.load(open(folder / "summary.json"))
    assert summary["n_items"] == 4 and summary["resolution"] == [24, 24]
    assert all(item["indirect_min"] >= -1e-4 for item in summary["items"])
    for name in ("light00_view00_indirect.exr", "light01_view01_full.png", "contact_sheet.png",
                 "gbuffer_view00_attributes.exr", "config.json"):
        assert (folder / name).exists(), name


@pytest.mark.parametrize("argv, message", [
    (["run", "experiments/cornell_gt.py", "--set", "dataset.spp=-1"], "spp must be a positive integer"),
    (["run", "experiments/cornell_gt.py", "--set", "dataset.cameras.widht=3"], "did you mean 'dataset.cameras.width'"),
    (["run", "experiments/cornell_gt.py", "--set", 'dataset.scene={"name": "xml", "path": "/no/such.xml"}'],
     "scene file not found: /no/such.xml"),
    (["run", "experiments/nope.py"], "experiment file not found"),
    (["run", "experiments/cornell_gt.py", "--preset", "huge"], "unknown preset 'huge'"),
])
def test_bad_input_is_one_line(argv, message, tmp_path):
    env = dict(os.environ, JPRT_CACHE=str(tmp_path / "cache"))
    proc = subprocess.run([sys.executable, "-m", "jprt.cli", *argv], capture_output=True, text=True, cwd=ROOT,
                          env=env, timeout=120)
    assert proc.returncode == 2
    lines = [li for li in proc.stderr.splitlines() if li.strip()]
    assert len(lines) == 1 and lines[0].startswith("jprt: error:") and message in lines[0], proc.stderr
    assert not (tmp_path / "cache").exists()
