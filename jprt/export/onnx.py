"""ONNX of a neural evaluator (RRF, neural-wavelet PRT, SG environment visibility) via ``jax2onnx``.

The evaluator is traced at fixed argument shapes to a jaxpr, which is rewritten
(``lowerable_jaxpr``) into primitives ``jax2onnx`` converts, then converted. The rewrite is
where ``jax2onnx`` cannot express an operation and it is written here by hand (``HAND_WRITTEN``
says which, and the manifest lists the ones a model needed):

* nested ``jit`` and ``custom_jvp`` calls are inlined (only the primal program is exported);
* ``lt_to`` / ``le_to`` / ``eq_to`` (XLA's total-order comparisons) become ``lt`` / ``le`` /
  ``eq``, equal except on NaN and the order of -0 and +0;
* ``stack`` becomes a concatenation of expanded operands, and a concatenation drops its empty
  operands (``jax2onnx`` converts an empty operand as one row);
* a bitwise-OR ``reduce`` of integers (ONNX reduces only booleans with OR) is one boolean
  reduction per bit, packed back into the word;
* every ``gather`` becomes a flat ``take``: the operand's linear index of every output element is
  computed with integer arithmetic (XLA's gather semantics, clamped or filled per its mode), and
  the operand is read through it as one 1-D ``Gather``; ``jax2onnx`` handles only some gather
  forms (slices at batched start indices, as ``vmap`` of ``dynamic_slice`` makes, fail).
* every ``scatter`` / ``scatter-add`` likewise becomes a flat scatter at linear indices.

Loops (``scan``, ``while``) and ``cond`` keep their structure (ONNX ``Loop`` / ``If``); their
bodies are rewritten the same way.
"""

from __future__ import annotations

import contextlib
import logging
import os
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

__all__ = ["HAND_WRITTEN", "lowerable_jaxpr", "to_onnx", "export_evaluator", "input_names", "run_onnx"]

#: Operations ``jax2onnx`` does not convert (as traced from jprt's evaluators), written by hand here.
HAND_WRITTEN = {
    "lt_to": "total-order less-than: written as lt (differs only on NaN, -0 < +0)",
    "le_to": "total-order less-or-equal: written as le",
    "eq_to": "total-order equality: written as eq",
    "stack": "no jax2onnx rule: written as expand_dims + concatenate",
    "concatenate_empty": "a concatenation with empty operands (jax2onnx gives an empty operand one row): the "
                         "empty operands are dropped",
    "reduce_or_int": "bitwise-OR reduce of integers (ONNX's OR reductions are boolean): one boolean reduction "
                     "per bit, packed back",
    "gather": "jax2onnx lowers only some gather forms: written as a flat take at computed linear indices",
    "scatter": "written as a flat scatter at computed linear indices",
    "scatter-add": "written as a flat scatter-add at computed linear indices",
}

_INLINE = {"pjit", "jit", "closed_call", "core_call", "custom_jvp_call", "custom_vjp_call", "remat", "checkpoint"}
_COMPARE = {"lt_to": lax.lt, "le_to": lax.le, "eq_to": lax.eq}


def _sub_jaxpr(eqn):
    for key in ("jaxpr", "call_jaxpr", "fun_jaxpr"):
        if key in eqn.params:
            sub = eqn.params[key]
            return (sub.jaxpr, sub.consts) if hasattr(sub, "consts") else (sub, ())
    raise KeyError(f"{eqn.primitive.name}: no sub-jaxpr")


