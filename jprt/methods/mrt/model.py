"""Modular Radiance Transfer (Loos, Antani, Mitchell, Nowrouzezahrai, Jarosz, Sloan 2011).

Indirect light of a scene made of canonical blocks (``jprt.layouts``: the 2D-maze dictionary of
§6.1), from direct light measured at each block's texels, entirely in reduced spaces. In the
paper's order:

* **Gather operator** (Eq. 1): F of the closed unit cube (``operators.form_factors``, exact form
  factors instead of the paper's gather rays; a missing face zeroes its rows and columns).
  Texel values are radiance; F l is the mean incident radiance (E / pi); the outgoing indirect
  radiance is albedo x F l, the albedo applied per texel at run time (the dictionary is
  albedo-free, so one dictionary serves every material).
* **Light prior** (§4): L_d = direct light of unit point lights on a ``prior_grid^3`` lattice in
  the block and in the cube beyond each missing side (``operators.prior_lights``; the paper's
  6^3 sphere lights become point lights). P = the k_d left singular vectors of L_d (no mean
  removed, as the paper says), S = their singular values.
* **Reduced transfer** (Eq. 2-3): M = F P S = U_m Sigma_m V_m^T; U_b = U_m Sigma_m and
  T_d->b = V_m^T S^-1 P^T truncated to k_b; L_imp = P S V_m (so F L_imp = U_b, §4.1). Erratum
  (papers/README): M acts on S^-1 P^T l_d.
* **Enrichment** (App. A): the prior is rebuilt from [P S, face-constant functions, U_b], each
  scaled to Frobenius norm 1 ("equally weighted"), SVD, then M and everything after it again.
* **Interfaces** (§5.1): H_lf = the lightfields leaving side 0 of every dictionary type lit by
  each of its implicit lights, through each of its missing sides (12 in all), turned to side 0
  (``operators.exit_resampling``); H_rlf = U Sigma of its SVD truncated to k_rlf, enriched
  ``enrich_iterations`` times with its own responses through the three propagation operators
  (App. A: each set scaled to norm 1, SVD again). Coefficients of a lightfield f are
  H_rlf^+ f. R_b->rlf[type][side] = H_rlf^+ A L_imp (turned), R_rel = H_rlf^+ R H_rlf for the
  left / opposite / right side (the paper's R_{up,down,r}, R_{up,up,r}, R_gamma), G = F_rlf
  H_rlf = U_g Sigma_g V_g^T, U_r = U_g truncated to k_r, T_rlf->r = Sigma_g V_g^T (k_r rows).
* **Per layout** (§6.3, ``layout_operators``): T_b->r by breadth-first propagation from every
  block through its open sides, to depth ``d_max``, summing the matrices of paths that arrive at
  the same interface in the same state ("if a path from the same source block has already been
  computed, the matrices are summed"). **Cycles**: light travels in straight lines, so a path
  that crosses interfaces in both directions of one grid axis (east then west, north then south)
  is no path of light and is dropped; this removes every path that revisits a block or an
  interface, so layouts with cycles need no special case, and ``d_max`` bounds the rest. Stored
  block-sparse: one (k_r x k_b) matrix per (receiving interface, source block).
* **Per frame** (§7.3, ``lightmap``): b = T_d->b l_d per block, U_b b, r = T_b->r b, U_r r per
  receiving interface, times the texel albedo; ``feedback`` more bounces feed the previous
  bounce's outgoing indirect light back as direct light (§7.3, Fig. 8). Direct light l_d comes
  from Mitsuba at the texel centres (the paper renders shadow maps; here it is exact).
* **Vector irradiance** (§6.4, App. B): quadratic SH of each texel's incident radiance under
  each implicit light (``operators.hemisphere_sh``), mapped to 4 OHLSH coefficients
  (``jprt.sphere.sh.ohlsh``); ``vector_irradiance`` evaluates either for perturbed normals.
* **Irradiance volumes** (§6.5, §7.3 step 8 "from b's and r's"): U_bvol maps b to quadratic SH
  at a ``volume_grid^3`` lattice of probes in each block (``operators.volume_sh`` of L_imp);
  U_rvol maps a receiving side's r to the SH of the lightfield entering there
  (``operators.volume_lightfield_sh`` of H_rlf), reading r back as lightfield coefficients
  c ~ V_g Sigma_g^-1 r on the k_r kept modes (the paper does not say how); ``volume_probes``.
* **Feedback in the reduced spaces** (not in the paper, equal to it): the bounce
  b' = T_d->b (albedo x (U_b b + U_r r)) is W b + sum_s V_s r with W, V precomputed per level
  (``feedback_operators``), so a frame touches the texels twice, not twice per bounce.

Decisions the paper leaves open: blocks are unit cubes (a layout's ``size`` scales the world,
not the transport); lightfields are 4^2 positions x 8^2 directions at ``small`` (the paper's
12^2 x 24^2 is ``paper``); the texels of missing faces stay in every block's vector (always 0)
so all blocks share one layout; a 90-degree turn of a block is a texel permutation
(``jprt.layouts.rotate_pattern``), so the operators of the six types are stored once, canonical.

Contract (``jprt.methods.base``): ``data.make_dataset`` -> ``MRTData``; ``fit`` -> params (the
dictionary and the layout's operators, arrays only); ``evaluator`` -> ``evaluate(inputs,
PointRadiance)`` -> (H, W, 3) through the padded lightmap atlas (``atlas_inputs`` shows the
texels themselves).
"""

from __future__ import annotations

