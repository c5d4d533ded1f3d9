"""The float32-vs-float64 differential harness: specs read from docstrings, inputs drawn by
Hypothesis, values and gradients compared.

Every public function of the covered modules (``MODULES``) carries a ``Numerics:`` section in
its docstring. Either one line giving the reason it is not covered::

    Numerics: not differentiable (integer texel indices).

or a block stating where it is accurate and how well::

    Numerics:
        sharpness: (32,) in [0, 1e4]
        amplitude: (32,) in [0, 1e5]
        float32: value rtol 1e-6 atol 1e-30; grad rtol 1e-5 atol 1e-30

Argument lines (``name: ...``) give the domain the harness draws from:

* ``(shape) in [lo, hi]``: floats, every value exactly representable in float32 (so both
  precisions see the same input), ``lo``, ``hi`` and 0 (when inside) always among them;
* ``(shape) int in [lo, hi]``: integers;
* ``(shape) unit``: unit vectors (last axis 3), axis-aligned ones among them;
  ``unit near OTHER``: each row the same as, opposite to, 1e-3 rad from, or independent of the
  row of unit argument OTHER (aligned and antipodal lobes);
  ``unit within DEG of OTHER``: at a polar angle in [0, DEG] degrees about OTHER, DEG itself
  included (grazing views);
* ``= literal``: a fixed Python value.

Other lines: ``grad: a, b`` (the arguments differentiated; default every float and unit
argument), ``case: name (words)`` (inputs built by ``cases.py``'s function ``name`` for
functions of parameter pytrees; the words say the domain), ``fd: off (reason)`` (no finite-
difference check of the float64 gradient, e.g. at a kink), ``float32: value rtol R atol A;
grad rtol R atol A`` (required; rtol at most 1e-3); a line in parentheses is a note (why a
tolerance is what it is).

The checks, per drawn point: the float64 run really is float64 (and the float32 one float32);
float32 values and vector-Jacobian products are within ``atol + rtol |float64|`` of float64
elementwise; float32 is finite wherever float64 is; and the float64 gradient agrees with a
second-order one-sided finite difference (stepping into the domain), so a gradient that is
wrong in both precisions (a zero slope at a kink-free 0) is caught too.
"""

from __future__ import annotations

import ast
import dataclasses
import importlib
import inspect
import re
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np

MODULES = [
    "jprt.sphere.cubemap", "jprt.sphere.haar", "jprt.sphere.octahedral", "jprt.sphere.quadrature",
    "jprt.sphere.sg", "jprt.sphere.sh", "jprt.sphere.envmap",
    "jprt.nn.cnn", "jprt.nn.encoding", "jprt.nn.factor", "jprt.nn.hashgrid", "jprt.nn.mlp",
    "jprt.solve.losses",
] + [f"jprt.methods.{m}.model" for m in ("datadriven", "mrt", "rrf", "sg_lightfield", "sh_prt", "wavelet_prt")] + [
    "jprt.methods.rrf.features", "jprt.methods.rrf.fitting", "jprt.methods.rrf.renderer",
    "jprt.methods.wavelet_prt.views", "jprt.methods.mrt.block_atlas", "jprt.design",
]

MAX_RTOL = 1e-3  # issue 20: float32 within 1e-3 relative (or a stated absolute tolerance near 0)


@dataclasses.dataclass
class Arg:
    name: str
    kind: str  # "float", "int", "unit", "fixed"
    shape: tuple = ()
    lo: float = 0.0
    hi: float = 0.0
    relation: str = ""  # "", "near", "within"
    other: str = ""
    degrees: float = 0.0
    value: Any = None


@dataclasses.dataclass
class Spec:
    qualname: str
    fn: Callable
    exempt: str | None = None
    args: list = dataclasses.field(default_factory=list)
    grad: list | None = None
    case: str | None = None
    fd: bool = True
    value_tol: tuple = (None, None)  # (rtol, atol)
    grad_tol: tuple = (None, None)


def public_functions() -> list[tuple[str, Callable]]:
    """(qualified name, function) of every public function defined in ``MODULES``."""
    out = []
    for name in MODULES:
        mod = importlib.import_module(name)
        names = getattr(mod, "__all__", None) or [n for n in vars(mod) if not n.startswith("_")]
        for n in names:
            v = getattr(mod, n)
            base = inspect.unwrap(v) if callable(v) else v  # a jitted function wraps one
            if inspect.isfunction(base) and base.__module__ == name:
                out.append((f"{name}.{n}", v))
    return out


