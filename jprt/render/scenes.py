"""Scenes: JSON-able descriptions, and Mitsuba scenes built from them with swappable lights.

A scene *description* is a plain dict (so it hashes into dataset cache keys and configs):

  {"name": "cornell_box", "area_light": True, "materials": {"floor": {...}, ...}}
  {"name": "glossy_cornell", "floor_roughness": 0.2, "sphere_roughness": 0.05, ...}
  {"name": "xml", "path": "/abs/scene.xml", "sha256": "...", "keep_emitters": True}
                                             (+ "opening": "ceiling" to cut the ceiling away)
                                             disks, spheres and cylinders become triangle meshes,
                                             instances one mesh per (instance, member) named
                                             "<instance>/<member>"; media inside surfaces kept
  {"name": "asset_room", "mesh": "/abs/spot.obj", "sha256": "...", "albedo": [...], ...}
                                             a UV-mapped mesh (object "asset") in an open room corner
  {"name": "empty"}                          no geometry: only the jprt lighting (probes, tests)
  {"name": "blocks", "layout": {...}, "size": 1.0, "albedo": {...}}
                                             a layout of cube blocks (``jprt.layouts``; MRT's scenes)

Materials (``materials`` entries override the defaults per object):

  {"type": "diffuse", "albedo": [r, g, b]}                       Lambertian
  {"type": "diffuse", "albedo": {"checker": [[r,g,b], [r,g,b]], "scale": 4}}  textured albedo
  {"type": "diffuse", "albedo": {"texture": "/path/image.png"}}  textured albedo from a file
  {"type": "glossy", "albedo": [...], "specular": [...], "roughness": a}  diffuse + GGX coat
  {"type": "metal", "specular": [...], "roughness": a}          GGX conductor, Fresnel = 1

``roughness`` is always Mitsuba's microfacet ``alpha`` (GGX), not its square root.

``SceneHandle`` builds the Mitsuba scene once and swaps point lights or an environment map by
writing scene parameters, rebuilding only when the *kind* or count of lights changes.
"""

from __future__ import annotations

import copy
import hashlib
import os
import re
from typing import Any

import numpy as np

from jprt.config import section_defaults, section_from_string
from jprt.render.lights import (DirectionalLights, EnvMap, Lighting, PointLights, SpotLights, mitsuba_envmap_data,
                               to_mitsuba_envmap, validate_lighting)
from jprt.render.setup import mitsuba

__all__ = [
    "empty",
    "cornell_box",
    "glossy_cornell",
    "xml",
    "asset_room",
    "blocks",
    "BLOCK_ALBEDO",
    "BLOCK_INSET",
    "describe",
    "section_defaults",
    "section_from_string",
    "REFUSED_INTEGRATORS",
    "SceneHandle",
    "CORNELL_OBJECTS",
    "CORNELL_CAMERA",
]

CORNELL_OBJECTS = ("floor", "ceiling", "back", "green-wall", "red-wall", "small-box", "large-box")
#: The built-in Cornell box's own camera: (origin, target, fov along the smaller axis).
CORNELL_CAMERA = ((0.0, 0.0, 3.9), (0.0, 0.0, 0.0), 39.3077)

_WHITE = [0.885809, 0.698859, 0.666422]
_CORNELL_DEFAULT_MATERIALS = {
    "floor": {"type": "diffuse", "albedo": _WHITE},
    "ceiling": {"type": "diffuse", "albedo": _WHITE},
    "back": {"type": "diffuse", "albedo": _WHITE},
    "green-wall": {"type": "diffuse", "albedo": [0.105421, 0.37798, 0.076425]},
    "red-wall": {"type": "diffuse", "albedo": [0.570068, 0.0430135, 0.0443706]},
    "small-box": {"type": "diffuse", "albedo": _WHITE},
    "large-box": {"type": "diffuse", "albedo": _WHITE},
}
_MATERIAL_KEYS = {
    "diffuse": {"type", "albedo"},
    "glossy": {"type", "albedo", "specular", "roughness"},
    "metal": {"type", "specular", "roughness"},
}


def _check_material(name: str, material: dict) -> dict:
    kind = material.get("type")
    if kind not in _MATERIAL_KEYS:
        raise ValueError(f"material {name!r}: unknown type {kind!r} (use one of {sorted(_MATERIAL_KEYS)})")
    extra = set(material) - _MATERIAL_KEYS[kind]
    if extra:
        raise ValueError(f"material {name!r} of type {kind!r}: unknown keys {sorted(extra)}")
    roughness = material.get("roughness", 0.1)
    if not (1e-4 <= float(roughness) <= 1.0):
        raise ValueError(f"material {name!r}: roughness (GGX alpha) must be in [1e-4, 1], got {roughness}")
    return material


def empty() -> dict:
    """A scene with no geometry; rays see only the lighting (environment-map probes and tests)."""
    return {"name": "empty"}


def cornell_box(*, area_light: bool = True, materials: dict | None = None, open_top: bool = False) -> dict:
    """Mitsuba's built-in Cornell box (embedded default; needs no asset files).

    Args:
      area_light: keep the ceiling's area light. Turn it off to light the box with point lights
        or an environment map only (the light's quad is then removed).
      materials: per-object overrides keyed by ``CORNELL_OBJECTS`` names.
      open_top: remove the ceiling, so an environment map lights the box through its top as well
        as its open front (needs ``area_light=False``).
    """
    materials = dict(materials or {})
    unknown = set(materials) - set(CORNELL_OBJECTS)
    if unknown:
        raise ValueError(f"unknown Cornell box objects {sorted(unknown)}; objects are {list(CORNELL_OBJECTS)}")
    if open_top and area_light:
        raise ValueError("cornell_box: open_top removes the ceiling light; use area_light=False")
    merged = {k: _check_material(k, materials.get(k, v)) for k, v in _CORNELL_DEFAULT_MATERIALS.items()}
    desc = {"name": "cornell_box", "area_light": bool(area_light), "materials": merged}
    if open_top:  # only present when set, so existing descriptions (and their cache hashes) are unchanged
        desc["open_top"] = True
    return desc


