"""Camera: hierarchical culling, screen position, centre offset and apparent speed of boxes."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from server.select.camera import (
    View,
    centre_offset,
    cull_boxes,
    cull_hierarchy,
    frustum_planes,
    screen_centre,
    screen_speed,
)

BOUNDS = np.array([[-100.0, -100.0, -10.0], [100.0, 100.0, 10.0]])


def _view(forward=(0, 1, 0), fov=90.0, w=400, h=400):
    # At the origin, z up; by default looking along +y.
    return View.of_pose([0, 0, 0], forward, [0, 0, 1], fov, (w, h), BOUNDS)


def _yawed(theta):
    return _view(forward=(np.sin(theta), np.cos(theta), 0.0))


# ----------------------------------------------------------------------------- hierarchy


def test_a_child_of_a_culled_parent_is_culled_even_when_its_own_box_is_in_view():
    planes = frustum_planes(_view().matrix())
    # 0: root in view; 1: child of 0 behind the eye; 2: child of 1 in view; 3: child of 0 in view.
    lo = np.array([[-1, 5, -1], [-1, -20, -1], [-1, 8, -1], [-1, 9, -1]], float)
    hi = lo + 1.0
    parent = np.array([-1, 0, 1, 0])
    assert cull_boxes(lo, hi, planes).tolist() == [True, False, True, True]
    assert cull_hierarchy(parent, lo, hi, planes).tolist() == [True, False, False, True]


def _brute(parent, own):
    def vis(i):
        return bool(own[i]) and (parent[i] < 0 or vis(parent[i]))

    return np.array([vis(i) for i in range(parent.size)], bool)


@st.composite
def _trees(draw):
    n = draw(st.integers(1, 60))
    parent = np.array([draw(st.integers(-1, i - 1)) for i in range(n)], np.int64)
    centres = np.array(draw(st.lists(st.tuples(*[st.floats(-30, 30)] * 3), min_size=n, max_size=n)), float)
    half = np.array(draw(st.lists(st.floats(0.01, 5), min_size=n, max_size=n)), float)[:, None]
    return parent, centres - half, centres + half


@settings(max_examples=60, deadline=None)
@given(_trees(), st.floats(0, 2 * np.pi))
def test_cull_hierarchy_equals_the_recursive_definition(tree, yaw):
    parent, lo, hi = tree
    planes = frustum_planes(_yawed(yaw).matrix())
    got = cull_hierarchy(parent, lo, hi, planes)
    assert got.tolist() == _brute(parent, cull_boxes(lo, hi, planes)).tolist()


def test_cull_hierarchy_on_a_deep_chain():
    n = 40  # a chain deeper than any real hierarchy; the last box alone is out of view
    parent = np.arange(n) - 1
    lo = np.tile([-1.0, 5.0, -1.0], (n, 1))
    hi = lo + 1.0
    lo[0], hi[0] = [-1.0, -20.0, -1.0], [0.0, -19.0, 0.0]
    planes = frustum_planes(_view().matrix())
    assert not cull_hierarchy(parent, lo, hi, planes).any()
    lo[0], hi[0] = lo[1], hi[1]
    assert cull_hierarchy(parent, lo, hi, planes).all()


# ----------------------------------------------------------------------------- screen position


def test_screen_centre_and_offset_on_hand_worked_boxes():
    view = _view()  # fov 90°, 400 × 400: NDC x = X / Y ahead
    lo = np.array([[-1, 9, -1], [4, 9, -1], [-1, -11, -1], [9, 9, 9]], float)
    hi = lo + 2.0
    px = screen_centre(lo, hi, view.matrix(), 400, 400)
    off = centre_offset(lo, hi, view.matrix(), 400, 400)
    # Box 0 is dead ahead; box 1's centre (5, 10, 0) is at NDC x = 0.5 → pixel 300.
    np.testing.assert_allclose(px[0], [200, 200], atol=1e-9)
    np.testing.assert_allclose(px[1], [300, 200], atol=1e-9)
    assert off[0] == 0.0 and abs(off[1] - 100 / np.hypot(200, 200)) < 1e-12
    # Box 2 is straight behind: as far off-centre as anything (a corner).
    assert off[2] == 1.0
    # Box 3 is in front but off to the upper right beyond the screen: clamped to the corner.
    np.testing.assert_allclose(px[3], [400, 400])
    assert ((px >= 0) & (px <= 400)).all()


@settings(max_examples=40, deadline=None)
@given(st.lists(st.tuples(*[st.floats(-50, 50)] * 3), min_size=1, max_size=30), st.floats(0, 2 * np.pi))
def test_centre_offset_lies_in_unit_interval(centres, yaw):
    c = np.array(centres, float)
    off = centre_offset(c - 0.5, c + 0.5, _yawed(yaw).matrix(), 640, 360)
    assert off.shape == (len(centres),) and ((off >= 0) & (off <= 1)).all()


# ----------------------------------------------------------------------------- apparent speed


def test_screen_speed_is_zero_for_identical_views():
    c = np.random.default_rng(0).uniform(-30, 30, (50, 3))
    m = _view().matrix()
    assert (screen_speed(c - 1, c + 1, m, m, 0.1, 400, 400) == 0).all()


def test_screen_speed_when_the_camera_turns_matches_the_projection():
    # Turning by θ moves a point dead ahead to NDC x = −tan θ (fov 90°): 200·tan θ pixels.
    lo, hi = np.array([[-1.0, 9.0, -1.0]]), np.array([[1.0, 11.0, 1.0]])
    theta = np.radians(5.0)
    speed = screen_speed(lo, hi, _yawed(theta).matrix(), _view().matrix(), 0.5, 400, 400)
    assert abs(speed[0] - 200 * np.tan(theta) / 0.5) < 1e-6


@settings(max_examples=40, deadline=None)
@given(st.floats(0.01, 0.3), st.floats(0, 2 * np.pi))
def test_screen_speed_is_positive_for_objects_in_view_when_the_camera_turns(turn, yaw):
    rng = np.random.default_rng(1)
    c = rng.uniform(-30, 30, (40, 3))
    before, now = _yawed(yaw), _yawed(yaw + turn)
    in_view = cull_boxes(c - 0.1, c + 0.1, frustum_planes(before.matrix()))
    speed = screen_speed(c - 0.1, c + 0.1, now.matrix(), before.matrix(), 0.1, 400, 400)
    assert (speed >= 0).all() and (speed[in_view] > 0).all()
