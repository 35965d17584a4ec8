"""The navigation the path prediction knows: tour plans (exact future poses) and where a camera can go.

Zach (2002, 4.3) adapts path prediction to the degrees of freedom the interface
gives; a kiosk's navigation is known to the server outright, so the prediction
uses it instead of extrapolating:

- **A tour plan** (``proto.messages.TourPlan``) says where the camera will be:
  while a ``Plan`` covers a time, the predictor returns the plan's pose there,
  interpolated as ``proto.tour.Tour`` does but played once (a plan does not
  loop); outside its keys, or after an empty plan (the visitor drives), the
  prediction is linear again. A new plan replaces the one held from its first
  key's time on; the stretch between an older plan's last kept key and a new
  plan's first is not covered (the visitor may drive there).
- **Where the camera can go** (``Navigable``): in walk mode the linearly
  predicted eye stays at ``eye_height`` above walkable ground
  (``proto.walkable.WalkableGrid``) — a predicted path that runs into a wall
  stops there, or slides along it when it meets it at an angle — and, in any
  mode, inside the hello's navigation bounds.

Pure: arrays in and out, no clock, no I/O.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from types import SimpleNamespace
from typing import Sequence

import numpy as np

from proto.errors import ProtocolError
from proto.messages import MAX_PLAN_KEYS, Navigation, TourKey, TourPlan
from proto.tour import Tour
from proto.walkable import WalkableGrid

from .snapshot import dump_fields, load_fields

__all__ = ["Plan", "Navigable", "plan_after", "check_plan", "PLAN_MARGIN"]

#: Plan keys may lie this far outside the scene's bounds (m), or the scene's diagonal if larger: a camera
#: stands off to look at a scene, but a key kilometres away is a mistake (or a unit error) in the plan.
PLAN_MARGIN = 100.0


@dataclass(frozen=True, eq=False)
class Plan:
    """The camera path a client announced, over client time.

    t      : (k,) float64 key times, ascending
    x      : (k, 9) float64 eye, unit forward, unit up of each key
    joined : (k,) bool — the stretch from key i − 1 to key i belongs to the plan (False where one plan ended
             and the next began; always False for key 0)
    issued : the client time of the message that made the plan (``TourPlan.t``): a resumed session keeps a
             plan unless the hello's own is newer
    """

    t: np.ndarray
    x: np.ndarray
    joined: np.ndarray
    issued: float

    STATE = ("t", "x", "joined", "issued")

    @classmethod
    def of(cls, keys: Sequence[TourKey], issued: float) -> "Plan":
        """A plan from tour keys in client time (validated ``TourKey``s, ascending t)."""
        tour = Tour(keys)
        x = np.concatenate([tour.eye, tour.forward, tour.up], axis=1)
        joined = np.ones(len(tour.t), bool)
        joined[0] = False
        return cls(tour.t.copy(), x, joined, float(issued))

    def __len__(self) -> int:
        return int(self.t.size)

    def covers(self, times: np.ndarray) -> np.ndarray:
        """(n,) bool: the plan says the pose at each of ``times`` (n,)."""
        times = np.asarray(times, np.float64)
        i = np.searchsorted(self.t, times, side="right") - 1  # the key at or before
        at_key = (i >= 0) & (self.t[np.clip(i, 0, None)] == times)
        inner = (i >= 0) & (i + 1 < self.t.size)
        return at_key | (inner & self.joined[np.clip(i + 1, 0, self.t.size - 1)])

    def poses(self, times: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Eye, forward, up (each (n, 3) float64) at ``times`` (n,) that the plan covers: linear eye, nlerp'd
        directions between the keys around each time, as ``proto.tour.Tour`` interpolates."""
        times = np.asarray(times, np.float64)
        k = self.t.size
        i = np.clip(np.searchsorted(self.t, times, side="right") - 1, 0, max(k - 2, 0))
        j = np.minimum(i + 1, k - 1)
        span = self.t[j] - self.t[i]
        w = np.where(span > 0, (times - self.t[i]) / np.where(span > 0, span, 1.0), 0.0)
        w = np.clip(w, 0.0, 1.0)[:, None]
        x = (1 - w) * self.x[i] + w * self.x[j]
        f = x[:, 3:6]
        n = np.linalg.norm(f, axis=1, keepdims=True)
        f = np.where(n > 1e-9, f / np.maximum(n, 1e-300), self.x[i, 3:6])  # opposite keys: hold the earlier
        u = x[:, 6:9] - np.sum(x[:, 6:9] * f, axis=1, keepdims=True) * f
        nu = np.linalg.norm(u, axis=1, keepdims=True)
        u = np.where(nu > 1e-9, u / np.maximum(nu, 1e-300), Tour._orthogonal_up(f, self.x[i, 6:9]))
        return x[:, :3], f, u

    def before(self, t: float) -> "Plan | None":
        """The part of the plan before time ``t`` (None when nothing is left)."""
        keep = self.t < t
        if not keep.any():
            return None
        return Plan(self.t[keep], self.x[keep], self.joined[keep], self.issued)

    def since(self, t: float) -> "Plan":
        """The plan without keys that end before ``t``: the last key at or before ``t`` stays (it starts the
        stretch ``t`` is in)."""
        first = max(int(np.searchsorted(self.t, t, side="right")) - 1, 0)
        joined = self.joined[first:].copy()
        joined[0] = False
        return Plan(self.t[first:], self.x[first:], joined, self.issued)

    def then(self, new: "Plan") -> "Plan":
        """This plan up to ``new``'s first key, then ``new`` (not joined to it)."""
        head = self.before(float(new.t[0]))
        if head is None:
            return new
        return Plan(np.concatenate([head.t, new.t]), np.concatenate([head.x, new.x]),
                    np.concatenate([head.joined, new.joined]), new.issued)

    def to_state(self) -> dict:
        return dump_fields(self, self.STATE)

    @classmethod
    def from_state(cls, state) -> "Plan | None":
        """``to_state``'s data back (None for None); ValueError if it does not fit."""
        if state is None:
            return None
        holder = SimpleNamespace(t=np.zeros(0), x=np.zeros((0, 9)), joined=np.zeros(0, bool), issued=0.0)
        load_fields(holder, state, cls.STATE, "predictor.plan", variable=("t", "x", "joined"))
        t, x, joined = holder.t, holder.x, holder.joined
        if not (t.size == x.shape[0] == joined.size) or t.size == 0 or np.any(np.diff(t) < 0):
            raise ValueError("predictor.plan: keys, poses and joins do not match")
        return cls(t, x, joined, float(holder.issued))