def glossy_cornell(*, floor_roughness: float = 0.15, sphere_roughness: float = 0.02,
                   area_light: bool = False, albedo_checker: bool = True, open_top: bool = False) -> dict:
    """A Cornell box with glossy interreflection and a caustic.

    The floor is diffuse + GGX (``roughplastic``, alpha = ``floor_roughness``), the tall box is
    replaced by a near-mirror metal sphere (alpha = ``sphere_roughness``) that focuses light
    onto the walls and floor (a reflective caustic), the back wall has a checker albedo texture.
    ``open_top`` removes the ceiling (and the light's quad), so an environment map lights the box
    through its top as well as its open front (the environment-lit variant of
    ``jprt.methods.wavelet_prt``).
    """
    materials = dict(_CORNELL_DEFAULT_MATERIALS)
    materials["floor"] = {"type": "glossy", "albedo": [0.35, 0.35, 0.4], "specular": [0.8, 0.8, 0.8],
                          "roughness": float(floor_roughness)}
    if albedo_checker:
        materials["back"] = {"type": "diffuse", "albedo": {"checker": [_WHITE, [0.3, 0.3, 0.55]], "scale": 4}}
    materials["large-box"] = {"type": "metal", "specular": [0.95, 0.93, 0.88], "roughness": float(sphere_roughness)}
    for k, v in materials.items():
        _check_material(k, v)
    if open_top and area_light:
        raise ValueError("glossy_cornell: open_top removes the ceiling light; use area_light=False")
    desc = {"name": "glossy_cornell", "area_light": bool(area_light), "materials": materials}
    if open_top:  # only present when set, so existing descriptions (and their cache hashes) are unchanged
        desc["open_top"] = True
    return desc


#: How jprt reads scene files (materials per pixel, two-sided surfaces' orientation, xatlas
#: charts: 3; analytic shapes tessellated, instances flattened, interior media kept: 4); part of
#: every file's description, so data cached under an older reading is not reused.
XML_READER = 4

#: Analytic shapes of scene files that ``xml`` replaces by triangle meshes (Mitsuba class names).
#: Rectangles stay analytic (``lightmap.mesh_triangles`` reads them as two triangles); cubes, obj,
#: ply and serialized shapes are meshes already.
TESSELLATED_SHAPES = ("Disk", "Sphere", "Cylinder")
#: Tessellation tolerance of analytic shapes: no chord strays from the true surface by more than
#: this fraction of the shape's radius (the sagitta r (1 - cos(pi / n)) of n segments per turn),
#: so a full turn has 71 segments and a sphere 36 rows, whatever the shape's size: at 1e-3 of the
#: radius the facets lie far inside a lightmap texel of any atlas that gives the shape a few
#: texels across (a texel is r / 2 or smaller; the surface error is 1/500 of it or less), and the
#: area is within 0.2 % (measured: sphere -0.16 %, disk -0.13 %, cylinder -0.03 %).
TESSELLATION_SAGITTA = 1e-3


#: Openings ``xml`` can cut into a file's geometry, so that an environment map lights an interior.
OPENINGS = ("", "ceiling")
#: The ceiling opening removes what lies within this fraction of the scene's height of its top.
CEILING_SLAB = 0.02


def xml(path: str, *, keep_emitters: bool = True, opening: str = "") -> dict:
    """Description of a Mitsuba XML scene file (content-hashed, so an edited file re-renders; with
    ``XML_READER``, so a changed reading does too).

    Args:
      keep_emitters: keep the file's own emitters (False: only jprt's lighting lights it).
      opening: "" (the file as it is) or "ceiling": every surface within ``CEILING_SLAB`` of the
        scene's height of its top, facing up or down, is removed (whole shapes, or a mesh's
        triangles), so that an environment map lights an interior from above as through a
        skylight. "Up" is the file camera's up axis (y without a camera).
    """
    path = os.path.abspath(path)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"scene file not found: {path}")
    if opening not in OPENINGS:
        raise ValueError(f"unknown scene opening {opening!r}: use one of {list(OPENINGS)}")
    with open(path, "rb") as f:
        content = f.read()
    digest = hashlib.sha256(content).hexdigest()
    desc = {"name": "xml", "path": path, "sha256": digest, "keep_emitters": bool(keep_emitters), "reader": XML_READER}
    if opening:  # only present when set, so descriptions without one (and their cache hashes) are unchanged
        desc["opening"] = opening
    if re.search(rb"<medium\b", content):  # the file defines a medium: renders use volpath (datasets record it)
        desc["media"] = True
    return desc


_ROOM_MATERIALS = {
    "floor": {"type": "diffuse", "albedo": [0.6, 0.6, 0.6]},
    "back": {"type": "diffuse", "albedo": [0.7, 0.7, 0.7]},
    "side": {"type": "diffuse", "albedo": [0.65, 0.12, 0.1]},
}


def asset_room(mesh: str, *, albedo=(0.75, 0.6, 0.45), margin: float = 1.0, size: float = 3.0,
               walls: bool = True) -> dict:
    """A mesh asset (object ``"asset"``, diffuse ``albedo``) standing on a grey floor in the corner
    of two walls (a light grey back wall and a red side wall), open to the front and the sky.

    The floor is placed at the bottom of the mesh's bounding box; the walls stand ``margin`` away
    from it and the floor and walls extend ``size`` past the asset. Open sides let distant lights
    (directional, environment maps) reach the asset, so classic PRT baselines apply to it too.
    """
    path = os.path.abspath(mesh)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"mesh not found: {path}")
    if not path.lower().endswith((".obj", ".ply")):
        raise ValueError(f"asset mesh must be .obj or .ply, got {path}")
    with open(path, "rb") as f:
        digest = hashlib.sha256(f.read()).hexdigest()
    albedo = [float(a) for a in np.broadcast_to(np.asarray(albedo, np.float64), (3,))]
    if not all(0.0 <= a <= 1.0 for a in albedo):
        raise ValueError(f"asset albedo must lie in [0, 1], got {albedo}")
    if margin <= 0 or size <= 0:
        raise ValueError(f"margin and size must be positive, got {margin} and {size}")
    return {"name": "asset_room", "mesh": path, "sha256": digest, "albedo": albedo, "margin": float(margin),
            "size": float(size), "walls": bool(walls)}


#: Default albedo of block layouts: floor, ceiling and a palette the side walls cycle through.
BLOCK_ALBEDO = {"floor": [0.6, 0.6, 0.6], "ceiling": [0.75, 0.75, 0.75],
                "walls": [[0.7, 0.7, 0.7], [0.75, 0.45, 0.35], [0.4, 0.6, 0.75], [0.65, 0.7, 0.45]]}
#: Each block's faces sit this fraction of its size inside its cube, so the back-to-back walls of
#: two unconnected neighbours never coincide (no z-fighting, no light through a shared plane).
BLOCK_INSET = 5e-4


