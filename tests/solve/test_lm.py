"""Levenberg-Marquardt: fits, float64 finite differences, batching with masks, never NaN."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jprt.nn import count_parameters, mlp, with_scaling
from jprt.solve import lm


def smooth_target(x):
    return np.stack([np.sin(2 * x[:, 0]) * np.cos(x[:, 1]) + 0.3 * x[:, 2],
                     np.exp(-x[:, 0] ** 2 - x[:, 2] ** 2) - 0.5 * x[:, 1]], axis=1).astype(np.float32)


NET = mlp((3, 12, 8, 2), activation="tanh", init="rrf")
#: The float64 solves of the mask and batching tests (one compiled solver for problems of 128 samples).
BATCH_SETTINGS = lm.LMSettings(max_iters=15, chunk_size=64)


def residual(params, sample):
    return NET.apply(params, sample["x"]) - sample["y"]


def problem(n, seed=0):
    x = np.random.default_rng(seed).uniform(-1, 1, (n, 3)).astype(np.float32)
    y = smooth_target(x)
    params = with_scaling(NET.init(jax.random.PRNGKey(seed)), x, y)
    return params, {"x": x, "y": y}


def test_fits_a_smooth_function():
    params, data = problem(2000)
    start = float(jnp.sqrt(jnp.mean(jnp.square(jax.vmap(lambda s: residual(params, s))(data)))))
    result = lm.solve(residual, params, data, settings=lm.LMSettings(max_iters=60, chunk_size=512))
    assert float(result.rmse) < 0.02 < start
    assert np.all(np.diff(np.asarray(result.history)) <= 1e-6 * np.asarray(result.history)[:-1] + 1e-7)  # monotone
    assert int(result.iterations) <= 60


def test_normal_equations_match_float64_finite_differences():
    """The chunk-accumulated J^T J and J^T r equal those of a float64 central-difference Jacobian
    of the full residual vector (optimistix-style finite-difference check), padding included."""
    with jax.enable_x64(True):
        net = mlp((2, 4, 1), activation="tanh", init="glorot", dtype=jnp.float64)
        x = np.random.default_rng(1).uniform(-1, 1, (40, 2))
        data = {"x": x, "y": np.sin(x[:, :1] * 2)}
        params = net.init(jax.random.PRNGKey(3))
        res = lambda p, s: net.apply(p, s["x"]) - s["y"]  # noqa: E731
        from jax.flatten_util import ravel_pytree

        flat, unravel = ravel_pytree(params)
        # one program for the 2 x P evaluations of the difference quotients (eagerly, each
        # primitive compiled on its own)
        full = jax.jit(lambda f: jax.vmap(lambda s: res(unravel(f), s))(data).reshape(-1))
        eps = 1e-6
        jac = np.stack([(full(flat + eps * e) - full(flat - eps * e)) / (2 * eps) for e in np.eye(flat.size)], axis=1)
        r = np.asarray(full(flat))
        jtj, jtr, loss = lm.normal_equations(res, params, data, chunk_size=7)  # 40 = 5 chunks of 7 + padding
        # ravel order puts "layers" before "scaling"; the scaling is frozen (stop_gradient), so the
        # solver sees zero columns there while finite differences see the function change.
        n = count_parameters(params)
        jac = jac[:, :n]
        np.testing.assert_allclose(np.asarray(jtj)[:n, :n], jac.T @ jac, rtol=1e-6, atol=1e-8)
        np.testing.assert_allclose(np.asarray(jtr)[:n], jac.T @ r, rtol=1e-6, atol=1e-8)
        assert not np.asarray(jtj)[n:].any() and not np.asarray(jtr)[n:].any()
        assert float(loss) == pytest.approx(float(r @ r), rel=1e-12)


def test_mask_equals_dropping_samples():
    """Masked-out samples contribute nothing: the normal equations agree to rounding, and (in
    float64, where rounding cannot flip an accept/reject decision) so does a 15-iteration solve
    (the problem size and settings of ``test_batched_equals_sequential``: one compiled solver)."""
    params, data = problem(128, seed=2)
    mask = np.zeros(128, np.float32)
    mask[:100] = 1
    kept = jax.tree_util.tree_map(lambda a: a[:100], data)
    eq_masked = lm.normal_equations(residual, params, data, mask=mask, chunk_size=64)
    eq_dropped = lm.normal_equations(residual, params, kept, chunk_size=64)
    for a, b in zip(eq_masked, eq_dropped):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-4, atol=1e-3)
    with jax.enable_x64(True):
        p64 = jax.tree_util.tree_map(lambda a: jnp.asarray(a, jnp.float64), params)
        d64 = jax.tree_util.tree_map(lambda a: np.asarray(a, np.float64), data)
        masked = lm.solve(residual, p64, d64, mask=mask, settings=BATCH_SETTINGS)
        dropped = lm.solve(residual, p64, jax.tree_util.tree_map(lambda a: a[:100], d64), settings=BATCH_SETTINGS)
        np.testing.assert_allclose(masked.loss, dropped.loss, rtol=1e-8)
        jax.tree_util.tree_map(lambda a, b: np.testing.assert_allclose(a, b, rtol=1e-7, atol=1e-9),
                               masked.params, dropped.params)


def test_batched_equals_sequential():
    """``solve_batched`` runs each problem as ``solve`` does: the same accepted steps, losses and
    parameters. In float64: in float32 the vmapped reductions round in another order, and over
    15 iterations that can flip an accept/reject decision (on one 2-core AMD EPYC problem 3
    ended at loss 0.4195 batched against 0.4246 alone; float64 takes it to 0.0941 both ways)."""
    drawn = [problem(128, seed=s) for s in range(4)]  # float32 draws (their programs are compiled already)
    with jax.enable_x64(True):
        problems = [jax.tree_util.tree_map(lambda a: jnp.asarray(a, jnp.float64), p) for p in drawn]
        params = jax.tree_util.tree_map(lambda *a: jnp.stack(a), *[p for p, _ in problems])
        data = jax.tree_util.tree_map(lambda *a: jnp.stack(a), *[d for _, d in problems])
        mask = np.ones((4, 128), np.float64)
        mask[1, 50:] = 0  # problem 1 has only 50 real samples
        batched = lm.solve_batched(residual, params, data, mask=mask, settings=BATCH_SETTINGS)
        for i, (p, d) in enumerate(problems):
            single = lm.solve(residual, p, d, mask=mask[i], settings=BATCH_SETTINGS)
            assert int(batched.iterations[i]) == int(single.iterations)
            np.testing.assert_allclose(batched.history[i], single.history, rtol=1e-9)
            jax.tree_util.tree_map(lambda a, b: np.testing.assert_allclose(a[i], b, rtol=1e-7, atol=1e-10),
                                   batched.params, single.params)


def test_stops_on_loss_threshold():
    params, data = problem(128)  # E = 886 at the start, 0.70 after 10 iterations
    result = lm.solve(residual, params, data, settings=lm.LMSettings(max_iters=200, loss_threshold=1.0))
    assert float(result.loss) <= 1.0 and lm.STOP_REASONS[int(result.reason)] == "loss_threshold"
    assert int(result.iterations) < 200


def test_ill_conditioned_problems_never_return_nan():
    """Duplicated samples, a dead input feature, huge targets: finite results, loss not increased."""
    params, data = problem(64)
    x = np.repeat(data["x"][:4], 16, axis=0)
    x[:, 2] = 0.0  # a feature with no variation: zero Jacobian columns
    data = {"x": x, "y": 1e6 * smooth_target(x)}
    result = lm.solve(residual, params, data, settings=lm.LMSettings(max_iters=30))
    leaves = jax.tree_util.tree_leaves(result.params)
    assert all(bool(jnp.all(jnp.isfinite(leaf))) for leaf in leaves)
    # history[0]: E after the first iteration (what a 1-iteration solve returns)
    assert np.isfinite(float(result.loss)) and float(result.loss) <= float(result.history[0])


def test_residuals_that_overflow_float32_never_return_nan():
    """Targets of 1e20 (squared residuals overflow float32 to inf) on a rank-deficient problem:
    the steps that come out non-finite are rejected, the parameters stay finite."""
    params, data = problem(64)
    x = np.repeat(data["x"][:4], 16, axis=0)
    x[:, 2] = 0.0
    data = {"x": x, "y": 1e20 * smooth_target(x)}
    # the settings of the test above: the same compiled solver
    result = lm.solve(residual, params, data, settings=lm.LMSettings(max_iters=30))
    assert all(bool(jnp.all(jnp.isfinite(leaf))) for leaf in jax.tree_util.tree_leaves(result.params))


@pytest.mark.slow  # ~7 s: importing and compiling the archived jaxopt (the comparison backend)
def test_jaxopt_backend_runs_the_same_problem():
    params, data = problem(300)
    ours = lm.solve(residual, params, data, settings=lm.LMSettings(max_iters=20))
    theirs = lm.solve(residual, params, data, backend="jaxopt", settings=lm.LMSettings(max_iters=20))
    assert np.isfinite(float(theirs.loss))
    assert float(theirs.rmse) < 0.5 and float(ours.rmse) < 0.5
    with pytest.raises(ValueError, match="unknown LM backend"):
        lm.solve(residual, params, data, backend="scipy")


def test_early_stopping_keeps_the_best_validation_parameters():
    """A polynomial with as many coefficients as noisy training points overfits; with validation
    data the solver returns the iterate with the lowest validation loss and says so."""
    rng = np.random.default_rng(0)
    deg = 12
    xt = np.linspace(-1, 1, 14)
    xv = np.linspace(-0.97, 0.97, 40)
    f = lambda x: np.sin(2 * x)  # noqa: E731
    yt = f(xt) + 0.3 * rng.normal(size=xt.shape)

    def residual(p, s):
        x, y = s
        return jnp.polyval(p["c"], x)[None] - y[None]

    params = {"c": jnp.zeros((1, deg + 1))}
    data = (jnp.asarray(xt[None], jnp.float32), jnp.asarray(yt[None], jnp.float32))
    val = (jnp.asarray(xv[None], jnp.float32), jnp.asarray(f(xv)[None], jnp.float32))

    def val_loss(c):
        return float(np.sum((np.polyval(np.asarray(c[0]), xv) - f(xv)) ** 2))

    plain = lm.solve_batched(residual, params, data, settings=lm.LMSettings(max_iters=60, rtol=0.0))
    early = lm.solve_batched(residual, params, data, val_data=val,
                             settings=lm.LMSettings(max_iters=60, rtol=0.0, max_fail=3))
    assert lm.STOP_REASONS[int(early.reason[0])] == "validation"
    assert val_loss(early.params["c"]) < val_loss(plain.params["c"])
    assert float(early.loss[0]) >= float(plain.loss[0])  # worse on training data, better on validation
