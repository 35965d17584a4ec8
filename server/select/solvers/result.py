"""What every solver returns."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["Result"]


@dataclass
class Result:
    """A selection: the chosen option per object or node (−1: not drawn), its predicted cost and benefit.

    level : (n,) int64 — for flat solvers the option index into ``Candidates`` (level × algorithm);
            for the hierarchical solver, per node, the level drawn (−1: not in the cut)
    x     : (n_c,) float64 in [0, 1] — continuous resolutions (mixed solver), else None
    stats : solver figures (increments, rounds, "stopped": "done" | "limit" | "budget", ...)
    """

    level: np.ndarray
    cost: float
    benefit: float
    stats: dict = field(default_factory=dict)
    x: np.ndarray | None = None
