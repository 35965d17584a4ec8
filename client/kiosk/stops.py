"""Authored tours → camera keys in client time: paths between stops at bounded speed, a dwell at each stop.

A tour is a list of stops (pose, dwell, caption); the attract playlist is its tours' stops one after the
other, looping from the last back to the first. Between two stops the eye flies in a straight line, or
walks the shortest way round what blocks it on the walkable grid (``proto.walkpath``; a straight line where
the grid knows no walk between them), while the view turns along the great circle (slerp); a leg is cut
into steps of at most ``STEP_DEG`` of turn (and, walking on a grid, one cell of ground), and each step lasts

    max(|Δeye| / speed, 2·tan(δ/2) / turn)

where δ is the step's turn: ``proto.tour.Tour`` blends directions between keys by nlerp, whose angular rate
peaks at 2·tan(δ/2)/δ times the mean mid-step, so this is what keeps every instant, not only the mean of
the leg, within ``turn``. A leg therefore takes at least max(distance/speed, angle/turn). A walk tour keeps
the eye ``eye_height`` above the walkable ground where the grid says where that is.

``Playlist.segment`` gives what the director plays and tells the server (``proto.messages.TourPlan``): a
lead-in leg from wherever the camera is to a stop, then the whole loop from that stop back to it (or only
that stop's dwell, for a visitor's "next stop"). ``Segment.stop_at`` says which stop is current at ``t``
(the one dwelt at, or headed to) for the caption and the heartbeat.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from proto.messages import TourKey
from proto.tour import Tour
from proto.walkable import WalkableGrid
from proto.walkpath import NoPath, along, walk_path

__all__ = ["Stop", "Leg", "Segment", "Playlist", "plan_leg", "walk_route", "playlist_stops", "STEP_DEG", "DETOUR"]

#: A leg's steps turn the view at most this much (nlerp between them then stays within 0.1 % of slerp's rate).
STEP_DEG = 5.0
#: A walk leg is searched for only as far as this many times the straight distance (plus ``DETOUR_M``): a
#: search bounded so keeps a kiosk's legs cheap on a city-sized grid; beyond it the leg is a straight line.
DETOUR = 4.0
DETOUR_M = 50.0
#: Walks between places a playlist remembers (its stops' legs, and the latest lead-ins), so a day's
#: visitors do not grow it.
ROUTES_KEPT = 256
_EPS = 1e-9


@dataclass(frozen=True)
class Stop:
    """One stop of the playlist: ``tour`` and ``index`` (its place in that tour), pose, dwell, captions, and
    how the camera travels to it (its tour's ``mode``, ``speed`` m/s, ``turn`` °/s)."""

    tour: str
    index: int
    eye: np.ndarray
    forward: np.ndarray
    up: np.ndarray
    dwell: float
    caption: dict[str, str] = field(default_factory=dict)
    mode: str = "fly"
    speed: float = 3.0
    turn: float = 45.0

    def text(self, language: str, default: str) -> str:
        """The caption in ``language``, else in the ``default`` language, else ""."""
        return self.caption.get(language) or self.caption.get(default, "")


def playlist_stops(tours: Sequence) -> list[Stop]:
    """The stops of ``tours`` (``client.kiosk.config.TourConfig``, in playlist order) as one list."""
    out = []
    for tour in tours:
        for i, s in enumerate(tour.stops):
            out.append(Stop(tour.name, i, np.asarray(s.eye, np.float64), s.direction, np.asarray(s.up, np.float64),
                            float(s.dwell_s), dict(s.caption), tour.mode, float(tour.speed), float(tour.turn)))
    return out


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), _EPS)


