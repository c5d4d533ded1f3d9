"""Stable hashes of configs, JSON-able descriptions and arrays: the keys of the dataset cache and
of run folders. A leaf module (NumPy and the standard library only), so every layer can hash.

The hash of a value is the SHA-256 of its canonical JSON (keys sorted, arrays replaced by a
digest of their dtype, shape and bytes), the same across processes, machines and dict orders.
"""

from __future__ import annotations

import hashlib
import json
from typing import Any, Mapping

import numpy as np

__all__ = ["stable_hash", "config_hash", "array_digest", "canonical"]


def canonical(obj: Any) -> Any:
    """``obj`` as canonical JSON-able data: mappings with string keys in sorted order, tuples as
    lists, NumPy scalars as Python numbers, arrays as ``{"__array__": array_digest(a)}``."""
    if isinstance(obj, Mapping):
        return {str(k): canonical(v) for k, v in sorted(obj.items(), key=lambda kv: str(kv[0]))}
    if isinstance(obj, (list, tuple)):
        return [canonical(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return {"__array__": array_digest(obj)}
    if isinstance(obj, np.generic):
        return obj.item()
    return obj


def stable_hash(obj: Any, length: int = 16) -> str:
    """SHA-256 of the canonical JSON of ``obj`` (sorted keys; arrays by content), hex prefix."""
    text = json.dumps(canonical(obj), sort_keys=True, separators=(",", ":"), allow_nan=True)
    return hashlib.sha256(text.encode()).hexdigest()[:length]


def config_hash(config: Mapping) -> str:
    """Stable 16-hex-digit hash of a resolved config."""
    return stable_hash(config)


def array_digest(array) -> str:
    """Content digest of an array: dtype, shape and bytes."""
    a = np.ascontiguousarray(array)
    h = hashlib.sha256()
    h.update(str(a.dtype).encode())
    h.update(str(a.shape).encode())
    h.update(a.tobytes())
    return h.hexdigest()[:16]