import time
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jprt import cache, layouts
from jprt.inputs import PointRadiance
from jprt.methods.base import FitResult, resolve
from jprt.methods.lightmap_lookup import atlas_lookup
from jprt.methods.mrt import operators as ops
from jprt.methods.mrt.block_atlas import atlas_gbuffer_inputs, atlas_layout, texels_of

__all__ = ["DEFAULT_CONFIG", "MRTData", "block_prior", "reduce_transfer", "enrich_prior", "block_operators",
           "interface_operators", "dictionary", "layout_operators", "lightmap", "lightmap_parts",
           "lightmap_parts_texels", "feedback_operators", "level_feedback", "coefficients",
           "projection", "vector_irradiance", "volume_probes", "fit", "evaluator", "example", "TYPES"]

#: The dictionary types in storage order.
TYPES = tuple(layouts.DICTIONARY)

DEFAULT_CONFIG: dict[str, Any] = {
    # an 11-block maze with one cycle; MRT's dictionary is scene-independent, the layout is the scene
    "scene": {"name": "blocks", "layout": layouts.random_maze(11, seed=3, extra_edges=1).as_dict()},
    "dictionary": {
        "texels": 8,  # t: t x t texels per face (the paper: 16)
        "quadrature": 2,  # Gauss-Legendre points per texel axis in the form factors
        "prior_grid": 6,  # prior lights on a grid^3 lattice per cube (the paper: 6^3)
        "k_d": 64,  # light prior modes
        "k_b": 32,  # indirect light space modes (the paper's k_self)
        "enrich": True,  # App. A for the block prior
    },
    "interfaces": {
        "enabled": True,
        "spatial": 4, "directional": 8,  # lightfield cells per axis (the paper: 12 and 24)
        "spatial_ss": 2, "directional_ss": 3,  # sub-rays per cell axis (the paper: 5 directional)
        "k_rlf": 64, "k_r": 16,  # reduced lightfield and response modes (the paper: 128, 32)
        "enrich_iterations": 3,
        "d_max": 8,  # interfaces a path may cross
    },
    "runtime": {"feedback": 4},  # extra bounces fed back (0 = one bounce)
    "vector": {"directions": 12},  # hemisphere quadrature per axis for the SH of §6.4
    "volume": {"grid": 2, "directions": 10},  # probes per block axis, sphere quadrature per axis
    # where the blocks sit in a scene that is not itself a "blocks" layout (§6.2, §7.2: a proxy of
    # coarse blocks; e.g. the Cornell box is one block with its front open): a layout (with
    # "exterior" openings), the world position of cell (0, 0)'s corner and the block size. null
    # for "blocks" scenes, whose layout is the proxy
    "proxy": {"layout": None, "origin": [0.0, 0.0, 0.0], "size": 1.0},
    "lights": {
        "count": 1,  # point lights per held-out lighting, each in a block drawn uniformly
        "intensity": [0.5, 2.0],  # W/sr (max channel), uniform in this range, times a random colour
        "saturation": 0.5,  # 0 = white lights, 1 = fully random colours
        "clearance": 0.15,  # least distance of a light from its block's faces (a fraction of a block)
    },
    "data": {
        "n_test": 8,  # held-out lightings
        "test_spp": 4096,  # samples per texel of the references (their noise well under MRT's error)
        "seed": 0,  # seed of the lights and the references
    },
}


def _cfg(config) -> dict:
    """``DEFAULT_CONFIG`` merged strictly with ``config``, its sizes checked (one line each)."""
    cfg = resolve(DEFAULT_CONFIG, config)
    positive = [("dictionary", k) for k in ("texels", "quadrature", "prior_grid", "k_d", "k_b")]
    positive += [("interfaces", k) for k in ("spatial", "directional", "spatial_ss", "directional_ss", "k_rlf", "k_r",
                                             "d_max")]
    positive += [("vector", "directions"), ("volume", "grid"), ("volume", "directions")]
    for section, key in positive:
        v = cfg[section][key]
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
            raise ValueError(f"{section}.{key} must be a positive integer, got {v!r}")
    for key in ("enrich_iterations",):
        if int(cfg["interfaces"][key]) < 0:
            raise ValueError(f"interfaces.{key} must be >= 0, got {cfg['interfaces'][key]!r}")
    if int(cfg["runtime"]["feedback"]) < 0:
        raise ValueError(f"runtime.feedback (extra bounces) must be >= 0, got {cfg['runtime']['feedback']!r}")
    return cfg


# --------------------------------------------------------------------------------------------
# §4: light prior, reduced transfer, implicit lighting; App. A enrichment


def block_prior(t: int, missing: tuple[int, ...], grid: int) -> np.ndarray:
    """L_d (n, m): direct light of the prior's point lights (§4, §7.1) on a block type.

    Numerics: not differentiable (a float64 NumPy precomputation).
    """
    return ops.point_light_direct(t, ops.prior_lights(grid, missing), missing)


def _svd(a):
    u, s, vt = np.linalg.svd(np.asarray(a, np.float64), full_matrices=False)
    return u, s, vt


def reduce_transfer(f: np.ndarray, p: np.ndarray, s: np.ndarray, k_b: int) -> dict:
    """Eq. 2-3: M = F P S, its SVD, U_b = U_m Sigma_m, T_d->b = V_m^T S^-1 P^T and
    L_imp = P S V_m, truncated to k_b modes. Returns the arrays and M's singular values.

    Numerics: not differentiable (a float64 NumPy precomputation).
    """
    m = f @ (p * s[None])
    um, sm, vmt = _svd(m)
    k = min(int(k_b), int(np.sum(sm > sm[0] * 1e-12)) if sm.size and sm[0] > 0 else 0)
    k = max(k, 1)
    ub = um[:, :k] * sm[:k]
    tdb = (vmt[:k] / s[None]) @ p.T
    limp = (p * s[None]) @ vmt[:k].T
    return {"U_b": ub, "T_db": tdb, "L_imp": limp, "sv_M": sm}


