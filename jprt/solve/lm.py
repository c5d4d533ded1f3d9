"""Levenberg-Marquardt for sums of squared residuals of any function family.

Minimises E(w) = sum_i m_i ||r(w, sample_i)||^2 (Ren et al. 2013, Eq. 6; m_i in {0, 1} masks
padding) with the update of Eq. 10,

    w <- w - (J^T J + mu D)^-1 J^T r,     D = diag(J^T J)   (Marquardt's scaling),

and Nielsen's (1999) damping rule: after a step with gain ratio rho = (actual decrease) /
(decrease predicted by the linear model) > 0, accept and set mu <- mu max(1/3, 1 - (2 rho - 1)^3),
nu <- 2; otherwise reject and set mu <- mu nu, nu <- 2 nu.

Memory: J^T J (P x P) and J^T r (P) are accumulated over chunks of ``chunk_size`` samples from
per-sample Jacobians (``vmap(jacrev)``), so the solver holds O(P^2 + chunk_size R P) numbers,
never the N R x P Jacobian; chunks are dynamic slices of the caller's arrays, so the data is not
copied either (pass JAX arrays to avoid the one host-to-device copy of NumPy inputs). The linear system is solved by Cholesky in float64 when JAX's x64 mode
is on, and otherwise in float32 with a diagonal jitter; a step that still comes out non-finite is
treated as rejected, so the returned parameters are never NaN.

Stopping: E <= ``loss_threshold``, a relative decrease below ``rtol`` on an accepted step, mu
beyond 1e16 (no progress possible), or ``max_iters`` iterations.

The solver is a pure function of arrays and ``jax.vmap``s over a batch of independent problems of
equal shape (``solve_batched``: the leaves of an RRF kd-tree), with masks for unequal sample
counts. ``backend="jaxopt"`` runs ``jaxopt.LevenbergMarquardt`` on the same problem (flattened
parameters, full Jacobian) for comparison.
"""

from __future__ import annotations

import functools
import warnings
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
from jax.flatten_util import ravel_pytree

__all__ = ["LMSettings", "LMResult", "solve", "solve_batched", "normal_equations", "STOP_REASONS"]

STOP_REASONS = ("running", "loss_threshold", "relative_decrease", "max_iters", "damping_overflow", "validation")


class LMSettings(NamedTuple):
    """The solver's static settings, one frozen value (hashable: one compiled program per value).

    Fields:
      max_iters: iterations at most (>= 1).
      loss_threshold: stop when E <= this.
      rtol: stop when an accepted step decreases E by less than this fraction.
      damping: initial mu (relative to diag(J^T J), Marquardt scaling).
      chunk_size: samples per Jacobian chunk (memory O(P^2 + chunk_size R P)).
      jitter: diagonal jitter of the float32 Cholesky solve, relative to max diag(J^T J).
      max_fail: with validation data, accepted steps without improving it before stopping.
    """

    max_iters: int = 100
    loss_threshold: float = 0.0
    rtol: float = 1e-7
    damping: float = 1e-3
    chunk_size: int = 2048
    jitter: float = 1e-7
    max_fail: int = 6

    def checked(self, n_samples: int) -> "LMSettings":
        """Validated, with every field of its type and the chunk no larger than the data."""
        if int(self.max_iters) < 1:
            raise ValueError(f"max_iters must be >= 1, got {self.max_iters}")
        return LMSettings(int(self.max_iters), float(self.loss_threshold), float(self.rtol), float(self.damping),
                          min(int(self.chunk_size), int(n_samples)), float(self.jitter), max(int(self.max_fail), 1))


class LMResult(NamedTuple):
    """Outcome of a solve (fields batched along a leading axis for ``solve_batched``).

    Fields:
      params:     the solution, same pytree structure as the start.
      loss:       () E = sum of squared (masked) residuals.
      rmse:       () sqrt(E / (number of unmasked residual entries)).
      iterations: () int32 iterations taken (accepted and rejected).
      history:    (max_iters,) E after each iteration (the last value repeats once stopped).
      reason:     () int32 index into STOP_REASONS.
    """

    params: Any
    loss: jax.Array
    rmse: jax.Array
    iterations: jax.Array
    history: jax.Array
    reason: jax.Array


