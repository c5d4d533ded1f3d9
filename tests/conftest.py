"""Shared test set-up: an isolated dataset cache, Mitsuba configured once, asset paths."""

import atexit
import fcntl
import os
import pickle
import shutil
import tempfile
import warnings

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
def _session_folder(variable: str, prefix: str) -> str:
    """A temporary folder for the whole test session: made by the first process that loads this
    file (pytest itself, before it starts its xdist workers), removed when that process exits;
    the workers inherit its name through ``variable`` in the environment."""
    folder = os.environ.get(variable)
    if not folder or not os.path.isdir(folder):
        folder = tempfile.mkdtemp(prefix=prefix)
        os.environ[variable] = folder
        atexit.register(shutil.rmtree, folder, ignore_errors=True)
    return folder


_COMPILE_CACHE = _session_folder("JPRT_TEST_COMPILE_CACHE", "jprt_xla_cache_")
#: Fits of the methods' test presets, shared by the workers (``fitted_preset``).
_SHARED_FITS = _session_folder("JPRT_TEST_SHARED_FITS", "jprt_test_fits_")
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
def fitted_preset():
    """``get(name) -> (method, config, dataset, FitResult)`` on the method's ``test`` preset. The
    dataset and the fit are made once for the whole session: the first worker to ask renders the
    dataset, fits it and pickles both into a folder the workers share (under a file lock), the
    others load them (test_contract, test_self_check, test_export and test_design use the same
    presets, often on different workers). Its fit warnings (a test preset's systems are
    ill-conditioned) are not shown."""
    from jprt.hashing import config_hash
    from jprt.methods import REGISTRY

    done = {}

    def get(name):
        if name not in done:
            m = REGISTRY[name]
            config = m.resolve(m.presets["test"])
            path = os.path.join(_SHARED_FITS, f"{name}_{config_hash(config)}.pkl")
            with open(path + ".lock", "w") as lock:
                fcntl.flock(lock, fcntl.LOCK_EX)
                if os.path.exists(path):
                    with open(path, "rb") as f:
                        dataset, result = pickle.load(f)
                else:
                    dataset = m.make_dataset(config["scene"], config, progress=False)
                    with warnings.catch_warnings():
                        warnings.simplefilter("ignore")
                        result = m.fit(dataset, config)
                    with open(path + ".tmp", "wb") as f:
                        pickle.dump((dataset, result), f)
                    os.replace(path + ".tmp", path)
            done[name] = (m, config, dataset, result)
        return done[name]

    return get


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


#: The test files that take longest (pytest --durations=0 on the 2-core VM: 75-105 s of worker
#: time each, a tenth of the suite's total or less), handed to the xdist workers first: with
#: --dist loadfile a long file started last is the suite's tail, and longest-first is the usual
#: cure for that (the order of tests inside a file is kept).
LONGEST_FILES = ("methods/test_wavelet_prt.py", "numerics/test_numerics.py", "methods/test_contract.py",
                 "methods/test_rrf.py", "sphere/test_sg.py", "faults/test_kill_and_resume.py", "test_export.py")


def pytest_collection_modifyitems(config, items):
    here = os.path.dirname(os.path.abspath(__file__))
    rank = {os.path.join(here, name): i for i, name in enumerate(LONGEST_FILES)}
    items.sort(key=lambda item: rank.get(os.path.abspath(str(item.path)), len(rank)))


@pytest.fixture(scope="module")
def small_machine_measurements():
    """Every run's roofline measures the machine (``jeval.matmul_peak_gflops``: 1024 x 1024
    matmuls; ``jeval.stream_bandwidth_gbs``: 256 MiB arrays). A module whose tests run whole
    experiments but never read those numbers asks for this fixture: the same measurements at
    test_eval's sizes (test_eval checks them)."""
    import functools

    from jprt import eval as jeval

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(jeval, "matmul_peak_gflops", functools.partial(jeval.matmul_peak_gflops, n=64, repeats=2))
        mp.setattr(jeval, "stream_bandwidth_gbs",
                   functools.partial(jeval.stream_bandwidth_gbs, n_bytes=1 << 20, repeats=2))
        mp.setattr(jeval, "SIZED_STREAM_REPEATS", 2)  # the triad at each frame's size (stream_at_size)
        yield
