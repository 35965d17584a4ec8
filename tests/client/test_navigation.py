"""Tour: piecewise-linear eye, nlerp'd orthonormal directions, looping, fixed one-key tours."""

from __future__ import annotations

import numpy as np
import pytest

from proto.tour import Tour
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


# --------------------------------------------------------------------------- interactive controllers

from hypothesis import given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

from client.navigation import KEYS, FlyController, Navigator, WalkController  # noqa: E402
from proto.messages import Pose  # noqa: E402

START = Pose(eye=[0.0, 0.0, 1.7], forward=[0.0, 1.0, 0.0], up=[0.0, 0.0, 1.0])


def _held(c, names: str, t0: float, t1: float):
    """Hold the keys over [t0, t1] (one call per key name, space-separated) and return the pose at t1."""
    c.pose_at(t0)
    for name in names.split():
        c.key(name, True)
    pose = c.pose_at(t1)
    for name in names.split():
        c.key(name, False)
    return pose


def test_fly_moves_along_the_view_and_the_camera_up() -> None:
    c = FlyController(START, speed=3.0, fast=4.0)
    eye, f, u = c.pose_at(0.0)  # the first call only sets the clock
    np.testing.assert_allclose(eye, [0, 0, 1.7])
    eye, _, _ = _held(c, "w", 0.0, 2.0)
    np.testing.assert_allclose(eye, [0, 6, 1.7], atol=1e-12)
    eye, _, _ = _held(c, "e", 2.0, 3.0)
    np.testing.assert_allclose(eye, [0, 6, 4.7], atol=1e-12)
    eye, _, _ = _held(c, "d shift", 3.0, 3.5)  # right of +y looking along it is +x; Shift ×4
    np.testing.assert_allclose(eye, [6, 6, 4.7], atol=1e-12)
    eye, _, _ = _held(c, "w d", 3.5, 4.5)  # diagonal: no faster than straight
    np.testing.assert_allclose(np.linalg.norm(eye - [6, 6, 4.7]), 3.0, atol=1e-12)
    assert c.max_speed == 12.0


