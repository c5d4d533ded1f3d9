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

# The `small` budget: ~80k training samples spread over 200 lights x 20 views x 20 rays (the
# method's default is 20 lights x 100 rays) with tree.min_samples 1600 (default 1500); until
# 2026-12-02, 100 lights and min_samples 800 (the measurements below, to the last paragraph). Held-out
# indirect RMSE / 99.9th-percentile error, same budget (2026-11-30, one fit each): 20 lights x 100
# rays, min_samples 1500: 0.0172 / 0.175 (15 leaves); 800: 0.0146 / 0.116 (32 leaves); 400: 0.0144 /
# 0.118 (64); 20 x 200 rays: 0.0201 / 0.172; 40 lights x 50: 0.0083 / 0.064; 60 x 33: 0.0102 / 0.075;
# 100 x 20: 0.0062 / 0.049; 200 x 10: 0.0072 / 0.063. Twenty lights leave the light box too sparse:
# a held-out light between them lit a blob on the back wall that no training light did.
# Mitsuba then needs about 4096 spp for that error (the reference's own spp).
# The 99.9th percentile (8x the RMSE; issue 17 asks 6x): of the worst 0.1 % of pixel channels, a
# quarter are the tall box's top face, seen at grazing angles (24 of the 39k training rays hit it),
# the rest bright ceiling, back-wall and left-wall corners near the light, predicted 8-15 % low.
# Measured against that (2026-11-30, one fit each, `python experiments/rrf_tail.py '{...}'`, RMSE /
# p99.9 / ratio): this config 0.0064 / 0.053
# / 8.3 (27 leaves); train.max_iters 100: 0.0065 / 0.053 / 8.3; data.oversample 2 (rays balanced
# over faces): 0.0068 / 0.061 / 9.0; tree.min_samples 400: 0.0066 / 0.057 / 8.6 (58 leaves); 200
# lights (80k samples): 0.0072 / 0.055 / 7.7 (60 leaves; the top face then half the tail); 200
# lights and min_samples 400: 0.0073 / 0.059 / 8.0 (64 leaves, the cap); data.min_face_rays 1 (every
# face the candidate rays see gets a ray, the rest uniform): 0.0065 / 0.054 / 8.4, the top face's
# share of the tail 51 -> 12 of 195 channels, the corners' share up by as much; 200 lights and
# min_face_rays 1: 0.0089 / 0.098 / 11.0 (61 leaves; the whole tail on the back wall: one badly
# fitted leaf).
# The kd-trees do not split on the light position (tree.split_on, NO_LIGHT_SPLIT; the paper's rule
# splits every axis): every leaf then serves every light, so a frame's lights share each pixel's
# traversal and the light-free part of the first layer, and four lights cost about 2x one light
# instead of about 3.7x, at about the paper rule's accuracy (the split_rule_ablation stage fits
# the paper's rule on the same samples and times both models interleaved; README, issue 17).
# Every surface of the box is Lambertian, so the networks do not read the view (model.attributes
# "diffuse": the indirect radiance leaving a diffuse point does not depend on it; with it, the trees
# split on the view 10 times of 24, and a held-out view gives the networks directions no training
# view did). Same samples, one fit each (2026-12-02 evening, AMD EPYC VM, `python
# experiments/rrf_tail.py '{"small": {}, "diffuse": {...}}'`, RMSE / p99.9 / ratio): augmented
# without light splits 0.0065 / 0.055 / 8.4 (31 leaves); diffuse 0.0058 / 0.044 / 7.5 (32);
# diffuse with hidden [30, 15] 0.0060 / 0.047 / 7.8; diffuse with min_samples 400 0.0058 / 0.046 /
# 8.0 (63 leaves). Of the diffuse fit's worst 0.1 %, 155 of 195 channels are under one held-out
# light (the one nearest the red wall and the ceiling), on the ceiling and the floor.
# Each object's kd-tree box stretched a wall's constant coordinate (one or two float32 ulps) to
# [0, 1], and the trees split the floor, the ceiling and both side walls at their roots on that
# rounding: each wall two leaves fitted on random halves of its samples, alternating pixel by pixel
# (speckle in the error images). With the box flat there (2026-12-02 night, same command, RMSE / p99.9
# / ratio): this config with 100 lights and min_samples 800 0.0060 / 0.051 / 8.5 (27 leaves; 0.0058
# / 0.044 / 7.5 before: the speckle is spread-out error, which lowers the ratio); 200 lights 0.0053 /
# 0.042 / 8.0 (50 leaves); 200 lights and min_samples 1600 0.0053 / 0.042 / 7.9 (27 leaves, kept:
# the leaf count and frame of the 100-light config); training lights from a box grown by 10 % of
# its size on every side (the held-out light of the tail is 0.06 inside the box's edge), 173
# lights (the same density inside the box): 0.0066 / 0.052 / 8.0. The references' own noise at
# 4096 spp (``--noise``: |A - B| / sqrt 2) is RMSE 0.0030 with p99.9 6.4x it: what a perfect
# predictor scores against one reference set (the reference_noise stage reports it each run).
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
    # make demo: renders, trains, evaluates and reports within 5 minutes.
    "demo": {
        # 6000 uniform rays miss the tall box's top face (a black seam along its edge): balance them
        "data": {"n_lights": 10, "n_views": 10, "n_rays": 60, "spp": 256, "oversample": 8},
        "tree": {"max_depth": 1, "min_samples": 800, "max_leaves": 10},
        "train": {"max_iters": 25, "trial_iters": 6, "trial_samples": 512},
        "eval": {"n_views": 2, "n_lights": 2, "resolution": 64, "reference_spp": 1024, "ablations": False,
                 "robustness": 0, "sizes": [], "train_spp": [], "timing_repeats": 5, "pathtrace_repeats": 1,
                 "equal_error_spp": [1, 2, 4, 8, 16, 32, 64, 128, 256]},
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

