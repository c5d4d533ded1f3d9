"""Hash grid: tiny-cuda-nn parameter counts, constant tables, dense/hash indexing, gradients."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

from jprt.nn.hashgrid import PRIMES, hashgrid, level_resolutions, level_table_sizes


def tcnn_level_params(n_levels, n_features, log2_t, n_min, b):
    """The formula of tiny-cuda-nn encodings/grid.h, written out independently. It is evaluated in
    float32 as there (exp2f, float log2_per_level_scale): in float64, level 3 of b = 1.5 gives
    scale 53.000000000000014 and resolution 55 instead of 54."""
    out = []
    log2b = np.float32(math.log2(b))
    for level in range(n_levels):
        scale = np.exp2(np.float32(level) * log2b) * np.float32(n_min) - np.float32(1.0)
        assert scale.dtype == np.float32
        res = math.ceil(float(scale)) + 1
        entries = res**3
        entries = (entries + 7) // 8 * 8
        out.append(min(entries, 2**log2_t) * n_features)
    return out


@pytest.mark.parametrize("config", [(16, 2, 19, 16, 1.5), (32, 2, 19, 16, 1.3)])
def test_per_level_parameter_counts(config):
    n_levels, n_features, log2_t, n_min, b = config
    grid = hashgrid(n_levels=n_levels, n_features=n_features, log2_table_size=log2_t, base_resolution=n_min,
                    per_level_scale=b)
    ours = [size * n_features for size in grid.table_sizes]
    assert ours == tcnn_level_params(*config)
    params = jax.eval_shape(grid.init, jax.random.PRNGKey(0))  # no 12M-float allocation needed
    assert [t.shape[0] * t.shape[1] for t in params["tables"]] == ours
    assert ours[0] == 16**3 * 2  # level 0: scale 15 -> resolution 16, dense


def test_resolutions_follow_the_spec():
    assert level_resolutions(3, 16, 2.0) == [16, 32, 64]  # scale 15, 31, 63 -> ceil + 1
    assert level_table_sizes(3, 14, 16, 2.0) == [4096, 2**14, 2**14]


def test_constant_table_interpolates_to_the_constant():
    grid = hashgrid(n_levels=6, n_features=3, log2_table_size=10, base_resolution=4, per_level_scale=1.7)
    params = {"tables": [jnp.full_like(t, 0.37) for t in grid.init(jax.random.PRNGKey(0))["tables"]]}
    x = jax.random.uniform(jax.random.PRNGKey(1), (100, 3))
    np.testing.assert_allclose(grid.apply(params, x), 0.37, rtol=1e-6)


def _numpy_level(table, x, scale, res, size):
    """Reference lookup of one level in NumPy (uint32 hash as in tiny-cuda-nn)."""
    pos = x.astype(np.float32) * np.float32(scale) + np.float32(0.5)
    base = np.floor(pos).astype(np.uint32)
    frac = pos - np.floor(pos)
    out = np.zeros((x.shape[0], table.shape[1]), np.float64)
    for c in range(8):
        corner = np.array([(c >> d) & 1 for d in range(3)], np.uint32)
        g = base + corner
        if res**3 <= size:
            idx = g[:, 0] + g[:, 1] * res + g[:, 2] * res * res
        else:
            idx = (g[:, 0] * np.uint32(PRIMES[0])) ^ (g[:, 1] * np.uint32(PRIMES[1])) ^ (g[:, 2] * np.uint32(PRIMES[2]))
        w = np.prod(np.where(corner == 1, frac, 1 - frac), axis=1)
        out += w[:, None] * table[idx % np.uint32(size)]
    return out


def test_matches_numpy_reference_dense_and_hashed():
    grid = hashgrid(n_levels=3, n_features=2, log2_table_size=9, base_resolution=6, per_level_scale=2.0)
    params = grid.init(jax.random.PRNGKey(2))
    params = {"tables": [jax.random.normal(jax.random.PRNGKey(i), t.shape) for i, t in enumerate(params["tables"])]}
    x = np.random.default_rng(0).random((50, 3)).astype(np.float32)
    ours = np.asarray(grid.apply(params, jnp.asarray(x)))
    res = level_resolutions(3, 6, 2.0)  # [6, 12, 24]: 216 dense, 1728 and 13824 hashed into 512
    for level, (table, r, size) in enumerate(zip(params["tables"], res, grid.table_sizes)):
        scale = 2.0 ** (level * 1.0) * 6 - 1
        ref = _numpy_level(np.asarray(table), x, scale, r, size)
        np.testing.assert_allclose(ours[:, 2 * level:2 * level + 2], ref, rtol=1e-5, atol=1e-6)


def test_check_grads():
    grid = hashgrid(n_levels=2, n_features=2, log2_table_size=6, base_resolution=3, per_level_scale=2.0)
    params = grid.init(jax.random.PRNGKey(0))
    x = jax.random.uniform(jax.random.PRNGKey(1), (4, 3), minval=0.05, maxval=0.95)
    with jax.enable_x64(True):
        p64 = jax.tree_util.tree_map(lambda t: jnp.asarray(t, jnp.float64) * 1e3, params)
        # jitted: each derivative is one program (eagerly, every primitive compiles apart)
        check_grads(jax.jit(lambda p: grid.apply(p, jnp.asarray(x, jnp.float64))), (p64,), order=2, modes=["rev"])
        check_grads(jax.jit(lambda y: grid.apply(p64, y)), (jnp.asarray(x, jnp.float64),), order=1, modes=["rev"])
