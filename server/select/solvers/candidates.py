"""What a flat solver is given: every visible object's candidate tuples, and an optional time limit.

Funkhouser & Séquin's *object tuple* (O, L, R) is object O at level L drawn
with rendering algorithm R. A ``Candidates`` holds, for n visible objects, all
K = levels × algorithms tuples as (n, K) arrays; option k of an object is level
``k // algorithms`` with algorithm ``k % algorithms`` (algorithms ordered
cheapest first: flat, lit, textured). Options an object lacks are padding,
marked False in ``valid``.

Solvers are pure: the time limit is a ``TimeLimit`` carrying the caller's clock, so
``server/select`` itself never reads one and a test can pass a fake clock that
expires after a set number of checks.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np

__all__ = ["Candidates", "TimeLimit", "NO_LIMIT"]


@dataclass(frozen=True)
class Candidates:
    """Per visible object, per option (level × algorithm): benefit, cost and what the baselines read.

    benefit, cost : (n, K) float64 — cost in seconds, rising with the level for a fixed algorithm
    valid         : (n, K) bool
    algorithms    : R, the number of rendering algorithms interleaved in K (1: levels only)
    size          : (n,) float64 — pixels each object covers (Static/Feedback read it)
    faces         : (n, K) int — polygons of each option's level (Static/Feedback read it)
    previous      : (n,) int64 — the option drawn in the last selection, −1 if none (the
                    incremental solver starts from it; hysteresis is already in ``benefit``)
    """

    benefit: np.ndarray
    cost: np.ndarray
    valid: np.ndarray
    algorithms: int = 1
    size: np.ndarray | None = None
    faces: np.ndarray | None = None
    previous: np.ndarray | None = None

    @property
    def n(self) -> int:
        return int(self.benefit.shape[0])

    @property
    def k(self) -> int:
        return int(self.benefit.shape[1])

    def level_of(self, option: np.ndarray) -> np.ndarray:
        """Level of each option index (−1 stays −1)."""
        option = np.asarray(option, np.int64)
        return np.where(option >= 0, option // self.algorithms, -1)

    def algorithm_of(self, option: np.ndarray) -> np.ndarray:
        """Rendering algorithm of each option index (−1 stays −1)."""
        option = np.asarray(option, np.int64)
        return np.where(option >= 0, option % self.algorithms, -1)

    @classmethod
    def of(cls, benefit: np.ndarray, cost: np.ndarray, valid: np.ndarray | None = None, **more) -> "Candidates":
        benefit = np.asarray(benefit, np.float64)
        cost = np.asarray(cost, np.float64)
        valid = np.ones(benefit.shape, bool) if valid is None else np.asarray(valid, bool)
        if benefit.ndim != 2 or cost.shape != benefit.shape or valid.shape != benefit.shape:
            raise ValueError(f"benefit, cost and valid must be (n, K) alike; got {benefit.shape}, "
                             f"{cost.shape}, {valid.shape}")
        return cls(benefit, cost, valid, **more)


@dataclass
class TimeLimit:
    """A time limit as the caller's clock sees it: ``expired()`` once ``clock() ≥ deadline``.

    Solvers check it between rounds and return the best feasible solution found so far,
    with ``stats["stopped"] = "limit"``.
    """

    clock: Callable[[], float]
    deadline: float
    checks: int = field(default=0, init=False)

    def expired(self) -> bool:
        self.checks += 1
        return self.clock() >= self.deadline


class _NoTimeLimit(TimeLimit):
    def __init__(self) -> None:
        super().__init__(clock=lambda: 0.0, deadline=float("inf"))

    def expired(self) -> bool:
        return False


#: The default: run to completion.
NO_LIMIT: TimeLimit = _NoTimeLimit()