def blocks(layout, *, size: float = 1.0, albedo: dict | None = None) -> dict:
    """A layout of cube blocks (``jprt.layouts.Layout`` or its ``as_dict``) as one scene: every
    block's floor, ceiling and walls are one-sided diffuse rectangles facing into the block (a
    missing side is an opening onto its connected neighbour), ``size`` the edge of a block in
    world units (cell (i, j) spans x in [i, i + 1] size, z in [j, j + 1] size, y in [0, size]).
    No emitters: the lighting is jprt's."""
    from jprt.layouts import layout_from_dict

    lay = layout_from_dict(layout)
    alb = copy.deepcopy(BLOCK_ALBEDO if albedo is None else albedo)
    if set(alb) != {"floor", "ceiling", "walls"}:
        raise ValueError(f"blocks albedo has keys floor, ceiling, walls (a palette), got {sorted(alb)}")
    for key in ("floor", "ceiling"):
        alb[key] = [float(c) for c in np.broadcast_to(np.asarray(alb[key], np.float64), (3,))]
    alb["walls"] = np.asarray(alb["walls"], np.float64).reshape(-1, 3).tolist()
    for v in [alb["floor"], alb["ceiling"], *alb["walls"]]:
        if not all(0.0 <= c < 1.0 for c in v):
            raise ValueError(f"blocks albedo values lie in [0, 1), got {v}")
    if not float(size) > 0:
        raise ValueError(f"blocks size must be positive, got {size}")
    return {"name": "blocks", "layout": lay.as_dict(), "size": float(size), "albedo": alb}


def describe(scene: dict | str) -> dict:
    """Normalise a scene given as a description dict or a name ("cornell_box", "glossy_cornell",
    or a path to an .xml file) into a full description."""
    if isinstance(scene, str):
        if scene == "empty":
            return empty()
        if scene == "cornell_box":
            return cornell_box()
        if scene == "glossy_cornell":
            return glossy_cornell()
        if scene.endswith(".xml"):
            return xml(scene)
        raise ValueError(f"unknown scene {scene!r}: use 'empty', 'cornell_box', 'glossy_cornell' or an .xml path")
    name = scene.get("name")
    kwargs = {k: v for k, v in scene.items() if k != "name"}
    if name == "empty":
        return empty()
    if name == "cornell_box":
        return cornell_box(**kwargs)
    if name == "glossy_cornell":
        if "materials" in kwargs:  # already a full description
            unknown = set(kwargs) - {"area_light", "materials", "open_top"}
            if unknown or set(kwargs["materials"]) != set(CORNELL_OBJECTS):
                raise ValueError(f"malformed glossy_cornell description (keys {sorted(kwargs)})")
            for k, v in kwargs["materials"].items():
                _check_material(k, v)
            desc = {"name": name, "area_light": bool(kwargs.get("area_light", False)),
                    "materials": dict(kwargs["materials"])}
            if kwargs.get("open_top"):
                desc["open_top"] = True
            return desc
        return glossy_cornell(**kwargs)
    if name == "xml":
        if not scene.get("path"):
            raise ValueError("an xml scene needs its file: set scene.path (e.g. --set scene.path=/abs/scene.xml)")
        return xml(scene["path"], keep_emitters=scene.get("keep_emitters", True), opening=scene.get("opening", ""))
    if name == "asset_room":
        kwargs.pop("sha256", None)
        return asset_room(**kwargs)
    if name == "blocks":
        return blocks(**kwargs)
    raise ValueError(f"unknown scene name {name!r}: use 'empty', 'cornell_box', 'glossy_cornell', 'xml', "
                     "'asset_room' or 'blocks'")


# --------------------------------------------------------------------------------------------
# Building Mitsuba objects


def _rgb(value) -> dict:
    value = np.broadcast_to(np.asarray(value, np.float64), (3,))
    return {"type": "rgb", "value": [float(c) for c in value]}


def _albedo_texture(albedo, mi) -> dict:
    if isinstance(albedo, dict):
        if "checker" in albedo:
            c0, c1 = albedo["checker"]
            scale = float(albedo.get("scale", 4))
            return {"type": "checkerboard", "color0": _rgb(c0), "color1": _rgb(c1),
                    "to_uv": mi.ScalarTransform3f().scale([scale, scale])}
        if "texture" in albedo:
            path = albedo["texture"]
            if not os.path.isfile(path):
                raise FileNotFoundError(f"albedo texture not found: {path}")
            return {"type": "bitmap", "filename": path}
        raise ValueError(f"albedo must be an RGB triple, {{'checker': ...}} or {{'texture': path}}, got {albedo!r}")
    return _rgb(albedo)


def _bsdf_dict(material: dict, mi) -> dict:
    kind = material["type"]
    if kind == "diffuse":
        return {"type": "diffuse", "reflectance": _albedo_texture(material["albedo"], mi)}
    if kind == "glossy":
        return {"type": "roughplastic", "distribution": "ggx", "alpha": float(material["roughness"]),
                "diffuse_reflectance": _albedo_texture(material["albedo"], mi),
                "specular_reflectance": _rgb(material.get("specular", [1.0, 1.0, 1.0])), "nonlinear": False}
    if kind == "metal":
        return {"type": "roughconductor", "distribution": "ggx", "alpha": float(material["roughness"]),
                "material": "none", "specular_reflectance": _rgb(material.get("specular", [1.0, 1.0, 1.0]))}
    raise ValueError(f"unknown material type {kind!r}")