def enrich_prior(p: np.ndarray, s: np.ndarray, ub: np.ndarray, mask: np.ndarray, t: int, k_d: int):
    """App. A: [P S, one function constant on each existing face, U_b], each scaled to Frobenius
    norm 1, concatenated; the new prior is its k_d left singular vectors and singular values.

    Numerics: not differentiable (a float64 NumPy precomputation).
    """
    face = layouts.texel_centres(t)[2]
    faces = [np.where((face == f) & mask, 1.0, 0.0) for f in range(6) if np.any((face == f) & mask)]
    parts = [p * s[None], np.stack(faces, 1), ub]
    cat = np.concatenate([x / max(np.linalg.norm(x), 1e-30) for x in parts], axis=1)
    u, sv, _ = _svd(cat)
    k = min(int(k_d), int(np.sum(sv > sv[0] * 1e-10)))
    return u[:, :k], sv[:k]


def block_operators(f_closed: np.ndarray, t: int, missing: tuple[int, ...], cfg: dict) -> dict:
    """Every §4 array of one dictionary type (missing faces masked out of F): P, S, U_b,
    T_d->b, L_imp, and the singular values of L_d and M (Table 2).

    Numerics: not differentiable (a float64 NumPy precomputation).
    """
    dcfg = cfg["dictionary"]
    mask = ops.face_mask(t, missing)
    f = f_closed * mask[:, None] * mask[None, :]
    ld = block_prior(t, missing, int(dcfg["prior_grid"]))
    ud, sd, _ = _svd(ld)
    k_d = min(int(dcfg["k_d"]), int(np.sum(sd > sd[0] * 1e-10)))
    p, s = ud[:, :k_d], sd[:k_d]
    out = reduce_transfer(f, p, s, int(dcfg["k_b"]))
    out["sv_Ld"] = sd
    if dcfg["enrich"]:
        p, s = enrich_prior(p, s, out["U_b"], mask, t, k_d)
        out.update(reduce_transfer(f, p, s, int(dcfg["k_b"])))
    out.update(P=p, S=s, mask=mask, F=f)
    return out


# --------------------------------------------------------------------------------------------
# §5.1: interfaces


def _pad_cols(a: np.ndarray, k: int) -> np.ndarray:
    return np.pad(a, ((0, 0), (0, k - a.shape[1])))


def interface_operators(blocks: dict, t: int, cfg: dict) -> dict:
    """H_rlf and the reduced interface operators of §5.1 from the dictionary's implicit lights:
    R_b->rlf per type and canonical side (k_rlf, k_b), R_rel for relative sides 1-3
    (k_rlf, k_rlf), U_r (n, k_r), T_rlf->r (k_r, k_rlf); plus H_lf's singular values.

    Numerics: not differentiable (a float64 NumPy precomputation).
    """
    icfg = cfg["interfaces"]
    sp, dr = int(icfg["spatial"]), int(icfg["directional"])
    rays = ops.lightfield_rays(sp, dr, int(icfg["spatial_ss"]), int(icfg["directional_ss"]))
    a_out = ops.exit_resampling(t, rays, sp, dr)
    f_rlf = ops.entry_response(t, rays, sp, dr, int(icfg["directional_ss"]), int(icfg["spatial_ss"]))
    prop = ops.propagation(rays, sp, dr)
    # each type's implicit lights seen leaving through each of its missing sides (turned to side 0)
    leaving = {(name, side): a_out @ layouts.rotate_pattern(blocks[name]["L_imp"], t, (4 - side) % 4)
               for name in TYPES for side in layouts.DICTIONARY[name]}
    h_lf = np.concatenate(list(leaving.values()), axis=1)
    u, s, _ = _svd(h_lf)
    k = min(int(icfg["k_rlf"]), int(np.sum(s > s[0] * 1e-10)))
    h = u[:, :k] * s[:k]
    for _ in range(int(icfg["enrich_iterations"])):
        temp = np.concatenate([prop[r] @ h for r in (1, 2, 3)], axis=1)
        cat = np.concatenate([h / np.linalg.norm(h), temp / max(np.linalg.norm(temp), 1e-30)], axis=1)
        u2, s2, _ = _svd(cat)
        k = min(int(icfg["k_rlf"]), int(np.sum(s2 > s2[0] * 1e-10)))
        # keep the enriched basis on H_lf's scale: its columns carry the singular values of the
        # lightfields they represent (H_rlf = U Sigma); rescale by H_lf's energy
        h = u2[:, :k] * (s2[:k] / s2[0] * s[0])
    h_pinv = np.linalg.pinv(h)
    r_b = {key: h_pinv @ lf for key, lf in leaving.items()}
    r_rel = {r: h_pinv @ (prop[r] @ h) for r in (1, 2, 3)}
    g = f_rlf @ h
    ug, sg, vgt = _svd(g)
    k_r = min(int(icfg["k_r"]), len(sg))
    return {"H_rlf": h, "H_pinv": h_pinv, "R_b": r_b, "R_rel": r_rel, "U_r": ug[:, :k_r],
            "T_rlf_r": sg[:k_r, None] * vgt[:k_r], "r_to_c": vgt[:k_r].T / sg[None, :k_r], "sv_H": s, "sv_G": sg,
            "A_out": a_out, "F_rlf": f_rlf, "propagation": prop}


# --------------------------------------------------------------------------------------------
# The dictionary (scene-independent, cached)


