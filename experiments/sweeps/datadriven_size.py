"""Data-driven PRT: accuracy against cost over the basis size n and the measurement-point count P
(Belcour et al. 2022 Fig. 14 and §5.1).

    jprt sweep experiments/sweeps/datadriven_size.py
    jprt sweep experiments/sweeps/datadriven_size.py --select "indirect_rmse<=0.02" --minimize model_bytes
"""

SWEEP = {
    "experiment": "../datadriven.py",
    "preset": "small",
    "grid": {"basis.n": [4, 16, 64], "points.count": [64, 128, 256]},
    "set": ["eval.basis_sizes=[16]", "eval.lambdas=[]", "eval.point_counts=[]", "eval.oos_n=0"],
}
