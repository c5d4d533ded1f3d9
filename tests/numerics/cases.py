"""Inputs for the harness where a function's arguments are not plain arrays (NamedTuples,
parameter pytrees) or where its raw output holds an arbitrary part (a frame that is undefined
where the lobe is isotropic): ``case(draw, spec) -> Problem``. Each case draws from the domain
its function's docstring states."""

from __future__ import annotations

from .harness import Problem, Spec, _parse_arg, draw_args


def _draw(draw, **domains) -> dict:
    """Arrays drawn by the harness's own rules from ``name="domain"`` pairs (in order)."""
    spec = Spec("case", None, args=[_parse_arg("case", k, v) for k, v in domains.items()])
    return draw_args(draw, spec)


# jprt.sphere.sg ----------------------------------------------------------------------------

def sg_product(draw, spec):
    import jax.numpy as jnp
    import numpy as np

    from jprt.sphere import sg

    args = _draw(draw, axis1="(32, 3) unit", sharpness1="(32,) in [0, 1e4]", amplitude1="(32,) in [0, 1e5]",
                 axis2="(32, 3) unit near axis1", sharpness2="(32,) in [0, 1e4]", amplitude2="(32,) in [0, 1e5]")
    um = args["sharpness1"][:, None] * args["axis1"] + args["sharpness2"][:, None] * args["axis2"]
    keep = np.linalg.norm(um, axis=-1) >= 1e-2 * (args["sharpness1"] + args["sharpness2"]) + 1e-30

    def fn(**lobes):
        out = sg.product(**lobes)
        return out.sharpness, out.amplitude, jnp.where(keep[:, None], out.axis, 0.0)

    return Problem(fn, args, list(args))


def _asg(draw):
    args = _draw(draw, z="(32, 3) unit", sharpness_x="(32,) in [0, 1e4]", sharpness_y="(32,) in [0, 1e4]",
                 amplitude="(32,) in [0, 1e5]", v="(32, 3) unit near z")
    return args


def asg(draw, spec):
    from jprt.sphere import sg

    def fn(v, z, sharpness_x, sharpness_y, amplitude):
        x, y = sg.orthonormal_basis(z)
        return sg.asg_evaluate(v, sg.ASG(x, y, z, sharpness_x, sharpness_y, amplitude))

    return Problem(fn, _asg(draw), ["v", "sharpness_x", "sharpness_y", "amplitude"])


def warp_asg(draw, spec):
    from jprt.sphere import sg

    args = _draw(draw, normal="(32, 3) unit", view="(32, 3) unit within 89.9 of normal",
                 roughness="(32,) in [1e-2, 1]", v="(32, 3) unit")

    def fn(normal, view, roughness, v):
        lobe = sg.warp_ndf_to_asg(normal, view, roughness)
        return sg.asg_evaluate(lobe.z, lobe), sg.asg_evaluate(v, lobe), lobe.sharpness_x, lobe.sharpness_y

    return Problem(fn, args, ["view", "roughness"])


def convolve(draw, spec):
    from jprt.sphere import sg

    args = {**_asg(draw), **_draw(draw, sharpness="(32,) in [0, 1e4]", light_amplitude="(32,) in [0, 1e5]")}

    def fn(v, z, sharpness_x, sharpness_y, amplitude, sharpness, light_amplitude):
        x, y = sg.orthonormal_basis(z)
        return sg.convolve_sg_asg(v, sharpness, light_amplitude, sg.ASG(x, y, z, sharpness_x, sharpness_y, amplitude))

    return Problem(fn, args, ["v", "sharpness_x", "sharpness_y", "amplitude", "sharpness", "light_amplitude"])


# jprt.nn ------------------------------------------------------------------------------------

def _f32_exact(tree):
    """A float32 pytree as float64 NumPy (the values both precisions then start from)."""
    import jax
    import numpy as np

    return jax.tree_util.tree_map(lambda x: np.asarray(x, np.float32).astype(np.float64), tree)


