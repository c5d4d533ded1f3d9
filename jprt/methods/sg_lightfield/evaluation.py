"""What the SG light-field report measures beyond the method contract (Currius et al. 2020): the
held-out views, the raw captured maps shaded by quadrature (the compression-free bound),
interpolation at captured midpoints (§4, Fig. 2) and §5's environment visibility against
Mitsuba's direct light of the receivers (Table 3 setting).

Renders with Mitsuba through ``jprt.render``; the model's math stays in ``model.py``.
"""

from __future__ import annotations

import jax
import numpy as np

from jprt.methods.lightmap_lookup import atlas_image, atlas_lookup
from jprt.methods.sg_lightfield import baselines
from jprt.methods.sg_lightfield import model as sgm
from jprt.sphere import octahedral, sg

__all__ = ["HELD_OUT_VIEWS", "cameras", "stored_lobes", "quadrature_images", "midpoints", "midpoint_log_l2", "environment_images",
           "references", "pathtracer", "roughness_masks"]


#: Held-out views on an arc in front of the Cornell box (``cameras``): count, radius (scene units),
#: arc and its start (degrees), height of the arc's centre.
HELD_OUT_VIEWS = {"n": 3, "radius": 3.9, "arc_deg": 50.0, "start_deg": -25.0, "height": 0.0}


def cameras(views: dict, resolution: int) -> list:
    """Held-out cameras on an arc in front of the scene (``views``: n, radius, arc_deg,
    start_deg, height), square images of ``resolution``; none is a capture position."""
    from jprt.render import cameras as cams

    return cams.orbit((0.0, float(views["height"]), 0.0), float(views["radius"]), int(views["n"]),
                      arc_deg=float(views["arc_deg"]), start_deg=float(views["start_deg"]), width=int(resolution),
                      height=int(resolution))


def stored_lobes(params) -> sgm.Lobes:
    """The lobes of a stored light-field texture (``params`` axes, sharpness, amplitude) in float32."""
    return sgm.Lobes(*(np.asarray(params[k], np.float32) for k in ("axes", "sharpness", "amplitude")))


def quadrature_images(data, params, gbuffers, sub: int) -> tuple[list, list]:
    """§3's raw light-field texture without lobes: each pixel's captured map filtered bilinearly
    between its texels like the lobes, shaded by quadrature of the rendered BRDF
    (``model.shade_quadrature``, ``sub``^2 directions per map pixel); and the lobes of ``params``
    shaded the same way. Returns (raw images, lobe images), one per G-buffer, 0 off it."""
    n = data.images.shape[1]
    table = atlas_image(np.asarray(data.images, np.float32).reshape(len(data.images), -1),
                        np.asarray(data.atlas["fill_index"]))
    dirs = octahedral.texel_directions(n).reshape(-1, 3)
    raw, lobed = [], []
    for g in gbuffers:
        def shade(maps, g=g):
            image = sgm.shade_quadrature(maps, g.normal, g.view, g.roughness, g.specular_albedo, sub=int(sub))
            return np.where(g.valid[..., None], np.asarray(image), 0.0)

        raw.append(shade(np.asarray(atlas_lookup(table, g.uv)).reshape(g.uv.shape[:2] + (n, n, 3))))
        lobes = sgm.lookup_lobes(params, g.uv)  # the lobes as the pixel-space evaluator filters them
        at = dirs.reshape((1,) * (g.uv.ndim - 1) + dirs.shape)  # the pixels' leading axes, for broadcasting
        lobed.append(shade(np.asarray(sgm.lobe_radiance(lobes, at)).reshape(g.uv.shape[:2] + (n, n, 3))))
    return raw, lobed


