"""LOD selection solvers, one per module, reachable by name.

Every solver takes per-object, per-level ``benefit`` and ``cost`` arrays and a
budget, and returns a ``Result``. A session picks one by name in its ``hello``.
"""

from __future__ import annotations

from typing import Callable

from . import greedy
from .result import Result

__all__ = ["SOLVERS", "Result", "get"]

SOLVERS: dict[str, Callable[..., Result]] = {"greedy": greedy.solve}


def get(name: str) -> Callable[..., Result]:
    """The solver called ``name``; KeyError lists the known ones."""
    try:
        return SOLVERS[name]
    except KeyError:
        raise KeyError(f"unknown solver {name!r}; known: {', '.join(sorted(SOLVERS))}") from None
