"""G-buffers from exact pixel-centre primary rays.

Mitsuba's ``aov`` integrator averages over each pixel's footprint, which blurs edges and makes
integer quantities (object ids) meaningless at partially covered pixels. Here every pixel gets
one primary ray through its centre (``sensor.sample_ray`` at film position ((x + 0.5) / W,
(y + 0.5) / H)), intersected with ``scene.ray_intersect``.

Conventions: ``view`` points from the surface to the camera; the shading ``normal`` is flipped to
the viewer's side (n . v >= 0) so back-facing hits behave like two-sided surfaces, and
``reflected = reflect(-view, normal) = 2 (n . v) n - v``. Invalid pixels (the ray escapes) are
zero with ``object_id = -1``.

BRDF parameters per pixel, read from each hit's BSDF at the hit (``read_materials``; textured
values per pixel, through Mitsuba's ``eval_attribute``) as the Lambert + GGX model every method
here assumes: ``diffuse_albedo`` (the Lambertian reflectance), ``specular_albedo`` (F0, the
specular reflectance at normal incidence) and ``roughness`` (GGX alpha; 1 where there is no
specular lobe):

* ``twosided``: its front BSDF.  ``diffuse`` / ``roughdiffuse``: reflectance, no specular.
* ``conductor`` / ``roughconductor``: F0 from the complex IOR (eta, k) times
  ``specular_reflectance`` (1 for ``material = none``), alpha (the mean of alpha_u and alpha_v
  when anisotropic; 0 when smooth).
* ``plastic`` / ``roughplastic``: ``diffuse_reflectance``, F0 = ((eta - 1) / (eta + 1))^2 times
  ``specular_reflectance``; ``dielectric`` / ``roughdielectric`` / ``thindielectric`` likewise
  with no diffuse term (the transmission is not represented).
* ``principled`` (Burley): diffuse = (1 - metallic)(1 - spec_trans) base_color, F0 = (1 - metallic)
  0.08 specular + metallic base_color, alpha = roughness^2 (Mitsuba's own mapping).
* ``blendbsdf``: both BSDFs read and mixed by ``weight`` (alpha weighted by each side's specular).
* ``mask``: its BSDF.  Anything else: Mitsuba's ``eval_diffuse_reflectance`` as the diffuse term,
  no specular, and a warning naming the BSDF class (approximated, never silently).
"""

from __future__ import annotations

import numpy as np

from jprt.inputs import GBuffer

from jprt.render.cameras import Camera, check_rays, to_sensor_dict
from jprt.render.scenes import SceneHandle

__all__ = ["GBuffer", "gbuffer", "gbuffer_rays", "hit_objects", "object_materials", "read_materials",
           "view_dependent_objects"]


def _child_objects(obj, mi) -> dict:
    """{name: child object} of a Mitsuba object (nested BSDFs and textures), through its traversal."""

    class Collect(mi.TraversalCallback):
        def __init__(self):
            super().__init__()
            self.found = {}

        def put(self, name, value, flags):
            if isinstance(value, (mi.BSDF, mi.Texture)):
                self.found[name] = value

    cb = Collect()
    obj.traverse(cb)
    return cb.found


def _attribute(bsdf, name: str, si, active, channels: int, default, n: int) -> np.ndarray:
    """``bsdf``'s attribute ``name`` at the hits (textures evaluated per hit): (n, channels) or (n,),
    ``default`` where the BSDF does not have it."""
    # Mitsuba returns 0 for an attribute the BSDF does not have (measured: a rough plastic's
    # unset specular_reflectance reads 0, its default is 1), so ask first; eval_attribute (a
    # spectrum) works for every texture, eval_attribute_1 not for all (a checkerboard has no
    # eval_1) and scalars (eta) only through it
    if not bsdf.has_attribute(name):
        calls = []
    else:
        calls = [bsdf.eval_attribute] if channels == 3 else [bsdf.eval_attribute_1, bsdf.eval_attribute]
    for call in calls:
        try:
            a = np.array(call(name, si, active), dtype=np.float32)  # (3, m) or (m,); m = 1 when uniform
        except Exception:  # a texture without that variant of eval
            continue
        if channels == 3:
            return np.broadcast_to(a.reshape(3, -1).T, (n, 3)).copy()
        a = a.reshape(3, -1).mean(axis=0) if a.ndim == 2 else a.reshape(-1)
        return np.broadcast_to(a, (n,)).copy()
    return np.broadcast_to(np.asarray(default, np.float32), (n, channels) if channels == 3 else (n,)).copy()


