"""Shipping a fitted model out of JAX.

* ``export_function`` / ``load_function``: ``jax.export`` of an evaluator at fixed shapes
  (StableHLO bytes any JAX loads; ``jprt.serialize``, re-exported here).
* ``export_run(RUN_FOLDER, OUT)`` (``jprt export``): the model in the formats engines and browsers
  read: glTF lightmaps and the relightable parts for the lightmap methods, ONNX for the neural
  evaluators, GLSL for RRF (``jprt.export.glsl``), with a manifest (``jprt.export.engine``).
* ``load(OUT)``: an export folder back in Python, its evaluator rebuilt from the exported buffers
  (``jprt.export.bundle``).

This package sits with the runner and the viewer (it loads run folders as the viewer does);
``jprt.serialize`` sits in the foundations, so anything may serialise an evaluator.
"""

from jprt.export.bundle import MANIFEST, Exported, NotAnExport, load, read_manifest
from jprt.export.engine import LIGHTMAP_METHODS, ONNX_METHODS, export_run
from jprt.serialize import export_function, load_function

__all__ = ["export_function", "load_function", "export_run", "load", "read_manifest", "Exported", "NotAnExport",
           "MANIFEST", "LIGHTMAP_METHODS", "ONNX_METHODS"]
