"""jprt.sphere functions run under jax.jit and jax.vmap; differentiable ones pass check_grads.

Not listed: functions of static sizes only (texel_directions, solid angles, support areas, ...),
which are constants under jit, and the mixture fitters (fit_gd, fit_em, peak_axes), which run
NumPy initialisation and jit their own inner loops.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

from jprt.sphere import cubemap, haar, octahedral, sg, sh

D = jnp.array([[0.36, 0.48, 0.8], [0.0, -0.6, 0.8], [-0.8, 0.0, -0.6]], jnp.float32)
CUBE = jnp.asarray(np.random.default_rng(0).random((4, 6, 4, 4, 2)), jnp.float32)  # batch of cube maps
ASG_ARGS = (jnp.array([[0.0, 0.0, 1.0]] * 3), D, jnp.array([0.3, 0.5, 0.8]))

# name -> (function of batched arrays, batched args, differentiable argnums)
REGISTRY = {
    "cubemap.direction_to_face_uv": (lambda d: cubemap.direction_to_face_uv(d)[1:], (D,), (0,)),
    "cubemap.face_uv_to_direction": (lambda u, f: cubemap.face_uv_to_direction(f, u, 1 - u),
                                     (jnp.array([0.2, 0.5, 0.9]), jnp.array([0, 2, 5])), (0,)),
    "cubemap.direction_to_texel": (lambda d: cubemap.direction_to_texel(d, 4), (D,), ()),
    "cubemap.equirect_to_cubemap": (lambda e: cubemap.equirect_to_cubemap(e, 4), (jnp.ones((3, 8, 16, 1)),), ()),
    "cubemap.cubemap_to_equirect": (lambda c: cubemap.cubemap_to_equirect(c, 8, 16), (CUBE[:3],), ()),
    "haar.forward": (haar.forward, (CUBE,), (0,)),
    "haar.inverse": (haar.inverse, (CUBE,), (0,)),
    "haar.top_k": (lambda c: haar.top_k(c, 5)[1], (CUBE,), ()),
    "haar.unflatten_index": (lambda i: haar.unflatten_index(i, 4).level, (jnp.array([0, 17, 95]),), ()),
    "sh.evaluate": (lambda d: sh.evaluate(d, 4), (D,), (0,)),
    "sh.irradiance": (lambda c, n: sh.irradiance(c, n), (jnp.ones((3, 9)), D), (0, 1)),
    "sh.ohlsh": (sh.ohlsh, (jnp.arange(27.0).reshape(3, 9),), (0,)),
    "sg.evaluate": (lambda v, lam: sg.evaluate(v, jnp.array([0.0, 0.0, 1.0]), lam, 2.0), (D, jnp.array([1.0, 5.0, 50.0])),
                    (0, 1)),
    "sg.integral": (lambda lam: sg.integral(lam, 1.5), (jnp.array([1e-3, 1.0, 100.0]),), (0,)),
    "sg.inner_product": (lambda u, lam: sg.inner_product(u, lam, 1.0, jnp.array([0.0, 0.0, 1.0]), 3.0, 2.0),
                         (D, jnp.array([1.0, 5.0, 50.0])), (1,)),
    "sg.convolve_sg_asg": (lambda n, v, r: sg.convolve_sg_asg(n, 20.0, 1.0, sg.warp_ndf_to_asg(n, v, r)), ASG_ARGS, (2,)),
    "cubemap.sample_cubemap_nearest": (lambda d: cubemap.sample_cubemap_nearest(CUBE[0], d), (D,), ()),
    "haar.flat_index": (lambda f, i: haar.flat_index(f, 1, haar.BAND_D, i, 1, 4), (jnp.array([0, 3, 5]),
                                                                                   jnp.array([0, 1, 1])), ()),
    "sh.project_cubemap": (lambda c: sh.project_cubemap(c, 2), (CUBE[:3],), (0,)),
    "sh.reconstruct": (lambda c, d: sh.reconstruct(c, d), (jnp.ones((3, 16)), D), (0, 1)),
    "sg.product": (lambda u, lam: sg.product(u, lam, 1.0, jnp.array([0.0, 0.0, 1.0]), 2.0, 3.0).amplitude,
                   (D, jnp.array([1.0, 5.0, 50.0])), (1,)),
    "sg.mixture_evaluate": (lambda d, a: sg.mixture_evaluate(d, jnp.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]]),
                                                             jnp.array([3.0, 8.0]), a),
                            (D, jnp.ones((3, 2, 3))), (0, 1)),
    "sg.asg_evaluate": (lambda v, r: sg.asg_evaluate(v, sg.warp_ndf_to_asg(jnp.array([0.0, 0.0, 1.0]),
                                                                           jnp.array([0.6, 0.0, 0.8]), r)),
                        (D, jnp.array([0.2, 0.5, 0.9])), (0, 1)),
    "octahedral.encode": (octahedral.encode, (D,), (0,)),
    "octahedral.direction_to_texel": (lambda d: octahedral.direction_to_texel(d, 8), (D,), ()),
    "octahedral.decode": (octahedral.decode, (jnp.array([[0.1, 0.2], [0.5, -0.3], [-0.8, 0.7]]),), (0,)),
}


@pytest.mark.parametrize("name", sorted(REGISTRY))
def test_jit_and_vmap(name):
    fn, args, _ = REGISTRY[name]
    eager = [fn(*(a[i] for a in args)) for i in range(args[0].shape[0])]  # one example at a time
    mapped = jax.jit(jax.vmap(fn))(*args)
    for i, row in enumerate(eager):
        jax.tree_util.tree_map(lambda a, b: np.testing.assert_allclose(a, np.asarray(b)[i], rtol=1e-5, atol=1e-5),
                               row, mapped)


@pytest.mark.parametrize("name", sorted(n for n, (_, _, argnums) in REGISTRY.items() if argnums))
def test_check_grads(name):
    fn, args, argnums = REGISTRY[name]
    with jax.enable_x64(True):
        args64 = [jnp.asarray(np.asarray(a)[0], jnp.float64) if np.issubdtype(np.asarray(a).dtype, np.floating)
                  else jnp.asarray(np.asarray(a)[0]) for a in args]

        def partial_fn(*diff):
            full = list(args64)
            for k, value in zip(argnums, diff):
                full[k] = value
            return fn(*full)

        # jitted: each derivative is one program (eagerly, every primitive of the forward and
        # backward pass compiled on its own)
        check_grads(jax.jit(partial_fn), tuple(args64[k] for k in argnums), order=1, atol=1e-4, rtol=1e-4)
