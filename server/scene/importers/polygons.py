"""Triangulate planar 3-D polygons with holes (CityJSON / CityGML surfaces) in one vectorised pass.

Each polygon is projected onto the plane of its outer ring's Newell normal and cut
by earcut. The per-ring work (cleaning, normals, projection, orientation) is done
for all rings at once with numpy; only the earcut call runs per polygon, and plain
triangles skip it. Output triangles wind like the outer ring, so the outward
normal of a closed shell is kept.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import mapbox_earcut
import numpy as np

__all__ = ["Rings", "flatten_polygons", "newell_normal", "triangulate_polygon", "triangulate_polygons",
           "triangulate_rings"]

# A ring whose area is below this fraction of its squared perimeter is a sliver (collinear points).
_SLIVER = 1e-10


@dataclass
class Rings:
    """Polygons as flat arrays: ring r holds ``index[start[r]:start[r] + length[r]]``; ``outer[r]`` starts a polygon."""

    index: np.ndarray  # (N,) int64 vertex indices, all rings concatenated
    length: np.ndarray  # (R,) int64
    outer: np.ndarray  # (R,) bool; every polygon's first ring is its outer ring

    @property
    def start(self) -> np.ndarray:
        return np.concatenate([[0], np.cumsum(self.length)[:-1]]).astype(np.int64)

    @property
    def n_polygons(self) -> int:
        return int(np.count_nonzero(self.outer))


def flatten_polygons(polygons: Sequence[Sequence[Sequence[int]]]) -> Rings:
    """Flatten ``[[outer, hole, ...], ...]`` (rings as index lists) into :class:`Rings`.

    Raises ``ValueError`` when an index is not an integer or a ring is not a flat list.
    """
    flat: list = []
    lengths: list[int] = []
    outer: list[bool] = []
    for poly in polygons:
        first = True
        for ring in poly:
            flat.extend(ring)
            lengths.append(len(ring))
            outer.append(first)
            first = False
    try:
        index = np.asarray(flat) if flat else np.zeros(0, np.int64)
    except (ValueError, TypeError) as exc:
        raise ValueError(f"ring is not a flat list of vertex indices ({exc})") from None
    if index.ndim != 1 or index.dtype.kind not in "iu":
        bad = next((v for v in flat if not isinstance(v, int) or isinstance(v, bool)), flat[0] if flat else None)
        raise ValueError(f"vertex index {bad!r} is not an integer")
    return Rings(index.astype(np.int64), np.asarray(lengths, np.int64), np.asarray(outer, bool))


def newell_normal(points: np.ndarray) -> np.ndarray:
    """Newell's normal of a closed ring (k, 3): length = twice the area, direction by right-hand winding."""
    p = np.asarray(points, np.float64)
    p = p - p[0]
    return np.cross(p, np.roll(p, -1, axis=0)).sum(axis=0)


def triangulate_polygon(rings: Sequence[np.ndarray]) -> np.ndarray:
    """One polygon: ``rings[0]`` the outer (k, 3) ring, the rest holes.

    Returns (t, 3) int64 indices into ``np.concatenate(rings)``; empty when the outer ring is degenerate.
    """
    pts = [np.asarray(r, np.float64).reshape(-1, 3) for r in rings]
    if not pts:
        return np.zeros((0, 3), np.int64)
    vertices = np.concatenate(pts)
    lengths = np.array([len(p) for p in pts], np.int64)
    outer = np.zeros(len(pts), bool)
    outer[0] = True
    faces, _ = triangulate_rings(vertices, Rings(np.arange(len(vertices)), lengths, outer))
    return faces


def triangulate_polygons(vertices: np.ndarray, polygons: Sequence[Sequence[Sequence[int]]]) -> np.ndarray:
    """Polygons given as rings of indices into ``vertices`` → (m, 3) int64 triangles of those indices."""
    return triangulate_rings(vertices, flatten_polygons(polygons))[0]


