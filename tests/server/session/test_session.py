"""The sans-I/O session driven with raw frames, asserting the frames it answers with."""

from __future__ import annotations

from time import perf_counter

import msgpack
import numpy as np
import pytest
from pydantic import ValidationError

from proto import PROTOCOL_VERSION
from proto.codec import decode_server, encode
from proto.messages import Camera, Delta, Error, FrameReport, Hello, Ping, Pong, Welcome
from server.scene.store import SceneStore
from server.session import Session, SessionConfig, SessionState


@pytest.fixture()
def scenes(demo_store):
    store = SceneStore.open(demo_store)
    yield {store.index.name: store}
    store.close()


def _hello(scenes, **kw) -> bytes:
    fields = dict(protocol=PROTOCOL_VERSION, scene=next(iter(scenes)), viewport=[640, 360], target_frame_time=0.05)
    return encode(Hello(**{**fields, **kw}))


def _camera(scenes, t=0.0) -> bytes:
    start = next(iter(scenes.values())).index.start
    return encode(Camera(t=t, **start))


def _wire(out):
    """Everything a session emits must survive the wire."""
    return [decode_server(encode(m)) for m in out]


def _open(scenes, config=None, **hello) -> Session:
    s = Session(scenes, "s1", config, stopwatch=perf_counter)
    welcome, ping = _wire(s.receive(_hello(scenes, **hello), now=0.0))
    assert isinstance(welcome, Welcome) and welcome.session == "s1" and len(welcome.tour) >= 2
    assert isinstance(ping, Ping) and ping.sent == 0.0
    assert s.receive(encode(Pong(id=ping.id, sent=ping.sent, t=0.0)), now=0.0) == []  # same clock, no delay
    assert s.clock.known and s.clock.rtt == 0.0
    return s


def _deltas(out) -> list[Delta]:
    return [m for m in _wire(out) if isinstance(m, Delta)]


def _next_delta(s: Session) -> Delta:
    for _ in range(100):  # pings may fall due first
        found = _deltas(s.poll(s.next_deadline()))
        if found:
            (delta,) = found
            return delta
    raise AssertionError("no delta came due")


def test_first_camera_is_answered_at_once_then_on_the_pipeline(scenes):
    s = _open(scenes)
    assert s.poll(0.0) == []  # no pose yet
    assert s.receive(_camera(scenes), now=1.0) == []
    assert s.next_deadline() == 1.0
    (delta,) = _deltas(s.poll(1.0))
    assert isinstance(delta, Delta) and delta.seq == 1 and delta.reset
    assert delta.selection and {a.rep for a in delta.add} == set(delta.selection)
    # Before it has seen a frame the cost model budgets for its tail (the cap, 1.5): the first selection of a
    # heavy scene is otherwise its worst frames; the fixed overhead is not known yet either.
    assert delta.predicted_cost <= delta.budget == pytest.approx(0.05 / 1.5)
    due = s.next_deadline()
    assert due > 1.0 + 0.5 * s.config.tau  # the next selection waits for its slot ...
    assert _deltas(s.poll(due - 0.01)) == []
    second = _next_delta(s)  # ... and then targets the interval after the next
    assert second.seq == 2 and not second.reset and second.add == []  # same pose: nothing new to send
    assert second.t0 - delta.t0 == pytest.approx(2 * s.config.tau)
    assert second.start == pytest.approx(second.t0 - s.config.tau)


def test_frame_reports_drive_the_cost_model(scenes):
    s = _open(scenes)
    s.receive(_camera(scenes), now=0.0)
    (first,) = _deltas(s.poll(0.0))
    for i in range(30):  # the client says: 1e-6 s per vertex
        s.receive(encode(FrameReport(frame=i, t=0.1 * i, time=0.1, triangles=200_000, vertices=100_000, draws=5)), 0.1)
    second = _next_delta(s)
    assert second.cost_coeff == pytest.approx(1e-6, rel=0.01) and first.cost_coeff < 5e-7
    index = scenes[s.scene_name].index
    assert index.rep_vertices[second.selection].sum() * 1e-6 <= 0.05 * (1 + 1e-9)
    assert s.stats["frames"] == 30
    assert s.cost.tail_min_time == pytest.approx(0.25 * 0.05)  # the budget's tail: frames of its size
    # GET /sessions says which model prices the selection, why, and its coefficients.
    stats = s.stats
    assert stats["cost_why"].startswith(stats["cost_model"]) and stats["cost_coefficients"]
    assert all(v >= 0 for c in stats["cost_coefficients"].values() for v in np.atleast_1d(c))


