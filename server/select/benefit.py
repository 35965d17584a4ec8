"""Benefit of drawing an object at a level: Size · Accuracy (Funkhouser & Séquin 1993, section 4).

The skeleton uses the two factors that matter most: the pixels an object covers
and the accuracy of the level, 1 − BaseError / Samples^m with Samples the
level's polygon count (flat shading, m = 1). Later factors (importance, focus,
motion, hysteresis) multiply in.
"""

from __future__ import annotations

import numpy as np

__all__ = ["BASE_ERROR", "accuracy", "benefit"]

BASE_ERROR = 0.5


def accuracy(samples: np.ndarray, m: float = 1.0) -> np.ndarray:
    """(k,) float64 in [0.5, 1): 1 − 0.5 / samples^m; more samples, diminishing returns."""
    samples = np.maximum(np.asarray(samples, np.float64), 1.0)
    return 1.0 - BASE_ERROR / samples**m


def benefit(size: np.ndarray, faces: np.ndarray, m: float = 1.0) -> np.ndarray:
    """(k,) float64 benefit of representations with ``faces`` polygons on objects covering ``size`` pixels."""
    return np.asarray(size, np.float64) * accuracy(faces, m)
