"""LOD selection solvers, one per module, reachable by name.

A flat solver is ``solve(cand: Candidates, budget, *, limit, state, **opts) -> Result``.
The names are Funkhouser & Séquin's test methods ("none", "static", "feedback",
"optimization": the incremental solver) plus the greedy from scratch and the
exact MIP; "hierarchical" (takes a ``Forest``) and "mixed" join when present.
A session picks one by name in its ``hello``.
"""

from __future__ import annotations

from typing import Callable

from . import baselines, exact, greedy, incremental
from .candidates import NO_LIMIT, Candidates, TimeLimit
from .result import Result

__all__ = ["SOLVERS", "Candidates", "TimeLimit", "NO_LIMIT", "Result", "get"]

SOLVERS: dict[str, Callable[..., Result]] = {
    "none": baselines.none,
    "static": baselines.static,
    "feedback": baselines.feedback,
    "greedy": greedy.solve,
    "optimization": incremental.solve,
    "incremental": incremental.solve,
    "exact": exact.solve,
}

try:
    from . import hierarchical

    SOLVERS["hierarchical"] = hierarchical.solve
except ImportError:
    pass

try:
    from . import mixed

    SOLVERS["mixed"] = mixed.solve
except ImportError:
    pass


def get(name: str) -> Callable[..., Result]:
    """The solver called ``name``; KeyError lists the known ones."""
    try:
        return SOLVERS[name]
    except KeyError:
        raise KeyError(f"unknown solver {name!r}; known: {', '.join(sorted(SOLVERS))}") from None
