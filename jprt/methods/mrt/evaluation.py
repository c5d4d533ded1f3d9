"""What MRT's report measures beyond the method contract (Loos et al. 2011): texel errors of a
layout, the padded-atlas images of texel arrays, per-layout baselines (data-driven PRT, the
ambient term), the reference quadratures of §6.4 and §6.5 (irradiance at tilted normals; the
radiance a probe sees, by marching rays through a layout's open sides) and the run time's frame
time by block count.

Per-texel arrays are (B, 6 t^2, ...) per block (``block_atlas.texels_of``), stacked over lightings
as (L, B, n, 3).
"""

from __future__ import annotations

import time

import jax
import jax.numpy as jnp
import numpy as np

from jprt import eval as jeval
from jprt import layouts
from jprt.methods.mrt import model, operators
from jprt.methods.mrt.block_atlas import atlas_layout, texels_of

__all__ = ["texel_rmse", "atlas_images", "predict", "layout_operators", "energy_counts", "bytes_per_type",
           "datadriven_baseline", "ambient_baseline", "tilted_normals", "march", "tilted_quadrature",
           "volume_reference", "frame_times"]


def texel_rmse(pred, ref, mask) -> tuple[float, float]:
    """RMSE and relative RMSE over the existing texels (``mask`` (B, n)) of (L, B, n, 3) arrays:
    ``jprt.eval.score_images`` with each lighting's texels as one (B, n, 3) image."""
    pred, ref = np.asarray(pred), np.asarray(ref)
    s = jeval.score_images(list(pred), list(ref), [np.asarray(mask, bool)] * len(ref),
                           scores=("indirect_rmse", "indirect_rel_rmse"))
    return s["indirect_rmse"], s["indirect_rel_rmse"]


def atlas_images(texels, albedo_shape) -> list:
    """(L, B, n, 3) texel arrays -> padded-atlas images (R, R, 3) (gutters 0)."""
    b, t = texels_of(np.zeros(albedo_shape))
    res, texel_index, _ = atlas_layout(b, t)
    out = []
    for x in np.asarray(texels, np.float32):
        img = np.zeros((res * res, 3), np.float32)
        img[texel_index] = x.reshape(-1, 3)
        out.append(img.reshape(res, res, 3))
    return out


def predict(params, direct, albedo, cfg: dict, **kw) -> np.ndarray:
    """The run time's indirect texels (``model.lightmap``) of each direct lighting of ``direct``;
    ``kw`` overrides its options (``feedback``, ``interfaces``)."""
    arrays = {k: jnp.asarray(params[k]) for k in model.RUNTIME_KEYS if k in params}
    opts = {"feedback": int(cfg["runtime"]["feedback"]), "interfaces": bool(cfg["interfaces"]["enabled"])} | kw
    return np.asarray(model.lightmap(arrays, jnp.asarray(direct, jnp.float32), jnp.asarray(albedo, jnp.float32),
                                     **opts))


def layout_operators(cfg: dict, layout: dict) -> dict:
    """The operators of ``layout`` from the dictionary of ``cfg`` (both cached by ``jprt.cache``)."""
    return model.layout_operators(model.dictionary(cfg), layout, cfg)


def energy_counts(sv, levels=(0.8, 0.9, 0.95)) -> dict:
    """How many singular values hold each fraction of ``levels`` of the energy (sum of squares)."""
    e = np.cumsum(np.asarray(sv, np.float64) ** 2)
    e = e / e[-1]
    return {f"{int(round(100 * q))}%": int(np.searchsorted(e, q) + 1) for q in levels}


def bytes_per_type(dic: dict) -> dict:
    """Run-time bytes of one dictionary type (float32 T_d->b, U_b, U_quad, U_vol) and of the
    shared interface operators (U_r, R_b for every type)."""
    per = {name: int(sum(np.asarray(dic[k][i], np.float32).nbytes for k in ("T_db", "U_b")))
           for i, name in enumerate(model.TYPES)}
    per["_vector_and_volume_per_type"] = int(np.asarray(dic["U_quad"][0], np.float32).nbytes
                                             + np.asarray(dic["U_vol"][0], np.float32).nbytes)
    if "U_r" in dic:
        per["_interfaces_shared"] = int(np.asarray(dic["U_r"], np.float32).nbytes)
    return per


