"""``jprt export RUN_FOLDER --out DIR``: a fitted model in the formats engines and browsers read.

The run folder is loaded as the viewer loads it (``jprt.view.Session``: the params, the method's
config, its dataset from the cache, the scene and its default view and lighting), then:

* **every method**: ``export.json`` (the manifest, ``jprt.export.bundle.MANIFEST_KEYS``) and the
  params as exact binary buffers under ``params/``; ``jprt.export.load`` rebuilds the evaluator
  from them.
* **lightmap methods** (``LIGHTMAP_METHODS``: data-driven PRT, SH PRT, SG light-field textures,
  MRT): ``scene.glb`` (the meshes the atlas covers with the atlas UVs as ``TEXCOORD_1``, base
  colours read from the scene's materials the way the G-buffer reads them, the lightmap as an
  embedded RGBM PNG referenced by the ``JPRT_lightmap`` material extension), ``lightmap.exr``
  (the same lightmap in float32), ``lightmap_radiance.exr`` (what the evaluator predicts at each
  texel), and the relightable parts (``relightable_parts``): the basis, transfer coefficients,
  lobes or operators the method relights with, as textures and binary buffers; and
  ``relight.js``, a three.js material that relights from the lighting the evaluator takes
  (``RELIGHT_JS_METHODS``: on the GPU, after a small CPU product for data-driven PRT's transfer
  and MRT's reduced-space operators).
* **neural evaluators** (``ONNX_METHODS``: RRF, neural-wavelet PRT, SG environment visibility):
  ``evaluator.onnx``, the evaluator at the view's frame size (``jprt.export.onnx``), with a
  reference frame (``reference_inputs.npz``, ``reference_output.npy``) an engine can check
  itself against. RRF also ships as GLSL (``jprt.export.glsl``): ``rrf.glsl`` (Eq. 9 as GLSL ES
  3.00 functions), ``rrf_data.bin`` (its numbers, an R32F texture) and ``rrf_pass.js`` (a three.js
  full-screen pass over a G-buffer that calls them).

The lightmap is irradiance E as three.js reads a ``lightMap`` (its diffuse shading is
albedo / pi x E): E = pi L / albedo per texel and channel, L the indirect radiance the evaluator
predicts at the texel under the run's default lighting (the viewer's), albedo the diffuse albedo
there (0 where the albedo is below ``ALBEDO_FLOOR``: such a texel reflects no diffuse light, and
its L, if any, is glossy; 0 too where a fitted model predicts slightly negative light). SG
light-field textures store their texels' irradiance themselves.
"""

from __future__ import annotations

import os
import time
from typing import Any

import jax
import numpy as np

from jprt import io
from jprt.export import bundle, gltf

__all__ = ["LIGHTMAP_METHODS", "ONNX_METHODS", "RELIGHT_JS_METHODS", "ALBEDO_FLOOR", "export_run", "lightmap_layout",
           "texel_materials", "scene_meshes", "relightable_parts"]

#: Methods whose prediction lives in a lightmap atlas (exported as glTF + textures).
LIGHTMAP_METHODS = ("datadriven", "sh_prt", "sg_lightfield", "mrt")

#: Methods whose evaluator is a neural network over G-buffer attributes (exported as ONNX).
ONNX_METHODS = ("rrf", "wavelet_prt", "sg_environment")

#: Lightmap methods whose export ships ``relight.js`` (three.js relighting on the GPU).
RELIGHT_JS_METHODS = ("sh_prt", "datadriven", "sg_lightfield", "mrt")

#: Diffuse albedo below which a texel's lightmap irradiance is 0 (it reflects no diffuse light).
ALBEDO_FLOOR = 1e-4

