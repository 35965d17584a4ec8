"""What both mixed solvers share (``mixed``: band steps; ``mixed_gradient``: the paper's barrier
gradient): the problem's continuous part (``Smooth``), the increments of the discrete
part's upper hulls, and the ``Result`` of a mixed selection (Zach, Mantler & Karner 2002).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .candidates import Candidates
from .result import Result

__all__ = ["Smooth", "discrete_increments", "mixed_result"]


@dataclass(frozen=True)
class Smooth:
    """The continuous part: m smooth objects with resolution x ∈ [0, 1].

    weight   : (m,) benefit at full resolution (pixels covered × importance); benefit = weight · x^power
    slope    : (m,) seconds per unit resolution (> 0); cost = fixed + slope · x once drawn
    fixed    : (m,) seconds paid once the object is drawn at all (the paper's c_tree)
    power    : exponent of the concave benefit, in (0, 1); ½ is the paper's √x
    quadtree : optional (q,) int parent array, q ≥ m: nodes 0..m−1 are the objects,
               m..q−1 the quadtree's inner nodes, −1 marks a root. Objects under a node
               share one variable until Appendix A's bound says split.
    """

    weight: np.ndarray
    slope: np.ndarray
    fixed: np.ndarray
    power: float = 0.5
    quadtree: np.ndarray | None = None

    @property
    def m(self) -> int:
        return int(np.asarray(self.weight).shape[0])

    @classmethod
    def empty(cls) -> "Smooth":
        return cls(np.zeros(0), np.ones(0), np.zeros(0))

    @classmethod
    def of(cls, weight, slope, fixed=None, **more) -> "Smooth":
        weight = np.asarray(weight, np.float64)
        slope = np.asarray(slope, np.float64)
        fixed = np.zeros_like(weight) if fixed is None else np.asarray(fixed, np.float64)
        if weight.ndim != 1 or slope.shape != weight.shape or fixed.shape != weight.shape:
            raise ValueError("weight, slope and fixed must be (m,) alike")
        return cls(weight, slope, fixed, **more)


def _hull(bx: np.ndarray, cx: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """(n, K) bool: options on each object's upper concave hull from (0, 0) = not drawn (cost rising along K).

    Kept here (not greedy.upper_hull, whose signature is another module's business) so the
    discrete increments have strictly falling values along each object.
    """
    n, k = bx.shape
    bx = np.concatenate([np.zeros((n, 1)), bx], axis=1)
    cx = np.concatenate([np.zeros((n, 1)), cx], axis=1)
    ok = np.concatenate([np.ones((n, 1), bool), ok], axis=1)
    stack = np.zeros((n, k + 1), dtype=np.int64)
    top = np.ones(n, dtype=np.int64)
    rows = np.arange(n)
    for j in range(1, k + 1):
        last = stack[rows, top - 1]
        take = ok[:, j] & (bx[:, j] > bx[rows, last]) & (cx[:, j] > cx[rows, last])
        for _ in range(k):
            a = stack[rows, np.maximum(top - 2, 0)]
            b = stack[rows, top - 1]
            pop = take & (top >= 2) & (
                (bx[rows, b] - bx[rows, a]) * (cx[:, j] - cx[rows, b])
                <= (bx[:, j] - bx[rows, b]) * (cx[rows, b] - cx[rows, a])
            )
            if not pop.any():
                break
            top -= pop
        stack[rows[take], top[take]] = j
        top += take
    on = np.zeros((n, k + 1), dtype=bool)
    depth = np.arange(k + 1)[None, :] < top[:, None]
    on[np.repeat(rows, k + 1)[depth.ravel()], stack[depth]] = True
    return on[:, 1:]


def discrete_increments(cand: Candidates, budget: float):
    """Increments of every object's upper concave hull, sorted by value (falling).

    Options are sorted by cost per object first, so interleaved algorithms need
    not have cost rising along K. Returns obj, option, Δbenefit, Δcost, value, chain position.
    """
    benefit = np.asarray(cand.benefit, np.float64)
    cost = np.asarray(cand.cost, np.float64)
    n, k = benefit.shape
    valid = np.asarray(cand.valid, bool) & (cost <= budget) & (cost > 0) & np.isfinite(benefit)
    order = np.argsort(np.where(valid, cost, np.inf), axis=1, kind="stable")
    b = np.take_along_axis(benefit, order, 1)
    c = np.take_along_axis(cost, order, 1)
    v = np.take_along_axis(valid, order, 1)
    hull = _hull(np.where(v, b, 0.0), np.where(v, c, 0.0), v) if n and k else np.zeros((n, k), bool)
    obj, col = np.nonzero(hull)
    first = np.r_[True, obj[1:] != obj[:-1]] if obj.size else np.zeros(0, bool)
    pb = np.where(first, 0.0, np.r_[0.0, b[obj, col][:-1]])
    pc = np.where(first, 0.0, np.r_[0.0, c[obj, col][:-1]])
    db = b[obj, col] - pb
    dc = c[obj, col] - pc
    value = db / dc
    start = np.flatnonzero(first)
    chain = np.arange(obj.size) - np.repeat(start, np.diff(np.r_[start, obj.size]))
    s = np.argsort(-value, kind="stable")  # ties keep row-major order: chain order within an object
    return obj[s], order[obj, col][s], db[s], dc[s], value[s], chain[s]


def mixed_result(cand: Candidates, budget: float, steps, smooth, x, active, stats) -> Result:
    """The Result of taken increments and resolutions, trimmed of the bisections' float slack."""
    obj, opt, chain, taken = steps
    w, s, f, p = smooth
    n = cand.n
    level = np.full(n, -1, np.int64)
    if taken.any():
        best = np.full(n, -1, np.int64)
        np.maximum.at(best, obj[taken], chain[taken])
        hit = taken & (chain == best[obj])
        level[obj[hit]] = opt[hit]
    drawn = np.flatnonzero(level >= 0)
    cost_d = float(cand.cost[drawn, level[drawn]].sum()) if drawn.size else 0.0
    ben_d = float(cand.benefit[drawn, level[drawn]].sum()) if drawn.size else 0.0
    x = np.clip(np.where(active, x, 0.0), 0.0, 1.0)
    cost_c = float(np.dot(f, active) + np.dot(s, x))
    if cost_d + cost_c > budget and cost_c > 0:
        # Float slack from the bisections: give it back from the continuous part.
        var = float(np.dot(s, x))
        scale = max(0.0, (budget - cost_d - float(np.dot(f, active))) / var) if var > 0 else 0.0
        x = x * min(1.0, scale)
        cost_c = float(np.dot(f, active) + np.dot(s, x))
    ben_c = float(np.dot(w, np.where(active, x, 0.0) ** p))
    stats.update(continuous_cost=cost_c, discrete_cost=cost_d)
    return Result(level=level, cost=cost_d + cost_c, benefit=ben_d + ben_c, stats=stats, x=x)
