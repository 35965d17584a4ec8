"""LOD chains by quadric decimation, and the geometric error of each level.

A chain is a list of meshes ordered coarsest → finest (the store's level
convention: level 0 is the coarsest, the last level is full detail). Each level
is simplified from the next finer one with ``fast_simplification`` (Garland &
Heckbert quadrics), so errors compound the way they do for any successive
simplifier and every level has strictly fewer faces than the next finer one.

The error of a level is the one-sided Hausdorff distance from the full-detail
surface to that level, estimated on a deterministic subsample of full-detail
vertices; on that subsample the maximum is exact. trimesh's ``closest_point``
wants ``rtree``, which this project does not depend on, and would measure every
point exactly when only the largest distance is needed. Here a k-d tree over the
coarse triangles' centroids proposes a few candidate triangles per point, which
gives an upper bound on each distance; points are then made exact in order of
falling bound until no remaining bound can exceed the largest exact distance
(typically a few dozen points).

Example::

    >>> import trimesh
    >>> m = trimesh.creation.icosphere(4)
    >>> chain = build_chain(m.vertices, m.faces, levels=3)
    >>> [f.shape[0] for _, f in chain]        # doctest: +SKIP
    [320, 1280, 5120]
"""

from __future__ import annotations

import fast_simplification
import numpy as np
from scipy.spatial import cKDTree

__all__ = ["build_chain", "clean_mesh", "geometric_error", "chain_errors"]

#: Candidate triangles tried first per sample point (see the module docstring).
_CANDIDATES = 6
#: Points made exact per round while looking for the maximum.
_BATCH = 32


