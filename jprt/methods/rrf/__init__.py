"""Radiance Regression Functions (Ren et al. 2013): ``model`` (the paper's math, pure JAX),
``data`` (training samples rendered with Mitsuba), ``kdtree`` (the error-driven partition)."""

from jprt.inputs import PointLights
from jprt.methods.base import Method
from jprt.methods.rrf import data, kdtree, model

__all__ = ["METHOD", "PRESETS", "data", "kdtree", "model"]

#: Named config overrides; ``test`` runs the whole contract in seconds.
PRESETS = {
    "test": {
        "data": {"n_lights": 3, "n_views": 3, "n_rays": 40, "spp": 8},
        "model": {"hidden": [6, 4]},
        "tree": {"max_depth": 1, "min_samples": 40, "max_leaves": 10},
        "train": {"max_iters": 3, "trial_iters": 1, "trial_samples": 64},
    },
}

METHOD = Method.of_package(
    "rrf",
    "Ren, Wang, Gong, Lin, Tong, Guo 2013, Global Illumination with Radiance Regression Functions",
    PointLights, model, data, PRESETS)