def _plastic_diffuse(bsdf, si, active, n: int, mi) -> np.ndarray:
    """A plastic's effective Lambertian albedo (n, 3): pi x its diffuse component, as Mitsuba
    evaluates it, at normal incidence and exitance. The coating's transmissions and internal
    reflections scale the diffuse_reflectance (0.94 x for eta 1.49 at 0.5); away from the normal
    the (1 - F) factors vary a little, which Lambert does not."""
    component = next((i for i in range(bsdf.component_count())
                      if bsdf.flags(i) & int(mi.BSDFFlags.DiffuseReflection)), None)
    if component is None:
        return np.zeros((n, 3), np.float32)
    ctx = mi.BSDFContext()
    ctx.component = component
    local = mi.SurfaceInteraction3f(si)
    local.wi = mi.Vector3f(0.0, 0.0, 1.0)
    value = np.array(bsdf.eval(ctx, local, mi.Vector3f(0.0, 0.0, 1.0), active), np.float32)
    return np.pi * np.broadcast_to(value.reshape(3, -1).T, (n, 3))


def _dielectric_f0(eta: np.ndarray) -> np.ndarray:
    return np.square((eta - 1.0) / (eta + 1.0))


#: BSDF classes ``read_materials`` knows, and the unknown ones it has warned about (once each).
_WARNED: set = set()


#: ``read_materials`` gathers each shape's hits into a batch of their own above this many (shapes
#: hit x hits): below it the fixed cost per shape outweighs the passes saved (timed on staircase,
#: living-room and veach-bidir, CHANGELOG 2026-12-05 evening).
GATHER_ABOVE = 4_000_000


def read_materials(handle: SceneHandle, si, valid, n: int, object_id: np.ndarray | None = None) -> dict:
    """Per hit of a surface interaction batch ``si`` (``valid`` (n,) its hits): the Lambert + GGX
    parameters of the BSDF hit (module docstring): {"diffuse_albedo" (n, 3), "specular_albedo"
    (n, 3), "roughness" (n,) GGX alpha in [0, 1]}, zero where there is no hit.

    ``object_id`` (n,) (the shape index of each hit, -1 for none) limits the reads to the shapes
    hit (a file of many meshes and a small batch: a pass per shape of the file otherwise), and
    when the shapes hit times the hits exceed ``GATHER_ABOVE`` each shape's BSDF is read at its
    own hits only (gathered into a batch of their own): one pass over the hits instead of one per
    shape over all of them, plus a fixed cost per shape. Same values either way."""
    shapes = handle.shapes()
    if object_id is None:
        return _read_shapes(handle, si, valid, n, shapes)
    object_id = np.asarray(object_id).reshape(n)
    order = np.argsort(object_id, kind="stable")
    ids, starts = np.unique(object_id[order], return_index=True)
    if np.count_nonzero(ids >= 0) * n <= GATHER_ABOVE:  # only the shapes hit, each at every hit
        return _read_shapes(handle, si, valid, n, [shapes[int(k)] for k in ids if k >= 0])
    import drjit as dr

    mi = handle.mi
    out = _no_materials(n)  # object_id is -1 exactly where nothing is hit: those stay zero
    for k, idx in zip(ids, np.split(order, starts[1:])):
        if k < 0 or shapes[int(k)].bsdf() is None:
            continue
        sub = dr.gather(type(si), si, mi.UInt32(idx.astype(np.uint32)))
        m = _read_shapes(handle, sub, mi.Bool(np.ones(idx.size, bool)), int(idx.size), [shapes[int(k)]])
        for key in out:
            out[key][idx] = m[key]
    return out


def _no_materials(n: int) -> dict:
    """``read_materials``' fields for ``n`` hits, all zero."""
    return {"diffuse_albedo": np.zeros((n, 3), np.float32), "specular_albedo": np.zeros((n, 3), np.float32),
            "roughness": np.zeros(n, np.float32)}


