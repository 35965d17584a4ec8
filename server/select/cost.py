"""Cost of drawing a representation, and the feedback that keeps it true (Zach 2002, 4.2).

The skeleton's model is Zach's: render time = c_vertex · vertices. After each
frame the client reports what it drew and how long it took; c_vertex moves to
the measured time per vertex by a weighted average, so the budget holds on the
client's real machine whatever its speed. Fixed per-frame overheads are
absorbed into c_vertex; the loop still converges (the fixed point of
V ← B·V / (a + b·V) is stable while the overhead a is below the budget B).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["CostModel"]


@dataclass
class CostModel:
    """Seconds per vertex, fitted online.

    c_vertex : initial guess, seconds per vertex (llvmpipe on two cores: ~1.5e-7)
    alpha    : weight of the newest measurement in the running average
    min_vertices : frames drawing fewer vertices than this say little about c_vertex
    """

    c_vertex: float = 2.0e-7
    alpha: float = 0.2
    min_vertices: int = 1000
    updates: int = 0

    def predict(self, vertices: np.ndarray) -> np.ndarray:
        """Seconds to draw representations with ``vertices`` vertices; shape follows the input."""
        return self.c_vertex * np.asarray(vertices, np.float64)

    def update(self, time: float, vertices: int) -> bool:
        """Fold in one measured frame; returns whether it was used."""
        if vertices < self.min_vertices or not np.isfinite(time) or time <= 0:
            return False
        measured = time / vertices
        self.c_vertex += self.alpha * (measured - self.c_vertex)
        self.updates += 1
        return True
