"""Results as strict JSON: numpy to Python, non-finite floats to null, paths to text.

The evaluation, its report and the failure scenarios all write results files; strict
JSON has no NaN or ∞, and a figure that never came (no frames in a window, never
recovered) is null — the text beside it has already said what it meant.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["jsonable"]


def jsonable(x: Any) -> Any:
    """numpy scalars and arrays to Python numbers and lists, recursively; NaN and ±∞ to None; a Path to str."""
    if isinstance(x, dict):
        return {str(k): jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return jsonable(x.tolist())
    if isinstance(x, (bool, np.bool_)):
        return bool(x)
    if isinstance(x, (int, np.integer)):
        return int(x)
    if isinstance(x, (float, np.floating)):
        return float(x) if math.isfinite(x) else None
    if isinstance(x, Path):
        return str(x)
    return x
