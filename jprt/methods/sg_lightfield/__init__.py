"""Spherical-Gaussian light-field textures (Currius et al. 2020): ``model`` (lobes, constraints,
the log-L2 loss, the CNN encoder's training, the run-time shading; pure JAX), ``data`` (the
receivers' light-field texture, captured by ``jprt.render.lightfield``, and the environment
setting's inputs), ``environment`` (§5: the illumination-weighted environment visibility W_E and
the pre-convolved environment U, Eq. 6-8) and ``baselines`` (the per-texel fits the paper compares
with). ``experiments/sg_lightfield.py`` runs all of it; ``benchmarks/sg_lightfield.py`` reports it."""


from jprt.inputs import LightScale
from jprt.methods.base import Method
from jprt.methods.sg_lightfield import baselines, data, environment, model

__all__ = ["METHOD", "PRESETS", "baselines", "data", "environment", "model"]

#: Named config overrides; ``test`` captures, fits and shades the floor's 16^2 atlas in seconds
#: (one direction per lobe in ``shade_sampled``: the default's code at a third of its compile time).
PRESETS = {
    "test": {
        "objects": ["floor"],
        "lightmap": {"resolution": 16},
        "capture": {"size": 8, "spp": 2, "block": 256},
        "model": {"n_lobes": 2, "channels": [4, 8]},
        "train": {"steps": 20, "batch": 16},
        "shading": {"samples": 1},
    },
}


METHOD = Method.of_package(
    "sg_lightfield",
    "Currius, Dolonius, Assarsson, Sintorn 2020, Spherical Gaussian Light-field Textures for Fast Precomputed "
    "Global Illumination",
    LightScale, model, data, PRESETS)
