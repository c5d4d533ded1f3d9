"""Neural-wavelet PRT's speed-accuracy front (Raghavan et al. 2023 §5, Table 2): the MLP width
crossed with the features per hash-grid level (the feature count M = levels x features, the
rank of Eq. 7, which sets the run-time cost; L only costs in training, as U folds into f's first
layer) and the run-time wavelet count K. Each model trains at the full step count (the K of one
model share its checkpoint); every point's far-view accuracy, frame time at 256^2 with its FLOP
count, and Mitsuba's time at equal error are the sweep's columns, its Pareto fronts the plots.

    jprt sweep experiments/sweeps/wavelet_prt_front.py
    jprt sweep experiments/sweeps/wavelet_prt_front.py --select "speedup_equal_error>=20" --minimize indirect_rmse
"""

SWEEP = {
    "experiment": "../wavelet_prt_cornell.py",
    "preset": "small",
    "grid": {"model.hidden": [128, 64, 32], "model.features_per_level": [2, 1], "render.k": [16, 32, 64]},
    # each point: the common summary only (no transport check, K sweep, generalisation or ablations)
    "set": ["eval.gt_check.ks=[]", "eval.ks=[]", "eval.generalisation=[]", "eval.ablation_steps=0",
            "eval.timing_resolutions=[[256, 256]]"],
}
