"""Mitsuba / libLLVM set-up: the missing-LLVM error path, version parsing, variant selection."""

import os
import subprocess
import sys

import pytest

from jprt.render import setup

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def _env(**extra):
    env = {k: v for k, v in os.environ.items() if k not in ("DRJIT_LIBLLVM_PATH", "JPRT_MITSUBA_VARIANT")}
    env.update(extra)
    return env


@pytest.mark.parametrize(
    "name, major",
    [("/usr/lib/x86_64-linux-gnu/libLLVM-19.so", 19), ("/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1", 19),
     ("/usr/lib/x86_64-linux-gnu/libLLVM-15.so.1", 15), ("/usr/lib/llvm-17/lib/libLLVM.so", 17),
     ("/usr/lib/libfoo.so", None)],
)
def test_llvm_major(name, major):
    assert setup.llvm_major(name) == major


def test_find_libllvm_prefers_newest_good_version(tmp_path, monkeypatch):
    for name in ("libLLVM-14.so", "libLLVM-15.so.1", "libLLVM-17.so", "libLLVM.so.20.1", "libLLVM-20.so"):
        (tmp_path / name).write_bytes(b"")
    monkeypatch.setenv("JPRT_LLVM_SEARCH_DIRS", str(tmp_path))
    monkeypatch.delenv("DRJIT_LIBLLVM_PATH", raising=False)
    assert setup.find_libllvm() == str(tmp_path / "libLLVM-20.so")
    for name in ("libLLVM.so.20.1", "libLLVM-20.so", "libLLVM-17.so"):
        (tmp_path / name).unlink()
    assert setup.find_libllvm() is None  # only 14 and 15 remain: both crash Dr.Jit


def test_missing_llvm_fails_with_install_command(tmp_path):
    """No libLLVM >= 16: one line on stderr naming the exact install command, never a fallback."""
    code = "from jprt.render.setup import mitsuba; mitsuba()"
    proc = subprocess.run([sys.executable, "-c", code], env=_env(JPRT_LLVM_SEARCH_DIRS=str(tmp_path)),
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode != 0
    assert setup.INSTALL_COMMAND in proc.stderr
    assert "LLVMNotFoundError" in proc.stderr

    # Through the CLI: exactly one line, exit status 2, nothing rendered.
    proc = subprocess.run([sys.executable, "-m", "jprt.cli", "render", "experiments/cornell_gt.py", "--preset", "test"],
                          env=_env(JPRT_LLVM_SEARCH_DIRS=str(tmp_path), JPRT_CACHE=str(tmp_path / "cache")),
                          capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert proc.returncode == 2, proc.stderr
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("jprt: error:") and setup.INSTALL_COMMAND in lines[0]
    assert not (tmp_path / "cache").exists()


def test_variant_override_and_unknown_variant():
    code = "from jprt.render.setup import mitsuba; print(mitsuba().variant())"
    proc = subprocess.run([sys.executable, "-c", code], env=_env(JPRT_MITSUBA_VARIANT="scalar_rgb"),
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == "scalar_rgb"
    proc = subprocess.run([sys.executable, "-c", code], env=_env(JPRT_MITSUBA_VARIANT="llvm_nonsense"),
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode != 0 and "unknown Mitsuba variant 'llvm_nonsense'" in proc.stderr


def test_default_variant_uses_llvm(mi):
    assert mi.variant() == setup.DEFAULT_VARIANT or os.environ.get("JPRT_MITSUBA_VARIANT")
    assert setup.llvm_major(os.environ["DRJIT_LIBLLVM_PATH"]) >= setup.MIN_LLVM_MAJOR