def check_plan(message: TourPlan, scene_bounds: np.ndarray, now: float | None = None) -> None:
    """Refuse a plan the prediction cannot use (``ProtocolError("invalid", …)`` naming the field).

    scene_bounds : (2, 3) the scene's [min, max]; a key beyond ``PLAN_MARGIN`` (or the scene's diagonal)
        outside them is refused
    now : the client time the plan is judged against (the newest camera sample, or the message's own
        ``t`` if later): a plan whose last key precedes it is in the past
    """
    keys = message.keys
    if len(keys) > MAX_PLAN_KEYS:
        raise ProtocolError("invalid", f"tour_plan.keys: {len(keys)} keys, at most {MAX_PLAN_KEYS}")
    if not keys:
        return
    lo, hi = np.asarray(scene_bounds, np.float64)
    margin = max(PLAN_MARGIN, float(np.linalg.norm(hi - lo)))
    eye = np.array([k.eye for k in keys], np.float64)
    far = np.flatnonzero(((eye < lo - margin) | (eye > hi + margin)).any(axis=1))
    if far.size:
        i = int(far[0])
        raise ProtocolError("invalid", f"tour_plan.keys[{i}].eye {eye[i].tolist()} lies more than {margin:.0f} m "
                            f"outside the scene's bounds {lo.tolist()}…{hi.tolist()}")
    ref = max(float(message.t), -math.inf if now is None else float(now))
    if keys[-1].t < ref:
        raise ProtocolError("invalid", f"tour_plan.keys end at t={keys[-1].t:g}, before the client's time "
                            f"t={ref:g}: the plan is in the past")


def plan_after(current: Plan | None, message: TourPlan, latest: float | None) -> Plan | None:
    """The plan held after ``message`` (checked with ``check_plan`` first): an empty message ends the plan
    at its ``t`` (the visitor drives); otherwise the message's keys replace the plan from their first key's
    time. Keys wholly before the newest sample ``latest`` are dropped first; a plan that would still hold
    more than ``MAX_PLAN_KEYS`` keys is refused."""
    if current is not None and latest is not None:
        current = current.since(latest)
    if not message.keys:
        return None if current is None else current.before(float(message.t))
    new = Plan.of(message.keys, message.t)
    merged = new if current is None else current.then(new)
    if len(merged) > MAX_PLAN_KEYS:
        raise ProtocolError("invalid", f"tour_plan.keys: with the {len(merged) - len(new)} keys still held from "
                            f"the last plan it would hold {len(merged)}, at most {MAX_PLAN_KEYS}")
    return merged