def test_a_governed_session_asks_more_of_a_richer_cost_model(scenes):
    """With the governor on, the cost model goes past its simplest rung only when that rung's held-out error is
    over (1 + ``governed_within``) × the best's; without it, (1 + 0.30) ×. /sessions says which limit holds."""
    plain, governed = _open(scenes), _open(scenes, governor=True)
    wide = _open(scenes, config=SessionConfig(governed_within=2.5), governor=True)
    assert plain.cost.within == pytest.approx(0.30)
    assert governed.cost.within == pytest.approx(SessionConfig().governed_within) == pytest.approx(1.0)
    assert wide.cost.within == pytest.approx(2.5)
    for s in (plain, governed, wide):
        s.receive(_camera(scenes), now=0.0)
        _deltas(s.poll(0.0))
        for i in range(30):
            s.receive(encode(FrameReport(frame=i, t=0.1 * i, time=0.02 + 1e-3 * (i % 3), triangles=200_000,
                                         vertices=100_000, draws=5)), 0.1)
    assert "(1 + 0.3)" in plain.stats["cost_why"] and "(1 + 1)" in governed.stats["cost_why"]
    with pytest.raises(ValueError, match="governed_within"):
        SessionConfig(governed_within=float("nan"))


def test_a_report_riding_with_a_pose_counts_as_if_it_came_alone(scenes):
    """One message a frame (``Camera.report``) drives the session exactly as the two messages did."""
    start = next(iter(scenes.values())).index.start
    apart, together = _open(scenes), _open(scenes)
    for s in (apart, together):
        s.receive(_camera(scenes), now=0.0)
        _deltas(s.poll(0.0))
    for i in range(30):
        report = FrameReport(frame=i, t=0.1 * i, time=0.1, triangles=200_000, vertices=100_000, draws=5)
        pose = dict(start, eye=[start["eye"][0] + 0.01 * i, *start["eye"][1:]])
        assert apart.receive(encode(report), 0.1 * i) == []
        assert apart.receive(encode(Camera(t=0.1 * i + 0.05, **pose)), 0.1 * i) == []
        assert together.receive(encode(Camera(t=0.1 * i + 0.05, report=report, **pose)), 0.1 * i) == []
    assert together.stats["frames"] == apart.stats["frames"] == 30
    assert together.camera == apart.camera and together.camera.report is None  # the pose is kept, not the frame
    one, two = _next_delta(apart), _next_delta(together)
    assert two.cost_coeff == one.cost_coeff == pytest.approx(1e-6, rel=0.01)
    assert two.selection == one.selection
    # A report that does not validate refuses the whole message, naming the field, and changes nothing.
    before = dict(together.stats)
    bad = msgpack.packb({"type": "camera", "t": 5.0, **start,
                         "report": {"type": "frame_report", "frame": 1, "t": 5.0, "time": -1.0, "triangles": 1,
                                    "vertices": 3, "draws": 1}})
    (err,) = _wire(together.receive(bad, 5.0))
    assert isinstance(err, Error) and err.code == "invalid" and "report.time" in err.message
    assert together.stats["frames"] == before["frames"] and together.camera.t < 5.0


def test_a_60_hz_client_is_folded_into_the_cost_model_at_observe_hz(scenes):
    s = _open(scenes, config=SessionConfig(observe_hz=20.0))
    s.receive(_camera(scenes), now=0.0)
    for i in range(120):  # two seconds at 60 Hz, the last ten frames far slower: the sample must still see them
        slow = i >= 110
        s.receive(encode(FrameReport(frame=i, t=i / 60, time=0.5 if slow else 0.1, triangles=200_000,
                                     vertices=100_000, draws=5)), i / 60)
    assert s.stats["frames"] == 120  # every report is counted ...
    assert 38 <= s.cost.updates <= 42  # ... about 20 a second are fitted, evenly in time
    assert max(s.cost._ratios) > 3  # the late slow frames were among them (measured ≈ 5 × predicted)


