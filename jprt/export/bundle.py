"""The export folder's manifest and its exact parameter buffers, and loading an export back.

Every export holds ``export.json`` (the manifest: ``MANIFEST_KEYS``) and the fitted parameters as
raw little-endian binary buffers under ``params/`` (one file per array of the run's
``model.npz``, each described in the manifest's ``params`` list by its tree keys, dtype and
shape), so the export alone rebuilds the evaluator bit for bit (``load``); the engine files
(glTF, EXR, PNG, ONNX) are views of the same numbers in the formats engines read.
"""

from __future__ import annotations

import json
import os
import re
from typing import Any, Callable, NamedTuple

import numpy as np

from jprt import io
from jprt.cache import sha256
from jprt.checkpoint import as_lists, place

__all__ = ["MANIFEST", "FORMAT", "FORMAT_VERSION", "MANIFEST_KEYS", "NotAnExport", "Exported", "write_params",
           "read_params", "read_manifest", "write_manifest", "load", "file_sha256"]

#: The manifest's file name in an export folder.
MANIFEST = "export.json"

#: ``format`` and ``format_version`` of every manifest (a reader refuses other versions).
FORMAT = "jprt-export"
FORMAT_VERSION = 1

#: Every key of the manifest, with its meaning.
MANIFEST_KEYS: dict[str, str] = {
    "format": f"always {FORMAT!r}",
    "format_version": "the layout of this folder (an integer; a reader refuses versions it does not know)",
    "method": "the method's registry name (jprt.methods.REGISTRY)",
    "paper": "the citation the method follows",
    "lighting_type": "the jprt.inputs type the evaluator takes (PointLights, CubeMap, PointRadiance, ...)",
    "lighting": "the lighting's fields: {name: {shape, dtype, meaning}} (shapes with -1 for a free size)",
    "predicts": "'indirect' (every method but one) or 'direct' (SG environment visibility)",
    "units": "what the numbers mean physically (radiance, irradiance, positions, light intensities)",
    "jprt_version": "the jprt version that wrote the export",
    "config_hash": "the run's config hash (jprt.hashing.config_hash of its resolved config)",
    "config": "the method's resolved config (what jprt.export.load rebuilds the evaluator with)",
    "source": "the run folder the export was made from",
    "files": "{relative path: {holds, format, ...}} for every file of the export but this one",
    "params": "[{keys, file, dtype, shape}]: every array of the fitted params as a raw little-endian buffer",
    "lightmap": "lightmap methods: atlas resolution, quantity, lighting baked in, RGBM range (else absent)",
    "camera": "the run's default view (origin, target, up, fov in degrees along the smaller image axis), where "
              "it has one",
    "onnx": "neural evaluators: the ONNX model's inputs and outputs and the operations written by hand",
    "glsl": "RRF: its GLSL (source and data files, the data texture's width and height, the most lights one "
            "call sums, x's columns by attribute)",
}


class NotAnExport(ValueError):
    """A folder given to ``jprt.export.load`` that is not an export (no or unreadable manifest)."""


#: Hex SHA-256 of a file's bytes (the dataset cache's checksum).
file_sha256 = sha256


def _leaf_name(keys: list) -> str:
    """A file name for a leaf from its tree keys: ['leaves', 'layers', 0, 'w'] -> leaves.layers.0.w."""
    name = ".".join(str(k) for k in keys) or "value"
    return re.sub(r"[^A-Za-z0-9_.-]", "_", name)


def _keys(path) -> list:
    """Tree keys of a ``jax.tree_util`` key path as plain JSON values (str or int)."""
    import jax

    out = []
    for k in path:
        if isinstance(k, jax.tree_util.DictKey):
            out.append(k.key if isinstance(k.key, (str, int)) else str(k.key))
        elif isinstance(k, jax.tree_util.SequenceKey):
            out.append(int(k.idx))
        elif isinstance(k, jax.tree_util.GetAttrKey):
            out.append(k.name)
        else:
            raise TypeError(f"params tree key {k!r} is not a dict key, index or attribute")
    return out


