"""Every shape a scene file can hold (issue 45): disks, spheres and cylinders become meshes,
instanced shape groups become one mesh per (instance, member), and all of them work in
G-buffers, renders (an area-lit disk still lights the scene) and lightmap atlases."""

import numpy as np
import pytest

from jprt.render import images, lightmap, scenes
from jprt.render.cameras import camera_rays
from jprt.render.gbuffer import gbuffer
from jprt.render.scenes import SceneHandle

pytestmark = pytest.mark.mitsuba

SCENE = """<scene version="3.0.0">
  <bsdf type="diffuse" id="white"><rgb name="reflectance" value="0.7"/></bsdf>
  <shape type="rectangle" id="floor"><ref id="white"/>
    <transform name="to_world"><rotate x="1" angle="-90"/><scale value="3"/><translate y="-1"/></transform></shape>
  <shape type="disk" id="lamp"><bsdf type="diffuse"><rgb name="reflectance" value="0.2"/></bsdf>
    <transform name="to_world"><rotate x="1" angle="90"/><scale value="0.5"/><translate y="1.6" z="1"/></transform>
    <emitter type="area"><rgb name="radiance" value="8"/></emitter></shape>
  <shape type="sphere" id="ball"><point name="center" x="-1.2" y="-0.4" z="0.3"/><float name="radius" value="0.6"/>
    <bsdf type="diffuse"><rgb name="reflectance" value="0.3, 0.6, 0.3"/></bsdf></shape>
  <shape type="cylinder" id="can"><point name="p0" x="1.2" y="-1" z="0.3"/><point name="p1" x="1.2" y="0.2" z="0.3"/>
    <float name="radius" value="0.4"/><bsdf type="twosided"><ref id="white"/></bsdf></shape>
  <shape type="cube" id="box"><ref id="white"/>
    <transform name="to_world"><rotate y="1" angle="30"/><scale value="0.35"/><translate y="-0.65" z="0.6"/></transform>
  </shape>
  <shape type="shapegroup" id="pair">
    <shape type="sphere" id="bead"><float name="radius" value="0.25"/><ref id="white"/></shape>
    <shape type="cube" id="cap"><transform name="to_world"><scale value="0.12"/><translate y="0.35"/></transform>
      <ref id="white"/></shape>
  </shape>
  <shape type="instance" id="left"><ref id="pair"/>
    <transform name="to_world"><translate x="-0.6" y="0.6" z="-1"/></transform></shape>
  <shape type="instance"><ref id="pair"/>
    <transform name="to_world"><rotate z="1" angle="20"/><translate x="0.7" y="0.5" z="-1"/></transform></shape>
  <sensor type="perspective"><float name="fov" value="55"/>
    <transform name="to_world"><lookat origin="0, 0.3, 5" target="0, 0, 0" up="0, 1, 0"/></transform>
    <film type="hdrfilm"><integer name="width" value="40"/><integer name="height" value="40"/></film></sensor>
</scene>"""

#: Object names: file ids, "<instance id>/<member id>" (the unnamed 2nd instance is shape 6 of the
#: loaded file, counting from 0: shape_0006).
NAMES = ["floor", "lamp", "ball", "can", "box", "left/bead", "left/cap", "shape_0006/bead", "shape_0006/cap"]


@pytest.fixture(scope="module")
def shapes_scene(mi, tmp_path_factory):
    path = tmp_path_factory.mktemp("shapes") / "shapes.xml"
    path.write_text(SCENE)
    handle = SceneHandle(scenes.xml(str(path)))
    return str(path), handle, handle.default_camera()


def test_analytic_shapes_and_instances_become_named_meshes(shapes_scene, mi):
    _, handle, _ = shapes_scene
    assert handle.object_names() == NAMES
    assert handle.tessellated == {"lamp", "ball", "can", "left/bead", "shape_0006/bead"}
    assert not handle.has_media
    shapes = dict(zip(NAMES, handle.shapes()))
    assert all(isinstance(shapes[n], mi.Mesh) for n in NAMES)  # the floor is Mitsuba's rectangle (a Mesh too)
    area = {n: float(np.ravel(shapes[n].surface_area())[0]) for n in NAMES}
    # TESSELLATION_SAGITTA = 1e-3 of the radius: areas within 0.2 % of the true ones (facets lie inside)
    for name, exact in (("lamp", np.pi * 0.5 ** 2), ("ball", 4 * np.pi * 0.6 ** 2), ("can", 2 * np.pi * 0.4 * 1.2),
                        ("left/bead", 4 * np.pi * 0.25 ** 2), ("shape_0006/bead", 4 * np.pi * 0.25 ** 2)):
        assert 0.998 * exact < area[name] <= exact, (name, area[name], exact)
    np.testing.assert_allclose(area["left/cap"], 6 * 0.24 ** 2, rtol=1e-5)
    assert shapes["lamp"].emitter() is not None  # the area light moved onto the disk's mesh
    # the instances sit where their transforms put them (the group's sphere is centred at its origin)
    for name, centre in (("left/bead", [-0.6, 0.6, -1.0]), ("shape_0006/bead", [0.7, 0.5, -1.0])):
        box = shapes[name].bbox()
        np.testing.assert_allclose(0.5 * (np.array(box.min) + np.array(box.max)), centre, atol=1e-3)