def test_malformed_frames_get_error_frames_and_change_nothing(scenes):
    s = _open(scenes)
    s.receive(_camera(scenes), now=0.0)
    before = dict(s.stats)
    bad = [
        (b"\xc1", "bad_msgpack"),
        (msgpack.packb({"type": "camera", "t": 1.0, "eye": [0, 0, float("nan")], "forward": [1, 0, 0], "up": [0, 0, 1]}), "invalid"),
        (msgpack.packb({"type": "warp"}), "unknown_type"),
        (b"\x00" * 70_000, "too_large"),
        ("text", "not_binary"),
        (_hello(scenes), "bad_state"),
    ]
    for data, code in bad:
        (err,) = _wire(s.receive(data, now=0.1))
        assert isinstance(err, Error) and err.code == code
    assert s.state is SessionState.ACTIVE and s.camera is not None
    assert s.stats["errors"] == before["errors"] + len(bad) and s.stats["frames"] == before["frames"]
    (delta,) = _deltas(s.poll(0.2))
    assert isinstance(delta, Delta)


@pytest.mark.parametrize(
    "fields, code",
    [({"scene": "nowhere"}, "unknown_scene"), ({"protocol": 99}, "version"), ({"solver": "magic"}, "unknown_solver")],
)
def test_bad_hello_is_refused_and_may_be_retried(scenes, fields, code):
    s = Session(scenes, "s2", stopwatch=perf_counter)
    (err,) = s.receive(_hello(scenes, **fields), 0.0)
    assert isinstance(err, Error) and err.code == code and s.state is SessionState.AWAIT_HELLO
    (err,) = s.receive(_camera(scenes), 0.0)
    assert err.code == "bad_state"
    welcome, _ = s.receive(_hello(scenes), 0.0)
    assert isinstance(welcome, Welcome)


def test_cache_mirror_evicts_under_pressure_and_keeps_to_the_budget(scenes):
    index = next(iter(scenes.values())).index
    small = int(np.sort(index.rep_bytes)[::-1][:8].sum())  # room for about 8 representations
    s = _open(scenes, SessionConfig(cache_bytes=small), predict=False)
    held: set[int] = set()
    tour = index.tour
    dropped = unsent = 0
    for i, key in enumerate(tour * 2):
        pose = {k: key[k] for k in ("eye", "forward", "up")}
        s.receive(encode(Camera(t=float(i), **pose)), now=float(i))
        (delta,) = _deltas(s.poll(max(float(i), s.next_deadline())))
        added = {a.rep for a in delta.add}
        assert not added & held  # nothing the client holds is sent again
        held |= added
        held -= set(delta.drop)
        dropped += len(delta.drop)
        assert int(index.rep_bytes[sorted(held)].sum()) <= small  # the client never gets more than its budget
        unsent += len(set(delta.selection) - held)
        assert held == set(np.nonzero(s.mirror.resident)[0].tolist())  # the mirror agrees with the client
    assert dropped > 0
    # A working set larger than the budget is cut, and the cut is counted, not hidden.
    assert s.stats["over_budget"] >= unsent > 0


# ----------------------------------------------------------------------------- hostile input, property-tested

from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

_finite = st.floats(-1e4, 1e4, allow_nan=False)
_any_float = st.one_of(_finite, st.just(float("nan")), st.just(float("inf")), st.just(1e30))
_vec = st.lists(_any_float, min_size=2, max_size=4)
_frames = st.one_of(
    st.binary(max_size=64),
    st.builds(lambda t, e, f, u: msgpack.packb({"type": "camera", "t": t, "eye": e, "forward": f, "up": u}),
              _any_float, _vec, _vec, _vec),
    st.builds(lambda fr, t, tm, v: msgpack.packb({"type": "frame_report", "frame": fr, "t": t, "time": tm,
                                                 "triangles": v, "vertices": v, "draws": 1}),
              st.integers(-5, 10**10), _any_float, _any_float, st.integers(-5, 10**7)),
    st.builds(lambda d: msgpack.packb(d), st.dictionaries(st.sampled_from(["type", "t", "scene", "x"]),
                                                          st.one_of(st.integers(-(2**63), 2**64 - 1), st.text(max_size=8), st.none()))),
)


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.lists(_frames, max_size=25), st.lists(st.floats(0, 0.01), min_size=25, max_size=25))
def test_any_sequence_of_frames_keeps_the_session_sound(scenes, frames, gaps):
    s = _open(scenes)
    s.receive(_camera(scenes), now=0.0)
    now = 0.0
    for data, gap in zip(frames, gaps):
        now += gap * 100
        out = s.receive(data, now) + s.poll(now)
        for m in _wire(out):  # every answer is a valid frame
            if isinstance(m, Delta):
                assert set(m.selection) <= set(np.nonzero(s.mirror.resident)[0].tolist())
                assert m.predicted_cost <= m.budget * (1 + 1e-9)
    assert s.state is SessionState.ACTIVE
    assert np.isfinite(s.cost.c_vertex) and s.cost.c_vertex > 0


