"""The inputs of SG environment visibility (Currius et al. 2020 §5): the receivers' atlas, their
captured visibility and W_E (Eq. 7) under the config's environment
(``jprt.methods.sg_lightfield.data.make_environment_dataset``, cached there), and how the viewer
turns a camera view and an environment into the evaluator's inputs."""

from __future__ import annotations

import numpy as np

from jprt.methods.base import resolve
from jprt.methods.sg_environment.model import DEFAULT_CONFIG, preconvolved

__all__ = ["make_dataset", "TASK_LIGHTINGS", "VIEW_LIGHTINGS", "PREDICTS", "task_inputs", "task_lighting",
           "view_environments"]

#: The shared tasks of experiments/atlas.py compare indirect light; this method predicts the
#: environment's glossy reflection (direct light), so it takes part in none of them.
TASK_LIGHTINGS: tuple = ()

#: What ``jprt view`` relights it with: an environment map and its rotation.
VIEW_LIGHTINGS = ("environment",)

#: The evaluator's output is direct light (the environment reflected once), not indirect.
PREDICTS = "direct"


def make_dataset(scene=None, config: dict | None = None, *, cache_dir: str | None = None,
                 progress: bool | None = None):
    """The receivers' (``objects``) atlas, visibility, W_E and U in ``scene`` (default
    ``config['scene']``) under ``config['environment']``: an ``EnvData``."""
    from jprt.methods.sg_lightfield.data import make_environment_dataset

    cfg = resolve(DEFAULT_CONFIG, config)
    parts = {"objects": list(cfg["objects"]), "lightmap": dict(cfg["lightmap"]),
             "capture": {"block": cfg["capture"]["block"]}}
    return make_environment_dataset(parts, cfg["environment"], scene=scene if scene is not None else cfg["scene"],
                                    cache_dir=cache_dir, progress=progress)


def task_inputs(handle, dataset, camera):
    """The atlas G-buffer (lightmap ``uv``, normal, view, GGX alpha, specular) of ``camera``."""
    from jprt.render import lightmap

    return lightmap.atlas_gbuffer(handle, lightmap.Atlas(**dataset.atlas), camera)


def task_lighting(handle, dataset, params, config, lighting):
    """A ``CubeMap`` (or ``EnvMap``) pre-convolved (Eq. 6, ``model.preconvolved``): once per
    environment, as a renderer would."""
    from jprt.inputs import CubeMap
    from jprt.sphere.envmap import render_equirect

    radiance = render_equirect(np.asarray(lighting.radiance)) if isinstance(lighting, CubeMap) else lighting.radiance
    return preconvolved(radiance, config)


def view_environments(dataset, config, face: int = 32) -> dict:
    """{name: (6, face, face, 3) cube map} the viewer offers: the map W_E was computed under, then
    two seeded synthetic skies (no files needed)."""
    from jprt.sphere.envmap import prepare_environment, synthetic_environments

    cfg = resolve(DEFAULT_CONFIG, config)
    out = {str(cfg["environment"]["map"]): prepare_environment(np.asarray(dataset.environment), face, normalise=False)}
    for i, cube in enumerate(synthetic_environments(2, face, seed=int(cfg["environment"]["seed"]) + 101)):
        out[f"synthetic sky {i + 1}"] = np.asarray(cube, np.float32)
    return out