def _base_dict(desc: dict, mi, tessellated: set | None = None) -> dict:
    """Scene dict without sensor, integrator or jprt lights; ``tessellated`` (when given) receives
    the names of the meshes made from a file's analytic shapes."""
    name = desc["name"]
    if name == "empty":
        return {"type": "scene"}
    if name in ("cornell_box", "glossy_cornell"):
        base = mi.cornell_box()
        for key in ("integrator", "sensor", "white", "green", "red"):
            base.pop(key, None)
        for obj in CORNELL_OBJECTS:
            base[obj] = dict(base[obj])
            base[obj]["bsdf"] = _bsdf_dict(desc["materials"][obj], mi)
        if name == "glossy_cornell":
            base["large-box"] = {"type": "sphere", "center": [0.33, -0.6, 0.1], "radius": 0.4,
                                 "bsdf": base["large-box"]["bsdf"]}
        if desc["area_light"]:
            base["light"] = dict(base["light"], bsdf=_bsdf_dict({"type": "diffuse", "albedo": _WHITE}, mi))
        else:
            base.pop("light")  # its quad sits just below the ceiling; without emission it only casts slivers
        if desc.get("open_top"):
            base.pop("ceiling")
        return base
    if name == "asset_room":
        return _asset_room_dict(desc, mi)
    if name == "blocks":
        return _blocks_dict(desc, mi)
    if name == "xml":
        loaded = mi.load_file(desc["path"], optimize=False)
        _check_file_scene(loaded, desc["path"], mi)
        base = {"type": "scene"}
        groups = _instance_groups(loaded, desc["path"], mi)
        made = set() if tessellated is None else tessellated
        for k, shape in enumerate(loaded.shapes()):
            if shape.emitter() is not None and not desc["keep_emitters"]:
                continue
            name = shape.id()
            key = name if name and name not in base else f"shape_{k:04d}"
            if shape.class_name() == "Instance":
                for member, analytic in _flatten_instance(shape, key, groups[k], base, mi):
                    base[member.id()] = member
                    if analytic:
                        made.add(member.id())
            elif shape.class_name() in TESSELLATED_SHAPES:
                base[key] = _new_mesh(key, _shape_arrays(shape, mi), shape, mi)
                made.add(key)
            else:
                base[key] = shape
        if desc["keep_emitters"]:
            for k, emitter in enumerate(loaded.emitters()):
                if not mi.has_flag(emitter.flags(), mi.EmitterFlags.Surface):  # area lights come with their shapes
                    base[f"emitter_{k:04d}"] = emitter
        if desc.get("opening") == "ceiling":
            up = _up_axis(loaded.sensors()[0] if loaded.sensors() else None, mi)
            surfaces = {k: v for k, v in base.items() if isinstance(v, mi.Shape) and v.emitter() is None}
            removed, shortened = _cut_ceiling(surfaces, up, mi)
            base = {k: v for k, v in base.items() if k not in removed}
            base.update(shortened)
        if loaded.sensors():
            base["jprt_sensor"] = loaded.sensors()[0]
        return base
    raise ValueError(f"unknown scene name {name!r}")


def _free_key(taken, name: str) -> str:
    """``name``, or ``name#2``, ``name#3``, ... when ``taken`` (a dict or set) holds it already."""
    key, k = name, 1
    while key in taken:
        k += 1
        key = f"{name}#{k}"
    return key


def _turn_segments(angle: float) -> int:
    """Segments of an arc of ``angle`` radians at ``TESSELLATION_SAGITTA`` (at least 3 per turn)."""
    step = 2.0 * np.arccos(1.0 - TESSELLATION_SAGITTA)
    return max(int(np.ceil(angle / step - 1e-9)), 3 if angle > np.pi else 2)


def _local_tessellation(kind: str):
    """A Mitsuba analytic shape in its object space, as (positions (V, 3), outward unit normals
    (V, 3), Mitsuba's own UVs (V, 2), faces (F, 3) wound counter-clockwise seen from outside).

    Object spaces and UVs are Mitsuba's (``sphere``: the unit sphere, uv = (phi / 2 pi, theta / pi)
    with theta from +z; ``disk``: the unit disk in z = 0 facing +z, uv = (r, phi / 2 pi);
    ``cylinder``: radius 1 about z in [0, 1], no caps, uv = (phi / 2 pi, z)), so textures map as on
    the analytic shape. The seam (phi = 0 = 2 pi) has two columns of vertices (u = 0 and 1), and a
    pole or centre one vertex per segment (at the segment's middle u), so the UVs never wrap."""
    n = _turn_segments(2.0 * np.pi)
    j = np.arange(n + 1)
    phi = 2.0 * np.pi * j / n
    if kind == "Sphere":
        rows = _turn_segments(np.pi)
        i = np.arange(rows + 1)
        th, ph = np.meshgrid(np.pi * i / rows, phi, indexing="ij")  # (rows + 1, n + 1)
        pos = np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], -1).reshape(-1, 3)
        pos[np.abs(pos) < 1e-15] = 0.0
        u = np.broadcast_to(j / n, th.shape).copy()
        u[0, :n] = u[-1, :n] = (j[:n] + 0.5) / n  # poles: the middle of their segment
        uv = np.stack([u, th / np.pi], -1).reshape(-1, 2)
        vid = (i[:, None] * (n + 1) + j[None, :])
        a, b, c, d = vid[:-1, :-1], vid[1:, :-1], vid[:-1, 1:], vid[1:, 1:]  # (theta, phi) corners
        faces = [np.stack([a[0], b[0], d[0]], -1)]  # the north cap: one triangle per segment
        if rows > 2:
            mid = (slice(1, rows - 1), slice(None))
            faces.append(np.stack([a[mid], b[mid], c[mid]], -1).reshape(-1, 3))
            faces.append(np.stack([b[mid], d[mid], c[mid]], -1).reshape(-1, 3))
        faces.append(np.stack([a[-1], b[-1], c[-1]], -1))  # the south cap
        return pos, pos.copy(), uv, np.concatenate(faces).astype(np.int64)
    if kind == "Disk":
        rim = np.stack([np.cos(phi), np.sin(phi), np.zeros_like(phi)], -1)
        pos = np.concatenate([rim, np.zeros((n, 3))])
        uv = np.concatenate([np.stack([np.ones(n + 1), j / n], -1), np.stack([np.zeros(n), (j[:n] + 0.5) / n], -1)])
        faces = np.stack([n + 1 + j[:n], j[:n], j[:n] + 1], -1)
        nrm = np.broadcast_to([0.0, 0.0, 1.0], pos.shape).copy()
        return pos, nrm, uv, faces.astype(np.int64)
    if kind == "Cylinder":
        ring = np.stack([np.cos(phi), np.sin(phi), np.zeros_like(phi)], -1)
        ring[np.abs(ring) < 1e-15] = 0.0
        pos = np.concatenate([ring, ring + [0.0, 0.0, 1.0]])
        uv = np.concatenate([np.stack([j / n, np.zeros(n + 1)], -1), np.stack([j / n, np.ones(n + 1)], -1)])
        lo, hi = j[:n], j[:n] + n + 1
        faces = np.concatenate([np.stack([lo, lo + 1, hi], -1), np.stack([lo + 1, hi + 1, hi], -1)])
        return pos, np.concatenate([ring, ring]), uv, faces.astype(np.int64)
    raise ValueError(f"no tessellation for Mitsuba shape class {kind!r}")


