"""Lighting design through a fitted model (``jprt.design``, docs/design.md): the point lights
(RRF, data-driven PRT, MRT) or an environment's turn and scale (neural-wavelet PRT, SH PRT, SG
environment visibility) that
meet an objective, found by gradient descent through a run folder's model, corrected by one
Mitsuba render of what it found, and verified on another.

    jprt run experiments/design.py                     # fits RRF on the Cornell box (demo), then designs
    jprt run experiments/design.py --set run=results/rrf_cornell/<hash> --set objective=objective.json
    jprt run experiments/design.py --set run=FOLDER --set design.lights=3 --set design.steps=300

Output (``output.dir``/<config hash>/): ``config.json``, ``objective.json`` (the objective as
run), ``design.json`` (``jprt.design.design_run``'s report: the lighting found, the objective on
the model and on Mitsuba's verification render, every bound met or not, the times) and
``design.png`` (the objective per step; each term on the model beside the render).
"""

from __future__ import annotations

from jprt import design

CONFIG = {
    # the run folder to design through; null: fit `fit.experiment` at `fit.preset` first (its
    # own output folder)
    "run": None,
    "fit": {"experiment": "experiments/rrf_cornell.py", "preset": "demo"},
    # an objective file's path, or its content (jprt.design's module docstring); null: DEMO_OBJECTIVE
    "objective": None,
    # jprt.design.design_run's keywords: point lights to place, the frame's size (pixels), Adam's
    # step budget and rate, the start ("search" or null: spread), correction passes and spp,
    # the verification's spp, the seed, an environment map's name (environment-lit runs), what
    # moves (null: position and power, or rotation and scale; a list of names)
    "design": {"lights": 2, "size": 64, "steps": 200, "learning_rate": 0.05, "start": "search",
               "correct": 1, "correct_spp": 256, "verify_spp": 256, "seed": 0, "env": None, "optimise": None},
    "output": {"dir": "results/design"},
}

#: The demo's objective, for the Cornell box: its back wall at least 1.9 W m^-2 of mean
#: irradiance, its green wall at most 2.3.
DEMO_OBJECTIVE = {"objects": [{"name": "back", "quantity": "irradiance", "min": 1.9},
                              {"name": "green-wall", "quantity": "irradiance", "max": 2.3}]}

PRESETS = {
    # seconds, through a given run folder (--set run=FOLDER; tests/test_design.py)
    "test": {"design": {"lights": 1, "size": 12, "steps": 6, "correct_spp": 4, "verify_spp": 4}},
}


def main(config: dict) -> dict:
    """Design the lighting of ``config`` (``jprt.design.run_design``; the demo's objective where
    it names none)."""
    if config.get("objective") is None:
        config = {**config, "objective": DEMO_OBJECTIVE}
    return design.run_design(config)
