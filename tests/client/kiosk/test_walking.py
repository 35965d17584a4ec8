"""Constrained navigation: no input sequence leaves the bounds, enters a blocked cell or beats the caps."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from client.kiosk.walking import MAX_STEP, BoundedFly, ConstrainedWalk, KioskNavigator
from proto.walkable import WalkableGrid

MOVES = ("w", "a", "s", "d", "left", "right", "up", "down", "q", "e")
steps = st.lists(st.tuples(st.sampled_from(MOVES + ("none",)), st.booleans(), st.floats(-300, 300),
                           st.floats(-300, 300), st.floats(0.001, 0.5)), min_size=1, max_size=80)


def _grid(seed: int) -> WalkableGrid:
    """A 24 × 24 grid of 0.5 m cells: walls (NaN), ledges of up to 1 m, gentle slopes."""
    rng = np.random.default_rng(seed)
    ground = np.round(rng.uniform(0, 1.0, (24, 24)) * rng.integers(0, 2, (24, 24)), 1).astype(np.float32)
    ground[rng.uniform(size=(24, 24)) < 0.3] = np.nan
    ground[12, 12] = 0.0
    return WalkableGrid((-6.0, -6.0), 0.5, ground)


def _drive(ctrl, script):
    t, poses = 0.0, [ctrl.pose_at(0.0)]
    for key, press, dx, dy, dt in script:
        if key != "none":
            ctrl.key(key, press)
        ctrl.look(dx, dy)
        t += dt
        poses.append(ctrl.pose_at(t))
    return poses


@settings(max_examples=120, deadline=None)
@given(st.integers(0, 2**31 - 1), steps, st.floats(0.5, 4.0), st.floats(20, 120))
def test_a_walker_never_leaves_the_bounds_or_walks_into_a_wall(seed, script, speed, turn):
    grid = _grid(seed)
    bounds = np.array([[-4.0, -5.0, -1.0], [4.5, 5.0, 3.0]])
    start = ((0.25, 0.25, 1.7), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))  # on cell (12, 12), walkable
    walker = ConstrainedWalk(start, bounds=bounds, grid=grid, eye_height=1.6, speed=speed, max_turn=turn)
    held: set[str] = set()
    t, prev = 0.0, walker.pose_at(0.0)
    for key, press, dx, dy, dt in script:
        if key != "none":
            walker.key(key, press)
            held = held | {key} if press else held - {key}
        walker.look(dx, dy)
        t += dt
        eye, forward, up = walker.pose_at(t)
        assert np.all(eye >= bounds[0] - 1e-9) and np.all(eye <= bounds[1] + 1e-9)
        assert np.isfinite(grid.height(eye[None])[0]), f"walked from {prev[0]} into a blocked cell at {eye}"
        step = np.linalg.norm(eye - prev[0])
        assert step <= speed * dt * (1 + 1e-9) + 1e-12  # along and up together within the cap
        turned = np.degrees(np.arccos(np.clip(np.dot(forward, prev[1]), -1, 1)))
        assert turned <= turn * dt * (1 + 1e-6) + 1e-6
        assert abs(up[2]) > 0 and forward[2] ** 2 < 1  # the horizon stays level: up in the vertical plane
        prev = (eye, forward, up)


def test_the_eye_follows_the_ground_and_a_wall_is_slid_along():
    ground = np.zeros((10, 10), np.float32)
    ground[:, 6:] = 0.3  # a step up at x = 3
    ground[8, :] = np.nan  # a wall along y ∈ [4, 4.5)
    grid = WalkableGrid((0.0, 0.0), 0.5, ground)
    walker = ConstrainedWalk(((1.0, 1.0, 1.7), (1.0, 1.0, 0.0), (0.0, 0.0, 1.0)),
                             bounds=[[0, 0, 0], [5, 5, 5]], grid=grid, eye_height=1.7, speed=2.0)
    walker.pose_at(0.0)
    walker.key("w", True)  # north-east, at 45°: into the wall, then along it eastwards
    eye = walker.pose_at(5.0)[0]
    assert eye[1] < 4.0 and eye[0] > 3.0  # stopped at the wall, slid along it, over the step
    for t in np.arange(5.0, 10.0, 0.1):
        eye = walker.pose_at(t)[0]
    assert abs(eye[2] - (np.float32(0.3) + 1.7)) < 1e-6  # the eye rose with the ground


def test_a_ledge_higher_than_a_step_is_a_wall():
    ground = np.zeros((4, 10), np.float32)
    ground[:, 5:] = MAX_STEP + 0.1  # a stage's edge at x = 2.5
    walker = ConstrainedWalk(((1.0, 1.0, 1.7), (1.0, 0.0, 0.0), (0.0, 0.0, 1.0)), bounds=[[0, 0, 0], [5, 2, 5]],
                             grid=WalkableGrid((0.0, 0.0), 0.5, ground), speed=2.0)
    walker.pose_at(0.0)
    walker.key("w", True)
    eye = walker.pose_at(3.0)[0]
    assert 2.0 < eye[0] < 2.5 and eye[1] == 1.0


@settings(max_examples=60, deadline=None)
@given(steps)
def test_a_flyer_never_leaves_the_bounds(script):
    bounds = np.array([[-2.0, -2.0, 0.5], [2.0, 3.0, 4.0]])
    fly = BoundedFly(((0.0, 0.0, 1.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)), bounds=bounds, speed=3.0, max_turn=90.0)
    for eye, _, _ in _drive(fly, script):
        assert np.all(eye >= bounds[0] - 1e-9) and np.all(eye <= bounds[1] + 1e-9)


def test_the_kiosk_navigator_takes_over_where_it_is_put_within_bounds():
    nav = KioskNavigator("walk", bounds=[[0, 0, 0], [10, 10, 10]], max_speed=2.0, max_turn=60.0)
    nav.place(((20.0, 5.0, 1.7), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)), t=3.0)
    assert nav.pose[0].tolist() == [10.0, 5.0, 1.7]  # a pose outside is brought inside
    nav.key("w", True)
    assert nav.pose_at(4.0)[0][1] == 7.0  # 2 m/s from t = 3, no Shift boost
    assert nav.max_speed == 2.0 and nav.controller.max_speed == 2.0
