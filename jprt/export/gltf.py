"""Binary glTF 2.0 (``.glb``) of lightmapped meshes, and the RGBM encoding of HDR lightmaps.

Each mesh is written as a triangle list without indices (flat normals: lightmap charts cut the
surface anyway), with ``TEXCOORD_1`` the lightmap atlas's UVs (three.js reads a ``lightMap``
through UV channel 1) and ``TEXCOORD_0`` the mesh's own UVs where it has them, else the atlas's.
Every material refers to the lightmap through the vendor extension ``JPRT_lightmap`` (in the
style of ``MOZ_lightmap``: the texture's index, its UV set, an intensity, plus how the texture
is encoded), since core glTF has no lightmap slot. The lightmap texture is an RGBM PNG embedded
in the binary chunk (glTF images are PNG or JPEG; the float EXR lies beside the ``.glb``).

glTF's UV origin is the image's top-left corner, like the atlas's (row 0 of the atlas image is
v in [0, 1 / R)), so atlas UVs go in unchanged and images are stored row 0 first.
"""

from __future__ import annotations

import io as _io
from typing import NamedTuple, Sequence

import numpy as np

from jprt import io

__all__ = ["EXTENSION", "Mesh", "rgbm_encode", "rgbm_decode", "rgbm_png", "write_glb"]

#: The vendor extension naming a material's lightmap.
EXTENSION = "JPRT_lightmap"

_ARRAY_BUFFER = 34962
_FLOAT = 5126
_LINEAR = 9729
_CLAMP = 33071


class Mesh(NamedTuple):
    """One object of the scene as a triangle list (3 vertices per triangle, float32).

    Fields:
      name: the object's name.  position: (V, 3).  normal: (V, 3) unit.
      uv0: (V, 2) the object's own UVs (or the atlas's).  uv1: (V, 2) atlas UVs.
      base_color: (3,) linear RGB.  metallic, roughness: glTF's factors (roughness perceptual).
    """

    name: str
    position: np.ndarray
    normal: np.ndarray
    uv0: np.ndarray
    uv1: np.ndarray
    base_color: np.ndarray
    metallic: float
    roughness: float


def rgbm_encode(image, value_range: float) -> np.ndarray:
    """(H, W, 3) non-negative linear values -> (H, W, 4) uint8 RGBM: value = rgb / 255 x a / 255
    x ``value_range`` (three.js's RGBM, linear, no gamma). a is the smallest step that holds the
    pixel's largest channel, so the relative error of bright pixels is about 1 / 510."""
    x = np.clip(np.asarray(image, np.float64), 0.0, float(value_range))
    if x.ndim != 3 or x.shape[-1] != 3:
        raise ValueError(f"RGBM encodes (H, W, 3) images, got shape {x.shape}")
    m = np.max(x, axis=-1) / float(value_range)
    a = np.clip(np.ceil(m * 255.0), 1.0, 255.0)
    rgb = np.clip(np.round(x / (a[..., None] / 255.0 * float(value_range)) * 255.0), 0.0, 255.0)
    return np.concatenate([rgb, a[..., None]], axis=-1).astype(np.uint8)


def rgbm_decode(rgbm, value_range: float) -> np.ndarray:
    """Inverse of ``rgbm_encode``: (H, W, 4) uint8 -> (H, W, 3) float32."""
    q = np.asarray(rgbm, np.float64) / 255.0
    return (q[..., :3] * q[..., 3:4] * float(value_range)).astype(np.float32)


def rgbm_png(image, value_range: float) -> bytes:
    """The RGBM encoding of ``image`` as PNG bytes (RGBA, 8 bits per channel)."""
    from PIL import Image

    buf = _io.BytesIO()
    Image.fromarray(rgbm_encode(image, value_range), "RGBA").save(buf, format="PNG")
    return buf.getvalue()


def _pad4(blob: bytearray) -> None:
    blob.extend(b"\x00" * (-len(blob) % 4))


