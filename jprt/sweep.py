"""Sweeps: grids of config overrides over one experiment, every point one ``jprt.runner`` run.

    jprt sweep experiments/rrf_cornell.py --preset small --grid model.hidden=[[12,6],[20,10]] \\
        --grid tree.threshold=[0.05,0.1]
    jprt sweep experiments/sweeps/wavelet_k.py            # a sweep file: SWEEP = {...}
    jprt sweep ... --select "psnr_indirect>=30" --minimize frame_ms
    jprt sweep ... --ray                       # points as Ray tasks (or JPRT_RAY_ADDRESS=auto|host:port)

Every point is the experiment's config with the point's overrides merged in (strictly: an unknown
key is an error before anything runs), run in its own report folder keyed by its config hash under
``<sweep folder>/points/``. A re-run skips the points whose ``summary.json`` exists (nothing is
rendered or trained for them) and re-runs interrupted ones (their datasets come back from
``jprt.cache``); a point that raises is recorded with its error (``error.txt`` in its folder) and
the sweep goes on. Output in the sweep folder (``output.dir/sweep_<hash of the grid>``):

* ``sweep.json``: the grid, one row per point (the varied keys, ``status``, the common summary
  of ``jprt.runner.SUMMARY_SCHEMA``), the Pareto fronts;
* ``sweep.csv``: the same rows as a table;
* ``pareto_<x>.png``: indirect RMSE against ``frame_ms``, ``model_bytes`` and ``train_s``, the
  front marked; the frame-time plot also draws Mitsuba's own curve (RMSE against measured render
  time over the spp of each point's equal-error search), so the reader sees where a model beats
  path tracing.

``select(rows, "psnr_indirect>=30", minimize="frame_ms")`` is "model only what the scene needs":
the cheapest point meeting every constraint, written by ``--select`` as ``selected.json`` (a
config that ``jprt run experiment --config selected.json`` runs); no point meeting a constraint is
an error that names the best value reached.
"""

from __future__ import annotations

import csv
import itertools
import json
import math
import operator
import os
import re
import sys
import time
import traceback
from types import ModuleType
from typing import Any, Callable, Mapping, Sequence

from jprt import io
from jprt.config import ConfigError, apply_overrides, merge, parse_value
from jprt.hashing import config_hash, stable_hash
from jprt.runner import SUMMARY_SCHEMA

__all__ = ["parse_grid", "grid_points", "point_config", "run_sweep", "pareto_front", "parse_constraint", "select",
           "selected_config", "is_sweep_file", "load_sweep_file", "mitsuba_curve", "ROW_KEYS"]

#: The summary keys every row of a sweep carries (the common schema; ``extra`` stays in the points' folders).
ROW_KEYS = tuple(k for k in SUMMARY_SCHEMA if k not in ("extra", "scene"))
#: x axes of the Pareto plots (all minimised, like the error on the y axis).
PARETO_AXES = ("frame_ms", "model_bytes", "train_s")


def parse_grid(items: Sequence[str]) -> dict[str, list]:
    """``["model.hidden=[[12,6],[20,10]]", "render.k=[16,32]"]`` -> {key: [values]} (in order)."""
    grid: dict[str, list] = {}
    for item in items:
        if "=" not in item:
            raise ConfigError(f"grid item {item!r} is not of the form key.path=[v1, v2, ...]")
        key, text = (part.strip() for part in item.split("=", 1))
        values = parse_value(text)
        if not isinstance(values, list) or not values:
            raise ConfigError(f"grid {key!r} needs a non-empty list of values, got {text!r}")
        if key in grid:
            raise ConfigError(f"grid key {key!r} given twice")
        grid[key] = values
    return grid


def grid_points(grid: Mapping[str, Sequence]) -> list[dict[str, Any]]:
    """Every combination of the grid's values, the first key varying slowest."""
    keys = list(grid)
    return [dict(zip(keys, combo)) for combo in itertools.product(*(grid[k] for k in keys))]


def point_config(config: Mapping, point: Mapping[str, Any]) -> dict:
    """``config`` with the point's dotted overrides (strict: an unknown key raises ConfigError)."""
    return apply_overrides(config, [f"{k}={json.dumps(v)}" for k, v in point.items()])


