"""Each fit says when it is wrong: the shared part of every method's self-check.

A method's ``data.self_check(dataset, result, config)`` (``Method.self_check``) scores its fit on
held-out lights or maps of its own training renders, with no path-traced camera view, and returns
the dict ``result`` builds here::

    {"rel_rmse": float,             # pooled over every held-out item and object (``scores``)
     "per_object": {name: float},   # relative RMSE per object over the held-out items
     "train_rel_rmse": float | None,  # the same pooled score on (a subset of) the training items
     "held_out": str,               # what was scored
     "warning": str | None}         # ``self_check_warning``'s one line, None when the check is fine

Scoring is ``jprt.eval.object_scores``, as the references of experiments/real_scenes.py are
scored: per object ||p - r|| / ||r|| over its entries of every item (predicting zero scores 1;
an object dark against its items is judged on their scale instead, so it never divides by ~0).
The pooled score is the same function with every labelled entry given one id.

The held-out renders are rendered at the method's own data spp, so a self-check includes their
noise (an upper bound on the error against the truth; at ``test`` preset sample counts it is
mostly noise).

The warning rule (``self_check_warning``), one for every method: an object whose held-out score is
>= 1 (worse than predicting zero), or a pooled held-out score above ``FACTOR`` times the training
score (the training score floored at ``TRAIN_FLOOR``: a fit that reproduces its own noisy renders
to 0.1 % is not expected to predict new ones to 0.3 %). ``result`` emits the line as a
``SelfCheckWarning`` (a ``RuntimeWarning``) as well as returning it, so a caller that only looks at
the return value and one that only watches warnings both see it.
"""

from __future__ import annotations

import math
import warnings
from typing import Mapping, Sequence

import numpy as np

__all__ = ["FACTOR", "TRAIN_FLOOR", "SelfCheckWarning", "scores", "self_check_warning", "result", "KEYS"]

#: A pooled held-out score above FACTOR x max(training score, TRAIN_FLOOR) warns. 3: held-out
#: error within 3x the training error is what a fit that generalises at all shows on these
#: renders (noise of both sets included); beyond it the fit has learnt its training lightings.
FACTOR = 3.0
#: The training score is floored at this before the comparison (a training error near 0 would make
#: any held-out error "far worse"): with FACTOR 3 a held-out score under 0.15 never warns on this rule.
TRAIN_FLOOR = 0.05
#: The keys of a self-check's dict.
KEYS = ("rel_rmse", "per_object", "train_rel_rmse", "held_out", "warning")


class SelfCheckWarning(RuntimeWarning):
    """A method's self-check found its fit untrustworthy (``self_check_warning``)."""


def scores(predictions: Sequence, references: Sequence, object_id, names: Sequence[str]) -> tuple[float, dict]:
    """(pooled relative RMSE, {object name: relative RMSE}) of a set of items (images (H, W, 3) or
    texels (T, 3)) by ``jprt.eval.object_scores``; ``object_id`` one array of the items' leading
    shape or a list of one per item (-1: not scored). The pooled score gives every labelled entry
    the same id (for lit items: ||p - r|| / ||r|| over all of them). NaN and {} when no entry is
    labelled."""
    from jprt.eval import object_scores

    ids = list(object_id) if isinstance(object_id, (list, tuple)) else [object_id] * len(references)
    ids = [np.asarray(i) for i in ids]
    if not any((i >= 0).any() for i in ids):
        return float("nan"), {}
    per = object_scores(predictions, references, ids, list(names))
    pooled = object_scores(predictions, references, [np.where(i >= 0, 0, -1) for i in ids], ["all"])
    return float(pooled["all"]["rel_rmse"]), {k: float(v["rel_rmse"]) for k, v in per.items()}


def self_check_warning(method: str, per_object: Mapping[str, float], rel_rmse: float,
                       train_rel_rmse: float | None, *, factor: float = FACTOR,
                       floor: float = TRAIN_FLOOR) -> str | None:
    """The one-line warning of a self-check, or None when it is fine (module docstring).

    Warns when an object's held-out relative RMSE is >= 1 (or not finite), naming those objects and
    their scores; or when the pooled score ``rel_rmse`` exceeds ``factor`` x max(``train_rel_rmse``,
    ``floor``), naming the objects above that bound (the worst one when none is alone). No
    training score (None, NaN): only the first rule."""
    parts = []
    bad = sorted(((k, v) for k, v in per_object.items() if not (math.isfinite(v) and v < 1.0)),
                 key=lambda kv: -kv[1] if math.isfinite(kv[1]) else -math.inf)
    if bad:
        parts.append("worse than predicting zero (relative RMSE >= 1) on "
                     + ", ".join(f"{k} {v:.2f}" for k, v in bad))
    if train_rel_rmse is not None and math.isfinite(train_rel_rmse) and math.isfinite(rel_rmse):
        bound = float(factor) * max(float(train_rel_rmse), float(floor))
        if rel_rmse > bound:
            finite = sorted(((k, v) for k, v in per_object.items() if math.isfinite(v)), key=lambda kv: -kv[1])
            over = [kv for kv in finite if kv[1] > bound] or finite[:1]
            parts.append(f"held-out relative RMSE {rel_rmse:.3f} > {factor:g} x training {train_rel_rmse:.3f}"
                         + (" on " + ", ".join(f"{k} {v:.2f}" for k, v in over) if over else ""))
    if not parts:
        return None
    return f"{method} self-check: " + "; ".join(parts) + " (do not trust this fit there)"


def result(method: str, per_object: Mapping[str, float], rel_rmse: float, train_rel_rmse: float | None,
           held_out: str, *, emit: bool = True, **extra) -> dict:
    """A self-check's dict (``KEYS``, then ``extra``), its warning from ``self_check_warning``;
    emitted as a ``SelfCheckWarning`` too unless ``emit`` is False."""
    per = {str(k): float(v) for k, v in per_object.items()}
    train = None if train_rel_rmse is None else float(train_rel_rmse)
    warning = self_check_warning(method, per, float(rel_rmse), train)
    if warning and emit:
        warnings.warn(warning, SelfCheckWarning, stacklevel=3)
    return {"rel_rmse": float(rel_rmse), "per_object": per, "train_rel_rmse": train, "held_out": str(held_out),
            "warning": warning, **extra}
