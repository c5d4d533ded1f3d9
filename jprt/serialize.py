"""Serialised evaluators: ``jax.export`` of a jitted function at fixed argument shapes.

An exported evaluator is a byte string that any JAX installation can load and run without jprt
or the Python code that built it (StableHLO plus calling convention), e.g. an RRF renderer for a
given image size and number of lights. ``jprt.export`` re-exports both functions; it also ships a
fitted model to engines (glTF lightmaps, ONNX), which needs the methods and sits above them.
"""

from __future__ import annotations

from typing import Callable

import jax
import numpy as np

__all__ = ["export_function", "load_function"]


def export_function(fn: Callable, *example_args, platforms: tuple[str, ...] | None = None) -> bytes:
    """Serialise ``fn`` (jitted or not) for arguments shaped like ``example_args`` (pytrees of
    arrays: a method's (inputs, lighting), e.g. ``jprt.inputs`` NamedTuples).

    ``platforms`` (e.g. ("cpu", "cuda")) lowers for several backends; default: the current one.
    """
    jitted = fn if hasattr(fn, "lower") else jax.jit(fn)
    shapes = jax.tree_util.tree_map(lambda a: jax.ShapeDtypeStruct(np.shape(a), jax.numpy.asarray(a).dtype),
                                    example_args)
    exported = jax.export.export(jitted, platforms=platforms)(*shapes)
    return bytes(exported.serialize())


def load_function(blob: bytes) -> Callable:
    """Deserialise bytes from ``export_function`` into a callable of the same arguments."""
    exported = jax.export.deserialize(bytearray(blob))
    return exported.call