def test_bad_pongs_and_acks_get_error_frames_and_harm_nothing(scenes):
    s = _open(scenes)
    s.receive(_camera(scenes), now=0.0)
    (first,) = _deltas(s.poll(0.0))
    resident = s.mirror.resident.copy()
    offset, rtt = s.clock.offset, s.clock.rtt
    bad = [
        msgpack.packb({"type": "pong", "id": 1, "sent": float("nan"), "t": 0.0}),
        msgpack.packb({"type": "pong", "id": -1, "sent": 0.0, "t": 0.0}),
        msgpack.packb({"type": "ack", "seq": 1, "t": float("inf")}),
        msgpack.packb({"type": "ack", "seq": 1, "t": 0.0, "rejected": [-3]}),
        msgpack.packb({"type": "ack", "seq": "one", "t": 0.0}),
    ]
    for data in bad:
        (err,) = _wire(s.receive(data, now=0.1))
        assert err.code == "invalid"
    # Well-formed but meaningless: a pong for a ping never sent, an ack naming reps beyond the scene.
    assert s.receive(encode(Pong(id=99, sent=-50.0, t=5.0)), now=0.1) == []
    from proto.messages import Ack

    assert s.receive(encode(Ack(seq=77, t=0.2, rejected=[10**9])), now=0.2) == []
    assert (s.mirror.resident == resident).all() and s.clock.offset == offset and s.clock.rtt == rtt
    # A real refusal unmarks the rep in the mirror, so it is sent again when next needed.
    refused = first.add[0].rep
    s.receive(encode(Ack(seq=first.seq, t=0.1, rejected=[refused])), now=0.1)
    assert not s.mirror.resident[refused] and s.stats["errors"] == len(bad) and s.state is SessionState.ACTIVE


# ----------------------------------------------------------------------------- protocol 3's new fields

def _raw_hello(scenes, **kw) -> bytes:
    fields = dict(type="hello", protocol=PROTOCOL_VERSION, scene=next(iter(scenes)), viewport=[640, 360])
    return msgpack.packb({**fields, **kw})


@pytest.mark.parametrize("bad, field", [
    ({"algorithms": ["flat", "phong"]}, "algorithms"),
    ({"algorithms": ["lit", "lit"]}, "repeat"),
    ({"algorithms": []}, "algorithms"),
    ({"cache_bytes": 10}, "cache_bytes"),
    ({"cache_bytes": "lots"}, "cache_bytes"),
])
def test_a_bad_hello_of_protocol_3_is_refused_by_name(scenes, bad, field):
    s = Session(scenes, "s1", stopwatch=perf_counter)
    (err,) = _wire(s.receive(_raw_hello(scenes, **bad), now=0.0))
    assert isinstance(err, Error) and err.code == "invalid" and field in err.message
    assert s.state is SessionState.AWAIT_HELLO  # nothing opened; a good hello still works
    assert isinstance(_wire(s.receive(_hello(scenes, algorithms=["flat", "textured"]), now=0.0))[0], Welcome)


