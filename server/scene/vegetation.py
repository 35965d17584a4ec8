"""Vegetation for the mixed solver: procedural tree models, forests on height fields, tree groups.

ZMK 2002 (§4, §5.3–5.4) give every group of at most 64 trees one continuous
variable x (the share of each tree's splats drawn) and organise the groups in a
quadtree, so that variables can be tied together per quadtree node. The groups
here are the leaves of a quadtree over the trees' ground positions, found for
all trees at once from their Morton codes, so a forest of 1.4 million trees
(the paper's test scene) groups in about a second.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh

from .points import tree_face_colors
from .source import HeightGrid, Mesh, TreeInstances, TreeModel

__all__ = ["TreeGroups", "group_trees", "instance_boxes", "conifer", "broadleaf", "forest", "MORTON_BITS"]

#: Bits per axis of the quadtree's Morton codes (cells down to span / 2^20).
MORTON_BITS = 20


@dataclass
class TreeGroups:
    """Tree groups (quadtree leaves of ≤ max_group trees) as a structure of arrays.

    order       : (k,) int64 instance indices, each group's trees contiguous
    group_first : (g,) int64 first position of group j in ``order``
    group_count : (g,) int64 trees in group j (1 ≤ count ≤ max_group)
    lo, hi      : (g, 3) float64 world box of the group's transformed model boxes
    points      : (g,) int64 splats of the group at x = 1 (its models' point counts summed)
    trees       : (g,) int64 same as group_count (the N_trees of ZMK's benefit)
    level       : (g,) int64 quadtree depth of the group's cell (0 = the root square)
    node_parent : (q,) int64 quadtree nodes (leaves and their ancestors), parent or −1;
                  node_level (q,), node_lo/node_hi (q, 3), node_points (q,), node_trees (q,)
                  aggregate their leaves
    group_node  : (g,) int64 the node of each group
    """

    order: np.ndarray
    group_first: np.ndarray
    group_count: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    points: np.ndarray
    trees: np.ndarray
    level: np.ndarray
    node_parent: np.ndarray
    node_level: np.ndarray
    node_lo: np.ndarray
    node_hi: np.ndarray
    node_points: np.ndarray
    node_trees: np.ndarray
    group_node: np.ndarray

    def __len__(self) -> int:
        return int(self.group_first.shape[0])

    def members(self, j: int) -> np.ndarray:
        """Instance indices of group j."""
        return self.order[self.group_first[j] : self.group_first[j] + self.group_count[j]]


def _spread_bits(v: np.ndarray) -> np.ndarray:
    """Interleave zeros between the low 32 bits of v (uint64): b → 0b0b0b…"""
    v = v.astype(np.uint64) & np.uint64(0xFFFFFFFF)
    for shift, mask in ((16, 0x0000FFFF0000FFFF), (8, 0x00FF00FF00FF00FF), (4, 0x0F0F0F0F0F0F0F0F),
                        (2, 0x3333333333333333), (1, 0x5555555555555555)):
        v = (v | (v << np.uint64(shift))) & np.uint64(mask)
    return v


def instance_boxes(instances: TreeInstances, model_boxes: list[tuple[np.ndarray, np.ndarray]] | None
                   ) -> tuple[np.ndarray, np.ndarray]:
    """(k, 3) lo and hi: each instance's model box through its matrix.

    The box of the 8 transformed corners equals centre' ± |A|·half (A the matrix's
    linear part), which needs no (k, 8, 3) array. Without model boxes an instance's
    box is its base point.
    """
    m = instances.matrix
    if model_boxes is None:
        base = m[:, :3, 3]
        return base.copy(), base.copy()
    mlo = np.array([np.asarray(b[0], np.float64).reshape(3) for b in model_boxes]).reshape(-1, 3)
    mhi = np.array([np.asarray(b[1], np.float64).reshape(3) for b in model_boxes]).reshape(-1, 3)
    ids = instances.model
    if ids.size and (ids.min() < 0 or ids.max() >= mlo.shape[0]):
        raise ValueError(f"instance model ids must lie in 0..{mlo.shape[0] - 1}")
    centre = ((mlo + mhi) / 2)[ids]
    half = ((mhi - mlo) / 2)[ids]
    c = np.einsum("kij,kj->ki", m[:, :3, :3], centre) + m[:, :3, 3]
    h = np.einsum("kij,kj->ki", np.abs(m[:, :3, :3]), half)
    return c - h, c + h


def group_trees(
    instances: TreeInstances,
    models_points: list[int],
    *,
    max_group: int = 64,
    model_boxes: list[tuple[np.ndarray, np.ndarray]] | None = None,
) -> TreeGroups:
    """Group trees into the leaves of a quadtree over their xy positions, ≤ max_group trees per leaf.

    The root is the square around all trees; a cell holding more than max_group
    trees splits into four. Trees sorted by Morton code make every cell a
    contiguous run, so each level is a run-length pass over the codes. Trees closer
    than span / 2^MORTON_BITS share a code; an over-full cell at the last level is
    cut into consecutive chunks.

    models_points : splats per model at full resolution (index = model id)
    model_boxes   : (lo, hi) per model in model space, for the group boxes
    """
    if max_group < 1:
        raise ValueError(f"max_group must be ≥ 1, got {max_group}")
    k = len(instances)
    pts = np.asarray(models_points, np.int64).reshape(-1)
    if k and (instances.model.min() < 0 or instances.model.max() >= pts.size):
        raise ValueError(f"instance model ids must lie in 0..{pts.size - 1}")
    xy = instances.matrix[:, :2, 3]
    if not np.isfinite(instances.matrix).all():
        raise ValueError("instance matrices contain NaN or infinity")
    if k == 0:
        e, z3 = np.zeros(0, np.int64), np.zeros((0, 3))
        return TreeGroups(e, e, e, z3, z3, e, e, e, e, e, z3, z3, e, e, e)
    lo_xy = xy.min(axis=0)
    span = max(float((xy.max(axis=0) - lo_xy).max()), 1e-9)
    cells = 1 << MORTON_BITS
    q = np.minimum((xy - lo_xy) / span * cells, cells - 1).astype(np.uint64)
    code = _spread_bits(q[:, 0]) | (_spread_bits(q[:, 1]) << np.uint64(1))
    order = np.argsort(code, kind="stable")
    code = code[order]

    firsts, counts, levels, keys = [], [], [], []
    todo = np.arange(k)  # positions (in sorted order) not yet in a leaf; always whole cells
    for level in range(MORTON_BITS + 1):
        if todo.size == 0:
            break
        key = code[todo] >> np.uint64(2 * (MORTON_BITS - level))
        run_start = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
        run_count = np.diff(np.r_[run_start, todo.size])
        if level == MORTON_BITS:
            leaf = np.ones(run_start.size, bool)
        else:
            leaf = run_count <= max_group
        firsts.append(todo[run_start[leaf]])
        counts.append(run_count[leaf])
        levels.append(np.full(int(leaf.sum()), level))
        keys.append(key[run_start[leaf]])
        todo = todo[np.repeat(~leaf, run_count)]
    first = np.concatenate(firsts)
    count = np.concatenate(counts)
    level = np.concatenate(levels).astype(np.int64)
    key = np.concatenate(keys)
    by_first = np.argsort(first, kind="stable")
    first, count, level, key = first[by_first], count[by_first], level[by_first], key[by_first]
    # Coincident trees at the finest level: cut over-full cells into chunks of max_group.
    pieces = -(-count // max_group)
    if (pieces > 1).any():
        idx = np.repeat(np.arange(first.size), pieces)
        within = np.arange(idx.size) - np.repeat(np.cumsum(pieces) - pieces, pieces)
        first = first[idx] + within * max_group
        count = np.minimum(count[idx] - within * max_group, max_group)
        level, key = level[idx], key[idx]

    tlo, thi = instance_boxes(instances, model_boxes)
    tlo, thi = tlo[order], thi[order]
    g_lo = np.minimum.reduceat(tlo, first, axis=0)
    g_hi = np.maximum.reduceat(thi, first, axis=0)
    g_points = np.add.reduceat(pts[instances.model[order]], first)

    # Quadtree nodes: every leaf cell and all its ancestors, (level, key) made unique.
    depth = level + 1
    leaf_of = np.repeat(np.arange(first.size), depth)
    anc_level = np.arange(leaf_of.size) - np.repeat(np.cumsum(depth) - depth, depth)
    anc_key = key[leaf_of] >> (2 * (level[leaf_of] - anc_level)).astype(np.uint64)
    packed = (anc_level.astype(np.uint64) << np.uint64(2 * MORTON_BITS + 2)) | anc_key
    nodes, node_of = np.unique(packed, return_inverse=True)
    node_level = (nodes >> np.uint64(2 * MORTON_BITS + 2)).astype(np.int64)
    node_key = nodes & np.uint64((1 << (2 * MORTON_BITS + 2)) - 1)
    parent_packed = ((np.maximum(node_level - 1, 0).astype(np.uint64) << np.uint64(2 * MORTON_BITS + 2))
                     | (node_key >> np.uint64(2)))
    node_parent = np.where(node_level > 0, np.searchsorted(nodes, parent_packed), -1).astype(np.int64)
    q_n = nodes.size
    node_lo = np.full((q_n, 3), np.inf)
    node_hi = np.full((q_n, 3), -np.inf)
    np.minimum.at(node_lo, node_of, g_lo[leaf_of])
    np.maximum.at(node_hi, node_of, g_hi[leaf_of])
    node_points = np.bincount(node_of, g_points[leaf_of], minlength=q_n).astype(np.int64)
    node_trees = np.bincount(node_of, count[leaf_of], minlength=q_n).astype(np.int64)
    # The leaf's own node is its last ancestor entry (anc_level == level).
    group_node = node_of[np.cumsum(depth) - 1].astype(np.int64)

    return TreeGroups(
        order=order.astype(np.int64),
        group_first=first.astype(np.int64),
        group_count=count.astype(np.int64),
        lo=g_lo,
        hi=g_hi,
        points=g_points.astype(np.int64),
        trees=count.astype(np.int64),
        level=level,
        node_parent=node_parent,
        node_level=node_level,
        node_lo=node_lo,
        node_hi=node_hi,
        node_points=node_points,
        node_trees=node_trees,
        group_node=group_node,
    )


# -- procedural tree models ---------------------------------------------------------------------


def _model(name: str, trunk: trimesh.Trimesh, crown: list[trimesh.Trimesh], seed: int, **attrs) -> TreeModel:
    whole = trimesh.util.concatenate([trunk, *crown])
    mesh = Mesh(np.asarray(whole.vertices), np.asarray(whole.faces))
    trunk_faces = len(trunk.faces)
    attributes = {"trunk_faces": trunk_faces, "face_colors": tree_face_colors(mesh, trunk_faces, seed),
                  "generator": name.split("_")[0], "seed": seed, **attrs}
    return TreeModel(name, mesh, attributes)


def _trunk(radius: float, height: float) -> trimesh.Trimesh:
    t = trimesh.creation.cylinder(radius=radius, height=height, sections=8)
    t.apply_translation([0.0, 0.0, height / 2])
    return t


def conifer(seed: int, height: float | None = None) -> TreeModel:
    """A spruce-like tree: trunk cylinder and five stacked, jittered cones (~190 triangles).

    height : metres; drawn from 14–26 m by the seed if None. Base at the origin, z up.
    """
    rng = np.random.default_rng([seed, 1])
    h = float(height) if height is not None else float(rng.uniform(14.0, 26.0))
    trunk = _trunk(0.025 * h, 0.45 * h)
    tiers = 5
    crown = []
    for i in range(tiers):
        f = i / (tiers - 1)
        base = (0.18 + 0.55 * f) * h + rng.uniform(-0.02, 0.02) * h
        top = h if i == tiers - 1 else base + (0.30 - 0.08 * f) * h
        radius = (0.26 - 0.17 * f) * h * rng.uniform(0.9, 1.1)
        cone = trimesh.creation.cone(radius=radius, height=top - base, sections=16)
        v = cone.vertices.copy()
        skirt = v[:, 2] < 1e-9  # jitter the rim so tiers look ragged
        v[skirt, :2] *= rng.uniform(0.85, 1.15, (int(skirt.sum()), 1))
        v[skirt, 2] += rng.uniform(-0.02, 0.02, int(skirt.sum())) * h
        v[:, :2] += rng.uniform(-0.02, 0.02, 2) * h * f
        v[:, 2] += base
        crown.append(trimesh.Trimesh(v, cone.faces, process=False))
    return _model(f"conifer_{seed}", trunk, crown, seed, height=h)


def broadleaf(seed: int, height: float | None = None) -> TreeModel:
    """A deciduous tree: trunk cylinder and a lumpy icosphere crown (~350 triangles).

    height : metres; drawn from 8–16 m by the seed if None. Base at the origin, z up.
    """
    rng = np.random.default_rng([seed, 2])
    h = float(height) if height is not None else float(rng.uniform(8.0, 16.0))
    trunk = _trunk(0.04 * h, 0.55 * h)
    ball = trimesh.creation.icosphere(subdivisions=2, radius=1.0)
    d = np.asarray(ball.vertices)
    # Low-frequency lumps: a few random cosine waves over the sphere's directions.
    waves = rng.normal(size=(4, 3)) * 2.5
    phase = rng.uniform(0, 2 * np.pi, 4)
    lump = 1.0 + 0.12 * np.cos(d @ waves.T + phase).sum(axis=1) / 2
    radii = np.array([0.32, 0.32, 0.28]) * h * rng.uniform(0.9, 1.1, 3)
    v = d * lump[:, None] * radii
    v[:, 2] += h - radii[2] * float(lump[d[:, 2].argmax()])
    crown = trimesh.Trimesh(v, ball.faces, process=False)
    return _model(f"broadleaf_{seed}", trunk, [crown], seed, height=h)


# -- forests on height fields -------------------------------------------------------------------


def _bilinear(grid: HeightGrid, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Height and its x/y slopes at (x, y) (NaN outside the grid or next to a void)."""
    h = grid.heights
    rows, cols = h.shape
    u = (x - grid.origin[0]) / grid.spacing[0]
    v = (y - grid.origin[1]) / grid.spacing[1]
    c0 = np.clip(np.floor(u).astype(np.int64), 0, cols - 2)
    r0 = np.clip(np.floor(v).astype(np.int64), 0, rows - 2)
    fu, fv = u - c0, v - r0
    h00, h01 = h[r0, c0], h[r0, c0 + 1]
    h10, h11 = h[r0 + 1, c0], h[r0 + 1, c0 + 1]
    z = (h00 * (1 - fu) + h01 * fu) * (1 - fv) + (h10 * (1 - fu) + h11 * fu) * fv
    dzdx = ((h01 - h00) * (1 - fv) + (h11 - h10) * fv) / grid.spacing[0]
    dzdy = ((h10 - h00) * (1 - fu) + (h11 - h01) * fu) / grid.spacing[1]
    outside = (u < 0) | (u > cols - 1) | (v < 0) | (v > rows - 1)
    z = np.where(outside, np.nan, z)
    return z, dzdx, dzdy


def forest(
    grid: HeightGrid,
    n_trees: int,
    seed: int,
    models: int,
    *,
    max_slope: float = 35.0,
    treeline: float = 0.75,
    scale: tuple[float, float] = (0.8, 1.2),
) -> TreeInstances:
    """n_trees trees placed on a height field; the same seed places the same forest.

    Candidates are drawn uniformly over the grid and rejected where the bilinear
    surface touches a void (NaN), is steeper than ``max_slope`` degrees, or lies
    above ``treeline`` of the way from the lowest to the highest elevation (the
    summit stays bare). Each tree gets a random model (0..models−1), yaw and
    uniform scale; its base sits on the interpolated surface. Fewer trees are
    returned only if the terrain has no room at all (no candidate survives).
    """
    if n_trees < 0 or models < 1:
        raise ValueError(f"need n_trees ≥ 0 and models ≥ 1, got {n_trees}, {models}")
    h = np.asarray(grid.heights, np.float64)
    rows, cols = h.shape
    if rows < 2 or cols < 2:
        raise ValueError(f"height grid {grid.name!r} needs at least 2 × 2 samples, got {h.shape}")
    finite = h[np.isfinite(h)]
    if finite.size == 0:
        return TreeInstances(np.zeros(0), np.zeros((0, 4, 4)))
    z_lo, z_hi = float(finite.min()), float(finite.max())
    z_max = z_lo + treeline * (z_hi - z_lo) if z_hi > z_lo else np.inf
    max_grad = np.tan(np.radians(max_slope))
    lo = np.array(grid.origin, np.float64)
    hi = lo + np.array([(cols - 1) * grid.spacing[0], (rows - 1) * grid.spacing[1]])
    rng = np.random.default_rng(seed)
    kept_xy, kept_z, have = [], [], 0
    batch = max(1024, int(n_trees * 1.5))
    for _ in range(64):
        if have >= n_trees:
            break
        xy = rng.uniform(lo, hi, (batch, 2))
        z, gx, gy = _bilinear(grid, xy[:, 0], xy[:, 1])
        with np.errstate(invalid="ignore"):
            ok = np.isfinite(z) & (np.hypot(gx, gy) <= max_grad) & (z <= z_max)
        if not ok.any():
            break
        kept_xy.append(xy[ok])
        kept_z.append(z[ok])
        have += int(ok.sum())
        batch = max(1024, int((n_trees - have) / ok.mean() * 1.2))
    if not kept_xy:
        return TreeInstances(np.zeros(0), np.zeros((0, 4, 4)))
    xy = np.concatenate(kept_xy)[:n_trees]
    z = np.concatenate(kept_z)[:n_trees]
    k = xy.shape[0]
    yaw = rng.uniform(0, 2 * np.pi, k)
    s = rng.uniform(scale[0], scale[1], k)
    m = np.zeros((k, 4, 4))
    m[:, 0, 0] = m[:, 1, 1] = np.cos(yaw) * s
    m[:, 0, 1], m[:, 1, 0] = -np.sin(yaw) * s, np.sin(yaw) * s
    m[:, 2, 2] = s
    m[:, 0, 3], m[:, 1, 3], m[:, 2, 3] = xy[:, 0], xy[:, 1], z
    m[:, 3, 3] = 1.0
    return TreeInstances(rng.integers(0, models, k), m)