def _transformed(arrays: tuple, m: np.ndarray) -> tuple:
    """Mesh arrays (positions, normals or None, uvs or None, faces) moved by the 4 x 4 affine
    ``m``: normals by its inverse transpose, and the winding reversed where ``m`` mirrors, so
    faces keep facing the side their normals point to."""
    pos, nrm, uv, faces = arrays
    pos = pos @ m[:3, :3].T + m[:3, 3]
    if nrm is not None:
        nrm = nrm @ np.linalg.inv(m[:3, :3])
        nrm = nrm / np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-30)
    if np.linalg.det(m[:3, :3]) < 0:
        faces = faces[:, ::-1]
    return pos, nrm, uv, faces


def _shape_arrays(shape, mi) -> tuple:
    """World-space (positions (V, 3), vertex normals (V, 3) or None, UVs (V, 2) or None, faces
    (F, 3)) of a shape of a scene file: a mesh's own buffers, a rectangle's two triangles, an
    analytic shape's tessellation (``_local_tessellation`` at ``TESSELLATION_SAGITTA``) moved by
    its ``to_world``; anything else (curves, SDF grids, ellipsoids) is refused in one line."""
    params = mi.traverse(shape)
    keys = set(params.keys())
    kind = shape.class_name()
    if "vertex_positions" in keys:
        pos = np.array(params["vertex_positions"], np.float64).reshape(-1, 3)
        faces = np.array(params["faces"], np.int64).reshape(-1, 3)
        nrm = uv = None
        if "vertex_normals" in keys and not shape.has_face_normals():
            nrm = np.array(params["vertex_normals"], np.float64).reshape(-1, 3)
        if "vertex_texcoords" in keys:
            uv = np.array(params["vertex_texcoords"], np.float64).reshape(-1, 2)
        return pos, nrm, (uv if uv is not None and uv.shape[0] == pos.shape[0] else None), faces
    if kind == "Rectangle" or kind in TESSELLATED_SHAPES:
        m = np.array(params["to_world"].matrix, np.float64).reshape(4, 4)
        if kind == "Rectangle":
            local = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], np.float64)
            arrays = (local, np.broadcast_to([0.0, 0.0, 1.0], (4, 3)).copy(), (local[:, :2] + 1.0) / 2.0,
                      np.array([[0, 1, 2], [0, 2, 3]], np.int64))
        else:
            arrays = _local_tessellation(kind)
        pos, nrm, uv, faces = _transformed(arrays, m)
        if kind == "Cylinder" and np.linalg.det(m[:3, :3]) < 0:
            # Mitsuba's cylinder takes its normal from the cross product of its tangents, which a
            # mirroring to_world turns inwards (spheres and disks keep theirs): so do the facets
            nrm, faces = -nrm, faces[:, ::-1]
        return pos, nrm, uv, faces
    raise ValueError(f"shape {shape.id() or '(unnamed)'!r}: Mitsuba {kind} shapes are not supported (jprt reads "
                     f"triangle meshes, rectangles, disks, spheres, cylinders, cubes and instances of shape groups)")


def _area_light_copy(emitter, mi):
    """A new area light with the radiance texture and sampling weight of ``emitter`` (a Mitsuba
    emitter belongs to one shape: the mesh that replaces an analytic shape needs its own)."""
    if emitter.class_name() != "AreaLight":
        raise ValueError(f"shape emitter {emitter.class_name()} is not supported (jprt reads 'area' emitters)")
    radiance = dict(_children(emitter, mi)).get("radiance")
    if not isinstance(radiance, mi.Texture):
        raise ValueError("an area emitter without a radiance texture cannot be copied")
    params = mi.traverse(emitter)
    d = {"type": "area", "radiance": radiance}
    if "sampling_weight" in params.keys():
        d["sampling_weight"] = float(np.ravel(params["sampling_weight"])[0])
    return mi.load_dict(d)


def _new_mesh(name: str, arrays: tuple, like, mi):
    """A Mitsuba triangle mesh ``name`` of ``arrays`` (``_shape_arrays``) with the BSDF, area
    emitter, interior and exterior media and normal flip of the shape ``like``; smooth shading
    where there are vertex normals."""
    pos, nrm, uv, faces = arrays
    props = mi.Properties()
    if like.bsdf() is not None:
        props["bsdf"] = like.bsdf()
    if like.emitter() is not None:
        props["emitter"] = _area_light_copy(like.emitter(), mi)
    for side, medium in (("interior", like.interior_medium()), ("exterior", like.exterior_medium())):
        if medium is not None:
            props[side] = medium
    props["face_normals"] = nrm is None
    props["flip_normals"] = bool(like.has_flipped_normals())
    mesh = mi.Mesh(name, int(pos.shape[0]), int(faces.shape[0]), props=props, has_vertex_normals=nrm is not None,
                   has_vertex_texcoords=uv is not None)
    mesh.set_id(name)
    out = mi.traverse(mesh)
    out["vertex_positions"] = mi.Float(pos.astype(np.float32).ravel())
    out["faces"] = mi.UInt32(faces.astype(np.uint32).ravel())
    if nrm is not None:
        out["vertex_normals"] = mi.Float(nrm.astype(np.float32).ravel())
    if uv is not None:
        out["vertex_texcoords"] = mi.Float(uv.astype(np.float32).ravel())
    out.update()
    return mesh


def _children(obj, mi) -> list:
    """[(name, child object)] of a Mitsuba object in traversal order."""

    class Collect(mi.TraversalCallback):
        def __init__(self):
            super().__init__()
            self.found = []

        def put(self, name, value, *args):
            self.found.append((name, value))

    cb = Collect()
    obj.traverse(cb)
    return cb.found


def _ref_id(ref) -> str:
    return ref.id() if callable(ref.id) else ref.id