_LIGHTING_FIELDS = {
    "PointLights": {"position": ((-1, 3), "float32", "world-space light positions (scene units)"),
                    "intensity": ((-1, 3), "float32", "RGB radiant intensity of each light (W/sr)")},
    "CubeMap": {"radiance": ((6, -1, -1, 3), "float32", "environment radiance as a cube map: faces +X, -X, +Y, "
                             "-Y, +Z, -Z (jprt.sphere.cubemap), RGB (W m^-2 sr^-1)")},
    "PointRadiance": {"direct": ((-1, 3), "float32", "direct outgoing radiance (W m^-2 sr^-1) at the method's "
                                 "measurement points (data-driven PRT) or texels (MRT), from the engine's direct "
                                 "pass")},
    "SHLighting": {"coefficients": ((-1, 3), "float32", "real SH coefficients of the distant incident radiance, "
                                    "band by band (jprt.sphere.sh order), RGB")},
    "LightScale": {"scale": ((3,), "float32", "RGB factor on the baked emitters' power")},
    "PreconvolvedEnvironment": {"u": ((-1, -1, -1, 3), "float32", "the environment convolved with GGX lobes at "
                                      "each alpha, octahedral maps (Eq. 6 of Currius et al. 2020)"),
                                "alphas": ((-1,), "float32", "the GGX alphas of the convolutions")},
}

_UNITS = {
    "radiance": "W m^-2 sr^-1 per RGB channel, linear (what every evaluator predicts; Mitsuba's units)",
    "irradiance": "W m^-2 per RGB channel, linear (the lightmaps: pi x radiance / diffuse albedo)",
    "position": "scene units, world space, right-handed, +Y up as in the scene file",
    "light_intensity": "W/sr per RGB channel (point lights)",
}


def _say(progress, msg: str) -> None:
    if progress:
        import sys

        print(f"[export] {msg}", file=sys.stderr, flush=True)


# --------------------------------------------------------------------------------------------
# The lightmap atlas and the scene's geometry


def lightmap_layout(session) -> tuple[int, np.ndarray, np.ndarray]:
    """(resolution R, texel_index (T,) flat atlas pixel of each texel, fill_index (R * R,) texel
    each atlas pixel shows) of a lightmap method's run (the params' layout, else its dataset's
    atlas)."""
    params, ds = session.params, session.dataset
    fill = np.asarray(params["fill_index"], np.int64)
    if "texel_index" in params:
        texels = np.asarray(params["texel_index"], np.int64)
    elif isinstance(getattr(ds, "atlas", None), dict):
        texels = np.asarray(ds.atlas["texel_index"], np.int64)
    else:
        raise ValueError(f"{session.method.name}: the run has no lightmap layout (texel_index)")
    res = int(round(np.sqrt(fill.size)))
    if res * res != fill.size:
        raise ValueError(f"fill_index of {fill.size} entries is not a square atlas")
    return res, texels, fill


def _atlas_image(texels, fill) -> np.ndarray:
    """Texel values (T, C) -> the (R, R, C) atlas image, gutters repeating their nearest texel."""
    res = int(round(np.sqrt(fill.size)))
    t = np.asarray(texels)
    return t[fill].reshape((res, res) + t.shape[1:])


def texel_materials(session, texel_index) -> dict:
    """{"diffuse", "specular" (T, 3), "roughness" (T,)}: the scene's materials at each lightmap
    texel, read as the G-buffer reads them (MRT: the albedo of its fit, which is that reading)."""
    ds = session.dataset
    if session.method.name == "mrt":
        albedo = np.asarray(session.params["albedo"], np.float32).reshape(-1, 3)
        zeros = np.zeros_like(albedo)
        return {"diffuse": albedo, "specular": zeros, "roughness": np.ones(len(albedo), np.float32)}
    from jprt.render.gbuffer import gbuffer_rays
    from jprt.render.lightmap import ray_offset

    pos = np.asarray(ds.atlas["position"], np.float64)
    nrm = np.asarray(ds.atlas["normal"], np.float64)
    eps = ray_offset(session.handle)
    g = gbuffer_rays(session.handle, pos + 4.0 * eps * nrm, -nrm)
    ok = np.asarray(g.valid, bool)[:, None]
    return {"diffuse": np.where(ok, np.asarray(g.diffuse_albedo), 0.0).astype(np.float32),
            "specular": np.where(ok, np.asarray(g.specular_albedo), 0.0).astype(np.float32),
            "roughness": np.where(ok[:, 0], np.asarray(g.roughness), 1.0).astype(np.float32)}