def midpoints(handle, scene, data, capture: dict, count: int, seed: int):
    """Pairs (a, b) of horizontally adjacent texels of one object, both captured as OK (at most
    ``count``, drawn with ``seed``), and the light field captured halfway between them with the
    ``capture`` settings (a ``jprt.cache`` entry like the light field). Returns (first texels,
    second texels, images, below masks) of the midpoints captured OK."""
    from jprt import cache
    from jprt.render import lightfield as lf

    a = data.atlas
    r, index, obj = int(a["resolution"]), np.asarray(a["texel_index"]), np.asarray(a["texel_object"])
    where = np.full(r * r, -1)
    where[index] = np.arange(len(index))
    right = np.where(index % r < r - 1, where[np.minimum(index + 1, r * r - 1)], -1)
    ok = (right >= 0) & (data.flags == lf.OK)
    ok &= (obj[np.maximum(right, 0)] == obj) & (data.flags[np.maximum(right, 0)] == lf.OK)
    first = np.nonzero(ok)[0]
    rng = np.random.default_rng(int(seed))
    first = np.sort(rng.choice(first, min(int(count), len(first)), replace=False))
    second = right[first]
    pos = 0.5 * (np.asarray(a["position"])[first] + np.asarray(a["position"])[second])
    nrm = np.asarray(a["normal"])[first] + np.asarray(a["normal"])[second]
    nrm /= np.linalg.norm(nrm, axis=-1, keepdims=True)
    points, flags = lf.capture_points(handle, pos, nrm, float(a["texel_size"]))
    c = capture
    spec = {"format": 1, "scene": scene, "points": lf.atlas_digest(points, nrm), "size": int(c["size"]),
            "spp": int(c["spp"]), "seed": int(c["seed"]) + 104729}
    maps, _ = cache.cached("lightfield_midpoints", spec, lambda: lf.capture_block(
        handle, points, nrm, flags, int(c["size"]), spp=int(c["spp"]), seed=spec["seed"]))
    keep = flags == lf.OK
    return first[keep], second[keep], maps[c["field"]][keep], maps["below"][keep]


def midpoint_log_l2(first, second, images, below, lobe_sets: dict, fitted: dict) -> dict:
    """The interpolation claim (§4, Fig. 2): each lobe set of ``lobe_sets`` ({name: Lobes per
    texel}) halfway between texels ``first`` and ``second`` as the run time filters them (every
    parameter linear, axes renormalised), and the SH fits of ``fitted`` ({name: baseline result
    with "sh"}) interpolated in their coefficients; each scored by log-L2 against the light field
    captured at the midpoints (``images``, ``below``). Returns {name: log-L2}."""
    size = images.shape[1]
    dirs = np.asarray(octahedral.texel_directions(size)).reshape(-1, 3)
    targets, weights = images.reshape(len(images), -1, 3), sgm.pixel_weights(size, below)
    at = np.broadcast_to(dirs, (len(images),) + dirs.shape)
    out = {}
    for name, res in fitted.items():  # SH: linear in its coefficients
        mid = 0.5 * (res["sh"][first] + res["sh"][second])
        out[name] = float(sg.log_l2(baselines.sh_radiance(mid, dirs), targets, weights))
    for name, lobes in lobe_sets.items():
        pick = lambda idx: sgm.Lobes(*(np.asarray(x)[idx] for x in lobes))  # noqa: E731
        mid = baselines.interpolate_lobes(pick(first), pick(second))
        out[name] = float(sgm.log_l2_loss(mid, at, targets, weights))
    return out


