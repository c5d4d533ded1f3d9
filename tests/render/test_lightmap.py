"""Lightmap atlases, surface samples and radiance at surface points (jprt.render.lightmap)."""

import os

import numpy as np
import pytest

from jprt.render import lightmap
from jprt.render.gbuffer import hit_objects
from jprt.render.cameras import look_at
from jprt.render.lights import DirectionalLights, PointLights, SpotLights
from jprt.render.scenes import SceneHandle, asset_room, cornell_box


@pytest.fixture(scope="module")
def cornell(mi):
    handle = SceneHandle(cornell_box(area_light=False))
    return handle, lightmap.build_atlas(handle, None, resolution=48)


def test_texels_lie_on_their_surfaces_and_face_outwards(cornell):
    handle, atlas = cornell
    mi = handle.mi
    p, n = atlas.position.astype(np.float64), atlas.normal.astype(np.float64)
    ray = mi.Ray3f(mi.Point3f(*(p + 1e-2 * n).T.astype(np.float32)), mi.Vector3f(*(-n).T.astype(np.float32)))
    si = handle.scene.ray_intersect(ray)
    t = np.array(si.t, np.float64).reshape(-1)
    assert np.mean(np.abs(t - 1e-2) < 1e-4) > 0.99  # the offset ray hits the texel's own surface
    assert set(np.unique(atlas.texel_object)) == set(range(7))
    # the cubes' overlapping UVs were split into planar charts: one per visible face direction
    for obj in (5, 6):
        dirs = np.unique(np.round(atlas.normal[atlas.texel_object == obj], 2), axis=0)
        assert len(dirs) >= 5, dirs
    assert np.all(atlas.fill_index >= 0) and atlas.fill_index.max() < atlas.count


