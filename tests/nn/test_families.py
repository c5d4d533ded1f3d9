"""Generic contract tests for every registered family (optax's alias_test style)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jprt.nn import REGISTRY

NAMES = sorted(REGISTRY)


def _make(name):
    entry = REGISTRY[name]
    family = entry.family()
    params = family.init(jax.random.PRNGKey(0))
    inputs = entry.example_inputs(jax.random.PRNGKey(1))
    return family, params, inputs


@pytest.mark.parametrize("name", NAMES)
def test_jit_finite_and_shapes(name):
    family, params, inputs = _make(name)
    eager = family.apply(params, *inputs)
    jitted = jax.jit(family.apply)(params, *inputs)
    assert eager.shape == jitted.shape and eager.dtype == jnp.float32
    assert jnp.all(jnp.isfinite(jitted))
    np.testing.assert_allclose(eager, jitted, rtol=1e-5, atol=1e-6)
    # Batch dims are kept: the first input's leading axis is the output's leading axis.
    assert jitted.shape[0] == inputs[0].shape[0]
    # Parameter dtypes are kept by init.
    assert all(leaf.dtype == jnp.float32 for leaf in jax.tree_util.tree_leaves(params))


@pytest.mark.parametrize("name", NAMES)
def test_gradients_finite(name):
    family, params, inputs = _make(name)
    # jitted: one program (eagerly, every primitive of the forward and backward pass compiles apart)
    grads = jax.jit(jax.grad(lambda p: jnp.sum(jnp.square(family.apply(p, *inputs)))))(params)
    leaves = jax.tree_util.tree_leaves(grads)
    assert all(bool(jnp.all(jnp.isfinite(g))) for g in leaves)
    assert any(bool(jnp.any(g != 0)) for g in leaves)
    jax.tree_util.tree_map(lambda g, p: None if g.shape == p.shape and g.dtype == p.dtype else pytest.fail(name),
                           grads, params)


@pytest.mark.parametrize("name", NAMES)
def test_no_recompilation_on_second_call(name):
    family, params, inputs = _make(name)
    traces = []

    @jax.jit
    def apply(p, *xs):
        traces.append(1)  # runs only while tracing
        return family.apply(p, *xs)

    apply(params, *inputs).block_until_ready()
    other = jax.tree_util.tree_map(lambda a: a + 0.5 if jnp.issubdtype(a.dtype, jnp.floating) else a, inputs)
    apply(params, *other).block_until_ready()
    assert len(traces) == 1
