"""Camera tours for scenes that come without one: a looping flight round and over the scene.

A tour is a list of keys {"t", "eye", "forward", "up"} (``proto.messages.TourKey``),
z up; the client plays it back with linear interpolation, so keys are dense
enough (every half second) for the path to look smooth.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["orbit_tour"]


def orbit_tour(lo: np.ndarray, hi: np.ndarray, *, duration: float = 60.0, step: float = 0.5) -> list[dict]:
    """A loop round the box (lo, hi): an orbit whose height and radius breathe, looking at the centre.

    The camera swings from a low, close pass (objects large on screen, where the
    budget bites) to a high, far one (everything in view, small), and the first
    key equals the last so the tour loops.
    """
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    centre = (lo + hi) / 2
    half = np.maximum((hi - lo)[:2] / 2, 1.0)
    reach = float(np.linalg.norm(half))
    ground = float(lo[2])
    tall = float(max(hi[2] - lo[2], 2.0))
    keys = []
    n = max(8, int(round(duration / step)))
    for i in range(n + 1):
        s = i / n
        a = 2 * math.pi * s
        breathe = 0.5 - 0.5 * math.cos(2 * a)  # 0 at start, 1 at a quarter, 0 at a half…
        radius = reach * (0.55 + 0.75 * breathe)
        height = ground + tall * (0.6 + 0.4 * breathe) + reach * 0.35 * breathe + 1.7
        eye = np.array([centre[0] + radius * math.cos(a), centre[1] + radius * math.sin(a), height])
        target = np.array([centre[0], centre[1], ground + 0.3 * tall])
        fwd = target - eye
        fwd /= np.linalg.norm(fwd)
        keys.append({"t": round(s * duration, 6), "eye": eye.tolist(), "forward": fwd.tolist(),
                     "up": [0.0, 0.0, 1.0]})
    keys[-1] = {**keys[0], "t": keys[-1]["t"]}
    return keys
