"""The multiple-choice knapsack solved exactly, and its LP bound (Funkhouser & Séquin 1993, section 4.3).

``solve`` states the selection as a mixed-integer program for HiGHS: a binary
x_ik per object i and option k, Σ_k x_ik ≤ 1, Σ cost·x ≤ budget, maximise
Σ benefit·x. It is the yardstick for small instances (benchmarks, the greedy's
factor two). ``upper_bound`` is the LP relaxation's optimum for any size: the
LP of a multiple-choice knapsack is solved exactly by the greedy over each
object's upper hull with a fractional last increment (Dyer; Zemel), so it needs
no LP solver.
"""

from __future__ import annotations

import numpy as np

from . import greedy
from .candidates import NO_LIMIT, Candidates, TimeLimit
from .result import Result

__all__ = ["solve", "upper_bound"]


def upper_bound(cand: Candidates, budget: float) -> float:
    """Optimum of the LP relaxation (0 ≤ x_ik, Σ_k x_ik ≤ 1): an upper bound on any selection's benefit.

    Options dearer than the budget stay in: the relaxation may take a fraction of them.
    """
    if cand.n == 0 or cand.k == 0 or not budget > 0:
        return 0.0
    hull = greedy.upper_hull(cand)
    value, d_cost, d_benefit = hull.value.ravel(), hull.d_cost.ravel(), hull.d_benefit().ravel()
    taken = greedy.cut(value, d_cost, budget)
    total = float(np.sum(d_benefit, where=taken))
    left = budget - float(np.sum(d_cost, where=taken))
    rest = np.where(taken, -np.inf, value)
    nxt = int(np.argmax(rest))
    # The cut stopped at an increment that does not fit; its value is the best left, and a
    # fraction of it fills the budget (ties may put another of equal value first: same value).
    if rest[nxt] > 0 and left > 0:
        total += left * float(rest[nxt])
    return total


def solve(
    cand: Candidates,
    budget: float,
    *,
    limit: TimeLimit = NO_LIMIT,
    state: dict | None = None,
    mip_gap: float = 1e-6,
    time_limit: float | None = None,
) -> Result:
    """Optimal selection by branch and bound in HiGHS (small instances: a few thousand options).

    ``limit`` is checked once before the solve (HiGHS has its own clock: ``time_limit``
    seconds); on a time-limited solve the incumbent is returned with stopped="limit",
    and the empty selection if HiGHS found none.
    """
    import highspy

    n, k = cand.n, cand.k
    level = np.full(n, -1, dtype=np.int64)
    ok = greedy._usable(cand, budget) & (cand.benefit > 0) if budget > 0 else np.zeros((n, k), bool)
    obj, opt = np.nonzero(ok)
    if obj.size == 0:
        return Result(level, 0.0, 0.0, {"stopped": "done", "status": "empty"})
    if limit.expired():
        return Result(level, 0.0, 0.0, {"stopped": "limit", "status": "not started"})
    m = obj.size
    # Costs in units of the budget: per-object costs of microseconds sit near HiGHS' tolerances, and its
    # "Optimal" could then fall short of the greedy. Scaling both leaves the knapsack unchanged.
    b, c = cand.benefit[obj, opt], cand.cost[obj, opt] / budget
    rows_used, row_of = np.unique(obj, return_inverse=True)
    r = rows_used.size

    lp = highspy.HighsLp()
    lp.num_col_ = m
    lp.num_row_ = r + 1
    lp.col_cost_ = -b  # HiGHS minimises
    lp.col_lower_ = np.zeros(m)
    lp.col_upper_ = np.ones(m)
    lp.row_lower_ = np.full(r + 1, -highspy.kHighsInf)
    lp.row_upper_ = np.r_[np.ones(r), 1.0]
    # Column-wise: column j sits in its object's row and in the budget row.
    lp.a_matrix_.format_ = highspy.MatrixFormat.kColwise
    lp.a_matrix_.start_ = np.arange(0, 2 * m + 1, 2, dtype=np.int32)
    lp.a_matrix_.index_ = np.stack([row_of, np.full(m, r)], axis=1).ravel().astype(np.int32)
    lp.a_matrix_.value_ = np.stack([np.ones(m), c], axis=1).ravel()
    lp.integrality_ = [highspy.HighsVarType.kInteger] * m

    h = _silent_highs(highspy)
    h.setOptionValue("mip_rel_gap", float(mip_gap))
    if time_limit is None and np.isfinite(limit.deadline):  # HiGHS keeps its own clock: hand it what is left
        time_limit = max(limit.deadline - limit.clock(), 1e-3)
    if time_limit is not None:
        h.setOptionValue("time_limit", float(time_limit))
    h.passModel(lp)
    h.run()
    status = h.modelStatusToString(h.getModelStatus())
    x = np.asarray(h.getSolution().col_value) if h.getInfo().primal_solution_status else np.zeros(m)
    pick = x > 0.5
    level[obj[pick]] = opt[pick]
    cost, benefit = greedy.totals(cand, level)
    if cost > budget * (1 + 1e-9):  # HiGHS' feasibility tolerance; never hand back an over-budget answer
        level, cost, benefit = _repair(cand, budget, level)
    stopped = "done" if status == "Optimal" else "limit"
    return Result(level, cost, benefit, {"stopped": stopped, "status": status,
                                         "mip_gap": float(h.getInfo().mip_gap), "columns": m})


def _repair(cand: Candidates, budget: float, level: np.ndarray):
    """Drop the lowest-value options until the cost fits (only after tolerance slips)."""
    level = level.copy()
    rows = np.flatnonzero(level >= 0)
    value = cand.benefit[rows, level[rows]] / cand.cost[rows, level[rows]]
    for i in rows[np.argsort(value)]:
        cost, _ = greedy.totals(cand, level)
        if cost <= budget:
            break
        level[i] = -1
    cost, benefit = greedy.totals(cand, level)
    return level, cost, benefit


def _silent_highs(highspy):
    """A HiGHS solver that writes nothing to stdout. ``highspy.Highs``' constructor enables its callbacks,
    a solver call that prints HiGHS' banner to file descriptor 1 before any option can be set, which would
    break ``--json`` output and server logs; the bare solver it extends (``highspy._Highs``, all this module
    calls) takes the options first."""
    h = highspy._Highs()
    h.setOptionValue("output_flag", False)
    h.setOptionValue("log_to_console", False)
    return h
