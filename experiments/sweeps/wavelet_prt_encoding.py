"""Neural-wavelet PRT's encodings as a sweep (Raghavan et al. 2023 Tables 3 and 4): the hash-table
size crossed with the reflection-direction encoding, each point a full training run (the
experiment's in-report ablations, ``eval.ablations``, run shorter and stay for the benchmark report).

    jprt sweep experiments/sweeps/wavelet_prt_encoding.py
"""

SWEEP = {
    "experiment": "../wavelet_prt_cornell.py",
    "preset": "small",
    "grid": {"model.log2_table_size": [10, 12, 14], "model.reflection": ["sh4", "raw", "none"]},
    "set": ["eval.gt_check.ks=[]", "eval.ks=[]", "eval.generalisation=[]", "eval.ablation_steps=0",
            "eval.timing_resolutions=[[256, 256]]"],
}
