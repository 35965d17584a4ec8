"""Camera tours a scene gets at build time: an orbit round it, a walk through its streets, a flyover above them.

A tour is a list of keys {"t", "eye", "forward", "up"} (``proto.messages.TourKey``),
z up; the client plays it back with linear interpolation (``proto.tour.Tour``),
so keys are dense enough (every half second) for the path to look smooth, and
the last key repeats the first so that the tour loops without a jump.

- ``orbit_tour`` — round and over the whole scene, for scenes that come without a tour;
- ``walk_tour`` — a person's walk through the densest blocks (``server.scene.streets``):
  ``EYE_HEIGHT`` above the walkable ground, at ``WALK_SPEED``, never in a building,
  looking ahead along the path and turning no faster than ``WALK_TURN``;
- ``flyover_tour`` — a longer loop of the same kind, smoothed wide, ``FLY_HEIGHT``
  above the ground and at least ``ROOF_CLEARANCE`` above every roof and treetop
  within ``FLY_REACH``, at ``FLY_SPEED``, looking ahead and down.

A store keeps its tours by name (``named_tours``); its ``tour`` is the default one,
what a client that names none is sent.
"""

from __future__ import annotations

import math

import numpy as np
from scipy import ndimage

from proto.walkable import WalkableGrid

from .index import MESH, TREES
from .streets import StreetLoop, dense_blocks, footprints, open_ground, resample_loop, smooth_within, street_loop
from .walkable import GROUND_CLASSES

__all__ = ["orbit_tour", "walk_tour", "flyover_tour", "scene_tours", "named_tours", "default_tour_name", "tour_for",
           "TOUR_KINDS", "EYE_HEIGHT", "WALK_SPEED", "WALK_TURN", "FLY_SPEED", "FLY_HEIGHT", "ROOF_CLEARANCE",
           "FLY_REACH", "KEY_STEP", "MIN_WALK", "MIN_FLY", "MIN_FLY_SPREAD"]

#: What a tour is: a walk at eye height, a flyover above the roofs, an orbit of the whole scene, or the tour
#: that came with the scene (its author's: the auditorium's A → B → C, the demo's flight).
TOUR_KINDS = ("walk", "flyover", "orbit", "scene")
#: Seconds between a generated tour's keys.
KEY_STEP = 0.5

#: Eye height of a walking person above the ground (m).
EYE_HEIGHT = 1.7
#: Walking pace (m/s).
WALK_SPEED = 1.4
#: A walk's loop lasts at most this long (s).
WALK_SECONDS = 420.0
#: A loop shorter than this (m) is no walk: the scene has too little open ground between its buildings.
MIN_WALK = 30.0
#: The view looks at the path this far ahead (m) ...
LOOK_AHEAD = 4.0
#: ... and turns at most this fast (degrees/s), ...
WALK_TURN = 60.0
#: ... this far below the horizon (degrees).
WALK_PITCH = -5.0
#: Corners are rounded over this distance (m, the smoothing's σ) where the rounded walk keeps its clearance.
WALK_SMOOTH = 2.0

#: Flying speed (m/s).
FLY_SPEED = 8.0
#: A flyover's loop lasts at most this long (s) ...
FLY_SECONDS = 150.0
#: ... and at least this long (m): a scene smaller than that gets no flyover, nor one whose buildings all lie
#: within this (m) of each other.
MIN_FLY = 120.0
MIN_FLY_SPREAD = 40.0
#: Height above the ground (m) ...
FLY_HEIGHT = 40.0
#: ... and at least this above every roof and treetop ...
ROOF_CLEARANCE = 15.0
#: ... within this distance (m) of the camera.
FLY_REACH = 20.0
#: The flight path's smoothing (m, σ), and the height's window.
FLY_SMOOTH = 15.0
#: The view looks at the path this far ahead (m), turns at most this fast (degrees/s), this far down (degrees).
FLY_LOOK_AHEAD = 30.0
FLY_TURN = 30.0
FLY_PITCH = -30.0


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
    n = max(8, round(duration / step))
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


def _yaw(xy: np.ndarray, ahead: int, limit: float) -> np.ndarray:
    """(n,) headings (radians) of a closed loop's samples ``xy`` (n, 2): towards the sample ``ahead`` further on,
    changing at most ``limit`` from one sample to the next, the first equal to what follows the last.

    The rate limit runs three times round the loop and the middle round is kept: by then it no longer depends
    on where it started, so the loop closes without a jump.
    """
    n = len(xy)
    d = np.roll(xy, -max(1, ahead), axis=0) - xy
    raw = np.arctan2(d[:, 1], d[:, 0])
    ext = np.unwrap(np.append(raw, raw[0]))
    wind = ext[-1] - ext[0]  # 2π × the loop's winding number
    target = np.concatenate([ext[:-1] + wind * k for k in range(3)])
    out = np.empty_like(target)
    out[0] = target[0]
    for i in range(1, target.size):  # a rate limit is sequential; it runs over keys, a few hundred
        out[i] = out[i - 1] + min(max(target[i] - out[i - 1], -limit), limit)
    return out[n:2 * n] - wind


