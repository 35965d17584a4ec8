"""A session told its navigation: the walkable grid in the welcome, tour plans, and resuming along a plan."""

from __future__ import annotations

import msgpack
import numpy as np
import pytest

from proto import PROTOCOL_VERSION
from proto.codec import decode_server, encode
from proto.messages import Camera, Delta, Error, Hello, Navigation, Pong, Resume, TourKey, TourPlan, Welcome
from proto.tour import Tour
from proto.walkable import decode
from server.scene.store import SceneStore
from server.session import Session, SessionState


@pytest.fixture(scope="module")
def scenes(demo_store):
    store = SceneStore.open(demo_store)
    yield {store.index.name: store}
    store.close()


def _poses(scenes):
    """Two poses a quarter of the scene's tour apart, the second looking back: they see different things."""
    index = next(iter(scenes.values())).index
    tour = Tour(index.tour)
    out = []
    for t, turn in ((tour.t[0], 1.0), (tour.t[0] + tour.duration / 4, -1.0)):
        eye, fwd, up = tour.pose_at(t)
        fwd = fwd * [turn, turn, 1.0]
        out.append({"eye": eye.tolist(), "forward": fwd.tolist(), "up": up.tolist()})
    return out


def _hello(scenes, **kw) -> Hello:
    fields = dict(protocol=PROTOCOL_VERSION, scene=next(iter(scenes)), viewport=[320, 180], target_frame_time=0.05)
    return Hello(**{**fields, **kw})


def _open(scenes, sid="s", **hello) -> tuple[Session, Welcome]:
    s = Session(scenes, sid, stopwatch=None)
    welcome, ping = [decode_server(encode(m)) for m in s.receive(encode(_hello(scenes, **hello)), now=0.0)]
    assert isinstance(welcome, Welcome)
    s.receive(encode(Pong(id=ping.id, sent=ping.sent, t=0.0)), now=0.0)
    return s, welcome


def _first_delta(s: Session, pose: dict) -> Delta:
    t = max(0.1, s.predictor.latest or 0.0)
    s.receive(encode(Camera(t=t, **pose)), now=t)
    for _ in range(20):
        found = [m for m in s.poll(s.next_deadline()) if isinstance(m, Delta)]
        if found:
            return found[0]
    raise AssertionError("no delta")


def _still_plan(pose: dict, t0=0.0, t1=60.0) -> TourPlan:
    return TourPlan(t=0.0, keys=[TourKey(t=t0, **pose), TourKey(t=t1, **pose)], tour="still")


def test_a_hello_asking_for_the_walkable_grid_gets_it_in_the_welcome(scenes):
    store = next(iter(scenes.values()))
    _, welcome = _open(scenes, walkable=True)
    grid = decode(welcome.walkable)
    assert grid.shape == store.walkable().shape and grid.cell == store.walkable().cell
    np.testing.assert_array_equal(np.isfinite(grid.ground), np.isfinite(store.walkable().ground))
    _, plain = _open(scenes)
    assert plain.walkable is None


def test_a_plan_makes_the_session_select_for_the_plans_poses(scenes):
    here, there = _poses(scenes)
    slow = dict(c_vertex=2e-5)  # a renderer this slow cannot draw the garden in full: the view decides
    planned, _ = _open(scenes, "a", plan=_still_plan(there), **slow)
    moved, _ = _open(scenes, "b", **slow)
    stayed, _ = _open(scenes, "c", **slow)
    a, b, c = _first_delta(planned, here), _first_delta(moved, there), _first_delta(stayed, here)
    assert a.selection == b.selection  # the camera is still here, but the plan says it will be there
    assert a.selection != c.selection  # (and what is seen from here differs)


