"""The method contract every system implements (DESIGN.md, "Contracts"), so that the runner,
sweeps, the cross-method report and the contract tests treat them alike.

A method is a ``Method`` NamedTuple of plain functions::

    m = REGISTRY["datadriven"]
    config = m.resolve(m.presets["test"])            # strict: unknown keys raise ConfigError
    dataset = m.make_dataset(config["scene"], config)  # renders via jprt.render, cached by jprt.cache
    result = m.fit(dataset, config)                    # FitResult(params: arrays only, info: dict)
    evaluate = m.evaluator(result.params, config)      # pure: (inputs, lighting) -> (H, W, 3)
    inputs, lighting = m.example(dataset, config)      # a held-out input / lighting pair
    image = jax.jit(evaluate)(inputs, lighting)
    check = m.self_check(dataset, result, config)      # held-out lights / maps of its own renders

* ``inputs`` is a G-buffer-like pytree of arrays (``jprt.inputs.GBuffer`` or a dict of its
  fields), ``lighting`` the method's lighting pytree (``Method.lighting``, a ``jprt.inputs``
  type). Neither needs Mitsuba.
* The evaluator is a plain function with no attributes and no hidden state: it jits, vmaps over
  a batch of lightings and exports with ``jax.export``. What used to hang on it (lightmaps,
  transfer coefficients) are module functions of the method's ``model.py``.
* ``fit`` returns ``FitResult(params, info)`` for every method: ``params`` a pytree of arrays
  (nothing else: it is checkpointed and exported), ``info`` a plain dict (timings, losses, choices
  made during the fit).
* ``self_check`` (optional, ``data.self_check`` of the package): the fit scored on held-out
  lights or maps of the method's own training renders, without a path-traced reference, scored
  as the references are (``jprt.eval.object_scores``), with a one-line warning when the fit is
  worse than predicting zero on an object or far worse than on its training items
  (``jprt.methods.selfcheck``).
* The task adapter (optional): ``task_lightings``, the kinds of lighting ("point",
  "environment") under which the method can be compared with the others on a shared scene and
  camera (the atlas of methods), and ``task_inputs`` / ``task_lighting``, which turn such a
  camera view and lighting into the evaluator's arguments::

      inputs = m.task_inputs(handle, dataset, camera)                  # handle: a SceneHandle
      lighting = m.task_lighting(handle, dataset, params, config, task_lighting)
      image = m.evaluator(params, config)(inputs, lighting)

* The viewer adapter (optional): ``view_lightings`` (what ``jprt view`` relights with; the
  task lightings unless the package says otherwise), ``predicts`` ("indirect", or "direct" for
  a method whose evaluator returns the environment reflected once) and ``view_environments``.
* Progress output (bars, messages on stderr) of ``fit`` and ``make_dataset`` follows one policy,
  ``jprt.progress``: a call's ``progress=`` True / False where it takes one, else
  ``$JPRT_PROGRESS``, else shown when stderr is a terminal.
"""

from __future__ import annotations

import functools
from typing import Any, Callable, Mapping, NamedTuple

import jax
import numpy as np

from jprt.config import ConfigError, merge

__all__ = ["Method", "FitResult", "LIGHTING_KINDS", "PREDICTS", "resolve", "check_params", "model_bytes"]

#: The kinds of task and view lighting: point lights (``PointLights``) and environments
#: (``CubeMap``, an environment map as a cube map).
LIGHTING_KINDS = ("point", "environment")

#: What an evaluator can return: indirect light, or direct light (the environment reflected once).
PREDICTS = ("indirect", "direct")


class FitResult(NamedTuple):
    """What ``Method.fit`` returns.

    Fields:
      params: pytree of arrays (the evaluator's only state).
      info: plain dict of side results (timings, losses, chosen hyperparameters, warnings).
    """

    params: Any
    info: dict