def _read_shapes(handle: SceneHandle, si, valid, n: int, shapes) -> dict:
    """``read_materials`` of the hits of ``si`` on ``shapes`` (each shape's hits: ``si.shape`` equal to it)."""
    import warnings

    mi = handle.mi
    valid_np = np.array(valid, dtype=bool).reshape(n)
    out = _no_materials(n)

    def read(bsdf, active):
        """(diffuse, specular, alpha) of one BSDF at every hit (only ``active`` ones matter)."""
        name = bsdf.class_name()
        attr = lambda key, c, default: _attribute(bsdf, key, si, active, c, default, n)  # noqa: E731
        zero3, one = np.zeros((n, 3), np.float32), np.ones(n, np.float32)
        if name in ("TwoSidedBRDF", "MaskBSDF"):
            kids = _child_objects(bsdf, mi)
            inner = kids.get("brdf_0") or kids.get("bsdf") or next((v for v in kids.values() if isinstance(v, mi.BSDF)),
                                                                    None)
            if inner is not None:
                return read(inner, active)
        if name in ("SmoothDiffuse", "RoughDiffuse"):
            return attr("reflectance", 3, 0.5), zero3, one
        if name in ("SmoothConductor", "RoughConductor"):
            eta, k = attr("eta", 3, 0.0), attr("k", 3, 1.0)
            f0 = (np.square(eta - 1.0) + np.square(k)) / np.maximum(np.square(eta + 1.0) + np.square(k), 1e-12)
            alpha = attr("alpha", 1, np.nan)
            if np.isnan(alpha).all():
                alpha = 0.5 * (attr("alpha_u", 1, 0.0) + attr("alpha_v", 1, 0.0))
            return zero3, f0 * attr("specular_reflectance", 3, 1.0), alpha
        if name in ("SmoothPlastic", "RoughPlastic", "SmoothDielectric", "RoughDielectric", "ThinDielectric"):
            f0 = _dielectric_f0(attr("eta", 1, 1.5))[:, None] * attr("specular_reflectance", 3, 1.0)
            diffuse = _plastic_diffuse(bsdf, si, active, n, mi) if "Plastic" in name else zero3
            return diffuse, f0, attr("alpha", 1, 0.0)
        if name == "Principled":
            base, metallic = attr("base_color", 3, 0.5), attr("metallic", 1, 0.0)[:, None]
            spec, trans = attr("specular", 1, 0.5)[:, None], attr("spec_trans", 1, 0.0)[:, None]
            rough = attr("roughness", 1, 0.5)
            return ((1.0 - metallic) * (1.0 - trans) * base, (1.0 - metallic) * 0.08 * spec + metallic * base,
                    np.square(rough))
        if name == "BlendBSDF":
            kids = _child_objects(bsdf, mi)
            w = attr("weight", 1, 0.5)[:, None]
            (d0, s0, a0), (d1, s1, a1) = read(kids["bsdf_0"], active), read(kids["bsdf_1"], active)
            m0, m1 = (1.0 - w[:, 0]) * s0.mean(axis=1), w[:, 0] * s1.mean(axis=1)
            both = m0 + m1
            alpha = np.where(both > 0, (m0 * a0 + m1 * a1) / np.where(both > 0, both, 1.0),
                             (1.0 - w[:, 0]) * a0 + w[:, 0] * a1)
            return (1.0 - w) * d0 + w * d1, (1.0 - w) * s0 + w * s1, alpha
        if name not in _WARNED:
            _WARNED.add(name)
            warnings.warn(f"G-buffer: BSDF {name} is not one jprt reads; approximated as diffuse with Mitsuba's "
                          f"eval_diffuse_reflectance and no specular lobe", stacklevel=3)
        a = np.array(bsdf.eval_diffuse_reflectance(si, active), dtype=np.float32)
        return (a.T if a.ndim == 2 else a).reshape(n, 3), zero3, one

    for shape in shapes:
        active = valid & (si.shape == mi.ShapePtr(shape))
        hit = np.array(active, dtype=bool).reshape(n)
        if not hit.any() or shape.bsdf() is None:
            continue
        d, s, a = read(shape.bsdf(), active)
        has_spec = np.asarray(s).max(axis=1) > 0
        out["diffuse_albedo"][hit] = np.maximum(d[hit], 0.0)
        out["specular_albedo"][hit] = np.clip(s[hit], 0.0, 1.0)
        out["roughness"][hit] = np.where(has_spec[hit], np.clip(a[hit], 0.0, 1.0), 1.0)
    for key in out:
        out[key][~valid_np] = 0.0
    return out


