"""Paths on the walkable grid: the shortest walk between two points that never leaves walkable ground.

The grid's walkable cells are the nodes of a graph whose edges join each cell
to its eight neighbours (a diagonal only where both cells it cuts past are
walkable too, so a path never squeezes between two blocked corners), weighted
by their length; Dijkstra (``scipy.sparse.csgraph``) finds the shortest walk.
The walk is then shortened to the waypoints where it turns, keeping only
shortcuts whose straight line stays on walkable ground. Walk tours (a kiosk's,
or one generated for a scene) are strings of such paths.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import dijkstra

from proto.walkable import WalkableGrid

__all__ = ["largest_region", "walk_path", "walk_distances", "walk_window", "along", "NoPath"]


class NoPath(ValueError):
    """No walk joins the two points (one is not on walkable ground, or they lie in different regions)."""


def largest_region(grid: WalkableGrid) -> np.ndarray:
    """(ny, nx) bool: the largest region of walkable cells joined side by side."""
    labels, n = ndimage.label(np.isfinite(grid.ground))
    if n == 0:
        return np.zeros(grid.shape, bool)
    sizes = np.bincount(labels.reshape(-1), minlength=n + 1)
    sizes[0] = 0
    return labels == int(np.argmax(sizes))


def _graph(open_: np.ndarray, cell: float):
    ny, nx = open_.shape
    idx = np.arange(ny * nx).reshape(ny, nx)
    rows, cols, weights = [], [], []
    for dj, di in ((0, 1), (1, 0), (1, 1), (1, -1)):  # each edge once; the graph is undirected
        sj0, sj1 = slice(0, ny - dj), slice(dj, ny)
        si0, si1 = (slice(0, nx - di), slice(di, nx)) if di >= 0 else (slice(-di, nx), slice(0, nx + di))
        both = open_[sj0, si0] & open_[sj1, si1]
        if dj and di:  # a diagonal passes the two cells at its sides
            both &= open_[sj0, si1] & open_[sj1, si0]
        rows.append(idx[sj0, si0][both])
        cols.append(idx[sj1, si1][both])
        weights.append(np.full(int(both.sum()), cell * (1.4142135623730951 if dj and di else 1.0)))
    r, c, w = np.concatenate(rows), np.concatenate(cols), np.concatenate(weights)
    return coo_matrix((w, (r, c)), shape=(ny * nx, ny * nx)).tocsr()


def _line_open(grid: WalkableGrid, a: np.ndarray, b: np.ndarray) -> bool:
    """The straight line a → b (2,) stays on walkable ground: every cell it passes through is walkable (the
    line's crossings of the grid lines cut it into pieces, one per cell, each tested at its middle)."""
    o, d = np.asarray(grid.origin, np.float64), b - a
    cuts = [np.array([0.0, 1.0])]
    for k in (0, 1):
        if abs(d[k]) > 1e-12:
            lo, hi = sorted(((a[k] - o[k]) / grid.cell, (b[k] - o[k]) / grid.cell))
            lines = np.arange(np.ceil(lo), np.floor(hi) + 1)
            cuts.append((o[k] + lines * grid.cell - a[k]) / d[k])
    t = np.unique(np.clip(np.concatenate(cuts), 0.0, 1.0))
    mid = (t[:-1] + t[1:]) / 2 if len(t) > 1 else np.array([0.0])
    return bool(grid.walkable(a + mid[:, None] * d).all() and grid.walkable(np.stack([a, b])).all())


def walk_distances(grid: WalkableGrid, points, limit: float = np.inf) -> np.ndarray:
    """(k, k) float64: the length (m) of the shortest walk on the grid's eight-neighbour graph between each pair
    of ``points`` ((k, 2) x, y), inf where there is none, where an end is not on walkable ground, or where the
    walk is longer than ``limit`` (searches stop there, which keeps them cheap on a large grid)."""
    pts = np.asarray(points, np.float64).reshape(-1, 2)
    out = np.full((len(pts), len(pts)), np.inf)
    open_ = np.isfinite(grid.ground)
    rows, cols, inside = grid.cells(pts)
    ok = inside & open_[rows, cols]
    if not ok.any():
        return out
    nodes = rows * grid.shape[1] + cols
    dist = dijkstra(_graph(open_, grid.cell), directed=False, indices=nodes[ok], limit=limit)
    dist = np.atleast_2d(dist)
    sub = np.full((int(ok.sum()), len(pts)), np.inf)
    sub[:, ok] = dist[:, nodes[ok]]
    out[ok] = sub
    return out


def walk_path(grid: WalkableGrid, start, goal, limit: float = np.inf) -> np.ndarray:
    """The shortest walk from ``start`` to ``goal`` ((2,) x, y) on the grid, as waypoints (k, 2) float64 from
    start to goal, each straight leg on walkable ground; ``NoPath`` if there is none (none within ``limit``
    m). A finite ``limit`` searches only the box round the ellipse with foci ``start`` and ``goal`` that such a
    walk cannot leave, which keeps a short walk on a large grid cheap."""
    start, goal = np.asarray(start, np.float64)[:2], np.asarray(goal, np.float64)[:2]
    if np.isfinite(limit):
        grid, _ = walk_window(grid, start, goal, limit)
    open_ = np.isfinite(grid.ground)
    (r0, r1), (c0, c1), inside = grid.cells(np.stack([start, goal]))
    if not inside.all() or not open_[r0, c0] or not open_[r1, c1]:
        raise NoPath(f"no walk from {start.tolist()} to {goal.tolist()}: an end is not on walkable ground")
    ny, nx = grid.shape
    a, b = r0 * nx + c0, r1 * nx + c1
    _, pred = dijkstra(_graph(open_, grid.cell), directed=False, indices=a, return_predecessors=True, limit=limit)
    if b != a and pred[b] < 0:
        far = "" if np.isinf(limit) else f" within {limit:g} m"
        raise NoPath(f"no walk from {start.tolist()} to {goal.tolist()}{far}: they lie in different regions")
    chain = [b]
    while chain[-1] != a:
        chain.append(int(pred[chain[-1]]))
    cells = np.array(chain[::-1])
    centres = np.asarray(grid.origin) + (np.column_stack([cells % nx, cells // nx]) + 0.5) * grid.cell
    points = np.vstack([start, centres[1:-1], goal]) if len(cells) > 1 else np.stack([start, goal])
    keep = [0]  # greedy string-pulling: jump to the farthest point still in plain sight
    while keep[-1] < len(points) - 1:
        i = keep[-1]
        j = len(points) - 1
        while j > i + 1 and not _line_open(grid, points[i], points[j]):
            j = max(i + 1, i + (j - i) // 2)
        keep.append(j)
    return points[keep]


def walk_window(grid: WalkableGrid, a, b, limit: float) -> tuple[WalkableGrid, tuple[slice, slice]]:
    """The part of ``grid`` a walk from ``a`` to ``b`` no longer than ``limit`` can reach (the box round the
    ellipse with foci a and b, a cell wider each side), as a grid of its own, and its (rows, cols) slices
    into ``grid``."""
    a, b = np.asarray(a, np.float64)[:2], np.asarray(b, np.float64)[:2]
    ny, nx = grid.shape
    reach = max(0.0, (limit - float(np.linalg.norm(b - a))) / 2) + 2 * grid.cell
    o = np.asarray(grid.origin, np.float64)
    c0, r0 = np.maximum(np.floor((np.minimum(a, b) - reach - o) / grid.cell).astype(np.int64), 0)
    c1, r1 = np.minimum(np.ceil((np.maximum(a, b) + reach - o) / grid.cell).astype(np.int64), [nx, ny])
    c1, r1 = max(int(c1), int(c0) + 1), max(int(r1), int(r0) + 1)
    origin = o + np.array([c0, r0]) * grid.cell
    rows, cols = slice(int(r0), int(r1)), slice(int(c0), int(c1))
    return WalkableGrid((float(origin[0]), float(origin[1])), grid.cell, grid.ground[rows, cols]), (rows, cols)


def along(points: np.ndarray, step: float) -> np.ndarray:
    """Points every ``step`` (or less) along the polyline ``points`` (m, d), its vertices among them."""
    points = np.asarray(points, np.float64)
    a, b = points[:-1], points[1:]
    n = np.maximum(np.ceil(np.linalg.norm(b - a, axis=1) / step).astype(np.int64), 1)
    seg = np.repeat(np.arange(len(a)), n)
    s = (np.arange(seg.size) - np.repeat(np.cumsum(n) - n, n)) / n[seg]
    return np.vstack([a[seg] + s[:, None] * (b - a)[seg], points[-1:]])
