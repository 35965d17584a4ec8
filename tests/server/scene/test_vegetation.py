"""Tree groups, procedural tree models and forests on height fields."""

from __future__ import annotations

import numpy as np
import pytest

from server.scene.source import HeightGrid, TreeInstances
from server.scene.vegetation import broadleaf, conifer, forest, group_trees, instance_boxes


def _grid(rows: int = 257, spacing: float = 10.0) -> HeightGrid:
    yy, xx = np.mgrid[0:rows, 0:rows] / rows
    h = 900 * np.exp(-((xx - 0.5) ** 2 + (yy - 0.5) ** 2) / 0.04) + 30 * np.sin(xx * 9) + 100
    h[:40, :60] = np.nan  # a void in one corner
    return HeightGrid("g", h, (1000.0, -500.0), (spacing, spacing))


def _bilinear_reference(g: HeightGrid, x: float, y: float) -> float:
    u, v = (x - g.origin[0]) / g.spacing[0], (y - g.origin[1]) / g.spacing[1]
    c, r = int(np.floor(u)), int(np.floor(v))
    fu, fv = u - c, v - r
    h = g.heights
    return float(h[r, c] * (1 - fu) * (1 - fv) + h[r, c + 1] * fu * (1 - fv) + h[r + 1, c] * (1 - fu) * fv
                 + h[r + 1, c + 1] * fu * fv)


@pytest.fixture(scope="module")
def models():
    return [conifer(i) for i in range(3)] + [broadleaf(i) for i in range(2)]


@pytest.fixture(scope="module")
def boxes(models):
    return [(m.mesh.positions.min(axis=0), m.mesh.positions.max(axis=0)) for m in models]


def test_tree_models_are_small_and_stand_on_the_origin(models):
    for m in models:
        p = m.mesh.positions
        assert 100 <= m.mesh.n_faces <= 600
        assert abs(p[:, 2].min()) < 1e-9 and p[:, 2].max() > 5
        assert np.abs(p[:, :2].mean(axis=0)).max() < 0.1 * p[:, 2].max()
        assert m.attributes["face_colors"].shape == (m.mesh.n_faces, 3)
        assert 0 < m.attributes["trunk_faces"] < m.mesh.n_faces
    assert np.array_equal(conifer(1).mesh.positions, conifer(1).mesh.positions)
    assert not np.array_equal(conifer(1).mesh.positions, conifer(2).mesh.positions)
    assert conifer(0, height=30.0).mesh.positions[:, 2].max() == pytest.approx(30.0)


def test_forest_sits_on_the_surface_and_avoids_voids():
    g = _grid()
    trees = forest(g, 5000, seed=4, models=5)
    assert len(trees) == 5000 and trees.model.min() >= 0 and trees.model.max() < 5
    m = trees.matrix
    assert np.allclose(m[:, 3], [0, 0, 0, 1])
    scale = np.cbrt(np.linalg.det(m[:, :3, :3]))
    assert (scale >= 0.8 - 1e-9).all() and (scale <= 1.2 + 1e-9).all()
    assert np.allclose(m[:, 2, 2], scale)  # yaw only: upright trees
    for i in range(0, 5000, 97):
        x, y, z = m[i, :3, 3]
        assert z == pytest.approx(_bilinear_reference(g, x, y), abs=1e-6)
    col = np.floor((m[:, 0, 3] - g.origin[0]) / g.spacing[0]).astype(int)
    row = np.floor((m[:, 1, 3] - g.origin[1]) / g.spacing[1]).astype(int)
    h = g.heights
    corners = np.stack([h[row, col], h[row + 1, col], h[row, col + 1], h[row + 1, col + 1]])
    assert np.isfinite(corners).all()  # no tree on (or next to) a void
    finite = h[np.isfinite(h)]
    assert m[:, 2, 3].max() <= finite.min() + 0.75 * (finite.max() - finite.min())  # bare summit
    again = forest(g, 5000, seed=4, models=5)
    assert np.array_equal(again.matrix, trees.matrix) and np.array_equal(again.model, trees.model)
    assert not np.array_equal(forest(g, 5000, seed=5, models=5).matrix, trees.matrix)


def test_forest_on_an_all_void_grid_is_empty():
    g = HeightGrid("void", np.full((10, 10), np.nan), (0.0, 0.0), (1.0, 1.0))
    assert len(forest(g, 100, seed=0, models=2)) == 0