def _numerics_block(doc: str) -> tuple[str, list[str]] | None:
    lines = (doc or "").splitlines()
    for i, line in enumerate(lines):
        if line.strip().startswith("Numerics:"):
            indent = len(line) - len(line.lstrip())
            head = line.strip()[len("Numerics:"):].strip()
            body, key_indent = [], None
            for rest in lines[i + 1:]:
                if not rest.strip():
                    continue
                depth = len(rest) - len(rest.lstrip())
                if depth <= indent:
                    break
                key_indent = depth if key_indent is None else key_indent
                if depth > key_indent and body:  # a continuation of the line above
                    body[-1] += " " + rest.strip()
                else:
                    body.append(rest.strip())
            return head, body
    return None


_TOL = re.compile(r"(value|grad)\s+rtol\s+([^\s;]+)\s+atol\s+([^\s;]+)")


def parse(qualname: str, fn: Callable) -> Spec:
    """The ``Numerics:`` section of ``fn``'s docstring as a ``Spec`` (ValueError when missing or
    malformed: a function cannot join the library without saying where it is accurate)."""
    block = _numerics_block(inspect.getdoc(fn))
    if block is None:
        raise ValueError(f"{qualname}: no 'Numerics:' section in its docstring")
    head, body = block
    spec = Spec(qualname, fn)
    if head:
        m = re.match(r"not differentiable \((.+)\)\.?$", head)
        if not m:
            raise ValueError(f"{qualname}: a one-line Numerics section must read 'not differentiable (reason).'")
        spec.exempt = m[1]
        return spec
    for line in body:
        if line.startswith("("):  # a note: why the tolerance is what it is
            continue
        key, _, rest = line.partition(":")
        key, rest = key.strip(), rest.strip()
        if key == "float32":
            for kind, rtol, atol in _TOL.findall(rest):
                setattr(spec, f"{kind}_tol", (float(rtol), float(atol)))
        elif key == "grad":
            spec.grad = [g.strip() for g in rest.split(",") if g.strip()]
        elif key == "case":
            spec.case = rest.split()[0]
        elif key == "fd":
            spec.fd = not rest.startswith("off")
        else:
            spec.args.append(_parse_arg(qualname, key, rest))
    for kind in ("value", "grad"):
        rtol, atol = getattr(spec, f"{kind}_tol")
        if rtol is None:
            raise ValueError(f"{qualname}: Numerics states no float32 {kind} tolerance")
        if rtol > MAX_RTOL:
            raise ValueError(f"{qualname}: float32 {kind} rtol {rtol} is above {MAX_RTOL}")
    if spec.case is None and not spec.args:
        raise ValueError(f"{qualname}: Numerics names neither arguments nor a case")
    return spec


def _parse_arg(qualname: str, name: str, text: str) -> Arg:
    if text.startswith("="):
        return Arg(name, "fixed", value=ast.literal_eval(text[1:].strip()))
    m = re.match(r"(\([\d,\s]*\))\s+(.*)$", text)
    if not m:
        raise ValueError(f"{qualname}: cannot read the domain of {name!r}: {text!r}")
    shape, rest = ast.literal_eval(m[1]), m[2].strip()
    shape = tuple(shape) if isinstance(shape, tuple) else (shape,)
    if r := re.match(r"(int\s+)?in \[([^,]+),([^\]]+)\]$", rest):
        return Arg(name, "int" if r[1] else "float", shape, float(r[2]), float(r[3]))
    if rest == "unit":
        return Arg(name, "unit", shape)
    if r := re.match(r"unit near (\w+)$", rest):
        return Arg(name, "unit", shape, relation="near", other=r[1])
    if r := re.match(r"unit within ([\d.]+) of (\w+)$", rest):
        return Arg(name, "unit", shape, relation="within", other=r[2], degrees=float(r[1]))
    raise ValueError(f"{qualname}: cannot read the domain of {name!r}: {text!r}")


# ------------------------------------------------------------------------------------------
# Drawing


def _f32_bounds(lo: float, hi: float) -> tuple[float, float]:
    lo32, hi32 = np.float32(lo), np.float32(hi)
    if lo32 < lo:
        lo32 = np.nextafter(lo32, np.float32(np.inf))
    if hi32 > hi:
        hi32 = np.nextafter(hi32, np.float32(-np.inf))
    return float(lo32), float(hi32)


