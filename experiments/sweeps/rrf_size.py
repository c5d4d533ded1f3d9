"""RRF: accuracy against cost over the kd-tree's error threshold and the networks' hidden sizes
(Ren et al. 2013 §4; the paper's 20-10 networks and 5 % threshold are one point).

    jprt sweep experiments/sweeps/rrf_size.py
    jprt sweep experiments/sweeps/rrf_size.py --select "indirect_rel_rmse<=0.2" --minimize frame_ms
"""

SWEEP = {
    "experiment": "../rrf_cornell.py",
    "preset": "small",
    "grid": {"tree.threshold": [0.03, 0.05, 0.1], "model.hidden": [[10, 5], [20, 10], [32, 16]]},
    # the ablations of the report are the experiment's own; a sweep point is the common summary
    "set": ["eval.ablations=false", "eval.robustness=0", "eval.sizes=[]", "eval.train_spp=[]"],
}