def _object_materials(handle, object_id: int, tris: np.ndarray, normal: np.ndarray):
    """(base colour (3,), metallic, perceptual roughness, normals oriented to the side rays
    reach) of an object, the area-weighted mean of the G-buffer's reading at its triangles."""
    from jprt.render.gbuffer import gbuffer_rays
    from jprt.render.lightmap import ray_offset

    centre = tris.mean(axis=1)
    eps = 4.0 * ray_offset(handle)
    area = 0.5 * np.linalg.norm(np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0]), axis=1)
    front = gbuffer_rays(handle, centre + eps * normal, -normal)
    back = gbuffer_rays(handle, centre - eps * normal, normal)
    hit_front = np.asarray(front.valid, bool) & (np.asarray(front.object_id) == object_id)
    hit_back = np.asarray(back.valid, bool) & (np.asarray(back.object_id) == object_id) & ~hit_front
    oriented = np.where(hit_back[:, None], -normal, normal)
    w = area * (hit_front | hit_back)
    if not w.sum() > 0:
        return np.full(3, 0.5), 0.0, 1.0, oriented
    w = w / w.sum()

    def mean(field, axis_shape=True):
        a = np.where(hit_front[:, None] if axis_shape else hit_front, np.asarray(getattr(front, field)),
                     np.asarray(getattr(back, field)))
        return np.tensordot(w, a, axes=(0, 0))

    diffuse = mean("diffuse_albedo")
    specular = mean("specular_albedo")
    alpha = float(mean("roughness", axis_shape=False))
    metallic = float(np.max(specular) > np.max(diffuse))  # a conductor: its colour is its specular albedo
    base = specular if metallic else diffuse
    return np.asarray(base, np.float64), metallic, float(np.sqrt(max(alpha, 0.0))), oriented


def _unit_normals(tris: np.ndarray) -> np.ndarray:
    n = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def scene_meshes(session) -> list:
    """``jprt.export.gltf.Mesh`` of every object the lightmap covers, its triangles (zero-area ones
    left out) with atlas UVs: the atlas's per-triangle affine map of the world position (data-driven
    PRT, SH PRT, SG light-field textures), or MRT's block proxy (``proxy_uv``: each triangle on the
    face of its block that faces its way)."""
    from jprt.render.lightmap import Atlas, mesh_triangles

    handle = session.handle
    names = handle.object_names()
    out = []
    if session.method.name == "mrt":
        from jprt.methods.mrt.block_atlas import proxy_uv
        from jprt.methods.mrt.data import block_frame

        cfg = session.dataset.meta["config"]
        layout, origin, size, _ = block_frame(session.dataset.meta["scene"], cfg)
        t = int(cfg["dictionary"]["texels"])
        ids = range(len(names))
    else:
        atlas = Atlas(**session.dataset.atlas)
        ids = [int(o) for o in atlas.objects]
    for slot, obj in enumerate(ids):
        try:
            tris, own_uv = mesh_triangles(handle, obj)
        except ValueError:
            continue  # not a mesh: no lightmap covers it
        area = 0.5 * np.linalg.norm(np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0]), axis=1)
        keep = np.flatnonzero(area > 1e-12 * max(float(area.max(initial=0.0)), 1e-300))
        if keep.size == 0:
            continue
        base, metallic, roughness, normal = _object_materials(handle, obj, tris[keep], _unit_normals(tris[keep]))
        if session.method.name == "mrt":
            centre = tris[keep].mean(axis=1, keepdims=True)
            cell = np.floor((centre[:, 0] - origin) / size)
            inward = (origin + (cell + 0.5) * size) - centre[:, 0]  # towards the centre of the block holding it
            normal = np.where((np.sum(normal * inward, axis=1) < 0)[:, None], -normal, normal)
            # proxy_uv of points just inside the triangle (one block and face for all of them),
            # extrapolated to the corners: the map is affine on a face
            shrink = 1e-3
            corners = tris[keep] + shrink * (centre - tris[keep])
            uv, ok = proxy_uv(corners, np.repeat(normal[:, None], 3, axis=1), layout, origin, size, t)
            uv_c, ok_c = proxy_uv(centre, normal[:, None], layout, origin, size, t)
            uv = uv_c + (uv - uv_c) / (1.0 - shrink)
            good = ok.all(axis=1) & ok_c[:, 0]
            if not good.any():
                continue
            keep, normal, uv = keep[good], normal[good], uv[good]
        else:
            affine = atlas.tri_affine[int(atlas.tri_offset[slot]) + keep]  # (F, 2, 4)
            p1 = np.concatenate([tris[keep], np.ones(tris[keep].shape[:2] + (1,))], axis=-1)
            uv = np.einsum("fij,fkj->fki", affine, p1)
        uv0 = own_uv[keep] if own_uv is not None else uv
        out.append(gltf.Mesh(names[obj], tris[keep].reshape(-1, 3).astype(np.float32),
                             np.repeat(normal, 3, axis=0).astype(np.float32),
                             np.asarray(uv0, np.float32).reshape(-1, 2), np.asarray(uv, np.float32).reshape(-1, 2),
                             base, metallic, roughness))
    if not out:
        raise ValueError(f"{session.method.name}: no mesh of the scene is covered by the lightmap")
    return out