def object_materials(handle: SceneHandle) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per shape of the scene, its material at its first vertex-free query point (a default
    surface interaction: textures at uv = 0): (specular_albedo (S, 3), roughness (S,),
    has_diffuse (S,) bool). A summary for reports; G-buffers read per pixel (``read_materials``)."""
    mi = handle.mi
    specular, roughness, has_diffuse = [], [], []
    for shape in handle.shapes():
        si = mi.SurfaceInteraction3f()
        si.shape = mi.ShapePtr(shape)
        m = _read_one(handle, si)
        specular.append(m["specular_albedo"][0])
        roughness.append(float(m["roughness"][0]))
        has_diffuse.append(bool(m["diffuse_albedo"][0].max() > 0))
    return np.stack(specular).astype(np.float32), np.asarray(roughness, np.float32), np.asarray(has_diffuse)


def view_dependent_objects(handle: SceneHandle) -> list[int]:
    """Ids of the shapes whose material reflects or transmits other than diffusely (a glossy or
    delta lobe: rough and smooth plastics, conductors, glass), read from Mitsuba's BSDF flags
    (a ``twosided`` BSDF reports its sides'). Their outgoing indirect light depends on the view
    direction; a diffuse material's does not. Shapes without a BSDF (emitters only) are not
    listed."""
    mi = handle.mi
    lobes = (mi.BSDFFlags.Glossy, mi.BSDFFlags.DeltaReflection, mi.BSDFFlags.DeltaTransmission)
    out = []
    for k, shape in enumerate(handle.shapes()):
        bsdf = shape.bsdf()
        if bsdf is not None and any(mi.has_flag(bsdf.flags(), f) for f in lobes):
            out.append(k)
    return out


def _read_one(handle: SceneHandle, si) -> dict:
    return read_materials(handle, si, handle.mi.Bool(True), 1)


def hit_objects(handle: SceneHandle, si) -> np.ndarray:
    """(N,) int64 object id (index into ``handle.shapes()``) of each hit of a surface-interaction
    batch, -1 where the ray escaped.

    A hit's shape pointer is a Dr.Jit registry id; one table from the scene's shapes' ids to their
    indices reads every hit at once, instead of a pass over all hits per shape (slow on files of
    hundreds of shapes)."""
    import drjit as dr

    mi = handle.mi
    valid = np.array(si.is_valid(), bool).reshape(-1)
    raw = np.array(dr.reinterpret_array(mi.UInt32, si.shape), np.int64).reshape(-1)
    ids = np.array([int(np.array(dr.reinterpret_array(mi.UInt32, mi.ShapePtr(shape)))[0])
                    for shape in handle.shapes()], np.int64)
    table = np.full(int(max(ids.max(initial=0), raw.max(initial=0))) + 1, -1, np.int64)
    table[ids] = np.arange(ids.size)
    return np.where(valid, table[raw], -1)


def _hits(handle: SceneHandle, ray, n: int) -> dict:
    """Flat (n, ...) first-hit attributes of a Dr.Jit ray batch (see ``GBuffer`` for the fields)."""
    mi = handle.mi
    import drjit as dr

    si = handle.scene.ray_intersect(ray)
    valid = si.is_valid()
    nrm = si.sh_frame.n
    v = -ray.d
    flip = dr.select(dr.dot(nrm, v) < 0, -1.0, 1.0)
    nrm = nrm * flip
    ndotv = dr.dot(nrm, v)
    r = 2.0 * ndotv * nrm - v

    def arr(value, c):
        a = np.array(value, dtype=np.float32)
        a = a.T if a.ndim == 2 else a
        return a.reshape(n, c) if c > 1 else a.reshape(n)

    valid_np = np.array(valid, dtype=bool).reshape(n)
    mask = valid_np[:, None]
    object_np = hit_objects(handle, si).astype(np.int32).reshape(n)
    materials = read_materials(handle, si, valid, n, object_np)

    def unit(a):
        norm = np.linalg.norm(a, axis=-1, keepdims=True)
        return np.where(mask, a / np.maximum(norm, 1e-12), 0.0).astype(np.float32)

    return dict(
        position=np.where(mask, arr(si.p, 3), 0.0).astype(np.float32),
        normal=unit(arr(nrm, 3)),
        view=unit(arr(v, 3)),
        reflected=unit(arr(r, 3)),
        uv=np.where(mask, arr(si.uv, 2), 0.0).astype(np.float32),
        **materials,
        object_id=object_np,
        valid=valid_np,
    )


def gbuffer(handle: SceneHandle, camera: Camera) -> GBuffer:
    """Exact pixel-centre G-buffer of ``camera`` in the scene of ``handle``."""
    mi = handle.mi
    import drjit as dr

    sensor = mi.load_dict(to_sensor_dict(camera, 1, mi))
    w, h = camera.width, camera.height
    idx = dr.arange(mi.UInt32, w * h)
    x = mi.Float(idx % w) + 0.5
    y = mi.Float(idx // w) + 0.5
    film_pos = mi.Point2f(x / w, y / h)
    ray, _ = sensor.sample_ray(mi.Float(0.0), mi.Float(0.5), film_pos, mi.Point2f(0.5, 0.5))
    flat = _hits(handle, ray, w * h)
    return GBuffer(**{k: v.reshape((h, w) + v.shape[1:]) for k, v in flat.items()})


def gbuffer_rays(handle: SceneHandle, origins, directions) -> GBuffer:
    """First-hit attributes of arbitrary rays: a ``GBuffer`` whose fields are (N, ...) instead of
    (H, W, ...) (training samples of Ren et al. 2013, Appendix A: attributes at the first
    intersection of random viewing rays). ``view`` is minus the ray direction."""
    mi = handle.mi
    o, d = check_rays(origins, directions)
    ray = mi.Ray3f(mi.Point3f(o[:, 0], o[:, 1], o[:, 2]), mi.Vector3f(d[:, 0], d[:, 1], d[:, 2]))
    return GBuffer(**_hits(handle, ray, o.shape[0]))