def test_hit_objects_names_each_hits_shape(cornell):
    """The registry-id table reads the same object per hit as comparing the hits' shape pointers
    with each shape in turn, and -1 for rays that leave the box through its open side."""
    handle, _ = cornell
    mi = handle.mi
    rng = np.random.default_rng(3)
    d = rng.normal(size=(4000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    o = np.tile([0.1, 0.2, -0.1], (4000, 1))
    si = lightmap.intersect(handle, o, d)
    expected = np.full(4000, -1)
    for k, shape in enumerate(handle.shapes()):
        expected[np.array(si.shape == mi.ShapePtr(shape), bool).reshape(-1)] = k
    got = hit_objects(handle, si)
    np.testing.assert_array_equal(got, expected)
    assert len(np.unique(got[got >= 0])) >= 5 and np.any(got == -1)


def test_atlas_gbuffer_uv_points_at_the_texel_under_the_pixel(cornell):
    handle, atlas = cornell
    gb = lightmap.atlas_gbuffer(handle, atlas, handle.default_camera(48, 48))
    assert gb.valid.mean() > 0.9
    r = atlas.resolution
    ij = np.clip((gb.uv[gb.valid] * r).astype(int), 0, r - 1)
    texel = atlas.fill_index[ij[:, 1] * r + ij[:, 0]]
    dist = np.linalg.norm(atlas.position[texel] - gb.position[gb.valid], axis=1) / atlas.texel_size
    assert np.median(dist) < 0.75 and np.percentile(dist, 95) < 1.5


def test_direct_at_points_matches_the_analytic_point_light(cornell):
    handle, _ = cornell
    light = np.array([0.1, 0.5, 0.2])
    handle.set_lighting(PointLights.create(light, [2.0, 3.0, 4.0]))
    p = np.array([[-0.6, -1.0, 0.7], [0.8, -1.0, -0.3]])  # floor points the blocks do not shadow
    n = np.array([[0.0, 1.0, 0.0]] * 2)
    got = lightmap.radiance_at_points(handle, p, n, spp=1)
    d = light - p
    r2 = np.sum(d * d, axis=1)
    cos = d[:, 1] / np.sqrt(r2)
    albedo = np.array([0.885809, 0.698859, 0.666422])
    expected = albedo / np.pi * np.array([2.0, 3.0, 4.0]) * (cos / r2)[:, None]
    np.testing.assert_allclose(got, expected, rtol=2e-3)


def test_spot_and_directional_lights(cornell):
    handle, _ = cornell
    spot = SpotLights.create([0.0, 0.8, 0.0], [0.0, -1.0, 0.0], [5.0, 5.0, 5.0], 30.0)
    handle.set_lighting(spot)
    builds = handle.builds
    moved = SpotLights.create([0.2, 0.7, 0.1], [0.2, -1.0, 0.1], [1.0, 2.0, 3.0], 30.0)
    handle.set_lighting(moved)
    assert handle.builds == builds  # same layout: parameters written, no rebuild
    dirs, irr = lightmap.incident_delta_lights(handle, [0.2, -0.3, 0.1], moved)
    np.testing.assert_allclose(dirs[0], [0, 1, 0], atol=1e-5)
    np.testing.assert_allclose(irr[0], np.array([1.0, 2.0, 3.0]) / 1.0 ** 2, rtol=1e-4)
    # off the cone: nothing
    _, irr_off = lightmap.incident_delta_lights(handle, [0.9, -0.3, 0.9], moved)
    assert np.all(irr_off == 0)
    sun = DirectionalLights.create([0.0, -1.0, -1.0], [1.0, 1.0, 1.0])
    dirs, _ = lightmap.incident_delta_lights(handle, [0, 0, 0], sun)
    np.testing.assert_allclose(dirs[0], [0, np.sqrt(0.5), np.sqrt(0.5)], atol=1e-6)
    with pytest.raises(ValueError, match="beam_deg"):
        SpotLights.create([0, 0, 0], [0, -1, 0], [1, 1, 1], cutoff_deg=20, beam_deg=30)


def test_free_positions_and_surface_samples(cornell):
    handle, _ = cornell
    inside_large_box, centre, near_wall = [-0.33, -0.4, -0.28], [0.0, 0.3, 0.3], [0.0, 0.3, -0.97]
    free = lightmap.free_positions(handle, [inside_large_box, centre, near_wall], clearance=0.1)
    assert free.tolist() == [False, True, False]
    pts = lightmap.surface_samples(handle, 500, objects=["floor", "small-box"], seed=1)
    assert set(np.unique(pts.object_id)) <= {0, 5}
    np.testing.assert_allclose(pts.area, 4.0 + 5 * 0.6 ** 2 + 0.36, rtol=0.05)  # floor + cube faces
    assert np.all(pts.albedo[pts.object_id == 0] > 0.6)


def test_asset_room_atlas_uses_the_mesh_uvs(assets):
    mesh = os.path.join(assets, "meshes", "c3d_spot.obj")
    handle = SceneHandle(asset_room(mesh))
    atlas = lightmap.build_atlas(handle, ["asset"], resolution=32)
    assert set(np.unique(atlas.texel_object)) == {handle.object_names().index("asset")}
    cam = look_at([2.6, 1.3, 2.4], [0.0, 0.1, 0.2], fov=40.0, width=32, height=32)
    gb = lightmap.atlas_gbuffer(handle, atlas, cam)
    assert 0.05 < gb.valid.mean() < 0.9  # the asset, not the room


def test_vertex_interpolation_reproduces_surface_points(mi):
    """Interpolating the subdivided mesh's vertex positions gives back the surface points: exactly on
    flat triangles, within the chord error on the (analytic, lat-long tessellated) sphere."""
    from jprt.render.cameras import look_at
    from jprt.render.gbuffer import gbuffer
    from jprt.render.lightmap import vertex_interpolation
    from jprt.render.scenes import SceneHandle, glossy_cornell

    handle = SceneHandle(glossy_cornell(open_top=True))
    g = gbuffer(handle, look_at((0.2, 0.8, 3.5), (0, -0.1, 0), width=24, height=24))
    edge = 0.25
    idx, w, verts = vertex_interpolation(handle, g.position, edge=edge)
    np.testing.assert_allclose(w.sum(-1), 1.0, rtol=1e-5)
    assert idx.min() >= 0 and idx.max() < len(verts)
    rec = np.einsum("...k,...kc->...c", w, verts[idx])
    err = np.linalg.norm(rec - g.position, axis=-1)
    names = handle.object_names()
    sphere = g.object_id == names.index("large-box")
    flat = g.valid & ~sphere
    assert flat.any() and sphere.any()
    assert err[flat].max() < 1e-4
    assert err[sphere].max() < edge**2 / (8 * 0.4) * 2 + 1e-4  # sagitta of the chords at radius 0.4
    # vertices are shared: neighbouring pixels on one wall reuse them
    assert len(np.unique(idx[flat][:, :3])) < 3 * flat.sum()


def _sphere_obj(path, center, radius, uv_mode, n=10, degenerate=0):
    """A UV sphere as an OBJ: ``uv_mode`` "collapsed" (every corner at one UV), "overlap" (every
    triangle on the same UV triangle) or "none"; ``degenerate`` zero-area triangles appended."""
    lines, faces = [], []
    for i in range(n + 1):
        th = np.pi * i / n
        for j in range(2 * n):
            ph = np.pi * j / n
            p = np.asarray(center) + radius * np.array([np.sin(th) * np.cos(ph), np.cos(th), np.sin(th) * np.sin(ph)])
            lines.append("v %.6f %.6f %.6f" % tuple(p))
    idx = lambda i, j: i * 2 * n + (j % (2 * n)) + 1  # noqa: E731
    for i in range(n):
        for j in range(2 * n):
            if i < n - 1:  # not the pole row below (its corners coincide)
                faces.append((idx(i, j), idx(i + 1, j), idx(i + 1, j + 1)))
            if i > 0:
                faces.append((idx(i, j), idx(i + 1, j + 1), idx(i, j + 1)))
    faces += [(idx(n // 2, 0), idx(n // 2, 0), idx(n // 2, 1))] * degenerate
    if uv_mode == "collapsed":
        lines.append("vt 0.5 0.5")
        lines += ["f %d/1 %d/1 %d/1" % f for f in faces]
    elif uv_mode == "overlap":
        lines += ["vt 0 0", "vt 1 0", "vt 0 1"]
        lines += ["f %d/1 %d/2 %d/3" % f for f in faces]
    else:
        lines += ["f %d %d %d" % f for f in faces]
    path.write_text("\n".join(lines) + "\n")


@pytest.mark.mitsuba
def test_atlas_of_meshes_with_collapsed_overlapping_and_degenerate_uvs(mi, tmp_path):
    """Issue 21's meshes: UVs collapsed to a point, every triangle on the same UV triangle, no
    UVs, zero-area triangles, and a tiny object beside big ones. xatlas charts them (a curved mesh
    would otherwise make hundreds of planar charts), every object gets at least ``min_texels``
    texels, the dropped triangles are counted, and the atlas G-buffer looks up texels of the
    object under each pixel."""
    import warnings

    from jprt.render.cameras import look_at
    from jprt.render.scenes import SceneHandle

    shapes = []
    for name, (center, radius, mode, bad) in {"collapsed": ((-1.2, 0, 0), 0.5, "collapsed", 3),
                                               "overlap": ((0, 0, 0), 0.5, "overlap", 0),
                                               "plain": ((1.2, 0, 0), 0.5, "none", 2),
                                               "tiny": ((0, 0.9, 0), 0.03, "none", 0)}.items():
        _sphere_obj(tmp_path / f"{name}.obj", center, radius, mode, degenerate=bad)
        shapes.append(f'<shape type="obj" id="{name}"><string name="filename" value="{tmp_path / name}.obj"/>'
                      f'<boolean name="face_normals" value="true"/><bsdf type="diffuse"/></shape>')
    scene = tmp_path / "spheres.xml"
    scene.write_text('<scene version="3.0.0">' + "".join(shapes) + "</scene>")
    handle = SceneHandle({"name": "xml", "path": str(scene)})
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        atlas = lightmap.build_atlas(handle, resolution=64, min_texels=4)
    counted = [str(w.message) for w in caught if "zero-area" in str(w.message)]
    assert counted and "5 zero-area triangles" in counted[0] and "collapsed: 3" in counted[0], counted
    per_object = np.bincount(atlas.texel_object, minlength=4)
    assert per_object.min() >= 4, per_object
    assert per_object[:3].min() > 100  # the big spheres share the atlas by area
    camera = look_at((0.0, 0.2, 4.0), (0.0, 0.2, 0.0), fov=45.0, width=48, height=32)
    g = lightmap.atlas_gbuffer(handle, atlas, camera)
    res = atlas.resolution
    texel = np.clip((g.uv * res).astype(int), 0, res - 1)
    fill = atlas.fill_index[texel[..., 1] * res + texel[..., 0]]
    hit = g.valid
    assert hit.sum() > 200
    owner = atlas.texel_object[fill[hit]]
    assert np.mean(owner == g.object_id[hit]) > 0.97  # pixels read texels of their own object


@pytest.mark.mitsuba
def test_a_chart_thinner_than_a_texel_still_gets_texels(mi, tmp_path):
    """Conservative rasterisation (issue 21: veach-bidir's table edge): a slab 1/20 of a texel
    thick beside a large floor has texels on all six faces, each on its own face, and the pixels
    that see the slab's thin side read a texel of that side, not the nearest covered texel of the
    atlas (before: the side had no texel, and its pixels read texels up to 26 texels away)."""
    slab = ('<shape type="cube" id="slab"><transform name="to_world"><scale x="0.5" y="{t}" z="0.5"/>'
            '<translate y="{t}"/></transform><bsdf type="diffuse"/></shape>')
    floor = ('<shape type="rectangle" id="floor"><transform name="to_world"><scale value="4"/>'
             '<rotate x="1" angle="-90"/></transform><bsdf type="diffuse"/></shape>')
    scene = tmp_path / "slab.xml"
    res = 32
    texel = 2 * 4 * 1.3 / res  # about the texel size of the floor alone at this resolution
    scene.write_text('<scene version="3.0.0">' + floor + slab.format(t=texel / 40) + "</scene>")
    handle = SceneHandle({"name": "xml", "path": str(scene)})
    atlas = lightmap.build_atlas(handle, resolution=res)
    obj = handle.object_names().index("slab")
    mine = atlas.texel_object == obj
    faces = np.unique(np.round(atlas.normal[mine], 3), axis=0)
    assert len(faces) == 6, faces  # every face, the four thin sides included
    thickness = 2 * texel / 40
    assert thickness < 0.1 * atlas.texel_size
    # each texel lies on the slab's surface (a thin side's texels at the side's nearest point)
    p = np.abs(atlas.position[mine].astype(np.float64))
    on_face = (np.abs(p[:, 0] - 0.5) < 1e-5) | (np.abs(p[:, 2] - 0.5) < 1e-5) | (p[:, 1] < 1e-5) | \
        (np.abs(p[:, 1] - thickness) < 1e-5)
    assert on_face.all() and (p[:, [0, 2]] <= 0.5 + 1e-5).all()
    # a camera level with the slab's front side, close: pixels of the side read a texel within a
    # texel of where they look
    camera = look_at((0.0, texel / 40, 0.7), (0.0, texel / 40, 0.0), fov=40.0, width=32, height=32)
    g = lightmap.atlas_gbuffer(handle, atlas, camera)
    side = g.valid & (g.object_id == obj)
    assert side.sum() >= 8
    ij = np.clip((g.uv[side] * res).astype(int), 0, res - 1)
    fill = atlas.fill_index[ij[:, 1] * res + ij[:, 0]]
    dist = np.linalg.norm(atlas.position[fill] - g.position[side], axis=1) / atlas.texel_size
    assert dist.max() < 1.0, dist.max()


def _many_quads_file(tmp_path, n: int, flat: bool = False) -> str:
    """An XML scene of ``n`` separate unit quads in a row (and one mesh of zero area when ``flat``)."""
    quads = "".join(f'<shape type="rectangle" id="q{k}"><transform name="to_world"><translate x="{3 * k}"/>'
                    "</transform></shape>" for k in range(n))
    extra = ""
    if flat:
        (tmp_path / "flat.obj").write_text("v 0 0 1\nv 1 0 1\nv 2 0 1\nf 1 2 3\n")
        extra = '<shape type="obj" id="flat"><string name="filename" value="flat.obj"/></shape>'
    path = tmp_path / "quads.xml"
    path.write_text(f'<scene version="3.0.0">{quads}{extra}</scene>')
    return str(path)


def test_an_atlas_grows_when_its_charts_gutters_overfill_it(mi, tmp_path):
    """Forty charts with their gutters cannot fit 8 x 8 texels: the atlas doubles (with a warning
    naming the size) and every quad gets texels, instead of refusing a file of many small meshes."""
    from jprt.render.scenes import SceneHandle, xml

    handle = SceneHandle(xml(_many_quads_file(tmp_path, 40)))
    with pytest.warns(UserWarning, match=r"do not fit a 8 x 8 atlas at the texel density it asks; the atlas is \d+ x \d+"):
        atlas = lightmap.build_atlas(handle, resolution=8)
    assert 8 < atlas.resolution <= 8 * lightmap.ATLAS_GROWTH
    assert set(np.unique(atlas.texel_object)) == set(range(40))


def test_an_object_without_area_is_left_out_of_the_atlas(mi, tmp_path):
    from jprt.render.scenes import SceneHandle, xml

    handle = SceneHandle(xml(_many_quads_file(tmp_path, 2, flat=True)))
    names = handle.object_names()
    with pytest.warns(UserWarning, match="1 objects without area left out \\(flat\\)"):
        atlas = lightmap.build_atlas(handle, resolution=32)
    assert names.index("flat") not in atlas.objects.tolist() and len(atlas.objects) == 2


def _strewn_file(tmp_path, name: str, n: int, size: float, seed: int) -> str:
    """A 4 x 4 floor and one mesh ``name`` of ``n`` separate triangles of side ``size`` (random
    orientations) strewn over 2 m: xatlas makes a chart of each, padded by its gutter."""
    rng = np.random.default_rng(seed)
    lines, faces = [], []
    for k in range(n):
        centre = rng.uniform(-1.0, 1.0, 3) + [0.0, 0.0, 1.0]
        a, b = rng.normal(size=3), rng.normal(size=3)
        for p in (centre, centre + size * a / np.linalg.norm(a), centre + size * b / np.linalg.norm(b)):
            lines.append("v {:.6f} {:.6f} {:.6f}".format(*p))
        faces.append(f"f {3 * k + 1} {3 * k + 2} {3 * k + 3}")
    (tmp_path / f"{name}.obj").write_text("\n".join(lines + faces) + "\n")
    path = tmp_path / f"{name}.xml"
    path.write_text('<scene version="3.0.0"><shape type="rectangle" id="floor"><transform name="to_world">'
                    '<scale value="2"/></transform></shape>'
                    f'<shape type="obj" id="{name}"><string name="filename" value="{name}.obj"/></shape></scene>')
    return str(path)


def _specks_file(tmp_path) -> str:
    """40 tiny triangles (1 mm): almost no area over a wide layout."""
    return _strewn_file(tmp_path, "specks", 40, 1e-3, 3)


def test_an_object_of_almost_no_area_cannot_take_the_atlas_over(mi, tmp_path, monkeypatch):
    """Raising the texel density of an object too small for its texels keeps its charts within
    a few texels (RAISED_SPAN, and LAYOUT_SLACK on the layout it grows to): the atlas keeps the
    density the asked resolution promises and the floor gets the texels its area asks at that
    texel size, the specks some of their own. With neither bound (both at infinity) the same
    file's specks take the atlas over (the failure they prevent)."""
    from jprt.render.scenes import SceneHandle, xml

    handle = SceneHandle(xml(_specks_file(tmp_path)))
    names = handle.object_names()
    atlas = lightmap.build_atlas(handle, resolution=32)
    counts = np.bincount(np.asarray(atlas.texel_object), minlength=2)
    # the density the asked resolution promises (the specks' gutters may double the atlas once)
    assert atlas.resolution <= 64 and atlas.texel_size <= lightmap.DENSITY_SLACK * 4.0 / 32
    assert counts[names.index("floor")] >= 0.9 * 16.0 / atlas.texel_size ** 2
    assert counts[names.index("specks")] >= 1
    monkeypatch.setattr(lightmap, "RAISED_SPAN", np.inf)
    monkeypatch.setattr(lightmap, "LAYOUT_SLACK", np.inf)
    try:
        unbounded = lightmap.build_atlas(handle, resolution=32)
    except ValueError:  # no atlas up to ATLAS_GROWTH x fits
        return
    floor = np.asarray(unbounded.texel_object) == names.index("floor")
    assert floor.sum() < 0.1 * counts[names.index("floor")]  # the specks took the atlas over


def _foliage_file(tmp_path) -> str:
    """300 separate 2 cm triangles (foliage, a curtain's folds: charts smaller than a texel)."""
    return _strewn_file(tmp_path, "foliage", 300, 0.02, 5)


def test_a_layout_of_charts_smaller_than_a_texel_keeps_its_share_of_the_atlas(mi, tmp_path, monkeypatch):
    """A mesh of many separate pieces smaller than a texel (foliage) is laid out as hundreds of
    charts, each padded by gutters: a layout far wider than its area. It is shrunk to LAYOUT_SLACK
    x its area, so the floor keeps the texel density its area asks at the asked resolution and
    the foliage still has texels of its own (its pieces share them). Without the bound the
    foliage's gutters coarsen the floor's texels several times over (the failure this prevents)."""
    from jprt.render.scenes import SceneHandle, xml

    handle = SceneHandle(xml(_foliage_file(tmp_path)))
    names = handle.object_names()
    floor, foliage = names.index("floor"), names.index("foliage")

    def counts(atlas):
        return np.bincount(np.asarray(atlas.texel_object), minlength=2)

    alone = lightmap.build_atlas(handle, ["floor"], resolution=64)
    bounded = lightmap.build_atlas(handle, resolution=64)
    n = counts(bounded)
    foliage_area = 300 * 0.5 * 0.02 ** 2  # about: two random unit directions are near orthogonal
    assert n[floor] >= 0.5 * alone.texel_index.size
    assert 1 <= n[foliage] <= 4.0 * lightmap.LAYOUT_SLACK * foliage_area / bounded.texel_size ** 2
    monkeypatch.setattr(lightmap, "LAYOUT_SLACK", np.inf)
    unbounded = counts(lightmap.build_atlas(handle, resolution=64))
    assert unbounded[floor] < 0.5 * n[floor]


def test_an_atlas_grows_until_its_texels_are_as_fine_as_asked(mi, tmp_path):
    """Forty small quads' gutters beside one large floor: at the asked resolution the floor would
    get texels far coarser than a gutter-free packing of the same area; the atlas doubles until
    its texel is within DENSITY_SLACK of that (so the large surfaces a camera sees keep their
    texels), and an atlas of one quad stays at the asked resolution."""
    from jprt.render.scenes import SceneHandle, xml

    quads = "".join(f'<shape type="rectangle" id="q{k}"><transform name="to_world"><scale value="0.05"/>'
                    f'<translate x="{0.3 * (k % 8) - 1}" y="{0.3 * (k // 8) - 1}" z="1"/></transform></shape>'
                    for k in range(40))
    path = tmp_path / "mixed.xml"
    path.write_text('<scene version="3.0.0"><shape type="rectangle" id="floor"><transform name="to_world">'
                    f'<scale value="2"/></transform></shape>{quads}</scene>')
    handle = SceneHandle(xml(str(path)))
    total = 16.0 + 40 * 0.01
    atlas = lightmap.build_atlas(handle, resolution=16)
    assert atlas.resolution > 16
    assert atlas.texel_size <= lightmap.DENSITY_SLACK * np.sqrt(total) / 16
    single = SceneHandle(xml(_many_quads_file(tmp_path, 1)))
    assert lightmap.build_atlas(single, resolution=16).resolution == 16


def _wall_through_ceiling_file(tmp_path) -> str:
    """A 2 x 2 room's floor (y = 0) and ceiling (y = 1), and a back wall that runs on up to y = 2
    (walls modelled taller than the room are common in scene files)."""
    return _two_sided_quads_file(tmp_path, "room", {
        "floor": [(-1, 0, -1), (1, 0, -1), (1, 0, 1), (-1, 0, 1)],
        "ceiling": [(-1, 1, -1), (-1, 1, 1), (1, 1, 1), (1, 1, -1)],
        "wall": [(-1, 0, -1), (-1, 2, -1), (1, 2, -1), (1, 0, -1)]})


def _two_sided_quads_file(tmp_path, stem: str, quads: dict) -> str:
    """A scene file of quads ({id: four corners}), each its own OBJ with a two-sided diffuse BSDF."""
    body = ""
    for name, corners in quads.items():
        (tmp_path / f"{name}.obj").write_text("".join("v {} {} {}\n".format(*c) for c in corners) + "f 1 2 3\nf 1 3 4\n")
        body += (f'<shape type="obj" id="{name}"><string name="filename" value="{name}.obj"/>'
                 '<bsdf type="twosided"><bsdf type="diffuse"/></bsdf></shape>')
    path = tmp_path / f"{stem}.xml"
    path.write_text(f'<scene version="3.0.0">{body}</scene>')
    return str(path)


def test_texels_no_view_sees_are_never_shown(mi, tmp_path):
    """The back wall's texels above the ceiling are seen from none of the room's view points: they
    are baked, but no atlas pixel shows them (their pixels show the nearest wall texel below the
    ceiling), so a bilinear lookup at the top of the wall never blends in light from above the
    ceiling. Without ``seen_from`` every texel shows itself."""
    from jprt.render.scenes import SceneHandle, xml

    handle = SceneHandle(xml(_wall_through_ceiling_file(tmp_path)))
    wall = handle.object_names().index("wall")
    inside = np.array([[0.0, 0.5, 0.0], [0.5, 0.8, 0.5]])
    atlas = lightmap.build_atlas(handle, resolution=32, seen_from=inside)
    on_wall = np.asarray(atlas.texel_object) == wall
    sees = lightmap.sees_points(handle, atlas.position, atlas.normal, inside)
    y = np.asarray(atlas.position)[:, 1]
    assert np.all(sees[on_wall & (y < 0.95)]) and not np.any(sees[on_wall & (y > 1.05)])
    shown = np.asarray(atlas.fill_index)
    objects = np.asarray(atlas.texel_object)
    assert np.all(sees[shown[objects[shown] == wall]])  # no pixel shows a wall texel above the ceiling
    assert np.all(objects[shown[atlas.texel_index]] == objects)  # a texel's pixel shows its own object
    plain = lightmap.build_atlas(handle, resolution=32, seen_from=None)
    np.testing.assert_array_equal(np.asarray(plain.fill_index)[plain.texel_index], np.arange(plain.count))
    np.testing.assert_array_equal(plain.position, atlas.position)


def _landing_file(tmp_path) -> str:
    """A 2 x 2 floor (y = 0), a two-sided landing (y = 1) authored facing up, and a loft ceiling
    (y = 1.2) just above the landing: the landing's upper side sees the loft, its underside the
    floor, so the rays of ``_orient``'s escape test find geometry on both sides."""
    return _two_sided_quads_file(tmp_path, "landing", {
        "floor": [(-1, 0, -1), (-1, 0, 1), (1, 0, 1), (1, 0, -1)],
        "landing": [(-1, 1, -1), (-1, 1, 1), (1, 1, 1), (1, 1, -1)],
        "loft": [(-1.5, 1.2, -1.5), (1.5, 1.2, -1.5), (1.5, 1.2, 1.5), (-1.5, 1.2, 1.5)]})


def test_a_two_sided_surface_seen_from_one_side_only_faces_the_views(mi, tmp_path):
    """The landing is authored facing up, and both its sides see other geometry, so without view
    points its texels keep the authored side (which no view sees). Views from under it turn every
    landing texel to face down; views from between landing and loft keep them facing up."""
    from jprt.render.scenes import SceneHandle, xml

    handle = SceneHandle(xml(_landing_file(tmp_path)))
    landing = handle.object_names().index("landing")

    def landing_normals(seen_from):
        atlas = lightmap.build_atlas(handle, resolution=32, seen_from=seen_from)
        return np.asarray(atlas.normal)[np.asarray(atlas.texel_object) == landing]

    assert np.all(landing_normals(None)[:, 1] > 0.99)
    below = np.array([[0.0, 0.5, 0.0], [0.3, 0.4, -0.2]])
    assert np.all(landing_normals(below)[:, 1] < -0.99)
    between = np.array([[0.0, 1.1, 0.0], [0.4, 1.1, 0.3]])
    assert np.all(landing_normals(between)[:, 1] > 0.99)
