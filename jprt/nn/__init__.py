"""Learnable function families, each an (init, apply) pair of pure functions over plain pytrees.

``REGISTRY`` names every family with a small instance and example inputs, so generic contract
tests (jit, finite outputs and gradients, shapes and dtypes, no recompilation) cover all of them.
"""

from __future__ import annotations

from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp

from jprt.nn.cnn import CNN, sg_encoder
from jprt.nn.encoding import one_blob, roughness_remap, sh4, sh_encoding
from jprt.nn.factor import FactorField, factor_field
from jprt.nn.hashgrid import HashGrid, hashgrid
from jprt.nn.mlp import MLP, count_parameters, mlp, with_scaling

__all__ = ["MLP", "HashGrid", "FactorField", "CNN", "mlp", "hashgrid", "factor_field", "sg_encoder", "with_scaling",
           "count_parameters", "sh4", "sh_encoding", "one_blob", "roughness_remap", "RegistryEntry", "REGISTRY"]


class RegistryEntry(NamedTuple):
    """A small instance of a family and a function key -> example inputs (a tuple after params)."""

    family: Callable[[], NamedTuple]
    example_inputs: Callable[[jax.Array], tuple]


def _points(key, n=5):
    return (jax.random.uniform(key, (n, 3)),)


REGISTRY: dict[str, RegistryEntry] = {
    "mlp_rrf": RegistryEntry(lambda: mlp((12, 20, 10, 3), activation="tanh", init="rrf"),
                             lambda key: (jax.random.uniform(key, (7, 12), minval=-1, maxval=1),)),
    "mlp_relu": RegistryEntry(lambda: mlp((16, 128, 128, 3), activation="relu", init="he"),
                              lambda key: (jax.random.normal(key, (4, 16)),)),
    "mlp_linear_nobias": RegistryEntry(lambda: mlp((8, 8), activation="linear", use_bias=False, init="glorot"),
                                       lambda key: (jax.random.normal(key, (3, 8)),)),
    "hashgrid": RegistryEntry(lambda: hashgrid(n_levels=4, n_features=2, log2_table_size=8, base_resolution=4,
                                               per_level_scale=2.0), _points),
    "factor_field": RegistryEntry(lambda: factor_field(face_size=4, n_features=8, n_levels=4, features_per_level=2,
                                                       log2_table_size=8, base_resolution=4, per_level_scale=1.5),
                                  lambda key: (jax.random.uniform(key, (5, 3)), jnp.array([0, 7, 95], jnp.int32))),
    "sg_encoder": RegistryEntry(lambda: sg_encoder(image_size=16, n_lobes=2, params_per_lobe=7, channels=(4, 8)),
                                lambda key: (jax.random.uniform(key, (2, 16, 16, 3)),)),
}