def _angle(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angles (radians) between unit row vectors a, b (n, 3) (robust near 0 and π)."""
    return np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), np.sum(a * b, axis=-1))


def _slerp(a: np.ndarray, b: np.ndarray, s: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """Unit vectors (n, 3) from unit a to unit b (3,) at fractions s (n,); opposite ones turn about ``axis``."""
    theta = float(_angle(a[None], b[None])[0])
    if theta < 1e-7:
        return np.repeat(a[None], len(s), axis=0)
    k = np.cross(a, b)
    if np.linalg.norm(k) < 1e-7:  # opposite: any axis ⟂ a will do; the stop's up keeps the turn level
        k = axis - np.dot(axis, a) * a
        if np.linalg.norm(k) < 1e-7:
            k = np.cross(a, [1.0, 0.0, 0.0]) if abs(a[0]) < 0.9 else np.cross(a, [0.0, 1.0, 0.0])
    k = k / np.linalg.norm(k)
    ang = (s * theta)[:, None]
    return a * np.cos(ang) + np.cross(k, a) * np.sin(ang) + k * np.dot(k, a) * (1 - np.cos(ang))


@dataclass(frozen=True)
class Leg:
    """A path's keys relative to its start: ``t`` (n,), ``eye`` / ``forward`` / ``up`` (n, 3) float64."""

    t: np.ndarray
    eye: np.ndarray
    forward: np.ndarray
    up: np.ndarray


def walk_route(ground: WalkableGrid, a, b) -> np.ndarray | None:
    """The waypoints ((k, 2) x, y) of the shortest walk on ``ground`` from ``a`` to ``b`` (their x, y), or None
    where there is none within ``DETOUR`` × the straight distance (an end off the walkable ground, say)."""
    a, b = np.asarray(a, np.float64)[:2], np.asarray(b, np.float64)[:2]
    limit = DETOUR * float(np.linalg.norm(b - a)) + DETOUR_M
    try:
        return walk_path(ground, a, b, limit=limit)
    except NoPath:
        return None


def plan_leg(a: tuple, b: tuple, *, speed: float, turn: float, walk: bool = False,
             ground: WalkableGrid | None = None, eye_height: float = 1.7, route: np.ndarray | None = None) -> Leg:
    """The path from pose ``a`` to pose ``b`` (each (eye, forward, up), (3,) float) at ≤ ``speed`` m/s and
    ≤ ``turn`` °/s; walking with a ``ground`` grid, along ``route`` (waypoints (k, 2) from a to b, as
    ``walk_route`` gives them; default a straight line) with the eye ``eye_height`` above walkable cells."""
    ea, fa, ua = (np.asarray(v, np.float64) for v in a)
    eb, fb, ub = (np.asarray(v, np.float64) for v in b)
    fa, fb, ua, ub = _unit(fa), _unit(fb), _unit(ua), _unit(ub)
    theta = max(float(_angle(fa[None], fb[None])[0]), float(_angle(ua[None], ub[None])[0]))
    n = max(1, int(np.ceil(np.degrees(theta) / STEP_DEG - 1e-9)))
    walking = walk and ground is not None
    xy = np.asarray(route, np.float64) if walking and route is not None else np.stack([ea[:2], eb[:2]])
    if walking:  # every cell of ground a sample, each corner of the route among them
        xy = along(xy, ground.cell)
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(xy, axis=0), axis=1))])
    length = float(arc[-1])
    if length > _EPS:
        s = np.union1d(arc / length, np.linspace(0.0, 1.0, n + 1))
        eye = np.column_stack([np.interp(s, arc / length, xy[:, 0]), np.interp(s, arc / length, xy[:, 1]),
                               ea[2] + s * (eb[2] - ea[2])])
    else:  # standing (or rising straight up): the turn alone sets the steps
        s = np.linspace(0.0, 1.0, n + 1)
        eye = ea + s[:, None] * (eb - ea)
    if walking:
        z = ground.height(eye[:, :2]) + eye_height
        eye[:, 2] = np.where(np.isfinite(z), z, eye[:, 2])  # off the walkable ground: the line between stops
    forward = _slerp(fa, fb, s, ua)
    up = Tour._orthogonal_up(forward, _slerp(ua, ub, s, fa))  # valid keys even where a stop looks straight down
    step = np.linalg.norm(np.diff(eye, axis=0), axis=1) / speed
    delta = np.maximum(_angle(forward[:-1], forward[1:]), _angle(up[:-1], up[1:]))
    rate = np.where(delta > 1e-12, 2.0 * np.tan(np.minimum(delta, 3.0) / 2.0), 0.0)
    dt = np.maximum(step, rate / np.radians(turn))
    return Leg(np.concatenate([[0.0], np.cumsum(dt)]), eye, forward, up)


