"""A terrain quadtree of grid patches with skirts, from a HeightGrid (Zach 2002; Zach, Mantler & Karner 2002).

**Layout.** With ``patch`` = P cells per leaf side, the depth D is the
smallest with P·2^D ≥ the grid's larger cell count; the root's footprint is
the grid padded (logically) to P·2^D cells, clipped to the grid. Node (d, i, j)
covers rows i·s … (i+1)·s and cols j·s … (j+1)·s of full-resolution samples,
s = P·2^(D−d), clipped, and samples every 2^(D−d)-th of them plus the last
row / column where the grid edge clips it. So every patch is a ≤ (P+1)² grid
mesh, a coarser node's samples are a subset of every finer node's samples on
the same ground, and patches meeting on a border put identical vertices at
every sample the coarser one has (same index → same float64 position).
Nodes whose footprint holds no valid sample (all NaN, or beyond the grid)
are omitted; NaN samples are filled from the nearest valid sample for meshing
and recorded in ``void``.

**Error.** ``deviation[n]`` is the largest |surface(n) − h| over the
full-resolution samples of n's footprint *including its border*, where
surface(n) is the patch's own triangulation (every quad split along its
(r, c)–(r+1, c+1) diagonal, the same split the meshes use). ``error`` is that
saturated upward: error[n] = max(deviation[n], error[children]), so errors are
0 at leaves and non-decreasing toward the root, and still bound the deviation.

**Skirts, and why they close every crack.** Take two rendered patches a, b
sharing a border segment. Both border polylines have their vertices at
full-resolution samples of that segment and are linear between consecutive
samples, so their vertical gap is largest at a sample p, where
|z_a(p) − z_b(p)| ≤ |z_a(p) − h(p)| + |h(p) − z_b(p)| ≤ err(a) + err(b).
A crack at p is hidden if the *higher* patch's skirt reaches down to the lower
border, i.e. skirt(higher) ≥ gap. So skirt(a) ≥ err(a) + max err(b) over every
b that can ever sit next to a suffices. Across one side of a (at depth d),
b is either an ancestor of the same-depth node n across that side, or a
descendant of it; ancestors shared with a would overlap a and cannot be
rendered with it. So b lies in the subtree of c = the child of LCA(a, n)
on n's side, and err(b) ≤ err(c) by saturation. Hence

    skirt(a) = err(a) + max over a's four sides of err(c_side)   (+ min_skirt)

which holds for *any* cut of the tree, not only restricted ones (no
neighbour-level constraint is needed). ``min_skirt`` (default 5 % of the
spacing) hides T-junction sparkles where the bound is 0.

Boxes ``lo``/``hi`` bound the full-resolution samples of the footprint, the
skirt below, and every descendant's box, so they nest.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from server.scene.source import HeightGrid

__all__ = ["TerrainTree", "build_quadtree", "surface_deviation"]

_SIDES = np.array([[0, -1], [0, 1], [-1, 0], [1, 0]])  # (di, dj): west, east, south, north


@dataclass
class TerrainTree:
    """A quadtree of terrain patches as a structure of arrays, nodes in BFS order (parents first).

    parent    : (N,) int32, −1 for the root
    children  : (N, 4) int32, −1 where a child is omitted; order (row, col) = (0,0), (0,1), (1,0), (1,1)
    depth     : (N,) int16; the leaves of a full tree are at ``depth_max``
    index     : (N, 2) int32 (i, j): row / col of the node among the 2^depth × 2^depth at its depth
    footprint : (N, 4) int64 (col0, row0, col1, row1), inclusive full-resolution sample indices
    step      : (N,) int64, sample stride 2^(depth_max − depth)
    deviation : (N,) float64, the node's own largest vertical deviation (see module docstring)
    error     : (N,) float64, deviation saturated upward: 0 at leaves, non-decreasing toward the root
    skirt     : (N,) float64, depth the skirt hangs below the border (see module docstring)
    lo, hi    : (N, 3) float64 boxes, skirts included, nesting
    filled    : (rows, cols) float64 heights meshed (NaN filled from the nearest valid sample)
    void      : (rows, cols) bool, samples the source had no value for
    """

    grid: HeightGrid
    patch: int
    depth_max: int
    parent: np.ndarray
    children: np.ndarray
    depth: np.ndarray
    index: np.ndarray
    footprint: np.ndarray
    step: np.ndarray
    deviation: np.ndarray
    error: np.ndarray
    skirt: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    filled: np.ndarray
    void: np.ndarray

    def __len__(self) -> int:
        return int(self.parent.shape[0])

    def samples(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """Full-resolution row and column indices node i samples (its patch vertices are their product)."""
        c0, r0, c1, r1 = (int(v) for v in self.footprint[i])
        s = int(self.step[i])
        return _axis(r0, r1, s), _axis(c0, c1, s)

    def mesh(self, i: int, *, skirt: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """Node i's patch: positions (n, 3) float64, faces (m, 3) int64, counter-clockwise seen from +z.

        The first len(rows)·len(cols) positions are the surface samples in row-major order
        (``samples(i)``); skirt vertices follow, one under each border vertex.
        """
        rows, cols = self.samples(i)
        ox, oy = self.grid.origin
        dx, dy = self.grid.spacing
        nr, nc = len(rows), len(cols)
        x = ox + cols * dx
        y = oy + rows * dy
        pos = np.empty((nr, nc, 3))
        pos[..., 0] = x[None, :]
        pos[..., 1] = y[:, None]
        pos[..., 2] = self.filled[np.ix_(rows, cols)]
        pos = pos.reshape(-1, 3)
        ids = np.arange(nr * nc).reshape(nr, nc)
        a, b = ids[:-1, :-1].ravel(), ids[:-1, 1:].ravel()
        c, d = ids[1:, :-1].ravel(), ids[1:, 1:].ravel()
        faces = [np.column_stack([a, b, d]), np.column_stack([a, d, c])]
        if skirt:
            # border walked counter-clockwise: south (→ +x), east (→ +y), north (→ −x), west (→ −y)
            ring = np.concatenate([ids[0, :-1], ids[:-1, -1], ids[-1, :0:-1], ids[:0:-1, 0]])
            hang = pos[ring].copy()
            hang[:, 2] -= self.skirt[i]
            s = nr * nc + np.arange(len(ring))
            v0, v1 = ring, np.roll(ring, -1)
            s0, s1 = s, np.roll(s, -1)
            faces += [np.column_stack([v0, s0, s1]), np.column_stack([v0, s1, v1])]
            pos = np.concatenate([pos, hang])
        return pos, np.concatenate(faces).astype(np.int64)

    def meshes(self, *, skirt: bool = True):
        """Every node's mesh, in node order."""
        return [self.mesh(i, skirt=skirt) for i in range(len(self))]