def _unit(v: np.ndarray) -> np.ndarray:
    """Rows normalised in float64 and rounded to float32 (both precisions then see these)."""
    v = (v / np.linalg.norm(v, axis=-1, keepdims=True)).astype(np.float32)
    v[np.abs(v) < np.finfo(np.float32).tiny] = 0.0  # XLA's CPU float32 flushes subnormals to zero
    return v.astype(np.float64)


def _frame(z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    helper = np.where(np.abs(z[..., :1]) < 0.9, np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0]))
    x = np.cross(helper, z)
    x /= np.linalg.norm(x, axis=-1, keepdims=True)
    return x, np.cross(z, x)


def draw_args(draw, spec: Spec) -> dict:
    """Inputs of one example: float64 NumPy arrays whose values are float32-exact."""
    from hypothesis import strategies as st
    from hypothesis.extra import numpy as hnp

    out: dict[str, Any] = {}
    for a in spec.args:
        if a.kind == "fixed":
            out[a.name] = a.value
        elif a.kind == "int":
            x = draw(hnp.arrays(np.int64, a.shape, elements=st.integers(int(a.lo), int(a.hi))))
            flat = x.reshape(-1)
            flat[:2][: flat.size] = [int(a.lo), int(a.hi)][: min(2, flat.size)]
            out[a.name] = x.astype(np.int32)
        elif a.kind == "float":
            lo, hi = _f32_bounds(a.lo, a.hi)
            x = draw(hnp.arrays(np.float32, a.shape, elements=st.floats(lo, hi, width=32, allow_subnormal=False)))
            flat = x.reshape(-1)
            ends = [lo, hi] + ([0.0] if lo < 0.0 < hi else [])
            n = min(len(ends), flat.size)
            flat[:n] = ends[:n]
            out[a.name] = x.astype(np.float64)
        else:  # unit
            rows = int(np.prod(a.shape[:-1]))
            comp = draw(hnp.arrays(np.float32, (rows, 3), elements=st.floats(-1, 1, width=32)))
            comp[np.linalg.norm(comp, axis=-1) < 1e-3] = (0.0, 0.0, 1.0)
            base = _unit(comp.astype(np.float64))
            if a.relation == "near":
                ref = out[a.other].reshape(rows, 3)
                mode = np.asarray(draw(st.lists(st.integers(0, 3), min_size=rows, max_size=rows)))
                mode[:4][: rows] = np.arange(4)[: min(4, rows)]
                x, y = _frame(ref)
                tilt = _unit(np.cos(1e-3) * ref + np.sin(1e-3) * x)
                base = np.where((mode == 0)[:, None], ref, np.where((mode == 1)[:, None], -ref,
                                np.where((mode == 2)[:, None], tilt, base)))
            elif a.relation == "within":
                ref = out[a.other].reshape(rows, 3)
                deg = draw(hnp.arrays(np.float64, (rows,), elements=st.floats(0.0, a.degrees)))
                deg[:2][: rows] = [0.0, a.degrees][: min(2, rows)]
                phi = draw(hnp.arrays(np.float64, (rows,), elements=st.floats(0.0, 2 * np.pi)))
                x, y = _frame(ref)
                t = np.radians(deg)[:, None]
                base = _unit(np.cos(t) * ref + np.sin(t) * (np.cos(phi)[:, None] * x + np.sin(phi)[:, None] * y))
            else:
                axes = np.array([[1, 0, 0], [0, 1, 0], [0, 0, 1], [-1, 0, 0], [0, -1, 0], [0, 0, -1]], np.float64)
                base[: min(6, rows)] = axes[: min(6, rows)]
            out[a.name] = base.reshape(a.shape)
    return out


# ------------------------------------------------------------------------------------------
# Running and comparing


def _cast(x, dtype):
    if isinstance(x, np.ndarray) and x.dtype.kind == "f":
        return jnp.asarray(x, dtype)
    if isinstance(x, np.ndarray):
        return jnp.asarray(x)
    return x


def _cast_tree(tree, dtype):
    return jax.tree_util.tree_map(lambda x: jnp.asarray(x, dtype) if np.asarray(x).dtype.kind == "f" else x, tree)