def _gather_indices(operand_shape, indices, dnums, slice_sizes, out_shape, clip: bool):
    """(linear index into the flattened operand of every output element (out_shape), in-bounds
    mask or None): XLA's gather semantics with the index vector in the last dimension."""
    rank_out = len(out_shape)
    offset_dims = tuple(dnums.offset_dims)
    batch_out = [d for d in range(rank_out) if d not in offset_dims]
    collapsed = set(dnums.collapsed_slice_dims)
    op_batch = tuple(getattr(dnums, "operand_batching_dims", ()))
    idx_batch = tuple(getattr(dnums, "start_indices_batching_dims", ()))
    window = [d for d in range(len(operand_shape)) if d not in collapsed and d not in op_batch]
    idx = jnp.asarray(indices).astype(jnp.int32)
    batch_shape = [out_shape[d] if d in batch_out else 1 for d in range(rank_out)]

    def to_out(a):  # an array over the indices' batch dims -> broadcastable to out_shape
        return jnp.reshape(a, batch_shape)

    strides = np.cumprod((list(operand_shape[1:]) + [1])[::-1])[::-1].astype(np.int64)
    linear = jnp.zeros([1] * rank_out, jnp.int32)
    inside = None
    for d, size in enumerate(operand_shape):
        comp = jnp.zeros([1] * rank_out, jnp.int32)
        if d in dnums.start_index_map:
            start = idx[..., list(dnums.start_index_map).index(d)]
            top = int(size) - int(slice_sizes[d])
            if not clip:
                ok = to_out((start >= 0) & (start <= top))
                inside = ok if inside is None else inside & ok
            comp = comp + to_out(jnp.clip(start, 0, top))
        if d in op_batch:
            along = idx_batch[op_batch.index(d)]  # a dimension of the indices' batch shape
            shape = [1] * (idx.ndim - 1)
            shape[along] = idx.shape[along]
            comp = comp + to_out(jnp.broadcast_to(lax.broadcasted_iota(jnp.int32, shape, along), idx.shape[:-1]))
        if d in window:
            od = offset_dims[window.index(d)]
            comp = comp + lax.broadcasted_iota(jnp.int32, [out_shape[od] if k == od else 1 for k in range(rank_out)],
                                               od)
        linear = linear + comp * int(strides[d])
    linear = jnp.broadcast_to(linear, out_shape)
    return linear, (None if inside is None else jnp.broadcast_to(inside, out_shape))


def _clip_mode(mode) -> bool:
    """True for clamped or promised-in-bounds indices, False for fill-or-drop."""
    return "FILL" not in str(mode).upper()


def _flat_gather(eqn, operand, indices):
    p = eqn.params
    out_shape = tuple(eqn.outvars[0].aval.shape)
    clip = _clip_mode(p.get("mode"))
    linear, inside = _gather_indices(operand.shape, indices, p["dimension_numbers"], p["slice_sizes"], out_shape,
                                     clip)
    flat = jnp.reshape(operand, (-1,))
    if flat.shape[0] == 0:
        return jnp.zeros(out_shape, operand.dtype)
    got = jnp.take(flat, jnp.reshape(linear, (-1,)), mode="clip").reshape(out_shape)
    if inside is not None:
        fill = p.get("fill_value")
        if fill is None:
            fill = np.nan if jnp.issubdtype(operand.dtype, jnp.inexact) else (
                False if operand.dtype == jnp.bool_ else np.iinfo(operand.dtype).min)
        got = jnp.where(inside, got, jnp.asarray(fill, operand.dtype))
    return got


def _flat_scatter(eqn, operand, indices, updates, add: bool):
    p = eqn.params
    dn = p["dimension_numbers"]
    from types import SimpleNamespace

    # a scatter is a gather run backwards: the updates' window dims are the gather's offset dims
    gdn = SimpleNamespace(offset_dims=dn.update_window_dims, collapsed_slice_dims=dn.inserted_window_dims,
                          start_index_map=dn.scatter_dims_to_operand_dims,
                          operand_batching_dims=getattr(dn, "operand_batching_dims", ()),
                          start_indices_batching_dims=getattr(dn, "scatter_indices_batching_dims", ()))
    window = [d for d in range(operand.ndim) if d not in set(gdn.collapsed_slice_dims)
              and d not in set(gdn.operand_batching_dims)]
    sizes = [1] * operand.ndim
    for k, d in enumerate(window):
        sizes[d] = updates.shape[dn.update_window_dims[k]]
    clip = _clip_mode(p.get("mode"))
    linear, inside = _gather_indices(operand.shape, indices, gdn, sizes, tuple(updates.shape), clip)
    n = int(np.prod(operand.shape))
    target = jnp.reshape(linear, (-1,))
    if inside is not None:  # dropped updates go to one extra element, sliced off
        target = jnp.where(jnp.reshape(inside, (-1,)), target, n)
    flat = jnp.concatenate([jnp.reshape(operand, (-1,)), jnp.zeros((1,), operand.dtype)])
    vals = jnp.reshape(updates, (-1,))
    flat = flat.at[target].add(vals) if add else flat.at[target].set(vals)
    return jnp.reshape(flat[:n], operand.shape)


