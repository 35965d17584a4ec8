"""HLOD proxies as a 2.5-D footprint set: merged block models simplified on a plan grid.

A cluster of buildings seen from afar is its skyline and its walls. Merging
the children's meshes and decimating them (the former proxy) removes the walls
first and leaves roof slabs over empty space. Here the children's shapes are
rasterised from above (``fidelity``'s z-buffer) into a height map on a G × G
plan grid; a cell is built up when at least half of it is covered, to the mean
covered height, quantised. Equal cells merge into rectangles (runs along rows, then
equal runs over consecutive rows), each a top and a bottom at the cluster's
ground, and every run of cell edges where the height changes gets one wall
from the lower to the higher side, so the proxy is
a closed 2.5-D block set whose walls and silhouette follow the buildings'.
The grid is the finest whose proxy fits the face budget.
"""

from __future__ import annotations

import numpy as np

from .fidelity import _draw
from .lod import clean_mesh

__all__ = ["footprint_proxy"]

_SUPER = 4  #: height samples per cell side


def _height_map(pos: np.ndarray, fac: np.ndarray, lo: np.ndarray, ext: np.ndarray, g: int) -> np.ndarray:
    """(g, g) heights above ``lo[2]`` (0: empty), rows along y, from a top-view z-buffer."""
    r = g * _SUPER
    uv = (pos[:, :2] - lo[:2]) / ext[:2] * r
    tri = np.column_stack([uv, pos[:, 2]])[fac]
    _, depth = _draw(tri, np.ones(fac.shape[0]), r, r)
    seen = np.isfinite(depth)
    z = np.where(seen, depth - lo[2], 0.0).reshape(g, _SUPER, g, _SUPER)
    n = seen.reshape(g, _SUPER, g, _SUPER).sum(axis=(1, 3))
    mean = z.sum(axis=(1, 3)) / np.maximum(n, 1)
    step = max(float(ext[2]) / 64.0, 1e-6)  # quantised, so neighbours of one building share a height
    h = np.round(mean / step) * step
    return np.where(n * 2 >= _SUPER * _SUPER, np.maximum(h, step), 0.0)


def _segments(line: np.ndarray, key: np.ndarray, pos: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Merge unit steps ``pos`` that share ``line`` and ``key`` rows and are consecutive: (first, last) indices."""
    order = np.lexsort((pos, *key.T[::-1], line))
    ln, k, p = line[order], key[order], pos[order]
    new = np.ones(order.size, bool)
    new[1:] = (ln[1:] != ln[:-1]) | (k[1:] != k[:-1]).any(axis=1) | (p[1:] != p[:-1] + 1)
    first = np.flatnonzero(new)
    last = np.append(first[1:] - 1, order.size - 1)
    return order[first], order[last]


def _quad(a: np.ndarray, b: np.ndarray, c: np.ndarray, d: np.ndarray) -> np.ndarray:
    return np.stack([a, b, c, d], axis=1)


def _mesh(h: np.ndarray, lo: np.ndarray, ext: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The closed block set of a height map: merged rectangles for tops and bottoms, merged walls."""
    g = h.shape[0]
    cx, cy = ext[0] / g, ext[1] / g
    rows, cols = np.nonzero(h > 0)
    if rows.size == 0:
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64)
    hv = h[rows, cols]
    # Runs of equal height along each row, then runs of equal runs over consecutive rows.
    f, l = _segments(rows, hv[:, None], cols)
    r0, c0, c1, z = rows[f], cols[f], cols[l] + 1, hv[f]
    f, l = _segments(np.zeros_like(r0), np.column_stack([c0, c1, z]), r0)
    x0, x1 = lo[0] + c0[f] * cx, lo[0] + c1[f] * cx
    y0, y1 = lo[1] + r0[f] * cy, lo[1] + (r0[l] + 1) * cy
    zt, zb = lo[2] + z[f], np.full(f.size, lo[2])
    col = np.column_stack
    quads = [_quad(col([x0, y0, zt]), col([x1, y0, zt]), col([x1, y1, zt]), col([x0, y1, zt])),
             _quad(col([x0, y0, zb]), col([x0, y1, zb]), col([x1, y1, zb]), col([x1, y0, zb]))]
    pad = np.pad(h, 1)
    # Walls where the height changes across an edge x = lo + c·cx (cells left/right) ...
    left, right = pad[1:-1, :-1], pad[1:-1, 1:]
    r, c = np.nonzero(left != right)
    a, b = left[r, c], right[r, c]
    f, l = _segments(c, np.column_stack([a, b]), r)
    a, b, x = a[f], b[f], lo[0] + c[f] * cx
    ya, yb = lo[1] + r[f] * cy, lo[1] + (r[l] + 1) * cy
    zl, zh = lo[2] + np.minimum(a, b), lo[2] + np.maximum(a, b)
    plus = a > b  # high side on the left: the wall faces +x
    s, e = np.where(plus, ya, yb), np.where(plus, yb, ya)
    quads.append(_quad(col([x, s, zl]), col([x, e, zl]), col([x, e, zh]), col([x, s, zh])))
    # ... and across an edge y = lo + r·cy (cells below/above).
    below, above = pad[:-1, 1:-1], pad[1:, 1:-1]
    r, c = np.nonzero(below != above)
    a, b = below[r, c], above[r, c]
    f, l = _segments(r, np.column_stack([a, b]), c)
    a, b, y = a[f], b[f], lo[1] + r[f] * cy
    xa, xb = lo[0] + c[f] * cx, lo[0] + (c[l] + 1) * cx
    zl, zh = lo[2] + np.minimum(a, b), lo[2] + np.maximum(a, b)
    plus = a > b  # high side below: the wall faces +y
    s, e = np.where(plus, xb, xa), np.where(plus, xa, xb)
    quads.append(_quad(col([s, y, zl]), col([e, y, zl]), col([e, y, zh]), col([s, y, zh])))
    allq = np.concatenate(quads)
    pos = allq.reshape(-1, 3)
    base = 4 * np.arange(allq.shape[0])[:, None]
    fac = np.concatenate([base + [0, 1, 2], base + [0, 2, 3]])
    key, inverse = np.unique(np.round(pos, 6), axis=0, return_inverse=True)
    return clean_mesh(key, inverse.reshape(-1)[fac])


def footprint_proxy(pos: np.ndarray, fac: np.ndarray, max_faces: int, grid: int = 64,
                    min_grid: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """The finest 2.5-D footprint set of the merged meshes within ``max_faces`` (empty if none fits)."""
    pos = np.asarray(pos, np.float64)
    fac = np.asarray(fac, np.int64)
    lo, hi = pos.min(axis=0), pos.max(axis=0)
    ext = np.maximum(hi - lo, 1e-6)
    g = grid
    while g >= min_grid:
        p, f = _mesh(_height_map(pos, fac, lo, ext, g), lo, ext)
        if 0 < f.shape[0] <= max_faces:
            return p, f
        g = int(g * 0.75)
    return np.zeros((0, 3)), np.zeros((0, 3), np.int64)