def _instance_groups(loaded, path: str, mi) -> dict:
    """{index in ``loaded.shapes()``: the ``shapegroup`` shape it instances} for every instance of
    a loaded scene file. Mitsuba's Python API does not say which group an instance shows, so the
    file is parsed again (``mitsuba.parser``) for each instance's reference, matched to the loaded
    instance by id and ``to_world`` (in file order)."""
    shapes = list(loaded.shapes())
    wanted = [k for k, s in enumerate(shapes) if s.class_name() == "Instance"]
    if not wanted:
        return {}
    groups = {v.id(): v for _, v in _children(loaded, mi)
              if isinstance(v, mi.Shape) and v.class_name() == "ShapeGroupPlugin"}
    state = mi.parser.parse_file(mi.parser.ParserConfig(mi.variant()), path)
    nodes = []
    for node in state.nodes:
        props = node.props
        if props.plugin_name() != "instance":
            continue
        refs = [_ref_id(props[k]) for k in props.keys() if type(props[k]).__name__ == "Reference"]
        m = np.array(props["to_world"].matrix, np.float64).reshape(4, 4) if "to_world" in props.keys() else np.eye(4)
        nodes.append((props.id(), refs[0] if refs else None, m))
    out, used = {}, set()
    for k in wanted:
        inst = shapes[k]
        m = np.array(mi.traverse(inst)["to_world"].matrix, np.float64).reshape(4, 4)
        match = next((i for i, (node_id, _, node_m) in enumerate(nodes) if i not in used and node_id == inst.id()
                      and np.allclose(node_m, m, rtol=1e-5, atol=1e-5 * max(1.0, float(np.abs(m).max())))), None)
        if match is None or nodes[match][1] not in groups:
            raise ValueError(f"{os.path.basename(path)}: cannot tell which shape group instance "
                             f"{inst.id() or '(unnamed)'!r} shows (jprt flattens instances into meshes)")
        used.add(match)
        out[k] = groups[nodes[match][1]]
    return out


def _flatten_instance(instance, key: str, group, taken, mi) -> list:
    """World-space meshes of one instance of a shape group, as [(mesh, made from an analytic
    shape)]: one per member, named
    ``"<instance key>/<member id>"`` (``member<j>`` for an unnamed j-th member), each with its
    member's BSDF, media and normal flip (G-buffer object ids, atlases and materials are per
    object, so every instance gets its own copies); a name already in ``taken`` gets a suffix
    ``#2``, ``#3``, ..."""
    m = np.array(mi.traverse(instance)["to_world"].matrix, np.float64).reshape(4, 4)
    members = [v for _, v in _children(group, mi) if isinstance(v, mi.Shape)]
    if not members:
        raise ValueError(f"instance {key!r}: its shape group holds no shapes")
    out = []
    for j, member in enumerate(members):
        name = _free_key(set(taken) | {m.id() for m, _ in out}, f"{key}/{member.id() or f'member{j}'}")
        if member.emitter() is not None:
            raise ValueError(f"instance {key!r}: member {name!r} is an emitter (Mitsuba does not instance emitters)")
        mesh = _new_mesh(name, _transformed(_shape_arrays(member, mi), m), member, mi)
        out.append((mesh, member.class_name() in TESSELLATED_SHAPES))
    return out


def _up_axis(sensor, mi) -> int:
    """The world axis nearest a sensor's up vector (1, y, without a sensor)."""
    if sensor is None:
        return 1
    to_world = np.array(mi.traverse(sensor)["to_world"].matrix, np.float64).reshape(4, 4)
    return int(np.argmax(np.abs(to_world[:3, 1])))


def _cut_ceiling(shapes: dict, up: int, mi) -> tuple[list[str], dict]:
    """The ceiling opening of ``xml``: what to remove from ``shapes`` ({key: Mitsuba shape}) and
    what replaces it, as (keys removed, {key: shortened mesh}).

    The slab is the top ``CEILING_SLAB`` of the shapes' joint bounds along axis ``up``. A shape
    inside the slab is removed whole; a mesh reaching into it loses the triangles whose vertices
    all lie in the slab and whose face normal is within 25 degrees of the up axis (the ceiling,
    not a wall's top row), keeping its BSDF, media, id, normals and UVs. "Top" is the largest coordinate.
    """
    boxes = {k: (np.array(s.bbox().min, np.float64), np.array(s.bbox().max, np.float64)) for k, s in shapes.items()}
    lo = min(b[0][up] for b in boxes.values())
    hi = max(b[1][up] for b in boxes.values())
    top = hi - CEILING_SLAB * (hi - lo)
    removed, shortened = [], {}
    for key, shape in shapes.items():
        b_lo, b_hi = boxes[key]
        if b_lo[up] >= top:
            removed.append(key)
            continue
        if b_hi[up] < top or not isinstance(shape, mi.Mesh):
            continue
        v = np.array(shape.vertex_positions_buffer(), np.float64).reshape(-1, 3)
        f = np.array(shape.faces_buffer(), np.int64).reshape(-1, 3)
        tri = v[f]
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        vertical = np.abs(n[:, up]) > np.cos(np.radians(25.0)) * np.maximum(np.linalg.norm(n, axis=1), 1e-30)
        cut = (tri[:, :, up].min(axis=1) >= top) & vertical
        if not cut.any():
            continue
        removed.append(key)
        if cut.all():
            continue
        props = mi.Properties()
        props["bsdf"] = shape.bsdf()
        for side, medium in (("interior", shape.interior_medium()), ("exterior", shape.exterior_medium())):
            if medium is not None:
                props[side] = medium
        props["face_normals"] = bool(shape.has_face_normals())
        props["flip_normals"] = bool(shape.has_flipped_normals())
        mesh = mi.Mesh(shape.id() or key, int(v.shape[0]), int((~cut).sum()), props=props,
                       has_vertex_normals=bool(shape.has_vertex_normals()),
                       has_vertex_texcoords=bool(shape.has_vertex_texcoords()))
        out = mi.traverse(mesh)
        out["vertex_positions"] = shape.vertex_positions_buffer()
        out["faces"] = mi.UInt32(f[~cut].ravel().astype(np.uint32))
        if shape.has_vertex_normals():
            out["vertex_normals"] = shape.vertex_normals_buffer()
        if shape.has_vertex_texcoords():
            out["vertex_texcoords"] = shape.vertex_texcoords_buffer()
        out.update()
        shortened[key] = mesh
    return removed, shortened


#: Integrators of a scene file that do not estimate the radiance jprt renders its ground truth
#: with (Mitsuba class name -> plugin name); refused. Any other (path, volpath, volpathmis, bdpt,
#: ptracer, prb, ...) is unbiased for the same radiance on surfaces: the file's choice changes the
#: noise, not the expectation, so jprt's own ``path`` renders (``volpath`` where the scene has
#: media) stand in for it.
REFUSED_INTEGRATORS = {"AOVIntegrator": "aov", "DepthIntegrator": "depth", "DirectIntegrator": "direct",
                       "MomentIntegrator": "moment", "StokesIntegrator": "stokes"}


