"""Tree models as point sets whose every prefix is a good splat model (ZMK 2002, §5.1–5.2).

ZMK store a tree's leaf positions in a K-d tree built by splitting at the median
of the longest axis, and render a budget of N splats by walking that tree. We
flatten the walk once, offline: every split of the same K-d tree emits one
representative, coarsest cell first, so the first N points represent a cut of
the tree into N cells (about the cells of depth log2 N) — a budget is then just
a prefix length, which a GPU draws with one call and a stream can send
incrementally. Along the order we also
record the splat radius that makes each prefix hole-free.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .source import Mesh, TreeModel

__all__ = ["PointModel", "sample_surface", "prefix_order", "prefix_tree", "tree_colors", "tree_face_colors",
           "point_model"]

_GREY = np.array([128, 128, 128], np.uint8)


@dataclass
class PointModel:
    """A tree model as prefix-ordered splats (model space: base at the origin, z up).

    positions : (n, 3) float64, in prefix order
    normals   : (n, 3) float64, unit
    colors    : (n, 3) uint8, rgb
    radius    : (n,) float64, non-increasing; radius[N − 1] is the splat radius that
                lets the prefix of N points cover the model without holes
    lo, hi    : (3,) float64, the box of all points
    """

    name: str
    positions: np.ndarray
    normals: np.ndarray
    colors: np.ndarray
    radius: np.ndarray
    lo: np.ndarray
    hi: np.ndarray

    def __len__(self) -> int:
        return int(self.positions.shape[0])


def _face_geometry(mesh: Mesh) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    tri = mesh.positions[mesh.faces]  # (m, 3, 3)
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    double_area = np.linalg.norm(cross, axis=1)
    normals = cross / np.where(double_area > 0, double_area, 1.0)[:, None]
    return tri, cross, double_area / 2, normals


def sample_surface(
    mesh: Mesh, n: int, seed: int, colors: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """n area-weighted uniform samples of the surface; the same seed gives the same samples.

    colors : per-face (m, 3) uint8, or a single (3,) colour; grey if None.
    Returns positions (n, 3) float64, normals (n, 3) float64 (the face normals),
    colors (n, 3) uint8.
    """
    if n <= 0:
        raise ValueError(f"sample count must be positive, got {n}")
    if mesh.n_faces == 0:
        raise ValueError("cannot sample a mesh without faces")
    tri, _, area, face_normals = _face_geometry(mesh)
    cum = np.cumsum(area)
    if not np.isfinite(cum[-1]) or cum[-1] <= 0:
        raise ValueError("mesh has no surface area to sample")
    rng = np.random.default_rng(seed)
    u = rng.random((n, 3))
    face = np.minimum(np.searchsorted(cum, u[:, 0] * cum[-1], side="right"), mesh.n_faces - 1)
    # Uniform barycentrics by folding the unit square onto the triangle.
    a, b = u[:, 1], u[:, 2]
    fold = a + b > 1
    a, b = np.where(fold, 1 - a, a), np.where(fold, 1 - b, b)
    t = tri[face]
    positions = t[:, 0] + a[:, None] * (t[:, 1] - t[:, 0]) + b[:, None] * (t[:, 2] - t[:, 0])
    if colors is None:
        out_colors = np.broadcast_to(_GREY, (n, 3)).copy()
    else:
        colors = np.asarray(colors, np.uint8)
        if colors.shape == (3,):
            out_colors = np.broadcast_to(colors, (n, 3)).copy()
        elif colors.shape == (mesh.n_faces, 3):
            out_colors = colors[face]
        else:
            raise ValueError(f"colors must be (3,) or ({mesh.n_faces}, 3), got {colors.shape}")
    return positions, face_normals[face].copy(), out_colors


def _first_min(values: np.ndarray, starts: np.ndarray, seg: np.ndarray) -> np.ndarray:
    """For contiguous segments of values, the position of each segment's first minimum."""
    low = np.minimum.reduceat(values, starts)
    pos = np.where(values == low[seg], np.arange(values.size), values.size)
    return np.minimum.reduceat(pos, starts)