def _or_reduce(x, init, dims):
    """Bitwise OR of an integer array over ``dims``: per bit, a boolean any, shifted back."""
    bits = np.iinfo(x.dtype).bits
    out = jnp.zeros([s for k, s in enumerate(x.shape) if k not in dims], x.dtype)
    for b in range(bits):
        bit = ((x >> jnp.asarray(b, x.dtype)) & jnp.asarray(1, x.dtype)).astype(bool)
        out = out | (jnp.any(bit, axis=tuple(dims)).astype(x.dtype) << jnp.asarray(b, x.dtype))
    return out | init


def _is_or(closed) -> bool:
    j = closed.jaxpr if hasattr(closed, "jaxpr") else closed
    return len(j.eqns) == 1 and j.eqns[0].primitive.name == "or"


def _rewrite_closed(closed, used: set):
    """A closed jaxpr with the same signature, its body rewritten (loop and branch bodies)."""
    return jax.make_jaxpr(lambda *a: _interpret(closed.jaxpr, closed.consts, a, used))(*closed.in_avals)


def _rewrite_eqn(eqn, ins: list, used: set):
    name = eqn.primitive.name
    if name in _INLINE:
        jaxpr, consts = _sub_jaxpr(eqn)
        outs = _interpret(jaxpr, consts, ins, used)
        return outs if eqn.primitive.multiple_results else outs[0]
    if name in _COMPARE:
        used.add(name)
        return _COMPARE[name](*ins)
    if name == "concatenate" and any(0 in x.shape for x in ins):
        used.add("concatenate_empty")
        kept = [x for x in ins if 0 not in x.shape]
        if not kept:
            return jnp.zeros(eqn.outvars[0].aval.shape, eqn.outvars[0].aval.dtype)
        return kept[0] if len(kept) == 1 else lax.concatenate(kept, eqn.params["dimension"])
    if name == "stack":
        used.add(name)
        axis = eqn.params["axis"]
        return lax.concatenate([lax.expand_dims(x, (axis,)) for x in ins], axis)
    if name == "reduce" and len(ins) == 2 and _is_or(eqn.params["jaxpr"]) \
            and jnp.issubdtype(ins[0].dtype, jnp.integer):
        used.add("reduce_or_int")
        return [_or_reduce(ins[0], ins[1], tuple(eqn.params["dimensions"]))]
    if name == "gather":
        used.add(name)
        return _flat_gather(eqn, *ins)
    if name in ("scatter", "scatter-add") and len(ins) == 3:
        used.add(name)
        return _flat_scatter(eqn, *ins, add=name == "scatter-add")
    if name == "scan":
        return eqn.primitive.bind(*ins, **{**eqn.params, "jaxpr": _rewrite_closed(eqn.params["jaxpr"], used)})
    if name == "while":
        return eqn.primitive.bind(*ins, **{**eqn.params, "cond_jaxpr": _rewrite_closed(eqn.params["cond_jaxpr"], used),
                                           "body_jaxpr": _rewrite_closed(eqn.params["body_jaxpr"], used)})
    if name == "cond":
        return eqn.primitive.bind(*ins, **{**eqn.params,
                                           "branches": tuple(_rewrite_closed(b, used) for b in eqn.params["branches"])})
    return eqn.primitive.bind(*ins, **eqn.params)


