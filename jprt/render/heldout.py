"""Held-out views, lights and references of a scene file as a user brings it: what an
evaluation of any method on any Mitsuba scene needs, with nothing set per scene.

* ``turned_views``: the file's camera and views turned about it (never a training view);
* ``held_out_lights``: point lights in the scene's light region, with a held-out seed;
* ``specular_objects``: purely specular objects (scored apart: their indirect light is what
  they refract or mirror, a function of the view);
* ``references``: two independent reference sets along the pixel-centre rays, rendered until
  their own noise is small against the target (``reference_noise``), each batch a
  ``jprt.cache`` entry (``reference_batch``);
* ``lighting_setup``: one lighting set-up of a scene (handle, G-buffers, judged objects,
  references, their noise floor, Mitsuba's time for a reference frame).

The ``e`` arguments are the evaluation section of a config: ``resolution``, ``extra_views``,
``seed``, ``n_lights``, ``reference_spp``, ``reference_spp_max``, ``reference_noise``,
``target``, ``min_object_fraction``.
"""

from __future__ import annotations

import time

import numpy as np

from jprt import eval as jeval

__all__ = ["turned_views", "views_about", "held_out_lights", "specular_objects", "reference_batch", "references",
           "reference_noise", "pathtrace_ms", "face_counts", "lighting_setup"]


def turned_views(handle, e: dict) -> list:
    """The held-out views: the file's camera at ``eval.resolution``, then ``eval.extra_views``
    views drawn about it (``eval.seed``): the same origin (always free space) turned by a yaw of
    10-25 degrees either way about the camera's up axis and a pitch of up to 5 degrees. The
    methods' training views are drawn in a box about the camera with other seeds, so neither is
    a training view."""
    res = int(e["resolution"])
    first = handle.default_camera(res, res)
    return [first] + views_about(first, int(e["extra_views"]), int(e["seed"]))


def views_about(camera, n: int, seed: int, yaw_deg=(10.0, 25.0), pitch_deg: float = 5.0) -> list:
    """``n`` views from ``camera``'s origin (free space wherever the camera is), turned by a yaw of
    ``yaw_deg[0]``-``yaw_deg[1]`` degrees either way about its up axis and a pitch of up to
    ``pitch_deg`` degrees (drawn with ``seed``); same field of view and film size."""
    from jprt.render.cameras import look_at

    rng = np.random.default_rng([int(seed), 17])
    origin, up = np.asarray(camera.origin, np.float64), np.asarray(camera.up, np.float64)
    forward = np.asarray(camera.target, np.float64) - origin
    views = []
    for _ in range(int(n)):
        yaw = np.radians(rng.uniform(*yaw_deg)) * rng.choice([-1.0, 1.0])
        pitch = np.radians(rng.uniform(-pitch_deg, pitch_deg))
        d = _rotate(_rotate(forward, up, yaw), np.cross(forward, up), pitch)
        views.append(look_at(origin, origin + d, up, fov=camera.fov, width=camera.width, height=camera.height))
    return views


def _rotate(v, axis, angle: float) -> np.ndarray:
    """``v`` turned by ``angle`` (radians) about ``axis`` (Rodrigues)."""
    k = np.asarray(axis, np.float64) / np.linalg.norm(axis)
    v = np.asarray(v, np.float64)
    return v * np.cos(angle) + np.cross(k, v) * np.sin(angle) + k * np.dot(k, v) * (1.0 - np.cos(angle))


def held_out_lights(desc: dict, regions: dict, e: dict) -> list:
    """``eval.n_lights`` point lights drawn in the scene's light region with the held-out seed."""
    from jprt.inputs import PointLights
    from jprt.render.sampling import free_lights, latin_hypercube

    rng = np.random.default_rng(int(e["seed"]))
    positions = latin_hypercube(rng, int(e["n_lights"]), regions["light_lo"], regions["light_hi"])
    positions = free_lights(desc, positions, regions["light_lo"], regions["light_hi"], rng)
    return [PointLights.create([p], [1.0, 1.0, 1.0]) for p in positions]


def specular_objects(handle) -> list[str]:
    """Objects whose material is purely specular (smooth glass, mirror: delta lobes only, no
    diffuse or glossy part). Their indirect light is what they refract or mirror, a function of
    the view a surface-point radiance model cannot hold: the report scores them apart."""
    mi = handle.mi
    out = []
    for shape in handle.shapes():
        bsdf = shape.bsdf()
        if bsdf is None:
            continue
        flags = bsdf.flags()
        if mi.has_flag(flags, mi.BSDFFlags.Delta) and not mi.has_flag(flags, mi.BSDFFlags.Smooth):
            out.append(shape.id())
    return out


def reference_batch(desc, handle, camera, lighting, spp: int, seed: int) -> np.ndarray:
    """Mitsuba's indirect light along the camera's pixel-centre rays (``images.centre_rays``: a
    rendered image averages each pixel's footprint, which no per-pixel prediction can show) at
    ``spp`` and ``seed``, a ``jprt.cache`` entry (scene, camera, lighting, spp, seed)."""
    from jprt import cache
    from jprt.render.images import centre_rays
    from jprt.render.lights import lighting_description
    from jprt.render.scenes import describe

    spec = {"format": 2, "scene": describe(desc), "camera": camera._asdict(), "spp": int(spp), "seed": int(seed),
            "lighting": None if lighting is None else lighting_description(lighting)}

    def render():
        handle.set_lighting(lighting)
        return {"indirect": centre_rays(handle, camera, spp=int(spp), seed=int(seed)).indirect}

    return cache.cached("real_scenes_reference", spec, render)[0]["indirect"]


