"""Which pixels of a frame show the scene rather than what it is drawn against (the sky or the plain
background), for tests that assert a frame shows the scene."""

from __future__ import annotations

import numpy as np

from client.renderer import BACKGROUND
from client.sky import BELOW, HORIZON, ZENITH

#: How far (0–255 per channel) a pixel may lie from the sky's colours and still be sky.
TOLERANCE = 4.0


def _distance_to_segment(p: np.ndarray, a, b) -> np.ndarray:
    a, b = np.asarray(a, np.float64) * 255, np.asarray(b, np.float64) * 255
    d = b - a
    s = np.clip(((p - a) @ d) / float(d @ d), 0.0, 1.0)
    return np.linalg.norm(p - (a + s[..., None] * d), axis=-1)


def scene_share(image: np.ndarray) -> float:
    """The share of an (h, w, 3) uint8 frame's pixels that are neither the sky (any colour of its gradient,
    zenith → horizon → the haze below) nor the plain background."""
    p = np.asarray(image, np.float64)[..., :3]
    sky = np.minimum(_distance_to_segment(p, ZENITH, HORIZON), _distance_to_segment(p, HORIZON, BELOW))
    plain = np.abs(p - np.round(np.asarray(BACKGROUND) * 255)).max(axis=-1)
    return float(((sky > TOLERANCE) & (plain > 3)).mean())
