"""RRF as a GLSL function: Eq. 9 of Ren et al. 2013 (the sum over lights of each pixel's kd-tree
leaf network, Eq. 8) written out for a fragment shader (GLSL ES 3.00, WebGL2), its numbers in one
float texture.

``rrf_shader`` turns a fitted RRF into a ``Shader``: the GLSL source, which declares
``uniform highp sampler2D rrfData`` (an R32F texture ``width`` texels wide) and defines

* ``void rrfInputs(vec3 position, vec3 view, vec3 normal, vec3 diffuse, vec3 specular,
  float roughness, out float x[RRF_D])``: a pixel's G-buffer attributes in the columns of x the
  fit used (``jprt.methods.rrf.features.attribute_columns``; the light's columns left 0);
* ``int rrfLeaf(int object, float x[RRF_D])``: the kd-tree leaf of x in the object's tree (-1:
  the object has none), split values in x's own units (``renderer.raw_thresholds``);
* ``vec3 rrfNetwork(int leaf, float x[RRF_D])``: the leaf's tanh network (Eq. 8), inputs clipped
  to its training range where the fit's renderer clips them;
* ``vec3 rrfIndirect(float x[RRF_D], int object, int count, vec3 lightPos[RRF_MAX_LIGHTS],
  vec3 lightRGB[RRF_MAX_LIGHTS])``: Eq. 9, the indirect radiance of the pixel under ``count``
  point lights, as ``renderer.render_frame`` computes it (each light's term max(., 0) where the
  renderer takes it, lights moved onto the trained box where ``render.extrapolation`` is
  "clamp"; a shader cannot refuse a light, so under "error" it evaluates as "allow" does).

``data`` holds, as float32, the trees (roots, axes, raw thresholds, children, leaf indices;
integers are exact in float32 below 2^24), each leaf's input and output scaling and every
layer's weights and biases; the source names each block's first index as a constant. The
arithmetic is the renderer's in float32 but for GLSL's own ``tanh`` (its argument clipped to +-9,
where float32 tanh is +-1 and an exp-based GLSL tanh would overflow; the renderer uses a rational
approximation within 3.2e-7 of tanh) and the order of the sums.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

__all__ = ["Shader", "rrf_shader", "MAX_LIGHTS", "DATA_WIDTH"]

#: The most point lights one ``rrfIndirect`` call sums (a uniform array's length).
MAX_LIGHTS = 8
#: Texels per row of the data texture (WebGL2 guarantees textures 2048 wide).
DATA_WIDTH = 1024

#: G-buffer attribute -> the argument of ``rrfInputs`` that holds it, component by component.
_ARGUMENTS = {"position": ("position.x", "position.y", "position.z"), "view": ("view.x", "view.y", "view.z"),
              "normal": ("normal.x", "normal.y", "normal.z"),
              "brdf": ("diffuse.r", "diffuse.g", "diffuse.b", "specular.r", "specular.g", "specular.b", "roughness")}


class Shader(NamedTuple):
    """A GLSL function and its data texture.

    Fields:
      source: the GLSL ES 3.00 source (module docstring).
      data: (height, width) float32, the R32F texture ``rrfData``.
      inputs: the columns of x by name (``attribute_columns``), as [name, first, end].
      max_lights: ``MAX_LIGHTS``.
    """

    source: str
    data: np.ndarray
    inputs: list
    max_lights: int


def rrf_shader(params, config: dict) -> Shader:
    """The GLSL of a fitted RRF (module docstring); ``config`` its method config (the attribute
    set, ``render.extrapolation`` / ``clamp_inputs`` / ``nonnegative``).

    Raises ValueError for a material-editing RRF (its x holds the edit, not the view) and for a
    tree larger than float32 indices can hold exactly.

    Numerics: not differentiable (a code generator over trained parameters).
    """
    from jprt.methods.rrf.features import attribute_columns
    from jprt.methods.rrf.fitting import tree_of
    from jprt.methods.rrf.renderer import raw_thresholds

    if config["data"]["mode"] == "material":
        raise ValueError("the GLSL export covers view-mode RRFs; this one was trained for material editing")
    attributes = config["model"]["attributes"]
    columns = attribute_columns(attributes, "view")
    tree = tree_of(params)
    leaves = params["leaves"]
    layers = leaves["layers"]
    scaling = {k: np.asarray(v, np.float32) for k, v in leaves["scaling"].items()}
    n_leaves, d = scaling["in_min"].shape
    sizes = [d] + [int(np.shape(layer["b"])[-1]) for layer in layers]
    if len(np.asarray(tree.axis)) >= 2 ** 24:
        raise ValueError(f"{len(np.asarray(tree.axis))} kd-tree nodes: more than float32 indices hold exactly")

    blocks: list[tuple[str, np.ndarray]] = [
        ("ROOTS", np.asarray(tree.roots)), ("AXIS", np.asarray(tree.axis)), ("THRESHOLD", raw_thresholds(params)),
        ("LEFT", np.asarray(tree.left)), ("RIGHT", np.asarray(tree.right)), ("LEAF", np.asarray(tree.leaf)),
        ("IN_MIN", scaling["in_min"]), ("IN_MAX", scaling["in_max"]), ("IN_CENTER", scaling["in_center"]),
        ("IN_HALF", scaling["in_halfrange"]), ("OUT_CENTER", scaling["out_center"]),
        ("OUT_HALF", scaling["out_halfrange"]),
        ("LIGHT_LO", np.asarray(params["light_lo"])), ("LIGHT_HI", np.asarray(params["light_hi"]))]
    for i, layer in enumerate(layers):
        blocks += [(f"W{i}", np.asarray(layer["w"])), (f"B{i}", np.asarray(layer["b"]))]
    offsets, flat, at = {}, [], 0
    for name, values in blocks:
        offsets[name] = at
        flat.append(np.asarray(values, np.float32).ravel())
        at += flat[-1].size
    data = np.concatenate(flat)
    rows = -(-data.size // DATA_WIDTH)
    data = np.pad(data, (0, rows * DATA_WIDTH - data.size)).reshape(rows, DATA_WIDTH)

    rc = config["render"]
    depth = int(np.max(np.asarray(tree.depth))) if np.asarray(tree.depth).size else 0
    n_layers = len(layers)
    light0 = columns["light"][0]
    x_of = []  # rrfInputs' assignments, column by column
    for name, (first, end) in columns.items():
        if name == "light":
            continue
        x_of += [f"  x[{c}] = {arg};" for c, arg in zip(range(first, end), _ARGUMENTS[name])]
    consts = "\n".join(f"const int RRF_{name} = {offset};" for name, offset in offsets.items())
    source = f"""// Radiance regression functions (Ren et al. 2013, Eq. 8 and Eq. 9), generated by jprt export.
