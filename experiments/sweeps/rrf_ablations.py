"""RRF ablations as a sweep (Ren et al. 2013): the attribute set of Fig. 3 (basic (x_p, v, l)
against augmented (x_p, v, l, n, a)) crossed with the training-data spp of Fig. 7. Each point is
a full fit on its own data; the experiment's in-report versions of these (``eval.ablations``,
``eval.train_spp``) refit on one dataset and stay for the benchmark report.

    jprt sweep experiments/sweeps/rrf_ablations.py
"""

SWEEP = {
    "experiment": "../rrf_cornell.py",
    "preset": "small",
    "grid": {"model.attributes": ["basic", "augmented"], "data.spp": [64, 128, 512]},
    "set": ["eval.ablations=false", "eval.robustness=0", "eval.sizes=[]", "eval.train_spp=[]"],
}
