"""The prediction that knows the navigation: tour plans and walking on the walkable grid."""

from __future__ import annotations

import math

import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp
from scipy import ndimage

from proto.errors import ProtocolError
from proto.messages import MAX_PLAN_KEYS, Navigation, TourKey, TourPlan
from proto.tour import Tour
from proto.walkable import WalkableGrid
from server.select.navigation import Navigable, Plan
from server.select.predict import Predictor

BOUNDS = np.array([[-50.0, -50.0, -5.0], [50.0, 50.0, 20.0]])
UP = [0.0, 0.0, 1.0]


def _key(t, eye, forward=(1.0, 0.0, 0.0)) -> TourKey:
    return TourKey(t=t, eye=list(map(float, eye)), forward=list(map(float, forward)), up=UP)


#: An L-shaped walk at 1 m/s: along +x for 5 s, a turn to +y within half a second, then along +y.
_L = [_key(0.0, (0, 0, 1.7)), _key(5.0, (5, 0, 1.7)), _key(5.5, (5, 0.5, 1.7), (0, 1, 0)),
      _key(10.0, (5, 5, 1.7), (0, 1, 0))]


def _corner(t: float) -> tuple[np.ndarray, np.ndarray]:
    """The L walk's eye and forward at time t (0 ≤ t < 10)."""
    eye, forward, _ = Tour(_L).pose_at(t)
    return eye, forward


def _plan_keys(t0=0.0, t1=10.0) -> list[TourKey]:
    keys = [k for k in _L if t0 <= k.t <= t1]
    head = [_key(t0, *_corner(t0))] if keys[0].t > t0 else []
    tail = [_key(t1, *_corner(t1))] if keys[-1].t < t1 else []
    return head + keys + tail


def _fed(predictor: Predictor, until: float, rate: float = 20.0) -> Predictor:
    for t in np.arange(0.0, until + 1e-9, 1.0 / rate):
        eye, fwd = _corner(float(t))
        predictor.add(float(t), eye, fwd, UP)
    return predictor


def _err(pose, t) -> tuple[float, float]:
    eye, fwd = _corner(t)
    return float(np.linalg.norm(pose.eye - eye)), math.degrees(math.acos(min(1.0, float(pose.forward @ fwd))))


def test_a_plan_is_followed_exactly_where_linear_prediction_misses_the_turn():
    linear = _fed(Predictor(), 4.5)
    planned = _fed(Predictor(), 4.5)
    planned.set_plan(TourPlan(t=4.5, keys=_plan_keys()), BOUNDS)
    for t in (5.5, 6.0, 6.5):
        e_lin, a_lin = _err(linear.pose(t), t)
        e_plan, a_plan = _err(planned.pose(t), t)
        assert e_plan < 1e-9 and a_plan < 1e-6
        assert e_lin > 0.5 * (t - 5.0) and a_lin > 0  # straight on past the corner, still looking along x
    # Between keys the plan interpolates as proto.tour.Tour does (the pose at the corner's key is exact).
    assert np.allclose(planned.pose(5.0).eye, [5.0, 0.0, 1.7])


def test_outside_the_plan_and_after_an_empty_plan_the_prediction_is_linear_again():
    linear = _fed(Predictor(), 3.0)
    planned = _fed(Predictor(), 3.0)
    planned.set_plan(TourPlan(t=3.0, keys=_plan_keys(0.0, 4.0)), BOUNDS)
    assert planned.plan.covers(np.array([3.9, 4.0, 4.1])).tolist() == [True, True, False]
    for t in (4.2, 5.0, 6.0):  # past its last key: linear from the samples
        assert np.allclose(planned.pose(t).eye, linear.pose(t).eye)
    planned.set_plan(TourPlan(t=3.0, keys=[]), BOUNDS)  # the visitor drives from t = 3
    assert planned.plan is not None and not planned.plan.covers(np.array([3.2, 3.9])).any()
    assert np.allclose(planned.pose(3.5).eye, linear.pose(3.5).eye)


