"""Neural-wavelet PRT: accuracy against frame time over the run-time wavelet count K and the MLP
width (Raghavan et al. 2023 Table 2 and §5; K = 64 with 2 x 128 is the paper's point).

    jprt sweep experiments/sweeps/wavelet_prt_size.py
    jprt sweep experiments/sweeps/wavelet_prt_size.py --select "psnr_indirect>=26" --minimize frame_ms
"""

SWEEP = {
    "experiment": "../wavelet_prt_cornell.py",
    "preset": "small",
    "grid": {"render.k": [16, 32, 64], "model.hidden": [64, 128]},
    "set": ["eval.gt_check.ks=[]", "eval.ks=[]", "eval.generalisation=[]", "eval.ablation_steps=0",
            "eval.timing_resolutions=[[256, 256]]"],
}