# --------------------------------------------------------------------------------------------
# Lightmaps and relightable parts


def _texel_radiance(session, lighting, texel_index, materials) -> np.ndarray:
    """(T, 3) indirect radiance the method predicts at its texels under ``lighting``: the
    evaluator on the atlas seen as an image (``Method.example``'s inputs); SG light-field
    textures: the diffuse part, albedo / pi x the stored irradiance x the light scale (their
    evaluator's glossy part depends on the view and lives in the lobes)."""
    m, cfg = session.method, session.method_config
    if m.name == "sg_lightfield":
        irr = np.asarray(session.params["irradiance"], np.float32)
        scale = np.asarray(getattr(lighting, "scale", lighting), np.float32).reshape(3)
        return materials["diffuse"] / np.pi * irr * scale
    inputs = m.example(session.dataset, cfg)[0]
    res = int(round(np.sqrt(np.asarray(session.params["fill_index"]).size)))
    if np.shape(inputs.valid) != (res, res):
        raise ValueError(f"{m.name}: its example inputs are {np.shape(inputs.valid)}, not the ({res}, {res}) atlas")
    image = np.asarray(jax.jit(m.evaluator(session.params, cfg))(inputs, lighting), np.float32)
    return image.reshape(-1, 3)[texel_index]


def _irradiance(radiance, diffuse) -> np.ndarray:
    """pi L / albedo where the albedo reflects, else 0 (three.js's lightMap quantity); a slightly
    negative prediction (a fitted model's error) becomes 0, as no engine lights with less than none."""
    d = np.asarray(diffuse, np.float64)
    e = np.where(d > ALBEDO_FLOOR, np.pi * np.asarray(radiance, np.float64) / np.maximum(d, ALBEDO_FLOOR), 0.0)
    return np.maximum(e, 0.0).astype(np.float32)


def _channels(prefix: str, n: int, suffixes=("R", "G", "B")) -> list:
    return [f"{prefix}{i:02d}.{s}" for i in range(n) for s in suffixes]


