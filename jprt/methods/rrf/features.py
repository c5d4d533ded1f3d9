"""The inputs of a Radiance Regression Function (Ren, Wang, Gong, Lin, Tong, Guo 2013, Eq. 4).

Phi's input vector x of one shading point is the concatenation of the *augmented* attributes
(Eq. 4): surface position x_p, unit view direction v, light position l, unit normal n and the
BRDF parameters a (diffuse rgb, specular rgb, GGX alpha); ``ATTRIBUTE_SETS`` names the subsets
Fig. 3 compares. In material-editing mode (Appendix B) the edit parameters (roughness, albedo)
take the place of v.

Before the kd-tree (§4, Fig. 4 c-d) sees them, each object's inputs are mapped to the unit
hypercube of that object's input box (``unit``, ``normalise``): the one rule the fit and the
renderer share.

Pure NumPy / JAX; ``RRFData`` is the per-sample training data ``data.make_dataset`` returns.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["ATTRIBUTE_SETS", "RRFData", "features", "brdf_vector", "data_features", "attribute_columns",
           "split_dims", "input_size", "unit", "normalise"]

#: Inputs of Phi for each attribute set (Ren et al. Fig. 3: basic vs augmented attributes).
ATTRIBUTE_SETS = {
    "basic": ("position", "view", "light"),
    "basic+a": ("position", "view", "light", "brdf"),
    "augmented": ("position", "view", "light", "normal", "brdf"),
    # without v: for a scene whose surfaces are all Lambertian the indirect radiance leaving x does
    # not depend on the view direction (L_o = rho / pi * int L_i cos), so v can only carry the
    # finite set of training views' directions, which a held-out view leaves (view mode only)
    "diffuse": ("position", "light", "normal", "brdf"),
}
_WIDTHS = {"position": 3, "view": 3, "light": 3, "normal": 3, "brdf": 7}


class RRFData(NamedTuple):
    """Per-sample training data (N samples).

    Fields: position, view (unit, surface to camera), light (light position), normal (unit,
    facing the viewer), brdf (diffuse rgb, specular rgb, GGX alpha), edit ((N, 2) roughness and
    albedo of the edited object in material mode, (N, 0) otherwise), object_id (N,), direct and
    indirect (N, 3) radiance for a unit white light, pair (N,) index of the (light, view or
    material) pair, and ``meta`` (a dict: boxes, object names, spp, seed).
    """

    position: np.ndarray
    view: np.ndarray
    light: np.ndarray
    normal: np.ndarray
    brdf: np.ndarray
    edit: np.ndarray
    object_id: np.ndarray
    direct: np.ndarray
    indirect: np.ndarray
    pair: np.ndarray
    meta: dict

    def __len__(self) -> int:
        return int(self.position.shape[0])

    def subset(self, index) -> "RRFData":
        """The samples at ``index`` (bool mask or integer indices)."""
        return RRFData(*(np.asarray(a)[index] for a in self[:-1]), self.meta)


def features(attributes: str, position, view, light, normal, brdf, edit=None):
    """The input vector x of Phi for an attribute set (``ATTRIBUTE_SETS``), last axis features.

    In material mode (``edit`` given, (..., 2)) the edit parameters take the place of ``view``
    (Appendix B). Works on NumPy and JAX arrays of any batch shape.

    Numerics:
        case: rrf_features (every attribute set; positions, lights in [-1e3, 1e3], unit views and
          normals, BRDF attributes in [0, 1])
        float32: value rtol 0 atol 0; grad rtol 1e-6 atol 0
        (a concatenation: exact; the case's gradient sums the cotangents of several attribute sets)
    """
    if attributes not in ATTRIBUTE_SETS:
        raise ValueError(f"unknown attribute set {attributes!r}; use one of {sorted(ATTRIBUTE_SETS)}")
    parts = {"position": position, "view": view if edit is None else edit, "light": light, "normal": normal,
             "brdf": brdf}
    # float32 (NumPy training data is float64); JAX float64 inputs stay float64 (x64 tests)
    wide = any(isinstance(v, jax.Array) and v.dtype == jnp.float64 for v in parts.values())
    dtype = jnp.float64 if wide else jnp.float32
    return jnp.concatenate([jnp.asarray(parts[name], dtype) for name in ATTRIBUTE_SETS[attributes]], axis=-1)


def brdf_vector(diffuse_albedo, specular_albedo, roughness):
    """The BRDF attributes a of Eq. 4 per pixel or sample: diffuse rgb, specular rgb, GGX alpha
    (..., 7). NumPy in, NumPy out (training data); JAX in, JAX out (the evaluator).

    Numerics:
        diffuse_albedo: (16, 3) in [0, 1]
        specular_albedo: (16, 3) in [0, 1]
        roughness: (16,) in [1e-4, 1]
        float32: value rtol 0 atol 0; grad rtol 0 atol 0
        (a concatenation: exact)
    """
    xp = jnp if isinstance(roughness, jax.Array) else np
    return xp.concatenate([diffuse_albedo, specular_albedo, xp.asarray(roughness)[..., None]], axis=-1)


def data_features(data: RRFData, attributes: str) -> np.ndarray:
    """The inputs x of Phi for every sample of ``data`` (N, D).

    Numerics: not differentiable (training data in NumPy).
    """
    edit = data.edit if data.meta.get("mode") == "material" else None
    return np.asarray(features(attributes, data.position, data.view, data.light, data.normal, data.brdf, edit))


def attribute_columns(attributes: str, mode: str = "view") -> dict:
    """{attribute name: (first, end) columns of x} in ``features``' layout for an attribute set
    (the view is 2 wide, the edit, in material mode).

    Numerics: not differentiable (integer columns).
    """
    widths = dict(_WIDTHS, view=2 if mode == "material" else 3)
    out, start = {}, 0
    for name in ATTRIBUTE_SETS[attributes]:
        out[name] = (start, start + widths[name])
        start += widths[name]
    return out


def split_dims(config: dict) -> list[int] | None:
    """The input axes the kd-tree may split under ``config["tree"]["split_on"]``: None where that is
    None (every axis, the paper's), else the columns of the named ``ATTRIBUTE_SETS`` attributes in
    ``features``' layout.

    Numerics: not differentiable (integer axes).
    """
    split_on = config["tree"].get("split_on")
    if split_on is None:
        return None
    columns = attribute_columns(config["model"]["attributes"], config["data"].get("mode", "view"))
    if isinstance(split_on, str) or not set(split_on) <= set(columns) or not split_on:
        raise ValueError(f"tree.split_on must be None or a non-empty list of {list(columns)}, got {split_on!r}")
    return [c for name, (a, b) in columns.items() if name in split_on for c in range(a, b)]


def input_size(attributes: str, mode: str = "view") -> int:
    """Number of inputs of Phi for an attribute set (and data mode).

    Numerics: not differentiable (an integer size).
    """
    return max(end for _, end in attribute_columns(attributes, mode).values())


def unit(x, lo, hi, xp=np):
    """x mapped to the box [lo, hi] -> [0, 1] (§4, Fig. 4 c-d); a constant feature maps to x - lo.
    The one rule of the fit (NumPy) and the renderer (``xp=jnp``).

    Numerics: not differentiable (the kd-tree's input normalisation; its splits are comparisons).
    """
    span = hi - lo
    return (x - lo) / xp.where(span > 1e-8, span, 1.0)


def normalise(x, object_id, obj_lo, obj_hi) -> np.ndarray:
    """Inputs x (N, D) mapped to each object's unit box (``unit``): row i by the box of
    ``object_id[i]`` (a negative id takes object 0's).

    Numerics: not differentiable (the kd-tree's input normalisation, on the host).
    """
    safe = np.maximum(object_id, 0)
    return unit(x, np.asarray(obj_lo)[safe], np.asarray(obj_hi)[safe])