class _State(NamedTuple):
    best: jax.Array
    best_val: jax.Array
    fails: jax.Array
    flat: jax.Array
    jtj: jax.Array
    jtr: jax.Array
    loss: jax.Array
    mu: jax.Array
    nu: jax.Array
    iteration: jax.Array
    reason: jax.Array
    history: jax.Array


def _check_data(data, mask, sample_axis: int = 0) -> int:
    """Number of samples; raises a one-line ValueError on inconsistent data or mask."""
    leaves = jax.tree_util.tree_leaves(data)
    if not leaves:
        raise ValueError("LM needs data with a leading sample axis")
    n = leaves[0].shape[sample_axis]
    if any(leaf.shape[sample_axis] != n for leaf in leaves):
        raise ValueError("all data arrays need the same number of samples on their first axis")
    if n == 0:
        raise ValueError("LM needs at least one sample")
    if mask is not None and jnp.shape(mask)[sample_axis] != n:
        raise ValueError(f"mask has {jnp.shape(mask)[sample_axis]} entries for {n} samples")
    return n


def _chunked(fn: Callable, init, data, mask, chunk: int):
    """Fold ``fn(acc, chunk_data, chunk_mask)`` over consecutive chunks of the samples.

    Chunks are dynamic slices of the caller's arrays (no padded or reshaped copy of the data, so
    memory does not grow with N); a shorter tail chunk is handled by a second, static slice.
    """
    n = jax.tree_util.tree_leaves(data)[0].shape[0]
    n_full, tail = divmod(n, chunk)

    def take(start, size):
        part = jax.tree_util.tree_map(lambda a: jax.lax.dynamic_slice_in_dim(a, start, size), data)
        m = jnp.ones((size,), jnp.float32) if mask is None else jax.lax.dynamic_slice_in_dim(mask, start, size)
        return part, m

    acc = jax.lax.fori_loop(0, n_full, lambda i, acc: fn(acc, *take(i * chunk, chunk)), init)
    if tail:
        acc = fn(acc, *take(n_full * chunk, tail))
    return acc


def _per_sample_fn(residual_fn: Callable, unravel: Callable) -> Callable:
    def per_sample(flat, sample):
        return jnp.atleast_1d(residual_fn(unravel(flat), sample)).reshape(-1)

    return per_sample


def _normal_pass(per_sample: Callable, flat, data, mask, chunk: int):
    """(J^T J, J^T r, sum r^2) accumulated chunk by chunk from per-sample Jacobians."""
    p = flat.shape[0]

    def body(acc, chunk_data, m):
        jtj, jtr, loss = acc
        r = jax.vmap(per_sample, in_axes=(None, 0))(flat, chunk_data)  # (C, R)
        jac = jax.vmap(jax.jacrev(per_sample), in_axes=(None, 0))(flat, chunk_data)  # (C, R, P)
        w = jnp.sqrt(m).astype(flat.dtype)
        jac = jac * w[:, None, None]
        rm = r * w[:, None]
        jtj = jtj + jnp.einsum("crp,crq->pq", jac, jac)
        jtr = jtr + jnp.einsum("crp,cr->p", jac, rm)
        return jtj, jtr, loss + jnp.sum(jnp.square(rm))

    init = (jnp.zeros((p, p), flat.dtype), jnp.zeros((p,), flat.dtype), jnp.zeros((), flat.dtype))
    return _chunked(body, init, data, mask, chunk)


def _residual_pass(per_sample: Callable, flat, data, mask, chunk: int):
    """sum_i m_i ||r_i||^2, chunk by chunk."""

    def body(acc, chunk_data, m):
        r = jax.vmap(per_sample, in_axes=(None, 0))(flat, chunk_data)
        return acc + jnp.sum(m.astype(flat.dtype)[:, None] * jnp.square(r))

    return _chunked(body, jnp.zeros((), flat.dtype), data, mask, chunk)