def _row(point: dict, status: str, summary: dict | None, folder: str, error: str | None = None) -> dict:
    row = {**point, "status": status, "folder": folder, "error": error}
    row.update({k: (summary or {}).get(k) for k in ROW_KEYS})
    row["pathtrace_curve"] = mitsuba_curve(summary) if summary else []
    return row


def mitsuba_curve(summary: Mapping) -> list[dict]:
    """Mitsuba's (spp, ms, rmse) points of a run's equal-error search, each spp timed
    (``extra.pathtrace_curve``); [] for a run without a path tracer."""
    return list(summary.get("extra", {}).get("pathtrace_curve") or [])


def _attempt(module: ModuleType, cfg: dict, folder: str, run: Callable) -> tuple[str, dict | None, str | None]:
    """One point: ("done", summary, None), or ("failed", None, error) with the traceback in
    ``folder/error.txt`` (an error of the point never stops the sweep)."""
    try:
        return "done", run(module, cfg), None
    except Exception as e:
        os.makedirs(folder, exist_ok=True)
        with open(os.path.join(folder, "error.txt"), "w") as f:
            f.write(traceback.format_exc())
        return "failed", None, f"{type(e).__name__}: {e}"


def _point_task(experiment_path: str, cfg: dict, folder: str) -> tuple[str, dict | None, str | None]:
    """A sweep point in a Ray worker: load the experiment file there and run the point."""
    from jprt.experiment import load_experiment
    from jprt.runner import run

    return _attempt(load_experiment(experiment_path), cfg, folder, run)


def run_sweep(module: ModuleType, config: Mapping, grid: Mapping[str, Sequence], *, run: Callable | None = None,
              progress: bool | None = None, label: str = "", ray: bool | None = None, num_cpus: float | None = None,
              num_gpus: float | None = None) -> dict:
    """Run every point of ``grid`` over experiment ``module`` at ``config`` (its resolved CONFIG);
    returns the sweep record (also written as sweep.json / sweep.csv / pareto_*.png).

    ``run(module, config) -> summary`` runs one point in-process (default ``jprt.runner.run``).
    ``ray`` (default: whether ``JPRT_RAY_ADDRESS`` is set) runs the points as Ray tasks of
    ``num_cpus`` / ``num_gpus`` each (default: the config's optional ``resources`` section,
    ``{"cpus": 2, "gpus": 0}``, else 1 CPU; ``jprt.distributed``; the experiment is re-loaded from its
    file in the worker); a worker that dies is retried and its point is still one row.
    """
    from jprt import distributed
    from jprt.progress import bar as progress_bar
    from jprt.runner import run as run_point

    run = run or run_point
    points = grid_points(grid)
    configs = [point_config(config, p) for p in points]  # every point checked before anything runs
    folder = os.path.abspath(os.path.join(config["output"]["dir"], "sweep_" + stable_hash(
        {"base": config_hash(config), "grid": {k: list(v) for k, v in grid.items()}})))
    os.makedirs(folder, exist_ok=True)
    rows: list = [None] * len(points)
    counts = {"done": 0, "cached": 0, "failed": 0}
    todo = []
    for i, (point, cfg) in enumerate(zip(points, configs)):
        cfg = merge(cfg, {"output": {"dir": os.path.join(folder, "points")}})
        point_folder = os.path.join(folder, "points", config_hash(merge(module.CONFIG, cfg)))
        summary_path = os.path.join(point_folder, "summary.json")
        if os.path.isfile(summary_path):
            with open(summary_path) as f:
                rows[i] = _row(point, "cached", json.load(f), point_folder)
            counts["cached"] += 1
        else:
            todo.append((i, cfg, point_folder))
    bar = progress_bar(total=len(points), progress=progress, initial=counts["cached"], desc=f"sweep {label}".strip(),
                       unit="point")

    def finish(j: int, result: tuple) -> None:
        i, _, point_folder = todo[j]
        status, summary, error = result
        rows[i] = _row(points[i], status, summary, point_folder, error)
        counts[status] += 1
        if error:
            print(f"jprt sweep: point {points[i]} failed: {error}", file=sys.stderr)
        bar.update(1)
        bar.set_postfix(counts)

    if todo and distributed.requested(ray):
        path = getattr(module, "__file__", None)
        if not path:
            raise ValueError("a sweep on Ray needs an experiment file (the workers load it by path)")
        need = config.get("resources", {})
        num_cpus = float(need.get("cpus", 1) if num_cpus is None else num_cpus)
        num_gpus = float(need.get("gpus", 0) if num_gpus is None else num_gpus)
        distributed.map_tasks(_point_task, [(os.path.abspath(path), cfg, f) for _, cfg, f in todo],
                              num_cpus=num_cpus, num_gpus=num_gpus, on_done=finish)
    else:
        for j, (i, cfg, point_folder) in enumerate(todo):
            finish(j, _attempt(module, cfg, point_folder, run))
    bar.close()
    ok = [i for i, r in enumerate(rows) if r["status"] != "failed"]
    fronts = {x: [i for i, on in zip(ok, pareto_front([rows[i][x] for i in ok], [rows[i]["indirect_rmse"] for i in ok]))
                  if on] for x in PARETO_AXES}
    record = {"experiment": getattr(module, "__file__", None), "base_config_hash": config_hash(config),
              "grid": {k: list(v) for k, v in grid.items()}, "counts": counts, "rows": rows, "pareto": fronts,
              "folder": folder, "date": time.strftime("%Y-%m-%dT%H:%M:%S%z")}
    io.write_json(os.path.join(folder, "sweep.json"), record)
    _write_csv(os.path.join(folder, "sweep.csv"), rows, list(grid))
    for x in PARETO_AXES:
        _plot(os.path.join(folder, f"pareto_{x}.png"), rows, x, fronts[x], list(grid))
    print(f"sweep of {len(points)} points ({counts}) written to {folder}")
    return record


