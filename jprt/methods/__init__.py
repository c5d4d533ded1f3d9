"""The published systems (and baselines), one package each behind one contract
(``jprt.methods.base``): ``REGISTRY`` maps names to ``Method`` tuples.

* ``rrf``: Radiance Regression Functions (Ren et al. 2013).
* ``wavelet_prt``: neural-wavelet PRT, environment-map relighting from any view (Raghavan et al. 2023).
* ``datadriven``: data-driven PRT (Belcour et al. 2022).
* ``sh_prt``: classic SH PRT (Sloan et al. 2002), data-driven PRT's baseline.
* ``sg_lightfield``: SG light-field textures, baked glossy GI seen from any view (Currius et al. 2020).
* ``sg_environment``: the same paper's §5, glossy environment reflections with visibility, relit by any map.
* ``mrt``: Modular Radiance Transfer, indirect light for layouts of canonical blocks (Loos et al. 2011).

Each package has ``model.py`` (the paper's math in pure JAX, in the paper's order, no Mitsuba),
``data.py`` (its training data rendered through ``jprt.render``, cached by ``jprt.cache``) and
``METHOD``. Every method runs the same four verbs (the contract of ``jprt.methods.base``; the
README runs this loop, ``tests/methods/test_contract.py`` checks it)::

    for name, m in REGISTRY.items():
        config = m.resolve(m.presets["test"])              # strict: unknown keys raise ConfigError
        dataset = m.make_dataset(config["scene"], config)   # Mitsuba renders, cached
        params, info = m.fit(dataset, config)               # FitResult: arrays only, plain dict
        evaluate = m.evaluator(params, config)              # pure (inputs, lighting) -> (H, W, 3)
        image = jax.jit(evaluate)(*m.example(dataset, config))

``jprt.runner`` runs an experiment over a method: dataset, fit, held-out predictions, the common
summary (``jprt.runner.SUMMARY_SCHEMA``), timing and equal error against Mitsuba, stages.
"""

from jprt.methods import datadriven, mrt, rrf, sg_environment, sg_lightfield, sh_prt, wavelet_prt
from jprt.methods.base import FitResult, Method

__all__ = ["REGISTRY", "Method", "FitResult", "datadriven", "mrt", "rrf", "sg_environment", "sg_lightfield", "sh_prt", "wavelet_prt"]

#: Every method by name, in the order of the mission statement.
REGISTRY: dict[str, Method] = {m.name: m for m in (rrf.METHOD, wavelet_prt.METHOD, sg_lightfield.METHOD,
                                                   sg_environment.METHOD,
                                                   datadriven.METHOD, mrt.METHOD, sh_prt.METHOD)}
