"""Reading the evaluation's results dict: the methods in Table 1's order, the headline target, and the
run of a method at a budget (a budget-free method's only run counts for every budget). A run is with or
without the client's frame governor (``governor``) and one of several repeats (``repeat``): a method's
run at a budget is the median of its repeats by mean frame time, and ``repeats_at`` gives them all.
"""

from __future__ import annotations

import math
from typing import Any

from bench.methods import METHODS

__all__ = [
    "METHOD_ORDER", "BUDGET_FREE", "finite", "nearly_equal", "method_order", "target_of", "budget_free", "run_at",
    "repeats_at", "label",
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


def label(method: str, governor: bool) -> str:
    """A row's name: the method, with "+gov" when the client's frame governor ran."""
    return f"{method}+gov" if governor else method


def repeats_at(results: dict, method: str, target_ms: float, governor: bool = False) -> list[dict]:
    """Every repeat of the method's run at ``target_ms`` (a budget-free method's runs count for every budget)."""
    runs = [r for r in results.get("runs") or []
            if r.get("method") == method and bool(r.get("governor", False)) == bool(governor)]
    at = [r for r in runs if finite(r.get("target_ms")) is not None and nearly_equal(r["target_ms"], target_ms)]
    return at or [r for r in runs if budget_free(r)]


def run_at(results: dict, method: str, target_ms: float, governor: bool = False) -> dict | None:
    """The method's run at ``target_ms`` — the median of its repeats by mean frame time (the lower median of an
    even count); a budget-free method's runs count for every budget."""
    runs = repeats_at(results, method, target_ms, governor)
    if not runs:
        return None
    if len(runs) == 1:
        return runs[0]
    key = [finite((r.get("summary") or {}).get("frame_mean_ms")) for r in runs]
    order = sorted(range(len(runs)), key=lambda i: (key[i] is None, key[i] or 0.0, i))
    return runs[order[(len(runs) - 1) // 2]]