def triangulate_rings(vertices: np.ndarray, rings: Rings) -> tuple[np.ndarray, np.ndarray]:
    """Triangulate every polygon in ``rings`` (indices must already be in range).

    Returns ``(faces (m, 3) int64 vertex indices, polygon (m,) int64)``, faces sorted by polygon
    number (the order of outer rings). Degenerate rings (fewer than 3 distinct points, zero
    area) are skipped; a degenerate outer ring drops its whole polygon.
    """
    v = np.asarray(vertices, np.float64)
    n_rings = rings.length.shape[0]
    empty = (np.zeros((0, 3), np.int64), np.zeros(0, np.int64))
    if n_rings == 0 or rings.index.size == 0:
        return empty
    ring_poly = np.cumsum(rings.outer) - 1  # polygon number of each ring
    if ring_poly[0] < 0:
        raise ValueError("the first ring must be an outer ring")
    ring_of = np.repeat(np.arange(n_rings), rings.length)
    idx = rings.index
    p = v[idx]
    # Centre each polygon on its outer ring's first point: keeps precision for large map coordinates.
    outer_first = rings.start[rings.outer]
    p = p - p[outer_first][ring_poly[ring_of]]

    # Drop points equal to their successor (repeated closing points, stutters).
    nxt = _ring_next(rings.length)
    scale = max(1.0, float(np.abs(p).max()))
    keep = np.abs(p - p[nxt]).max(axis=1) > 1e-12 * scale
    if not keep.all():
        idx, p, ring_of = idx[keep], p[keep], ring_of[keep]
        length = np.bincount(ring_of, minlength=n_rings)
        nxt = _ring_next(length)
    else:
        length = rings.length

    # Newell normal, area and perimeter per ring.
    cross = np.cross(p, p[nxt])
    normal = np.stack([np.bincount(ring_of, cross[:, k], n_rings) for k in range(3)], axis=1)
    perimeter = np.bincount(ring_of, np.linalg.norm(p[nxt] - p, axis=1), n_rings)
    area = 0.5 * np.linalg.norm(normal, axis=1)
    good = (length >= 3) & (area > _SLIVER * perimeter ** 2)
    n_polys = int(ring_poly[-1]) + 1
    poly_ok = np.zeros(n_polys, bool)
    poly_ok[ring_poly[rings.outer]] = good[rings.outer]
    good &= poly_ok[ring_poly]
    if not good.any():
        return empty
    vkeep = good[ring_of]
    idx, p, ring_of = idx[vkeep], p[vkeep], ring_of[vkeep]
    kept_rings = np.flatnonzero(good)
    length = length[kept_rings]
    ring_poly = ring_poly[kept_rings]
    outer = rings.outer[kept_rings]
    ring_of = np.searchsorted(kept_rings, ring_of)  # renumber rings 0..r-1
    start = np.concatenate([[0], np.cumsum(length)[:-1]])

    # Plane basis (u, v, n̂) per polygon, right-handed, so a ring winding around n̂ is CCW in 2-D.
    n_hat = normal[kept_rings][outer]
    n_hat /= np.linalg.norm(n_hat, axis=1, keepdims=True)
    axis = np.eye(3)[np.argmin(np.abs(n_hat), axis=1)]
    u = np.cross(axis, n_hat)
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    w = np.cross(n_hat, u)
    poly_of = np.cumsum(outer)[ring_of] - 1  # compact polygon number of each point
    xy = np.column_stack([(p * u[poly_of]).sum(axis=1), (p * w[poly_of]).sum(axis=1)])

    # Plain triangles (one 3-point ring) are already triangles; the rest go through earcut.
    poly_start_ring = np.flatnonzero(outer)
    poly_rings = np.diff(np.append(poly_start_ring, len(length)))
    simple = (poly_rings == 1) & (length[poly_start_ring] == 3)
    tri_start = start[poly_start_ring[simple]]
    faces = [idx[tri_start[:, None] + np.arange(3)]]
    owner = [ring_poly[poly_start_ring[simple]]]

    # Ring ends relative to their polygon's first point, as earcut wants them.
    ends = (start + length - start[poly_start_ring][np.cumsum(outer) - 1]).astype(np.uint32)
    ear_polys = np.flatnonzero(~simple)
    ear_faces, ear_count = [], []
    for r0, nr, a in zip(poly_start_ring[ear_polys].tolist(), poly_rings[ear_polys].tolist(),
                         start[poly_start_ring[ear_polys]].tolist()):
        ring_ends = ends[r0:r0 + nr]
        local = mapbox_earcut.triangulate_float64(xy[a:a + int(ring_ends[-1])], ring_ends)
        ear_faces.append(local + a)
        ear_count.append(local.size // 3)
    if ear_faces:
        tri = np.concatenate(ear_faces).astype(np.int64).reshape(-1, 3)
        # earcut's output winding is its own; make every triangle CCW in the plane (normal along n̂).
        q = xy[tri]
        signed = ((q[:, 1, 0] - q[:, 0, 0]) * (q[:, 2, 1] - q[:, 0, 1])
                  - (q[:, 2, 0] - q[:, 0, 0]) * (q[:, 1, 1] - q[:, 0, 1]))
        flip = signed < 0
        tri[flip] = tri[flip][:, ::-1]
        faces.append(idx[tri])
        owner.append(np.repeat(ring_poly[poly_start_ring[ear_polys]], ear_count))
    faces_all = np.concatenate(faces).reshape(-1, 3)
    owner_all = np.concatenate(owner).astype(np.int64)
    order = np.argsort(owner_all, kind="stable")
    return faces_all[order], owner_all[order]


def _ring_next(length: np.ndarray) -> np.ndarray:
    """For the concatenated rings, the position of each point's successor (wrapping within its ring)."""
    total = int(length.sum())
    nxt = np.arange(1, total + 1)
    ends = np.cumsum(length)
    nonempty = length > 0
    nxt[ends[nonempty] - 1] = (ends - length)[nonempty]
    return nxt