def _vector_volume(blocks: dict, t: int, cfg: dict) -> dict:
    """U_quad (4, n, 9, k) and U_vol (4, P, 9, k) of every type at each of the four turns: the
    SH are in the layout's frames (each texel's own tangent frame, the block's frame for probes),
    so they are computed for the turned implicit lights rather than permuted."""
    hs = ops.hemisphere_sh(t, int(cfg["vector"]["directions"]))  # (n, 9, n)
    g = int(cfg["volume"]["grid"])
    c = (np.arange(g) + 0.5) / g
    probes = np.stack(np.meshgrid(c, c, c, indexing="ij"), -1).reshape(-1, 3)
    vs = ops.volume_sh(t, probes, int(cfg["volume"]["directions"]))  # (P, 9, n)
    out = {"probes": probes}
    for name in TYPES:
        turned = [layouts.rotate_pattern(blocks[name]["L_imp"], t, r) for r in range(4)]
        out[name] = {"U_quad": np.stack([np.einsum("iqn,nk->iqk", hs, l) for l in turned]),
                     "U_vol": np.stack([np.einsum("pqn,nk->pqk", vs, l) for l in turned])}
    return out


def dictionary(config: dict | None = None, *, cache_dir: str | None = None) -> dict:
    """The precomputed dictionary (§7.1): per type the §4 arrays (canonical, padded to k_b modes)
    and the §5.1 interface operators, stacked as arrays: a flat dict of NumPy arrays, cached by
    ``jprt.cache`` under the ``dictionary``, ``interfaces``, ``vector`` and ``volume`` sections.
    ``info`` keys (``_info`` prefix) carry the singular values and timings.

    Numerics: not differentiable (a float64 NumPy precomputation).
    """
    cfg = _cfg(config)
    spec = {"format": 4, **{k: cfg[k] for k in ("dictionary", "interfaces", "vector", "volume")}}

    def build() -> dict:
        return _build_dictionary(cfg)

    arrays, _ = cache.cached("mrt_dictionary", spec, build, cache_dir=cache_dir)
    return dict(arrays)


def _build_dictionary(cfg: dict) -> dict:
    t = int(cfg["dictionary"]["texels"])
    k_b = int(cfg["dictionary"]["k_b"])
    t0 = time.perf_counter()
    f = ops.form_factors(t, int(cfg["dictionary"]["quadrature"]))
    blocks = {name: block_operators(f, t, miss, cfg) for name, miss in layouts.DICTIONARY.items()}
    t_blocks = time.perf_counter() - t0
    out = {
        "T_db": np.stack([_pad_cols(blocks[n]["T_db"].T, k_b).T for n in TYPES]).astype(np.float32),
        "U_b": np.stack([_pad_cols(blocks[n]["U_b"], k_b) for n in TYPES]).astype(np.float32),
        "L_imp": np.stack([_pad_cols(blocks[n]["L_imp"], k_b) for n in TYPES]).astype(np.float64),
        "mask": np.stack([blocks[n]["mask"] for n in TYPES]),
        "F_closed": f,
        "info_sv_Ld_closed": blocks["closed"]["sv_Ld"], "info_sv_M_closed": blocks["closed"]["sv_M"],
    }
    if cfg["interfaces"]["enabled"]:
        t1 = time.perf_counter()
        io = interface_operators(blocks, t, cfg)
        k_rlf = io["H_rlf"].shape[1]
        r_b = np.zeros((len(TYPES), 4, k_rlf, k_b), np.float32)
        for (name, side), m in io["R_b"].items():
            r_b[TYPES.index(name), side, :, :m.shape[1]] = m
        out.update(R_b=r_b, R_rel=np.stack([io["R_rel"][r] for r in (1, 2, 3)]).astype(np.float64),
                   U_r=io["U_r"].astype(np.float32), T_rlf_r=io["T_rlf_r"].astype(np.float64),
                   info_sv_H=io["sv_H"], info_sv_G=io["sv_G"], info_interfaces_s=np.array(time.perf_counter() - t1))
    t2 = time.perf_counter()
    vv = _vector_volume(blocks, t, cfg)
    if cfg["interfaces"]["enabled"]:
        # §6.5 "from b's and r's": the probes' SH of the lightfield entering through each side,
        # read through the response coefficients (c ~ V_g Sigma_g^-1 r on the kept modes)
        icfg = cfg["interfaces"]
        out["U_rvol"] = np.stack([ops.volume_lightfield_sh(vv["probes"], int(cfg["volume"]["directions"]),
                                                           int(icfg["spatial"]), int(icfg["directional"]), side)
                                  @ (io["H_rlf"] @ io["r_to_c"]) for side in range(4)]).astype(np.float32)
    def padded(a):  # (4, X, 9, k) -> (4, X, 9, k_b)
        return np.pad(a, ((0, 0), (0, 0), (0, 0), (0, k_b - a.shape[-1])))

    out.update(U_quad=np.stack([padded(vv[n]["U_quad"]) for n in TYPES]).astype(np.float32),
               U_vol=np.stack([padded(vv[n]["U_vol"]) for n in TYPES]).astype(np.float32),
               probes=vv["probes"], info_vector_s=np.array(time.perf_counter() - t2),
               info_blocks_s=np.array(t_blocks), info_precompute_s=np.array(time.perf_counter() - t0))
    return out


# --------------------------------------------------------------------------------------------
# §6.3: one layout


def _turned(a, t: int, turns: int, axis: int):
    return layouts.rotate_pattern(np.asarray(a), t, turns, axis=axis)


