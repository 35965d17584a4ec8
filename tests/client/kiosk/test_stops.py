"""Stops → keys: every leg within its speed and turn, dwells where they belong, the loop closes on itself."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from client.kiosk.stops import Playlist, Stop, plan_leg
from proto.tour import Tour
from proto.walkable import WalkableGrid

coord = st.floats(-50, 50, allow_nan=False)
direction = st.tuples(st.floats(-1, 1), st.floats(-1, 1), st.floats(-0.9, 0.9)).filter(
    lambda v: np.hypot(v[0], v[1]) > 0.2)


@st.composite
def stops(draw, n=st.integers(1, 5)):
    out = []
    for i in range(draw(n)):
        f = np.asarray(draw(direction))
        out.append(Stop("t", i, np.array([draw(coord), draw(coord), draw(st.floats(0, 20))]), f / np.linalg.norm(f),
                        np.array([0.0, 0.0, 1.0]), draw(st.floats(0, 5)), {"en": f"stop {i}"},
                        speed=draw(st.floats(0.5, 10)), turn=draw(st.floats(10, 180))))
    return out


def _rates(tour: Tour, t0: float, t1: float, n: int = 4000):
    """Eye speed and view turn rate (deg/s) sampled densely over [t0, t1]."""
    t = np.linspace(t0, t1, n, endpoint=False)  # a Tour wraps round at its very end
    eye, f, _ = tour.pose_at(t)
    dt = np.diff(t)
    speed = np.linalg.norm(np.diff(eye, axis=0), axis=1) / dt
    angle = np.degrees(np.arctan2(np.linalg.norm(np.cross(f[:-1], f[1:]), axis=1), np.sum(f[:-1] * f[1:], axis=1)))
    return speed, angle / dt


@settings(max_examples=60, deadline=None)
@given(stops(), st.floats(0, 100), st.integers(0, 4))
def test_no_leg_is_faster_than_its_speed_or_turn(playlist_stops, t0, first):
    pl = Playlist(playlist_stops)
    first %= len(pl)
    seg = pl.segment(pl.pose(first + 1), t0, first)
    assert seg.start == pytest.approx(t0) and np.all(np.diff(seg.t) >= 0)
    speed_cap = max(s.speed for s in playlist_stops)
    turn_cap = max(s.turn for s in playlist_stops)
    # Key to key, the eye is never faster than the slowest... of the destination's tour speeds:
    dt = np.diff(seg.t)
    moving = dt > 1e-9
    step = np.linalg.norm(np.diff(seg.eye, axis=0), axis=1)
    assert np.all(step[~moving] < 1e-9)  # no jump in zero time
    assert np.all(step[moving] / dt[moving] <= speed_cap * (1 + 1e-9))
    # and between keys too, as the client interpolates them (nlerp): speed and turn rate within the caps.
    if seg.end - seg.start > 1e-6:  # sampled rates of a loop shorter than that are rounding, not motion
        speed, turn = _rates(seg._tour, seg.start, seg.end)
        assert speed.max() <= speed_cap * (1 + 1e-6)
        assert turn.max() <= turn_cap * (1 + 1e-3)
    # A loop visits every stop in order from ``first``, dwells its dwell there, and ends back at ``first``.
    assert seg.stops.tolist() == [(first + k) % len(pl) for k in range(len(pl))]
    np.testing.assert_allclose(seg.leave - seg.arrive, [playlist_stops[i].dwell for i in seg.stops], atol=1e-9)
    for i, a, b in zip(seg.stops, seg.arrive, seg.leave):
        np.testing.assert_allclose(seg.pose_at((a + b) / 2)[0], playlist_stops[i].eye, atol=1e-9)
        if b > a:
            assert seg.stop_at((a + b) / 2) == (i, True)
    np.testing.assert_allclose(seg.pose_at(seg.end)[0], playlist_stops[first].eye, atol=1e-9)


def test_a_leg_takes_the_longer_of_distance_over_speed_and_angle_over_turn():
    a = (np.zeros(3), np.array([1.0, 0.0, 0.0]), np.array([0.0, 0.0, 1.0]))
    far = (np.array([30.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0]), np.array([0.0, 0.0, 1.0]))
    near = (np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0]), np.array([0.0, 0.0, 1.0]))
    assert plan_leg(a, far, speed=3.0, turn=45.0).t[-1] == pytest.approx(10.0)  # 30 m at 3 m/s; 90° in 2 s
    assert plan_leg(a, near, speed=3.0, turn=45.0).t[-1] == pytest.approx(2.0, rel=2e-3)  # 90° at 45°/s
    back = (np.zeros(3), np.array([-1.0, 0.0, 0.0]), np.array([0.0, 0.0, 1.0]))
    leg = plan_leg(a, back, speed=3.0, turn=90.0)  # a half turn, level about the stop's up
    assert leg.t[-1] == pytest.approx(2.0, rel=2e-3) and np.allclose(leg.forward[:, 2], 0.0)


def test_a_visitors_next_is_one_leg_and_one_dwell():
    s = [Stop("t", i, np.array([10.0 * i, 0, 1.7]), np.array([0.0, 1, 0]), np.array([0.0, 0, 1]), 4.0,
              {"en": f"s{i}"}) for i in range(3)]
    seg = Playlist(s).segment(s[0] and (np.array([0.0, 0, 1.7]), np.array([0.0, 1, 0]), np.array([0.0, 0, 1])), 5.0, 2,
                              loop=False)
    assert seg.stops.tolist() == [2] and seg.arrive[0] == pytest.approx(5.0 + 20.0 / 3.0)
    assert seg.end == pytest.approx(seg.arrive[0] + 4.0)
    assert seg.stop_at(6.0) == (2, False) and seg.stop_at(seg.end) == (2, True)


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**31 - 1))
def test_a_walk_tour_keeps_the_eye_height_above_the_ground(seed):
    rng = np.random.default_rng(seed)
    ground = rng.uniform(0, 2, (20, 20)).astype(np.float32)
    grid = WalkableGrid((0.0, 0.0), 0.5, ground)
    pts = rng.uniform(0.5, 9.5, (3, 2))
    s = [Stop("w", i, np.r_[p, 0.0], np.array([1.0, 0, 0]), np.array([0.0, 0, 1]), 1.0, mode="walk", speed=1.5)
         for i, p in enumerate(pts)]
    seg = Playlist(s, ground=grid, eye_height=1.6).segment((np.r_[pts[0], 0.0], s[0].forward, s[0].up), 0.0, 0)
    moving = np.ones(len(seg.t), bool)
    for a, b in zip(seg.arrive, seg.leave):  # the stops' own poses are as authored
        moving &= ~((seg.t >= a - 1e-12) & (seg.t <= b + 1e-12))
    np.testing.assert_allclose(seg.eye[moving, 2], grid.height(seg.eye[moving, :2]) + 1.6, atol=1e-6)


@settings(max_examples=30, deadline=None)
@given(stops(), st.floats(0, 100), st.sampled_from([0.25, 0.5]))
def test_the_slow_attract_loop_visits_the_same_poses_slower(playlist_stops, t0, rate):
    pl = Playlist(playlist_stops)
    start = pl.pose(0)
    fast, slow = pl.segment(start, t0, 0), pl.segment(start, t0, 0, rate=rate)
    assert np.allclose(slow.t - t0, (fast.t - t0) / rate) and np.allclose(slow.eye, fast.eye)
    assert np.allclose(slow.arrive - t0, (fast.arrive - t0) / rate)
    with pytest.raises(ValueError, match="rate"):
        pl.segment(start, t0, 0, rate=0.0)


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**31 - 1))
def test_a_walk_leg_goes_round_a_wall_between_two_stops_and_never_through_it(seed):
    rng = np.random.default_rng(seed)
    ground = np.zeros((40, 40), np.float32)  # 20 × 20 m at 0.5 m
    gap = int(rng.integers(2, 36))
    ground[2:38, 19:21] = np.nan  # a wall across the middle, open only at the top and bottom rows
    ground[gap:gap + 2, 19:21] = 0.0  # ... and at a door somewhere along it
    grid = WalkableGrid((0.0, 0.0), 0.5, ground)
    a = np.array([rng.uniform(1, 8), rng.uniform(1, 19), 1.6])
    b = np.array([rng.uniform(12, 19), rng.uniform(1, 19), 1.6])
    s = [Stop("w", i, p, np.array([1.0, 0, 0]), np.array([0.0, 0, 1]), 1.0, mode="walk", speed=1.5)
         for i, p in enumerate((a, b))]
    seg = Playlist(s, ground=grid, eye_height=1.6).segment((a, s[0].forward, s[0].up), 0.0, 0)
    tour = Tour([{"t": float(t), "eye": e, "forward": f, "up": u} for t, e, f, u in zip(seg.t, seg.eye, seg.forward, seg.up)])
    t = np.linspace(seg.start, seg.end, 8000, endpoint=False)  # a Tour wraps round at its very end
    eye = tour.pose_at(t)[0]
    assert grid.walkable(eye[:, :2]).all(), "the walk crossed the wall"
    crossed = np.flatnonzero(np.diff(np.sign(eye[:, 0] - 10.0)) != 0)
    assert crossed.size, "the loop never went from one stop to the other"
    speed = np.linalg.norm(np.diff(eye, axis=0), axis=1) / np.diff(t)
    assert speed.max() <= 1.5 * 1.01


def test_a_walk_leg_without_a_walk_between_its_stops_is_the_straight_line():
    ground = np.zeros((20, 20), np.float32)
    ground[:, 9:11] = np.nan  # a wall with no door: two regions
    grid = WalkableGrid((0.0, 0.0), 0.5, ground)
    a, b = np.array([1.0, 5.0, 1.6]), np.array([9.0, 5.0, 1.6])
    leg = Playlist([Stop("w", 0, a, np.array([1.0, 0, 0]), np.array([0.0, 0, 1]), 1.0, mode="walk"),
                    Stop("w", 1, b, np.array([1.0, 0, 0]), np.array([0.0, 0, 1]), 1.0, mode="walk")],
                   ground=grid, eye_height=1.6).leg((a, np.array([1.0, 0, 0]), np.array([0.0, 0, 1])), 1)
    np.testing.assert_allclose(leg.eye[:, 1], 5.0)
    assert leg.eye[0, 0] == pytest.approx(1.0) and leg.eye[-1, 0] == pytest.approx(9.0)