def _key(draw):
    import jax
    from hypothesis import strategies as st

    return jax.random.PRNGKey(draw(st.integers(0, 2**16)))


def mlp(draw, spec):
    from jprt.nn.mlp import mlp as make

    net = make((8, 16, 16, 3), activation="tanh", init="rrf")
    params = _f32_exact(net.init(_key(draw)))
    args = {"layers": params["layers"], "scaling": params["scaling"], **_draw(draw, x="(32, 8) in [-1, 1]")}
    # the scaling is fixed (stop_gradient): the layers and the inputs are differentiated
    return Problem(lambda layers, scaling, x: net.apply({"layers": layers, "scaling": scaling}, x), args,
                   ["layers", "x"])


def hashgrid(draw, spec):
    from jprt.nn.hashgrid import hashgrid as make

    grid = make(n_levels=4, n_features=2, log2_table_size=8, base_resolution=4, per_level_scale=2.0)
    args = {"params": _f32_exact(grid.init(_key(draw))), **_draw(draw, x="(32, 3) in [0, 1]")}
    return Problem(lambda params, x: grid.apply(params, x), args, ["params", "x"])


def factor_field(draw, spec):
    import numpy as np

    from jprt.nn.factor import factor_field as make

    field = make(face_size=4, n_features=8, n_levels=4, features_per_level=2, log2_table_size=8,
                 base_resolution=4, per_level_scale=2.0)
    args = {"params": _f32_exact(field.init(_key(draw))), **_draw(draw, x="(16, 3) in [0, 1]"),
            "k": np.arange(6 * 4 * 4, dtype=np.int32)}
    return Problem(lambda params, x, k: field.apply(params, x, k), args, ["params"])


def sg_encoder(draw, spec):
    from jprt.nn.cnn import sg_encoder as make

    net = make(image_size=16, in_channels=3, n_lobes=4, params_per_lobe=7, channels=(4, 8))
    args = {"params": _f32_exact(net.init(_key(draw))), **_draw(draw, images="(2, 16, 16, 3) in [0, 12]")}
    return Problem(lambda params, images: net.apply(params, images), args, ["params", "images"])


# jprt.methods.sg_lightfield.model -----------------------------------------------------------

def _lobes(draw, lead=(2,)):
    """4 lobes per texel for ``lead`` texels and 16 directions, some aligned with the lobes."""
    import numpy as np

    n = int(np.prod(lead))
    a = _draw(draw, axes=f"({n * 4}, 3) unit", directions=f"({n * 4}, 3) unit near axes",
              sharpness=f"({n * 4},) in [0, 1e4]", amplitude=f"({n * 4}, 3) in [0, 1e5]")
    dirs = np.concatenate([a["directions"].reshape(n, 4, 3), _draw(draw, d=f"({n * 12}, 3) unit")["d"].reshape(n, 12, 3)], 1)
    return {"axes": a["axes"].reshape(lead + (4, 3)), "sharpness": a["sharpness"].reshape(lead + (4,)),
            "amplitude": a["amplitude"].reshape(lead + (4, 3)), "directions": dirs.reshape(lead + (16, 3))}


def lobe_radiance(draw, spec):
    from jprt.methods.sg_lightfield import model as m

    args = _lobes(draw)
    return Problem(lambda axes, sharpness, amplitude, directions: m.lobe_radiance(
        m.Lobes(axes, sharpness, amplitude), directions), args, list(args))


def log_l2_loss(draw, spec):
    from jprt.methods.sg_lightfield import model as m

    args = {**_lobes(draw), **_draw(draw, targets="(2, 16, 3) in [0, 1e5]", weights="(2, 16) in [0, 1]")}
    return Problem(lambda axes, sharpness, amplitude, directions, targets, weights: m.log_l2_loss(
        m.Lobes(axes, sharpness, amplitude), directions, targets, weights), args,
        ["axes", "sharpness", "amplitude", "targets"])