def relightable_parts(session, out: str, texel_index, fill, materials: dict | None = None) -> dict:
    """Write the method's relightable parts beside the glTF; returns their ``files`` entries.
    ``materials``: ``texel_materials`` of the texels (read again when None).

    * data-driven PRT: ``basis.exr`` (the basis lightmaps, one channel per basis vector and colour
      where the basis has colour), ``measurement_points.bin`` (the fine points where direct light
      is measured: (S, 6) float32 position, normal); the transfer matrix, grouping and counts are
      params buffers.
    * SH PRT: ``sh_transfer.exr`` (each texel's transfer vector: channel ``cII.R/G/B`` = the
      indirect radiance under the unit SH light II).
    * SG light-field textures: ``sg_lobes.exr`` (float16: per lobe J ``lobeJJ.X/Y/Z`` axis,
      ``lobeJJ.S`` sharpness, ``lobeJJ.R/G/B`` amplitude; ``irradiance.R/G/B``) and
      ``sg_materials.bin`` (the shading's material at every texel: (T, 7) float32 diffuse albedo
      RGB, specular reflectance RGB, GGX roughness).
    * MRT: the per-block operators are the params buffers (described in the manifest).
    """
    name, params, ds = session.method.name, session.params, session.dataset
    files: dict = {}
    if name == "datadriven":
        basis = np.asarray(params["basis"], np.float32)
        mean = np.asarray(params["mean"], np.float32)
        t = texel_index.size
        if basis.shape[0] == t:  # mono: one basis for the three channels
            stack, names = np.concatenate([mean[:, None], basis], axis=1), ["mean"] + [f"b{i:02d}" for i in
                                                                                         range(basis.shape[1])]
        else:  # multi: texel-major (T, 3) rows
            stack = np.concatenate([mean.reshape(t, 3), basis.reshape(t, 3, -1).transpose(0, 2, 1).reshape(t, -1)],
                                   axis=1)
            names = ["mean.R", "mean.G", "mean.B"] + _channels("b", basis.shape[1])
        io.write_exr(os.path.join(out, "basis.exr"), _atlas_image(stack, fill), names)
        files["basis.exr"] = {"format": "OpenEXR float32, atlas image (row 0 = v in [0, 1/R))",
                              "holds": "the lightmap basis of Belcour et al. 2022 §4.2: channel 'mean' (times |x| "
                                       "per channel, or a regressed coefficient with basis.mean='linear') and 'bNN' "
                                       "(the basis vector NN); lightmap = mean |x| + sum_NN bNN u_NN, u = M x "
                                       "(params/transfer.bin), x = the direct light averaged per coarse point"
                                       + ("; a demodulated fit (shading.demodulate): times params/texel_modulation "
                                          "per texel and channel, the texture its basis was fitted without"
                                          if "texel_modulation" in params else "")}
        cand = ds.candidates
        fine = np.asarray(params["fine_index"], np.int64)
        pts = np.concatenate([np.asarray(cand["position"], np.float32)[fine],
                              np.asarray(cand["normal"], np.float32)[fine]], axis=1)
        io.atomic_write_bytes(os.path.join(out, "measurement_points.bin"), np.ascontiguousarray(pts, "<f4").tobytes())
        files["measurement_points.bin"] = {
            "format": f"raw little-endian float32, shape [{pts.shape[0]}, 6]",
            "holds": "the fine measurement points (position xyz, unit normal xyz): an engine measures the direct "
                     "radiance there (its PointRadiance lighting); params/group.bin averages them to coarse points"}
    elif name == "sh_prt":
        transfer = np.asarray(params["transfer"], np.float32)  # (T, n, 3)
        n = transfer.shape[1]
        io.write_exr(os.path.join(out, "sh_transfer.exr"), _atlas_image(transfer.reshape(transfer.shape[0], -1), fill),
                     _channels("c", n))
        files["sh_transfer.exr"] = {"format": "OpenEXR float32, atlas image",
                                    "holds": f"SH transfer vectors (Sloan et al. 2002 Eq. 5) of {n} coefficients: "
                                             "channel cII.C = indirect radiance in colour C under the unit SH light "
                                             "II; lightmap_C = sum_II cII.C l_II.C"
                                             + (f" (the radiance along each texel's normal; the "
                                                f"{np.asarray(params['exit_transfer']).shape[0]} view-dependent "
                                                "texels' exit transfer is in params/, which relight.js does not "
                                                "shade)" if np.asarray(params.get("exit_transfer", [])).shape[0]
                                                else "")}
    elif name == "sg_lightfield":
        axes = np.asarray(params["axes"], np.float32)
        sharp = np.asarray(params["sharpness"], np.float32)
        amp = np.asarray(params["amplitude"], np.float32)
        n = sharp.shape[1]
        planes, names = [], []
        for j in range(n):
            planes += [axes[:, j], sharp[:, j:j + 1], amp[:, j]]
            names += [f"lobe{j:02d}.{c}" for c in ("X", "Y", "Z", "S", "R", "G", "B")]
        planes.append(np.asarray(params["irradiance"], np.float32))
        names += ["irradiance.R", "irradiance.G", "irradiance.B"]
        io.write_exr(os.path.join(out, "sg_lobes.exr"), _atlas_image(np.concatenate(planes, axis=1), fill), names,
                     half=True)
        files["sg_lobes.exr"] = {"format": "OpenEXR float16, atlas image",
                                 "holds": f"{n} spherical Gaussian lobes per texel (Currius et al. 2020 Eq. 1): "
                                          "lobeJJ.X/Y/Z axis (renormalise after filtering), lobeJJ.S sharpness, "
                                          "lobeJJ.R/G/B amplitude; irradiance.R/G/B the texel's irradiance "
                                          "(diffuse = albedo / pi x irradiance)"}
        mat = texel_materials(session, texel_index) if materials is None else materials
        table = np.concatenate([mat["diffuse"], mat["specular"], np.asarray(mat["roughness"])[:, None]], axis=1)
        io.atomic_write_bytes(os.path.join(out, "sg_materials.bin"),
                              np.ascontiguousarray(table, "<f4").tobytes())
        files["sg_materials.bin"] = {"format": f"raw little-endian float32, shape [{table.shape[0]}, 7]",
                                     "holds": "each texel's material as the G-buffer reads it: diffuse albedo RGB, "
                                              "specular reflectance at normal incidence RGB, GGX roughness (alpha)"}
    return files


