"""Training losses (pure JAX, mean over all elements unless stated).

* ``mse``: mean squared error.
* ``mu_law`` / ``mu_law_l2``: Raghavan et al. 2023, §5: TM(x) = sgn(x) log(mu |x| + eps) / log(mu + eps)
  with mu = 10, eps = 1 (TM(0) = 0), extended to negative values because wavelet-domain predictions
  can be negative; the loss is the mean of (TM(pred) - TM(target))^2.
* ``log_l2``: Currius et al. 2020, §4: mean of (log(T + 1) - log(P + 1))^2; predictions are clamped
  at 0 (an SG mixture with non-negative amplitudes is never negative).
* ``relative_l2``: sum (pred - target)^2 / (sum target^2 + eps), the squared relative error of
  Ren et al. 2013, §4 (scale-free).
"""

from __future__ import annotations

import math

import jax.numpy as jnp

__all__ = ["mse", "mu_law", "mu_law_l2", "log_l2", "relative_l2"]


def mse(pred, target):
    """Mean squared error."""
    return jnp.mean(jnp.square(jnp.asarray(pred) - jnp.asarray(target)))


def mu_law(x, mu: float = 10.0, eps: float = 1.0):
    """Sign-extended mu-law tonemap TM(x) = sgn(x) log(mu |x| + eps) / log(mu + eps) (eps = 1 -> TM(0) = 0)."""
    x = jnp.asarray(x)
    return jnp.sign(x) * jnp.log(mu * jnp.abs(x) + eps) / math.log(mu + eps)


def mu_law_l2(pred, target, mu: float = 10.0, eps: float = 1.0):
    """Mean squared difference of mu-law tonemapped prediction and target (Raghavan et al. §5)."""
    return jnp.mean(jnp.square(mu_law(pred, mu, eps) - mu_law(target, mu, eps)))


def log_l2(pred, target):
    """Mean of (log(T + 1) - log(max(P, 0) + 1))^2 (Currius et al. §4)."""
    return jnp.mean(jnp.square(jnp.log1p(jnp.maximum(jnp.asarray(pred), 0.0)) - jnp.log1p(jnp.asarray(target))))


def relative_l2(pred, target, eps: float = 1e-12):
    """sum (pred - target)^2 / (sum target^2 + eps)."""
    pred, target = jnp.asarray(pred), jnp.asarray(target)
    return jnp.sum(jnp.square(pred - target)) / (jnp.sum(jnp.square(target)) + eps)
