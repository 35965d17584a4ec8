"""Shape proxies for the coarse end of a chain: pruned shells, block model (CityGML LoD1), oriented box, hull.

City modelling coarsens a building along LoD2 → LoD1 → box, not by collapsing
edges: quadric decimation of a closed, box-like building removes walls first
and leaves roof slabs. The proxies here keep walls by construction:

- ``pruned`` — the mesh without its small shells: window frames, sills,
  ledges and parapets that stand out of the bigger shells by less than a given
  distance go, body and roof stay (the step from LoD2 with facade and roof
  detail to LoD2 without it, Biljecki et al. 2016's LoD2.0);

- ``block_model`` — the building's footprint (its downward faces at the
  ground, or the convex hull of its plan when it has none) extruded from the
  ground to its mean roof height (the plan-area-weighted mean height of its
  upward faces): CityGML's LoD1 block.
- ``oriented_box`` — the least-area rectangle around the plan (rotating
  calipers on the hull), from the ground to the same height.
- ``convex_hull`` — for meshes that are not buildings, the bottom of the chain.

All are closed, with outward counter-clockwise faces.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import ConvexHull, QhullError

from .fidelity import _draw
from .surface import shells

__all__ = ["pruned", "shell_reach", "block_model", "oriented_box", "convex_hull", "roof_height", "prism"]

#: Most shells ``pruned`` considers; beyond it the mesh is a triangle soup rather than a union of parts.
MAX_SHELLS = 4096


def _normals(positions: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    tri = positions[faces]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    return n, tri


def roof_height(positions: np.ndarray, faces: np.ndarray, res: int = 64) -> float:
    """Mean height of the roof as seen from above: the top-view height map averaged over the plan.

    Only surfaces visible from above count, so the tops of stacked storeys or of
    window sills under the roof do not pull the block down.
    """
    lo, hi = positions.min(axis=0), positions.max(axis=0)
    ext = np.maximum(hi - lo, 1e-9)
    uv = (positions - lo) / ext * res
    tri = np.stack([uv[:, 0], uv[:, 1], positions[:, 2]], axis=1)[faces]
    _, depth = _draw(tri, np.ones(faces.shape[0]), res, res)
    seen = np.isfinite(depth)
    return float(depth[seen].mean()) if seen.any() else float(hi[2])


def prism(ring: np.ndarray, z0: float, z1: float) -> tuple[np.ndarray, np.ndarray]:
    """A closed prism over a convex counter-clockwise ring (k, 2) from z0 to z1: (2k, 3), (4k − 4, 3)."""
    k = ring.shape[0]
    pos = np.concatenate([np.column_stack([ring, np.full(k, z0)]), np.column_stack([ring, np.full(k, z1)])])
    i = np.arange(1, k - 1)
    bottom = np.column_stack([np.zeros(k - 2, np.int64), i + 1, i])
    top = np.column_stack([np.full(k - 2, k), k + i, k + i + 1])
    a = np.arange(k)
    b = (a + 1) % k
    walls = np.concatenate([np.column_stack([a, b, k + b]), np.column_stack([a, k + b, k + a])])
    return pos, np.concatenate([bottom, top, walls]).astype(np.int64)


def _hull_ring(xy: np.ndarray) -> np.ndarray | None:
    try:
        h = ConvexHull(xy)
    except (QhullError, ValueError):
        return None
    return xy[h.vertices]  # counter-clockwise for 2-D hulls


def _ground_footprint(positions: np.ndarray, faces: np.ndarray, z0: float, height: float):
    """The downward faces at the ground and their boundary edges, or None when there are none."""
    n, tri = _normals(positions, faces)
    length = np.linalg.norm(n, axis=1)
    down = (n[:, 2] < -0.95 * np.maximum(length, 1e-30)) & (tri[:, :, 2].max(axis=1) <= z0 + 0.02 * height + 1e-6)
    if not down.any():
        return None
    g = faces[down]
    e = np.concatenate([g[:, [0, 1]], g[:, [1, 2]], g[:, [2, 0]]])
    key = np.sort(e, axis=1)
    _, inv, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    boundary = e[counts[inv.reshape(-1)] == 1]
    return g, boundary


def shell_reach(positions: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """How far each shell stands out of the box of a bigger shell: (label (m,) per face, reach (k,)).

    A shell's reach is the least, over the shells bigger than it (by box volume; ties by order),
    of the distance its box sticks out of theirs; the biggest shell's is infinite. None for a
    mesh of one shell or of more than ``MAX_SHELLS``.
    """
    p = np.asarray(positions, np.float64)
    f = np.asarray(faces, np.int64)
    k, label = shells(p.shape[0], f)
    if not 2 <= k <= MAX_SHELLS:
        return None
    tri = p[f]
    order = np.argsort(label, kind="stable")
    start = np.searchsorted(label[order], np.arange(k))
    lo = np.minimum.reduceat(tri[order].min(axis=1), start)
    hi = np.maximum.reduceat(tri[order].max(axis=1), start)
    volume = np.prod(np.maximum(hi - lo, 0.0), axis=1)
    rank = np.empty(k, np.int64)
    rank[np.lexsort((np.arange(k), -volume))] = np.arange(k)  # 0: the biggest
    reach = np.empty(k)
    for a in range(0, k, 256):  # rows in chunks: the pairwise test is k × k
        b = min(k, a + 256)
        out = np.maximum(lo[None] - lo[a:b, None], hi[a:b, None] - hi[None]).max(axis=2)
        out = np.where(rank[None, :] < rank[a:b, None], np.maximum(out, 0.0), np.inf)
        reach[a:b] = out.min(axis=1)
    return label, reach


def pruned(positions: np.ndarray, faces: np.ndarray, reach: float,
           shells_reach: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray] | None:
    """The mesh without the shells that stand out of a bigger shell's box by at most ``reach``.

    Such a shell changes the silhouette by at most ``reach``. Shells are the connected components
    of the faces, so this suits meshes modelled as unions of closed parts. None when nothing or
    everything would go. ``shells_reach``: ``shell_reach``'s result, when the caller has it.
    """
    p = np.asarray(positions, np.float64)
    f = np.asarray(faces, np.int64)
    found = shell_reach(p, f) if shells_reach is None else shells_reach
    if found is None:
        return None
    label, out = found
    keep = out > reach
    if keep.all() or not keep.any():
        return None
    kept = f[keep[label]]
    used = np.unique(kept)
    remap = np.full(p.shape[0], -1, np.int64)
    remap[used] = np.arange(used.size)
    return p[used], remap[kept]


def block_model(positions: np.ndarray, faces: np.ndarray, roof: float | None = None
                ) -> tuple[np.ndarray, np.ndarray] | None:
    """LoD1 block: footprint extruded from the ground to the mean roof height (``roof_height``, unless
    the caller has it); None if degenerate."""
    p = np.asarray(positions, np.float64)
    f = np.asarray(faces, np.int64)
    z0 = float(p[:, 2].min())
    height = float(p[:, 2].max()) - z0
    z1 = roof_height(p, f) if roof is None else float(roof)
    if not z1 > z0 + 1e-6:
        return None
    found = _ground_footprint(p, f, z0, height)
    if found is None:
        ring = _hull_ring(p[:, :2])
        return None if ring is None else prism(ring, z0, z1)
    g, boundary = found
    used = np.unique(np.concatenate([g.ravel(), boundary.ravel()]))
    remap = np.full(p.shape[0], -1, np.int64)
    remap[used] = np.arange(used.size)
    k = used.size
    base = np.column_stack([p[used, :2], np.full(k, z0)])
    pos = np.concatenate([base, base + [0.0, 0.0, z1 - z0]])
    gb = remap[g]
    a, b = remap[boundary[:, 0]], remap[boundary[:, 1]]
    # Ground faces point down, so their boundary edges run clockwise seen from above:
    # the outward wall over edge a → b is (b, a, a'), (b, a', b').
    walls = np.concatenate([np.column_stack([b, a, k + a]), np.column_stack([b, k + a, k + b])])
    top = gb[:, ::-1] + k
    return pos, np.concatenate([gb, top, walls]).astype(np.int64)


def oriented_box(positions: np.ndarray, faces: np.ndarray, roof: float | None = None
                 ) -> tuple[np.ndarray, np.ndarray] | None:
    """The least-area plan rectangle from the ground to the mean roof height (12 faces); None if degenerate."""
    p = np.asarray(positions, np.float64)
    f = np.asarray(faces, np.int64)
    z0 = float(p[:, 2].min())
    z1 = roof_height(p, f) if roof is None else float(roof)
    ring = _hull_ring(p[:, :2])
    if ring is None or not z1 > z0 + 1e-6:
        return None
    edges = np.roll(ring, -1, axis=0) - ring
    ang = np.arctan2(edges[:, 1], edges[:, 0])
    c, s = np.cos(ang), np.sin(ang)
    # Every hull point in every edge's frame; the rectangle of least area wins.
    u = ring[None, :, 0] * c[:, None] + ring[None, :, 1] * s[:, None]
    v = -ring[None, :, 0] * s[:, None] + ring[None, :, 1] * c[:, None]
    area = (u.max(1) - u.min(1)) * (v.max(1) - v.min(1))
    k = int(np.argmin(area))
    u0, u1, v0, v1 = u[k].min(), u[k].max(), v[k].min(), v[k].max()
    corners_uv = np.array([[u0, v0], [u1, v0], [u1, v1], [u0, v1]])
    rot = np.array([[c[k], -s[k]], [s[k], c[k]]])
    return prism(corners_uv @ rot.T, z0, z1)


def convex_hull(positions: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """The 3-D convex hull, outward faces; None when the points are flat."""
    p = np.asarray(positions, np.float64)
    try:
        h = ConvexHull(p)
    except (QhullError, ValueError):
        return None
    f = h.simplices.astype(np.int64)
    n = np.cross(p[f[:, 1]] - p[f[:, 0]], p[f[:, 2]] - p[f[:, 0]])
    flip = (n * h.equations[:, :3]).sum(axis=1) < 0
    f[flip] = f[flip][:, ::-1]
    used = np.unique(f)
    remap = np.full(p.shape[0], -1, np.int64)
    remap[used] = np.arange(used.size)
    return p[used], remap[f]