def _keys(xy: np.ndarray, z: np.ndarray, yaw: np.ndarray, pitch: float, dt: float) -> list[dict]:
    """Keys of a closed loop: eyes (n, 2) + heights (n,), headings (n,), one pitch (radians), ``dt`` s apart; the
    first key repeated as the last."""
    cp = math.cos(pitch)
    fwd = np.column_stack([cp * np.cos(yaw), cp * np.sin(yaw), np.full(len(yaw), math.sin(pitch))])
    eye = np.column_stack([xy, z])
    keys = [{"t": round(i * dt, 6), "eye": e.tolist(), "forward": f.tolist(), "up": [0.0, 0.0, 1.0]}
            for i, (e, f) in enumerate(zip(eye, fwd))]
    keys.append({**keys[0], "t": round(len(keys) * dt, 6)})
    return keys


def _chords_on(grid: WalkableGrid, xy: np.ndarray) -> bool:
    """Every straight step between consecutive points ``xy`` (n, 2) and back to the first stays on ``grid``."""
    a = xy
    b = np.roll(xy, -1, axis=0)
    m = int(np.ceil(np.linalg.norm(b - a, axis=1).max() / (0.25 * grid.cell))) + 1
    s = np.linspace(0.0, 1.0, max(m, 2))
    return bool(grid.walkable((a[:, None] + s[None, :, None] * (b - a)[:, None]).reshape(-1, 2)).all())


def walk_tour(grid: WalkableGrid, loop: StreetLoop) -> list[dict] | None:
    """A walk round ``loop`` (``server.scene.streets.street_loop``): keys every ``KEY_STEP`` s at ``WALK_SPEED``,
    the eye ``EYE_HEIGHT`` above ``grid``'s ground; None if the keyed walk would leave walkable ground."""
    step = min(0.25, 0.5 * grid.cell)
    fine, _ = resample_loop(loop.points, step)
    keep = open_ground(grid, 0.5 * loop.clearance, largest=False)
    if keep is not None:  # round the corners where that keeps half the loop's clearance
        fine = smooth_within(fine, WALK_SMOOTH / step, keep.walkable)
    xy, length = resample_loop(np.vstack([fine, fine[:1]]), WALK_SPEED * KEY_STEP)
    ground = grid.height(xy)
    if not np.isfinite(ground).all() or not _chords_on(grid, xy):
        return None
    n = len(xy)
    dt = length / n / WALK_SPEED
    yaw = _yaw(xy, round(LOOK_AHEAD / (length / n)), math.radians(WALK_TURN) * dt)
    return _keys(xy, ground + EYE_HEIGHT, yaw, math.radians(WALK_PITCH), dt)