def float_leaves(tree) -> list:
    return [x for x in jax.tree_util.tree_leaves(tree) if hasattr(x, "dtype") and jnp.issubdtype(x.dtype, jnp.floating)]


@dataclasses.dataclass
class Problem:
    """One drawn example: ``fn(**args)``, differentiated with respect to ``grad`` (names of
    entries of ``args``; each may be an array or a pytree of arrays)."""

    fn: Callable
    args: dict
    grad: list


def _is_float_tree(v) -> bool:
    leaves = jax.tree_util.tree_leaves(v)
    return bool(leaves) and all(isinstance(x, (np.ndarray, jax.Array)) and np.asarray(x).dtype.kind == "f"
                                for x in leaves)


def _split(problem: Problem, dtype):
    """(float arguments cast to dtype: traced, everything else: constants of the program)."""
    dynamic = {k: _cast_tree(v, dtype) for k, v in problem.args.items() if _is_float_tree(v)}
    static = {k: _cast(v, dtype) for k, v in problem.args.items() if k not in dynamic}
    return dynamic, static


FD_STEP = 1e-7  # relative to each input's scale: second-order truncation and float64 rounding both ~1e-9
FD_TS = (0.0, 0.5 * FD_STEP, FD_STEP, 2.0 * FD_STEP)


def fd_directions(problem: Problem, dynamic: dict, domains: dict, seed: int) -> dict:
    """A random direction per differentiated argument, each entry of the size of its input (or of
    1e-3 of its domain near 0) and pointing into the domain at its ends."""
    rng = np.random.default_rng(seed + 1)
    directions = {}
    for name in problem.grad:
        leaves, tree = jax.tree_util.tree_flatten(dynamic[name])
        lo, hi = domains.get(name, (-np.inf, np.inf))
        dirs = []
        for x in leaves:
            x = np.asarray(x)
            scale = np.maximum(np.abs(x), 1e-3 * (hi - lo) if np.isfinite(hi - lo) else 1.0)
            d = rng.choice([-1.0, 1.0], x.shape) * scale
            d = np.where(x + 2 * FD_STEP * d > hi, -np.abs(d), d)
            d = np.where(x + 2 * FD_STEP * d < lo, np.abs(d), d)
            dirs.append(d)
        directions[name] = jax.tree_util.tree_unflatten(tree, dirs)
    return directions


def run(problem: Problem, dtype, weights: list | None, seed: int, directions: dict | None = None):
    """(float leaves of the output, vjp of sum(weights * leaves) w.r.t. ``problem.grad``, and with
    ``directions`` sum(weights * leaves) at the inputs moved by t x directions for t in ``FD_TS``)
    in dtype, as one jitted program: one compile (op-by-op dispatch compiled every primitive anew,
    4 s for a small network)."""
    dynamic, static = _split(problem, dtype)

    def f(dyn):
        return float_leaves(problem.fn(**static, **dyn))

    if weights is None:
        rng = np.random.default_rng(seed)
        weights = [rng.uniform(0.5, 1.5, o.shape).astype(np.float32).astype(np.float64)
                   for o in jax.eval_shape(f, dynamic)]

    @jax.jit
    def program(dyn, cot):
        def g(*p):
            return f({**dyn, **dict(zip(problem.grad, p))})

        out, vjp = jax.vjp(g, *[dyn[n] for n in problem.grad])
        fd = None
        if directions is not None:
            def weighted(t):
                moved = {n: jax.tree_util.tree_map(lambda x, d: x + t * d, dyn[n], directions[n]) for n in problem.grad}
                return sum(jnp.sum(c * o) for c, o in zip(cot, f({**dyn, **moved})))

            fd = jnp.stack([weighted(jnp.asarray(t, dtype)) for t in FD_TS])
        return out, vjp(cot), fd

    cot = [jnp.asarray(w, dtype) for w in weights]
    out, grads, fd = program(dynamic, cot)
    return out, grads, weights, fd