def _write_csv(path: str, rows: list[dict], keys: list[str]) -> None:
    columns = keys + ["status"] + list(ROW_KEYS) + ["folder", "error"]
    with io.atomic_path(path, suffix=".csv") as tmp:
        with open(tmp, "w", newline="") as f:
            writer = csv.writer(f)
            writer.writerow(columns)
            for r in rows:
                writer.writerow([json.dumps(r.get(c)) if isinstance(r.get(c), (list, dict)) else r.get(c)
                                 for c in columns])


def pareto_front(xs: Sequence, ys: Sequence) -> list[bool]:
    """Which points (x_i, y_i) are on the Pareto front when both are minimised: no other point is
    at least as good in both and strictly better in one. ``None`` / NaN values are never on it."""
    pts = [(float(x), float(y)) if x is not None and y is not None else (math.nan, math.nan) for x, y in zip(xs, ys)]
    out = []
    for i, (x, y) in enumerate(pts):
        if math.isnan(x) or math.isnan(y):
            out.append(False)
            continue
        out.append(not any(j != i and not math.isnan(a) and not math.isnan(b) and a <= x and b <= y and (a < x or b < y)
                           for j, (a, b) in enumerate(pts)))
    return out


def _plot(path: str, rows: list[dict], x: str, front: list[int], keys: list[str]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    fig, ax = plt.subplots(figsize=(6, 4))
    pts = [(i, r[x], r["indirect_rmse"]) for i, r in enumerate(rows) if r["status"] != "failed"
           and r[x] is not None and r["indirect_rmse"] is not None]
    if pts:
        ax.scatter([p[1] for p in pts], [p[2] for p in pts], color="tab:blue", label="sweep points", zorder=2)
        for i, px, py in pts:
            ax.annotate(", ".join(f"{k.split('.')[-1]}={rows[i][k]}" for k in keys), (px, py), fontsize=6,
                        xytext=(3, 3), textcoords="offset points")
        on = sorted((rows[i][x], rows[i]["indirect_rmse"]) for i in front)
        if on:  # the front's points ringed (a front of one point has no line), joined by its staircase
            ax.scatter([p[0] for p in on], [p[1] for p in on], s=120, facecolors="none", edgecolors="tab:red",
                       label="Pareto front", zorder=3)
            ax.step([p[0] for p in on], [p[1] for p in on], where="post", color="tab:red")
    if x == "frame_ms":
        curves = [r["pathtrace_curve"] for r in rows if r.get("pathtrace_curve")]
        if curves:  # every point path traces the same held-out set: one Mitsuba curve
            c = max(curves, key=len)
            ax.plot([p["ms"] for p in c], [p["rmse"] for p in c], "k--o", markersize=3,
                    label="Mitsuba path tracing (spp 1, 2, 4, ...)")
    ax.set_xscale("log")
    ax.set_yscale("log")
    for axis in (ax.xaxis, ax.yaxis):  # labelled ticks at 1, 2, 5 x 10^k (all minor labels collide)
        axis.set_major_locator(matplotlib.ticker.LogLocator(subs=(1.0, 2.0, 5.0)))
        axis.set_major_formatter(matplotlib.ticker.FuncFormatter(lambda v, _: f"{v:g}"))
        axis.set_minor_formatter(matplotlib.ticker.NullFormatter())
    ax.set_xlabel(x)
    ax.set_ylabel("indirect RMSE (held-out)")
    ax.grid(True, alpha=0.3)
    if ax.get_legend_handles_labels()[0]:  # a sweep whose every point failed has nothing to label
        ax.legend(fontsize=7)
    fig.tight_layout()
    with io.atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=100, format="png")
    plt.close(fig)


