"""Pytree checkpoints (``save_checkpoint``, ``load_checkpoint``, ``load_tree``) and the atomic
writes every jprt file goes through (``atomic_path``).

Atomic means: data goes to a temporary file in the destination folder, is flushed and fsync-ed,
and is renamed over the destination (``os.replace``), so a reader sees the old file or the new
one, never half of one, and an interrupted write leaves at most a ``*.tmp`` file behind.

A leaf module (NumPy, JAX and the standard library), so a solver's resumable loop
(``jprt.solve.adam``) saves its state without the file formats of ``jprt.io``, which re-exports
everything here.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import re
import tempfile
from typing import Any, Iterator

import numpy as np

__all__ = ["atomic_path", "save_checkpoint", "load_checkpoint", "load_tree", "place", "as_lists", "CorruptCheckpoint"]


@contextlib.contextmanager
def atomic_path(path: str, suffix: str = "") -> Iterator[str]:
    """Yield a temporary path beside ``path``; on success it is renamed to ``path``.

    On any exception (KeyboardInterrupt included) the temporary file is removed and ``path`` is
    left untouched.
    """
    folder = os.path.dirname(os.path.abspath(path))
    os.makedirs(folder, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix="." + os.path.basename(path) + ".", suffix=suffix + ".tmp", dir=folder)
    os.close(fd)
    try:
        yield tmp
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException as e:
        with contextlib.suppress(FileNotFoundError):
            os.remove(tmp)
        if isinstance(e, OSError) and e.errno in (errno.ENOSPC, errno.EFBIG, errno.EDQUOT):
            raise OSError(e.errno, f"cannot write {path}: {e.strerror} (disk full or a file-size limit); the "
                                   f"partial file was removed, so no later run reads it") from e
        raise


def save_checkpoint(path: str, tree: Any, *, step: int | None = None, meta: dict | None = None) -> None:
    """Save a pytree of arrays atomically (an .npz keyed by tree paths, plus JSON metadata).

    Leaves are stored bit-exactly (dtype kept), so a resumed run is bit-identical.
    """
    import jax

    leaves_with_path, _ = jax.tree_util.tree_flatten_with_path(tree)
    arrays = {}
    for k, (key_path, leaf) in enumerate(leaves_with_path):
        arrays[f"{k:05d}|{jax.tree_util.keystr(key_path)}"] = np.asarray(leaf)
    header = {"step": step, "meta": meta or {}, "n_leaves": len(arrays)}
    arrays["__jprt_checkpoint__"] = np.frombuffer(json.dumps(header).encode(), dtype=np.uint8)
    with atomic_path(path, suffix=".npz") as tmp:
        with open(tmp, "wb") as f:
            np.savez(f, **arrays)


def _read_checkpoint(path: str) -> tuple[dict, dict]:
    """(arrays by stored key, header) of a ``save_checkpoint`` file, or ``CorruptCheckpoint``."""
    try:
        with np.load(path, allow_pickle=False) as data:
            stored = {k: data[k] for k in data.files}
        header = json.loads(bytes(stored.pop("__jprt_checkpoint__")).decode())
    except Exception as e:  # truncated, bit-flipped (the zip's CRC-32), or not a checkpoint at all
        raise CorruptCheckpoint(f"cannot read checkpoint {path}: {e}") from None
    return stored, header


_KEY = re.compile(r"\['((?:[^'\\]|\\.)*)'\]|\[(\d+)\]|\.(\w+)")


def load_tree(path: str) -> tuple[Any, int | None, dict]:
    """(tree, step, meta) of a ``save_checkpoint`` file, the tree rebuilt from its stored tree
    paths (dicts for string keys and attributes, lists for indices), without the model that made
    it. Raises ``CorruptCheckpoint`` when the file cannot be read."""
    stored, header = _read_checkpoint(path)
    root: dict = {}
    for key in sorted(stored):
        path_str = key.split("|", 1)[1]
        parts = [m.group(1) if m.group(1) is not None else int(m.group(2)) if m.group(2) is not None else m.group(3)
                 for m in _KEY.finditer(path_str)]
        if not parts:
            return stored[key], header["step"], header["meta"]  # a single array
        place(root, parts, stored[key])
    return as_lists(root), header["step"], header["meta"]


def place(root: dict, keys, value) -> None:
    """Put ``value`` into the nested dict ``root`` at the path ``keys`` (str or int each)."""
    node = root
    for k in keys[:-1]:
        node = node.setdefault(k, {})
    node[keys[-1]] = value


def as_lists(node):
    """A nested dict built by ``place`` with the dicts whose keys are 0..n-1 turned into lists."""
    if not isinstance(node, dict):
        return node
    out = {k: as_lists(v) for k, v in node.items()}
    if out and all(isinstance(k, int) for k in out):
        return [out[i] for i in range(len(out))]
    return out


class CorruptCheckpoint(ValueError):
    """A checkpoint file that cannot be read (truncated, bit-flipped, not a checkpoint)."""


def load_checkpoint(path: str, like: Any) -> tuple[Any, int | None, dict]:
    """Load a checkpoint written by ``save_checkpoint`` into the structure of ``like``.

    Returns (tree, step, meta). Raises ``CorruptCheckpoint`` (a ValueError) when the file cannot
    be read, ValueError when the stored tree paths, shapes or dtypes differ from ``like``'s (a
    checkpoint from a different model or config).
    """
    import jax

    if not os.path.isfile(path):
        raise FileNotFoundError(f"checkpoint not found: {path}")
    stored, header = _read_checkpoint(path)
    leaves_with_path, treedef = jax.tree_util.tree_flatten_with_path(like)
    keys = sorted(stored)
    if len(keys) != len(leaves_with_path):
        raise ValueError(f"checkpoint {path} has {len(keys)} leaves, the model has {len(leaves_with_path)}")
    leaves = []
    for key, (key_path, leaf) in zip(keys, leaves_with_path):
        want = jax.tree_util.keystr(key_path)
        if key.split("|", 1)[1] != want:
            raise ValueError(f"checkpoint {path}: leaf {key.split('|', 1)[1]!r} where the model has {want!r}")
        value = stored[key]
        ref = np.asarray(leaf)
        if value.shape != ref.shape or value.dtype != ref.dtype:
            raise ValueError(f"checkpoint {path}: {want} is {value.dtype}{value.shape}, model has {ref.dtype}{ref.shape}")
        leaves.append(value)
    return jax.tree_util.tree_unflatten(treedef, leaves), header["step"], header["meta"]