def environment_images(ed, lobes, cameras_, reference_spp: int, seed: int) -> tuple[dict, list]:
    """§5 (Table 3 setting) at the held-out views ``cameras_``: the receivers of ``ed`` (a
    ``data.make_environment_dataset``) under its distant environment, W_E from ``lobes`` (fitted
    to its maps) shaded by Eq. 8 ("we"), against visibility from the raw W_E maps ("we_raw"),
    tested only along the reflected direction ("reflected_visibility": exact per pixel, one ray),
    none ("no_visibility"), and Eq. 3 by quadrature of the captured visibility x environment
    ("quadrature": no split-sum approximation at all). References: Mitsuba's direct light of the
    receivers at ``reference_spp`` (the environment reflected once, visibility included; seed
    ``seed`` + view). Returns ({name: images}, references), 0 off the receivers."""
    from jprt.methods.sg_lightfield import data as sgdata
    from jprt.methods.sg_lightfield import environment as env
    from jprt.render import lightmap
    from jprt.render.images import render
    from jprt.render.lights import EnvMap
    from jprt.render.scenes import SceneHandle

    stored = sgm.to_storage(lobes)
    handle = SceneHandle(sgdata.ENV_RECEIVERS, EnvMap.create(ed.environment))
    atlas = lightmap.Atlas(**ed.atlas)
    texture = {"axes": stored.axes, "sharpness": stored.sharpness, "amplitude": stored.amplitude,
               "fill_index": np.asarray(ed.atlas["fill_index"])}
    raw = atlas_image(np.asarray(ed.images).reshape(len(ed.images), -1), np.asarray(ed.atlas["fill_index"]))
    eps = lightmap.ray_offset(handle)
    m, size = ed.visible.shape[1], ed.images.shape[1]
    lit = np.asarray(ed.visible)[..., None] * env.octahedral_environment(ed.environment, m)[None]  # V L per texel
    lit_table = atlas_image(lit.reshape(len(lit), -1), np.asarray(ed.atlas["fill_index"]))
    preds = {"we": [], "we_raw": [], "reflected_visibility": [], "no_visibility": [], "quadrature": []}
    refs = []
    for k, camera in enumerate(cameras_):
        g = lightmap.atlas_gbuffer(handle, atlas, camera)
        ref = render(handle, camera, spp=int(reference_spp), max_depth=2, seed=int(seed) + k)
        refs.append(np.where(g.valid[..., None], ref, 0.0))
        r = 2.0 * np.sum(g.normal * g.view, axis=-1, keepdims=True) * g.normal - g.view
        u = env.lookup_preconvolved(ed.u, ed.alphas, r, g.roughness)
        w = env.evaluate_lobes(sgm.lookup_lobes(texture, g.uv), r)
        w_raw = np.asarray(jax.vmap(env.octahedral_lookup)(
            np.asarray(atlas_lookup(raw, g.uv)).reshape(-1, size, size, 3), r.reshape(-1, 3))).reshape(r.shape)
        hit = lightmap.intersect(handle, (g.position + eps * g.normal).reshape(-1, 3), r.reshape(-1, 3))
        v_r = (~np.array(hit.is_valid(), bool)).reshape(r.shape[:2] + (1,)).astype(np.float32)
        for name, vis in (("we", w), ("we_raw", w_raw), ("reflected_visibility", v_r), ("no_visibility", 1.0)):
            img = env.shade_environment(u, vis, g.normal, g.view, g.roughness, g.specular_albedo)
            preds[name].append(np.where(g.valid[..., None], np.asarray(img), 0.0))
        # Eq. 3 itself: the captured V L maps, filtered between texels, by quadrature of the BRDF
        maps = np.asarray(atlas_lookup(lit_table, g.uv)).reshape(g.uv.shape[:2] + (m, m, 3))
        img = sgm.shade_quadrature(maps, g.normal, g.view, g.roughness, g.specular_albedo, sub=2)
        preds["quadrature"].append(np.where(g.valid[..., None], np.asarray(img), 0.0))
    return preds, refs


def references(scene, cameras_, gbuffers, spp: int, seed: int) -> tuple[list, list]:
    """Mitsuba's (indirect, direct) images of the held-out views under the scene's own emitters
    at ``spp`` (``jprt.render.dataset.render_dataset``, seed ``seed``), 0 off the receivers (the
    pixels of each view's atlas G-buffer): only they have a light-field texture."""
    from jprt.render.dataset import render_dataset

    refs = render_dataset(scene, cameras_, [None], spp=int(spp), seed=int(seed), gbuffers=False)
    rad = [refs.radiance(k) for k in range(len(refs))]
    mask = [g.valid[..., None] for g in gbuffers]
    return [np.where(m, r["indirect"], 0.0) for m, r in zip(mask, rad)], \
        [np.where(m, r["direct"], 0.0) for m, r in zip(mask, rad)]


def pathtracer(handle, cameras_, timed_camera):
    """Mitsuba as the equal-error peer: the indirect (full minus direct, seed 9001: unlike the
    references') of the held-out views, and its time for ``timed_camera`` (after a warm-up: Dr.Jit
    compiles for each film size)."""
    from jprt import eval as jeval
    from jprt.render.images import direct_indirect

    def render_at(spp):
        return [direct_indirect(handle, c, spp=spp, seed=9001).indirect for c in cameras_]

    def time_at(spp):
        direct_indirect(handle, timed_camera, spp=1, seed=3)
        return jeval.time_call(lambda: direct_indirect(handle, timed_camera, spp=spp, seed=3), repeats=1,
                               warmup=0)["median_ms"]

    return jeval.PathTracer(render_at, time_at, "Mitsuba llvm_ad_rgb, indirect = full (max_depth -1) minus direct "
                                                "(max_depth 2), both renders timed")


def roughness_masks(gbuffers, names, materials: dict) -> dict:
    """{GGX alpha (as "%g"): per-view masks of the receiver of that roughness} over the receivers
    of ``gbuffers`` that have one (``materials``: {object name: its material}) and that every view
    shows."""
    out = {}
    for obj in np.unique(np.concatenate([np.unique(g.object_id[g.valid]) for g in gbuffers])):
        alpha = materials[names[int(obj)]].get("roughness")
        masks = [g.valid & (g.object_id == obj) for g in gbuffers]
        if alpha is not None and all(m.any() for m in masks):
            out[f"{float(alpha):g}"] = masks
    return out
