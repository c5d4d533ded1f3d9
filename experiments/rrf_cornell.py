"""Radiance Regression Functions on the built-in Cornell box (Ren et al. 2013, §5, Table 3, Fig. 6-7).

    jprt run experiments/rrf_cornell.py                   # the `small` config (~80k training samples)
    jprt run experiments/rrf_cornell.py --preset demo     # < 5 min end to end (make demo)
    jprt run experiments/rrf_cornell.py --preset paper    # the paper's sizes (needs an accelerator)

Point lights move inside the box (light box below), the viewpoint moves in front of its opening.
The report (summary.json with every number, side-by-side images, error plots) goes to
results/rrf_cornell/<config hash>/.
"""

from rrf_common import (LABEL, METHOD, NO_LIGHT_SPLIT, PAPER_PRESET, STAGES, config, frame, held_out,  # noqa: F401
                         pathtracer)

from jprt.methods import REGISTRY

# The `small` budget: ~80k training samples over 200 lights x 20 views x 20 rays, leaves of at
# least 1600 samples. The kd-trees split on neither the light position (tree.split_on without
# "light": every leaf serves every light, so a frame's lights share each pixel's traversal and the
# light-free part of the first layer; the split_rule_ablation stage fits the paper's rule on the
# same samples) nor the view (model.attributes "diffuse": every surface of the box is Lambertian,
# so the indirect radiance leaving a point does not depend on the view). experiments/rrf_tail.py
# shows where the worst pixels of such a fit lie and what training settings do to them.
CONFIG = config("results/rrf_cornell", {"scene": {"name": "cornell_box", "area_light": False},
                                        "data": {"n_lights": 200, "n_rays": 20},
                                        "model": {"attributes": "diffuse"},
                                        "tree": {"min_samples": 1600,
                                                 "split_on": [a for a in NO_LIGHT_SPLIT if a != "view"]},
                                        "eval": {"equal_error_spp": [1, 2, 4, 8, 16, 32, 64, 128, 256, 512, 1024,
                                                                     2048, 4096]}})

PRESETS = {
    # The default CONFIG: trains in minutes on a 2-core CPU.
    "small": {},
    # make demo: renders, trains, evaluates and reports within 5 minutes, at 128 x 128.
    "demo": {
        # 80 lights: held-out lights between them are interpolated, not guessed from ten.
        # 6000 uniform rays miss the tall box's top face (a black seam along its edge): balance them
        "data": {"n_lights": 80, "n_views": 4, "n_rays": 60, "spp": 256, "oversample": 8},
        "tree": {"max_depth": 1, "min_samples": 800, "max_leaves": 10},
        "train": {"max_iters": 25, "trial_iters": 6, "trial_samples": 512},
        "eval": {"n_views": 2, "n_lights": 2, "resolution": 128, "reference_spp": 1024, "ablations": False,
                 "robustness": 0, "sizes": [], "train_spp": [], "timing_resolution": 128, "timing_repeats": 5,
                 "pathtrace_repeats": 1, "reference_noise": False,
                 "equal_error_spp": [1, 4, 16, 64, 256, 1024]},  # every fourth: half the render time
    },
    "paper": PAPER_PRESET,
    # Smoke test (tests/test_experiments.py).
    "test": {
        **REGISTRY["rrf"].presets["test"],  # the method's own smoke-test sizes
        "eval": {"n_views": 1, "n_lights": 2, "resolution": 12, "reference_spp": 16, "robustness": 2,
                 "sizes": [0.5], "train_spp": [4], "equal_error_spp": [1, 4], "timing_resolution": 16,
                 "timing_repeats": 2, "pathtrace_repeats": 1, "single_mlp_steps": 20, "images": 1},
    },
}

