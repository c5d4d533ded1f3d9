"""Modular Radiance Transfer (Loos et al. 2011): ``model`` (dictionary, interfaces, layout
operators, the run time; pure NumPy/JAX), ``operators`` (the canonical block's geometry) and
``data`` (held-out lightings of a block layout rendered with Mitsuba)."""

from jprt.inputs import PointRadiance
from jprt.methods.base import Method
from jprt.methods.mrt import data, model, operators

__all__ = ["METHOD", "PRESETS", "data", "model", "operators"]

#: Named config overrides; ``test`` runs the whole contract in seconds.
PRESETS = {
    "test": {
        "scene": {"name": "blocks", "layout": {"cells": [[0, 0], [1, 0], [1, 1]],
                                               "edges": [[[0, 0], [1, 0]], [[1, 0], [1, 1]]]}},
        "dictionary": {"texels": 4, "prior_grid": 3, "k_d": 24, "k_b": 12},
        "interfaces": {"spatial": 2, "directional": 4, "spatial_ss": 2, "directional_ss": 2, "k_rlf": 24,
                       "k_r": 12, "enrich_iterations": 1},
        "vector": {"directions": 6},
        "volume": {"grid": 1, "directions": 6},
        "data": {"n_test": 2, "test_spp": 16},
    },
}

METHOD = Method.of_package(
    "mrt", "Loos, Antani, Mitchell, Nowrouzezahrai, Jarosz, Sloan 2011, Modular Radiance Transfer",
    PointRadiance, model, data, PRESETS)
