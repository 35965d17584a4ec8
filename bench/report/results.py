"""Reading the evaluation's results dict: the methods in Table 1's order, the headline target, and the
run of a method at a budget (a budget-free method's only run counts for every budget).
"""

from __future__ import annotations

import math
from typing import Any

from bench.methods import METHODS

__all__ = [
    "METHOD_ORDER", "BUDGET_FREE", "finite", "nearly_equal", "method_order", "target_of", "budget_free", "run_at",
]


#: F&S Table 1's order, then the methods of Zach (2002) and Zach, Mantler & Karner (2002).
METHOD_ORDER = tuple(METHODS)
#: Methods that ignore the budget: run once (at the headline target), their run counts for every budget.
BUDGET_FREE = frozenset({"none", "static"})


def finite(x: Any) -> float | None:
    """``x`` as a float when it is a finite number, else None (missing, NaN, ±inf, not a number)."""
    if isinstance(x, bool) or x is None:
        return None
    try:
        v = float(x)
    except (TypeError, ValueError):
        return None
    return v if math.isfinite(v) else None


def nearly_equal(a: float, b: float) -> bool:
    return math.isclose(float(a), float(b), rel_tol=1e-6, abs_tol=1e-9)


def method_order(results: dict) -> list[str]:
    """Methods in Table 1's order, then any others in the order the results name or run them."""
    seen = list(results.get("methods") or []) + [r.get("method") for r in results.get("runs") or []]
    names = [m for m in METHOD_ORDER if m in seen]
    names += [m for m in dict.fromkeys(seen) if m and m not in names]
    return names


def target_of(results: dict, target_ms: float | None) -> float:
    target = results.get("target_ms") if target_ms is None else target_ms
    if finite(target) is None or float(target) <= 0:
        raise ValueError(f"the report needs a positive target frame time in ms, got {target!r}")
    return float(target)


def budget_free(run: dict) -> bool:
    flag = run.get("budget_dependent")
    return (not flag) if isinstance(flag, bool) else run.get("method") in BUDGET_FREE


def run_at(results: dict, method: str, target_ms: float) -> dict | None:
    """The method's run at ``target_ms``; a budget-free method's only run counts for every budget."""
    runs = [r for r in results.get("runs") or [] if r.get("method") == method]
    for run in runs:
        if finite(run.get("target_ms")) is not None and nearly_equal(run["target_ms"], target_ms):
            return run
    free = [r for r in runs if budget_free(r)]
    return free[0] if free else None