def write_glb(path: str, meshes: Sequence[Mesh], *, lightmap_png: bytes | None, extension: dict | None = None,
              generator: str = "jprt") -> dict:
    """Write ``meshes`` as one binary glTF scene (a node per mesh) to ``path``, with the lightmap
    PNG embedded and referenced from every material by ``EXTENSION`` (``extension``: the fields
    besides the texture's index, e.g. texCoord, intensity, encoding). Returns the glTF JSON as a
    dict (what the ``.glb``'s JSON chunk holds)."""
    import pygltflib as g

    if not meshes:
        raise ValueError("a glTF export needs at least one mesh")
    blob = bytearray()
    views, accessors = [], []

    def add(array, *, attribute: bool = True, bounds: bool = False) -> int:
        a = np.ascontiguousarray(np.asarray(array, np.float32))
        _pad4(blob)
        views.append(g.BufferView(buffer=0, byteOffset=len(blob), byteLength=a.nbytes,
                                  target=_ARRAY_BUFFER if attribute else None))
        blob.extend(a.tobytes())
        kind = {1: "SCALAR", 2: "VEC2", 3: "VEC3", 4: "VEC4"}[a.shape[1]]
        acc = g.Accessor(bufferView=len(views) - 1, byteOffset=0, componentType=_FLOAT, count=int(a.shape[0]),
                         type=kind)
        if bounds:
            acc.min = [float(v) for v in a.min(axis=0)]
            acc.max = [float(v) for v in a.max(axis=0)]
        accessors.append(acc)
        return len(accessors) - 1

    textures, images, samplers = [], [], []
    if lightmap_png is not None:
        _pad4(blob)
        views.append(g.BufferView(buffer=0, byteOffset=len(blob), byteLength=len(lightmap_png)))
        blob.extend(lightmap_png)
        images.append(g.Image(bufferView=len(views) - 1, mimeType="image/png", name="lightmap_rgbm"))
        samplers.append(g.Sampler(magFilter=_LINEAR, minFilter=_LINEAR, wrapS=_CLAMP, wrapT=_CLAMP))
        textures.append(g.Texture(sampler=0, source=0, name="lightmap"))

    nodes, gl_meshes, materials = [], [], []
    for mesh in meshes:
        n = int(np.asarray(mesh.position).shape[0])
        if n == 0 or n % 3:
            raise ValueError(f"mesh {mesh.name!r}: a triangle list needs 3k > 0 vertices, got {n}")
        attributes = g.Attributes(POSITION=add(mesh.position, bounds=True), NORMAL=add(mesh.normal),
                                  TEXCOORD_0=add(mesh.uv0), TEXCOORD_1=add(mesh.uv1))
        material = g.Material(name=mesh.name, doubleSided=True, pbrMetallicRoughness=g.PbrMetallicRoughness(
            baseColorFactor=[float(c) for c in np.clip(mesh.base_color, 0.0, 1.0)] + [1.0],
            metallicFactor=float(np.clip(mesh.metallic, 0.0, 1.0)),
            roughnessFactor=float(np.clip(mesh.roughness, 0.0, 1.0))))
        if lightmap_png is not None:
            material.extensions = {EXTENSION: {"index": 0, **(extension or {})}}
        materials.append(material)
        gl_meshes.append(g.Mesh(name=mesh.name, primitives=[g.Primitive(attributes=attributes,
                                                                        material=len(materials) - 1, mode=4)]))
        nodes.append(g.Node(name=mesh.name, mesh=len(gl_meshes) - 1))
    _pad4(blob)
    gltf = g.GLTF2(asset=g.Asset(version="2.0", generator=generator), scene=0,
                   scenes=[g.Scene(name="jprt", nodes=list(range(len(nodes))))], nodes=nodes, meshes=gl_meshes,
                   materials=materials, accessors=accessors, bufferViews=views,
                   buffers=[g.Buffer(byteLength=len(blob))], textures=textures, images=images, samplers=samplers,
                   extensionsUsed=[EXTENSION] if lightmap_png is not None else [])
    gltf.set_binary_blob(bytes(blob))
    with io.atomic_path(path, suffix=".glb") as tmp:
        gltf.save_binary(tmp)
    return gltf.to_dict()
