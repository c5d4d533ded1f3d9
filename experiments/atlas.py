"""The speed-accuracy atlas on the built-in tasks: every method of ``jprt.methods.REGISTRY`` that
relights a task's lighting, swept over its main size knob, against Mitsuba's own speed-accuracy
curve measured in the same run (``jprt.atlas``).

    jprt run experiments/atlas.py --preset small     # both tasks (python benchmarks/atlas.py records it)
    jprt run experiments/atlas.py --preset test      # seconds (tests/test_atlas.py)
    jprt run experiments/atlas.py --set eval.select="indirect_rel_rmse<=0.3"   # + each method's cheapest point

The tasks (``jprt.atlas.TASKS``):

* ``local_lights``: the built-in Cornell box (no area light) lit by one white point light inside
  it, views in front of its opening; RRF, data-driven PRT, SH PRT and MRT;
* ``environment``: the glossy Cornell box with its top open, relit by environment maps held out
  from neural-wavelet PRT's training (../shared/assets), seen from views around it; neural-wavelet
  PRT and SH PRT.

Each task's ``methods`` entry names a method's ``set`` items (on top of its defaults and the
task's scene) and its swept ``grid``; ``eval`` holds Mitsuba's curve (``curve_spp``), the timing
resolution and the selection (``select``, ``minimize``). The same atlas runs on one task, or on
any scene file, with ``jprt atlas TASK_OR_SCENE``.

Output (``output.dir``): ``atlas.json`` (per task, per method: the points with the common summary
keys, the Pareto fronts, the Mitsuba curve), ``atlas_<task>.png`` (every method's points and front,
Mitsuba's curve), ``atlas.md`` (the table) and, with ``eval.select``,
``selected_<task>_<method>.json`` (re-run with ``jprt run experiments/atlas.py --config FILE``).
"""

from __future__ import annotations

from jprt import atlas

CONFIG = {"tasks": atlas.TASKS, "eval": atlas.EVAL, "output": {"dir": "results/atlas"}}

PRESETS = atlas.PRESETS


def main(config: dict) -> dict:
    """Run the atlas on ``config``'s tasks; the selections re-run through this file."""
    return atlas.run_atlas(config, experiment=__file__)
