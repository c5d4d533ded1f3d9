"""Radiance Regression Functions on a scene with glossy interreflection and a caustic
(``glossy_cornell``: GGX floor, near-mirror metal sphere focusing the light, checker back wall),
plus the material-editing variant of Ren et al. 2013, Appendix B (fixed view; the floor's
roughness and albedo replace the view direction as inputs).

    jprt run experiments/rrf_glossy.py                    # `small`: the RRF report + the material demo
    jprt run experiments/rrf_glossy.py --preset paper     # the paper's sizes (needs an accelerator)
"""

import os

from rrf_common import LABEL, METHOD, PAPER_PRESET, STAGES, config, frame, held_out, pathtracer  # noqa: F401

from jprt import eval as jeval
from jprt import io
from jprt.config import merge
from jprt.methods.rrf import evaluation as ev

CONFIG = config("results/rrf_glossy", {
    "scene": {"name": "glossy_cornell", "floor_roughness": 0.15, "sphere_roughness": 0.02},
    "eval": {"robustness": 0, "sizes": [], "train_spp": []},
})
CONFIG["material_demo"] = {
    "enabled": True,
    "edits": [[0.05, 0.2], [0.2, 0.5], [0.45, 0.8]],   # (floor GGX alpha, floor albedo)
    "reference_spp": 1024,
    "data": {"n_lights": 12, "n_rays": 400, "spp": 256,
             "material": {"object": "floor", "roughness": [0.05, 0.5], "albedo": [0.1, 0.8], "n_materials": 12}},
}

PRESETS = {
    "small": {},
    "paper": {
        **merge(PAPER_PRESET, {"eval": {"sizes": [], "train_spp": []}}),
        "material_demo": {"reference_spp": 16384, "data": {"n_lights": 100, "n_rays": 20000, "spp": 4096,
                                                           "material": {"n_materials": 100}}},
    },
    "test": {
        "data": {"n_lights": 2, "n_views": 2, "n_rays": 30, "spp": 4},
        "model": {"hidden": [4, 2]},
        "tree": {"max_depth": 0},
        "train": {"max_iters": 2},
        "eval": {"n_views": 1, "n_lights": 1, "resolution": 10, "reference_spp": 8, "ablations": False,
                 "equal_error_spp": [1, 2], "timing_resolution": 12, "timing_repeats": 1, "pathtrace_repeats": 1,
                 "images": 1},
        "material_demo": {"edits": [[0.1, 0.5]], "reference_spp": 4,
                          "data": {"n_lights": 2, "n_rays": 20, "spp": 2, "material": {"n_materials": 2}}},
    },
}


def material_edit(run) -> dict:
    """Appendix B (``evaluation.material_edit``): a fixed-view RRF whose view inputs are one
    object's roughness and albedo; its edits beside Mitsuba's in the ``material_edit/`` folder.
    ``config['material_demo']`` holds them."""
    demo = run.config["material_demo"]
    if not demo["enabled"]:
        return {}
    cfg = run.with_config({"data": {**demo["data"], "mode": "material"}})
    out = os.path.join(run.out, "material_edit")
    os.makedirs(out, exist_ok=True)
    summary, rows = ev.material_edit(run.config["scene"], cfg, demo, run.config["eval"], run.say)
    jeval.side_by_side(os.path.join(out, "material_edit.png"), rows, exposure=float(run.config["eval"]["exposure"]))
    io.write_json(os.path.join(out, "summary.json"), summary)
    return {"material_edit": summary}


#: The RRF report's stages, then the material-editing demo.
STAGES = STAGES + [material_edit]