class Method(NamedTuple):
    """One published system (or baseline) behind the common contract (module docstring).

    Fields:
      name: registry key.
      paper: the citation the implementation follows.
      lighting: the ``jprt.inputs`` lighting type the evaluator takes.
      default_config: the method's config dict; ``resolve`` merges overrides into it strictly.
      presets: named override dicts; every method has ``"test"`` (seconds, for the contract tests).
      make_dataset: ``(scene, config) -> dataset`` (renders with Mitsuba, cached by ``jprt.cache``).
      fit: ``(dataset, config) -> FitResult``.
      evaluator: ``(params, config) -> fn(inputs, lighting) -> (H, W, 3)`` indirect radiance.
      example: ``(dataset, config) -> (inputs, lighting)`` a held-out pair of concrete arrays, the
        shapes the evaluator is timed and exported at.
      frame_flops: optional ``(params, config, inputs, lighting) -> float``: the FLOPs one
        evaluator call needs by the method's own count (``model.frame_flops`` when the package
        has one), where it counts what XLA's cannot (the work a data-dependent traversal reaches);
        None: the runner reports XLA's count (``jprt.eval.xla_flops``, every loop iteration counted).
      self_check: optional ``(dataset, result, config) -> dict`` (``data.self_check`` when the
        package has one): the fit scored on held-out lights or maps of its own training renders,
        {"rel_rmse", "per_object", "train_rel_rmse", "held_out", "warning"}
        (``jprt.methods.selfcheck``); None: the method has no self-check.
      task_lightings: the kinds of task lighting the method takes, a subset of ("point",
        "environment") (``data.TASK_LIGHTINGS``); () for a method baked for its scene's own
        lights, which takes part in no shared task.
      task_inputs: ``(handle, dataset, camera) -> inputs``, the evaluator's inputs for a camera
        view of the scene of ``handle`` (a ``jprt.render.scenes.SceneHandle``)
        (``data.task_inputs``); None when the method has no camera view.
      task_lighting: ``(handle, dataset, params, config, lighting) -> lighting`` of
        ``Method.lighting``, from a task lighting (``PointLights`` for "point", ``CubeMap`` for
        "environment") (``data.task_lighting``).
      view_lightings: the lighting kinds ``jprt view`` relights the method with
        (``data.VIEW_LIGHTINGS``, else ``task_lightings``); () shows its texture atlas under its
        bake's lighting times an RGB factor.
      predicts: what the evaluator returns, "indirect" (every method but one) or "direct" (the
        environment reflected once) (``data.PREDICTS``).
      view_environments: optional ``(dataset, config) -> {name: (6, n, n, 3) cube map}``, the
        environments the viewer offers (``data.view_environments``); None: the run's own maps.
      gradient_evaluator: optional, ``evaluator``'s signature and image by a program that
        reverse-mode differentiation (``jax.grad`` in the lighting) goes through, where
        ``evaluator``'s does not (``model.gradient_evaluator``; RRF's tiled renderer loops a
        data-dependent number of times); None: ``evaluator`` is one. ``jprt.design`` uses it.
      frame_roofline: optional ``(params, config, inputs, lighting, frame_ms, *, repeats,
        bandwidth_gbs) -> {"roofline", "detail"[, "frame_flops"]}``: the timed frame against what
        bounds it by the method's own model (``model.frame_roofline``; RRF: its networks' products
        timed alone), where the matmul peak and XLA's counts are the wrong roof; its "frame_flops",
        where given, is ``frame_flops``'s count, found on the way (so the report does not count
        twice); None: ``jprt.eval.roofline``. ``frame_report`` chooses.
    """

    name: str
    paper: str
    lighting: type
    default_config: dict
    presets: dict
    make_dataset: Callable
    fit: Callable
    evaluator: Callable
    example: Callable
    frame_flops: Callable | None = None
    self_check: Callable | None = None
    task_lightings: tuple = ()
    task_inputs: Callable | None = None
    task_lighting: Callable | None = None
    view_lightings: tuple = ()
    predicts: str = "indirect"
    view_environments: Callable | None = None
    gradient_evaluator: Callable | None = None
    frame_roofline: Callable | None = None

    def frame_report(self, params, config: dict, jitted: Callable, inputs, lighting, frame_ms: float, *,
                     peak_gflops: float | None = None, bandwidth_gbs: float | None = None, repeats: int = 10) -> dict:
        """The timed frame (``jitted(inputs, lighting)`` taking ``frame_ms``) against the machine:
        {"frame_flops" (``frame_flops``'s count where the method has one, else XLA's),
        "frame_flops_source" ("method" or "xla"), "matmul_peak_gflops" (``peak_gflops``, measured
        now unless given), "flops_fraction_of_peak", "roofline" (``frame_roofline``'s where the
        method has one, else ``jprt.eval.roofline``'s, whose "roof" is "matmul"), "roofline_matmul"
        (``jprt.eval.roofline``'s, kept beside the method's own; None without one),
        "roofline_detail" (the method's own counts; None without)}. Both rooflines share one
        bandwidth (``bandwidth_gbs``, the triad measured now unless given)."""
        from jprt import eval as jeval

        own, flops = None, None
        if self.frame_roofline is not None:
            bandwidth_gbs = jeval.stream_bandwidth_gbs() if bandwidth_gbs is None else float(bandwidth_gbs)
            own = self.frame_roofline(params, config, inputs, lighting, frame_ms, repeats=repeats,
                                      bandwidth_gbs=bandwidth_gbs)
            flops = own.get("frame_flops")
        if flops is None and self.frame_flops:
            flops = self.frame_flops(params, config, inputs, lighting)
        generic = jeval.roofline(jitted, inputs, lighting, frame_ms=frame_ms, flops=flops, peak_gflops=peak_gflops,
                                 bandwidth_gbs=bandwidth_gbs)
        generic["roofline"]["roof"] = "matmul"
        out = {"frame_flops": generic["frame_flops"], "frame_flops_source": "method" if flops is not None else "xla",
               "matmul_peak_gflops": generic["matmul_peak_gflops"],
               "flops_fraction_of_peak": generic["flops_fraction_of_peak"], "roofline": generic["roofline"],
               "roofline_matmul": None, "roofline_detail": None}
        if own is not None:
            out.update(roofline=own["roofline"], roofline_matmul=generic["roofline"], roofline_detail=own["detail"])
        return out

    def resolve(self, config: Mapping | None = None) -> dict:
        """``default_config`` deep-merged with ``config``; an unknown key raises ConfigError."""
        return resolve(self.default_config, config)

    @classmethod
    def of_package(cls, name: str, paper: str, lighting: type, model, data, presets: dict, *,
                   fit: Callable | None = None) -> "Method":
        """The method of a package laid out as DESIGN.md says: ``model.DEFAULT_CONFIG``,
        ``data.make_dataset``, ``model.fit`` (or ``fit``), ``model.evaluator``, ``model.example``;
        ``model.frame_flops``, ``data.self_check`` and the task and viewer adapters
        (``data.TASK_LIGHTINGS``, ``task_inputs``, ``task_lighting``, ``VIEW_LIGHTINGS``,
        ``PREDICTS``, ``view_environments``), ``model.gradient_evaluator`` and ``model.frame_roofline``
        where the package has them.

        Raises TypeError when the package declares lightings (task or view) without both
        adapter functions, or a lighting kind or ``PREDICTS`` value the contract does not know."""
        task_lightings = tuple(getattr(data, "TASK_LIGHTINGS", ()))
        view_lightings = tuple(getattr(data, "VIEW_LIGHTINGS", None) or task_lightings)
        predicts = getattr(data, "PREDICTS", "indirect")
        task_inputs, task_lighting = getattr(data, "task_inputs", None), getattr(data, "task_lighting", None)
        unknown = set(task_lightings + view_lightings) - set(LIGHTING_KINDS)
        if unknown:
            raise TypeError(f"{name}: unknown lighting kinds {sorted(unknown)}; kinds are {list(LIGHTING_KINDS)}")
        if predicts not in PREDICTS:
            raise TypeError(f"{name}: PREDICTS is {predicts!r}, one of {list(PREDICTS)}")
        if (task_lightings or view_lightings) and not (callable(task_inputs) and callable(task_lighting)):
            raise TypeError(f"{name}: lightings {sorted(set(task_lightings + view_lightings))} need data.task_inputs "
                            f"and data.task_lighting")
        return cls(name, paper, lighting, model.DEFAULT_CONFIG, presets, data.make_dataset, fit or model.fit,
                   checked_evaluator(model.evaluator, lighting), model.example, getattr(model, "frame_flops", None),
                   getattr(data, "self_check", None), task_lightings, task_inputs, task_lighting, view_lightings,
                   predicts, getattr(data, "view_environments", None),
                   checked_evaluator(model.gradient_evaluator, lighting) if hasattr(model, "gradient_evaluator")
                   else None, getattr(model, "frame_roofline", None))


