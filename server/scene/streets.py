"""Loops through a scene's streets: where its buildings stand densest, joined by walks on open ground.

Theory of operation. A scene's *footprints* are the plan boxes of its
buildings (objects of a building class; in a scene without any, every mesh
object that is not ground). How many of them cover each cell of the walkable
grid (``server.scene.walkable``), blurred over a city block (``BLOCK``), is a
density whose peaks are the densest blocks (``dense_blocks``).

A loop (``street_loop``) visits them on *open ground*: the largest walkable
region kept a clearance from anything that blocks (a wall, a tree, the edge
of the scene), so that a camera on it never grazes a facade. Each block's
centre moves to the nearest open cell; blocks join the loop in order of
density, each where it lengthens the loop least (cheapest insertion over the
walking distances between them, Dijkstra on a coarsened copy of the grid: they
only choose and order the stops), while the stops' shortest walks take at most
``STOPS_SHARE`` of the loop's length budget. The legs are shortest walks
(``proto.walkpath.walk_path``, each searched only where a walk of its
allowed length can reach) that keep ``AVOID`` off the legs before them where
the rest of the budget pays for the detour: a loop goes round a block rather
than out and back along one street. A lone building is walked round. The
widest clearance of ``CLEARANCES`` that lets a loop through is taken: a city's
streets take a metre, an auditorium's aisles less.

``smooth_within`` rounds the loop's corners where the rounded loop still lies
on the ground it must keep to, and eases back to the corner where it would not.
Everything runs on arrays over grid cells and loop samples; the only loops in
Python run over the few blocks.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
from scipy import ndimage

from proto.walkable import WalkableGrid
from proto.walkpath import NoPath, along, largest_region, walk_distances, walk_path, walk_window

from .ground import BUILDING_CLASSES
from .index import MESH
from .walkable import GROUND_CLASSES

__all__ = ["BLOCK", "CLEARANCES", "MAX_BLOCKS", "AVOID", "DETOUR", "STOPS_SHARE", "footprints", "dense_blocks", "open_ground",
           "StreetLoop", "street_loop", "resample_loop", "smooth_within"]

#: A city block (m): the density's blur, and the least distance between two blocks a loop visits.
BLOCK = 10.0
#: Clearances (m) from anything that blocks, widest first: a loop keeps the widest that lets it through.
CLEARANCES = (1.0, 0.5, 0.25)
#: At most this many blocks are candidates for a loop.
MAX_BLOCKS = 24
#: A leg keeps this far (m) off the legs before it, where that costs at most ``DETOUR`` × its shortest walk.
AVOID = 4.0
DETOUR = 2.0
#: The stops take up to this share of a loop's budget as shortest walks; the rest is for going round by
#: other streets than the ones walked already.
STOPS_SHARE = 0.75
#: Walking distances between blocks are measured on a grid of at most this many cells.
_DISTANCE_CELLS = 1 << 17
#: Peaks of the density lower than this share of the highest are no dense block.
_PEAK_SHARE = 0.05
#: Local maxima examined at most (a flat density has a plateau of them).
_MAX_PEAKS = 512


def footprints(index) -> tuple[np.ndarray, np.ndarray]:
    """Plan boxes of a scene's buildings, lo (n, 2) and hi (n, 2) float64: mesh objects of a building class,
    or, where there are none, every mesh object not of a ground class."""
    names = np.array([c.lower() for c in index.class_names] or [""], object)
    cls = names[index.object_class]
    mesh = index.object_kind == MESH
    building = mesh & np.isin(cls, BUILDING_CLASSES)
    pick = building if building.any() else mesh & ~np.isin(cls, GROUND_CLASSES)
    return index.object_lo[pick, :2].astype(np.float64), index.object_hi[pick, :2].astype(np.float64)


def _box_cells(grid: WalkableGrid, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, ...]:
    """First and last (row, column) each box (n, 2) covers on the grid, clipped to it: r0, r1, c0, c1 (n,)."""
    ny, nx = grid.shape
    o = np.asarray(grid.origin)
    a = np.floor((lo - o) / grid.cell).astype(np.int64)
    b = np.floor((hi - o) / grid.cell).astype(np.int64)
    c0, c1 = np.clip(a[:, 0], 0, nx - 1), np.clip(b[:, 0], 0, nx - 1)
    r0, r1 = np.clip(a[:, 1], 0, ny - 1), np.clip(b[:, 1], 0, ny - 1)
    return r0, r1, c0, c1


def _coverage(grid: WalkableGrid, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """(ny, nx) float64: how many boxes cover each cell (a summed difference array: no loop per box)."""
    ny, nx = grid.shape
    r0, r1, c0, c1 = _box_cells(grid, lo, hi)
    diff = np.zeros((ny + 1, nx + 1))
    np.add.at(diff, (r0, c0), 1.0)
    np.add.at(diff, (r0, c1 + 1), -1.0)
    np.add.at(diff, (r1 + 1, c0), -1.0)
    np.add.at(diff, (r1 + 1, c1 + 1), 1.0)
    return diff.cumsum(axis=0).cumsum(axis=1)[:ny, :nx]


def dense_blocks(grid: WalkableGrid, lo: np.ndarray, hi: np.ndarray, n: int = MAX_BLOCKS) -> np.ndarray:
    """(k, 2) float64 plan centres of the densest blocks of footprints ``lo``, ``hi`` (m, 2), densest first,
    at least a block apart; k ≤ n, 0 without footprints. A scene smaller than a few blocks is blurred over
    an eighth of its shorter side instead, so that its buildings do not merge into one peak."""
    if len(lo) == 0:
        return np.zeros((0, 2))
    ext = grid.bounds[1] - grid.bounds[0]
    block = max(min(BLOCK, float(ext.min()) / 8), 2 * grid.cell)
    density = ndimage.gaussian_filter(_coverage(grid, lo, hi), block / grid.cell, mode="constant")
    size = max(3, int(2 * block / grid.cell) | 1)
    peak = (density >= ndimage.maximum_filter(density, size=size, mode="constant")) & (
        density > _PEAK_SHARE * density.max())
    labels, count = ndimage.label(peak)
    if count == 0:
        return np.zeros((0, 2))
    # One point per plateau of maxima: its highest cell.
    at = np.array(ndimage.maximum_position(density, labels, np.arange(1, count + 1)), np.int64).reshape(-1, 2)
    value = density[at[:, 0], at[:, 1]]
    order = np.argsort(-value, kind="stable")[:_MAX_PEAKS]
    centres = np.asarray(grid.origin) + (at[order][:, ::-1] + 0.5) * grid.cell
    kept: list[np.ndarray] = []
    for p in centres:
        if all(np.linalg.norm(p - q) >= block for q in kept):
            kept.append(p)
            if len(kept) == n:
                break
    return np.array(kept).reshape(-1, 2)


def open_ground(grid: WalkableGrid, clearance: float, largest: bool = True) -> WalkableGrid | None:
    """The grid cut to open ground: its largest walkable region less the cells within ``clearance`` (m) of
    a cell no one can stand on or of the grid's edge, then (``largest``) the largest piece of what is left;
    None if nothing is."""
    walk = largest_region(grid)
    free = ndimage.distance_transform_edt(np.pad(walk, 1))[1:-1, 1:-1] * grid.cell
    # ``free`` runs from cell centre to blocked cell centre; the blocked cell's edge is half a cell nearer.
    open_ = walk & (free - 0.5 * grid.cell >= clearance)
    if not open_.any():
        return None
    if not largest:
        return WalkableGrid(origin=grid.origin, cell=grid.cell, ground=np.where(open_, grid.ground, np.nan))
    labels, count = ndimage.label(open_)
    sizes = np.bincount(labels.reshape(-1), minlength=count + 1)
    sizes[0] = 0
    keep = labels == int(np.argmax(sizes))
    return WalkableGrid(origin=grid.origin, cell=grid.cell, ground=np.where(keep, grid.ground, np.nan))


def _snap(ground: WalkableGrid, points: np.ndarray) -> np.ndarray:
    """Points (k, 2) moved to the centre of the nearest cell of ``ground`` one can stand on."""
    blocked = ~np.isfinite(ground.ground)
    _, (ri, ci) = ndimage.distance_transform_edt(blocked, return_indices=True)
    r, c, _ = ground.cells(points)
    return np.asarray(ground.origin) + (np.column_stack([ci[r, c], ri[r, c]]) + 0.5) * ground.cell


def _ring(centre: np.ndarray, radius: float, n: int = 6) -> np.ndarray:
    a = 2 * np.pi * np.arange(n) / n
    return centre + radius * np.column_stack([np.cos(a), np.sin(a)])


def _coarse(ground: WalkableGrid) -> WalkableGrid:
    """The grid coarsened to at most ``_DISTANCE_CELLS`` cells, a cell open where any of its own is: walking
    distances between blocks only choose and order them, and a coarse grid gives them cheaply."""
    ny, nx = ground.shape
    f = max(1, int(np.ceil(np.sqrt(ny * nx / _DISTANCE_CELLS))))
    if f == 1:
        return ground
    open_ = np.pad(np.isfinite(ground.ground), ((0, -ny % f), (0, -nx % f)))
    any_open = open_.reshape(open_.shape[0] // f, f, open_.shape[1] // f, f).any(axis=(1, 3))
    return WalkableGrid(ground.origin, ground.cell * f, np.where(any_open, 0.0, np.nan))


def _insertion(dist: np.ndarray, budget: float) -> list[int]:
    """The points (indices into ``dist``, (k, k) walking distances) a loop from point 0 visits, in order: each
    next point in turn where it lengthens the loop least, if the loop then stays within ``budget`` (m)."""
    loop = [0]
    length = 0.0
    for j in range(1, len(dist)):
        a = np.array(loop)
        b = np.roll(a, -1)
        add = dist[a, j] + dist[j, b] - np.where(a == b, 0.0, dist[a, b])
        i = int(np.argmin(add))
        if np.isfinite(add[i]) and length + add[i] <= budget:
            loop.insert(i + 1, j)
            length += float(add[i])
    return loop


@dataclass(frozen=True)
class StreetLoop:
    """A closed route on open ground.

    points    : (m, 2) float64 plan waypoints, the first repeated as the last; each straight leg on ``ground``
    ground    : the open ground it keeps to (``open_ground`` at ``clearance``)
    clearance : m kept from anything that blocks
    blocks    : (b, 2) the dense blocks it visits, in visiting order
    """

    points: np.ndarray
    ground: WalkableGrid
    clearance: float
    blocks: np.ndarray

    @property
    def length(self) -> float:
        return float(np.linalg.norm(np.diff(self.points, axis=0), axis=1).sum())


def _legs(ground: WalkableGrid, stops: np.ndarray, dist: np.ndarray, budget: float) -> np.ndarray:
    """The closed route through ``stops`` (k, 2) in order, as waypoints (m, 2), the first repeated last: each leg
    the shortest walk that keeps ``AVOID`` m off the legs before it (but not near its own ends), where that
    is at most ``DETOUR`` × the shortest walk ``dist`` (k, k) or fits in what the shortest walks leave of
    ``budget`` (m); else the shortest walk. A loop of two stops thus goes out by one street and back by
    another."""
    used = np.zeros(ground.shape, bool)
    route = [stops[:1]]
    k = len(stops)
    shortest = dist[np.arange(k), (np.arange(k) + 1) % k]
    spare = budget - float(shortest.sum())
    for i in range(k):
        a, b = stops[i], stops[(i + 1) % k]
        path = None
        if used.any():
            allowed = max((DETOUR - 1) * shortest[i], spare)
            try:
                path = _walk(ground, a, b, shortest[i] + allowed + BLOCK, used)
                extra = float(np.linalg.norm(np.diff(path, axis=0), axis=1).sum()) - shortest[i]
                if extra > allowed:
                    path = None
                else:
                    spare -= max(extra, 0.0)
            except NoPath:
                path = None
        if path is None:
            try:
                path = _walk(ground, a, b, 2 * shortest[i] + BLOCK)
            except NoPath:
                path = walk_path(ground, a, b)
        row, col, _ = ground.cells(along(path, 0.5 * ground.cell))
        used[row, col] = True
        route.append(path[1:])
    return np.vstack(route)


def _walk(ground: WalkableGrid, a: np.ndarray, b: np.ndarray, limit: float, used: np.ndarray | None = None
          ) -> np.ndarray:
    """``walk_path`` from ``a`` to ``b`` no longer than ``limit`` (m); with ``used`` ((ny, nx) bool), keeping
    ``AVOID`` m off those cells except within 2 · ``AVOID`` of either end."""
    if used is None:
        return walk_path(ground, a, b, limit=limit)
    part, (rows, cols) = walk_window(ground, a, b, limit)
    near = ndimage.distance_transform_edt(~used[rows, cols]) * ground.cell <= AVOID
    ys, xs = np.mgrid[rows, cols]
    centres = np.asarray(ground.origin) + (np.stack([xs, ys], axis=-1) + 0.5) * ground.cell
    ends = np.minimum(np.linalg.norm(centres - a, axis=-1), np.linalg.norm(centres - b, axis=-1))
    masked = np.where(near & (ends > 2 * AVOID), np.nan, part.ground)
    return walk_path(WalkableGrid(part.origin, ground.cell, masked), a, b, limit=limit)


def street_loop(grid: WalkableGrid, blocks: np.ndarray, budget: float, min_length: float,
                clearances: tuple[float, ...] = CLEARANCES) -> StreetLoop | None:
    """The loop through the densest of ``blocks`` ((k, 2), densest first) within ``budget`` m (as the shortest
    walks between them measure it), at the widest of ``clearances`` that gives one at least ``min_length`` m
    long; None if none does."""
    if len(blocks) == 0:
        return None
    for clearance in clearances:
        ground = open_ground(grid, clearance)
        if ground is None:
            continue
        points = _snap(ground, blocks)
        keep = [0]
        for i in range(1, len(points)):  # blocks that land on one street corner are one stop
            if np.linalg.norm(points[keep] - points[i], axis=1).min() >= 0.5 * BLOCK:
                keep.append(i)
        points = points[keep]
        dist = walk_distances(_coarse(ground), points, limit=budget / 2)
        order = _insertion(dist, STOPS_SHARE * budget)
        if len(order) < 2:  # no other block within reach of the densest: walk round it
            ext = grid.bounds[1] - grid.bounds[0]
            ring = _snap(ground, _ring(blocks[0], max(min(2 * BLOCK, float(ext.min()) / 4), 4 * grid.cell)))
            points = np.vstack([points[:1], ring])
            dist = walk_distances(_coarse(ground), points, limit=budget / 2)
            order = _insertion(dist, STOPS_SHARE * budget)
        if len(order) < 2:
            continue
        try:
            route = _legs(ground, points[order], dist[np.ix_(order, order)], budget)
        except NoPath:
            continue
        loop = StreetLoop(route, ground, clearance, points[order])
        if loop.length >= min_length:
            return loop
    return None


def resample_loop(points: np.ndarray, step: float) -> tuple[np.ndarray, float]:
    """A closed polyline (m, 2), first point repeated last, as n points evenly ``step`` (or a little less) apart
    along it, the first at its start and the closing point left out: ((n, 2), length in m)."""
    pts = np.asarray(points, np.float64)
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    pts = np.vstack([pts[:1], pts[1:][seg > 1e-9]])
    s = np.concatenate([[0.0], np.cumsum(seg[seg > 1e-9])])
    length = float(s[-1])
    n = max(3, int(np.ceil(length / step - 1e-9)))
    t = np.arange(n) * (length / n)
    return np.column_stack([np.interp(t, s, pts[:, 0]), np.interp(t, s, pts[:, 1])]), length


def smooth_within(points: np.ndarray, sigma: float, ok: Callable[[np.ndarray], np.ndarray],
                  rounds: int = 6) -> np.ndarray:
    """Closed-loop samples (n, 2) smoothed (Gaussian, ``sigma`` in samples, wrapping round the loop) wherever
    the smoothed point satisfies ``ok`` ((n, 2) → (n,) bool); where it would not, the loop eases back to
    ``points``, which must satisfy ``ok`` themselves."""
    smooth = ndimage.gaussian_filter1d(points, sigma, axis=0, mode="wrap")
    alpha = np.ones(len(points))
    for _ in range(rounds):
        out = points + alpha[:, None] * (smooth - points)
        bad = ~ok(out)
        if not bad.any():
            return out
        alpha[bad] = 0.0
        alpha = np.minimum(alpha, ndimage.gaussian_filter1d(alpha, sigma, mode="wrap"))
        alpha[bad] = 0.0
    out = points + alpha[:, None] * (smooth - points)
    bad = ~ok(out)
    out[bad] = points[bad]
    return out