// rrfData: an R32F texture {DATA_WIDTH} texels wide holding every number of the fit (offsets below).
uniform highp sampler2D rrfData;
const int RRF_DATA_WIDTH = {DATA_WIDTH};
const int RRF_D = {d};  // inputs of a leaf network (x of Eq. 8, the light's position included)
const int RRF_LIGHT = {light0};  // x's first light column
const int RRF_OBJECTS = {int(np.asarray(tree.roots).size)};
const int RRF_DEPTH = {depth};  // the deepest kd-tree
const int RRF_HMAX = {max(sizes)};  // the widest layer
const int RRF_LAYERS = {n_layers};
const int RRF_MAX_LIGHTS = {MAX_LIGHTS};
const bool RRF_CLAMP_INPUTS = {str(bool(rc["clamp_inputs"])).lower()};
const bool RRF_NONNEGATIVE = {str(bool(rc["nonnegative"])).lower()};
const bool RRF_CLAMP_LIGHTS = {str(rc["extrapolation"] == "clamp").lower()};
{consts}
const int RRF_SIZES[{n_layers + 1}] = int[]({", ".join(str(s) for s in sizes)});
const int RRF_W[{n_layers}] = int[]({", ".join(str(offsets[f"W{i}"]) for i in range(n_layers))});
const int RRF_B[{n_layers}] = int[]({", ".join(str(offsets[f"B{i}"]) for i in range(n_layers))});

float rrfAt(int i) {{
  return texelFetch(rrfData, ivec2(i % RRF_DATA_WIDTH, i / RRF_DATA_WIDTH), 0).r;
}}