def normal_equations(residual_fn: Callable, params, data, *, mask=None, chunk_size: int = 2048):
    """(J^T J (P, P), J^T r (P,), E) at ``params`` over flattened parameters (``ravel_pytree``
    order), accumulated in chunks exactly as the solver does (diagnostics and tests)."""
    flat, unravel = ravel_pytree(params)
    n = _check_data(data, mask)
    data = jax.tree_util.tree_map(jnp.asarray, data)
    mask = None if mask is None else jnp.asarray(mask, jnp.float32)
    per_sample = _per_sample_fn(residual_fn, unravel)
    return jax.jit(lambda f, d, m: _normal_pass(per_sample, f, d, m, min(chunk_size, n)))(flat, data, mask)


@functools.lru_cache(maxsize=64)
def _build(residual_fn: Callable, unravel_key, settings: LMSettings):
    """The pure solver for one residual function and settings (cached, so repeated calls reuse
    the compiled program)."""
    max_iters, loss_threshold, rtol, damping, chunk, jitter, max_fail = settings
    per_sample = _per_sample_fn(residual_fn, unravel_key.unravel)

    def residual_pass(flat, data, mask):
        return _residual_pass(per_sample, flat, data, mask, chunk)

    def normal_pass(flat, data, mask):
        return _normal_pass(per_sample, flat, data, mask, chunk)

    def step_direction(jtj, jtr, mu):
        solve_dtype = jnp.float64 if jax.config.jax_enable_x64 else jnp.float32
        a = jtj.astype(solve_dtype)
        g = jtr.astype(solve_dtype)
        diag = jnp.diagonal(a)
        scale = jnp.maximum(jnp.max(diag), jnp.finfo(solve_dtype).tiny)
        d = jnp.maximum(diag, jitter * scale)  # Marquardt scaling, floored for zero columns
        eye = jnp.eye(a.shape[0], dtype=solve_dtype)
        a = a + mu.astype(solve_dtype) * jnp.diag(d) + (jitter * scale) * eye
        chol = jnp.linalg.cholesky(a)
        delta = -jax.scipy.linalg.cho_solve((chol, True), g)
        return delta.astype(jtr.dtype)

    def solver(flat0, data, mask, val_data=None, val_mask=None):
        has_val = val_data is not None
        if has_val:
            n_val = jax.tree_util.tree_leaves(val_data)[0].shape[0]
            val_loss = lambda f: _residual_pass(per_sample, f, val_data, val_mask, min(chunk, n_val))  # noqa: E731
        else:
            val_loss = lambda f: jnp.zeros((), f.dtype)  # noqa: E731
        jtj, jtr, loss = normal_pass(flat0, data, mask)
        state = _State(flat0, val_loss(flat0), jnp.zeros((), jnp.int32), flat0, jtj, jtr, loss, jnp.asarray(damping, flat0.dtype), jnp.asarray(2.0, flat0.dtype),
                       jnp.zeros((), jnp.int32), jnp.where(loss <= loss_threshold, 1, 0).astype(jnp.int32),
                       jnp.full((max_iters,), loss, flat0.dtype))

        def cond(s):
            return (s.reason == 0) & (s.iteration < max_iters)

        def body(s):
            delta = step_direction(s.jtj, s.jtr, s.mu)
            trial = s.flat + delta
            new_loss = residual_pass(trial, data, mask)
            predicted = -(2.0 * jnp.dot(delta, s.jtr) + jnp.dot(delta, s.jtj @ delta))
            actual = s.loss - new_loss
            finite = jnp.all(jnp.isfinite(delta)) & jnp.isfinite(new_loss)
            rho = jnp.where(finite & (predicted > 0), actual / jnp.maximum(predicted, 1e-30), -1.0)
            accept = finite & (rho > 0)
            jtj, jtr, loss = jax.lax.cond(accept, lambda: normal_pass(trial, data, mask),
                                          lambda: (s.jtj, s.jtr, s.loss))
            flat = jnp.where(accept, trial, s.flat)
            mu = jnp.where(accept, s.mu * jnp.maximum(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3), s.mu * s.nu)
            nu = jnp.where(accept, 2.0, 2.0 * s.nu)
            rel = actual / jnp.maximum(s.loss, 1e-30)
            reason = jnp.where(loss <= loss_threshold, 1,
                               jnp.where(accept & (rel < rtol), 2, jnp.where(mu > 1e16, 4, 0))).astype(jnp.int32)
            # Early stopping on validation data (Beale et al.'s trainlm, max_fail): after each
            # accepted step, keep the best parameters on the validation set; stop after max_fail
            # accepted steps without improvement.
            v = jax.lax.cond(accept, lambda: val_loss(flat), lambda: s.best_val)
            better = accept & (v < s.best_val)
            best = jnp.where(better, flat, s.best)
            best_val = jnp.where(better, v, s.best_val)
            fails = jnp.where(better, 0, jnp.where(accept, s.fails + 1, s.fails)).astype(jnp.int32)
            if has_val:
                reason = jnp.where((reason == 0) & (fails >= max_fail), 5, reason).astype(jnp.int32)
            iteration = s.iteration + 1
            reason = jnp.where((reason == 0) & (iteration >= max_iters), 3, reason).astype(jnp.int32)
            history = jax.lax.dynamic_update_slice(s.history, loss[None], (s.iteration,))
            history = jnp.where(jnp.arange(max_iters) > s.iteration, loss, history)
            return _State(best, best_val, fails, flat, jtj, jtr, loss, mu, nu, iteration, reason, history)

        s = jax.lax.while_loop(cond, body, state)
        reason = jnp.where(s.reason == 0, 3, s.reason).astype(jnp.int32)
        residual_size = per_sample(flat0, jax.tree_util.tree_map(lambda a: a[0], data)).shape[0]
        n_real = jax.tree_util.tree_leaves(data)[0].shape[0] if mask is None else jnp.sum(mask)
        count = jnp.maximum(n_real * residual_size, 1.0)
        # With validation data: the best parameters on it, and their training loss.
        flat, loss = (s.best, residual_pass(s.best, data, mask)) if has_val else (s.flat, s.loss)
        return flat, loss, jnp.sqrt(loss / count), s.iteration, s.history, reason

    return solver