def _interpret(jaxpr, consts, args, used: set) -> list:
    """Evaluate ``jaxpr`` on ``args`` (under a trace: the rewritten program is what is traced)."""
    from jax.extend import core as jcore

    env = {}

    def read(v):
        return v.val if isinstance(v, jcore.Literal) else env[v]

    for v, c in zip(jaxpr.constvars, consts):
        env[v] = c
    for v, a in zip(jaxpr.invars, args):
        env[v] = a
    for eqn in jaxpr.eqns:
        outs = _rewrite_eqn(eqn, [read(v) for v in eqn.invars], used)
        if not eqn.primitive.multiple_results:
            outs = [outs]
        for v, o in zip(eqn.outvars, outs):
            env[v] = o
    return [read(v) for v in jaxpr.outvars]


def lowerable_jaxpr(fn: Callable, *args) -> tuple:
    """(closed jaxpr of ``fn`` at ``args``'s shapes rewritten for ``jax2onnx``, the names of
    ``HAND_WRITTEN`` operations it needed, the flat arguments' pytree)."""
    leaves, treedef = jax.tree_util.tree_flatten(args)
    leaves = [jnp.asarray(x) for x in leaves]

    def flat(*xs):
        return fn(*jax.tree_util.tree_unflatten(treedef, list(xs)))

    traced = jax.make_jaxpr(flat)(*leaves)
    if len(traced.jaxpr.outvars) != 1:
        raise ValueError(f"an exported evaluator returns one array, this one returns {len(traced.jaxpr.outvars)}")
    used: set = set()
    rewritten = jax.make_jaxpr(lambda *xs: _interpret(traced.jaxpr, traced.consts, xs, used))(*leaves)
    return rewritten, sorted(used), treedef


def input_names(*args) -> list[str]:
    """ONNX input names of the flattened arguments: ``inputs.position``, ``lighting.intensity``, ...
    (the first argument is ``inputs``, the second ``lighting``)."""
    out = []
    for path, _ in jax.tree_util.tree_leaves_with_path(args):
        head = ("inputs", "lighting")[path[0].idx] if isinstance(path[0], jax.tree_util.SequenceKey) else str(path[0])
        rest = [getattr(k, "name", None) or getattr(k, "key", None) or str(getattr(k, "idx", k)) for k in path[1:]]
        out.append(".".join([head] + [str(r) for r in rest]))
    return out


@contextlib.contextmanager
def _linear_output_check():
    """``jax2onnx`` checks, after lowering each equation, that its outputs are produced by some
    node, by scanning every node built so far: quadratic in the graph's size (most of a large
    evaluator's conversion time). The same check looking at the newest nodes first (they made the
    outputs) stops at once; the answer is the same."""
    try:
        from jax2onnx.converter import output_binding as ob
    except ImportError:  # another layout of jax2onnx: its own check
        yield
        return
    original = getattr(ob, "_value_is_graph_connected", None)
    matches = getattr(ob, "_value_matches_reference", None)
    if original is None or matches is None:
        yield
        return

    def connected(ctx, value) -> bool:
        if any(matches(v, value) for v in ctx.builder.inputs):
            return True
        producer = value.producer() if hasattr(value, "producer") else None
        if producer is not None:  # made by a node: is that node (or one of its name) in the graph?
            nodes = ctx.builder.nodes
            try:
                newest_first = reversed(nodes)
            except TypeError:
                newest_first = nodes
            for node in newest_first:
                if node is producer or any(matches(output, value) for output in node.outputs):
                    return True
        return any(matches(v, value) for v in ctx.builder.initializers) or original(ctx, value)

    ob._value_is_graph_connected = connected
    try:
        yield
    finally:
        ob._value_is_graph_connected = original


