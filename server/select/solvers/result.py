"""What every solver returns."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["Result"]


@dataclass
class Result:
    """A selection: the chosen level per object (−1: not drawn), its predicted cost and benefit.

    level : (n,) int64
    """

    level: np.ndarray
    cost: float
    benefit: float
    stats: dict = field(default_factory=dict)