_PARAM_MEANING = {
    "datadriven": {"basis": "lightmap basis U_n, (T, n) per texel (mono) or (3T, n)", "mean": "mean lightmap m",
                   "transfer": "transfer matrices M_n (Eq. 14): (3, n, P) per channel (mono) or (n, 3P)",
                   "group": "coarse point of each fine measurement point", "counts": "fine points per coarse point",
                   "fine_index": "candidate index of each fine measurement point", "texel_index": "atlas pixel of "
                   "each texel", "fill_index": "texel each atlas pixel shows", "singular_values": "of the basis SVD",
                   "texel_modulation": "(T, 3) a demodulated fit's texture per texel: the lightmap's light is the "
                   "basis's times it (lightmap_lookup.texel_modulation)",
                   "object_albedo": "(objects, 3) the mean albedo a Lambertian pixel's is taken relative to"},
    "sh_prt": {"transfer": "transfer vectors (T, n_coefficients, 3)", "texel_index": "atlas pixel of each texel",
               "fill_index": "texel each atlas pixel shows",
               "exit_transfer": "exit transfer (G, m_view, n_coefficients, 3) of the view-dependent texels: radiance "
                                "toward w = sum_j Y_j(w) sum_i M_ji l_i (not shaded by relight.js)",
               "exit_texel": "texel of each exit transfer", "exit_normal": "unit normal of each exit transfer's texel",
               "texel_modulation": "(T, 3) each texel's texture, divided out before a Lambertian pixel's own "
               "is applied (lightmap_lookup.texel_modulation; the transfer holds the texels' light)",
               "object_albedo": "(objects, 3) the mean albedo a Lambertian pixel's is taken relative to"},
    "sg_lightfield": {"axes": "lobe axes (T, N, 3) float16", "sharpness": "lobe sharpness (T, N) float16",
                      "amplitude": "lobe RGB amplitude (T, N, 3) float16", "irradiance": "texel irradiance (T, 3)",
                      "fill_index": "texel each atlas pixel shows"},
    "mrt": {"T_db": "per block T_d->b (k_b x texels): direct light to block coefficients b (Loos et al. Eq. 2-3)",
            "U_b": "per block U_b (texels x k_b): b to gathered radiance", "mask": "per block present texels",
            "rec_src": "T_b->r records: source block", "rec_dst": "T_b->r records: receiving block",
            "rec_side": "T_b->r records: receiving side", "rec_T": "T_b->r records: (k_r x k_b) matrices (§6.3)",
            "U_r_turned": "U_r per side (texels x k_r): interface coefficients r to radiance",
            "W": "feedback operator on b (reduced-space bounce)", "V": "feedback operators on r per side",
            "albedo": "texel diffuse albedo (B, texels, 3)", "texel_index": "atlas pixel of each texel",
            "fill_index": "texel each atlas pixel shows", "U_quad": "vector irradiance (§6.4) per block",
            "U_vol": "irradiance volume from b (§6.5)", "U_rvol": "irradiance volume from r (§6.5)"},
}


def _params_files(name: str, entries: list) -> dict:
    meanings = _PARAM_MEANING.get(name, {})
    files = {}
    for e in entries:
        key = e["keys"][0] if e["keys"] else ""
        what = meanings.get(key, f"array {'.'.join(map(str, e['keys']))} of the fitted params "
                                 f"(jprt.methods.{name}.model)")
        files[e["file"]] = {"format": f"raw little-endian {e['dtype']}, shape {e['shape']}, C order", "holds": what}
    return files


# --------------------------------------------------------------------------------------------
# The export


def _lighting_description(session) -> dict:
    fields = _LIGHTING_FIELDS.get(session.method.lighting.__name__, {})
    return {k: {"shape": list(s), "dtype": d, "meaning": m} for k, (s, d, m) in fields.items()}