def to_onnx(fn: Callable, *args, opset: int = 21, double: bool = False):
    """``(onnx.ModelProto, hand-written operation names)`` of ``fn`` at ``args``'s shapes: inputs
    named by ``input_names``, one output ``radiance``. ``double``: float64 tensors (trace ``fn``
    under ``jax.enable_x64`` with float64 params and arguments): a check that the graph computes
    the same function, free of float32 rounding."""
    from jax2onnx import to_onnx as j2o

    closed, used, _ = lowerable_jaxpr(fn, *args)

    def run(*xs):
        return jax.core.eval_jaxpr(closed.jaxpr, closed.consts, *xs)[0]

    leaves = [np.asarray(x) for x in jax.tree_util.tree_leaves(args)]
    quiet = logging.getLogger("onnx_ir")  # one warning per untyped intermediate value, none of them errors
    level = quiet.level
    quiet.setLevel(logging.ERROR)
    try:
        with _linear_output_check():
            model = j2o(run, [jax.ShapeDtypeStruct(x.shape, x.dtype) for x in leaves], model_name="jprt_evaluator",
                        opset=opset, input_names=input_names(*args), output_names=["radiance"],
                        enable_double_precision=bool(double))
    finally:
        quiet.setLevel(level)
    return model, used


def run_onnx(path_or_model, feeds: dict, *, threads: int | None = None):
    """The ONNX model's output for ``feeds`` ({input name: array}) on onnxruntime's CPU provider."""
    import onnxruntime as ort

    options = ort.SessionOptions()
    options.log_severity_level = 3  # errors only: the converter leaves unused initialisers it warns about
    if threads:
        options.intra_op_num_threads = int(threads)
    data = path_or_model if isinstance(path_or_model, (str, os.PathLike)) else path_or_model.SerializeToString()
    session = ort.InferenceSession(data, options, providers=["CPUExecutionProvider"])
    return session.run(None, feeds)[0]


def export_evaluator(evaluate: Callable, inputs, lighting, out: str) -> tuple[dict, dict]:
    """Write ``evaluator.onnx`` (``evaluate`` at the shapes of ``inputs`` and ``lighting``) and the
    reference frame (``reference_inputs.npz`` keyed by ONNX input name, ``reference_output.npy``,
    the JAX evaluator's output) to ``out``; returns (the manifest's ``onnx`` entry, ``files``
    entries)."""
    from jprt import io

    model, used = to_onnx(evaluate, inputs, lighting)
    names = input_names(inputs, lighting)
    leaves = [np.asarray(x) for x in jax.tree_util.tree_leaves((inputs, lighting))]
    io.atomic_write_bytes(os.path.join(out, "evaluator.onnx"), model.SerializeToString())
    want = np.asarray(jax.jit(evaluate)(inputs, lighting), np.float32)
    with io.atomic_path(os.path.join(out, "reference_inputs.npz"), suffix=".npz") as tmp:
        with open(tmp, "wb") as f:
            np.savez(f, **dict(zip(names, leaves)))
    with io.atomic_path(os.path.join(out, "reference_output.npy"), suffix=".npy") as tmp:
        with open(tmp, "wb") as f:
            np.save(f, want)
    entry = {"file": "evaluator.onnx", "opset": int(model.opset_import[0].version),
             "inputs": [{"name": n, "shape": list(x.shape), "dtype": x.dtype.name} for n, x in zip(names, leaves)],
             "outputs": [{"name": "radiance", "shape": list(want.shape), "dtype": "float32"}],
             "hand_written": {k: HAND_WRITTEN[k] for k in used}}
    files = {"evaluator.onnx": {"format": f"ONNX (opset {entry['opset']})", "holds": "the evaluator at fixed shapes: "
                                "G-buffer attributes and lighting in, indirect radiance (H, W, 3) out"},
             "reference_inputs.npz": {"format": "NumPy .npz", "holds": "the view's inputs, keyed by ONNX input name"},
             "reference_output.npy": {"format": "NumPy .npy float32", "holds": "the JAX evaluator's output for "
                                      "reference_inputs.npz (what evaluator.onnx should reproduce)"}}
    return entry, files
