"""Data-driven PRT's ridge regularisation as a sweep (Belcour et al. 2022 Eq. 14): a fixed lambda
per point (cross-validation off) crossed with the gamma encoding of §5.3. The experiment's
in-report lambda sweep (``eval.lambdas``) refits one dataset and stays for the benchmark report.

    jprt sweep experiments/sweeps/datadriven_regularisation.py --select "indirect_rmse<=0.02" --minimize train_s
"""

SWEEP = {
    "experiment": "../datadriven.py",
    "preset": "small",
    "grid": {"transfer.lam": [1e-4, 1e-3, 1e-2, 1e-1, 1.0], "basis.gamma": [0.0, 2.2]},
    "set": ["transfer.lam_cv=[]", "eval.basis_sizes=[16]", "eval.lambdas=[]", "eval.point_counts=[]", "eval.oos_n=0"],
}