def datadriven_baseline(d_train, i_train, positions, mask, direct_test, dcfg: dict, n_points: int,
                        dtype=np.float32):
    """Data-driven PRT (Belcour et al. 2022) fitted on a layout's training texels (direct
    ``d_train`` and indirect ``i_train`` (N, B, n, 3)) with ``n_points`` measurement points among
    the existing texels, its ``dcfg`` (basis, transfer); its indirect texels (L, B, n, 3) of
    ``direct_test`` (of ``dtype``, 0 where no texel is) and the fit's seconds."""
    from jprt.methods.datadriven import model as ddm

    flat = np.asarray(mask, bool).reshape(-1)
    t0 = time.perf_counter()
    pts = ddm.select_points(positions.reshape(-1, 3)[flat], min(int(n_points), int(flat.sum())))
    fine = np.flatnonzero(flat)[pts.fine_index]
    n = len(d_train)
    fitted = ddm.fit_arrays(d_train.reshape(n, -1, 3)[:, fine], i_train.reshape(n, -1, 3)[:, flat], pts.group, dcfg)
    fit_s = time.perf_counter() - t0
    out = np.zeros(np.shape(direct_test), dtype).reshape(len(direct_test), -1, 3)
    out[:, flat] = np.asarray(ddm.lightmap(fitted.params, direct_test.reshape(len(direct_test), -1, 3)[:, fine], dcfg))
    return out.reshape(np.shape(direct_test)), fit_s


def _block_mean(direct, mask) -> np.ndarray:
    """Each block's mean direct over its existing texels, broadcast to its texels."""
    return np.broadcast_to(np.sum(direct * mask[..., None], 1, keepdims=True) / mask.sum(1)[:, None, None],
                           direct.shape)


def ambient_baseline(d_train, i_train, mask, direct_test) -> tuple[np.ndarray, float]:
    """The ambient term: per block, c x its mean direct, with one c fitted by least squares on
    the training texels; its indirect texels of ``direct_test`` and c."""
    md_tr = np.stack([_block_mean(d, mask) for d in d_train])
    m = np.broadcast_to(mask[None, ..., None], md_tr.shape)
    c = float(np.sum(md_tr[m] * i_train[m]) / max(np.sum(md_tr[m] ** 2), 1e-30))
    return c * np.stack([_block_mean(d, mask) for d in direct_test]), c


def tilted_normals(rng, shape, max_deg: float) -> np.ndarray:
    """Unit normals (*shape, 3) tilted from +z by up to ``max_deg`` (uniform in solid angle's
    square root: the polar angle is max_deg sqrt(u)), in the local frame of each texel."""
    theta = np.radians(max_deg) * np.sqrt(rng.random(shape))
    phi = 2 * np.pi * rng.random(shape)
    return np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], -1)


def march(lay: layouts.Layout, t: int, origins: np.ndarray, dirs: np.ndarray, radiance: np.ndarray) -> np.ndarray:
    """Radiance (L, R, 3) of the texel each ray meets first, marching from cell to cell through
    open sides (a blocks layout of unit cells); rays that leave through an exterior side see 0.
    ``radiance`` (L, B, n, 3) per lighting."""
    index = {c: k for k, c in enumerate(lay.cells)}
    blocks = lay.blocks
    o = origins.copy()
    cell = np.floor(o[:, [0, 2]] + 1e-9 * dirs[:, [0, 2]]).astype(int)
    out = np.zeros((radiance.shape[0], len(o), 3))
    active = np.ones(len(o), bool)
    for _ in range(len(lay.cells) + 1):
        if not active.any():
            break
        ids = np.flatnonzero(active)
        b = np.array([index.get((int(i), int(j)), -1) for i, j in cell[ids]])
        gone = b < 0
        active[ids[gone]] = False
        ids, b = ids[~gone], b[~gone]
        off = np.stack([cell[ids, 0], np.zeros(len(ids)), cell[ids, 1]], -1)
        face, hit = layouts.exit_face(o[ids] - off, dirs[ids])
        side = face - 2
        is_open = np.array([s >= 0 and s in blocks[bb].open_sides for s, bb in zip(side, b)], bool)
        stop = ~is_open
        tex = layouts.locate(hit[stop], t, layouts.FACE_NORMALS[face[stop]])
        out[:, ids[stop]] = radiance[:, b[stop], tex]
        active[ids[stop]] = False
        go = ids[is_open]
        o[go] = hit[is_open] + off[is_open]
        step = np.array([layouts.SIDE_STEPS[s] for s in side[is_open]]).reshape(-1, 2)
        cell[go] = cell[go] + step
    return out


