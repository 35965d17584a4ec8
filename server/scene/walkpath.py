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

__all__ = ["largest_region", "walk_path", "walk_distances", "NoPath"]


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
    """The straight line a → b (2,) stays on walkable ground (sampled every quarter cell)."""
    n = max(2, int(np.ceil(np.linalg.norm(b - a) / (0.25 * grid.cell))) + 1)
    s = np.linspace(0.0, 1.0, n)[:, None]
    return bool(grid.walkable(a + s * (b - a)).all())


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
    m: the search stops there)."""
    start, goal = np.asarray(start, np.float64)[:2], np.asarray(goal, np.float64)[:2]
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