_OPS = {">=": operator.ge, "<=": operator.le, ">": operator.gt, "<": operator.lt, "==": operator.eq}


def parse_constraint(text: str) -> tuple[str, str, float]:
    """``"psnr_indirect>=30"`` -> ("psnr_indirect", ">=", 30.0)."""
    m = re.fullmatch(r"\s*([A-Za-z_][\w.]*)\s*(>=|<=|==|>|<)\s*([-+0-9.eE]+|inf|-inf)\s*", text)
    if not m:
        raise ValueError(f"constraint {text!r} is not of the form key>=value (ops: >= <= > < ==)")
    return m.group(1), m.group(2), float(m.group(3))


def select(rows: Sequence[Mapping], constraints: Sequence[str] | str, minimize: str) -> Mapping:
    """The row meeting every constraint with the smallest ``minimize`` (ties: the first row).

    Raises ValueError when no row meets them, naming the best value reached for each constraint
    (over the rows with a value for it) so the user sees how far the target is.
    """
    if isinstance(constraints, str):
        constraints = [c for c in constraints.split(",") if c.strip()]
    parsed = [parse_constraint(c) for c in constraints]
    usable = [r for r in rows if r.get("status", "done") != "failed" and r.get(minimize) is not None]
    ok = [r for r in usable if all(r.get(k) is not None and _OPS[op](float(r[k]), v) for k, op, v in parsed)]
    if not ok:
        best = []
        for k, op, v in parsed:
            values = [float(r[k]) for r in usable if r.get(k) is not None]
            if not values:
                best.append(f"{k}: no point has a value")
                continue
            reach = max(values) if op in (">=", ">") else min(values) if op in ("<=", "<") else \
                min(values, key=lambda a: abs(a - v))
            best.append(f"best {k} reached = {reach:.6g} (target {op} {v:g})")
        raise ValueError(f"no sweep point meets {', '.join(''.join(map(str, c)) for c in parsed)}; "
                         + "; ".join(best))
    return min(ok, key=lambda r: float(r[minimize]))


def selected_config(base: Mapping, row: Mapping, grid_keys: Sequence[str]) -> dict:
    """The full config of a selected row (base config + the row's grid values), for ``jprt run --config``."""
    return point_config(base, {k: row[k] for k in grid_keys})


def is_sweep_file(path: str) -> bool:
    """Whether the Python file at ``path`` assigns ``SWEEP`` at module level (read, not imported)."""
    import ast

    with open(path) as f:
        tree = ast.parse(f.read(), path)
    return any(isinstance(node, ast.Assign) and any(isinstance(t, ast.Name) and t.id == "SWEEP" for t in node.targets)
               for node in tree.body)


def load_sweep_file(path: str) -> dict:
    """A sweep file's ``SWEEP``: {"experiment": path (relative to the file), "preset": name or None,
    "grid": {key: [values]}, "set": ["key=value", ...]}."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("jprt_sweep_" + os.path.splitext(os.path.basename(path))[0], path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    sweep = getattr(module, "SWEEP", None)
    if not isinstance(sweep, dict) or "experiment" not in sweep or "grid" not in sweep:
        raise ValueError(f"{path} must define SWEEP = {{'experiment': ..., 'grid': {{...}}}}")
    unknown = set(sweep) - {"experiment", "preset", "grid", "set"}
    if unknown:
        raise ConfigError(f"{path}: unknown SWEEP keys {sorted(unknown)} (experiment, preset, grid, set)")
    out = dict(sweep)
    out["experiment"] = os.path.normpath(os.path.join(os.path.dirname(os.path.abspath(path)), sweep["experiment"]))
    return out
