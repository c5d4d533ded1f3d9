"""Ground truth for the built-in Cornell box: direct, indirect and G-buffer for a few views and
point lights, as EXR + PNG previews + a JSON summary (the demo until the first method lands).

    jprt run experiments/cornell_gt.py                      # 256x256, 3 views x 2 lights
    jprt run experiments/cornell_gt.py --preset test        # tiny, for smoke tests
"""

from jprt.render import report
from jprt.render.dataset import DEFAULT_DATASET_CONFIG
from jprt.config import merge

CONFIG = {
    "dataset": merge(DEFAULT_DATASET_CONFIG, {
        "scene": {"name": "cornell_box", "area_light": False},
        "cameras": {"kind": "orbit", "n": 3, "radius": 3.9, "start_deg": -20.0, "arc_deg": 40.0,
                    "width": 256, "height": 256},
        "lights": {"kind": "point", "positions": [[0.0, 0.8, 0.0], [-0.6, 0.5, 0.5]], "intensity": [4.0, 4.0, 4.0]},
        "spp": 128,
    }),
    "output": {"dir": "results/cornell_gt", "exposure": 0.0},
}

PRESETS = {
    "test": {"dataset": {"cameras": {"n": 2, "width": 24, "height": 24}, "spp": 8}},
}


def main(config):
    """Render (or reuse) the dataset and write its images and summary."""
    return report.write_ground_truth(config)
