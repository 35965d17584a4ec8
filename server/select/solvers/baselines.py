"""The baselines Funkhouser & Séquin compare against (1993, section 5, Table 1): None, Static, Feedback.

They ignore the budget by design: None draws every object at its highest level,
Static at the highest level whose average polygon covers at least N pixels
(N = 1024 in the paper), Feedback scales Static's N by how far the last frame
time was from the target. stats["over_budget"] says when the cost exceeds it.
"""

from __future__ import annotations

import numpy as np

from .candidates import NO_LIMIT, Candidates, TimeLimit
from .result import Result

__all__ = ["none", "static", "feedback", "PIXELS_PER_POLYGON"]

#: The paper's Static threshold: pixels the average polygon of the chosen level must cover.
PIXELS_PER_POLYGON = 1024.0
_CLAMP = (0.5, 2.0)  # Feedback's largest step down / up in one frame
_RANGE = (1e-3, 1e9)  # Feedback's threshold stays in here


def _result(cand: Candidates, level: np.ndarray, budget: float, **stats) -> Result:
    rows = np.flatnonzero(level >= 0)
    cost = float(np.nansum(cand.cost[rows, level[rows]]))
    benefit = float(np.nansum(cand.benefit[rows, level[rows]]))
    return Result(level, cost, benefit, {"stopped": "done", "over_budget": bool(cost > budget), **stats})


def _richest(cand: Candidates, mask: np.ndarray) -> np.ndarray:
    """(n,) the highest option index in ``mask`` per object: the highest level, then the richest algorithm."""
    k = cand.k
    if k == 0:
        return np.full(cand.n, -1, dtype=np.int64)
    last = k - 1 - np.argmax(mask[:, ::-1], axis=1)
    return np.where(mask.any(axis=1), last, -1).astype(np.int64)


def none(cand: Candidates, budget: float, *, limit: TimeLimit = NO_LIMIT, state: dict | None = None) -> Result:
    """Every visible object at its highest level with the richest algorithm, whatever it costs."""
    return _result(cand, _richest(cand, cand.valid), budget)


def static(
    cand: Candidates,
    budget: float,
    *,
    limit: TimeLimit = NO_LIMIT,
    state: dict | None = None,
    pixels_per_polygon: float = PIXELS_PER_POLYGON,
) -> Result:
    """The highest level whose average polygon covers ≥ ``pixels_per_polygon`` pixels (size / faces ≥ N).

    An object whose coarsest level is already too fine draws the coarsest one.
    Without size or faces it cannot judge and draws like None (stats["fallback"]).
    """
    valid = np.asarray(cand.valid, bool)
    if cand.size is None or cand.faces is None:
        return _result(cand, _richest(cand, valid), budget, threshold=float(pixels_per_polygon),
                       fallback="no size/faces")
    size = np.asarray(cand.size, np.float64).reshape(-1)[:, None]
    faces = np.asarray(cand.faces, np.float64)
    with np.errstate(invalid="ignore", over="ignore"):
        fits = valid & (faces * float(pixels_per_polygon) <= size)
    level = _richest(cand, fits)
    k = cand.k
    if k:
        lev = np.arange(k) // max(cand.algorithms, 1)
        coarsest = np.min(np.where(valid, lev[None, :], np.iinfo(np.int64).max), axis=1)
        fallback = _richest(cand, valid & (lev[None, :] == coarsest[:, None]))
        level = np.where(level >= 0, level, fallback)
    return _result(cand, level, budget, threshold=float(pixels_per_polygon))


def feedback(
    cand: Candidates,
    budget: float,
    *,
    limit: TimeLimit = NO_LIMIT,
    state: dict | None = None,
    pixels_per_polygon: float = PIXELS_PER_POLYGON,
) -> Result:
    """Static with its threshold scaled by last frame time / target (a slow frame raises it).

    state : {"threshold": N, "frame_time": last measured seconds, "target": seconds (default: budget)};
            the new threshold comes back in stats["threshold"] for the caller to keep.
    """
    state = state or {}
    threshold = float(state.get("threshold", pixels_per_polygon))
    if not np.isfinite(threshold) or threshold <= 0:
        threshold = float(pixels_per_polygon)
    frame_time, target = state.get("frame_time"), state.get("target", budget)
    try:
        ratio = float(frame_time) / float(target)
    except (TypeError, ValueError, ZeroDivisionError):
        ratio = 1.0
    if np.isfinite(ratio) and ratio > 0:
        threshold = float(np.clip(threshold * np.clip(ratio, *_CLAMP), *_RANGE))
    return static(cand, budget, limit=limit, pixels_per_polygon=threshold)