def _lobe_shading(draw, name: str, **options):
    """Eight pixels of 4 lobes each shaded by ``model.<name>`` (``shade``, ``shade_sampled``) with
    ``options``."""
    from jprt.methods.sg_lightfield import model as m

    lobes = _lobes(draw, (8,))
    lobes.pop("directions")
    args = {**lobes, **_draw(draw, normal="(8, 3) unit", view="(8, 3) unit within 89.9 of normal",
                              roughness="(8,) in [1e-3, 1]", specular="(8, 3) in [0, 1]",
                              diffuse_albedo="(8, 3) in [0, 1]", irradiance="(8, 3) in [0, 1e5]")}

    def fn(axes, sharpness, amplitude, **pixel):
        return getattr(m, name)(m.Lobes(axes, sharpness, amplitude), **pixel, **options)

    return Problem(fn, args, ["sharpness", "amplitude", "view", "roughness", "specular", "irradiance"])


def shade(draw, spec):
    return _lobe_shading(draw, "shade")


def shade_sampled(draw, spec):
    # one direction a lobe: the lobe-drawn and BRDF-drawn integrals' code as at the default 3 x 3,
    # its loops unrolled once instead of nine times (the case's compile time 4 s, 11 s at 2 x 2).
    # That direction has phi = pi: its bitangent terms carry weight ~1e-16 here (at 2 x 2 the
    # tangent terms did); the evaluator's test compares frames with shade_sampled at 2 x 2
    return _lobe_shading(draw, "shade_sampled", samples=1)


def shade_quadrature(draw, spec):
    from jprt.methods.sg_lightfield import model as m

    args = _draw(draw, maps="(2, 4, 4, 3) in [0, 1e5]", normal="(2, 3) unit", view="(2, 3) unit within 89.9 of normal",
                 roughness="(2,) in [1e-2, 1]", specular="(2, 3) in [0, 1]")
    return Problem(lambda **a: m.shade_quadrature(**a, sub=2), args, ["maps", "roughness", "specular"])


# jprt.methods.datadriven.model --------------------------------------------------------------

def coarse_direct(draw, spec):
    import numpy as np

    from jprt.methods.datadriven import model as m

    group = np.repeat(np.arange(4, dtype=np.int32), 4)
    args = {**_draw(draw, direct="(16, 3) in [0, 1e5]"), "group": group, "counts": np.full(4, 4, np.int32)}
    return Problem(m.coarse_direct, args, ["direct"])


def _dd_fit(draw, gamma: float):
    """A data-driven PRT fit to random configurations (float32 params, as ``fit_arrays`` stores)."""
    import warnings

    import numpy as np
    from hypothesis import strategies as st

    from jprt.methods.datadriven import model as m

    rng = np.random.default_rng(draw(st.integers(0, 2**16)))
    direct = rng.uniform(0, 1, (24, 16, 3)) * rng.uniform(0, 1, (24, 1, 1))
    indirect = np.einsum("nsc,st->ntc", direct, rng.uniform(0, 0.2, (16, 12)))
    group = np.repeat(np.arange(8), 2)
    config = {"basis": {"n": 4, "gamma": gamma}}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", m.IllConditionedWarning)
        params = m.fit_arrays(direct, indirect, group, config).params
    return params, config


def dd_reconstruct(draw, spec):
    from jprt.methods.datadriven import model as m

    params, _ = _dd_fit(draw, 0.0)
    args = {"mean": params["mean"].astype("float64"), "basis": params["basis"].astype("float64"),
            **_draw(draw, coeffs="(4, 3) in [-1e5, 1e5]", norms="(3,) in [0, 1e5]")}
    return Problem(lambda **a: m.reconstruct(**a, channels="mono"), args, list(args))


