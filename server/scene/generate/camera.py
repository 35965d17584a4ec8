"""Looping camera tours from a few control poses: smooth, shape-preserving, and exact at the controls.

Poses are interpolated as eye position, yaw and pitch with a monotone cubic
(PCHIP): unlike a natural spline it does not overshoot, so an eye held at one
place stays there (a spin on the spot) and a path between walls does not bulge
into them, and every control pose is met exactly (the viewpoints the
benchmarks name). The loop closes smoothly by padding the controls with their
neighbours across the seam.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.interpolate import PchipInterpolator

__all__ = ["yaw_pitch", "looping_tour"]


def yaw_pitch(forward: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Yaw (about +z, from +x) and pitch (above the xy plane) of view directions (k, 3), radians."""
    f = np.asarray(forward, np.float64).reshape(-1, 3)
    return np.arctan2(f[:, 1], f[:, 0]), np.arctan2(f[:, 2], np.hypot(f[:, 0], f[:, 1]))


def looping_tour(times, eyes, yaws, pitches, step: float = 0.1) -> list[dict]:
    """Tour keys {"t", "eye", "forward", "up"} every ``step`` seconds through closed control poses.

    times   : (k,) strictly increasing, times[0] = 0, times[-1] = the loop's duration
    eyes    : (k, 3); eyes[-1] must equal eyes[0]
    yaws    : (k,) unwrapped — a spin is a run of growing yaw; yaws[-1] − yaws[0] a multiple of 2π
    pitches : (k,); pitches[-1] must equal pitches[0]

    Control times on the ``step`` grid appear as keys with their exact pose.
    The last key repeats the first pose at t = duration; z is up.
    """
    t = np.asarray(times, np.float64)
    eye = np.asarray(eyes, np.float64).reshape(-1, 3)
    yaw = np.asarray(yaws, np.float64)
    pitch = np.asarray(pitches, np.float64)
    turns = (yaw[-1] - yaw[0]) / (2 * math.pi)
    if not (t[0] == 0.0 and np.all(np.diff(t) > 0) and np.allclose(eye[-1], eye[0])
            and abs(pitch[-1] - pitch[0]) < 1e-12 and abs(turns - round(turns)) < 1e-9):
        raise ValueError("controls must start at t = 0, increase, and end at the first pose")
    duration, wrap = float(t[-1]), 2 * math.pi * round(turns)
    chan = np.column_stack([eye, yaw, pitch])
    shift = np.array([0.0, 0.0, 0.0, wrap, 0.0])
    # Periodic padding: the slopes at the seam see the same neighbours from both sides.
    tt = np.concatenate([t[-3:-1] - duration, t, t[1:3] + duration])
    cc = np.concatenate([chan[-3:-1] - shift, chan, chan[1:3] + shift])
    spline = PchipInterpolator(tt, cc, axis=0)
    n = int(round(duration / step))
    kt = np.round(np.arange(n) * step, 9)
    v = spline(kt)
    # Exact poses at the controls that fall on the grid.
    grid = np.round(t / step)
    on = np.abs(grid * step - t) < 1e-9
    v[grid[on & (grid < n)].astype(int)] = chan[on & (grid < n)]
    y, p = v[:, 3], np.clip(v[:, 4], -1.4, 1.4)
    fwd = np.column_stack([np.cos(p) * np.cos(y), np.cos(p) * np.sin(y), np.sin(p)])
    keys = [{"t": float(ti), "eye": [float(a) for a in e], "forward": [float(a) for a in f], "up": [0.0, 0.0, 1.0]}
            for ti, e, f in zip(kt, v[:, :3], fwd)]
    keys.append({**keys[0], "t": duration})
    return keys