def checked_evaluator(evaluator: Callable, lighting_type: type) -> Callable:
    """``evaluator`` whose functions validate concrete arguments once, at the method's entry: a
    lighting of a ``jprt.inputs`` type must be the method's (``lighting_type``) and valid
    (``jprt.inputs.validate_lighting``: shapes, finite, non-negative), a ``GBuffer`` valid
    (``jprt.inputs.validate_gbuffer``). Traced calls (under ``jax.jit``, ``vmap``, export) skip
    the checks, so the timed program is the evaluator's alone; raw arrays where a method accepts
    them pass through to the method's own checks."""
    from jprt import inputs as jin

    @functools.wraps(evaluator)
    def make(params, config=None, **kwargs):
        evaluate = evaluator(params, config, **kwargs)

        @functools.wraps(evaluate)
        def checked(inputs, lighting):
            if not any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree_util.tree_leaves((inputs, lighting))):
                if isinstance(lighting, jin.LIGHTING_TYPES):
                    jin.validate_lighting(lighting, expected=lighting_type)
                if isinstance(inputs, jin.GBuffer):
                    jin.validate_gbuffer(inputs)
            return evaluate(inputs, lighting)

        return checked

    return make


def resolve(default_config: Mapping, config: Mapping | None = None) -> dict:
    """Strict merge of a method config: every key of ``config`` must exist in ``default_config``
    (``ConfigError`` names the nearest valid key). Resolving a resolved config is a no-op."""
    if config is not None and not isinstance(config, Mapping):
        raise ConfigError(f"a method config is a dict, got {type(config).__name__}")
    return merge(default_config, dict(config or {}))


def check_params(params) -> None:
    """Raise TypeError unless every leaf of ``params`` is an array (the FitResult contract)."""
    for path, leaf in jax.tree_util.tree_leaves_with_path(params):
        if not isinstance(leaf, (np.ndarray, jax.Array)):
            raise TypeError(f"params leaf {jax.tree_util.keystr(path)} is {type(leaf).__name__}, not an array")


def model_bytes(params) -> int:
    """Bytes of every array in ``params``."""
    return int(sum(np.asarray(leaf).nbytes for leaf in jax.tree_util.tree_leaves(params)))
