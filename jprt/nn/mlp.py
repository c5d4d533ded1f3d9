"""Multilayer perceptrons as (init, apply) pairs, with the RRF conventions of Ren et al. 2013.

Appendix A of Ren et al. 2013: every input and output feature is scaled to [-1, 1] by its range
(the scale factors are saved with the model and applied at run time), and the weights are
initialised uniformly in [-1, 1]; hidden layers use tanh. ``mlp(..., init="rrf")`` does exactly
that; "glorot" and "he" are the usual alternatives for ReLU networks (e.g. the 2 x 128 ReLU MLP
of Raghavan et al. 2023, §5).

Parameters are a plain dict {"layers": [{"w": (n_in, n_out), "b": (n_out,)}, ...],
"scaling": {"in_center", "in_halfrange", "out_center", "out_halfrange"}}. The scaling entries
pass through ``stop_gradient`` in ``apply``, so optimisers leave them unchanged; set them from
data with ``with_scaling``.
"""

from __future__ import annotations

from typing import Callable, NamedTuple, Sequence

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["MLP", "mlp", "ranges", "constant_up_to_rounding", "with_scaling", "ACTIVATIONS", "count_parameters"]

ACTIVATIONS: dict[str, Callable] = {
    "tanh": jnp.tanh,
    "relu": jax.nn.relu,
    "linear": lambda x: x,
    "sigmoid": jax.nn.sigmoid,
    "softplus": jax.nn.softplus,
}


class MLP(NamedTuple):
    """An MLP family: ``init(key) -> params``, ``apply(params, x) -> y`` for x (..., sizes[0])."""

    init: Callable
    apply: Callable
    sizes: tuple[int, ...]


def _check_activation(name: str) -> Callable:
    if name not in ACTIVATIONS:
        raise ValueError(f"unknown activation {name!r}; use one of {sorted(ACTIVATIONS)}")
    return ACTIVATIONS[name]


def mlp(sizes: Sequence[int], *, activation: str = "tanh", output_activation: str = "linear", init: str = "rrf",
        use_bias: bool = True, dtype=jnp.float32) -> MLP:
    """An MLP with layer sizes ``sizes`` (input, hidden..., output).

    Args:
      activation: hidden-layer nonlinearity (tanh, relu, linear, sigmoid, softplus).
      output_activation: applied to the last layer (default linear).
      init: "rrf" (uniform [-1, 1], Ren et al. 2013 Appendix A), "glorot" (uniform) or "he" (normal).
        ``init(key)`` takes a JAX key, or a ``numpy.random.Generator`` to draw the same
        distributions on the host (NumPy arrays).
      use_bias: False gives a bias-free network (the matrix U of Raghavan et al. 2023 is a
        one-layer, bias-free, linear MLP).

    Numerics:
        case: mlp (a tanh network 8-16-16-3 as ``init="rrf"`` draws it, inputs in [-1, 1], the range
          ``with_scaling`` maps data to; gradients w.r.t. weights, biases and inputs)
        float32: value rtol 1e-4 atol 1e-5; grad rtol 1e-4 atol 1e-5
    """
    sizes = tuple(int(s) for s in sizes)
    if len(sizes) < 2 or any(s <= 0 for s in sizes):
        raise ValueError(f"an MLP needs at least input and output sizes, all positive; got {sizes}")
    hidden = _check_activation(activation)
    final = _check_activation(output_activation)
    if init not in ("rrf", "glorot", "he"):
        raise ValueError(f"unknown init {init!r}; use 'rrf', 'glorot' or 'he'")

    def init_fn(key):
        if isinstance(key, np.random.Generator):
            return _host_init(key)
        layers = []
        for k, (n_in, n_out) in zip(jax.random.split(key, len(sizes) - 1), zip(sizes[:-1], sizes[1:])):
            kw, kb = jax.random.split(k)
            if init == "rrf":
                w = jax.random.uniform(kw, (n_in, n_out), dtype, -1.0, 1.0)
                b = jax.random.uniform(kb, (n_out,), dtype, -1.0, 1.0)
            elif init == "glorot":
                limit = (6.0 / (n_in + n_out)) ** 0.5
                w = jax.random.uniform(kw, (n_in, n_out), dtype, -limit, limit)
                b = jnp.zeros((n_out,), dtype)
            else:
                w = jax.random.normal(kw, (n_in, n_out), dtype) * (2.0 / n_in) ** 0.5
                b = jnp.zeros((n_out,), dtype)
            layers.append({"w": w, "b": b} if use_bias else {"w": w})
        scaling = {
            "in_center": jnp.zeros((sizes[0],), dtype), "in_halfrange": jnp.ones((sizes[0],), dtype),
            "out_center": jnp.zeros((sizes[-1],), dtype), "out_halfrange": jnp.ones((sizes[-1],), dtype),
        }
        return {"layers": layers, "scaling": scaling}

    def _host_init(rng: np.random.Generator):
        # the same distributions drawn on the host, in order (w then b, layer by layer): cheap for
        # thousands of tiny networks (RRF's kd-tree nodes) and reproducible from one NumPy seed
        layers = []
        for n_in, n_out in zip(sizes[:-1], sizes[1:]):
            if init == "rrf":
                w, b = rng.uniform(-1.0, 1.0, (n_in, n_out)), rng.uniform(-1.0, 1.0, (n_out,))
            elif init == "glorot":
                limit = (6.0 / (n_in + n_out)) ** 0.5
                w, b = rng.uniform(-limit, limit, (n_in, n_out)), np.zeros((n_out,))
            else:
                w, b = rng.normal(size=(n_in, n_out)) * (2.0 / n_in) ** 0.5, np.zeros((n_out,))
            layer = {"w": w.astype(dtype)}
            if use_bias:
                layer["b"] = b.astype(dtype)
            layers.append(layer)
        scaling = {"in_center": np.zeros((sizes[0],), dtype), "in_halfrange": np.ones((sizes[0],), dtype),
                   "out_center": np.zeros((sizes[-1],), dtype), "out_halfrange": np.ones((sizes[-1],), dtype)}
        return {"layers": layers, "scaling": scaling}

    def apply_fn(params, x):
        x = jnp.asarray(x)
        if x.shape[-1] != sizes[0]:
            raise ValueError(f"MLP expects inputs with {sizes[0]} features, got shape {x.shape}")
        s = jax.lax.stop_gradient(params["scaling"])
        batch_shape = x.shape[:-1]
        h = x.reshape(-1, sizes[0])
        h = (h - s["in_center"][None, :]) / s["in_halfrange"][None, :]
        layers = params["layers"]
        for i, layer in enumerate(layers):
            h = h @ layer["w"]
            if "b" in layer:
                h = h + layer["b"][None, :]
            h = hidden(h) if i < len(layers) - 1 else final(h)
        y = h * s["out_halfrange"][None, :] + s["out_center"][None, :]
        return y.reshape(batch_shape + (sizes[-1],))

    return MLP(init_fn, apply_fn, sizes)