def layout_operators(dic: dict, layout, config: dict | None = None) -> dict:
    """The per-layout arrays (level initialisation, §6.2-6.3): each block's T_d->b and U_b in
    the layout's frame (the canonical type's, turned), texel masks, and T_b->r block-sparse as
    records (source block, receiving block, receiving side, k_r x k_b matrix). ``tbr_build_s``
    is the propagation's wall time.

    Numerics: not differentiable (a float64 NumPy precomputation).
    """
    cfg = _cfg(config)
    lay = layouts.layout_from_dict(layout)
    t = int(cfg["dictionary"]["texels"])
    blocks = lay.blocks
    tdb, ub, mask, uq = [], [], [], []
    for blk in blocks:
        k = TYPES.index(blk.kind)
        tdb.append(_turned(dic["T_db"][k], t, blk.turns, axis=1))
        ub.append(_turned(dic["U_b"][k], t, blk.turns, axis=0))
        mask.append(_turned(dic["mask"][k], t, blk.turns, axis=0))
        uq.append(dic["U_quad"][k, blk.turns])
    out = {"T_db": np.stack(tdb).astype(np.float32), "U_b": np.stack(ub).astype(np.float32),
           **({"U_rvol": dic["U_rvol"]} if "U_rvol" in dic else {}),
           "mask": np.stack(mask), "U_quad": np.stack(uq).astype(np.float32),
           "U_vol": np.stack([dic["U_vol"][TYPES.index(b.kind), b.turns] for b in blocks]).astype(np.float32),
           "kind": np.array([TYPES.index(b.kind) for b in blocks], np.int32),
           "turns": np.array([b.turns for b in blocks], np.int32)}
    t0 = time.perf_counter()
    src, dst, side, mats = _propagate(dic, lay, int(cfg["interfaces"]["d_max"])) if "R_b" in dic else ([], [], [], [])
    out["tbr_build_s"] = np.array(time.perf_counter() - t0)
    k_r = dic["U_r"].shape[1] if "U_r" in dic else 1
    k_b = dic["T_db"].shape[1]
    out["rec_src"] = np.array(src, np.int32)
    out["rec_dst"] = np.array(dst, np.int32)
    out["rec_side"] = np.array(side, np.int32)
    out["rec_T"] = (np.stack(mats) if mats else np.zeros((0, k_r, k_b))).astype(np.float32)
    out["U_r_turned"] = (np.stack([_turned(dic["U_r"], t, s, axis=0) for s in range(4)])
                         if "U_r" in dic else np.zeros((4, layouts.texel_count(t), 1))).astype(np.float32)
    return out


def _propagate(dic: dict, lay: layouts.Layout, d_max: int):
    """Breadth-first propagation (§6.3) from every block; see the module docstring for cycles."""
    blocks = lay.blocks
    t_r = dic["T_rlf_r"]
    r_rel = dic["R_rel"]
    records: dict[tuple[int, int, int], np.ndarray] = {}
    axis_sign = {0: (0, 1), 1: (1, 1), 2: (0, -1), 3: (1, -1)}
    # the block across each open side, looked up once (None: an exterior opening)
    across = {(x, s): lay.neighbour(x, s) for x, b in enumerate(blocks) for s in b.open_sides}
    for x, blk in enumerate(blocks):
        kind = TYPES.index(blk.kind)
        frontier = {}
        for s_w in blk.open_sides:
            y = across[(x, s_w)]
            if y is None:  # an exterior opening: the light leaves the layout
                continue
            c = np.asarray(dic["R_b"][kind, (s_w - blk.turns) % 4], np.float64)
            sign = [0, 0]
            ax, sg = axis_sign[s_w]
            sign[ax] = sg
            key = (y, (s_w + 2) % 4, tuple(sign))
            frontier[key] = frontier.get(key, 0) + c
        for _depth in range(d_max):
            nxt = {}
            for (y, e, sign), c in frontier.items():
                rec = (y, e, x)
                records[rec] = records.get(rec, 0) + t_r @ c
                for k_w in blocks[y].open_sides:
                    if k_w == e:
                        continue
                    ax, sg = axis_sign[k_w]
                    if sign[ax] == -sg:
                        continue  # no straight ray turns back along an axis
                    z = across[(y, k_w)]
                    if z is None:
                        continue
                    s2 = list(sign)
                    s2[ax] = sg
                    key = (z, (k_w + 2) % 4, tuple(s2))
                    nxt[key] = nxt.get(key, 0) + r_rel[(k_w - e) % 4 - 1] @ c
            frontier = nxt
            if not frontier:
                break
    src, dst, side, mats = [], [], [], []
    for (y, e, x), m in sorted(records.items()):
        src.append(x)
        dst.append(y)
        side.append(e)
        mats.append(m)
    return src, dst, side, mats


# --------------------------------------------------------------------------------------------
# §7.3: the run time


def _records(params: dict, b, n_blocks: int):
    """r = T_b->r b, summed per receiving interface: (B, 4, k_r, 3) (block, side)."""
    r = jnp.einsum("ejk,ekc->ejc", params["rec_T"], b[params["rec_src"]])
    slot = params["rec_dst"] * 4 + params["rec_side"]
    return jax.ops.segment_sum(r, slot, num_segments=4 * n_blocks).reshape((n_blocks, 4) + r.shape[1:])