def prefix_tree(
    positions: np.ndarray, *, centre: str = "box", split_order: str = "coarsest"
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The median K-d order of ``prefix_order`` with its radii.

    The K-d tree is ZMK's: every cell of ≥ 2 points splits at the median of its
    longest axis. Each split emits one point: the child holding the cell's
    representative keeps it, the other child's representative is its point
    nearest its box centre (``centre="box"``) or centroid (``"centroid"``). So
    the first N points are the representatives of a cut of the tree into N cells.

    split_order : "coarsest" (default) makes the split with the largest covering
                  radius next (a vectorised sort of all splits once the tree is
                  built): every prefix is the greedy cut of the tree for
                  coverage. "breadth" is the strict level order (largest first
                  within a level): the prefix that completes depth d holds one point
                  per depth-d cell, but thin parts (a trunk) wait for whole levels;
                  so its prefix coverage on tree models is worse at N = 64…1024.

    All cells of a level are processed at once: the points are kept in three
    arrays, each sorted by one axis within every cell, and a split is a stable
    partition of all three (cumulative sums, no sorting after the first).

    Returns
      order       : (n,) int64 permutation — order[i] is the i-th point emitted
      cell_radius : (n,) float64 — for the i-th emitted point, the reach (largest
                    distance from it to a point of its cell) of the cell it represents
                    when emitted
      radius      : (n,) float64 non-increasing — every one of the n points lies within
                    radius[N − 1] of one of the first N emitted points (an upper bound
                    on the prefix's coverage distance; 0 once all points are emitted).
                    A cell's points are within its reach of its representative and within
                    every ancestor's reach of that ancestor's (emitted) representative.
    """
    p = np.asarray(positions, np.float64)
    if p.ndim != 2 or p.shape[1] != 3 or p.shape[0] == 0:
        raise ValueError(f"positions must be (n, 3) with n > 0, got {p.shape}")
    if not np.isfinite(p).all():
        raise ValueError("positions contain NaN or infinity")
    if split_order not in ("breadth", "coarsest"):
        raise ValueError(f"split_order must be 'breadth' or 'coarsest', got {split_order!r}")
    if centre not in ("centroid", "box"):
        raise ValueError(f"centre must be 'centroid' or 'box', got {centre!r}")
    n = p.shape[0]
    ar = np.arange(n)
    by_axis = [np.argsort(p[:, a], kind="stable") for a in range(3)]  # point ids, sorted per cell
    start, count = np.array([0]), np.array([n])
    seg = np.zeros(n, np.int64)

    pt = np.ascontiguousarray(p.T)  # (3, n): per-axis gathers are much faster than row gathers

    def representatives(q: np.ndarray, start: np.ndarray, seg: np.ndarray) -> np.ndarray:
        if centre == "centroid":
            counts = np.diff(np.append(start, n))
            c = np.add.reduceat(q, start, axis=1) / counts
        else:
            last = np.append(start[1:], n) - 1
            c = np.stack([pt[a, by_axis[a][start]] + pt[a, by_axis[a][last]] for a in range(3)]) / 2
        d2 = sum((q[a] - c[a][seg]) ** 2 for a in range(3))
        return by_axis[0][_first_min(d2, start, seg)]

    def reaches(q: np.ndarray, rep: np.ndarray, start: np.ndarray, seg: np.ndarray) -> np.ndarray:
        r = pt[:, rep]
        d2 = sum((q[a] - r[a][seg]) ** 2 for a in range(3))
        return np.sqrt(np.maximum.reduceat(d2, start))

    q = pt[:, by_axis[0]]
    rep = representatives(q, start, seg)
    reach = reaches(q, rep, start, seg)
    key = reach.copy()  # covering radius of a cell: its own reach, or an ancestor's if smaller
    root_rep, root_reach = rep.copy(), reach.copy()
    ev_key, ev_depth, ev_point, ev_reach, ev_kids = [], [], [], [], []
    depth = 0
    while (count >= 2).any():
        split = count >= 2
        end = start + count - 1
        ext = np.stack([pt[a, by_axis[a][end]] - pt[a, by_axis[a][start]] for a in range(3)], axis=1)
        axis = np.argmax(ext, axis=1)
        half = np.where(split, count // 2, count)
        offset = ar - start[seg]
        is_left = np.empty(n, bool)
        for a in range(3):
            mine = axis[seg] == a
            is_left[by_axis[a][mine]] = offset[mine] < half[seg[mine]]
        for a in range(3):
            left = is_left[by_axis[a]]
            rank = np.cumsum(left)
            rank -= (rank - left)[start][seg]  # lefts up to and including here, within the cell
            new_pos = np.where(left, start[seg] + rank - 1, start[seg] + half[seg] + offset - rank)
            moved = np.empty(n, np.int64)
            moved[new_pos] = by_axis[a]
            by_axis[a] = moved
        # Children: (start) and, for split cells, (start + half).
        kids = 1 + split.astype(np.int64)
        c_start = np.repeat(start, kids)
        second = np.zeros(c_start.size, bool)
        second[np.cumsum(kids)[split] - 1] = True
        parent = np.repeat(np.arange(start.size), kids)
        c_start[second] += half[parent[second]]
        c_count = np.diff(np.append(c_start, n))
        c_seg = np.repeat(np.arange(c_start.size), c_count)
        q = pt[:, by_axis[0]]
        fresh = representatives(q, c_start, c_seg)
        inherits = ~second == is_left[rep[parent]]  # first child ⇔ left half
        c_rep = np.where(inherits, rep[parent], fresh)
        c_reach = reaches(q, c_rep, c_start, c_seg)
        c_key = np.minimum(c_reach, key[parent])
        # One split event per split cell: it emits the representative of the child that did
        # not inherit the cell's own.
        new = ~inherits
        kid_key = np.zeros(start.size)
        np.maximum.at(kid_key, parent, c_key)
        ev_key.append(key[parent[new]])
        ev_depth.append(np.full(int(new.sum()), depth))
        ev_point.append(c_rep[new])
        ev_reach.append(c_reach[new])
        ev_kids.append(kid_key[parent[new]])
        start, count, seg, rep, reach, key = c_start, c_count, c_seg, c_rep, c_reach, c_key
        depth += 1
    if not ev_key:
        return root_rep.astype(np.int64), root_reach, np.zeros(1)
    e_key, e_depth = np.concatenate(ev_key), np.concatenate(ev_depth)
    e_point, e_reach, e_kids = np.concatenate(ev_point), np.concatenate(ev_reach), np.concatenate(ev_kids)
    seq = np.arange(e_key.size)
    if split_order == "coarsest":
        # Keys never grow from parent to child, so sorting by key (parents first on ties)
        # is a valid order; after j splits every remaining cell is covered within the
        # key of the next split.
        s = np.lexsort((seq, e_depth, -e_key))
        bound = np.append(e_key[s], 0.0)
    else:
        s = np.lexsort((seq, -e_key, e_depth))
        # After the k-th split of a level: the children made so far in this level, and the
        # next cell waiting (keys sorted within the level, so the next event's).
        span = float(e_key.max()) * 2 + 1.0
        made = np.maximum.accumulate(e_kids[s] + e_depth[s] * span) - e_depth[s] * span
        waiting = np.append(e_key[s][1:], 0.0)
        bound = np.r_[root_reach, np.maximum(made, waiting)]
        bound = np.maximum.accumulate(bound[::-1])[::-1]
    order = np.r_[root_rep, e_point[s]].astype(np.int64)
    cell_radius = np.r_[root_reach, e_reach[s]]
    return order, cell_radius, bound


def prefix_order(positions: np.ndarray) -> np.ndarray:
    """(n,) int64 permutation such that every prefix of ``positions[order]`` covers the set evenly."""
    return prefix_tree(positions)[0]


def tree_colors(points: np.ndarray, reference: np.ndarray | None = None, trunk: np.ndarray | None = None,
                seed: int = 0) -> np.ndarray:
    """(m, 3) uint8 bark-and-foliage colours: trunk brown, crown greens lighter with height.

    points    : (m, 3) float, what is coloured (face centres, or a scan's points), model space
    reference : (n, 3) float, the model's points its height and spread are measured on
                (default: ``points``)
    trunk     : (m,) bool, which points are trunk; if None, those near the z axis in the
                lowest third of the model
    """
    c = np.asarray(points, np.float64)
    ref = c if reference is None else np.asarray(reference, np.float64)
    z0, z1 = float(ref[:, 2].min()), float(ref[:, 2].max())
    rel = (c[:, 2] - z0) / max(z1 - z0, 1e-9)
    if trunk is None:
        axis_dist = np.hypot(c[:, 0], c[:, 1])
        spread = max(float(np.hypot(ref[:, 0], ref[:, 1]).max()), 1e-9)
        trunk = (rel < 1 / 3) & (axis_dist < 0.15 * spread)
    rng = np.random.default_rng(seed)
    jitter = rng.uniform(-12, 12, (c.shape[0], 1))
    green = np.column_stack([30 + 40 * rel, 80 + 80 * rel, 25 + 30 * rel]) + jitter
    brown = np.array([101.0, 67.0, 33.0]) + jitter / 2
    return np.clip(np.where(trunk[:, None], brown, green), 0, 255).astype(np.uint8)


def tree_face_colors(mesh: Mesh, trunk_faces: int | None = None, seed: int = 0) -> np.ndarray:
    """(m, 3) uint8 ``tree_colors`` of a mesh's faces.

    trunk_faces : the first faces that are trunk (procedural models record it); if None,
                  faces near the z axis in the lowest third of the model count as trunk.
    """
    trunk = None if trunk_faces is None else np.arange(mesh.n_faces) < trunk_faces
    return tree_colors(mesh.positions[mesh.faces].mean(axis=1), mesh.positions, trunk, seed)


def point_model(tree_model: TreeModel, n_points: int = 4096, seed: int = 0) -> PointModel:
    """A tree model's splats in prefix order: a mesh's surface samples, or a scan's own points.

    Mesh: colours come from ``attributes["face_colors"]`` (m, 3) if the model has them, else
    ``tree_face_colors`` (honouring ``attributes["trunk_faces"]``). The splat radius of a
    prefix is the larger of its coverage bound and the radius of N equal discs tiling the
    surface area, sqrt(A / (π N)), so the full set still draws closed.

    Scan (``tree_model.points``, ``server.scene.scans``): its points are ordered the same
    way and the first ``n_points`` kept; the discs are those of the whole scan, each of
    ``attributes["spacing"]`` (its point spacing), shared out over N points: spacing ·
    sqrt(n_scan / N).
    """
    if tree_model.points is not None:
        return _scan_point_model(tree_model, n_points)
    mesh = tree_model.mesh
    colors = tree_model.attributes.get("face_colors")
    if colors is None:
        colors = tree_face_colors(mesh, tree_model.attributes.get("trunk_faces"), seed)
    positions, normals, cols = sample_surface(mesh, n_points, seed, colors)
    order, _, bound = prefix_tree(positions)
    area = float(_face_geometry(mesh)[2].sum())
    disc = np.sqrt(area / (np.pi * np.arange(1, n_points + 1)))
    positions = positions[order]
    return PointModel(
        name=tree_model.name,
        positions=positions,
        normals=normals[order],
        colors=cols[order],
        radius=np.maximum(bound, disc),
        lo=positions.min(axis=0),
        hi=positions.max(axis=0),
    )


def _scan_point_model(tree_model: TreeModel, n_points: int) -> PointModel:
    scan = tree_model.points
    if n_points <= 0:
        raise ValueError(f"point count must be positive, got {n_points}")
    spacing = float(tree_model.attributes.get("spacing", 0.0))
    if not np.isfinite(spacing) or spacing < 0:
        raise ValueError(f"tree model {tree_model.name!r}: spacing must be finite and ≥ 0, got {spacing}")
    order, _, bound = prefix_tree(scan.positions)
    n = min(n_points, order.size)
    order, bound = order[:n], bound[:n]
    disc = spacing * np.sqrt(len(scan) / np.arange(1, n + 1))
    positions = scan.positions[order]
    return PointModel(
        name=tree_model.name,
        positions=positions,
        normals=scan.normals[order],
        colors=scan.colors[order],
        radius=np.maximum(bound, disc),
        lo=positions.min(axis=0),
        hi=positions.max(axis=0),
    )