def test_fly_looks_with_the_mouse_at_a_capped_turn_rate() -> None:
    c = FlyController(START, max_turn=90.0, sensitivity=0.1)
    c.pose_at(0.0)
    c.look(900, 0)  # 90° to the right, but at most 90°/s
    _, f, u = c.pose_at(0.5)
    np.testing.assert_allclose(f, [np.sin(np.pi / 4), np.cos(np.pi / 4), 0], atol=1e-12)
    _, f, u = c.pose_at(2.0)  # the rest of the drag, then nothing more
    np.testing.assert_allclose(f, [1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(u, [0, 0, 1], atol=1e-12)
    c.look(0, -300)  # drag up: look up 30°, about the camera's right
    _, f, u = c.pose_at(3.0)
    np.testing.assert_allclose(f, [np.cos(np.pi / 6), 0, np.sin(np.pi / 6)], atol=1e-12)
    np.testing.assert_allclose(u, [-np.sin(np.pi / 6), 0, np.cos(np.pi / 6)], atol=1e-12)
    eye0 = c.eye.copy()
    eye, _, _ = _held(c, "w", 3.0, 4.0)  # flying climbs along the view
    np.testing.assert_allclose(eye - eye0, 8.0 * f, atol=1e-12)


def test_walk_keeps_its_eye_height_and_clamps_pitch() -> None:
    c = WalkController(START, speed=1.5, max_pitch=60.0, sensitivity=1.0)
    c.pose_at(0.0)
    c.look(0, 200)  # look down far past the clamp
    _, f, u = c.pose_at(10.0)
    np.testing.assert_allclose(np.degrees(np.arcsin(f[2])), -60.0, atol=1e-9)
    assert u[2] > 0 and abs(np.dot(f, u)) < 1e-12
    eye, _, _ = _held(c, "w q e", 10.0, 12.0)  # looking down, W still walks level; Q/E do nothing
    np.testing.assert_allclose(eye, [0, 3.0, 1.7], atol=1e-12)
    c.look(-90, 0)  # turn left 90°: heading −x
    eye, f, _ = _held(c, "w", 12.0, 14.0)
    np.testing.assert_allclose(f[:2] / np.linalg.norm(f[:2]), [-1, 0], atol=1e-12)
    np.testing.assert_allclose(eye, [-3.0, 3.0, 1.7], atol=1e-12)  # one step: turn, then move the way it faces


def test_walk_levels_a_tilted_start() -> None:
    tilted = Pose(eye=[5.0, 5.0, 30.0], forward=[0.0, 0.0, -1.0], up=[1.0, 0.0, 0.0])  # looking straight down
    c = WalkController(tilted)
    eye, f, u = c.pose_at(0.0)
    np.testing.assert_allclose(eye, [5, 5, 30])
    assert f[0] > 0 and abs(f[1]) < 1e-12  # heading taken from the up vector
    np.testing.assert_allclose(np.degrees(np.arcsin(f[2])), -80.0, atol=1e-9)
    assert u[2] > 0


def test_time_never_runs_back_and_keys_are_named() -> None:
    c = FlyController(START)
    assert not c.key("x", True) and c.key("W", True)
    c.pose_at(1.0)
    eye1, _, _ = c.pose_at(2.0)
    eye2, _, _ = c.pose_at(1.5)
    np.testing.assert_allclose(eye1, eye2)
    c.clear_input()
    np.testing.assert_allclose(c.pose_at(5.0)[0], eye1)


def test_navigator_toggles_where_the_camera_is() -> None:
    nav = Navigator(mode="fly", fly_speed=10.0, walk_speed=2.0, fast=3.0, max_turn=45.0)
    assert (nav.max_speed, nav.max_turn) == (30.0, 45.0)  # both modes' limits, announced once in the Hello
    nav.place(START)
    nav.pose_at(0.0)
    nav.key("e", True)
    eye, f, _ = nav.pose_at(1.0)
    np.testing.assert_allclose(eye, [0, 0, 11.7])
    nav.key("e", False)
    nav.key("w", True)
    assert nav.toggle() == "walk"
    eye2, f2, _ = nav.pose_at(1.0)
    np.testing.assert_allclose(eye2, eye)
    np.testing.assert_allclose(f2, f, atol=1e-12)
    eye3, _, _ = nav.pose_at(2.0)  # W held through the switch: walks at walking speed, at the new height
    np.testing.assert_allclose(eye3, [0, 2.0, 11.7], atol=1e-12)
    assert nav.toggle() == "fly" and nav.mode == "fly"
    with pytest.raises(ValueError):
        Navigator(mode="swim")


_step = st.tuples(st.sampled_from(KEYS), st.booleans(), st.floats(-400, 400), st.floats(-400, 400),
                  st.floats(0.0, 0.5))


@settings(max_examples=60, deadline=None)
@given(st.sampled_from(["fly", "walk"]), st.lists(_step, min_size=1, max_size=40))
def test_never_faster_than_announced(mode, steps) -> None:
    nav = Navigator(START, mode=mode)
    t = 0.0
    eye, f, u = nav.pose_at(t)
    for name, pressed, dx, dy, dt in steps:
        nav.key(name, pressed)
        nav.look(dx, dy)
        t += dt
        eye1, f1, u1 = nav.pose_at(t)
        assert np.linalg.norm(eye1 - eye) <= nav.max_speed * dt + 1e-9
        angle = np.degrees(np.arctan2(np.linalg.norm(np.cross(f, f1)), np.dot(f, f1)))
        assert angle <= nav.max_turn * dt + 1e-6
        np.testing.assert_allclose([np.linalg.norm(f1), np.linalg.norm(u1), np.dot(f1, u1)], [1, 1, 0], atol=1e-9)
        if mode == "walk":
            assert eye1[2] == 1.7 and u1[2] > 0
        eye, f = eye1, f1
