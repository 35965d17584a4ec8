"""Tree models as prefix-ordered splats: every prefix covers the model, radii bound the coverage."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from server.scene.points import point_model, prefix_order, prefix_tree, sample_surface
from server.scene.source import Mesh
from server.scene.vegetation import broadleaf, conifer

PREFIXES = (16, 64, 256, 1024)


def _coverage(points: np.ndarray, chosen: np.ndarray) -> float:
    """Max over all points of the distance to the nearest chosen point."""
    return float(cKDTree(points[chosen]).query(points)[0].max())


@pytest.fixture(scope="module", params=["conifer", "broadleaf"])
def samples(request):
    tm = conifer(0) if request.param == "conifer" else broadleaf(1)
    return sample_surface(tm.mesh, 4096, seed=0)[0]


def test_order_is_a_permutation_with_non_increasing_radius(samples):
    order, cell, radius = prefix_tree(samples)
    assert order.dtype == np.int64 and np.array_equal(np.sort(order), np.arange(len(samples)))
    assert (np.diff(radius) <= 0).all() and radius[-1] == 0
    assert (cell >= 0).all() and cell[0] == radius[0]
    assert np.array_equal(prefix_order(samples), order)


def test_any_prefix_is_good(samples):
    order, _, radius = prefix_tree(samples)
    rng = np.random.default_rng(7)
    n = len(samples)
    for size in PREFIXES:
        ours = _coverage(samples, order[:size])
        assert ours <= radius[size - 1] + 1e-9  # the recorded radius is a true bound …
        assert radius[size - 1] <= 1.5 * ours  # … and a tight one
        best_random = min(_coverage(samples, rng.choice(n, size, replace=False)) for _ in range(8))
        random_prefix = np.mean([_coverage(samples, rng.permutation(n)[:size]) for _ in range(5)])
        assert ours <= 1.25 * best_random
        assert ours <= 0.9 * random_prefix


def test_breadth_order_completes_levels(samples):
    order, _, radius = prefix_tree(samples, split_order="breadth")
    assert np.array_equal(np.sort(order), np.arange(len(samples))) and (np.diff(radius) <= 0).all()
    for size in PREFIXES:
        assert _coverage(samples, order[:size]) <= radius[size - 1] + 1e-9


def test_sampling_is_deterministic_and_on_the_surface():
    tm = conifer(4)
    a = sample_surface(tm.mesh, 500, seed=3, colors=tm.attributes["face_colors"])
    b = sample_surface(tm.mesh, 500, seed=3, colors=tm.attributes["face_colors"])
    assert all(np.array_equal(x, y) for x, y in zip(a, b))
    assert np.allclose(np.linalg.norm(a[1], axis=1), 1)
    sq = Mesh([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], [[0, 1, 2], [0, 2, 3]])
    p, n, c = sample_surface(sq, 2000, seed=1, colors=np.array([[10, 20, 30], [40, 50, 60]], np.uint8))
    assert (p[:, 2] == 0).all() and (p[:, :2] >= 0).all() and (p[:, :2] <= 1).all()
    assert abs((p[:, 0] > p[:, 1]).mean() - 0.5) < 0.05  # area-weighted: both halves alike
    assert np.allclose(np.abs(n[:, 2]), 1)
    assert set(map(tuple, c)) == {(10, 20, 30), (40, 50, 60)}
    with pytest.raises(ValueError):
        sample_surface(Mesh(np.zeros((3, 3)), [[0, 1, 2]]), 10, seed=0)


def test_point_model_fields():
    pm = point_model(broadleaf(2), n_points=2048, seed=5)
    assert pm.positions.shape == pm.normals.shape == (2048, 3) and pm.colors.dtype == np.uint8
    assert (np.diff(pm.radius) <= 0).all() and pm.radius[-1] > 0
    assert (pm.positions >= pm.lo).all() and (pm.positions <= pm.hi).all()
    assert pm.lo[2] >= -1e-9  # base at the origin
    greens = pm.colors[:, 1] > pm.colors[:, 0]
    assert 0.5 < greens.mean() < 1  # mostly crown, some trunk
    again = point_model(broadleaf(2), n_points=2048, seed=5)
    assert np.array_equal(pm.positions, again.positions)


def test_ordering_of_many_points_is_a_permutation():
    """(Its speed is measured in test_perf.py.)"""
    p = np.random.default_rng(0).normal(size=(100_000, 3))
    order = prefix_order(p)
    assert np.array_equal(np.sort(order), np.arange(100_000))


def test_degenerate_inputs():
    order, cell, radius = prefix_tree(np.zeros((1, 3)))
    assert order.tolist() == [0] and radius.tolist() == [0.0]
    same = prefix_tree(np.ones((50, 3)))
    assert np.array_equal(np.sort(same[0]), np.arange(50)) and (same[2] == 0).all()
    with pytest.raises(ValueError):
        prefix_tree(np.array([[0, 0, np.nan]]))