vec3 rrfAt3(int i) {{
  return vec3(rrfAt(i), rrfAt(i + 1), rrfAt(i + 2));
}}

// tanh with its argument clipped to +-9 (tanh(9) is 1 in float32): GLSL implementations may form
// tanh from exp(2x), which overflows to inf / inf = NaN for |x| > 44 (SwiftShader does)
float rrfTanh(float s) {{
  return tanh(clamp(s, -9.0, 9.0));
}}

void rrfInputs(vec3 position, vec3 view, vec3 normal, vec3 diffuse, vec3 specular, float roughness,
               out float x[RRF_D]) {{
  for (int i = 0; i < RRF_D; i++) x[i] = 0.0;
{chr(10).join(x_of)}
}}

int rrfLeaf(int object, float x[RRF_D]) {{
  if (object < 0 || object >= RRF_OBJECTS) return -1;
  int node = int(rrfAt(RRF_ROOTS + object));
  if (node < 0) return -1;
  for (int s = 0; s < RRF_DEPTH; s++) {{
    int axis = int(rrfAt(RRF_AXIS + node));
    if (axis < 0) break;
    node = x[axis] >= rrfAt(RRF_THRESHOLD + node) ? int(rrfAt(RRF_RIGHT + node)) : int(rrfAt(RRF_LEFT + node));
  }}
  return int(rrfAt(RRF_LEAF + node));
}}

vec3 rrfNetwork(int leaf, float x[RRF_D]) {{
  float a[RRF_HMAX];
  float b[RRF_HMAX];
  for (int i = 0; i < RRF_D; i++) {{
    float v = x[i];
    if (RRF_CLAMP_INPUTS) v = clamp(v, rrfAt(RRF_IN_MIN + leaf * RRF_D + i), rrfAt(RRF_IN_MAX + leaf * RRF_D + i));
    a[i] = (v - rrfAt(RRF_IN_CENTER + leaf * RRF_D + i)) / rrfAt(RRF_IN_HALF + leaf * RRF_D + i);
  }}
  for (int l = 0; l < RRF_LAYERS; l++) {{
    int nIn = RRF_SIZES[l];
    int nOut = RRF_SIZES[l + 1];
    int w = RRF_W[l] + leaf * nIn * nOut;
    int bias = RRF_B[l] + leaf * nOut;
    for (int o = 0; o < nOut; o++) {{
      float s = rrfAt(bias + o);
      for (int i = 0; i < nIn; i++) s += a[i] * rrfAt(w + i * nOut + o);
      b[o] = l < RRF_LAYERS - 1 ? rrfTanh(s) : s;
    }}
    for (int o = 0; o < nOut; o++) a[o] = b[o];
  }}
  return vec3(a[0], a[1], a[2]) * rrfAt3(RRF_OUT_HALF + 3 * leaf) + rrfAt3(RRF_OUT_CENTER + 3 * leaf);
}}

vec3 rrfIndirect(float x[RRF_D], int object, int count, vec3 lightPos[RRF_MAX_LIGHTS],
                 vec3 lightRGB[RRF_MAX_LIGHTS]) {{
  vec3 sum = vec3(0.0);
  vec3 lo = rrfAt3(RRF_LIGHT_LO);
  vec3 hi = rrfAt3(RRF_LIGHT_HI);
  for (int k = 0; k < RRF_MAX_LIGHTS; k++) {{
    if (k >= count) break;
    vec3 p = RRF_CLAMP_LIGHTS ? clamp(lightPos[k], lo, hi) : lightPos[k];
    x[RRF_LIGHT] = p.x;
    x[RRF_LIGHT + 1] = p.y;
    x[RRF_LIGHT + 2] = p.z;
    int leaf = rrfLeaf(object, x);
    if (leaf < 0) continue;
    vec3 y = rrfNetwork(leaf, x);
    if (RRF_NONNEGATIVE) y = max(y, vec3(0.0));
    sum += y * lightRGB[k];
  }}
  return sum;
}}
"""
    if int(sizes[-1]) != 3:
        raise ValueError(f"the GLSL export writes RGB networks; this one has {sizes[-1]} outputs")
    return Shader(source, data, [[n, a, b] for n, (a, b) in columns.items()], MAX_LIGHTS)
