"""The one cache: content-addressed, atomic, checksummed ``.npz`` entries (DESIGN.md, "Datasets").

Every dataset a method renders and every baked artefact goes through here, so that

* an entry's name is the stable hash of everything it depends on (scene description, render
  settings, seeds): ``$JPRT_CACHE/<namespace>/<hash>.npz`` (``JPRT_CACHE`` defaults to
  ``~/.cache/jprt``);
* writes go to a temporary name and are renamed, and a ``<entry>.sha256`` file is written after
  the entry itself, so an entry counts as present only when its checksum exists and matches;
* a truncated or corrupt entry is reported and rebuilt, never silently used.

    arrays, path = cache.cached("rrf", spec, lambda: render_samples(...))

Only NumPy arrays are stored (``allow_pickle=False``); callers keep their own small metadata in
the arrays (0-d string arrays) or recompute it from the spec.
"""

from __future__ import annotations

import hashlib
import os
import sys
import warnings
from typing import Callable, Mapping

import numpy as np

from jprt.hashing import stable_hash
from jprt.io import atomic_path, atomic_write_bytes

__all__ = ["cache_root", "sha256", "save_npz", "load_npz", "entry_state", "entry_path", "cached", "unprefixed"]


def cache_root() -> str:
    """``$JPRT_CACHE`` or ``~/.cache/jprt``, absolute."""
    return os.path.abspath(os.path.expanduser(os.environ.get("JPRT_CACHE", "~/.cache/jprt")))


def sha256(path: str) -> str:
    """Hex SHA-256 of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def save_npz(path: str, arrays: Mapping[str, np.ndarray]) -> None:
    """Write ``arrays`` to ``path`` atomically, then its checksum file."""
    with atomic_path(path, suffix=".npz") as tmp:
        with open(tmp, "wb") as f:
            np.savez(f, **arrays)
    atomic_write_bytes(path + ".sha256", sha256(path).encode())


def entry_state(path: str) -> str:
    """'ok' (checksum present and matching), 'missing' (no checksum yet) or 'corrupt'."""
    if not os.path.exists(path + ".sha256"):
        return "missing"
    if not os.path.exists(path):
        return "corrupt"
    with open(path + ".sha256") as f:
        return "ok" if f.read().strip() == sha256(path) else "corrupt"


def load_npz(path: str, *, repair: str = "") -> dict[str, np.ndarray]:
    """The arrays of a verified entry; a missing or corrupt one raises ValueError (with the
    caller's ``repair`` advice appended)."""
    state = entry_state(path)
    if state != "ok":
        raise ValueError(f"cache entry {path} is {state}" + (f"; {repair}" if repair else ""))
    with np.load(path, allow_pickle=False) as f:
        return {k: f[k] for k in f.files}


def unprefixed(arrays: Mapping[str, np.ndarray], prefix: str, *, exclude: str | None = None) -> dict:
    """The entries of ``arrays`` whose names start with ``prefix`` (and not ``exclude``), prefix
    removed, 0-d arrays as Python scalars: a dict stored flat in one entry (``atlas_texel_index``
    ...) read back as a dict."""
    return {k[len(prefix):]: (v.item() if v.ndim == 0 else v) for k, v in arrays.items()
            if k.startswith(prefix) and not (exclude and k.startswith(exclude))}


def entry_path(namespace: str, spec, *, cache_dir: str | None = None) -> str:
    """Where the entry of ``spec`` (any JSON-able description) lives."""
    return os.path.join(cache_dir or cache_root(), namespace, stable_hash(spec) + ".npz")


def cached(namespace: str, spec, build: Callable[[], Mapping[str, np.ndarray]], *,
           cache_dir: str | None = None) -> tuple[dict[str, np.ndarray], str]:
    """The arrays of ``spec``'s entry, built by ``build()`` and stored when absent or corrupt.

    Returns ``(arrays, path)``. The arrays returned after a build are the ones read back from
    disk, so a first run and a cached run see identical values (dtypes included).
    """
    path = entry_path(namespace, spec, cache_dir=cache_dir)
    state = entry_state(path)
    if state == "ok":
        return load_npz(path), path
    if state == "corrupt":
        warnings.warn(f"cache entry {path} is corrupt (checksum mismatch or missing file); rebuilding it",
                      RuntimeWarning, stacklevel=2)
        print(f"jprt.cache: rebuilding corrupt entry {path}", file=sys.stderr)
    os.makedirs(os.path.dirname(path), exist_ok=True)
    save_npz(path, build())
    return load_npz(path), path
