"""Rendering with Radiance Regression Functions (Ren, Wang, Gong, Lin, Tong, Guo 2013, Eq. 8, Eq. 9).

Every pixel's indirect radiance is Eq. 9's sum over the frame's lights k of c_k Phi(x_p, v, l_k,
n, a), Phi the network (Eq. 8) of the kd-tree leaf (§4) its inputs fall in under light k.
``render_frame`` evaluates it for a G-buffer without sorting pixels by leaf: the image is cut
into tiles, every (leaf, tile) pair some pixel needs is one work item, and each chunk of items
of one leaf is one dense product per layer (``_predict_tiles``), with the light-free part of the
first layer shared by every light whose inputs fall in that leaf. ``_predict_sorted`` is the
same function for samples in any order (the tests' oracle).

``RENDER_LAYOUTS`` / ``render_layout`` pick the tile and chunk sizes; ``raw_thresholds`` maps the
tree's normalised split values back to the units of x, so traversal needs no division per pixel.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from jprt.methods.rrf import kdtree
from jprt.methods.rrf.features import ATTRIBUTE_SETS, attribute_columns, unit
from jprt.methods.rrf.fitting import layer_sizes, network, tree_of

__all__ = ["RENDER_LAYOUTS", "render_layout", "raw_thresholds", "render_frame", "render_dense", "GBUFFER_FIELDS",
           "gbuffer_arrays", "rational_tanh"]


#: ``render.tile`` x ``render.chunk`` by JAX backend when the config leaves them None, each the
#: fastest one-light 512^2 frame of ``benchmarks/device_evaluators.py`` on that kind of device: on
#: a CPU small tiles and chunks keep a chunk's activations in cache; on a GPU each loop step is a
#: few kernel launches, so fewer, larger steps win (frame times by layout: the docs' "Evaluators
#: on a GPU" benchmark page, generated from benchmarks/results/device_evaluators.json).
RENDER_LAYOUTS = {"cpu": (8, 64), "gpu": (32, 64)}


def render_layout(render: dict, backend: str | None = None) -> tuple[int, int]:
    """(tile, chunk) of the tiled renderer: ``render["tile"]`` and ``render["chunk"]`` where set,
    else ``RENDER_LAYOUTS`` of ``backend`` (default: JAX's default backend; others take the GPU's).

    Numerics: not differentiable (a layout choice; every layout gives the same image).
    """
    auto = RENDER_LAYOUTS.get(backend or jax.default_backend(), RENDER_LAYOUTS["gpu"])
    tile = auto[0] if render.get("tile") is None else int(render["tile"])
    chunk = auto[1] if render.get("chunk") is None else int(render["chunk"])
    if tile < 1 or chunk < 1:
        raise ValueError(f"render.tile and render.chunk must be >= 1 (or None: automatic), got {tile}, {chunk}")
    return tile, chunk


#: tanh(x) = x P(x^2) / Q(x^2) on |x| <= 7.905 (+-1 beyond in float32): the 13/6 minimax rational
#: approximation Eigen uses for float tanh (generic_fast_tanh_float), written out so the renderer's
#: hidden layers stay one fused multiply-add chain (XLA's tanh streams each layer through memory
#: again on this CPU: 2-4x slower per element). Within 3.2e-7 of tanh in float64, about 5 float32 ulps
#: near +-1 (XLA's own tanh: 2.6e-7; tested).
_TANH_P = (-2.76076847742355e-16, 2.00018790482477e-13, -8.60467152213735e-11, 5.12229709037114e-08,
           1.48572235717979e-05, 6.37261928875436e-04, 4.89352455891786e-03)
_TANH_Q = (1.19825839466702e-06, 1.18534705686654e-04, 2.26843463243900e-03, 4.89352518554385e-03)


def rational_tanh(x):
    """tanh by the rational approximation above (float32): the renderer's, and the network rate's
    (``model.network_rate_gflops``).

    Numerics: not differentiable (the float32 run-time tanh of the networks, tested against tanh in float64).
    """
    x = jnp.clip(x, -7.90531110763549805, 7.90531110763549805)
    x2 = x * x
    p = functools.reduce(lambda acc, c: acc * x2 + c, _TANH_P[1:], jnp.full_like(x, _TANH_P[0]))
    q = functools.reduce(lambda acc, c: acc * x2 + c, _TANH_Q[1:], jnp.full_like(x, _TANH_Q[0]))
    return x * p / q


def _leaf_apply(leaves, leaf, x, *, clamp: bool):
    """Phi_N of Eq. 8 (``jprt.nn.mlp`` apply) for rows ``x`` (B, R, D), the network of leaf
    ``leaf[b]`` on row block b; with ``clamp`` the inputs first clipped to the range of the leaf's
    training samples (a tanh network is not extrapolated; a feature constant in training stays at
    its constant)."""
    per_block = jax.tree_util.tree_map(lambda a: a[leaf], leaves)
    if clamp:
        x = jnp.clip(x, per_block["scaling"]["in_min"][:, None, :], per_block["scaling"]["in_max"][:, None, :])
    return jax.vmap(network(layer_sizes(leaves["layers"])).apply)(per_block, x)


def _leaf_of(params, x, object_id):
    """kd-tree leaf of each sample x (..., D) of objects ``object_id`` (...,); -1 for objects
    without a tree (or object_id < 0)."""
    obj = jnp.clip(object_id, 0, params["obj_lo"].shape[0] - 1)
    return kdtree.traverse(tree_of(params), object_id, unit(x, params["obj_lo"][obj], params["obj_hi"][obj], jnp))


def _predict_sorted(params, x, object_id, block: int = 512, clamp: bool = True):
    """Phi(x) for samples x (N, D) of objects ``object_id`` (N,) in any order; 0 for samples of
    objects without a tree (or object_id < 0).

    Samples are sorted by leaf into a padded layout where every leaf owns whole blocks of
    ``block`` samples, so each block is one small dense matrix product with its leaf's weights
    (N + (L + 1) x block padded rows). For samples in any order (the tests' oracle); on images
    the renderer's ``_predict_tiles`` gives the same numbers without XLA's sort and scatter, which
    dominate this function's time on a CPU."""
    n, d = x.shape
    leaves = params["leaves"]
    n_leaves = leaves["layers"][0]["w"].shape[0]
    leaf = _leaf_of(params, x, object_id)
    group = jnp.where(leaf >= 0, leaf, n_leaves)  # group n_leaves: no network, output 0
    counts = jnp.bincount(group, length=n_leaves + 1)
    padded = (counts + block - 1) // block * block
    ends = jnp.cumsum(padded)
    starts = ends - padded
    order = jnp.argsort(group, stable=True)
    g_sorted = group[order]
    rank = jnp.arange(n) - (jnp.cumsum(counts) - counts)[g_sorted]
    dest = starts[g_sorted] + rank
    n_blocks = -(-(n + (n_leaves + 1) * block) // block)
    xp = jnp.zeros((n_blocks * block, d), x.dtype).at[dest].set(x[order])
    block_group = jnp.searchsorted(ends, jnp.arange(n_blocks) * block, side="right")
    has_net = block_group < n_leaves
    y = _leaf_apply(leaves, jnp.minimum(block_group, n_leaves - 1), xp.reshape(n_blocks, block, d), clamp=clamp)
    y = jnp.where(has_net[:, None, None], y, 0.0).reshape(n_blocks * block, -1)
    return jnp.zeros((n, y.shape[-1]), y.dtype).at[order].set(y[dest])


def _tile_leaves(leaf, n_leaves: int):
    """Which leaves occur in each tile: ``leaf`` (K, th, tile, tw, tile) leaf ids (-1: none) ->
    (n_leaves, th, tw) bool. Each id is one bit of a 32-bit word, OR-reduced over the tile's
    pixels and the lights: one pass over the pixels per 32 leaves (a one-hot comparison against
    every leaf is one pass per leaf, and was a sixth of a one-light frame)."""
    words = []
    for w in range(-(-n_leaves // 32)):
        mine = (leaf >= 32 * w) & (leaf < 32 * (w + 1))
        bits = jnp.where(mine, jnp.left_shift(jnp.uint32(1), (leaf - 32 * w).astype(jnp.uint32) & 31), jnp.uint32(0))
        words.append(jax.lax.reduce(bits, jnp.uint32(0), jax.lax.bitwise_or, (0, 2, 4)))  # (th, tw)
    bit = jnp.arange(n_leaves, dtype=jnp.uint32)
    word = jnp.stack(words)[bit // 32]  # (L, th, tw)
    return (jnp.right_shift(word, (bit % 32)[:, None, None]) & 1) == 1


def _predict_tiles(params, parts, light_pos, light_rgb, object_id, *, light_cols: tuple, tile: int, chunk: int,
                   clamp: bool, nonnegative: bool):
    """Eq. 9, sum over lights k of c_k Phi(x_p, l_k) (each term max(., 0) with ``nonnegative``),
    for the pixels of an H x W image without a sort or a per-pixel scatter: (H, W, R).

    ``parts`` is a list of (H, W, c_i) arrays whose concatenation is every input of x but the
    light position, in x's column order; the light's columns in x are ``light_cols``;
    ``object_id`` (H, W) (-1: no network, output 0). The image is cut into ``tile`` x ``tile``
    pixel tiles (neighbouring pixels' leaves agree almost everywhere). Every (leaf, tile) pair
    that some pixel of the tile needs under some light is one work item (``_tile_leaves``).
    Items are listed leaf by leaf, each leaf's list padded to whole chunks of ``chunk`` items, so
    a chunk is one network applied to ``chunk`` x tile^2 pixels: one dense product per layer,
    features x pixels (the layout XLA's CPU dot runs fastest for layers 20 wide), in cache. A
    loop runs over exactly the chunks there are; each finds its items by cumulative sums and a
    binary search, reads its tiles straight from the G-buffer parts (one gather of tile-sized
    slices per part, fused with the clip to the leaf's range and one transposing copy to features
    x pixels), and adds its result into the output, kept as R planes of tile rows (R, tiles,
    tile^2), by one indexed add of whole tile rows (the chunk's items are distinct tiles). The
    light is constant over a frame, so its part of the first layer is one bias per (leaf, light),
    as is the input scaling (folded into the weights), and the rest of the first layer, the
    widest product, is computed once for all the lights whose inputs fall in the leaf (Eq. 9's
    sum shares the position / view / normal / BRDF part)."""
    hh, ww = object_id.shape
    k = light_pos.shape[0]
    leaves = params["leaves"]
    layers = leaves["layers"]
    n_leaves = layers[0]["w"].shape[0]
    n_out = light_rgb.shape[-1]
    ds = sum(int(q.shape[-1]) for q in parts)
    lc = np.asarray(light_cols)
    d = ds + 3
    rest = np.asarray([c for c in range(d) if c not in light_cols])
    th, tw = -(-hh // tile), -(-ww // tile)
    n_tiles, tp = th * tw, tile * tile
    if (th * tile, tw * tile) != (hh, ww):
        pad = ((0, th * tile - hh), (0, tw * tile - ww))
        parts = [jnp.pad(q, pad + ((0, 0),)) for q in parts]
        object_id = jnp.pad(object_id, pad, constant_values=-1)
    where = np.cumsum([0] + [int(q.shape[-1]) for q in parts])  # x column c_s of shared is in part i
    # params are constants of the program: the trees' thresholds are mapped once from each object's
    # unit box back to x's own units (``raw_thresholds``), so traversal compares each pixel's raw
    # inputs, selected per node without a per-pixel gather of x's columns or a division
    tree = tree_of(params)
    tree = tree._replace(threshold=jnp.asarray(raw_thresholds(params)))
    split_axes = [int(a) for a in np.unique(np.asarray(params["tree"]["axis"])) if a >= 0]
    # no node splits the light: every light of the frame falls in each pixel's one leaf
    shared_leaf = not any(a in light_cols for a in split_axes)

    def column(cs):  # column cs of the shared inputs, (H, W)
        i = int(np.searchsorted(where, cs, side="right") - 1)
        return parts[i][..., cs - where[i]]

    def leaf_under(lp):  # kd-tree leaf of every pixel under light lp, x never materialised
        raw = {a: lp[a - int(lc[0])] if a in light_cols else column(int(np.flatnonzero(rest == a)[0]))
               for a in split_axes}

        def value(axis):
            out = jnp.zeros(axis.shape, jnp.float32)
            for a, v in raw.items():
                out = jnp.where(axis == a, v, out)
            return out

        return kdtree.traverse(tree, object_id, None, column=value)

    leaf = jnp.stack([leaf_under(light_pos[kk]) for kk in range(1 if shared_leaf else k)])  # (K or 1, H, W)
    kl = leaf.shape[0]
    present = _tile_leaves(leaf.reshape(kl, th, tile, tw, tile), n_leaves).reshape(n_leaves, n_tiles)  # (L, T)
    rank = jnp.cumsum(present.astype(jnp.int32), axis=1)  # (L, T): 1 + the item's rank in its leaf's list
    count = rank[:, -1]
    padded = (count + chunk - 1) // chunk * chunk
    end = jnp.cumsum(padded)
    start = end - padded
    # the r-th present tile of leaf l: leaf l's ranks offset by l (T + 1) are one increasing list
    keys = (rank + (jnp.arange(n_leaves) * (n_tiles + 1))[:, None]).reshape(-1)

    def tiled(a):  # (H, W, ...) -> (T, tile^2, ...): each tile's pixels contiguous, tiles in raster order
        rest_shape = a.shape[2:]
        a = a.reshape((th, tile, tw, tile) + rest_shape)
        return jnp.swapaxes(a, 1, 2).reshape((n_tiles, tp) + rest_shape)

    leaf_t = jax.vmap(tiled)(leaf)  # (K, T, tile^2)

    def tiles_of(a, y0, x0):  # the tiles at (y0, x0) of an (H, W, ...) array: (chunk, tile, tile, ...)
        size = (tile, tile) + a.shape[2:]
        return jax.vmap(lambda y, x: jax.lax.dynamic_slice(a, (y, x) + (0,) * (a.ndim - 2), size))(y0, x0)

    def chunk_body(c, out):  # chunk c: its leaf's network on its tiles' pixels, added into out
        slot = c * chunk + jnp.arange(chunk)
        lf = jnp.clip(jnp.searchsorted(end, c * chunk, side="right", method="compare_all"), 0, n_leaves - 1)
        r = slot - start[lf]
        live = r < count[lf]
        tl = jnp.searchsorted(keys, lf * (n_tiles + 1) + r + 1, side="left", method="scan_unrolled") - lf * n_tiles
        tl = jnp.where(live, jnp.clip(tl, 0, n_tiles - 1), 0)
        mine = (leaf_t[:, tl] == lf) & live[None, :, None]  # (K or 1, chunk, tile^2)
        mine = mine.reshape(kl, chunk * tp)
        s = jax.tree_util.tree_map(lambda a: a[lf], leaves["scaling"])
        y0, x0 = tl // tw * tile, tl % tw * tile
        z = jnp.concatenate([tiles_of(q, y0, x0) for q in parts], axis=-1).reshape(chunk * tp, ds)  # (N, Ds)
        zl = light_pos  # (K, 3)
        if clamp:
            z = jnp.clip(z, s["in_min"][rest][None, :], s["in_max"][rest][None, :])
            zl = jnp.clip(zl, s["in_min"][lc][None, :], s["in_max"][lc][None, :])
        zl = (zl - s["in_center"][lc][None, :]) / s["in_halfrange"][lc][None, :]
        w0 = layers[0]["w"][lf]
        # the input scaling folded into the first layer: W^T (z - c) / h = (W / h)^T z - (W / h)^T c
        w_rest = w0[rest] / s["in_halfrange"][rest][:, None]  # (Ds, H1)
        # (H1, N): the light-free part, once for all lights. The barrier keeps z's transpose a copy
        # of its own: fused into the product as a transposed operand, XLA's CPU dot ran at about
        # half the rate
        h0 = w_rest.T @ jax.lax.optimization_barrier(z.T)
        bias = zl @ w0[lc] + layers[0]["b"][lf][None, :] - (s["in_center"][rest] @ w_rest)[None, :]  # (K, H1)

        def light_term(kk, y_sum):  # light kk's term of Eq. 9 on the chunk's pixels of this leaf
            h = rational_tanh(h0 + bias[kk][:, None])
            for i, layer in enumerate(layers[1:], start=1):
                h = layer["w"][lf].T @ h + layer["b"][lf][:, None]
                h = rational_tanh(h) if i < len(layers) - 1 else h
            y = h * s["out_halfrange"][:, None] + s["out_center"][:, None]
            y = jnp.maximum(y, 0.0) if nonnegative else y
            y = y * light_rgb[kk][:, None]
            return y_sum + (y if kl == 1 else jnp.where(mine[kk][None, :], y, 0.0))

        y_sum = jnp.zeros((n_out, chunk * tp), h0.dtype)
        for kk in range(k):  # Eq. 9's sum; where the trees split on the light: skip lights not in this leaf
            y_sum = light_term(kk, y_sum) if kl == 1 else jax.lax.cond(
                jnp.any(mine[kk]), functools.partial(light_term, kk), lambda v: v, y_sum)
        if kl == 1:  # one leaf for every light: the pixels of other leaves masked once
            y_sum = jnp.where(mine[0][None, :], y_sum, 0.0)
        # into each item's tile, one indexed add for the chunk (padding items add zeros to tile 0)
        return out.at[:, tl].add(y_sum.reshape(n_out, chunk, tp))

    out = jnp.zeros((n_out, n_tiles, tp), light_rgb.dtype)  # output planes, tile rows (no transpose per chunk)
    out = jax.lax.fori_loop(0, end[-1] // chunk, chunk_body, out)
    out = jnp.moveaxis(out.reshape(n_out, th, tw, tile, tile), 0, -1)  # (th, tw, tile, tile, R)
    out = jnp.swapaxes(out, 1, 2).reshape(th * tile, tw * tile, n_out)
    return out[:hh, :ww]


def raw_thresholds(params) -> np.ndarray:
    """Every kd-tree node's split value in the units of x (M,) float32: the normalised threshold
    t of its axis a mapped back through its object's box, lo_a + t (hi_a - lo_a) (``unit``'s
    inverse, a constant axis's span taken as 1, as there); leaves keep their value. Comparing raw
    inputs against these is the traversal of normalised inputs up to float rounding at the
    boundary itself, without a per-sample division.

    Numerics: not differentiable (split values of a trained tree).
    """
    tree = kdtree.KDTree(*(np.asarray(a) for a in tree_of(params)))
    owner = np.maximum(kdtree.node_objects(tree), 0)
    axis = np.maximum(tree.axis, 0)
    lo = np.asarray(params["obj_lo"], np.float64)[owner, axis]
    span = np.asarray(params["obj_hi"], np.float64)[owner, axis] - lo
    span = np.where(span > 1e-8, span, 1.0)
    return np.where(tree.axis >= 0, lo + np.asarray(tree.threshold, np.float64) * span,
                    tree.threshold).astype(np.float32)


def _frame_inputs(params, gb: dict, light_pos, edit, *, attributes: str, material: bool, clamp: bool):
    """What both frame programs take from their arguments: the lights (moved onto the trained box
    with ``clamp``), x of ``features`` without its light columns as a list of (H, W, c) parts in
    x's column order, the light's columns in x, and each pixel's object (-1 where invalid)."""
    h, w = gb["object_id"].shape
    if clamp:
        light_pos = jnp.clip(light_pos, params["light_lo"][None, :], params["light_hi"][None, :])
    # the BRDF attributes stay three parts (``brdf_vector``'s columns in its order): XLA's CPU
    # concatenation along the minor axis of a 512^2 x 7 array alone took 3.7 ms of a 19 ms frame
    parts = {"position": [gb["position"]], "normal": [gb["normal"]],
             "view": [jnp.broadcast_to(edit, (h, w, 2)) if material else gb["view"]],
             "brdf": [gb["diffuse_albedo"], gb["specular_albedo"], gb["roughness"][..., None]]}
    light_cols = tuple(range(*attribute_columns(attributes, "material" if material else "view")["light"]))
    shared = [jnp.asarray(q, jnp.float32) for n in ATTRIBUTE_SETS[attributes] if n != "light" for q in parts[n]]
    return light_pos, shared, light_cols, jnp.where(gb["valid"], gb["object_id"], -1)


def render_frame(params, gb: dict, light_pos, light_rgb, edit, *, attributes: str, material: bool,
                 clamp: bool, render: dict):
    """Eq. 9 for every pixel of ``gb`` (``gbuffer_arrays``): sum over lights k of c_k
    max(Phi(x_p, v, l_k, n, a), 0) (indirect radiance is never negative; the clamp is per light,
    so the image stays linear in the light colours). ``light_pos`` / ``light_rgb`` (K, 3),
    ``edit`` (2,) (material mode), ``clamp``: lights moved onto the trained box first;
    ``render``: the config's ``render`` section. Returns (H, W, 3).

    Numerics: not differentiable (the float32 run-time program: kd-tree traversal and per-leaf tanh networks, covered by ``jprt.nn.mlp``).
    """
    light_pos, shared, light_cols, obj = _frame_inputs(params, gb, light_pos, edit, attributes=attributes,
                                                       material=material, clamp=clamp)
    tile, chunk = render_layout(render)
    return _predict_tiles(params, shared, light_pos, light_rgb, obj, light_cols=light_cols, tile=tile,
                          chunk=chunk, clamp=bool(render["clamp_inputs"]),
                          nonnegative=bool(render["nonnegative"]))


#: G-buffer fields Eq. 9 reads, with their dtypes.
GBUFFER_FIELDS = {"position": jnp.float32, "normal": jnp.float32, "view": jnp.float32,
                  "diffuse_albedo": jnp.float32, "specular_albedo": jnp.float32, "roughness": jnp.float32,
                  "object_id": jnp.int32, "valid": bool}


def gbuffer_arrays(gb) -> dict:
    """The fields of ``gb`` that Eq. 9 reads, as JAX arrays of fixed dtypes (so a G-buffer from
    any source traces to the same program).

    Numerics: not differentiable (a dtype conversion of the inputs).
    """
    return {name: jnp.asarray(getattr(gb, name), dtype) for name, dtype in GBUFFER_FIELDS.items()}



def render_dense(params, gb: dict, light_pos, light_rgb, edit, *, attributes: str, material: bool,
                 clamp: bool, render: dict):
    """``render_frame``'s image (Eq. 9) by a program reverse-mode differentiation goes through:
    every pixel's kd-tree leaf under each light is found on the inputs with their gradient stopped
    (the leaf is piecewise constant in the light), then each pixel's input x (the light's columns
    included, so the gradient reaches the light) goes through its own leaf's network, the
    weights gathered per pixel: one batched matrix-vector product per layer. No loop with a
    data-dependent trip count (the tiled renderer's), so ``jax.grad`` of an objective of the image
    is one program; it costs a gather of every pixel's weights per light, a few times the tiled
    frame, which is for display. Same arguments and result as ``render_frame`` (the tanh is
    XLA's, not the rational one: within 3e-7).

    Differentiable in ``light_pos`` and ``light_rgb`` (reverse and forward mode) except on the
    leaves' boundaries, where the image jumps from one leaf's network to the next.

    Numerics: not differentiable (the float32 gradient program of per-leaf ``jprt.nn.mlp`` networks, covered there; its gradient is checked in tests/methods/test_rrf.py).
    """
    h, w = gb["object_id"].shape
    light_pos, shared, light_cols, obj = _frame_inputs(params, gb, light_pos, edit, attributes=attributes,
                                                       material=material, clamp=clamp)
    lc0, lc1 = light_cols[0], light_cols[-1] + 1
    shared = jnp.concatenate([q.reshape(h * w, -1) for q in shared], axis=-1)
    obj = obj.reshape(-1)
    leaves = params["leaves"]
    nonnegative = bool(render["nonnegative"])
    out = jnp.zeros((h * w, light_rgb.shape[-1]), jnp.float32)
    for k in range(light_pos.shape[0]):  # Eq. 9's sum over the frame's lights
        light = jnp.broadcast_to(light_pos[k].astype(jnp.float32), (h * w, lc1 - lc0))
        x = jnp.concatenate([shared[:, :lc0], light, shared[:, lc0:]], axis=-1)  # (P, D), x's column order
        leaf = _leaf_of(params, jax.lax.stop_gradient(x), obj)
        y = _leaf_apply(leaves, jnp.maximum(leaf, 0), x[:, None, :], clamp=bool(render["clamp_inputs"]))[:, 0]
        y = jnp.maximum(y, 0.0) if nonnegative else y
        out = out + jnp.where((leaf >= 0)[:, None], y * light_rgb[k][None, :], 0.0)
    return out.reshape(h, w, -1)
