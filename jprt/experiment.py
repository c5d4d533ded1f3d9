"""Experiment files: loading one (``load_experiment``) and resolving its config
(``resolve_config``: presets, a JSON config file, ``--set`` overrides).

An experiment file defines ``CONFIG`` (a nested dict) and either ``METHOD`` (a
``jprt.methods.REGISTRY`` name, run by ``jprt.runner``) or its own ``main(config)``; optionally
``PRESETS`` (named override dicts). The command line (``jprt.cli``), the runner and sweeps load
experiments through this module, so none of them imports another to do it.
"""

from __future__ import annotations

import importlib.util
import json
import os
import sys
from types import ModuleType

__all__ = ["load_experiment", "resolve_config"]


def load_experiment(path: str) -> ModuleType:
    """Import an experiment file and check it defines CONFIG and either METHOD (a REGISTRY name:
    ``jprt.runner`` runs it) or its own ``main(config)``."""
    if not os.path.isfile(path):
        raise FileNotFoundError(f"experiment file not found: {path}")
    name = "jprt_experiment_" + os.path.splitext(os.path.basename(path))[0]
    folder = os.path.dirname(os.path.abspath(path))
    if folder not in sys.path:  # sibling modules (shared experiment pipelines) import as in `python file.py`
        sys.path.insert(0, folder)
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    # registered under its name before it runs, as `import` does, so dataclasses and pickle defined
    # in the file find their module; a later load of a file of the same name replaces it
    sys.modules.update({name: module})
    spec.loader.exec_module(module)
    runnable = isinstance(getattr(module, "METHOD", None), str) or callable(getattr(module, "main", None))
    if not isinstance(getattr(module, "CONFIG", None), dict) or not runnable:
        raise ValueError(f"{path} must define CONFIG (a dict) and METHOD (a jprt.methods.REGISTRY name) or "
                         f"main(config)")
    return module


def resolve_config(module: ModuleType, overrides: list[str], preset: str | None = None,
                   config_file: str | None = None) -> dict:
    """The experiment's CONFIG, with a named preset (``PRESETS[preset]``), a JSON config file
    (e.g. a sweep's ``selected.json``: its ``config`` entry, merged strictly) and ``--set``
    overrides, in that order."""
    from jprt.config import apply_overrides, merge

    config = module.CONFIG
    if preset is not None:
        presets = getattr(module, "PRESETS", {})
        if preset not in presets:
            raise ValueError(f"unknown preset {preset!r}; this experiment has {sorted(presets) or 'none'}")
        config = merge(config, presets[preset])
    if config_file is not None:
        with open(config_file) as f:
            loaded = json.load(f)
        config = merge(config, loaded.get("config", loaded))
    return apply_overrides(config, overrides)