def _lighting_json(lighting) -> dict:
    return {k: np.asarray(v).tolist() for k, v in lighting._asdict().items()} if hasattr(lighting, "_asdict") \
        else {"value": np.asarray(lighting).tolist()}


def _ship(name: str, out: str) -> None:
    """Copy the module ``name`` that ships with this package (``jprt/export/*.js``) into ``out``."""
    with open(os.path.join(os.path.dirname(os.path.abspath(__file__)), name), "rb") as f:
        io.atomic_write_bytes(os.path.join(out, name), f.read())


def _rrf_glsl(session, out: str) -> tuple[dict, dict]:
    """RRF's GLSL (``jprt.export.glsl.rrf_shader``) written to ``out``: (the manifest's ``glsl``
    entry, the files' descriptions)."""
    from jprt.export import glsl

    shader = glsl.rrf_shader(session.params, session.method_config)
    io.atomic_write_bytes(os.path.join(out, "rrf.glsl"), shader.source.encode())
    io.atomic_write_bytes(os.path.join(out, "rrf_data.bin"), shader.data.astype("<f4").tobytes())
    _ship("rrf_pass.js", out)
    height, width = shader.data.shape
    entry = {"source": "rrf.glsl", "data": "rrf_data.bin", "data_width": int(width), "data_height": int(height),
             "max_lights": shader.max_lights, "inputs": shader.inputs}
    files = {
        "rrf.glsl": {"format": "GLSL ES 3.00 (WebGL2) source", "holds": "Eq. 9 as functions: rrfInputs (G-buffer "
                     "attributes -> x), rrfLeaf (kd-tree), rrfNetwork (a leaf's tanh network, Eq. 8), rrfIndirect "
                     "(the sum over point lights); reads the uniform rrfData"},
        "rrf_data.bin": {"format": f"float32 little-endian, {height} x {width} (an R32F texture, row 0 first)",
                         "holds": "the trees, scalings, weights and biases rrf.glsl reads (offsets in its constants)"},
        "rrf_pass.js": {"format": "ES module for three.js (imports 'three')",
                        "holds": "rrfPass(url): a ShaderMaterial that evaluates rrf.glsl per pixel of a G-buffer "
                                 "(deferred shading) under point lights"}}
    return entry, files