def test_meshes_match_the_analytic_shapes_mitsuba_loads(shapes_scene, mi):
    """Pixel-centre hits of jprt's scene against the file as Mitsuba loads it (analytic shapes,
    instances): same surface points, shading normals and (away from seams) UVs."""
    path, handle, camera = shapes_scene
    raw = mi.load_file(path, optimize=False)
    o, d = (a.reshape(-1, 3) for a in camera_rays(camera))
    ray = mi.Ray3f(mi.Point3f(*o.T.astype(np.float32)), mi.Vector3f(*d.T.astype(np.float32)))
    ours, theirs = handle.scene.ray_intersect(ray), raw.ray_intersect(ray)
    both = np.array(ours.is_valid()) & np.array(theirs.is_valid())
    assert np.mean(np.array(ours.is_valid()) == np.array(theirs.is_valid())) > 0.99
    rows = lambda v: np.array(v, np.float64).T[both]  # noqa: E731
    dist = np.linalg.norm(rows(ours.p) - rows(theirs.p), axis=1)
    assert np.mean(dist < 1e-2) > 0.98  # silhouette pixels may hit the facet's other side
    cos = np.sum(rows(ours.sh_frame.n) * rows(theirs.sh_frame.n), axis=1)
    assert np.mean(cos > 0.999) > 0.97
    duv = np.abs(rows(ours.uv) - rows(theirs.uv))
    assert np.median(duv) < 1e-3 and np.mean(duv.max(axis=1) < 0.02) > 0.95


def test_every_object_is_seen_and_lit(shapes_scene, mi):
    path, handle, camera = shapes_scene
    gb = gbuffer(handle, camera)
    seen = set(np.unique(gb.object_id[gb.valid]).tolist())
    assert seen == set(range(len(NAMES))), [NAMES[k] for k in set(range(len(NAMES))) - seen]
    image = images.render(handle, camera, spp=16, seed=3)
    for k, name in enumerate(NAMES):
        assert image[gb.object_id == k].mean() > 0.01, name
    # the disk lamp lights the scene as it did before it became a mesh: Mitsuba's own render of the
    # file (analytic disk and spheres, instances) has the same mean within noise and facets
    raw = mi.load_file(path, optimize=False)
    sensor = mi.load_dict(images.to_sensor_dict(camera, 64, mi))
    path_tracer = mi.load_dict({"type": "path", "max_depth": -1, "hide_emitters": False})
    theirs = np.array(mi.render(raw, sensor=sensor, integrator=path_tracer, spp=64, seed=5), np.float32)
    ours = images.render(handle, camera, spp=64, seed=5)
    lit = gb.valid & (gb.object_id != 1)  # the lamp's own pixels are its radiance: exclude its edge pixels
    np.testing.assert_allclose(ours[lit].mean(), theirs[lit].mean(), rtol=0.01)  # measured: 0.12 %


def test_atlas_maps_every_object(shapes_scene):
    _, handle, camera = shapes_scene
    atlas = lightmap.build_atlas(handle, resolution=64)
    counts = np.bincount(atlas.texel_object, minlength=len(NAMES))
    assert (counts >= 4).all(), dict(zip(NAMES, counts))
    gb = lightmap.atlas_gbuffer(handle, atlas, camera)
    r = atlas.resolution
    for k, name in enumerate(NAMES):
        pix = gb.object_id == k
        assert pix.any() and gb.valid[pix].all(), name
        uv = gb.uv[pix]
        assert ((uv >= 0) & (uv <= 1)).all(), name
        ij = np.clip((uv * r).astype(int), 0, r - 1)
        texel = atlas.fill_index[ij[:, 1] * r + ij[:, 0]]
        # the texel under each pixel belongs to the pixel's object and lies near its surface point
        assert np.mean(atlas.texel_object[texel] == k) >= 0.9, name
        near = np.linalg.norm(atlas.position[texel] - gb.position[pix], axis=1) < 2.0 * atlas.texel_size
        assert near.mean() >= 0.9, name


def test_non_mesh_objects_are_refused_in_one_line(mi):
    """The built-in glossy Cornell box keeps its analytic sphere (G-buffers and renders take it);
    only what needs triangles refuses it, naming it."""
    handle = SceneHandle(scenes.glossy_cornell())
    sphere = handle.object_names().index("large-box")
    with pytest.raises(ValueError, match=r"'large-box' \(Mitsuba Sphere\) is not a triangle mesh") as e:
        lightmap.mesh_triangles(handle, sphere)
    assert "\n" not in str(e.value)
