"""Planar polygon triangulation: holes, orientation, 3-D planes, degenerate rings."""

from __future__ import annotations

import numpy as np
import pytest

from server.scene.importers.polygons import (flatten_polygons, newell_normal, triangulate_polygon,
                                             triangulate_polygons, triangulate_rings)

SQUARE = np.array([[0, 0, 0], [4, 0, 0], [4, 4, 0], [0, 4, 0]], float)
HOLE = np.array([[1, 1, 0], [1, 3, 0], [3, 3, 0], [3, 1, 0]], float)


def _areas(points: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area vectors (m, 3) of the triangles: direction = their normals."""
    t = points[faces]
    return 0.5 * np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])


def test_square_with_hole_gives_eight_triangles_of_the_right_area():
    faces = triangulate_polygon([SQUARE, HOLE])
    assert faces.shape == (8, 3)
    area = _areas(np.concatenate([SQUARE, HOLE]), faces)
    assert np.allclose(area[:, :2], 0)
    assert area[:, 2].sum() == pytest.approx(16 - 4)
    assert (area[:, 2] > 0).all()  # counter-clockwise outer ring → +z normals


def test_clockwise_outer_ring_keeps_its_downward_normal():
    outer = SQUARE[::-1]
    faces = triangulate_polygon([outer, HOLE[::-1]])
    area = _areas(np.concatenate([outer, HOLE[::-1]]), faces)
    assert (area[:, 2] < 0).all() and area[:, 2].sum() == pytest.approx(-12)


def test_vertical_and_tilted_polygons_in_3d():
    # An L-shaped (concave) facade in the plane x = 5, wound so its normal is +x.
    yz = np.array([[0, 0], [6, 0], [6, 2], [2, 2], [2, 5], [0, 5]], float)
    wall = np.column_stack([np.full(6, 5.0), yz])
    faces = triangulate_polygon([wall])
    area = _areas(wall, faces)
    assert faces.shape == (4, 3)
    assert area.sum(axis=0) == pytest.approx([6 * 2 + 2 * 3, 0, 0])
    # The same polygon rotated into a tilted plane at map coordinates, with a little noise off the plane.
    rng = np.random.default_rng(1)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    tilted = wall @ q.T + [80_000.0, 455_000.0, 10.0] + rng.normal(scale=1e-6, size=wall.shape)
    faces2 = triangulate_polygon([tilted])
    n = newell_normal(tilted)
    area2 = _areas(tilted, faces2)
    assert faces2.shape == (4, 3)
    assert np.linalg.norm(area2.sum(axis=0)) == pytest.approx(18, rel=1e-6)
    assert (area2 @ n > 0).all()


def test_newell_normal_is_twice_the_area_along_the_right_hand_normal():
    assert newell_normal(SQUARE) == pytest.approx([0, 0, 32])
    assert newell_normal(SQUARE[::-1]) == pytest.approx([0, 0, -32])


def test_degenerate_rings_are_skipped():
    line = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0]], float)  # collinear: zero area
    twice = np.array([[0, 0, 0], [1, 1, 1], [1, 1, 1], [0, 0, 0]], float)  # two distinct points
    assert triangulate_polygon([line]).shape == (0, 3)
    assert triangulate_polygon([twice]).shape == (0, 3)
    # A degenerate hole is ignored, the outer ring still triangulated whole.
    faces = triangulate_polygon([SQUARE, line + [0.5, 0.5, 0]])
    assert _areas(np.concatenate([SQUARE, line]), faces)[:, 2].sum() == pytest.approx(16)


def test_repeated_closing_point_and_indexed_batch():
    v = np.concatenate([SQUARE, HOLE, [[0, 0, 9], [1, 0, 9], [0, 1, 9]]])
    polygons = [
        [[0, 1, 2, 3, 0], [4, 5, 6, 7]],  # closed outer ring (first point repeated) with a hole
        [[8, 9, 10]],  # plain triangle: kept as it is
        [[0, 1, 0]],  # degenerate: skipped
    ]
    faces, owner = triangulate_rings(v, flatten_polygons(polygons))
    assert faces.shape == (9, 3)
    assert np.bincount(owner).tolist() == [8, 1]
    assert faces[owner == 1].tolist() == [[8, 9, 10]]
    assert np.array_equal(triangulate_polygons(v, polygons), faces)


def test_flatten_rejects_non_integer_indices():
    with pytest.raises(ValueError, match="'a'"):
        flatten_polygons([[[0, 1, "a"]]])
    with pytest.raises(ValueError, match="1.5"):
        flatten_polygons([[[0, 1, 1.5]]])