def _check_groups(trees: TreeInstances, groups, boxes, max_group: int, points: list[int]) -> None:
    k = len(trees)
    assert np.array_equal(np.sort(groups.order), np.arange(k))  # every tree exactly once
    assert (groups.group_count >= 1).all() and (groups.group_count <= max_group).all()
    assert groups.group_first[0] == 0
    assert np.array_equal(groups.group_first[1:], np.cumsum(groups.group_count)[:-1])
    assert groups.group_count.sum() == k and np.array_equal(groups.trees, groups.group_count)
    group_of = np.repeat(np.arange(len(groups)), groups.group_count)
    member = groups.order
    # Group boxes hold the 8 transformed corners of every member's model box.
    lo = np.array([b[0] for b in boxes])[trees.model[member]]
    hi = np.array([b[1] for b in boxes])[trees.model[member]]
    corners = np.stack([np.where(np.array([(c >> a) & 1 for a in range(3)], bool), hi, lo) for c in range(8)], 1)
    world = np.einsum("kij,kcj->kci", trees.matrix[member, :3, :3], corners) + trees.matrix[member, None, :3, 3]
    eps = 1e-6
    assert (world >= groups.lo[group_of][:, None] - eps).all() and (world <= groups.hi[group_of][:, None] + eps).all()
    assert np.array_equal(groups.points, np.bincount(group_of, np.asarray(points)[trees.model[member]]).astype(int))
    # The quadtree above the groups: the root holds everything, parents hold their children.
    root = np.flatnonzero(groups.node_parent < 0)
    assert root.size == 1 and groups.node_trees[root[0]] == k
    child = np.flatnonzero(groups.node_parent >= 0)
    par = groups.node_parent[child]
    assert (groups.node_level[par] == groups.node_level[child] - 1).all()
    assert (groups.node_lo[par] <= groups.node_lo[child]).all() and (groups.node_hi[par] >= groups.node_hi[child]).all()
    # Chunks of coincident trees share a leaf node; otherwise each group is its own node.
    per_node = np.bincount(groups.group_node, groups.group_count, minlength=groups.node_parent.size)
    leaves = np.unique(groups.group_node)
    assert np.array_equal(groups.node_trees[leaves], per_node[leaves])


def test_groups_partition_the_forest(models, boxes):
    trees = forest(_grid(), 20000, seed=1, models=len(models))
    points = [4096, 2048, 1024, 512, 256]
    groups = group_trees(trees, points, max_group=64, model_boxes=boxes)
    _check_groups(trees, groups, boxes, 64, points)
    assert groups.group_count.mean() > 16  # leaves are not needlessly small
    again = group_trees(trees, points, max_group=64, model_boxes=boxes)
    assert np.array_equal(again.order, groups.order) and np.array_equal(again.lo, groups.lo)


def test_coincident_and_tiny_forests(boxes):
    m = np.tile(np.eye(4), (200, 1, 1))
    m[:100, :3, 3] = [5.0, 5.0, 0.0]  # 100 trees on one spot: chunked at the finest level
    m[100:, :3, 3] = np.random.default_rng(0).uniform(0, 100, (100, 3))
    trees = TreeInstances(np.zeros(200, int), m)
    groups = group_trees(trees, [100], max_group=64, model_boxes=boxes[:1])
    _check_groups(trees, groups, boxes[:1], 64, [100])
    one = TreeInstances([0], np.eye(4)[None])
    g1 = group_trees(one, [10], model_boxes=boxes[:1])
    assert g1.group_count.tolist() == [1] and g1.points.tolist() == [10]
    assert len(group_trees(TreeInstances(np.zeros(0), np.zeros((0, 4, 4))), [10])) == 0


def test_instance_boxes_match_corners(boxes):
    rng = np.random.default_rng(2)
    m = np.tile(np.eye(4), (50, 1, 1))
    m[:, :3, :3] = rng.normal(size=(50, 3, 3))
    m[:, :3, 3] = rng.normal(size=(50, 3))
    trees = TreeInstances(rng.integers(0, len(boxes), 50), m)
    lo, hi = instance_boxes(trees, boxes)
    blo = np.array([b[0] for b in boxes])[trees.model]
    bhi = np.array([b[1] for b in boxes])[trees.model]
    corners = np.stack([np.where(np.array([(c >> a) & 1 for a in range(3)], bool), bhi, blo) for c in range(8)], 1)
    world = np.einsum("kij,kcj->kci", m[:, :3, :3], corners) + m[:, None, :3, 3]
    assert np.allclose(lo, world.min(axis=1)) and np.allclose(hi, world.max(axis=1))


def test_big_forest_places_and_groups(boxes):
    """St. Helens' scale (its speed is measured in test_perf.py)."""
    g = _grid(rows=2049, spacing=58.6)
    trees = forest(g, 1_400_000, seed=0, models=len(boxes))
    groups = group_trees(trees, [4096] * len(boxes), model_boxes=boxes)
    assert len(trees) == 1_400_000 and groups.group_count.max() <= 64