@dataclass
class Segment:
    """Keys in client time the camera follows (``t`` (k,) ascending, ``eye``/``forward``/``up`` (k, 3)), and
    the stops it visits: ``stops`` (m,) indices into the playlist, ``arrive`` / ``leave`` (m,) client times."""

    t: np.ndarray
    eye: np.ndarray
    forward: np.ndarray
    up: np.ndarray
    stops: np.ndarray
    arrive: np.ndarray
    leave: np.ndarray
    loops: bool = True

    def __post_init__(self) -> None:
        self._tour = Tour([{"t": float(t), "eye": e, "forward": f, "up": u}
                           for t, e, f, u in zip(self.t, self.eye, self.forward, self.up)])

    @property
    def start(self) -> float:
        return float(self.t[0])

    @property
    def end(self) -> float:
        return float(self.t[-1])

    def pose_at(self, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(eye, forward, up) at client time ``t``, held at the ends outside [start, end]."""
        if t >= self.end:  # the Tour would wrap round to its start there
            return self.eye[-1].copy(), self._tour.forward[-1].copy(), self._tour.up[-1].copy()
        return self._tour.pose_at(max(float(t), self.start))

    def stop_at(self, t: float) -> tuple[int, bool]:
        """(playlist stop index, dwelling there) at ``t``: the stop dwelt at, or the next one headed to."""
        i = int(np.searchsorted(self.leave, t, side="left"))
        if i == len(self.stops):  # past the last dwell: looping, on the way back to the first stop
            return (int(self.stops[0]), False) if self.loops else (int(self.stops[-1]), True)
        return int(self.stops[i]), bool(self.arrive[i] <= t <= self.leave[i])

    def keys(self, limit: int) -> list[TourKey]:
        """The first ``limit`` keys as ``TourKey`` s (client time), for a ``TourPlan``."""
        return [TourKey(t=float(t), eye=e.tolist(), forward=f.tolist(), up=u.tolist())
                for t, e, f, u in zip(self.t[:limit], self.eye[:limit], self.forward[:limit], self.up[:limit])]


class Playlist:
    """The attract loop over ``stops`` (``Stop``, in order, looping); walk legs follow ``ground`` when given."""

    def __init__(self, stops: Sequence[Stop], *, ground: WalkableGrid | None = None, eye_height: float = 1.7) -> None:
        if not stops:
            raise ValueError("a playlist needs at least one stop")
        self.stops = list(stops)
        self.ground, self.eye_height = ground, float(eye_height)
        self._routes: dict[tuple, np.ndarray | None] = {}  # the walk between two places, searched once

    def __len__(self) -> int:
        return len(self.stops)

    def pose(self, i: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        s = self.stops[i % len(self.stops)]
        return s.eye, s.forward, s.up

    def leg(self, a: tuple, i: int) -> Leg:
        """From pose ``a`` to stop ``i``, as stop ``i``'s tour travels."""
        s = self.stops[i % len(self.stops)]
        route = None
        if s.mode == "walk" and self.ground is not None:
            key = (tuple(np.round(np.asarray(a[0], np.float64)[:2], 3)), tuple(np.round(s.eye[:2], 3)))
            if key not in self._routes:
                if len(self._routes) >= ROUTES_KEPT:  # lead-ins from where visitors left the camera: drop the oldest
                    self._routes.pop(next(iter(self._routes)))
                self._routes[key] = walk_route(self.ground, a[0], s.eye)
            route = self._routes[key]
        return plan_leg(a, self.pose(i), speed=s.speed, turn=s.turn, walk=s.mode == "walk", ground=self.ground,
                        eye_height=self.eye_height, route=route)

    def segment(self, pose: tuple, t0: float, stop: int, *, loop: bool = True, rate: float = 1.0) -> Segment:
        """From ``pose`` at client time ``t0`` to ``stop`` and its dwell; with ``loop``, on round every stop
        back to ``stop`` (arriving there at ``Segment.end``, ready for the next loop). ``rate`` < 1 plays it
        slower (legs and dwells alike: the slow attract loop outside opening hours)."""
        if not (np.isfinite(rate) and 0 < rate <= 1):
            raise ValueError(f"rate must lie in (0, 1], got {rate!r}")
        n = len(self.stops)
        order = [(stop + k) % n for k in range(n)] + [stop] if loop else [stop]
        ts, eyes, fs, us, arrive, leave = [], [], [], [], [], []
        t, here = float(t0), tuple(np.asarray(v, np.float64) for v in pose)
        for k, i in enumerate(order):
            leg = self.leg(here, i)
            if leg.t[-1] > _EPS or not ts:
                keep = slice(1, None) if ts else slice(None)
                ts.append(t + leg.t[keep]); eyes.append(leg.eye[keep]); fs.append(leg.forward[keep]); us.append(leg.up[keep])
                t += float(leg.t[-1])
            here = self.pose(i)
            if k == len(order) - 1 and loop:
                break  # back at the first stop: the next loop dwells there
            arrive.append(t)
            dwell = self.stops[i].dwell
            if dwell > 0:
                t += dwell
                ts.append([t]); eyes.append(here[0][None]); fs.append(here[1][None]); us.append(here[2][None])
            leave.append(t)
        if len(np.concatenate(ts)) == 1:  # one stop, no dwell, already there: hold it
            ts.append([t + 1.0]); eyes.append(here[0][None]); fs.append(here[1][None]); us.append(here[2][None])
        stops_seen = order[:-1] if loop else order
        t0 = float(t0)
        slow = (lambda x: t0 + (np.asarray(x, np.float64) - t0) / rate) if rate != 1.0 else np.asarray
        return Segment(slow(np.concatenate(ts)), np.concatenate(eyes), np.concatenate(fs), np.concatenate(us),
                       np.asarray(stops_seen, np.int64), slow(arrive), slow(leave), loop)