def dd_lightmap(draw, spec):
    from jprt.methods.datadriven import model as m

    gamma = draw(__import__("hypothesis").strategies.sampled_from([0.0, 2.2]))
    params, config = _dd_fit(draw, gamma)
    arrays = {k: params[k].astype("float64") for k in ("mean", "basis", "transfer")}
    ints = {k: params[k] for k in ("group", "counts")}
    args = {"arrays": arrays, **_draw(draw, direct="(2, 16, 3) in [0, 1e5]")}
    return Problem(lambda arrays, direct: m.lightmap({**arrays, **ints}, direct, config), args, ["arrays", "direct"])


def dd_transfer(draw, spec):
    from jprt.methods.datadriven import model as m

    params, config = _dd_fit(draw, 0.0)
    args = {"transfer": params["transfer"].astype("float64"), **_draw(draw, x="(8, 3) in [0, 1e5]")}
    return Problem(lambda transfer, x: m.transfer_coefficients({"transfer": transfer}, x, config), args,
                   ["transfer", "x"])


# jprt.methods.mrt.model ---------------------------------------------------------------------

def _mrt(draw):
    """Random reduced operators of 2 blocks (8 texels, k_b = 3, k_r = 2, one interface record)
    and inputs: (operators to differentiate, fixed integer/boolean arrays, inputs)."""
    import numpy as np
    from hypothesis import strategies as st

    rng = np.random.default_rng(draw(st.integers(0, 2**16)))
    f32 = lambda a: a.astype(np.float32).astype(np.float64)  # noqa: E731
    ops = {"T_db": f32(rng.normal(0, 0.2, (2, 3, 8))), "U_b": f32(rng.normal(0, 0.2, (2, 8, 3))),
           "U_r_turned": f32(rng.normal(0, 0.2, (4, 8, 2))), "rec_T": f32(rng.normal(0, 0.3, (1, 2, 3)))}
    mask = np.ones((2, 8), bool)
    mask[1, 6:] = False  # a missing face
    fixed = {"mask": mask, "rec_src": np.array([0], np.int32), "rec_dst": np.array([1], np.int32),
             "rec_side": np.array([2], np.int32)}
    inputs = _draw(draw, direct="(2, 8, 3) in [0, 1e5]", albedo="(2, 8, 3) in [0, 1]")
    return ops, fixed, inputs


def _mrt_problem(draw, fn):
    ops, fixed, inputs = _mrt(draw)
    args = {"ops": ops, **inputs}
    return Problem(lambda ops, direct, albedo: fn({**ops, **fixed}, direct, albedo), args, ["ops", "direct", "albedo"])


def mrt_texels(draw, spec):
    from jprt.methods.mrt import model as m

    return _mrt_problem(draw, lambda p, d, a: m.lightmap_parts_texels(p, d, a, feedback=2))


def mrt_feedback(draw, spec):
    from jprt.methods.mrt import model as m

    return _mrt_problem(draw, lambda p, d, a: m.feedback_operators(p, a))


def mrt_coefficients(draw, spec):
    from jprt.methods.mrt import model as m

    return _mrt_problem(draw, lambda p, d, a: m.coefficients(p, d, a, feedback=2))


def mrt_parts(draw, spec):
    from jprt.methods.mrt import model as m

    return _mrt_problem(draw, lambda p, d, a: m.lightmap_parts(p, d, a, feedback=2))


def mrt_lightmap(draw, spec):
    from jprt.methods.mrt import model as m

    return _mrt_problem(draw, lambda p, d, a: m.lightmap(p, d, a, feedback=2))


def mrt_vector_irradiance(draw, spec):
    import numpy as np
    from hypothesis import strategies as st

    from jprt.methods.mrt import model as m

    rng = np.random.default_rng(draw(st.integers(0, 2**16)))
    ops = {"U_b": rng.normal(0, 0.2, (2, 8, 3)).astype(np.float32).astype(np.float64),
           "U_quad": rng.normal(0, 0.2, (2, 8, 9, 3)).astype(np.float32).astype(np.float64)}
    args = {"ops": ops, **_draw(draw, b="(2, 3, 3) in [-1e5, 1e5]", normals="(16, 3) unit")}

    def fn(ops, b, normals):
        n = normals.reshape(2, 8, 3)
        return [m.vector_irradiance(ops, b, n, kind) for kind in ("scalar", "quadratic", "ohlsh")]

    return Problem(fn, args, ["ops", "b", "normals"])