def ranges(a, *, eps: float = 1e-5):
    """Centre and half-range per feature of samples ``a`` (samples on the first axes, features
    last), the map of Ren et al. 2013 Appendix A (Beale et al.'s mapminmax) to [-1, 1]; constant
    features get a half-range of 1 (they map to 0). NumPy in, NumPy out (same dtype); else JAX.

    A feature counts as constant when its half-range is at most ``eps`` x max(1, |centre|): a
    coordinate that is constant up to float32 rounding (a wall's z from ray intersections varies
    by ~1e-7) must not be stretched to [-1, 1], or the network fits that noise with weights of
    1e8 and the rendering is speckled wherever the rounding differs (the RRF's floor blotches).

    Numerics: not differentiable (a data statistic; it sets the fixed, stop-gradient scaling).
    """
    xp = np if isinstance(a, np.ndarray) else jnp
    a = xp.asarray(a).reshape(-1, a.shape[-1])
    lo, hi = a.min(axis=0), a.max(axis=0)
    half = 0.5 * (hi - lo)
    centre = 0.5 * (hi + lo)
    return centre, xp.where(constant_up_to_rounding(lo, hi, eps=eps), xp.ones_like(half), half)


def constant_up_to_rounding(lo, hi, *, eps: float = 1e-5):
    """Whether a feature whose samples span [lo, hi] is constant up to float rounding (elementwise
    bool): its half-range (hi - lo) / 2 is at most ``eps`` x max(1, |centre|). The rule of
    ``ranges``; the RRF's per-object kd-tree boxes use it too (a wall's constant coordinate
    spans one or two float32 ulps, which a unit box would stretch to [0, 1]).

    Numerics: not differentiable (a comparison).
    """
    xp = np if isinstance(lo, np.ndarray) and isinstance(hi, np.ndarray) else jnp
    return 0.5 * (hi - lo) <= eps * xp.maximum(1.0, xp.abs(0.5 * (hi + lo)))


def with_scaling(params, x=None, y=None, *, eps: float = 1e-5):
    """Return params whose input/output scaling maps the ranges of ``x`` / ``y`` (samples on the
    first axes, features last) to [-1, 1] (``ranges``).

    Numerics: not differentiable (sets the fixed, stop-gradient scaling from data).
    """
    scaling = dict(params["scaling"])
    if x is not None:
        scaling["in_center"], scaling["in_halfrange"] = ranges(jnp.asarray(x), eps=eps)
    if y is not None:
        scaling["out_center"], scaling["out_halfrange"] = ranges(jnp.asarray(y), eps=eps)
    return {**params, "scaling": scaling}


def count_parameters(params) -> int:
    """Number of trainable scalars (the layers; the fixed scaling is not counted).

    Numerics: not differentiable (an integer count).
    """
    return int(sum(leaf.size for leaf in jax.tree_util.tree_leaves(params["layers"])))
