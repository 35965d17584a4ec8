"""Zach, Mantler & Karner's mixed solver as the paper states it: barrier gradient ascent.

``mixed.solve`` (the one sessions use) moves every resolution straight to the
resolution whose marginal value per second equals the discrete slope, many
increments per iteration. This module keeps the paper's own iteration so the two
can be compared on the same instances (``mixed.solve(..., direction="barrier")``):

- each iteration takes either the best discrete increment (value slope_d) or one
  gradient step on the resolutions, whichever gains more per second;
- search direction a_i = max(0, ∂b/∂x_i − ε/(1 − x_i)), a_i = 0 at x_i = 1 (the barrier
  keeps x inside [0, 1]);
- along a, slope_c(t) = Σ ∂b/∂x_i(x + t·a)·a_i / Σ slope_i·a_i falls with t (b is concave):
  step to t_max (a bound or the budget) if slope_c there still beats slope_d, otherwise
  bisect to t_opt where slope_c = slope_d.

Every iteration ends feasible. Each smooth object is its own variable here
(no Appendix A splitting), and √x's infinite slope at 0 is evaluated at ``x_floor``
(default 10⁻³, a thousandth of a group's splats).
"""

from __future__ import annotations

import numpy as np

from .candidates import NO_LIMIT, Candidates, TimeLimit
from .mixed_problem import Smooth, discrete_increments, mixed_result
from .result import Result

__all__ = ["solve"]


def solve(
    cand: Candidates,
    budget: float,
    *,
    smooth: Smooth,
    limit: TimeLimit = NO_LIMIT,
    iterations: int = 10_000,
    barrier: float | None = None,
    x_floor: float = 1e-3,
) -> Result:
    """Select discrete options and resolutions by the paper's interleaved increments and barrier steps.

    barrier : ε of the barrier term, in benefit units (default 1e-9 × Σ weight)
    Result.stats: increments, activations, gradient_steps, iterations, stopped, discrete/continuous cost.
    """
    budget = max(float(budget), 0.0)
    n, m, p = cand.n, smooth.m, float(smooth.power)
    w = np.asarray(smooth.weight, np.float64)
    s = np.asarray(smooth.slope, np.float64)
    f = np.asarray(smooth.fixed, np.float64)
    eps = float(barrier) if barrier is not None else 1e-9 * max(float(w.sum()), 1e-300)
    obj, opt, d_b, d_c, value, chain = discrete_increments(cand, budget)
    live = np.ones(obj.size, bool)
    taken = np.zeros(obj.size, bool)
    spent_d = 0.0
    x = np.zeros(m)
    active = f == 0
    xstar = np.minimum(1.0, p * f / (s * (1 - p))) if m else np.zeros(0)  # activation: best benefit / cost
    a_cost = f + s * xstar
    a_val = np.where(w > 0, w * xstar**p / np.maximum(a_cost, 1e-300), -np.inf)
    tol = 1e-12 * max(budget, 1e-300)
    stats = {"iterations": 0, "increments": 0, "activations": 0, "gradient_steps": 0}
    stopped = "done"

    def grad(y):
        return w * p * np.maximum(y, x_floor) ** (p - 1.0)

    while True:
        if limit.expired() or stats["iterations"] >= iterations:
            stopped = "limit"
            break
        stats["iterations"] += 1
        remaining = budget - spent_d - float(np.dot(f, active) + np.dot(s, x * active))
        if remaining <= tol:
            break
        kill = live & (d_c > remaining)  # an increment that no longer fits never will, nor its successors
        if kill.any():
            first = np.full(max(n, 1), np.iinfo(np.int64).max)
            np.minimum.at(first, obj[kill], chain[kill])
            live &= chain < first[obj]
        d_i = int(np.argmax(live)) if live.any() else -1
        v_d = float(value[d_i]) if d_i >= 0 else -np.inf
        # Only an activation that fits and gains (a weightless group's value is −inf): argmax over none of
        # them would name the first group, fitting or not.
        offer = np.where(~active & (a_cost <= remaining), a_val, -np.inf)
        a_i = int(np.argmax(offer)) if m and offer.max() > -np.inf else -1
        v_a = float(a_val[a_i]) if a_i >= 0 else -np.inf
        slope_d = max(v_d, v_a)

        room = active & (x < 1.0) & (w > 0)
        g = grad(x)
        with np.errstate(divide="ignore"):
            a = np.where(room, np.maximum(0.0, g - eps / np.maximum(1.0 - x, 1e-300)), 0.0)
        denom = float(np.dot(s, a))
        slope_c = float(np.dot(g, a)) / denom if denom > 0 else -np.inf
        if slope_c > slope_d and slope_c > 0:
            up = a > 0
            t_hi = min(float(np.min((1.0 - x[up]) / a[up])), remaining / denom)

            def slope_at(t: float) -> float:
                return float(np.dot(grad(x + t * a), a)) / denom

            t = t_hi
            if slope_d > 0 and slope_at(t_hi) < slope_d:
                lo, hi = 0.0, t_hi  # slope_at(lo) > slope_d ≥ slope_at(hi)
                for _ in range(100):
                    mid = 0.5 * (lo + hi)
                    if slope_at(mid) > slope_d:
                        lo = mid
                    else:
                        hi = mid
                    if hi - lo <= 1e-15 * t_hi:
                        break
                t = lo
            if t > 0.0:
                x = np.clip(x + t * a, 0.0, 1.0)
                stats["gradient_steps"] += 1
                continue
            # No step gains more than slope_d within float precision: take the increment instead.
        if v_d >= v_a and d_i >= 0:
            taken[d_i] = True
            live[d_i] = False
            spent_d += float(d_c[d_i])
            stats["increments"] += 1
        elif a_i >= 0:
            active[a_i] = True
            x[a_i] = xstar[a_i]
            stats["activations"] += 1
        else:
            break
    stats["stopped"] = stopped
    return mixed_result(cand, budget, (obj, opt, chain, taken), (w, s, f, p), x, active, stats)