def mrt_volume_probes(draw, spec):
    import numpy as np
    from hypothesis import strategies as st

    from jprt.methods.mrt import model as m

    rng = np.random.default_rng(draw(st.integers(0, 2**16)))
    ops = {"U_vol": rng.normal(0, 0.2, (2, 4, 9, 3)).astype(np.float32).astype(np.float64),
           "U_rvol": rng.normal(0, 0.2, (4, 4, 9, 2)).astype(np.float32).astype(np.float64)}
    args = {"ops": ops, **_draw(draw, b="(2, 3, 3) in [-1e5, 1e5]", r="(2, 4, 2, 3) in [-1e5, 1e5]")}
    return Problem(lambda ops, b, r: m.volume_probes(ops, b, r), args, ["ops", "b", "r"])


# jprt.methods.rrf.model ---------------------------------------------------------------------

def rrf_features(draw, spec):
    from jprt.methods.rrf import model as m

    args = _draw(draw, position="(8, 3) in [-1e3, 1e3]", view="(8, 3) unit", light="(8, 3) in [-1e3, 1e3]",
                 normal="(8, 3) unit", brdf="(8, 7) in [0, 1]")
    return Problem(lambda **a: [m.features(name, **a) for name in sorted(m.ATTRIBUTE_SETS)], args, list(args))


# jprt.methods.wavelet_prt.model -------------------------------------------------------------

def _pixels(draw, n: int):
    return _draw(draw, position=f"({n}, 3) in [0, 1]", normal=f"({n}, 3) unit", reflected=f"({n}, 3) unit",
                 diffuse_albedo=f"({n}, 3) in [0, 1]", specular_albedo=f"({n}, 3) in [0, 1]",
                 roughness=f"({n},) in [0, 1]")


def wavelet_pixel_features(draw, spec):
    from jprt.methods.wavelet_prt import model as m

    args = {"g": _pixels(draw, 16)}
    return Problem(lambda g: m.pixel_features(g), args, ["g"])


def wavelet_model(draw, spec):
    import numpy as np

    from jprt.methods.wavelet_prt import model as m

    config = {"envmaps": {"face_size": 4}, "model": {"n_features": 8, "n_levels": 4, "features_per_level": 2,
                                                     "log2_table_size": 8, "base_resolution": 4,
                                                     "per_level_scale": 2.0, "hidden": 16, "layers": 2}}
    net = m.model(config)
    params = _f32_exact(net.init(_key(draw), np.array([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]], np.float32)))
    g = _pixels(draw, 8)
    g["valid"] = np.ones(8, np.float64)
    args = {"params": params, "g": g, "k": np.arange(6 * 16, dtype=np.int32)}
    return Problem(lambda params, g, k: net.transport(params, g, k), args, ["params"])


def wavelet_render(draw, spec):
    import numpy as np

    from jprt.methods.wavelet_prt import model as m

    args = {**_draw(draw, transport="(8, 6, 2, 2, 3) in [-1e3, 1e3]", light="(6, 2, 2, 3) in [-1e5, 1e5]"),
            "pixel": np.arange(8, dtype=np.int32)}

    def fn(transport, light, pixel):
        return m.render_pixels(m.exact_transport_fn(transport), {"pixel": pixel}, light, 8, chunk=3)

    return Problem(fn, args, ["transport", "light"])


# jprt.design ---------------------------------------------------------------------------------

def design_lights(draw, spec):
    from jprt import design

    args = _draw(draw, u="(4, 3) in [-20, 20]", log_intensity="(4, 3) in [-20, 20]")

    def fn(u, log_intensity):
        return design.from_params(design.LightParams(u, log_intensity), [-1.0, 0.5, -2.0], [2.0, 3.0, 1.0])

    return Problem(fn, args, ["u", "log_intensity"])