@pytest.mark.parametrize("terms, gpu", [
    ({"triangles": [1, 2], "vertices": [1], "pixels": [0, 0], "draws": [1, 1]}, None),  # ragged columns
    ({"triangles": [1, 2, 3, 4], "vertices": [1] * 4, "pixels": [0] * 4, "draws": [1] * 4}, None),  # 4 algorithms
    ({"triangles": [-1], "vertices": [1], "pixels": [0], "draws": [1]}, None),  # negative count
    (None, -0.5),  # negative GPU time
    (None, float("nan")),
])
def test_malformed_frame_report_terms_harm_nothing(scenes, terms, gpu):
    s = _open(scenes, algorithms=["flat", "lit", "textured"])
    frame = {"type": "frame_report", "frame": 1, "t": 0.1, "time": 0.02, "triangles": 10, "vertices": 10,
             "draws": 1, "terms": terms, "gpu_time": gpu}
    (err,) = _wire(s.receive(msgpack.packb({k: v for k, v in frame.items() if v is not None}), now=0.1))
    assert isinstance(err, Error) and err.code == "invalid"
    assert s.cost.updates == 0 and s.frames == 0  # the model learnt nothing from it
    good = FrameReport(frame=2, t=0.2, time=0.02, triangles=10_000, vertices=6_000, draws=10, pixels=5_000,
                       terms={"triangles": [10_000, 0, 0], "vertices": [6_000, 0, 0], "pixels": [5_000, 0, 0],
                              "draws": [10, 0, 0]})
    assert s.receive(encode(good), now=0.2) == [] and s.cost.updates == 1 and s.frames == 1


def test_the_clients_own_measure_of_a_vertex_is_the_cost_models_first_guess(scenes):
    """A hello's ``c_vertex`` (the client's calibration) replaces the server's guess for the first selection:
    a client that says its vertices cost 5 × the default gets a first delta of about a fifth of the vertices."""
    guessed = _open(scenes)
    measured = _open(scenes, c_vertex=5 * SessionConfig().c_vertex)
    assert measured.cost.c_vertex == pytest.approx(5 * SessionConfig().c_vertex)
    assert guessed.cost.c_vertex == pytest.approx(SessionConfig().c_vertex)
    index = next(iter(scenes.values())).index
    drawn = []
    for s in (guessed, measured):
        s.receive(_camera(scenes), now=0.0)
        delta = _next_delta(s)
        drawn.append(int(index.rep_vertices[np.asarray(delta.selection, np.int64)].sum()))
    assert drawn[1] < 0.4 * drawn[0], drawn
    with pytest.raises(ValidationError, match="c_vertex"):
        Hello(protocol=PROTOCOL_VERSION, scene="demo", viewport=[64, 64], c_vertex=1.0)  # a second a vertex


def test_a_heartbeat_is_kept_after_hello_and_one_session_reports_one_kiosk(scenes):
    from proto.messages import Heartbeat

    early = Session(scenes, "s0")
    (refused,) = _wire(early.receive(encode(Heartbeat(kiosk="hall-1", t=0.0, frames=0)), now=0.0))
    assert isinstance(refused, Error) and refused.code == "bad_state" and early.heartbeat is None
    s = _open(scenes)
    progress = s._progress()
    assert s.receive(encode(Heartbeat(kiosk="hall-1", t=1.0, frames=60, tour="harbour", stop=2)), now=1.0) == []
    assert s.heartbeat.frames == 60 and s.heartbeat.tour == "harbour" and s.stats["kiosk"] == "hall-1"
    assert s._progress() == progress  # a heartbeat is no state a resume needs
    (other,) = _wire(s.receive(encode(Heartbeat(kiosk="hall-2", t=2.0, frames=120)), now=2.0))
    assert isinstance(other, Error) and other.code == "bad_state" and "hall-2" in other.message
    assert s.heartbeat.kiosk == "hall-1" and s.heartbeat.frames == 60
    bad = msgpack.packb({"type": "heartbeat", "kiosk": "no spaces", "t": 3.0, "frames": 1})
    (invalid,) = _wire(s.receive(bad, now=3.0))
    assert invalid.code == "invalid" and "kiosk" in invalid.message and s.heartbeat.frames == 60


def test_a_denormal_turn_limit_is_the_least_turn_not_a_failure(scenes):
    s = Session(scenes, "s2")
    welcome, _ = _wire(s.receive(_hello(scenes, max_turn=5e-324), now=0.0))
    assert isinstance(welcome, Welcome) and s.predictor.limits.turn > 0.0