def lightmap_parts_texels(params: dict, direct, albedo, *, feedback: int, interfaces: bool = True):
    """``lightmap_parts`` as §7.3 writes it: every bounce expanded to texels, multiplied by the
    albedo and projected again (the reference the reduced-space feedback is tested against).

    Numerics:
        case: mrt_texels (2 blocks of 8 texels, k_b = 3, k_r = 2, random operators of norm < 1, one
          interface record, direct radiance in [0, 1e5], albedo in [0, 1], 2 feedback bounces)
        float32: value rtol 1e-4 atol 1e-1; grad rtol 1e-4 atol 1e-2
        (products of operators with both signs over inputs to 1e5: rounding is absolute near zero,
          ~1e-7 of the sum of |terms|, ~1e4 for the values and ~1e5 for the operators' gradients)
    """
    mask = params["mask"][..., None]
    tdb, ub = params["T_db"], params["U_b"]
    n_blocks = tdb.shape[0]
    within_total = jnp.zeros_like(direct)
    inter_total = jnp.zeros_like(direct)
    light = direct * mask
    for _ in range(1 + int(feedback)):
        b = jnp.einsum("bkn,bnc->bkc", tdb, light)
        within = jnp.einsum("bnk,bkc->bnc", ub, b) * mask
        inter = jnp.zeros_like(within)
        if interfaces and params["rec_T"].shape[0]:
            inter = jnp.einsum("snj,bsjc->bnc", params["U_r_turned"], _records(params, b, n_blocks)) * mask
        within_total = within_total + within
        inter_total = inter_total + inter
        light = albedo * (within + inter)
    return within_total, inter_total


def feedback_operators(params: dict, albedo) -> dict:
    """The feedback bounce in the reduced spaces (level initialisation: the albedo is static):
    W[b, c] = T_d->b diag(albedo_c) U_b (k_b x k_b) maps a block's b to the b of its reflected
    light, V[b, s, c] = T_d->b diag(albedo_c) U_r (turned to side s) (k_b x k_r) does the same
    for the light arriving through side s. Then b' = W b + sum_s V r_s, and only the final sum
    of all bounces is expanded to texels (equal to the texel-space loop, tested).

    Numerics:
        case: mrt_feedback (``mrt_texels``'s operators, albedo in [0, 1])
        float32: value rtol 1e-5 atol 1e-6; grad rtol 1e-5 atol 1e-6
    """
    xp = jnp if isinstance(params["T_db"], jax.Array) else np
    alb = xp.asarray(albedo, params["T_db"].dtype) * params["mask"][..., None]
    w = xp.einsum("bkn,bnc,bnj->bckj", params["T_db"], alb, params["U_b"])
    v = xp.einsum("bkn,bnc,snj->bsckj", params["T_db"], alb, params["U_r_turned"])
    return {"W": w, "V": v}


def level_feedback(params: dict, albedo) -> dict:
    """``feedback_operators`` of a level's params and albedo, computed in float64 and stored as
    the float32 ``W`` and ``V`` the run time reads (what ``fit`` adds to its params).

    Numerics: not differentiable (computed in float64 NumPy, stored as float32).
    """
    fb = feedback_operators({k: np.asarray(params[k], np.float64) for k in ("T_db", "U_b", "U_r_turned", "mask")},
                            np.asarray(albedo, np.float64))
    return {k: v.astype(np.float32) for k, v in fb.items()}


def coefficients(params: dict, direct, albedo, *, feedback: int, interfaces: bool = True):
    """The run time's reduced state summed over 1 + ``feedback`` bounces: b (B, k_b, 3) per block
    and r (B, 4, k_r, 3) per receiving side (zeros without interfaces). The bounces run in the
    reduced spaces (``feedback_operators``, taken from ``params["W"]``, ``params["V"]`` when
    ``fit`` stored them): the texels are read once, for b of the direct light.

    Numerics:
        case: mrt_coefficients (``mrt_texels``'s operators and inputs)
        float32: value rtol 1e-4 atol 1e-1; grad rtol 1e-4 atol 1e-2
        (products of operators with both signs over inputs to 1e5: rounding is absolute near zero,
          ~1e-7 of the sum of |terms|, ~1e4 for the values and ~1e5 for the operators' gradients)
    """
    mask = params["mask"][..., None]
    n_blocks = params["T_db"].shape[0]
    use_r = interfaces and params["rec_T"].shape[0] > 0
    fb = params if "W" in params else feedback_operators(params, albedo)
    b = jnp.einsum("bkn,bnc->bkc", params["T_db"], direct * mask)
    b_total = b
    k_r = params["U_r_turned"].shape[-1]
    r_total = jnp.zeros((n_blocks, 4, k_r) + direct.shape[-1:], direct.dtype)
    for k in range(1 + int(feedback)):
        r = _records(params, b, n_blocks) if use_r else None
        if r is not None:
            r_total = r_total + r
        if k < int(feedback):
            b = jnp.einsum("bckj,bjc->bkc", fb["W"], b)
            if r is not None:
                b = b + jnp.einsum("bsckj,bsjc->bkc", fb["V"], r)
            b_total = b_total + b
    return b_total, r_total


def lightmap_parts(params: dict, direct, albedo, *, feedback: int, interfaces: bool = True):
    """Albedo-free indirect light (incident radiance / pi, i.e. E / pi) at every texel, split by
    where it comes from: (within-block U_b b, through interfaces U_r r), each (B, n, 3) and summed
    over 1 + ``feedback`` bounces (each bounce's outgoing light, albedo x incident, is the next
    one's direct light). ``direct`` (B, n, 3) texel radiance in the layout's frame, ``albedo``
    (B, n, 3). The bounces run in the reduced spaces (``coefficients``); only their sum is
    expanded to texels. Pure JAX, jit-able; outgoing indirect radiance is albedo x (within +
    through).

    Numerics:
        case: mrt_parts (``mrt_texels``'s operators and inputs)
        float32: value rtol 1e-4 atol 1e-1; grad rtol 1e-4 atol 1e-2
        (products of operators with both signs over inputs to 1e5: rounding is absolute near zero,
          ~1e-7 of the sum of |terms|, ~1e4 for the values and ~1e5 for the operators' gradients)
    """
    mask = params["mask"][..., None]
    b_total, r_total = coefficients(params, direct, albedo, feedback=feedback, interfaces=interfaces)
    within = jnp.einsum("bnk,bkc->bnc", params["U_b"], b_total) * mask
    inter = jnp.einsum("snj,bsjc->bnc", params["U_r_turned"], r_total) * mask
    return within, inter


