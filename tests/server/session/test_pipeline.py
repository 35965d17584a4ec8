"""The session's three-stage pipeline end to end without sockets: a simulated client on a simulated link.

The client's clock runs ``OFFSET`` ahead of the server's; every message takes
``ONE_WAY`` seconds each way. The client follows the scene's tour, answers
pings, acks deltas on arrival and feeds every delta's schedule to the real
executor (``client.schedule``), so the issue's invariants are checked on the
schedules a real selection produces: only resident representations drawn,
levels continuous, and the predicted cost of what is drawn — a morph costs its
finer level — within the budget at every instant.
"""

from __future__ import annotations

import heapq
from time import perf_counter

import numpy as np
import pytest

from proto.tour import Tour
from client.schedule import Schedule
from proto import PROTOCOL_VERSION
from proto.codec import decode_client, decode_server, encode
from proto.messages import Ack, Camera, Delta, Hello, Ping, Pong, Welcome
from server.scene.store import SceneStore
from server.session import Session, SessionConfig

OFFSET = 100.0
FPS = 20.0


@pytest.fixture(scope="module")
def scenes(demo_store):
    store = SceneStore.open(demo_store)
    yield {store.index.name: store}
    store.close()


class Link:
    """A session and a simulated client joined by a link with a fixed one-way delay."""

    def __init__(self, scenes, *, one_way=0.02, config=None, predict=True, morph=True, poses=None, budget=0.05,
                 governor=False, report=None):
        self.session = Session(scenes, "sim", config or SessionConfig(), stopwatch=perf_counter)
        self.index = next(iter(scenes.values())).index
        self.one_way = one_way
        self.events: list = []  # (arrival server time, order, "server" | "client", bytes)
        self.order = 0
        self.now = 0.0
        self.deltas: list[tuple[float, Delta]] = []  # (client arrival time, delta)
        self.schedule = Schedule()
        self.resident: set[int] = set()
        self.resident_log: list[tuple[float, frozenset]] = []
        self.poses = poses or Tour(self.index.tour).pose_at
        self.report = report  # (frame, client time, the delta drawn) → the FrameReport sent with the pose, or None
        self.frame = 0
        hello = Hello(protocol=PROTOCOL_VERSION, scene=self.index.name, viewport=[640, 360],
                      target_frame_time=budget, predict=predict, morph=morph, governor=governor)
        self._to_client(self.session.receive(encode(hello), 0.0))

    def _to_client(self, messages):
        for m in messages:
            self.order += 1
            heapq.heappush(self.events, (self.now + self.one_way, self.order, "client", encode(m)))

    def _to_server(self, message):
        self.order += 1
        heapq.heappush(self.events, (self.now + self.one_way, self.order, "server", encode(message)))

    def client_time(self, t=None):
        return (self.now if t is None else t) + OFFSET

    def run(self, until: float, on_frame=None):
        """Advance to server time ``until``: frames every 1/FPS, polls at the session's deadlines."""
        next_frame = self.now
        while self.now < until:
            candidates = [next_frame, until]
            if self.events:
                candidates.append(self.events[0][0])
            deadline = self.session.next_deadline()
            if deadline is not None:
                candidates.append(max(deadline, self.now))
            self.now = min(candidates)
            if self.events and self.events[0][0] <= self.now:
                _, _, side, data = heapq.heappop(self.events)
                if side == "server":
                    self._to_client(self.session.receive(data, self.now))
                else:
                    self._client_receives(decode_server(data))
                continue
            if deadline is not None and deadline <= self.now:
                self._to_client(self.session.poll(self.now))
                continue
            if self.now >= next_frame:
                t = self.client_time()
                eye, forward, up = self.poses(t - OFFSET)
                drawn = self.deltas[-1][1].seq if self.deltas else -1
                report = None if self.report is None else self.report(self.frame, t, drawn)
                self.frame += 1
                self._to_server(Camera(t=t, eye=list(map(float, eye)), forward=list(map(float, forward)),
                                       up=list(map(float, up)), report=report))
                if on_frame is not None:
                    on_frame(t, self.schedule.at(t))
                next_frame += 1.0 / FPS

    def _client_receives(self, m):
        t = self.client_time()
        if isinstance(m, Ping):
            self._to_server(Pong(id=m.id, sent=m.sent, t=t))
        elif isinstance(m, Delta):
            self.deltas.append((t, m))
            self.resident |= {a.rep for a in m.add}
            self.resident -= set(m.drop)
            self.resident_log.append((t, frozenset(self.resident)))
            level = self.index.rep_level[np.asarray(m.selection, np.int64)].astype(np.float64)
            key = np.asarray(m.selection, np.int64) - level.astype(np.int64)
            to = np.asarray(m.morphs.level_to)
            self.schedule.apply(m.start, m.t0, key, level,
                                (np.asarray(m.morphs.rep) - to.astype(np.int64), np.asarray(m.morphs.level_from),
                                 to, np.asarray(m.morphs.t0), np.asarray(m.morphs.t1)),
                                reset=m.reset, now=t)
            self._to_server(Ack(seq=m.seq, t=t))
        else:
            assert isinstance(m, Welcome), m