def _check_file_scene(loaded, path: str, mi) -> None:
    """Refuse, in one line naming them, what jprt's ground truth cannot honour in a scene file: a
    medium that fills the camera's space (a sensor inside a medium: fog around the viewer; jprt's
    own cameras start their rays in vacuum) and an integrator that does not estimate radiance (aov,
    depth, moment, ...). Media inside or outside surfaces (a glass's ``interior`` medium) are
    kept: scenes with them render with Mitsuba's ``volpath`` (``SceneHandle.has_media``)."""
    fogged = [sensor.id() or f"sensor {k}" for k, sensor in enumerate(loaded.sensors())
              if sensor.get_medium() is not None]
    if fogged:
        raise ValueError(f"{os.path.basename(path)}: media that fill the camera's space are not supported "
                         f"({', '.join(fogged)} inside a medium; jprt's cameras start in vacuum); keep media "
                         f"inside surfaces (a shape's interior) or remove the sensor's medium")
    integrator = loaded.integrator()
    kind = REFUSED_INTEGRATORS.get(integrator.class_name()) if integrator is not None else None
    if kind is not None:
        raise ValueError(f"{os.path.basename(path)}: integrator {kind!r} does not estimate the full radiance jprt "
                         f"renders ground truth for (with 'path'); use path, volpath or bdpt in the file")


def _asset_room_dict(desc: dict, mi) -> dict:
    kind = "obj" if desc["mesh"].lower().endswith(".obj") else "ply"
    asset = {"type": kind, "filename": desc["mesh"], "face_normals": False,
             "bsdf": _bsdf_dict({"type": "diffuse", "albedo": desc["albedo"]}, mi)}
    box = mi.load_dict(asset).bbox()
    lo, hi = np.array(box.min, np.float64), np.array(box.max, np.float64)
    base = {"type": "scene", "asset": asset}
    if not desc["walls"]:
        return base
    m, s = desc["margin"], desc["size"]
    x0, z0, y0 = lo[0] - m, lo[2] - m, lo[1]
    x1, z1, y1 = hi[0] + s, hi[2] + s, hi[1] + s
    T = mi.ScalarTransform4f

    def quad(center, scale, rotate_axis, angle):
        return T().translate([float(c) for c in center]) @ T().rotate(rotate_axis, angle) @ T().scale(
            [float(c) for c in scale])

    walls = {
        # rectangles span [-1, 1]^2 in xy with normal +z: rotate so normals face the asset
        "floor": quad([(x0 + x1) / 2, y0, (z0 + z1) / 2], [(x1 - x0) / 2, (z1 - z0) / 2, 1], [1, 0, 0], -90),
        "back": quad([(x0 + x1) / 2, (y0 + y1) / 2, z0], [(x1 - x0) / 2, (y1 - y0) / 2, 1], [0, 1, 0], 0),
        "side": quad([x0, (y0 + y1) / 2, (z0 + z1) / 2], [(z1 - z0) / 2, (y1 - y0) / 2, 1], [0, 1, 0], 90),
    }
    for key, to_world in walls.items():
        base[key] = {"type": "rectangle", "to_world": to_world, "bsdf": _bsdf_dict(_ROOM_MATERIALS[key], mi)}
    return base


def _blocks_dict(desc: dict, mi) -> dict:
    from jprt import layouts

    lay = layouts.layout_from_dict(desc["layout"])
    size = float(desc["size"])
    alb = desc["albedo"]
    T = mi.ScalarTransform4f
    base = {"type": "scene"}
    shrink = 1.0 - 2.0 * BLOCK_INSET
    for b, blk in enumerate(lay.blocks):
        offset = np.array([blk.cell[0], 0.0, blk.cell[1]])
        for f in range(6):
            if f >= 2 and f - 2 in blk.open_sides:
                continue
            colour = (alb["floor"] if f == 0 else alb["ceiling"] if f == 1
                      else alb["walls"][(b + f - 2) % len(alb["walls"])])
            centre = (offset + 0.5 + shrink * (layouts.FACE_ORIGINS[f] + 0.5 * layouts.FACE_U[f]
                                                + 0.5 * layouts.FACE_V[f] - 0.5)) * size
            m = np.eye(4)
            m[:3, 0] = layouts.FACE_U[f] * 0.5 * shrink * size
            m[:3, 1] = layouts.FACE_V[f] * 0.5 * shrink * size
            m[:3, 2] = layouts.FACE_NORMALS[f]  # the rectangle's +z normal faces into the block
            m[:3, 3] = centre
            base[f"block{b:03d}_{layouts.FACE_NAMES[f]}"] = {
                "type": "rectangle", "to_world": T(m.tolist()),
                "bsdf": _bsdf_dict({"type": "diffuse", "albedo": colour}, mi)}
    return base


_EMITTER_KIND = {PointLights: "point", SpotLights: "spot", DirectionalLights: "directional"}


def _emitter(lighting, k: int, mi) -> dict:
    """Mitsuba emitter dict of light ``k`` of point, spot or directional ``lighting``."""
    if isinstance(lighting, PointLights):
        return {"type": "point", "position": [float(c) for c in lighting.position[k]],
                "intensity": _rgb(lighting.intensity[k])}
    if isinstance(lighting, SpotLights):
        return {"type": "spot", "to_world": _spot_to_world(lighting.position[k], lighting.target[k], mi),
                "intensity": _rgb(lighting.intensity[k]), "cutoff_angle": float(lighting.cutoff_deg[k]),
                "beam_width": float(lighting.beam_deg[k])}
    return {"type": "directional", "direction": [float(c) for c in lighting.direction[k]],
            "irradiance": _rgb(lighting.irradiance[k])}


def _lighting_dict(lighting: Lighting, mi) -> dict:
    if lighting is None:
        return {}
    if type(lighting) in _EMITTER_KIND:
        return {f"jprt_{_EMITTER_KIND[type(lighting)]}_{k}": _emitter(lighting, k, mi) for k in range(lighting.count)}
    if isinstance(lighting, EnvMap):
        return {"jprt_envmap": {"type": "envmap", "bitmap": mi.Bitmap(to_mitsuba_envmap(lighting.radiance))}}
    raise TypeError(f"unknown lighting type {type(lighting).__name__}")


def _spot_to_world(position, target, mi):
    """Mitsuba spot frame: +z along the axis from ``position`` to ``target``."""
    axis = np.asarray(target, np.float64) - np.asarray(position, np.float64)
    axis /= np.linalg.norm(axis)
    up = [0.0, 1.0, 0.0] if abs(axis[1]) < 0.99 else [1.0, 0.0, 0.0]
    return mi.ScalarTransform4f().look_at(origin=[float(c) for c in position], target=[float(c) for c in target], up=up)