def tilted_quadrature(t: int, normals: np.ndarray, radiance: np.ndarray, k: int) -> np.ndarray:
    """Irradiance / pi at each texel for its tilted local normal (``normals`` (L, B, n, 3)):
    quadrature (``k`` directions) of the block's own surface radiance (L, B, n, 3) over the
    directions above both the surface and the tilted normal."""
    pos, normal, face = layouts.texel_centres(t)
    d_loc, w = operators.sphere_directions(k, hemisphere=True)
    out = np.zeros(normals.shape[:3] + (3,))
    for i in range(len(pos)):
        frame = np.stack([layouts.FACE_U[face[i]], layouts.FACE_V[face[i]], normal[i]])
        f, hit = layouts.exit_face(np.repeat(pos[i:i + 1], len(d_loc), 0) + 1e-9 * normal[i], d_loc @ frame)
        tex = layouts.locate(hit, t, layouts.FACE_NORMALS[f])
        cosn = np.maximum(np.einsum("lbk,dk->lbd", normals[:, :, i], d_loc), 0.0) * w / np.pi  # (L, B, D)
        out[:, :, i] = np.einsum("lbd,lbdc->lbc", cosn, radiance[:, :, tex])
    return out


def volume_reference(lay: layouts.Layout, t: int, probes: np.ndarray, radiance: np.ndarray, k: int) -> np.ndarray:
    """The SH (order 3) of the radiance each irradiance-volume probe (``probes`` (P, 3) in a
    block's unit cell) sees across the whole layout, by quadrature over ``k`` sphere directions of
    rays marched through open sides (``march``): (L, B, P, 9, 3)."""
    d, w = operators.sphere_directions(k, hemisphere=False)
    y = operators.sh9(d) * w[:, None]
    ref = []
    for blk in lay.blocks:
        origin = np.array([blk.cell[0], 0.0, blk.cell[1]]) + probes  # (P, 3)
        rad = march(lay, t, np.repeat(origin, len(d), 0), np.tile(d, (len(origin), 1)), radiance)  # (L, P * D, 3)
        ref.append(np.einsum("dq,lpdc->lpqc", y, rad.reshape(len(radiance), len(origin), len(d), 3)))
    return np.stack(ref, 1)


def frame_times(dic: dict, cfg: dict, blocks, albedo_values, repeats: int) -> dict:
    """The run time (§7.3 steps 1-5, ``runtime.feedback`` bounces in the reduced spaces, texels
    out) on a random maze of each block count of ``blocks`` (a cycle per ten blocks; one block: a
    corridor) with random direct light: median frame ms, T_b->r build seconds and XLA's FLOP count
    by block count (``jprt.eval.time_call``, ``xla_flops``)."""
    rng = np.random.default_rng(0)
    by, tbr, flops = {}, {}, {}
    t = int(cfg["dictionary"]["texels"])
    fb = int(cfg["runtime"]["feedback"])
    for nb in (int(b) for b in blocks):
        lay = layouts.random_maze(nb, seed=nb, extra_edges=max(0, nb // 10)) if nb > 1 else layouts.corridor(1)
        ops = model.layout_operators(dic, lay.as_dict(), cfg)
        alb = layouts.texel_albedo(lay, t, albedo_values)
        ops.update(model.level_feedback(ops, alb))
        arrays = jax.device_put({k: jnp.asarray(ops[k]) for k in model.RUNTIME_KEYS})
        albedo = jax.device_put(jnp.asarray(alb, jnp.float32))
        direct = jax.device_put(jnp.asarray(rng.random((nb, layouts.texel_count(t), 3)), jnp.float32))
        fn = jax.jit(lambda a, d, al: model.lightmap(a, d, al, feedback=fb))
        by[str(nb)] = jeval.time_call(fn, arrays, direct, albedo, repeats=repeats)["median_ms"]
        tbr[str(nb)] = float(ops["tbr_build_s"])
        flops[str(nb)] = jeval.xla_flops(fn, arrays, direct, albedo)
    return {"frame_ms": by, "tbr_build_s": tbr, "flops": flops}