def test_a_tour_plan_message_takes_effect_and_an_empty_one_ends_it(scenes):
    here, there = _poses(scenes)
    s, _ = _open(scenes)
    s.receive(encode(Camera(t=0.1, **here)), now=0.1)
    assert s.receive(encode(_still_plan(there)), now=0.1) == []
    assert np.allclose(s.predictor.pose(1.0).eye, there["eye"])
    assert s.receive(encode(TourPlan(t=0.2, keys=[])), now=0.2) == []
    assert np.allclose(s.predictor.pose(1.0).eye, here["eye"])


def test_bad_plans_get_clear_errors_and_the_session_goes_on(scenes):
    here, there = _poses(scenes)
    s, _ = _open(scenes)
    s.receive(encode(Camera(t=5.0, **here)), now=5.0)
    far = {**there, "eye": [9e6, 0.0, 0.0]}
    past = TourPlan(t=5.0, keys=[TourKey(t=1.0, **there), TourKey(t=2.0, **there)])
    for plan, words in ((TourPlan(t=5.0, keys=[TourKey(t=6.0, **far)]), "keys[0].eye"), (past, "in the past")):
        (err,) = s.receive(encode(plan), now=5.0)
        assert isinstance(err, Error) and err.code == "invalid" and words in err.message
    raw = msgpack.packb({"type": "tour_plan", "t": 5.0, "keys": [{"t": 6.0 + i, **there} for i in range(10_001)]})
    (err,) = s.receive(raw, now=5.0)
    assert err.code in ("invalid", "too_large") and s.state is SessionState.ACTIVE
    assert s.predictor.plan is None and s.errors == 3
    assert s.receive(encode(_still_plan(there, 0.0, 60.0)), now=5.0) == []  # and a good one still works
    assert _first_delta(s, here).seq == 1
    fresh = Session(scenes, "bad", stopwatch=None)  # a hello with a bad plan is refused, and opens nothing
    (err,) = fresh.receive(encode(_hello(scenes, plan=TourPlan(t=0.0, keys=[TourKey(t=1.0, **far)]))), now=0.0)
    assert err.code == "invalid" and "keys[0].eye" in err.message
    assert fresh.state is SessionState.AWAIT_HELLO and fresh.hello is None


def test_a_walking_hello_confines_the_prediction_to_the_grid(scenes):
    store = next(iter(scenes.values()))
    s, _ = _open(scenes, navigation=Navigation(mode="walk", eye_height=1.7))
    assert s.predictor.navigable is not None and s.predictor.navigable.grid is store.walkable()
    grid = store.walkable()
    here = np.array([grid.origin[0] + 10.0, grid.origin[1] + 10.0])
    z = float(grid.height(here)[0])
    for i in range(10):
        s.receive(encode(Camera(t=0.05 * i, eye=[here[0] + 0.1 * i, here[1], z + 1.7], forward=[1.0, 0.0, 0.0],
                                up=[0.0, 0.0, 1.0])), now=0.05 * i)
    eye = s.predictor.pose(2.0).eye
    assert grid.walkable(eye[:2])[0] and eye[2] == pytest.approx(float(grid.height(eye[:2])[0]) + 1.7, abs=1e-5)


def test_a_resumed_session_keeps_predicting_along_its_plan(scenes):
    here, there = _poses(scenes)
    s, welcome = _open(scenes, "r")
    s.receive(encode(Camera(t=0.5, **here)), now=0.5)
    s.receive(encode(TourPlan(t=0.6, keys=[TourKey(t=0.5, **here), TourKey(t=10.0, **there)])), now=0.6)
    expected = s.predictor.pose(5.0)
    blob = s.snapshot()
    r = Session(scenes, "r", token=welcome.token, stopwatch=None)
    r.restore(blob)
    stale = TourPlan(t=0.0, keys=[TourKey(t=0.0, **here), TourKey(t=20.0, **here)])  # the first hello's plan
    out = r.receive(encode(_hello(scenes, plan=stale, resume=Resume(session="r", token=welcome.token))), now=1.0)
    assert isinstance(out[0], Welcome) and out[0].resumed
    got = r.predictor.pose(5.0)
    assert np.allclose(got.eye, expected.eye) and np.allclose(got.forward, expected.forward)
