"""Modular Radiance Transfer (Loos et al. 2011): the canonical block's operators against closed
forms, the §4 identities, block turns, the §6.3 propagation on tiny graphs (with a cycle), the
run time's stability on 1 block, a 41-block corridor and a layout with cycles, and a 2-block
Mitsuba smoke test (no light between unconnected blocks)."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from jprt import layouts
from jprt.methods.mrt import PRESETS, model
from jprt.methods.mrt import operators as ops

T = 4  # texels per face axis in these tests


@pytest.fixture(scope="module")
def ff():
    return ops.form_factors(T, 2)


@pytest.fixture(scope="module")
def dic(tmp_path_factory):
    cfg = model._cfg(PRESETS["test"])
    return model.dictionary(cfg, cache_dir=str(tmp_path_factory.mktemp("mrt"))), cfg


def test_gather_matches_cube_form_factors(ff):
    # unit cube: parallel faces 0.19982, faces sharing an edge 0.20004 (Hottel's crossed strings /
    # the closed forms of Howell's catalogue); rows of a closed cube sum to 1
    np.testing.assert_allclose(ff.sum(axis=1), 1.0, atol=1e-9)
    face = ff.reshape(6, T * T, 6, T * T).sum(-1).mean(1)
    assert face[0, 1] == pytest.approx(0.199825, abs=2e-4)  # floor -> ceiling
    assert face[2, 4] == pytest.approx(0.199825, abs=2e-4)  # side 0 -> side 2
    assert face[0, 2] == pytest.approx(0.200044, abs=2e-4)  # floor -> side 0
    assert face[3, 4] == pytest.approx(0.200044, abs=2e-4)
    assert np.all(np.diag(face) == 0)
    # reciprocity (equal texel areas): F is symmetric up to the receiver quadrature's error
    # (the source texel is integrated exactly), which a finer rule shrinks
    asym2 = np.abs(ff - ff.T).max()
    assert asym2 < 1e-2 * ff.max()
    f4 = ops.form_factors(T, 4)
    assert np.abs(f4 - f4.T).max() < 0.2 * asym2


def test_full_rank_prior_reproduces_f(ff):
    n = ff.shape[0]
    out = model.reduce_transfer(ff, np.eye(n), np.ones(n), n)
    np.testing.assert_allclose(out["U_b"] @ out["T_db"], ff, atol=1e-10)


def test_implicit_lighting_gives_u_b(dic):
    d, cfg = dic
    f = d["F_closed"]
    for k, name in enumerate(model.TYPES):
        mask = d["mask"][k]
        fm = f * mask[:, None] * mask[None]
        np.testing.assert_allclose(fm @ d["L_imp"][k], d["U_b"][k], atol=2e-5 * np.abs(d["U_b"][k]).max(), err_msg=name)


def test_closed_box_converges_to_geometric_series(dic):
    d, cfg = dic
    lay = layouts.corridor(1)
    params = model.layout_operators(d, lay.as_dict(), cfg)
    n = layouts.texel_count(T)
    rho, light = 0.6, 0.8
    out = np.asarray(model.lightmap(params, np.full((1, n, 3), light, np.float32), np.full((1, n, 3), rho, np.float32),
                                    feedback=60))
    # the reduced transfer keeps k_b = 12 modes here, so uniform light is reproduced to ~0.2 %
    np.testing.assert_allclose(out, rho * light / (1 - rho), rtol=5e-3)
    assert np.abs(out - rho * light / (1 - rho)).mean() < 2e-3 * rho * light / (1 - rho)


def test_turns_are_texel_permutations(ff):
    for r in range(4):
        perm = layouts.rotation_permutation(T, r)
        assert sorted(perm) == list(range(len(perm)))
        np.testing.assert_allclose(ff[np.ix_(perm, perm)], ff, atol=1e-12)  # the cube is symmetric
    p = layouts.rotation_permutation(T, 1)
    four = np.arange(len(p))
    for _ in range(4):
        four = p[four]
    np.testing.assert_array_equal(four, np.arange(len(p)))
    # the direct light of a turned light is the turned direct light (side 0 missing -> side 1)
    light = np.array([[0.3, 0.6, 0.2], [1.4, 0.5, 0.3]])  # inside, and beyond side 0
    a = ops.point_light_direct(T, light, (0,))
    b = ops.point_light_direct(T, layouts.rotate_points(light, 1), (1,))
    np.testing.assert_allclose(layouts.rotate_pattern(a, T, 1), b, atol=1e-12)


@settings(max_examples=25, deadline=None)
@given(st.floats(0.0, 1.0), st.floats(0.0, 1.0))
def test_concentric_map_round_trip(a, b):
    sq = np.array([[a, b]])
    disk = ops.concentric(sq)
    assert np.hypot(*disk[0]) <= 1 + 1e-12
    np.testing.assert_allclose(ops.concentric_inverse(disk), sq, atol=1e-9)


def test_lightfield_operators_conserve():
    rays = ops.lightfield_rays(2, 4, 2, 2)
    a = ops.exit_resampling(T, rays, 2, 4)
    np.testing.assert_allclose(np.asarray(a.sum(1)).ravel(), 1.0)  # a uniform block gives a uniform lightfield
    f_rlf = ops.entry_response(T, rays, 2, 4, 2, 2)
    # all light entering lands somewhere: sum_j A_j (E_j / pi) = flux / pi = 1 for unit radiance
    assert float(f_rlf.sum()) / T ** 2 == pytest.approx(1.0, abs=1e-9)
    for k, r in ops.propagation(rays, 2, 4).items():
        # a uniform entering lightfield leaves through a side with about the face-to-face form factor
        assert float(np.asarray(r.sum(1)).mean()) == pytest.approx(0.2, abs=0.03), k


@pytest.mark.parametrize("side", [0, 1, 3])
def test_probe_sees_an_entering_lightfield(side):
    # unit radiance entering through one side: from the block's centre that side covers 4 pi / 6
    # of the sphere, so the SH DC coefficient is Y00 * 4 pi / 6 = sqrt(pi) / 3
    op = ops.volume_lightfield_sh([[0.5, 0.5, 0.5]], 64, 2, 4, side)
    dc = float(op[0, 0].sum())
    assert dc == pytest.approx(np.sqrt(np.pi) / 3, rel=0.03)
    # and the linear band points towards that side (SH order: y, z, x for l = 1)
    lin = op[0, 1:4].sum(-1)
    towards = layouts.SIDE_NORMALS[side]
    assert np.dot(lin[[2, 0, 1]], towards) > 0.9 * np.linalg.norm(lin)


def test_layout_kinds_and_turns():
    g = layouts.grid(3, 3)
    kinds = {b.cell: (b.kind, b.turns) for b in g.blocks}
    assert kinds[(1, 1)][0] == "cross" and kinds[(0, 0)][0] == "corner" and kinds[(1, 0)][0] == "tee"
    for b in g.blocks:  # the turned canonical block has exactly the cell's open sides
        assert {(s + b.turns) % 4 for s in layouts.DICTIONARY[b.kind]} == set(b.open_sides)
    assert g.has_cycle() and not layouts.corridor(5).has_cycle()
    assert sum(len(v) for v in layouts.DICTIONARY.values()) == 12
    with pytest.raises(ValueError, match="4-adjacent"):
        layouts.Layout.create([(0, 0), (2, 0)], [((0, 0), (2, 0))])


def _records(params):
    return {(int(s), int(d), int(e)) for s, d, e in zip(params["rec_src"], params["rec_dst"], params["rec_side"])}


def test_propagation_on_tiny_graphs(dic):
    d, cfg = dic
    # a 2 x 2 loop: cells 0 (0,0), 1 (0,1), 2 (1,0), 3 (1,1) in sorted order
    loop = layouts.grid(2, 2)
    p = model.layout_operators(d, loop.as_dict(), cfg)
    rec = _records(p)
    assert all(s != t for s, t, _ in rec)  # no light returns to its own block around the loop
    from_0 = {(t, e) for s, t, e in rec if s == 0}
    # neighbours through their facing side, the far corner through both of its open sides
    assert from_0 == {(2, 2), (1, 3), (3, 2), (3, 3)}
    # depth 1: only the neighbours
    p1 = model.layout_operators(d, loop.as_dict(), model._cfg({**PRESETS["test"], "interfaces": {
        **PRESETS["test"]["interfaces"], "d_max": 1}}))
    assert {(t, e) for s, t, e in _records(p1) if s == 0} == {(2, 2), (1, 3)}
    # a corridor of 3: the far block is reached through the middle one only
    c = model.layout_operators(d, layouts.corridor(3).as_dict(), cfg)
    assert {(t, e) for s, t, e in _records(c) if s == 0} == {(1, 2), (2, 2)}
    # a 2 x 3 grid full of cycles still terminates with finite, summed records
    g = model.layout_operators(d, layouts.grid(2, 3).as_dict(), cfg)
    assert np.isfinite(g["rec_T"]).all() and len(_records(g)) == len(g["rec_src"])


@pytest.mark.parametrize("lay", [layouts.corridor(1), layouts.corridor(41), layouts.random_maze(19, seed=2, extra_edges=5)],
                         ids=["one_block", "corridor41", "maze_cycles"])
def test_run_time_is_stable(dic, lay):
    d, cfg = dic
    p = model.layout_operators(d, lay.as_dict(), cfg)
    rng = np.random.default_rng(0)
    n = layouts.texel_count(T)
    direct = rng.random((len(lay.cells), n, 3)).astype(np.float32)
    albedo = layouts.texel_albedo(lay, T, {"floor": [0.6] * 3, "ceiling": [0.75] * 3, "walls": [[0.7, 0.7, 0.7]]})
    out = np.asarray(model.lightmap(p, direct, albedo.astype(np.float32), feedback=6))
    assert np.isfinite(out).all()
    mask = np.asarray(p["mask"], bool)
    assert np.all(out[~mask] == 0)
    # energy: never more than the geometric series of the largest albedo over the direct light
    assert out[mask].sum() < 0.75 / (1 - 0.75) * direct[mask].sum()
    assert out[mask].sum() > 0.05 * direct[mask].sum()


def test_reduced_feedback_equals_texel_loop(dic):
    d, cfg = dic
    lay = layouts.random_maze(7, seed=4, extra_edges=2)
    p = model.layout_operators(d, lay.as_dict(), cfg)
    rng = np.random.default_rng(1)
    direct = rng.random((len(lay.cells), layouts.texel_count(T), 3)).astype(np.float32)
    albedo = layouts.texel_albedo(lay, T, {"floor": [0.6, 0.5, 0.4], "ceiling": [0.75] * 3,
                                           "walls": [[0.7, 0.2, 0.3], [0.3, 0.6, 0.8]]}).astype(np.float32)
    for fb in (0, 3):
        want = model.lightmap_parts_texels(p, direct, albedo, feedback=fb)
        got = model.lightmap_parts(p, direct, albedo, feedback=fb)
        for g, w in zip(got, want):
            np.testing.assert_allclose(np.asarray(g), np.asarray(w), rtol=1e-4, atol=1e-6 * float(np.abs(w).max()))


def test_vector_irradiance_kinds(dic):
    d, cfg = dic
    p = model.layout_operators(d, layouts.corridor(2).as_dict(), cfg)
    n = layouts.texel_count(T)
    b = np.ones((2, p["T_db"].shape[1], 3), np.float32)
    up = np.broadcast_to(np.array([0.0, 0.0, 1.0], np.float32), (2, n, 3))
    scalar = np.asarray(model.vector_irradiance(p, b, up, "scalar"))
    quad = np.asarray(model.vector_irradiance(p, b, up, "quadratic"))
    # at the unperturbed normal the quadratic SH irradiance approximates F l (SH truncation only)
    mask = np.asarray(p["mask"], bool)
    rel = np.linalg.norm(quad[mask] - scalar[mask]) / np.linalg.norm(scalar[mask])
    assert rel < 0.2
    with pytest.raises(ValueError, match="scalar"):
        model.vector_irradiance(p, b, up, "cubic")


@pytest.mark.mitsuba
def test_blocks_scene_two_block_smoke(mi):
    from jprt.inputs import PointLights
    from jprt.methods.mrt import data
    from jprt.render import lightmap
    from jprt.render.scenes import SceneHandle, blocks

    light = PointLights.create([0.5, 0.5, 0.5], [1.0, 1.0, 1.0])
    for connected in (True, False):
        lay = layouts.Layout.create([(0, 0), (1, 0)], [((0, 0), (1, 0))] if connected else [])
        desc = blocks(lay)
        pos, nrm, alb = data.texel_geometry(desc, T)
        h = SceneHandle(desc, light)
        direct = lightmap.radiance_at_points(h, pos.reshape(-1, 3), nrm.reshape(-1, 3), spp=1).reshape(pos.shape)
        # block 0's floor: Mitsuba's direct light equals the analytic one times the albedo (the
        # faces sit BLOCK_INSET inside the cube: distances to the centre shrink by 1 - 2 inset)
        from jprt.render.scenes import BLOCK_INSET

        want = ops.point_light_direct(T, [[0.5, 0.5, 0.5]], (0,) if connected else ())[:T * T, 0] * 0.6
        want = want / (1 - 2 * BLOCK_INSET) ** 2
        np.testing.assert_allclose(direct[0, :T * T, 0], want, rtol=2e-3)
        far = direct[1][np.asarray(alb[1].sum(-1) > 0)]
        if connected:
            assert far.max() > 0.01  # light reaches the neighbour through the opening
        else:
            assert far.max() == 0.0  # walls one-sided per block, back to back: nothing leaks


@pytest.mark.parametrize("override, match", [({"dictionary": {"k_b": 0}}, "dictionary.k_b"),
                                             ({"interfaces": {"spatial": 2.5}}, "interfaces.spatial"),
                                             ({"runtime": {"feedback": -1}}, "runtime.feedback")])
def test_bad_sizes_are_refused_with_one_line(override, match):
    with pytest.raises(ValueError, match=match):
        model._cfg(override)


def test_non_block_scene_needs_a_proxy():
    from jprt.methods.mrt import data

    with pytest.raises(ValueError, match="proxy.layout"):
        data.block_frame({"name": "cornell_box"}, model._cfg({}))