class _Tops:
    """The highest top of any obstacle near a point: boxes' tops on a plan raster, spread over a reach."""

    def __init__(self, grid: WalkableGrid, lo: np.ndarray, hi: np.ndarray, reach: float) -> None:
        ext = grid.bounds[1] - grid.bounds[0]
        self.origin = np.asarray(grid.origin)
        self.cell = max(grid.cell, reach / 4)
        nx, ny = (int(v) for v in np.maximum(np.ceil(ext / self.cell), 1))
        top = np.full(ny * nx, -np.inf)
        if len(lo):
            a = np.clip(np.floor((lo[:, :2] - self.origin) / self.cell).astype(np.int64), 0, [nx - 1, ny - 1])
            b = np.clip(np.floor((hi[:, :2] - self.origin) / self.cell).astype(np.int64), 0, [nx - 1, ny - 1])
            w, h = b[:, 0] - a[:, 0] + 1, b[:, 1] - a[:, 1] + 1
            box = np.repeat(np.arange(len(lo)), w * h)
            k = np.arange(box.size) - np.repeat(np.cumsum(w * h) - w * h, w * h)
            cells = (a[box, 1] + k // w[box]) * nx + a[box, 0] + k % w[box]
            np.maximum.at(top, cells, hi[box, 2])
        size = 2 * int(np.ceil(reach / self.cell)) + 1
        self.top = ndimage.maximum_filter(top.reshape(ny, nx), size=size, mode="nearest")

    def __call__(self, xy: np.ndarray) -> np.ndarray:
        """(n,) highest top within the reach of points ``xy`` (n, 2); −inf where there is none."""
        ny, nx = self.top.shape
        ij = np.floor((xy - self.origin) / self.cell).astype(np.int64)
        return self.top[np.clip(ij[:, 1], 0, ny - 1), np.clip(ij[:, 0], 0, nx - 1)]


def _obstacles(index) -> tuple[np.ndarray, np.ndarray]:
    """Boxes lo (n, 3), hi (n, 3) of everything a flyer must clear: mesh objects that are not ground, tree groups."""
    names = np.array([c.lower() for c in index.class_names] or [""], object)
    ground = np.isin(names[index.object_class], GROUND_CLASSES)
    pick = ((index.object_kind == MESH) & ~ground) | (index.object_kind == TREES)
    return index.object_lo[pick].astype(np.float64), index.object_hi[pick].astype(np.float64)


def flyover_tour(grid: WalkableGrid, loop: StreetLoop, tops_lo: np.ndarray, tops_hi: np.ndarray) -> list[dict]:
    """A flight round ``loop``: keys every ``KEY_STEP`` s at ``FLY_SPEED``, at least ``FLY_HEIGHT`` above the
    ground and ``ROOF_CLEARANCE`` above the tops of the obstacle boxes ``tops_lo``, ``tops_hi`` (n, 3) within
    ``FLY_REACH``, looking ahead and ``FLY_PITCH`` down.

    The height is a running mean of a running maximum of what each key asks, over one window: every value
    the mean takes in is the maximum over a window that holds the key, so the mean never dips below it.
    """
    fine, _ = resample_loop(loop.points, 1.0)
    fine = ndimage.gaussian_filter1d(fine, FLY_SMOOTH, axis=0, mode="wrap")
    xy, length = resample_loop(np.vstack([fine, fine[:1]]), FLY_SPEED * KEY_STEP)
    n = len(xy)
    spacing = length / n
    walk = np.isfinite(grid.ground)
    _, (ri, ci) = ndimage.distance_transform_edt(~walk, return_indices=True)
    row, col, _ = grid.cells(xy)
    ground = grid.ground[ri[row, col], ci[row, col]].astype(np.float64)  # under a roof: the nearest street's
    need = np.maximum(ground + FLY_HEIGHT, _Tops(grid, tops_lo, tops_hi, FLY_REACH)(xy) + ROOF_CLEARANCE)
    window = min(n, 2 * round(FLY_SMOOTH / spacing) + 1)
    z = ndimage.uniform_filter1d(ndimage.maximum_filter1d(need, window, mode="wrap"), window, mode="wrap")
    z = np.maximum(z, need)  # the mean's rounding
    dt = spacing / FLY_SPEED
    yaw = _yaw(xy, round(FLY_LOOK_AHEAD / spacing), math.radians(FLY_TURN) * dt)
    return _keys(xy, z, yaw, math.radians(FLY_PITCH), dt)


def scene_tours(index, grid: WalkableGrid) -> dict[str, dict]:
    """The street tours of a scene (its ``SceneIndex`` and walkable grid): {"walk": {"kind", "keys"},
    "flyover": {...}}, each where the scene's streets allow one (a walk of at least ``MIN_WALK`` m; a
    flyover of at least ``MIN_FLY`` m over buildings spread over ``MIN_FLY_SPREAD`` m or more); empty for a
    scene without buildings or open ground."""
    lo, hi = footprints(index)
    blocks = dense_blocks(grid, lo, hi)
    if len(blocks) == 0 or not np.isfinite(grid.ground).any():
        return {}
    out: dict[str, dict] = {}
    loop = street_loop(grid, blocks, WALK_SPEED * WALK_SECONDS, MIN_WALK)
    keys = walk_tour(grid, loop) if loop is not None else None
    if keys is not None:
        out["walk"] = {"kind": "walk", "keys": keys}
    if float(np.max(hi.max(axis=0) - lo.min(axis=0))) < MIN_FLY_SPREAD:
        return out  # a flight round buildings a single look takes in circles over empty ground
    flight = street_loop(grid, blocks, FLY_SPEED * FLY_SECONDS, MIN_FLY,
                         **({"clearances": (loop.clearance,)} if loop is not None else {}))
    if flight is not None:
        out["flyover"] = {"kind": "flyover", "keys": flyover_tour(grid, flight, *_obstacles(index))}
    return out


def named_tours(index) -> dict[str, dict]:
    """A store's tours by name, each {"kind", "duration", "keys"}; a store built before tours had names has one,
    its tour, named "scene" (none if it has no tour)."""
    tours = index.meta.get("tours")
    if tours:
        return dict(tours)
    if not index.tour:
        return {}
    return {"scene": {"kind": "scene", "duration": float(index.tour[-1]["t"] - index.tour[0]["t"]),
                      "keys": list(index.tour)}}


def default_tour_name(index) -> str | None:
    """The name of the tour a store sends a client that names none (its ``tour``); None if it has none."""
    return index.meta.get("default_tour") or ("scene" if index.tour else None)


def tour_for(index, name: str | None) -> tuple[list[dict], dict]:
    """The keys and the start pose ({"eye", "forward", "up"}: its first key's) of the store's tour ``name``;
    None: the default tour and the store's start. KeyError, its sentence naming the tours there are, if the
    store has no tour of that name."""
    if name is None:
        return list(index.tour), dict(index.start)
    tours = named_tours(index)
    if name not in tours or not tours[name]["keys"]:
        have = ", ".join(sorted(tours)) or "none"
        raise KeyError(f"scene {index.name!r} has no tour {name!r}; its tours: {have}")
    keys = list(tours[name]["keys"])
    return keys, {k: keys[0][k] for k in ("eye", "forward", "up")}