def test_schedules_arrive_before_they_start_and_hold_every_invariant(scenes):
    link = Link(scenes, one_way=0.03, budget=0.0015)  # a budget that binds, so levels trade off as the view turns
    index = link.index
    frames = []
    link.run(12.0, on_frame=lambda t, d: frames.append((t, d)))
    s = link.session
    assert s.clock.known and s.clock.offset == pytest.approx(OFFSET, abs=1e-6)
    assert s.clock.rtt == pytest.approx(0.06, abs=1e-6)
    deltas = link.deltas
    assert len(deltas) >= 15 and deltas[0][1].reset and not any(d.reset for _, d in deltas[1:])
    for arrived, d in deltas[1:]:
        assert arrived <= d.start  # every schedule is there before its window opens
        assert d.t0 - d.start == pytest.approx(s.config.tau)
    assert s.late == 0 and link.schedule.late == 0
    ups = sum(len([1 for a, b in zip(d.morphs.level_from, d.morphs.level_to) if b > a]) for _, d in deltas)
    downs = sum(len([1 for a, b in zip(d.morphs.level_from, d.morphs.level_to) if b < a]) for _, d in deltas)
    assert ups > 0 and downs > 0  # the tour makes objects grow and shrink on screen
    coeff = {d.seq: d.cost_coeff for _, d in deltas}
    assert len(set(coeff.values())) == 1  # no frame reports here: one cost model throughout
    c = next(iter(coeff.values()))
    budget = deltas[0][1].budget
    prev = {}
    for (t, d), (t_prev, _) in zip(frames[1:], frames[:-1]):
        held = [r for a, r in link.resident_log if a <= t]
        if not held:
            continue
        here = held[-1]
        drawn = d.rep.tolist()
        assert set(drawn) <= here  # only resident representations are drawn ...
        morphing = d.rep[d.weight < 1]
        assert set((morphing - 1).tolist()) <= here  # ... and the levels they morph from
        assert c * index.rep_vertices[d.rep].sum() <= budget * (1 + 1e-9)  # a morph costs its finer level
        for k, lv in zip(d.key.tolist(), d.level.tolist()):
            if k in prev:  # continuous: at most a chain of levels per τ
                assert abs(lv - prev[k]) <= (index.rep_count.max() - 1) / s.config.tau * (t - t_prev) + 1e-9
        prev = dict(zip(d.key.tolist(), d.level.tolist()))


