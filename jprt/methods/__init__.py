"""The published systems, each composing the layers below (DESIGN.md, "Methods").

Every method module exposes ``make_dataset(scene, config)``, ``fit(data, config)`` and
``evaluator(params, config)``; evaluation and reports go through ``jprt.eval`` and the
experiment files.

* ``rrf`` + ``kdtree``: Radiance Regression Functions (Ren et al. 2013).
* ``wavelet_prt``: neural-wavelet PRT, environment-map relighting from any view (Raghavan et al. 2023).
* ``datadriven`` (+ ``sh_prt``, the SH PRT baseline): data-driven PRT (Belcour et al. 2022).
"""