class _UnravelKey:
    """Hashable wrapper of a ravel_pytree unravel function, keyed by the pytree structure."""

    def __init__(self, params):
        flat, self.unravel = ravel_pytree(params)
        leaves, treedef = jax.tree_util.tree_flatten(params)
        self.key = (treedef, tuple((leaf.shape, str(leaf.dtype)) for leaf in map(jnp.asarray, leaves)))

    def __hash__(self):
        return hash(self.key)

    def __eq__(self, other):
        return isinstance(other, _UnravelKey) and self.key == other.key


def solve(residual_fn: Callable, params, data, *, mask=None, settings: LMSettings = LMSettings(),
          backend: str = "jax", jaxopt_solver: str = "qr") -> LMResult:
    """Minimise sum_i mask_i ||residual_fn(params, sample_i)||^2 by Levenberg-Marquardt.

    Args:
      residual_fn: (params, sample) -> residual vector (R,) for ONE sample (a slice of ``data``).
      params: starting pytree (any family's parameters).
      data: pytree of arrays with the samples on the first axis (N, ...).
      mask: optional (N,) 0/1 weights (unequal sample counts in batched problems).
      settings: ``LMSettings`` (stopping rules of the module docstring, damping, chunk size).
      backend: "jax" (this solver) or "jaxopt" (``jaxopt.LevenbergMarquardt`` for comparison;
        only ``settings.max_iters`` applies).
    """
    if backend == "jaxopt":
        return _solve_jaxopt(residual_fn, params, data, mask, int(settings.max_iters), jaxopt_solver)
    if backend != "jax":
        raise ValueError(f"unknown LM backend {backend!r}; use 'jax' or 'jaxopt'")
    key = _UnravelKey(params)
    flat0, _ = ravel_pytree(params)
    n = _check_data(data, mask)
    data = jax.tree_util.tree_map(jnp.asarray, data)
    mask = None if mask is None else jnp.asarray(mask, jnp.float32)
    flat, loss, rmse, iterations, history, reason = _jitted(residual_fn, key, settings.checked(n))(flat0, data, mask)
    return LMResult(key.unravel(flat), loss, rmse, iterations, history, reason)


