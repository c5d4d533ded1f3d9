"""SG environment visibility (Currius et al. 2020 §5): glossy reflections of a distant environment
map with visibility, relit by any map. ``model`` (the lobes of the illumination-weighted
environment visibility W_E, the pre-convolved environment U and Eq. 8's shading; pure JAX) and
``data`` (the receivers' captured visibility and W_E, through
``jprt.methods.sg_lightfield.data.make_environment_dataset``). The light-field half of the paper
(§3-4, baked for the scene's own emitters) is ``jprt.methods.sg_lightfield``."""


from jprt.inputs import PreconvolvedEnvironment
from jprt.methods.base import Method
from jprt.methods.sg_environment import data, model

__all__ = ["METHOD", "PRESETS", "data", "model"]

#: Named config overrides; ``test`` captures the floor's 16^2 atlas under a synthetic sky and fits
#: two lobes per texel in seconds.
PRESETS = {
    "test": {
        "objects": ["floor"],
        "lightmap": {"resolution": 16},
        "environment": {"map": "synthetic", "visibility_size": 16, "samples": 1, "size": 8, "u_size": 16,
                        "u_env_size": 32, "alphas": [0.1, 0.3, 0.6]},
        "model": {"n_lobes": 2, "channels": [4, 8]},
        "train": {"steps": 20, "batch": 16},
    },
}

METHOD = Method.of_package(
    "sg_environment",
    "Currius, Dolonius, Assarsson, Sintorn 2020, Spherical Gaussian Light-field Textures for Fast Precomputed "
    "Global Illumination (§5, illumination-weighted environment visibility)",
    PreconvolvedEnvironment, model, data, PRESETS)