def lightmap(params: dict, direct, albedo, *, feedback: int = 4, interfaces: bool = True):
    """Outgoing indirect radiance (..., B, n, 3) at every texel (§7.3 steps 1-5, plus feedback),
    for one direct lighting (B, n, 3) or a batch of them (..., B, n, 3).

    Numerics:
        case: mrt_lightmap (``mrt_texels``'s operators and inputs)
        float32: value rtol 1e-4 atol 1e-1; grad rtol 1e-4 atol 1e-2
        (products of operators with both signs over inputs to 1e5: rounding is absolute near zero,
          ~1e-7 of the sum of |terms|, ~1e4 for the values and ~1e5 for the operators' gradients)
    """
    direct = jnp.asarray(direct, params["T_db"].dtype)
    if direct.ndim > 3:
        return jax.vmap(lambda d: lightmap(params, d, albedo, feedback=feedback, interfaces=interfaces))(direct)
    w, i = lightmap_parts(params, direct, albedo, feedback=feedback, interfaces=interfaces)
    return albedo * (w + i)


def projection(params: dict, reference, use_interfaces: bool = True) -> np.ndarray:
    """The projection floor: each block's reference indirect (B, n, 3) projected (least squares,
    over its existing texels, per channel) onto the span of its U_b and of U_r turned to each of
    its receiving sides. No coefficients MRT can compute do better than this.

    Numerics: not differentiable (a float64 NumPy precomputation).
    """
    ref = np.asarray(reference, np.float64)
    out = np.zeros_like(ref)
    rec_dst = np.asarray(params["rec_dst"])
    rec_side = np.asarray(params["rec_side"])
    for bi in range(ref.shape[0]):
        m = np.asarray(params["mask"][bi], bool)
        cols = [np.asarray(params["U_b"][bi], np.float64)]
        if use_interfaces:
            for s in sorted(set(rec_side[rec_dst == bi].tolist())):
                cols.append(np.asarray(params["U_r_turned"][s], np.float64))
        basis = np.concatenate(cols, axis=1)[m]
        coef, *_ = np.linalg.lstsq(basis, ref[bi][m], rcond=None)
        out[bi][m] = basis @ coef
    return out


def vector_irradiance(params: dict, b, normals_local, kind: str):
    """Irradiance / pi at perturbed normals (§6.4, App. B): ``b`` (B, k_b, 3) block coefficients,
    ``normals_local`` (B, n, 3) unit normals in each texel's frame (tangent u, tangent v,
    normal). ``kind``: "scalar" (the unperturbed F l, ignores the normal), "quadratic" (9 SH
    coefficients convolved with the clamped cosine) or "ohlsh" (4 OHLSH coefficients).

    Numerics:
        case: mrt_vector_irradiance (2 blocks of 8 texels, k_b = 3, random U_b and U_quad, b in
          [-1e5, 1e5], unit normals, kinds "scalar", "quadratic" and "ohlsh")
        float32: value rtol 1e-4 atol 1; grad rtol 1e-4 atol 1e-4
        (sums of terms to 1e5 of both signs: rounding is absolute near zero)
    """
    from jprt.sphere import sh

    q = jnp.einsum("bnqk,bkc->bnqc", params["U_quad"], b)  # (B, n, 9, 3) incident radiance SH
    if kind == "scalar":
        return jnp.einsum("bnk,bkc->bnc", params["U_b"], b)
    y = sh.evaluate(normals_local, 2)  # (B, n, 9)
    a_l = sh.clamped_cosine_coeffs(2)
    band = jnp.asarray(np.concatenate([np.full(2 * l + 1, a_l[l]) for l in range(3)]) / np.pi)[None, None]  # A_l / pi
    if kind == "quadratic":
        return jnp.einsum("bnq,bnqc->bnc", y * band, q)
    if kind == "ohlsh":
        a = sh.ohlsh(jnp.moveaxis(q, 2, 0))  # (4, B, n, 3)
        return jnp.einsum("bnq,qbnc->bnc", (y * band)[..., :4], a)
    raise ValueError(f"vector irradiance kind is 'scalar', 'quadratic' or 'ohlsh', got {kind!r}")


def volume_probes(params: dict, b, r=None):
    """Quadratic SH (B, P, 9, 3) of the radiance at each block's probe lattice (§6.5, §7.3 step
    8): U_bvol b from the block's own light plus, with ``r`` (B, 4, k_r, 3) the summed response
    coefficients of its receiving sides (``coefficients``), U_rvol r for the light arriving
    through them.

    Numerics:
        case: mrt_volume_probes (2 blocks, 4 probes, k_b = 3, k_r = 2, random U_vol and U_rvol, b and r
          in [-1e5, 1e5])
        float32: value rtol 1e-5 atol 1e-1; grad rtol 1e-5 atol 1e-5
        (sums of terms to 1e5 of both signs: rounding is absolute near zero)
    """
    out = jnp.einsum("bpqk,bkc->bpqc", params["U_vol"], b)
    if r is not None and "U_rvol" in params:
        out = out + jnp.einsum("spqj,bsjc->bpqc", params["U_rvol"], r)
    return out