def test_a_slow_link_pushes_the_target_interval_later(scenes):
    link = Link(scenes, one_way=0.4)  # a 0.8 s round trip: more than τ
    link.run(10.0)
    s = link.session
    assert s.clock.rtt == pytest.approx(0.8, abs=1e-6)
    assert s.lead() > 0.4
    late = [(a, d) for a, d in link.deltas[1:] if a > d.start]
    assert late == [] and s.late == 0
    # Selected that much earlier: the start of each window is at least the lead after the selection.
    assert all(d.start - (a - 0.4) >= 0.4 for a, d in link.deltas[1:])


def test_a_teleport_resets_prediction_and_pipeline(scenes):
    index = next(iter(scenes.values())).index
    tour = Tour(index.tour)
    far = np.asarray(index.bounds, np.float64)[1] + 500.0

    def poses(t):
        eye, forward, up = tour.pose_at(t)
        return (far + eye * 0.01 if t >= 5.0 else eye), forward, up  # a jump of hundreds of metres at t = 5 s

    link = Link(scenes, poses=poses)
    link.run(8.0)
    s = link.session
    assert s.teleports == 1 and s.predictor.resets >= 1
    resets = [(a, d) for a, d in link.deltas if d.reset]
    assert len(resets) == 2
    arrived, d = resets[1]
    assert arrived - OFFSET >= 5.0 and arrived - OFFSET < 5.0 + 0.2  # answered at once, not at the next slot
    assert len(d.morphs) == 0 and d.start == d.t0  # nothing to morph from: it replaces what is drawn


def test_when_the_camera_stops_the_schedules_settle(scenes):
    index = next(iter(scenes.values())).index
    tour = Tour(index.tour)
    link = Link(scenes, poses=lambda t: tour.pose_at(min(t, 3.0)))  # walks for 3 s, then stands still
    link.run(9.0)
    late = [d for a, d in link.deltas if a - OFFSET > 6.0]
    # Settled: no delta changes more than a few of the scene's objects. An increment at the greedy's value
    # threshold can still flip on float noise as the prediction's last velocity decays and the cost model
    # goes on learning (seen once the compiled kernels changed the selection's timing) — a known gap.
    assert late and all(len(d.morphs) <= 3 and len(d.add) <= 2 for d in late)
    assert sum(len(d.morphs) for d in late) <= 2 * len(late)
    p = link.session.predictor
    eye, _, _ = tour.pose_at(3.0)
    assert np.linalg.norm(p.pose(link.client_time() + 1.5).eye - eye) < 1e-3


def test_without_morphing_selection_switches_at_its_interval(scenes):
    link = Link(scenes, morph=False)
    link.run(6.0)
    assert link.deltas and all(len(d.morphs) == 0 and d.start == d.t0 for _, d in link.deltas)
    assert all(a <= d.start for a, d in link.deltas[1:])


def test_without_prediction_the_last_pose_is_selected_for(scenes):
    link = Link(scenes, predict=False)
    link.run(4.0)
    assert link.session.predictor is None and len(link.deltas) >= 5
    assert all(a <= d.start for a, d in link.deltas[1:])


class _Recorded(Link):
    """A link that keeps every message the session built, before it was encoded."""

    def _to_client(self, messages):
        vars(self).setdefault("built", []).extend(messages)
        super()._to_client(messages)


@pytest.mark.parametrize("governor", [False, True])
def test_a_delta_as_built_encodes_as_its_validated_copy(scenes, governor):
    """The pipeline builds deltas without validating them: each must be exactly what validation gives, to the
    byte on the wire (a numpy scalar or an int where a float belongs would differ, or not encode at all)."""
    link = _Recorded(scenes, one_way=0.03, budget=0.0015, governor=governor)
    link.run(6.0)
    built = [m for m in link.built if isinstance(m, Delta)]
    assert len(built) >= 8
    assert any(d.morphs.rep for d in built) and any(d.add for d in built)
    if governor:
        assert any(d.ladder_rep for d in built)
    for d in built:
        validated = Delta.model_validate(d.model_dump())
        assert encode(validated, compress=False) == encode(d, compress=False), d.seq
