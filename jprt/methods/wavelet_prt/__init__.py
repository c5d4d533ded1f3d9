"""Neural-wavelet PRT (Raghavan et al. 2023): ``model`` (Haar wavelets, the CP feature field and
MLP, §5 training, Algorithm 1; pure JAX) and ``data`` (environment-lit images rendered with
Mitsuba)."""


from jprt.inputs import CubeMap
from jprt.methods.base import Method
from jprt.methods.wavelet_prt import data, model

__all__ = ["METHOD", "PRESETS", "data", "model"]

#: Named config overrides; ``test`` runs the whole contract in seconds (procedural maps).
PRESETS = {
    "test": {
        "envmaps": {"synthetic": 3, "face_size": 4, "rotations_deg": [0.0]},
        "cameras": {"width": 12, "height": 12, "sphere": {"n": 3}, "helix": {"n": 3}, "near": 2, "far": 2},
        "data": {"spp": 8, "test_spp": 32, "envs_per_view": 1},
        "model": {"n_levels": 3, "log2_table_size": 8, "n_features": 8, "hidden": 16},
        "train": {"steps": 30, "pixels": 32, "wavelets": 24, "checkpoint_every": 10, "log_every": 10},
        "render": {"k": 16, "chunk": 64},
    },
}


METHOD = Method.of_package(
    "wavelet_prt",
    "Raghavan, Xiao, Lin, Sun, Bi, Xu, Li, Ramamoorthi 2023, "
    "Neural Free-Viewpoint Relighting for Glossy Indirect Illumination",
    CubeMap, model, data, PRESETS)