def export_run(folder: str, out: str, *, size: int = 64, onnx: bool = True, progress: bool | None = None) -> dict:
    """Export the run folder ``folder`` to ``out`` (module docstring); returns the manifest.

    ``size``: the frame (``size`` x ``size``) at the run's default view that the ONNX model takes
    and the reference frame is rendered at (neural evaluators); ``onnx=False`` skips the ONNX
    conversion. Raises ``jprt.view.NotARunFolder`` for a folder that is not a run."""
    from jprt import __version__
    from jprt.view import Session

    t0 = time.perf_counter()
    session = Session(folder, progress=progress)
    m, cfg = session.method, session.method_config
    if m.name not in LIGHTMAP_METHODS + ONNX_METHODS:
        raise ValueError(f"jprt export knows {sorted(LIGHTMAP_METHODS + ONNX_METHODS)}, not {m.name!r}")
    out = os.path.abspath(out)
    os.makedirs(out, exist_ok=True)
    entries = bundle.write_params(out, session.params)
    files = _params_files(m.name, entries)
    manifest: dict[str, Any] = {
        "format": bundle.FORMAT, "format_version": bundle.FORMAT_VERSION, "method": m.name, "paper": m.paper,
        "lighting_type": m.lighting.__name__, "lighting": _lighting_description(session), "predicts": m.predicts,
        "units": dict(_UNITS), "jprt_version": __version__, "config_hash": session.summary.get("config_hash"),
        "config": cfg, "source": os.path.abspath(folder), "params": entries}
    if session.kind != "scale" or m.name in LIGHTMAP_METHODS:  # SG light-field textures: the scene's camera
        s = session.state
        manifest["camera"] = {"origin": list(s["origin"]), "target": list(s["target"]), "up": list(s["up"]),
                              "fov_deg": float(s["fov"]), "aspect": float(s["aspect"]),
                              "fov_axis": "the smaller image axis (Mitsuba's fov_axis='smaller', jprt.inputs.Camera)"}
    lighting = session.method_lighting()
    if m.name in LIGHTMAP_METHODS:
        _say(progress, f"{m.name}: lightmap, meshes, relightable parts")
        res, texel_index, fill = lightmap_layout(session)
        materials = texel_materials(session, texel_index)
        radiance = _texel_radiance(session, lighting, texel_index, materials)
        if m.name == "sg_lightfield":  # the texels' own irradiance, under the light scale
            scale = np.asarray(getattr(lighting, "scale", lighting), np.float32).reshape(3)
            irradiance = np.maximum(np.asarray(session.params["irradiance"], np.float32) * scale, 0.0)
        else:
            irradiance = _irradiance(radiance, materials["diffuse"])
        e_image = _atlas_image(irradiance, fill)
        top = float(np.max(e_image, initial=0.0))
        value_range = float(2.0 ** np.ceil(np.log2(max(top, 1e-6))))
        io.write_exr(os.path.join(out, "lightmap.exr"), e_image)
        io.write_exr(os.path.join(out, "lightmap_radiance.exr"), _atlas_image(radiance, fill))
        png = gltf.rgbm_png(e_image, value_range)
        io.atomic_write_bytes(os.path.join(out, "lightmap_rgbm.png"), png)
        ext = {"texCoord": 1, "intensity": 1.0, "encoding": "RGBM", "rgbmRange": value_range,
               "quantity": "irradiance"}
        doc = gltf.write_glb(os.path.join(out, "scene.glb"), scene_meshes(session), lightmap_png=png, extension=ext,
                             generator=f"jprt {__version__}")
        manifest["lightmap"] = {"resolution": res, "texels": int(texel_index.size), "quantity": "irradiance",
                                "rgbm_range": value_range, "albedo_floor": ALBEDO_FLOOR,
                                "lighting": {"type": type(lighting).__name__, **_lighting_json(lighting)},
                                "view_lighting": {k: session.state[k] for k in ("light", "colour", "power", "scale")
                                                  if k in session.state}}
        files.update({
            "scene.glb": {"format": "binary glTF 2.0", "holds": f"{len(doc['meshes'])} meshes the lightmap covers: "
                          "TEXCOORD_1 atlas UVs, base colours from the scene's materials, the RGBM lightmap "
                          f"(image 0) referenced by each material's {gltf.EXTENSION} extension (index, texCoord 1, "
                          "intensity, encoding, rgbmRange)"},
            "lightmap.exr": {"format": "OpenEXR float32 RGB, atlas image", "holds": "indirect irradiance E for a "
                             "three.js lightMap (diffuse shading = albedo / pi x E) under the view's default lighting"},
            "lightmap_rgbm.png": {"format": f"PNG RGBA, RGBM: E = rgb x a x {value_range} (linear, 8-bit)",
                                  "holds": "lightmap.exr, RGBM-encoded (also embedded in scene.glb)"},
            "lightmap_radiance.exr": {"format": "OpenEXR float32 RGB, atlas image", "holds": "the indirect radiance "
                                      "the evaluator predicts at each texel under the same lighting"}})
        files.update(relightable_parts(session, out, texel_index, fill, materials))
        if m.name in RELIGHT_JS_METHODS:
            _ship("relight.js", out)
            files["relight.js"] = {"format": "ES module for three.js (imports 'three')",
                                   "holds": "relightMaterial(url): a ShaderMaterial of the meshes of scene.glb that "
                                            "relights from the lighting the evaluator takes "
                                            f"({m.lighting.__name__}) and outputs indirect radiance"
                                            + (" (the reduced-space product in JavaScript, the texels on the GPU)"
                                               if m.name in ("datadriven", "mrt") else " (on the GPU)")}
    if m.name == "rrf":
        manifest["glsl"], glsl_files = _rrf_glsl(session, out)
        files.update(glsl_files)
    if m.name in ONNX_METHODS and onnx:
        from jprt.export import onnx as jonnx

        _say(progress, f"{m.name}: ONNX at {size} x {size}")
        inputs = session.inputs(int(size))
        manifest["onnx"], onnx_files = jonnx.export_evaluator(m.evaluator(session.params, cfg), inputs, lighting, out)
        files.update(onnx_files)
    manifest["files"] = files
    bundle.write_manifest(out, manifest)
    _say(progress, f"{m.name}: {len(files) + 1} files in {out} ({time.perf_counter() - t0:.1f} s)")
    return manifest