def references(desc, handle, camera, lightings, e, scored=None) -> tuple[list, list, list]:
    """Two independent reference sets of ``camera`` under each lighting (None: the file's
    emitters), each rendered until its own noise is small against the target.

    Each set starts at ``eval.reference_spp`` and doubles (a new batch of as many samples as it
    has, another seed, averaged in by sample count) until, for every object of ``scored`` (the
    G-buffer's object ids and names, objects to judge; None: the whole image), the two sets'
    difference says the reference's own relative noise (difference / sqrt 2) is at most
    ``eval.reference_noise`` times the target, or ``eval.reference_spp_max`` is reached. Returns
    (references, second references, spp per lighting)."""
    refs, refs2, spps = [], [], []
    limit = float(e["reference_noise"]) * float(e["target"])
    for i, lighting in enumerate(lightings):
        seeds = (int(e["seed"]) + 100 * i, int(e["seed"]) + 100 * i + 50)
        spp, batches = int(e["reference_spp"]), [[], []]
        while True:
            size = spp - sum(b[0] for b in batches[0])
            for k in (0, 1):
                seed = seeds[k] + len(batches[k])
                batches[k].append((size, reference_batch(desc, handle, camera, lighting, size, seed)))
            a, b = (sum(n * x for n, x in bs) / spp for bs in batches)
            noise = reference_noise(a, b, scored)
            if noise <= limit or 2 * spp > int(e["reference_spp_max"]):
                break
            spp *= 2
        refs.append(a.astype(np.float32))
        refs2.append(b.astype(np.float32))
        spps.append(spp)
    return refs, refs2, spps


def reference_noise(a, b, scored) -> float:
    """The largest relative noise of one reference (||a - b|| / sqrt 2, scored as ``object_scores``
    scores) over the objects of ``scored`` ((object ids, names, ids to judge) or None)."""
    if scored is None:
        ids, names, keep = np.zeros(a.shape[:-1], np.int64), ["image"], None
    else:
        ids, names, keep = scored
    floor = jeval.object_scores([b], [a], ids, names)
    values = [v["rel_rmse"] for k, v in floor.items() if keep is None or k in keep]
    return max(values, default=0.0) / np.sqrt(2.0)


def pathtrace_ms(handle, camera, lighting, spp: int) -> dict:
    """The peer: Mitsuba's time for one reference frame of the held-out view (full and direct
    paths along the pixel-centre rays, at the spp the reference needed), after a 1-spp warm-up
    (Dr.Jit compiles per ray count)."""
    from jprt.render.images import centre_rays

    handle.set_lighting(lighting)
    centre_rays(handle, camera, spp=1, seed=3)
    t0 = time.perf_counter()
    centre_rays(handle, camera, spp=int(spp), seed=3)
    return {"spp": int(spp), "ms": 1e3 * (time.perf_counter() - t0),
            "note": "Mitsuba llvm_ad_rgb, full (max_depth -1) and direct (max_depth 2) paths along the "
                    "pixel-centre rays at the spp the first held-out reference needed"}


def face_counts(handle) -> list[int]:
    """Triangles of each shape of ``handle`` in object-id order (0 for shapes that are not meshes)."""
    return [int(s.face_count()) if hasattr(s, "face_count") else 0 for s in handle.shapes()]


def lighting_setup(desc: dict, cameras: list, lightings: list, method_lightings: list, e: dict) -> dict:
    """One lighting set-up of a scene: its handle, the views' G-buffers, which objects are judged
    (>= ``eval.min_object_fraction`` of some view, not purely specular), the references, and the
    path tracer's time for one reference frame (``pathtrace_ms``; None where ``eval.time_peer`` is
    false: a diagnostic run that needs no speed-up skips minutes of path tracing)."""
    from jprt.render.gbuffer import gbuffer
    from jprt.render.scenes import SceneHandle

    h = SceneHandle(desc)
    names = h.object_names()
    gbs = [gbuffer(h, c) for c in cameras]
    apart = {n: "purely specular (smooth glass or mirror)" for n in specular_objects(h)}
    apart.update({s.id(): "an emitter (its look is its emission)" for s in h.shapes() if s.emitter() is not None})
    shown = set()
    for g in gbs:
        ids, counts = np.unique(g.object_id[g.object_id >= 0], return_counts=True)
        shown |= {names[int(k)] for k, c in zip(ids, counts) if c / g.object_id.size >= float(e["min_object_fraction"])}
    judged, apart = sorted(shown - set(apart)), {k: v for k, v in sorted(apart.items()) if k in shown}
    refs, refs2, spp = [], [], []
    for c, g in zip(cameras, gbs):
        r, r2, s = references(desc, h, c, lightings, e, (g.object_id, names, set(judged)))
        refs += r
        refs2 += r2
        spp.append(s)
    ids = [g.object_id for g in gbs for _ in lightings]  # every (view, lighting) item, the references' order
    return {"desc": desc, "handle": h, "names": names, "gbuffers": gbs, "judged": judged, "apart": apart,
            "lightings": lightings, "method_lightings": method_lightings, "refs": refs, "refs2": refs2,
            "ids": ids, "floor": jeval.object_scores(refs2, refs, ids, names),
            "spp": spp,
            "peer": pathtrace_ms(h, cameras[0], lightings[0], spp[0][0]) if e.get("time_peer", True) else None}
