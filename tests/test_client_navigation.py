"""Tour: piecewise-linear eye, nlerp'd orthonormal directions, looping, fixed one-key tours."""

from __future__ import annotations

import numpy as np
import pytest

from client.navigation import Tour
from proto.messages import TourKey


def _keys() -> list[TourKey]:
    return [
        TourKey(t=0.0, eye=[0.0, 0.0, 0.0], forward=[1.0, 0.0, 0.0], up=[0.0, 0.0, 1.0]),
        TourKey(t=2.0, eye=[10.0, 0.0, 0.0], forward=[0.0, 1.0, 0.0], up=[0.0, 0.0, 1.0]),
        TourKey(t=4.0, eye=[10.0, 10.0, 2.0], forward=[0.0, 2.0, 0.0], up=[0.0, 0.5, 3.0]),
    ]


def test_keys_are_hit_exactly() -> None:
    tour = Tour(_keys())
    assert tour.duration == 4.0
    eye, f, u = tour.pose_at(2.0)
    np.testing.assert_allclose(eye, [10, 0, 0])
    np.testing.assert_allclose(f, [0, 1, 0], atol=1e-12)
    np.testing.assert_allclose(u, [0, 0, 1], atol=1e-12)


def test_eye_is_linear_and_directions_are_orthonormal() -> None:
    tour = Tour(_keys())
    eye, f, u = tour.pose_at(1.0)
    np.testing.assert_allclose(eye, [5, 0, 0])
    np.testing.assert_allclose(f, np.array([1, 1, 0]) / np.sqrt(2), atol=1e-12)
    eye, f, u = tour.pose_at(np.linspace(0, 3.99, 50))
    assert eye.shape == f.shape == u.shape == (50, 3)
    np.testing.assert_allclose(np.linalg.norm(f, axis=1), 1, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(u, axis=1), 1, atol=1e-12)
    np.testing.assert_allclose(np.sum(f * u, axis=1), 0, atol=1e-12)
    # Key 3's up (0, 0.5, 3) is not perpendicular to its forward: re-orthogonalised.
    _, f3, u3 = tour.pose_at(3.999999)
    np.testing.assert_allclose(u3, [0, 0, 1], atol=1e-5)


def test_loops_over_duration() -> None:
    tour = Tour(_keys())
    t = np.array([0.5, 1.7, 3.2])
    for a, b in zip(tour.pose_at(t), tour.pose_at(t + 3 * tour.duration)):
        np.testing.assert_allclose(a, b, atol=1e-9)
    np.testing.assert_allclose(tour.pose_at(4.0)[0], [0, 0, 0])  # wraps to the first key


def test_one_key_tour_is_fixed_and_dicts_accepted() -> None:
    tour = Tour([{"t": 5.0, "eye": [1, 2, 3], "forward": [0, 0, -2], "up": [0, 1, 0]}])
    assert tour.duration == 0.0
    eye, f, u = tour.pose_at(123.4)
    np.testing.assert_allclose(eye, [1, 2, 3])
    np.testing.assert_allclose(f, [0, 0, -1])
    eyes, _, _ = tour.pose_at(np.array([0.0, 1e5]))
    np.testing.assert_allclose(eyes, [[1, 2, 3], [1, 2, 3]])


def test_unsorted_keys_and_opposite_forwards() -> None:
    keys = [
        {"t": 1.0, "eye": [1, 0, 0], "forward": [-1, 0, 0], "up": [0, 1, 0]},
        {"t": 0.0, "eye": [0, 0, 0], "forward": [1, 0, 0], "up": [0, 1, 0]},
    ]
    tour = Tour(keys)
    eye, f, u = tour.pose_at(0.5)  # the nlerp of opposite directions is zero: hold the earlier one
    np.testing.assert_allclose(eye, [0.5, 0, 0])
    np.testing.assert_allclose(f, [1, 0, 0])
    assert np.all(np.isfinite(u)) and abs(np.dot(f, u)) < 1e-12


def test_empty_tour_refused() -> None:
    with pytest.raises(ValueError):
        Tour([])
