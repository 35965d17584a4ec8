"""The scenarios' camera paths: where they happen (``Anchor``, from the store's tour, viewpoints and
bounds) and the tour keys of a spin, a turn, an oscillation, a straight walk and a tour segment.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

__all__ = [
    "Anchor", "WALK_SPEED", "SPEED_SHARE", "STEP_DEG", "forward_of", "visible_counts", "max_speed", "anchor_of",
    "spin_path", "turn_path", "oscillation_path", "straight_path", "tour_segment",
]


#: A walker's speed (m/s): the oscillation's 2 m are scaled by the tour's speed over it in larger scenes.
WALK_SPEED = 1.4
#: Paths move at most this share of the predictor's teleport speed: faster, every camera sample is a teleport
#: (a reset) and the scenario would test that instead of what it is about.
SPEED_SHARE = 0.5
#: Degrees per tour key in a spin or turn: keys are blended by nlerp, fine for steps well under 90°.
STEP_DEG = 15.0
#: Tour keys hold the last pose this long past a path's end (a ``Tour`` loops after its last key).
_HOLD_S = 3600.0


# ------------------------------------------------------------------------------------------------ paths


@dataclass(frozen=True)
class Anchor:
    """Where the scenarios happen: an eye, a dense view direction (yaw, pitch in radians, z up), the
    scene's walking speed (m/s, the tour's median) and where the pose came from."""

    eye: np.ndarray
    yaw: float
    pitch: float
    speed: float
    source: str
    t: float = 0.0  # tour time of the pose
    tour_speed: float = 0.0  # the tour's median speed before the cap (m/s)

    @property
    def ahead(self) -> np.ndarray:
        """(3,) unit horizontal direction of the view."""
        return np.array([math.cos(self.yaw), math.sin(self.yaw), 0.0])


def forward_of(yaw: float, pitch: float) -> list[float]:
    """The unit view direction of ``yaw`` and ``pitch`` (radians, z up)."""
    c = math.cos(pitch)
    return [c * math.cos(yaw), c * math.sin(yaw), math.sin(pitch)]


def _key(t: float, eye: Sequence[float], yaw: float, pitch: float) -> dict:
    return {"t": float(t), "eye": [float(v) for v in eye], "forward": forward_of(yaw, pitch), "up": [0.0, 0.0, 1.0]}


def _close(keys: list[dict]) -> list[dict]:
    """The keys with the last pose held for ``_HOLD_S`` more: a run longer than the path must not loop back."""
    last = dict(keys[-1])
    last["t"] = keys[-1]["t"] + _HOLD_S
    return keys + [last]


def visible_counts(index, poses: tuple[np.ndarray, np.ndarray, np.ndarray], fov_y: float,
                    viewport: tuple[int, int]) -> np.ndarray:
    """(k,) flat objects (leaf meshes, terrain patches) in the frustum of each pose."""
    from server.select.camera import View, cull_boxes

    flat = np.nonzero(index.flat)[0]
    lo, hi = index.object_lo[flat], index.object_hi[flat]
    eyes, fwds, ups = poses
    return np.array([int(cull_boxes(lo, hi, View.of_pose(e, f, u, fov_y, viewport, index.bounds).planes()).sum())
                     for e, f, u in zip(eyes, fwds, ups)], np.int64)


def max_speed() -> float:
    """The fastest a scenario path moves (m/s): ``SPEED_SHARE`` of the server predictor's teleport speed."""
    from server.select.predict import Predictor

    return SPEED_SHARE * Predictor().teleport_speed


def anchor_of(index, *, viewport: tuple[int, int] = (640, 360), fov_y: float = 60.0) -> Anchor:
    """The scene's viewpoint C when it has one, else the tour pose with the most objects in view
    (61 poses sampled over the tour), else the start pose. The pitch is kept within ±45°; the speed is the
    tour's median, at most ``max_speed()``."""
    from proto.tour import Tour

    keys = list(index.tour) or [{"t": 0.0, **index.start}]
    tour = Tour(keys)
    eyes = tour.eye
    dt = np.diff(tour.t)
    steps = np.linalg.norm(np.diff(eyes, axis=0), axis=1)
    moving = (dt > 0) & (steps > 1e-6)
    diag = float(np.linalg.norm(index.bounds[1] - index.bounds[0]))
    speed = float(np.median(steps[moving] / dt[moving])) if moving.any() else max(diag / 60.0, 0.5)
    viewpoints = (index.meta or {}).get("viewpoints") or {}
    if "C" in viewpoints:
        t, source = float(viewpoints["C"]), "viewpoint C"
    elif tour.duration > 0:
        ts = tour.t[0] + np.linspace(0.0, tour.duration, 61)[:-1]
        counts = visible_counts(index, tour.pose_at(ts), fov_y, viewport)
        i = int(np.argmax(counts)) if counts.max() > 0 else len(ts) // 2
        t = float(ts[i])
        source = (f"tour pose with most objects in view (t={t:.1f} s, {int(counts[i])})" if counts.max() > 0
                  else f"tour midpoint (t={t:.1f} s)")
    else:
        t, source = float(tour.t[0]), "start pose"
    eye, fwd, _ = tour.pose_at(t)
    yaw = math.atan2(fwd[1], fwd[0])
    pitch = float(np.clip(math.atan2(fwd[2], math.hypot(fwd[0], fwd[1])), -math.radians(45), math.radians(45)))
    return Anchor(eye=np.asarray(eye, np.float64), yaw=yaw, pitch=pitch, speed=min(speed, max_speed()), source=source,
                  t=t, tour_speed=speed)


