"""The visitor's constrained navigation: walking on the walkable grid with collision, flying within bounds.

``ConstrainedWalk`` walks at ``eye_height`` above the ground of a ``proto.walkable.WalkableGrid``: a step
into a cell no one can stand on (NaN: a wall, an object, off the grid) or up a ledge higher than
``max_step`` does not happen — the walker slides along it (the step's x or y part alone) or stops. A
diagonal step must clear both cells beside the corner it passes, so no one squeezes between two walls
touching at a corner. Steps are at most half a cell, so nothing thinner than a cell is walked through.
The eye follows the ground up and down at a bounded rate, and the whole motion — along and up —
stays within ``speed``: the cap the hello announces. A walker placed on a blocked cell (a tour's pose
taken over above a wall) may walk off it, never onto one.

``BoundedFly`` flies within the box; both clamp the eye into ``bounds`` (the config's, else the scene's).
``KioskNavigator`` holds one of the two for the config's mode: a kiosk does not switch modes.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from proto.walkable import WalkableGrid
from ..navigation import Driving, FlyController, WalkController

__all__ = ["ConstrainedWalk", "BoundedFly", "KioskNavigator", "MAX_STEP"]

#: The highest ledge a walker steps up or down (m): a stair's riser, not a stage.
MAX_STEP = 0.5
_EPS = 1e-9


def _box(bounds: Any) -> np.ndarray:
    b = np.asarray(bounds, np.float64).reshape(2, 3)
    if not np.all(b[0] <= b[1]):
        raise ValueError(f"bounds must be [min corner, max corner], got {b.tolist()}")
    return b


class BoundedFly(FlyController):
    """Free flight whose eye never leaves ``bounds`` (2, 3) [min corner, max corner]; no Shift boost."""

    def __init__(self, start: Any, *, bounds: Any, speed: float = 2.0, max_turn: float = 60.0,
                 sensitivity: float = 0.15) -> None:
        self.bounds = _box(bounds)
        super().__init__(start, speed=speed, fast=1.0, max_turn=max_turn, sensitivity=sensitivity)

    def _place(self, eye: np.ndarray, forward: np.ndarray, up: np.ndarray) -> None:
        super()._place(np.clip(eye, self.bounds[0], self.bounds[1]), forward, up)

    def _move(self, dt: float) -> None:
        super()._move(dt)
        self.eye = np.clip(self.eye, self.bounds[0], self.bounds[1])


class ConstrainedWalk(WalkController):
    """Walking with collision on ``grid`` (None: level walking at the start height) within ``bounds``."""

    def __init__(self, start: Any, *, bounds: Any, grid: WalkableGrid | None = None, eye_height: float = 1.7,
                 speed: float = 2.0, max_turn: float = 60.0, sensitivity: float = 0.15,
                 max_step: float = MAX_STEP) -> None:
        self.bounds, self.grid = _box(bounds), grid
        self.eye_height, self.max_step = float(eye_height), float(max_step)
        super().__init__(start, speed=speed, fast=1.0, max_turn=max_turn, sensitivity=sensitivity)

    def _place(self, eye: np.ndarray, forward: np.ndarray, up: np.ndarray) -> None:
        super()._place(np.clip(eye, self.bounds[0], self.bounds[1]), forward, up)

    def _ground(self, xy: np.ndarray) -> float:
        return float(self.grid.height(np.asarray(xy)[None])[0]) if self.grid is not None else np.nan

    def _free(self, a: np.ndarray, b: np.ndarray) -> bool:
        """Whether a step from xy ``a`` to xy ``b`` (each (2,)) may be taken."""
        lo, hi = self.bounds[0, :2], self.bounds[1, :2]
        if np.any(b < lo - _EPS) or np.any(b > hi + _EPS):
            return False
        if self.grid is None:
            return True
        ha = self._ground(a)
        if not np.isfinite(ha):  # standing where no one can: any way out is allowed
            return True
        hb = self._ground(b)
        return bool(np.isfinite(hb) and abs(hb - ha) <= self.max_step)

    def _move(self, dt: float) -> None:
        h = self.held
        direction = self._direction(("w" in h) - ("s" in h), ("d" in h) - ("a" in h), 0)[:2]
        budget = self.speed * dt  # metres this frame, along and up together
        # The eye follows the ground first (at most half the budget), the rest is walking.
        ground = self._ground(self.eye[:2])
        target = ground + self.eye_height if np.isfinite(ground) else self.eye[2]
        rise = float(np.clip(target - self.eye[2], -budget / 2, budget / 2))
        self.eye[2] += rise
        n = float(np.linalg.norm(direction))
        if n > _EPS:
            along = np.sqrt(max(budget * budget - rise * rise, 0.0))
            step = direction / n * along
            cell = self.grid.cell / 2 if self.grid is not None else max(along, _EPS)
            k = max(1, int(np.ceil(along / cell)))
            xy = self.eye[:2].copy()
            for _ in range(k):
                d = step / k
                if self._free(xy, xy + d) and self._free(xy, xy + [d[0], 0.0]) and self._free(xy, xy + [0.0, d[1]]):
                    xy = xy + d
                elif d[0] and self._free(xy, xy + [d[0], 0.0]):
                    xy = xy + [d[0], 0.0]
                elif d[1] and self._free(xy, xy + [0.0, d[1]]):
                    xy = xy + [0.0, d[1]]
                else:
                    break
            self.eye[:2] = xy
        self.eye = np.clip(self.eye, self.bounds[0], self.bounds[1])
        self.height = float(self.eye[2])


class KioskNavigator(Driving):
    """The visitor's camera in the config's mode ("walk" or "fly"), placed where the attract loop left it.

    Speeds and turns are the config's caps (announced in the hello); Shift does not speed up.
    """

    def __init__(self, mode: str, *, bounds: Any, max_speed: float, max_turn: float, eye_height: float = 1.7,
                 grid: WalkableGrid | None = None, start: Any = None) -> None:
        if mode not in ("walk", "fly"):
            raise ValueError(f"mode must be walk or fly, got {mode!r}")
        self.mode, self.bounds, self.grid = mode, _box(bounds), grid
        self.max_speed, self.max_turn, self.eye_height = float(max_speed), float(max_turn), float(eye_height)
        origin = start if start is not None else ((0.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))
        self.controller: ConstrainedWalk | BoundedFly = self._make(origin)

    def _make(self, start: Any) -> ConstrainedWalk | BoundedFly:
        if self.mode == "walk":
            return ConstrainedWalk(start, bounds=self.bounds, grid=self.grid, eye_height=self.eye_height,
                                   speed=self.max_speed, max_turn=self.max_turn)
        return BoundedFly(start, bounds=self.bounds, speed=self.max_speed, max_turn=self.max_turn)

    def place(self, start: Any, t: float | None = None) -> None:
        """Put the camera at ``start`` (a pose) at client time ``t``; held keys and pending turns are dropped."""
        self.controller = self._make(start)
        self.controller._t = t