def clean_mesh(positions: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Drop degenerate faces and unreferenced vertices, as the simplifier can leave both.

    positions : (n, 3) float
    faces     : (m, 3) int
    Returns (n', 3) float64 positions and (m', 3) int64 faces; the kept
    vertices keep their relative order.
    """
    positions = np.asarray(positions, np.float64)
    faces = np.asarray(faces, np.int64).reshape(-1, 3)
    a, b, c = faces[:, 0], faces[:, 1], faces[:, 2]
    distinct = (a != b) & (b != c) & (a != c)
    tri = positions[faces]
    area2 = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    faces = faces[distinct & (area2 > 0.0)]
    used = np.zeros(positions.shape[0], bool)
    used[faces.ravel()] = True
    remap = np.cumsum(used) - 1
    return positions[used], remap[faces]


def build_chain(
    positions: np.ndarray,
    faces: np.ndarray,
    *,
    levels: int = 4,
    ratio: float = 0.25,
    min_faces: int = 64,
    preserve_border: bool = True,
) -> list[tuple[np.ndarray, np.ndarray]]:
    """Successively simplified levels of one mesh, coarsest → finest.

    positions : (n, 3) float — the full-detail mesh
    faces     : (m, 3) int
    levels    : at most this many levels, full detail included
    ratio     : target face count of a level relative to the next finer one
    min_faces : a level whose target falls below this is not made (the chain
        stops early, so a small mesh gets fewer levels)
    preserve_border : keep open boundaries at full resolution. Without it the
        quadric simplifier erodes them (a 33 m ground tile lost 0.7 m at its
        edge after one step); with it, tiles that share a boundary meet without
        cracks at any pair of levels. Closed meshes are unaffected. The chain
        also stops when a step removes less than half of what ``ratio`` asks,
        as pinned borders may prevent it.

    Returns a list of ``(positions (n_k, 3) float64, faces (m_k, 3) int64)``
    with m_0 < m_1 < ... ; the last entry is the cleaned input.
    """
    if levels < 1:
        raise ValueError(f"levels must be ≥ 1, got {levels}")
    if not 0.0 < ratio < 1.0:
        raise ValueError(f"ratio must lie in (0, 1), got {ratio}")
    finest = clean_mesh(positions, faces)
    chain = [finest]
    while len(chain) < levels:
        pos, fac = chain[-1]
        target = int(round(fac.shape[0] * ratio))
        if target < min_faces:
            break
        p, f = fast_simplification.simplify(pos, fac, target_count=target, preserve_border=preserve_border)
        p, f = clean_mesh(p, f)
        if f.shape[0] < min_faces or f.shape[0] > fac.shape[0] * (1.0 + ratio) / 2.0:
            break
        chain.append((p, f))
    return chain[::-1]


def _closest_on_triangles(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Closest points on triangles (a, b, c) to points p; all (k, 3) float64 (Ericson, RTCD §5.1.5)."""
    ab, ac, ap = b - a, c - a, p - a
    d1 = np.einsum("ij,ij->i", ab, ap)
    d2 = np.einsum("ij,ij->i", ac, ap)
    bp = p - b
    d3 = np.einsum("ij,ij->i", ab, bp)
    d4 = np.einsum("ij,ij->i", ac, bp)
    cp = p - c
    d5 = np.einsum("ij,ij->i", ab, cp)
    d6 = np.einsum("ij,ij->i", ac, cp)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = 1.0 / (va + vb + vc)
        v = vb * denom
        w = vc * denom
        out = a + ab * v[:, None] + ac * w[:, None]  # interior
        # Edge regions, then vertex regions (later assignments win, as in the branchy original).
        t_ab = d1 / (d1 - d3)
        m = (vc <= 0) & (d1 >= 0) & (d3 <= 0)
        out[m] = a[m] + ab[m] * t_ab[m, None]
        t_ac = d2 / (d2 - d6)
        m = (vb <= 0) & (d2 >= 0) & (d6 <= 0)
        out[m] = a[m] + ac[m] * t_ac[m, None]
        t_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        m = (va <= 0) & ((d4 - d3) >= 0) & ((d5 - d6) >= 0)
        out[m] = b[m] + (c[m] - b[m]) * t_bc[m, None]
    m = (d1 <= 0) & (d2 <= 0)
    out[m] = a[m]
    m = (d3 >= 0) & (d4 <= d3)
    out[m] = b[m]
    m = (d6 >= 0) & (d5 <= d6)
    out[m] = c[m]
    # Degenerate triangles whose weights did not resolve: fall back to vertex a.
    bad = ~np.isfinite(out).all(axis=1)
    out[bad] = a[bad]
    return out


def geometric_error(
    fine_positions: np.ndarray,
    coarse_positions: np.ndarray,
    coarse_faces: np.ndarray,
    samples: int = 2000,
    seed: int = 0,
) -> float:
    """Estimated one-sided Hausdorff distance from the fine vertices to the coarse surface.

    fine_positions   : (n, 3) float — vertices of the full-detail mesh
    coarse_positions : (n', 3) float
    coarse_faces     : (m', 3) int
    samples : at most this many fine vertices are measured (all when fewer)
    seed    : picks the subsample, so the estimate is deterministic

    Returns the largest distance found, in the positions' units (object space).
    """
    fine = np.asarray(fine_positions, np.float64)
    pos = np.asarray(coarse_positions, np.float64)
    fac = np.asarray(coarse_faces, np.int64).reshape(-1, 3)
    if fine.shape[0] == 0 or fac.shape[0] == 0:
        raise ValueError("geometric_error needs a non-empty fine point set and coarse mesh")
    if fine.shape[0] > samples:
        pick = np.random.default_rng(seed).choice(fine.shape[0], samples, replace=False)
        fine = fine[np.sort(pick)]
    tri = pos[fac]  # (m', 3, 3)
    centroid = tri.mean(axis=1)
    # Every point of a triangle lies within `reach` of its centroid.
    reach = float(np.linalg.norm(tri - centroid[:, None, :], axis=2).max())
    tree = cKDTree(centroid)
    k = min(_CANDIDATES, fac.shape[0])
    _, cand = tree.query(fine, k=k)
    upper = _distances(fine, tri, np.asarray(cand).reshape(-1, k))  # (n,) ≥ the true distances
    # Only the maximum matters: visit points by falling upper bound, make each
    # distance exact over every triangle whose centroid is within (bound + reach),
    # and stop once no remaining bound can beat the largest exact distance.
    order = np.argsort(-upper, kind="stable")
    best = 0.0
    for start in range(0, order.size, _BATCH):
        idx = order[start : start + _BATCH]
        if upper[idx[0]] <= best:
            break
        balls = tree.query_ball_point(fine[idx], upper[idx] + reach)
        sizes = np.fromiter((len(b) for b in balls), np.int64, idx.size)
        flat = np.fromiter((j for b in balls for j in b), np.int64, int(sizes.sum()))
        owner = np.repeat(np.arange(idx.size), sizes)
        exact = np.full(idx.size, np.inf)
        np.minimum.at(exact, owner, _point_triangle_distance(fine[idx][owner], tri[flat]))
        best = max(best, float(np.minimum(exact, upper[idx]).max()))
    return best


def _point_triangle_distance(p: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """Distances (k,) from points p (k, 3) to triangles tri (k, 3, 3)."""
    q = _closest_on_triangles(p, tri[:, 0], tri[:, 1], tri[:, 2])
    return np.linalg.norm(p - q, axis=1)


def _distances(points: np.ndarray, tri: np.ndarray, cand: np.ndarray) -> np.ndarray:
    """Per point (n, 3), the least distance to its candidate triangles cand (n, k) of tri (m, 3, 3)."""
    k = cand.shape[1]
    return _point_triangle_distance(np.repeat(points, k, axis=0), tri[cand.ravel()]).reshape(-1, k).min(axis=1)


def chain_errors(chain: list[tuple[np.ndarray, np.ndarray]], samples: int = 2000, seed: int = 0) -> list[float]:
    """Geometric error of every level of a chain against its last (full-detail) level.

    The estimates are made non-increasing toward full detail (a running maximum
    from the finest level down), because selection relies on diminishing
    returns: a coarser level is never reported as more accurate than a finer one.
    The full-detail level's error is exactly 0.
    """
    fine = chain[-1][0]
    raw = [geometric_error(fine, p, f, samples, seed) for p, f in chain[:-1]] + [0.0]
    return [float(e) for e in np.maximum.accumulate(np.asarray(raw)[::-1])[::-1]]