def spin_path(anchor: Anchor, *, hold: float = 4.0, spin: float = 1.0, after: float = 2.0,
              look_up_deg: float = 60.0) -> list[dict]:
    """Stand at the anchor looking up (``look_up_deg``: ceiling or sky, few objects) for ``hold`` s, then
    turn a full 360° about z in ``spin`` s, pitching down to the anchor's dense view in the spin's first
    quarter, and hold that view for ``after`` s."""
    if hold <= 0 or spin <= 0 or after < 0:
        raise ValueError("hold and spin must be positive, after non-negative")
    up = math.radians(look_up_deg)
    keys = [_key(0.0, anchor.eye, anchor.yaw, up), _key(hold, anchor.eye, anchor.yaw, up)]
    n = int(math.ceil(360.0 / STEP_DEG))
    for i in range(1, n + 1):
        s = i / n
        pitch = up + (anchor.pitch - up) * min(1.0, s / 0.25)
        keys.append(_key(hold + s * spin, anchor.eye, anchor.yaw + 2 * math.pi * s, pitch))
    if after > 0:
        keys.append(_key(hold + spin + after, anchor.eye, anchor.yaw + 2 * math.pi, anchor.pitch))
    return _close(keys)


def turn_path(anchor: Anchor, *, walk: float = 4.0, turn_deg: float = 150.0, turn_s: float = 0.15,
              after: float = 3.0, speed: float | None = None) -> list[dict]:
    """Walk straight along the anchor's view for ``walk`` s (at the tour's speed), arriving at the anchor;
    turn ``turn_deg`` (positive: left) in ``turn_s`` s on the spot; walk on along the new view ``after`` s."""
    if walk <= 0 or turn_s <= 0 or after < 0:
        raise ValueError("walk and turn_s must be positive, after non-negative")
    v = anchor.speed if speed is None else float(speed)
    start = anchor.eye - anchor.ahead * v * walk
    keys = [_key(0.0, start, anchor.yaw, anchor.pitch), _key(walk, anchor.eye, anchor.yaw, anchor.pitch)]
    n = max(1, int(math.ceil(abs(turn_deg) / STEP_DEG)))
    for i in range(1, n + 1):
        keys.append(_key(walk + turn_s * i / n, anchor.eye, anchor.yaw + math.radians(turn_deg) * i / n, anchor.pitch))
    yaw = anchor.yaw + math.radians(turn_deg)
    if after > 0:
        end = anchor.eye + np.array([math.cos(yaw), math.sin(yaw), 0.0]) * v * after
        keys.append(_key(walk + turn_s + after, end, yaw, anchor.pitch))
    return _close(keys)


def oscillation_path(anchor: Anchor, *, amplitude: float = 2.0, period: float = 1.0,
                     duration: float = 8.0) -> list[dict]:
    """Forward ``amplitude`` m and back along the anchor's view, a full cycle every ``period`` s (a triangle
    wave: the eye reverses every half period), for ``duration`` s; the view direction is held."""
    if amplitude <= 0 or period <= 0 or duration <= 0:
        raise ValueError("amplitude, period and duration must be positive")
    half = period / 2
    n = int(math.ceil(duration / half))
    keys = [_key(i * half, anchor.eye + anchor.ahead * (amplitude if i % 2 else 0.0), anchor.yaw, anchor.pitch)
            for i in range(n + 1)]
    return _close(keys)


def straight_path(anchor: Anchor, *, duration: float, speed: float) -> list[dict]:
    """A straight walk along the anchor's view at ``speed`` m/s for ``duration`` s, centred on the anchor."""
    if duration <= 0 or speed < 0:
        raise ValueError("duration must be positive and speed non-negative")
    d = anchor.ahead * speed * duration / 2
    return _close([_key(0.0, anchor.eye - d, anchor.yaw, anchor.pitch),
                   _key(duration, anchor.eye + d, anchor.yaw, anchor.pitch)])


def tour_segment(index, start: float, duration: float, step: float = 0.1) -> list[dict]:
    """The store's tour from tour time ``start`` for ``duration`` s, re-timed to begin at 0 (keys every ``step``)."""
    from proto.tour import Tour

    tour = Tour(list(index.tour) or [{"t": 0.0, **index.start}])
    ts = np.arange(0.0, duration + step / 2, step)
    eyes, fwds, ups = tour.pose_at(start + ts)
    keys = [{"t": float(t), "eye": e.tolist(), "forward": f.tolist(), "up": u.tolist()}
            for t, e, f, u in zip(ts, eyes, fwds, ups)]
    return _close(keys)