# --------------------------------------------------------------------------------------------
# Contract: data, fit, evaluator, example


class MRTData(NamedTuple):
    """A layout and its held-out lightings (``data.make_dataset``).

    Fields:
      layout: ``jprt.layouts.Layout.as_dict()``.
      albedo: (B, n, 3) texel albedo (missing faces 0).
      positions / normals: (B, n, 3) world texel centres (on the inset faces) and inward normals.
      direct_test / indirect_test: (N, B, n, 3) Mitsuba direct (exact) and indirect
        (``data.test_spp``) outgoing radiance at the texels.
      lights_test: dict of the lights' stacked fields.
      meta: scene description, render seconds, cache path.
    """

    layout: dict
    albedo: np.ndarray
    positions: np.ndarray
    normals: np.ndarray
    direct_test: np.ndarray
    indirect_test: np.ndarray
    lights_test: dict
    meta: dict


def fit(data: MRTData, config: dict | None = None) -> FitResult:
    """The dictionary (scene-independent, cached) and the layout's operators. ``info``:
    precompute and T_b->r build seconds, k's, singular values for Table 2.

    Numerics: not differentiable (a fitting or training procedure).
    """
    cfg = _cfg(config)
    t0 = time.perf_counter()
    dic = dictionary(cfg)
    t_dic = time.perf_counter() - t0
    lay = layout_operators(dic, data.layout, cfg)
    params = {k: v for k, v in lay.items() if k not in ("tbr_build_s", "kind", "turns")}
    params["albedo"] = np.asarray(data.albedo, np.float32)
    params.update(level_feedback(params, data.albedo))
    b, t = texels_of(data.albedo)
    res, texel_index, fill = atlas_layout(b, t)
    params["texel_index"] = texel_index.astype(np.int32)
    params["fill_index"] = fill.astype(np.int32)
    info = {"dictionary_s": t_dic, "precompute_s": float(dic["info_precompute_s"]),
            "tbr_build_s": float(lay["tbr_build_s"]), "records": int(len(lay["rec_src"])),
            "blocks": int(b), "texels": int(t), "k_b": int(dic["T_db"].shape[1]),
            "k_r": int(dic["U_r"].shape[1]) if "U_r" in dic else 0,
            "kinds": [TYPES[k] for k in lay["kind"]], "resolution": res}
    return FitResult(params, info)


#: The transport operators ``lightmap_parts`` applies at run time (the evaluator also reads
#: ``albedo`` and ``fill_index``; the rest of ``params`` serves fitting and reports).
RUNTIME_KEYS = ("T_db", "U_b", "mask", "rec_src", "rec_dst", "rec_side", "rec_T", "U_r_turned", "W", "V")


def evaluator(params: dict, config: dict | None = None):
    """``evaluate(inputs, lighting) -> (H, W, 3)`` outgoing indirect radiance (§7.3).

    ``inputs``: a G-buffer whose ``uv`` are lightmap-atlas coordinates (``atlas_layout``), with
    ``valid`` and ``diffuse_albedo`` (the pixel's albedo; the lightmap stores albedo-free incident
    light / pi, step 7 multiplies). ``lighting``: a ``PointRadiance`` with the direct radiance at
    every texel (B n, 3), in the layout's texel order. One jit: b, U_b b, T_b->r, U_r r,
    ``runtime.feedback`` bounces, the padded atlas, a bilinear lookup.

    Numerics: not differentiable (builds the float32 run-time program; its arithmetic is ``lightmap``'s, covered).
    """
    cfg = _cfg(config)
    arrays = {k: jnp.asarray(params[k]) for k in RUNTIME_KEYS}
    albedo = jnp.asarray(params["albedo"])
    fill = jnp.asarray(params["fill_index"])
    b, n = albedo.shape[:2]
    res = int(round(np.sqrt(fill.shape[0])))
    feedback = int(cfg["runtime"]["feedback"])
    interfaces = bool(cfg["interfaces"]["enabled"])

    @jax.jit
    def image(uv, valid, pix_albedo, direct):
        w, i = lightmap_parts(arrays, direct.reshape(b, n, 3), albedo, feedback=feedback, interfaces=interfaces)
        incident = (w + i).reshape(b * n, 3)  # albedo-free: each pixel's own albedo applies
        atlas = incident[fill].reshape(res, res, 3)
        return jnp.where(valid[..., None], pix_albedo * atlas_lookup(atlas, uv), 0.0)

    def evaluate(inputs, lighting):
        direct = jnp.asarray(lighting.direct, jnp.float32)
        if direct.shape != (b * n, 3):
            raise ValueError(f"lighting.direct must be ({b * n}, 3) radiance at every texel, got {direct.shape}")
        uv = jnp.asarray(inputs.uv, jnp.float32)
        valid = jnp.asarray(inputs.valid, bool)
        if uv.shape[:-1] != valid.shape or uv.shape[-1] != 2:
            raise ValueError(f"inputs.uv must be (H, W, 2) matching valid (H, W), got {uv.shape} and {valid.shape}")
        return image(uv, valid, jnp.asarray(inputs.diffuse_albedo, jnp.float32), direct)

    return evaluate


def example(data: MRTData, config: dict | None = None):
    """A held-out (inputs, lighting) pair: the atlas itself (every texel, its albedo) and the
    first held-out lighting's direct light at the texels.

    Numerics: not differentiable (a held-out input and lighting from a dataset).
    """
    return atlas_gbuffer_inputs(data.albedo), PointRadiance(
        np.asarray(data.direct_test[0], np.float32).reshape(-1, 3))