def _axis(a: int, b: int, s: int) -> np.ndarray:
    v = np.arange(a, b + 1, s, dtype=np.int64)
    return v if v[-1] == b else np.append(v, b)


def surface_deviation(h: np.ndarray, step: int) -> np.ndarray:
    """|surface − h| at every sample, where the surface triangulates h's every step-th sample (plus the last).

    Quads are split along their (r0, c0)–(r1, c1) diagonal, as ``TerrainTree.mesh`` does.
    """
    R, C = h.shape
    if step == 1:
        return np.zeros_like(h)

    def cells(n):
        i = np.arange(n)
        i0 = (i // step) * step
        last = i0 >= n - 1  # the last sample on a stride: use the cell before it
        i0[last] = ((n - 2) // step) * step
        i1 = np.minimum(i0 + step, n - 1)
        return i0, i1, (i - i0) / (i1 - i0)

    r0, r1, v = cells(R)
    c0, c1, u = cells(C)
    z00 = h[np.ix_(r0, c0)]
    z01 = h[np.ix_(r0, c1)]
    z10 = h[np.ix_(r1, c0)]
    z11 = h[np.ix_(r1, c1)]
    u, v = u[None, :], v[:, None]
    za = z00 + u * (z01 - z00) + v * (z11 - z01)
    zb = z00 + v * (z10 - z00) + u * (z11 - z10)
    return np.abs(np.where(u >= v, za, zb) - h)


def build_quadtree(grid: HeightGrid, *, patch: int = 32, skirt: bool = True,
                   min_skirt: float | None = None) -> TerrainTree:
    """The terrain quadtree of ``grid`` with ``patch`` × ``patch``-cell leaves (see the module docstring).

    ``skirt=False`` sets every skirt depth to 0 (meshes still carry the zero-height strip if asked).
    """
    h = np.asarray(grid.heights, np.float64)
    if h.ndim != 2 or min(h.shape) < 2:
        raise ValueError(f"grid {grid.name!r}: heights must be at least 2 × 2, got {h.shape}")
    if patch < 1:
        raise ValueError(f"patch must be ≥ 1, got {patch}")
    void = ~np.isfinite(h)
    if void.all():
        raise ValueError(f"grid {grid.name!r}: no valid sample")
    if void.any():
        idx = ndimage.distance_transform_edt(void, return_distances=False, return_indices=True)
        filled = h[idx[0], idx[1]]
    else:
        filled = h.copy()
    R, C = h.shape
    D = 0
    while patch << D < max(R, C) - 1:
        D += 1
    # valid-sample counts for "footprint holds a valid sample" (summed-area table, inclusive footprints)
    sat = np.zeros((R + 1, C + 1), np.int64)
    sat[1:, 1:] = (~void).cumsum(0).cumsum(1)

    def valid(c0, r0, c1, r1):
        return sat[r1 + 1, c1 + 1] - sat[r0, c1 + 1] - sat[r1 + 1, c0] + sat[r0, c0]

    parent, depth, index, children_of = [np.int32(-1)], [0], [(0, 0)], []
    level_ids = [np.zeros((1, 1), np.int64)]  # node id per (i, j) at each depth, −1 if omitted
    start = 0
    for d in range(1, D + 1):
        size = patch << (D - d)
        n = 1 << d
        ids = np.full((n, n), -1, np.int64)
        for p in range(start, len(parent)):
            pi, pj = index[p]
            for di in (0, 1):
                for dj in (0, 1):
                    i, j = 2 * pi + di, 2 * pj + dj
                    r0, c0 = i * size, j * size
                    if r0 >= R - 1 or c0 >= C - 1:
                        continue
                    if valid(c0, r0, min(c0 + size, C - 1), min(r0 + size, R - 1)) == 0:
                        continue
                    ids[i, j] = len(parent)
                    parent.append(p)
                    depth.append(d)
                    index.append((i, j))
        start = len(parent) - int((ids >= 0).sum())
        level_ids.append(ids)
    parent = np.asarray(parent, np.int32)
    depth = np.asarray(depth, np.int16)
    index = np.asarray(index, np.int32).reshape(-1, 2)
    N = len(parent)
    size = patch * (1 << (D - depth.astype(np.int64)))
    fp = np.column_stack([index[:, 1] * size, index[:, 0] * size,
                          np.minimum((index[:, 1] + 1) * size, C - 1), np.minimum((index[:, 0] + 1) * size, R - 1)])
    step = 1 << (D - depth.astype(np.int64))
    children = np.full((N, 4), -1, np.int32)
    nz = np.flatnonzero(parent >= 0)
    children[parent[nz], (index[nz, 0] % 2) * 2 + index[nz, 1] % 2] = nz

    deviation = np.zeros(N)
    for d in range(D + 1):
        sel = np.flatnonzero(depth == d)
        if d == D:
            continue
        dev = surface_deviation(filled, 1 << (D - d))
        for k in sel:
            c0, r0, c1, r1 = fp[k]
            deviation[k] = dev[r0:r1 + 1, c0:c1 + 1].max()
    error = deviation.copy()
    for d in range(D, 0, -1):
        sel = np.flatnonzero(depth == d)
        np.maximum.at(error, parent[sel], error[sel])

    if min_skirt is None:
        min_skirt = 0.05 * float(min(grid.spacing))
    across = np.zeros(N)
    if skirt:
        for d in range(1, D + 1):
            sel = np.flatnonzero(depth == d)
            i, j = index[sel, 0].astype(np.int64), index[sel, 1].astype(np.int64)
            for di, dj in _SIDES:
                ni, nj = i + di, j + dj
                inside = (ni >= 0) & (nj >= 0) & (ni < 1 << d) & (nj < 1 << d)
                # coarsest level L where a's and n's ancestors differ: the child of their LCA on n's side
                best = np.zeros(len(sel))
                found = np.zeros(len(sel), bool)
                for L in range(1, d + 1):
                    sh = d - L
                    differ = inside & ~found & (((i >> sh) != (ni >> sh)) | ((j >> sh) != (nj >> sh)))
                    if differ.any():
                        ids = level_ids[L][(ni[differ] >> sh), (nj[differ] >> sh)]
                        best[differ] = np.where(ids >= 0, error[np.maximum(ids, 0)], 0.0)
                        found |= differ
                across[sel] = np.maximum(across[sel], best)
        skirt_depth = error + across + min_skirt
    else:
        skirt_depth = np.zeros(N)

    ox, oy = grid.origin
    dx, dy = grid.spacing
    lo = np.empty((N, 3))
    hi = np.empty((N, 3))
    lo[:, 0], hi[:, 0] = ox + fp[:, 0] * dx, ox + fp[:, 2] * dx
    lo[:, 1], hi[:, 1] = oy + fp[:, 1] * dy, oy + fp[:, 3] * dy
    for k in range(N):
        c0, r0, c1, r1 = fp[k]
        block = filled[r0:r1 + 1, c0:c1 + 1]
        lo[k, 2], hi[k, 2] = block.min() - skirt_depth[k], block.max()
    for d in range(D, 0, -1):
        sel = np.flatnonzero(depth == d)
        np.minimum.at(lo, parent[sel], lo[sel])
        np.maximum.at(hi, parent[sel], hi[sel])

    return TerrainTree(grid=grid, patch=patch, depth_max=D, parent=parent, children=children, depth=depth,
                       index=index, footprint=fp.astype(np.int64), step=step, deviation=deviation, error=error,
                       skirt=skirt_depth, lo=lo, hi=hi, filled=filled, void=void)