def _directional_to_world(direction, mi):
    """Mitsuba directional frame: +z along the travel direction."""
    d = np.asarray(direction, np.float64)
    up = [0.0, 1.0, 0.0] if abs(d[1]) < 0.99 else [1.0, 0.0, 0.0]
    return mi.ScalarTransform4f().look_at(origin=[0.0, 0.0, 0.0], target=[float(c) for c in d], up=up)


def _lighting_layout(lighting: Lighting) -> Any:
    if lighting is None:
        return None
    if isinstance(lighting, PointLights):
        return ("point", lighting.count)
    if isinstance(lighting, SpotLights):
        # cone angles are baked into the emitter at construction: a change rebuilds
        return ("spot", lighting.count, lighting.cutoff_deg.tobytes(), lighting.beam_deg.tobytes())
    if isinstance(lighting, DirectionalLights):
        return ("directional", lighting.count)
    return ("envmap", tuple(lighting.radiance.shape))


class SceneHandle:
    """A built Mitsuba scene with swappable jprt lighting.

    >>> handle = SceneHandle(cornell_box(area_light=False))
    >>> handle.set_lighting(PointLights.create([0, 0.8, 0], [5, 5, 5]))

    ``set_lighting`` writes emitter parameters (positions, intensities, the halo-padded envmap
    array) when the layout (kind and count of lights, map shape) is unchanged, and rebuilds the
    scene otherwise. ``builds`` counts rebuilds (tests use it).
    ``has_media``: some surface bounds a participating medium (renders then use ``volpath``).
    """

    def __init__(self, scene: dict | str, lighting: Lighting = None):
        self.description = describe(scene)
        self._mi = mitsuba()
        tessellated: set = set()
        self._base = _base_dict(self.description, self._mi, tessellated)
        #: Names of the objects jprt tessellated from a file's analytic shapes (disks, spheres,
        #: cylinders): their UVs are Mitsuba's polar / latitude-longitude ones, right for textures
        #: but stretched, so lightmap atlases unwrap them afresh (``lightmap.mesh_triangles``).
        self.tessellated = frozenset(tessellated)
        self.builds = 0
        self.lighting: Lighting = None
        self._layout: Any = "unbuilt"
        self.scene = None
        self.set_lighting(lighting)

    @property
    def mi(self):
        return self._mi

    @property
    def has_media(self) -> bool:
        """Some surface bounds a participating medium (a glass's interior): renders use Mitsuba's
        ``volpath`` instead of ``path`` (same ``max_depth`` meaning, so the direct / indirect split
        holds; ``jprt.render.images``)."""
        return self._has_media

    def _build(self, lighting: Lighting) -> None:
        d = copy.copy(self._base)
        d.update(_lighting_dict(lighting, self._mi))
        # optimize=False keeps one shape per object (merging would break object ids and materials).
        self.scene = self._mi.load_dict(d, optimize=False)
        self._has_media = any(s.interior_medium() is not None or s.exterior_medium() is not None
                              for s in self.scene.shapes())
        self.builds += 1
        self._layout = _lighting_layout(lighting)

    def set_lighting(self, lighting: Lighting) -> None:
        """Use ``lighting`` (PointLights, SpotLights, DirectionalLights, EnvMap, or None for the
        scene's own emitters)."""
        lighting = validate_lighting(lighting)
        layout = _lighting_layout(lighting)
        if layout != self._layout:
            self._build(lighting)
        elif lighting is not None:
            params = self._mi.traverse(self.scene)
            if isinstance(lighting, PointLights):
                for k in range(lighting.count):
                    params[f"jprt_point_{k}.position"] = self._mi.Point3f(*map(float, lighting.position[k]))
                    params[f"jprt_point_{k}.intensity.value"] = self._mi.Color3f(*map(float, lighting.intensity[k]))
            elif isinstance(lighting, SpotLights):
                for k in range(lighting.count):
                    params[f"jprt_spot_{k}.to_world"] = _spot_to_world(lighting.position[k], lighting.target[k], self._mi)
                    params[f"jprt_spot_{k}.intensity.value"] = self._mi.Color3f(*map(float, lighting.intensity[k]))
            elif isinstance(lighting, DirectionalLights):
                for k in range(lighting.count):
                    params[f"jprt_directional_{k}.to_world"] = _directional_to_world(lighting.direction[k], self._mi)
                    params[f"jprt_directional_{k}.irradiance.value"] = self._mi.Color3f(
                        *map(float, lighting.irradiance[k]))
            else:
                params["jprt_envmap.data"] = self._mi.TensorXf(mitsuba_envmap_data(lighting.radiance))
            params.update()
        self.lighting = lighting

    def default_camera(self, width: int | None = None, height: int | None = None):
        """The scene's own camera as a jprt ``Camera`` (the XML file's first sensor; the
        built-in Cornell box camera otherwise), at its film size unless ``width``/``height``."""
        from jprt.render.cameras import look_at

        sensors = self.scene.sensors()
        if self.description["name"] == "xml" and sensors:
            params = self._mi.traverse(sensors[0])
            to_world = np.array(params["to_world"].matrix, np.float64).reshape(4, 4)
            film_w, film_h = (int(v) for v in sensors[0].film().size())
            w, h = width or film_w, height or film_h
            x_fov = float(np.ravel(params["x_fov"])[0])
            fov = x_fov if w <= h else float(np.degrees(2 * np.arctan(np.tan(np.radians(x_fov) / 2) * h / w)))
            origin = to_world[:3, 3]
            return look_at(origin, origin + to_world[:3, 2], to_world[:3, 1], fov=fov, width=w, height=h)
        origin, target, fov = CORNELL_CAMERA
        return look_at(origin, target, fov=fov, width=width or 256, height=height or 256)

    def scene_dict(self) -> dict:
        """A copy of the scene's Mitsuba dict without sensor, integrator or jprt lights: callers
        add their own emitters and sensor to it. (``set_lighting`` builds on the same dict with a
        scene file's own camera kept as the scene's first sensor; here it is left out, since it
        would be the sensor a render of the dict uses.)"""
        return {k: v for k, v in self._base.items() if k != "jprt_sensor"}

    def shapes(self) -> list:
        """The scene's shapes in object-id order."""
        return list(self.scene.shapes())

    def object_names(self) -> list[str]:
        """Shape ids in object-id order (the ``object_id`` of the G-buffer indexes this list)."""
        return [s.id() for s in self.scene.shapes()]