def test_a_new_plan_replaces_the_held_one_from_its_first_key_and_leaves_the_gap_uncovered():
    p = _fed(Predictor(), 1.0)
    p.set_plan(TourPlan(t=1.0, keys=[_key(0.0, (0, 0, 1.7)), _key(4.0, (4, 0, 1.7))]), BOUNDS)
    p.set_plan(TourPlan(t=1.5, keys=[_key(6.0, (0, 9, 1.7)), _key(8.0, (0, 11, 1.7))]), BOUNDS)
    assert p.plan.covers(np.array([2.0, 3.9, 4.0, 5.0, 6.0, 7.0, 8.5])).tolist() == [
        True, True, True, False, True, True, False]
    assert np.allclose(p.pose(7.0).eye, [0, 10, 1.7]) and np.allclose(p.pose(2.0).eye, [2, 0, 1.7])
    p.set_plan(TourPlan(t=1.6, keys=[_key(3.0, (0, 0, 1.7)), _key(5.0, (0, 0, 1.7))]), BOUNDS)
    assert np.allclose(p.pose(4.5).eye, [0, 0, 1.7]) and not p.plan.covers(np.array([7.0])).any()


def test_bad_plans_are_refused_and_leave_the_plan_held():
    p = _fed(Predictor(), 2.0)
    p.set_plan(TourPlan(t=2.0, keys=_plan_keys()), BOUNDS)
    held = p.plan
    far = TourPlan(t=2.0, keys=[_key(3.0, (0, 0, 1.7)), _key(4.0, (1e5, 0, 1.7))])
    with pytest.raises(ProtocolError, match=r"keys\[1\]\.eye .* outside the scene's bounds") as e:
        p.set_plan(far, BOUNDS)
    assert e.value.code == "invalid"
    with pytest.raises(ProtocolError, match="in the past"):
        p.set_plan(TourPlan(t=2.0, keys=[_key(0.5, (0, 0, 1.7)), _key(1.0, (1, 0, 1.7))]), BOUNDS)
    with pytest.raises(ProtocolError, match="in the past"):  # judged against the newest sample, too
        p.set_plan(TourPlan(t=0.0, keys=[_key(0.5, (0, 0, 1.7)), _key(1.5, (1, 0, 1.7))]), BOUNDS)
    many = [_key(3.0 + i * 1e-3, (0, 0, 1.7)) for i in range(MAX_PLAN_KEYS)]
    p.set_plan(TourPlan(t=2.0, keys=many[: MAX_PLAN_KEYS // 2]), BOUNDS)
    held = p.plan
    with pytest.raises(ProtocolError, match="at most"):  # the held keys and the new ones together
        p.set_plan(TourPlan(t=2.0, keys=[_key(20.0 + i * 1e-3, (0, 0, 1.7)) for i in range(MAX_PLAN_KEYS // 2 + 10)]),
                   BOUNDS)
    assert p.plan is held


def test_a_snapshot_carries_the_plan():
    p = _fed(Predictor(), 4.5)
    p.set_plan(TourPlan(t=4.5, keys=_plan_keys()), BOUNDS)
    state = msgpack.unpackb(msgpack.packb(p.to_state(), use_bin_type=True), raw=False)
    q = Predictor()
    q.from_state(state)
    for t in (5.5, 7.0, 12.0):
        assert np.allclose(q.pose(t).eye, p.pose(t).eye) and np.allclose(q.pose(t).forward, p.pose(t).forward)
    assert q.plan.issued == 4.5
    old = {k: v for k, v in state.items() if k != "plan"}  # a snapshot from before plans were
    r = Predictor()
    r.from_state(old)
    assert r.plan is None
    with pytest.raises(ValueError, match="plan"):
        Predictor().from_state({**state, "plan": {**state["plan"], "joined": state["plan"]["t"]}})


def _room() -> WalkableGrid:
    """A 20 × 20 m floor at z = 0 in 0.25 m cells with a wall along x = 10 m from y = 0 to 20."""
    ground = np.zeros((80, 80), np.float32)
    ground[:, 40] = np.nan
    return WalkableGrid(origin=(0.0, 0.0), cell=0.25, ground=ground)


def test_walking_into_a_wall_stops_at_it_and_an_angled_walk_slides_along_it():
    nav = Navigable(_room(), eye_height=1.7)
    start = np.array([8.0, 5.0, 1.7])
    straight, angled = nav.confine(start, np.array([[14.0, 5.0, 1.7], [14.0, 9.0, 1.7]]))
    assert 9.5 <= straight[0] < 10.0 and straight[1] == pytest.approx(5.0) and straight[2] == pytest.approx(1.7)
    assert 9.5 <= angled[0] < 10.0 and angled[1] == pytest.approx(9.0)  # slid along the wall to its y
    free = nav.confine(start, np.array([[4.0, 2.0, 5.0]]))[0]
    assert np.allclose(free, [4.0, 2.0, 1.7])  # on the floor at eye height, whatever the line's z


def test_a_driving_visitor_is_predicted_along_the_floor_and_never_through_the_wall():
    p = Predictor(teleport_speed=50.0)
    p.navigable = Navigable.of(Navigation(mode="walk", eye_height=1.6), _room())
    for t in np.arange(0.0, 1.0, 0.05):  # walking at 2 m/s towards the wall
        p.add(float(t), [6.0 + 2.0 * t, 5.0, 1.6], [1.0, 0.0, 0.0], UP)
    far = p.pose(4.0).eye
    assert far[0] < 10.0 and far[2] == pytest.approx(1.6)
    fly = Predictor(teleport_speed=50.0)
    for t in np.arange(0.0, 1.0, 0.05):
        fly.add(float(t), [6.0 + 2.0 * t, 5.0, 1.6], [1.0, 0.0, 0.0], UP)
    assert fly.pose(4.0).eye[0] > 12.0  # unconstrained, the line runs on through the wall


def test_bounds_hold_the_prediction_in_any_mode():
    nav = Navigable.of(Navigation(mode="fly", bounds=[[-1.0, -1.0, 0.0], [1.0, 1.0, 3.0]]), None)
    out = nav.confine(np.zeros(3), np.array([[5.0, -5.0, 9.0]]))[0]
    assert out.tolist() == [1.0, -1.0, 3.0]
    assert Navigable.of(Navigation(mode="fly"), _room()) is None  # flying knows no ground


@settings(max_examples=60, deadline=None)
@given(hnp.arrays(np.bool_, (24, 24)), st.integers(0, 575), st.floats(-12.0, 12.0), st.floats(-12.0, 12.0))
def test_walking_never_predicts_an_eye_over_a_blocked_cell(blocked, start_cell, dx, dy):
    ground = np.where(blocked, np.nan, (np.arange(24)[None, :] * 0.01).repeat(24, 0)).astype(np.float32)
    grid = WalkableGrid(origin=(-3.0, -3.0), cell=0.5, ground=ground)
    j, i = divmod(start_cell, 24)
    if blocked[j, i]:
        return
    start = np.array([-3.0 + (i + 0.5) * 0.5, -3.0 + (j + 0.5) * 0.5, 5.0])
    nav = Navigable(grid, eye_height=1.7)
    ends = start + np.array([[dx, dy, 0.0], [0.5 * dx, 0.5 * dy, 1.0], [dx, 0.0, 0.0], [0.0, dy, 0.0]])
    out = nav.confine(start, ends)
    assert grid.walkable(out[:, :2]).all()
    np.testing.assert_allclose(out[:, 2], grid.height(out[:, :2]) + 1.7)
    # No step of the way crosses a blocked wall: every end lies in the start's walkable region.
    labels, _ = ndimage.label(~blocked, structure=np.ones((3, 3)))
    rows, cols, _ = grid.cells(out[:, :2])
    assert (labels[rows, cols] == labels[j, i]).all()


def test_a_plan_restored_into_a_plan_object_round_trips():
    plan = Plan.of(_plan_keys(), 1.0)
    back = Plan.from_state(msgpack.unpackb(msgpack.packb(plan.to_state(), use_bin_type=True), raw=False))
    assert np.array_equal(back.t, plan.t) and np.array_equal(back.x, plan.x) and back.issued == 1.0
