"""Data-driven PRT (Belcour et al. 2022): ``model`` (measurement points, SVD basis, ridge
transfer, the lightmap function; pure NumPy/JAX) and ``data`` (examples rendered with Mitsuba)."""

from jprt.inputs import PointRadiance
from jprt.methods.base import Method
from jprt.methods.datadriven import data, model

__all__ = ["METHOD", "PRESETS", "data", "model"]

#: Named config overrides; ``test`` runs the whole contract in seconds.
PRESETS = {
    "test": {
        "lightmap": {"resolution": 32},
        "points": {"candidates": 512, "count": 16, "supersample": 2},
        "data": {"n_train": 12, "n_test": 3, "spp": 4, "test_spp": 8},
    },
}

METHOD = Method.of_package(
    "datadriven",
    "Belcour, Deliot, Barbier, Soler 2022, A Data-Driven Paradigm for Precomputed Radiance Transfer",
    PointRadiance, model, data, PRESETS)
