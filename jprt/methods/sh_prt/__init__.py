"""Classic SH PRT (Sloan et al. 2002), the baseline of Belcour et al. 2022 §6.4: ``model``
(SH projection of lights, the transfer product, pure JAX/NumPy) and ``data`` (the Mitsuba bake)."""

from jprt.inputs import SHLighting
from jprt.methods.base import Method
from jprt.methods.sh_prt import data, model

__all__ = ["METHOD", "PRESETS", "data", "model"]

#: Named config overrides; ``test`` bakes order 2 on a 32^2 atlas in seconds.
PRESETS = {"test": {"lightmap": {"resolution": 32},
                    "sh": {"order": 2, "spp": 2, "env_height": 8, "exit_directions": 8, "exit_spp": 2}}}

METHOD = Method.of_package(
    "sh_prt",
    "Sloan, Kautz, Snyder 2002, Precomputed Radiance Transfer for Real-Time Rendering in Dynamic, "
          "Low-Frequency Lighting Environments",
    SHLighting, model, data, PRESETS)
