"""The light-field texture of SG light-field textures (Currius et al. 2020 §3): the receivers'
lightmap atlas and every texel's captured incident radiance (``jprt.render.lightfield``, cached
and resumable there)."""

from __future__ import annotations

import numpy as np

from jprt.methods.sg_lightfield.model import SGData, _cfg, texel_irradiance

__all__ = ["make_dataset", "TASK_LIGHTINGS"]

#: The shared tasks of experiments/atlas.py relight with lights the bake never saw: a light-field
#: texture is baked for its scene's own emitters, so it takes part in none of them.
TASK_LIGHTINGS: tuple = ()


def make_dataset(scene=None, config: dict | None = None, *, cache_dir: str | None = None,
                 progress: bool = True) -> SGData:
    """Capture the light field of the receivers (``objects``) of ``scene`` (default
    ``config['scene']``) under the scene's own emitters; texels inside other geometry keep their
    ``INSIDE`` flag and zero maps (the fit sees them as black, the run time never looks them up)."""
    from jprt.render.lightfield import capture_lightfield

    cfg = _cfg(config)
    c = cfg["capture"]
    if c["field"] not in ("indirect", "full"):
        raise ValueError(f"capture.field must be 'indirect' or 'full', got {c['field']!r}")
    lf = capture_lightfield(scene if scene is not None else cfg["scene"], None, objects=list(cfg["objects"]) or None,
                            resolution=int(cfg["lightmap"]["resolution"]), size=int(c["size"]), spp=int(c["spp"]),
                            seed=int(c["seed"]), block=int(c["block"]), cache_dir=cache_dir, progress=progress)
    images = lf.indirect if c["field"] == "indirect" else lf.full
    irradiance = np.asarray(texel_irradiance(images, lf.normal, lf.size), np.float32)
    return SGData(lf.atlas, images, lf.below, lf.normal, lf.flags, irradiance,
                  {**lf.meta, "size": lf.size, "field": c["field"]})
