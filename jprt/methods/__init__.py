"""The published systems, each composing the layers below (DESIGN.md, "Methods").

Every method module exposes ``make_dataset(scene, config)``, ``fit(data, config)`` and
``evaluator(params, config)``; evaluation and reports go through ``jprt.eval`` and the
experiment files.

* ``rrf`` + ``kdtree``: Radiance Regression Functions (Ren et al. 2013).
"""