def write_params(out: str, params) -> list[dict]:
    """Write every array of ``params`` to ``out/params/<keys>.bin`` (raw, little-endian, C order);
    returns the manifest's ``params`` entries [{keys, file, dtype, shape}] in tree order."""
    import jax

    entries = []
    for path, leaf in jax.tree_util.tree_leaves_with_path(params):
        a = np.asarray(leaf)
        if a.dtype.kind not in "biuf":
            raise TypeError(f"params leaf {jax.tree_util.keystr(path)} has dtype {a.dtype}: an export stores "
                            "booleans, integers and floats")
        a = np.ascontiguousarray(a.astype(a.dtype.newbyteorder("<")))
        keys = _keys(path)
        rel = f"params/{_leaf_name(keys)}.bin"
        io.atomic_write_bytes(os.path.join(out, rel), a.tobytes())
        entries.append({"keys": keys, "file": rel, "dtype": a.dtype.name, "shape": list(a.shape)})
    return entries


def read_params(folder: str, entries: list[dict]):
    """The params tree written by ``write_params`` (dicts for string keys, lists for indices),
    each buffer checked against its declared size."""
    root: dict = {}
    for e in entries:
        path = os.path.join(folder, e["file"])
        if not os.path.isfile(path):
            raise NotAnExport(f"{folder}: the manifest lists {e['file']}, which is missing")
        dtype = np.dtype(e["dtype"]).newbyteorder("<")
        data = np.fromfile(path, dtype=dtype)
        shape = tuple(int(s) for s in e["shape"])
        if data.size != int(np.prod(shape, dtype=np.int64)):
            raise NotAnExport(f"{path} holds {data.size} values of {e['dtype']}, the manifest says shape {list(shape)}")
        value = data.reshape(shape).astype(dtype.newbyteorder("="))
        keys = e["keys"]
        if not keys:
            return value
        place(root, keys, value)
    return as_lists(root)


def write_manifest(out: str, manifest: dict) -> str:
    """Write ``manifest`` as ``out/export.json`` after checking it has exactly the known keys
    (``MANIFEST_KEYS``, the optional ones where they apply); returns the path."""
    unknown = sorted(set(manifest) - set(MANIFEST_KEYS))
    if unknown:
        raise KeyError(f"manifest keys {unknown} are not in MANIFEST_KEYS")
    required = set(MANIFEST_KEYS) - {"lightmap", "camera", "onnx", "glsl"}
    missing = sorted(required - set(manifest))
    if missing:
        raise KeyError(f"manifest lacks {missing}")
    path = os.path.join(out, MANIFEST)
    io.write_json(path, manifest)
    return path


def read_manifest(folder: str) -> dict:
    """The manifest of an export folder; ``NotAnExport`` in one line when there is none or it is
    not one this jprt reads."""
    path = os.path.join(folder, MANIFEST)
    if not os.path.isfile(path):
        raise NotAnExport(f"{folder} is not a jprt export (no {MANIFEST}; `jprt export RUN_FOLDER --out DIR` "
                          "writes it)")
    try:
        with open(path) as f:
            manifest = json.load(f)
    except ValueError as e:
        raise NotAnExport(f"{path} is not JSON: {e}") from None
    if manifest.get("format") != FORMAT or manifest.get("format_version") != FORMAT_VERSION:
        raise NotAnExport(f"{path}: format {manifest.get('format')!r} version {manifest.get('format_version')!r}, "
                          f"this jprt reads {FORMAT!r} version {FORMAT_VERSION}")
    return manifest


class Exported(NamedTuple):
    """A model loaded back from an export folder (``load``).

    Fields:
      folder: the export folder.  manifest: its ``export.json``.
      method: the ``jprt.methods.Method``.  config: the method's resolved config.
      params: the fitted params, rebuilt from the binary buffers.
      evaluate: the method's evaluator of those params, ``(inputs, lighting) -> (H, W, 3)``.
    """

    folder: str
    manifest: dict
    method: Any
    config: dict
    params: Any
    evaluate: Callable


def load(folder: str) -> Exported:
    """Load an export folder back into Python: the method's evaluator of the params stored in
    ``params/`` under the config stored in the manifest, equal to the run's own evaluator (the
    buffers are the params' exact bytes). Raises ``NotAnExport`` for a folder that is not one."""
    from jprt.methods import REGISTRY

    manifest = read_manifest(folder)
    name = manifest.get("method")
    if name not in REGISTRY:
        raise NotAnExport(f"{folder}: the manifest names method {name!r}, not one of {sorted(REGISTRY)}")
    method = REGISTRY[name]
    config = method.resolve(manifest["config"])
    params = read_params(folder, manifest["params"])
    return Exported(os.path.abspath(folder), manifest, method, config, params, method.evaluator(params, config))