@functools.lru_cache(maxsize=64)
def _jitted(residual_fn, key, settings: LMSettings):
    return jax.jit(_build(residual_fn, key, settings))


@functools.lru_cache(maxsize=64)
def _jitted_batched(residual_fn, key, settings: LMSettings, has_mask: bool, has_val: bool):
    solver = _build(residual_fn, key, settings)
    if has_val:
        return jax.jit(jax.vmap(solver))
    if has_mask:
        return jax.jit(jax.vmap(lambda f, d, m: solver(f, d, m)))
    return jax.jit(jax.vmap(lambda f, d: solver(f, d, None)))


def solve_batched(residual_fn: Callable, params, data, *, mask=None, settings: LMSettings = LMSettings(),
                  val_data=None, val_mask=None) -> LMResult:
    """Solve B independent problems of equal shape in one vmapped call.

    ``params`` and ``data`` carry a leading batch axis B (data: (B, N, ...)); ``mask`` (B, N)
    marks each problem's real samples, so problems with fewer samples are padded. Every
    ``LMResult`` field gets the leading B axis.

    ``val_data`` (B, Nv, ...) with ``val_mask`` (B, Nv) turns on early stopping (Beale et al.'s
    trainlm, used by Ren et al. 2013 Appendix A): each problem returns its parameters with the
    lowest validation loss and stops (reason "validation") after ``settings.max_fail`` accepted
    steps without improving it.
    """
    first = jax.tree_util.tree_map(lambda a: a[0], params)
    key = _UnravelKey(first)
    flat0 = jax.vmap(lambda p: ravel_pytree(p)[0])(params)
    n = _check_data(data, mask, sample_axis=1)
    data = jax.tree_util.tree_map(jnp.asarray, data)
    has_val = val_data is not None
    if has_val:
        _check_data(val_data, val_mask, sample_axis=1)
        val_data = jax.tree_util.tree_map(jnp.asarray, val_data)
        val_mask = jnp.ones(jax.tree_util.tree_leaves(val_data)[0].shape[:2], jnp.float32) if val_mask is None \
            else jnp.asarray(val_mask, jnp.float32)
        if mask is None:
            mask = jnp.ones(jax.tree_util.tree_leaves(data)[0].shape[:2], jnp.float32)
    solver = _jitted_batched(residual_fn, key, settings.checked(n), mask is not None, has_val)
    args = (flat0, data) if mask is None else (flat0, data, jnp.asarray(mask, jnp.float32))
    if has_val:
        args = args + (val_data, val_mask)
    flat, loss, rmse, iterations, history, reason = solver(*args)
    return LMResult(jax.vmap(key.unravel)(flat), loss, rmse, iterations, history, reason)


def _solve_jaxopt(residual_fn, params, data, mask, max_iters, solver_name) -> LMResult:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)  # jaxopt is archived upstream
        import jaxopt

    flat0, unravel = ravel_pytree(params)
    n = jax.tree_util.tree_leaves(data)[0].shape[0]
    weights = jnp.ones((n,), flat0.dtype) if mask is None else jnp.asarray(mask, flat0.dtype)

    def all_residuals(flat):
        r = jax.vmap(lambda s: jnp.atleast_1d(residual_fn(unravel(flat), s)).reshape(-1))(data)
        return (r * jnp.sqrt(weights)[:, None]).reshape(-1)

    lm = jaxopt.LevenbergMarquardt(all_residuals, maxiter=max_iters, materialize_jac=True, solver=solver_name,
                                   jit=True)
    result = lm.run(flat0)
    flat = result.params
    loss = jnp.sum(jnp.square(all_residuals(flat)))
    count = jnp.sum(weights) * (all_residuals(flat).shape[0] // n)
    history = jnp.full((max_iters,), loss)
    return LMResult(unravel(flat), loss, jnp.sqrt(loss / count), jnp.asarray(result.state.iter_num, jnp.int32),
                    history, jnp.asarray(3, jnp.int32))