def design_direct(draw, spec):
    import jax.numpy as jnp
    import numpy as np

    from jprt import design
    from jprt.inputs import GBuffer

    args = _draw(draw, points="(8, 3) in [-1, 1]", normal="(8, 3) unit", view="(8, 3) unit within 89.9 of normal",
                 diffuse="(8, 3) in [0, 1]", specular="(8, 3) in [0, 1]", roughness="(8,) in [0.1, 1]",
                 position="(2, 3) in [2, 3]", intensity="(2, 3) in [0, 1e3]")
    vis = np.asarray(draw(_bits((8, 2))), np.float32)

    def fn(points, normal, view, diffuse, specular, roughness, position, intensity):
        zeros = jnp.zeros(points.shape[:-1] + (2,), points.dtype)
        gb = GBuffer(points, normal, view, view, zeros, diffuse, specular, roughness,
                     jnp.zeros(points.shape[:-1], jnp.int32), jnp.ones(points.shape[:-1], bool))
        return design.point_direct(gb, position, intensity, vis)

    return Problem(fn, args, ["position", "intensity", "diffuse", "specular", "roughness"])


def _bits(shape):
    from hypothesis import strategies as st
    import numpy as np

    n = int(np.prod(shape))
    return st.lists(st.integers(0, 1), min_size=n, max_size=n).map(lambda v: np.asarray(v).reshape(shape))


def design_objective(draw, spec):
    import numpy as np

    from jprt import design

    args = _draw(draw, target="(8, 8, 3) in [0, 1e3]", full="(8, 8, 3) in [0, 1e3]", indirect="(8, 8, 3) in [0, 1e3]",
                 irradiance="(8, 8, 3) in [0, 1e3]", intensity="(2, 3) in [0, 1e3]", bounds="(4,) in [1e-2, 1e3]")
    target = np.asarray(args.pop("target"), np.float64)
    b = np.sort(np.asarray(args.pop("bounds"), np.float64))
    mask = np.zeros((8, 8), bool)
    mask[2:6] = True
    obj = design.Objective(design.ImageTarget(target.astype(np.float32) + 1.0, mask, "full", 1.0),
                           (design.ObjectTarget("a", "irradiance", float(b[0]), float(b[1]), 1.0),
                            design.ObjectTarget("b", "radiance", None, float(b[3]), 2.0)), 0.5, "case")
    masks = np.stack([mask, ~mask]).astype(np.float32)

    def fn(full, indirect, irradiance, intensity):
        terms = design.objective_terms(obj, masks, full, indirect, irradiance, intensity, 10.0)
        return tuple(terms[k] for k in sorted(terms))

    return Problem(fn, args, ["full", "irradiance", "intensity"])


# jprt.sphere.cubemap (bilinear sampling, rotation) ------------------------------------------------

def cube_bilinear(draw, spec):
    import numpy as np

    from jprt.sphere import cubemap

    args = _draw(draw, cubemap="(6, 4, 4, 3) in [0, 1e5]", d="(32, 3) unit")
    d = np.asarray(args["d"], np.float64)
    a = np.sort(np.abs(d), axis=-1)
    keep = (a[:, 2] - a[:, 1]) > np.sin(np.radians(2.0))  # off the diagonals, where the face switches
    args["d"] = np.where(keep[:, None], d, np.array([0.3, 0.2, 0.93]) / np.linalg.norm([0.3, 0.2, 0.93]))
    return Problem(cubemap.sample_cubemap_bilinear, args, ["cubemap", "d"])


def cube_rotate(draw, spec):
    from jprt.sphere import cubemap

    args = _draw(draw, cubemap="(6, 4, 4, 3) in [0, 1e5]", angle="() in [0.1, 1.4]")
    return Problem(cubemap.rotate_cubemap_y, args, ["cubemap", "angle"])