@dataclass(frozen=True, eq=False)
class Navigable:
    """Where the hello's navigation lets the camera go.

    grid       : the scene's walkable grid, in walk mode (None: no ground constraint)
    eye_height : the eye above the ground in walk mode (m)
    bounds     : (2, 3) [min, max] the camera never leaves, or None
    """

    grid: WalkableGrid | None
    eye_height: float = 1.7
    bounds: np.ndarray | None = None

    @classmethod
    def of(cls, navigation: Navigation | None, grid: WalkableGrid | None) -> "Navigable | None":
        """The constraint of a hello's ``navigation`` (None when it constrains nothing)."""
        if navigation is None:
            return None
        walk = grid if navigation.mode == "walk" else None
        bounds = None if navigation.bounds is None else np.asarray(navigation.bounds, np.float64)
        if walk is None and bounds is None:
            return None
        return cls(walk, float(navigation.eye_height), bounds)

    def confine(self, start: np.ndarray, ends: np.ndarray) -> np.ndarray:
        """Eyes ``ends`` (n, 3), extrapolated from the eye ``start`` (3,), moved to where the camera can be.

        Walking (a grid, and ``start`` above a walkable cell): the straight path from ``start`` to each end
        stops before its first cell that is not walkable or out of bounds; what is left of the motion then
        slides along whichever axis goes further; the eye is set at ``eye_height`` above the ground reached.
        Otherwise each end is clamped into the bounds.
        """
        start = np.asarray(start, np.float64)
        ends = np.asarray(ends, np.float64).reshape(-1, 3)
        grid = self.grid
        if grid is not None and grid.walkable(start[:2])[0] and self._inside(start[None, :2])[0]:
            xy = self._walk(start[:2], ends[:, :2] - start[:2])
            out = np.column_stack([xy, grid.height(xy) + self.eye_height])
        else:
            out = ends.copy()
        if self.bounds is not None:
            out = np.clip(out, self.bounds[0], self.bounds[1])
        return out

    def _inside(self, xy: np.ndarray) -> np.ndarray:
        if self.bounds is None:
            return np.ones(len(xy), bool)
        return ((xy >= self.bounds[0, :2]) & (xy <= self.bounds[1, :2])).all(axis=1)

    def _open(self, xy: np.ndarray) -> np.ndarray:
        """(...,) bool: points (..., 2) a walker may stand on."""
        flat = xy.reshape(-1, 2)
        return (self.grid.walkable(flat) & self._inside(flat)).reshape(xy.shape[:-1])

    def _march(self, start: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """From each ``start`` (n, 2) along ``d`` (n, 2), in steps of at most half a cell: where each stops
        (n, 2) and the share of ``d`` covered (n,)."""
        length = np.linalg.norm(d, axis=1)
        m = max(1, int(math.ceil(float(length.max(initial=0.0)) / (0.5 * self.grid.cell))))
        s = np.linspace(0.0, 1.0, m + 1)
        pts = start[:, None, :] + s[None, :, None] * d[:, None, :]  # (n, m + 1, 2)
        ok = self._open(pts)
        ok[:, 0] = True  # where it stands now
        blocked = ~ok
        first = np.where(blocked.any(axis=1), np.argmax(blocked, axis=1), m + 1)
        reached = s[first - 1]
        return start + reached[:, None] * d, reached

    def _walk(self, start: np.ndarray, d: np.ndarray) -> np.ndarray:
        """Where walking ``d`` (n, 2) from ``start`` (2,) ends (n, 2): stopped at a wall, then slid along it."""
        p, done = self._march(np.broadcast_to(start, d.shape).copy(), d)
        rest = (1.0 - done)[:, None] * d
        if not (done < 1.0).any():
            return p
        along_x, share_x = self._march(p, rest * [1.0, 0.0])
        along_y, share_y = self._march(p, rest * [0.0, 1.0])
        gain_x, gain_y = share_x * np.abs(rest[:, 0]), share_y * np.abs(rest[:, 1])
        return np.where((gain_x >= gain_y)[:, None], along_x, along_y)
