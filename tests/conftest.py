"""Shared test set-up: an isolated dataset cache, Mitsuba configured once, asset paths."""

import atexit
import os
import shutil
import tempfile

# The suite's programs are tiny and each compiles once, so compiling (mostly LLVM's optimisation
# passes) is most of its time: the tests compile without them (tests/numerics: 65 -> 46 s). The
# operations are the same; last-bit rounding can differ from optimised code (no test compares bit
# patterns across flags). Benchmarks and users keep XLA's default. A level the caller sets wins.
if "xla_backend_optimization_level" not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " --xla_backend_optimization_level=0").strip()

import jax  # noqa: E402 (after XLA_FLAGS: XLA reads them when its backend starts)
import pytest  # noqa: E402

# Strict numerics (STYLE.md 9): implicit rank promotion is a bug waiting to happen in batched code.
jax.config.update("jax_numpy_rank_promotion", "raise")

# Trainers build a fresh jitted step per call (resume tests call them three times with identical
# shapes), and test files on different xdist workers compile the same evaluators: one persistent
# compilation cache per session compiles each program once. The process that loads this file
# first (pytest itself, before it starts its workers) makes the folder; the workers inherit its
# name through the environment.
_COMPILE_CACHE = os.environ.get("JPRT_TEST_COMPILE_CACHE")
if not _COMPILE_CACHE or not os.path.isdir(_COMPILE_CACHE):
    _COMPILE_CACHE = tempfile.mkdtemp(prefix="jprt_xla_cache_")
    os.environ["JPRT_TEST_COMPILE_CACHE"] = _COMPILE_CACHE
    atexit.register(shutil.rmtree, _COMPILE_CACHE, ignore_errors=True)
jax.config.update("jax_compilation_cache_dir", _COMPILE_CACHE)
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
ASSETS = os.path.abspath(os.path.join(ROOT, "..", "shared", "assets"))


@pytest.fixture(scope="session", autouse=True)
def _isolated_cache(tmp_path_factory):
    """Tests never read or write the user's ~/.cache/jprt."""
    old = os.environ.get("JPRT_CACHE")
    os.environ["JPRT_CACHE"] = str(tmp_path_factory.mktemp("jprt_cache"))
    yield
    if old is None:
        os.environ.pop("JPRT_CACHE", None)
    else:
        os.environ["JPRT_CACHE"] = old


@pytest.fixture(scope="session")
def mi():
    """Mitsuba with the jprt variant (fails, not skips, when libLLVM is missing: make test installs it)."""
    from jprt.render.setup import mitsuba

    return mitsuba()


@pytest.fixture(scope="session")
def assets():
    """Path of ../shared/assets; skips the test with the reason when the folder is absent."""
    if not os.path.isdir(ASSETS):
        pytest.skip(f"shared test assets not found at {ASSETS} (they live beside the project checkout)")
    return ASSETS