def close(a, b, rtol: float, atol: float):
    """Elementwise |a - b| <= atol + rtol |b|, NaN only where b is; the worst offender or None."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    if a.shape != b.shape:
        return f"shape {a.shape} != {b.shape}"
    finite = np.isfinite(b)
    if np.any(finite & ~np.isfinite(a)):
        i = np.unravel_index(np.argmax(finite & ~np.isfinite(a)), a.shape)
        return (f"at {tuple(int(j) for j in i)}: float32 not finite where float64 is "
                f"({int(np.sum(finite & ~np.isfinite(a)))} entries; float64 {b[i]:.9g})")
    err = np.where(finite, np.abs(a - b) - (atol + rtol * np.abs(b)), 0.0)
    if np.any(err > 0):
        i = np.unravel_index(np.argmax(err), err.shape)
        return (f"at {tuple(int(j) for j in i)}: float32 {a[i]:.9g}, float64 {b[i]:.9g} (rel "
                f"{abs(a[i] - b[i]) / max(abs(b[i]), 1e-300):.3g}; largest |float64| {np.max(np.abs(b[finite]), initial=0):.3g})")
    return None


def _inputs_at(problem: Problem, message: str) -> str:
    """The drawn inputs of the row a failure message names (arrays sharing its leading index)."""
    m = re.search(r"at \((\d+)", message)
    if not m:
        return ""
    i = int(m[1])
    rows = {k: np.asarray(v)[i].tolist() for k, v in problem.args.items()
            if isinstance(v, np.ndarray) and v.ndim and v.shape[0] > i}
    return f"; inputs of row {i}: {rows}"


def check(problem: Problem, spec: Spec, seed: int, domains: dict | None = None) -> None:
    """Compare float32 with float64 (values and vjps) and the float64 gradient with finite
    differences; AssertionError naming the function, the leaf and the worst entry."""
    with jax.enable_x64(True):
        directions = fd_directions(problem, _split(problem, jnp.float64)[0], domains or {}, seed) if spec.fd else None
        out64, vjp64, weights, fd = run(problem, jnp.float64, None, seed, directions)
        for leaf in float_leaves(out64) + float_leaves(vjp64):
            assert leaf.dtype == jnp.float64, f"{spec.qualname}: the float64 run computed in {leaf.dtype}"
    out32, vjp32, _, _ = run(problem, jnp.float32, weights, seed)
    for leaf in float_leaves(out32):
        assert leaf.dtype == jnp.float32, f"{spec.qualname}: float32 inputs gave {leaf.dtype} outputs"
    assert len(out32) == len(out64)
    for i, (a, b) in enumerate(zip(out32, out64)):
        bad = close(a, b, *spec.value_tol)
        assert bad is None, f"{spec.qualname}: value (output leaf {i}) {bad}{_inputs_at(problem, bad)}"
    g32, g64 = jax.tree_util.tree_leaves(vjp32), jax.tree_util.tree_leaves(vjp64)
    for i, (a, b) in enumerate(zip(g32, g64)):
        bad = close(a, b, *spec.grad_tol)
        assert bad is None, f"{spec.qualname}: gradient (leaf {i} of {problem.grad}) {bad}{_inputs_at(problem, bad)}"
    if spec.fd:
        _check_fd(spec, vjp64, directions, problem.grad, np.asarray(fd, np.float64))


def _check_fd(spec: Spec, vjp64, directions: dict, grad: list, values: np.ndarray) -> None:
    """The float64 vjp against a one-sided second-order difference along ``directions``
    (``values``: the weighted output at ``FD_TS``), which step into each argument's domain (so a
    domain's end is never left)."""
    h = FD_STEP
    f0, f_half, f1, f2 = (float(v) for v in values)
    fd = (-3 * f0 + 4 * f1 - f2) / (2 * h)
    fd_half = (-3 * f0 + 4 * f_half - f1) / h
    # the truncation error of the second-order formula, estimated from halving the step
    # (it dominates where the true gradient is 0 at a minimum: pred = target)
    truncation = 2.0 * abs(fd - fd_half)
    pairs = list(zip(jax.tree_util.tree_leaves(vjp64), jax.tree_util.tree_leaves([directions[n] for n in grad])))
    ad = sum(float(np.sum(np.asarray(g) * np.asarray(d))) for g, d in pairs)
    scale = sum(float(np.sum(np.abs(np.asarray(g) * np.asarray(d)))) for g, d in pairs)
    rounding = 1e-15 * (abs(f0) + abs(f_half) + abs(f1) + abs(f2)) / h
    assert abs(fd - ad) <= 1e-4 * max(abs(fd), abs(ad)) + 1e-6 * scale + truncation + rounding, \
        f"{spec.qualname}: float64 gradient {ad:.9g} disagrees with finite differences {fd:.9g} (step halved: {fd_half:.9g})"
