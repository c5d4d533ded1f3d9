"""The data side of the lightmap methods (data-driven PRT, SH PRT): what the scene says about a
lightmap's texels beyond their light, read through Mitsuba when a dataset is made or loaded."""

from __future__ import annotations

from jprt.methods.lightmap_lookup import texel_modulation

__all__ = ["atlas_modulation"]


def atlas_modulation(desc: dict, atlas: dict) -> tuple:
    """``lightmap_lookup.texel_modulation`` of an atlas's texels in scene ``desc``: their materials
    (``jprt.render.lightmap.albedo_at_points``, one ray per texel) and the scene's object count.
    Read each time a dataset is loaded, not cached, so datasets rendered before it stay valid."""
    from jprt.render import lightmap
    from jprt.render.scenes import SceneHandle

    handle = SceneHandle(desc)
    diffuse, specular, hit = lightmap.albedo_at_points(handle, atlas["position"], atlas["normal"])
    return texel_modulation(diffuse, specular, atlas["texel_object"], hit, len(handle.object_names()))
