"""The client cache stays under its byte budget all day: whatever deltas come, across resumes and server restarts.

First the cache alone, fed arbitrary deltas (adds of any size, replacements,
drops, corrupt payloads, adds over the budget): its bytes never pass the
budget and always equal what it holds. Then a kiosk's day against the real
sans-I/O ``Session`` and a real ``ResidentCache``: it looks around the scene
(jumping from view to view, so the server's mirror evicts), loses its
connection with deltas and acks in flight, resumes on a replica that restores
the session's snapshot, and meets a restarted server that knows nothing of it
(a fresh session that adopts the hello's held manifest, perhaps with a smaller
budget of its own). The cache never holds more than its budget, the server
never sends what it holds, and the mirror matches it after every settled ack.
"""

from __future__ import annotations

import secrets
import time

import numpy as np
import pytest
import trimesh
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from client.cache import ResidentCache
from proto import PROTOCOL_VERSION
from proto.codec import decode_server, encode
from proto.geometry import encode_geometry
from proto.manifest import digest, pack_held
from proto.messages import Ack, Camera, Delta, Hello, Ping, Pong, RepresentationAdd, Resume, Welcome
from server.scene.store import SceneStore
from server.session import Session, SessionConfig

# ----------------------------------------------------------------------------- the cache alone

PAYLOADS = [encode_geometry(m.vertices, m.faces) for m in (trimesh.creation.icosphere(k) for k in range(3))]


def _held(cache: ResidentCache) -> np.ndarray:
    return np.asarray(sorted(cache.resident) + sorted(cache.groups), np.int64)


# (rep, payload index) — a rep once per delta, as the server sends it.
adds = st.lists(st.tuples(st.integers(0, 20), st.sampled_from(range(len(PAYLOADS) + 1))), max_size=8,
                unique_by=lambda a: a[0])
deltas = st.lists(st.tuples(adds, st.lists(st.integers(0, 25), max_size=6)), min_size=1, max_size=25)


@given(st.integers(0, 3 * max(map(len, PAYLOADS))), deltas)
def test_no_sequence_of_deltas_takes_the_cache_over_its_budget(budget: int, script) -> None:
    cache = ResidentCache(budget)
    sizes: dict[int, int] = {}  # the model: rep → payload bytes, as the cache's documented rules have it
    for seq, (add, drop) in enumerate(script):
        # Payload index len(PAYLOADS) is a corrupt one: refused like an over-budget add.
        payloads = [PAYLOADS[k] if k < len(PAYLOADS) else b"\xc1bad" for _, k in add]
        delta = Delta(seq=seq, t0=seq, t1=seq + 0.5, drop=drop, selection=[r for r, _ in add],
                      add=[RepresentationAdd(rep=r, object=r, level=0, geometry=g)
                           for (r, _), g in zip(add, payloads)])
        changes = cache.apply(delta)
        refused = set(changes.rejected)
        for (r, _), g in zip(add, payloads):  # adds first, then drops
            if r in refused:
                sizes.pop(r, None)
            else:
                sizes[r] = len(g)
        for r in drop:
            sizes.pop(r, None)
        assert cache.held_bytes <= budget
        ids = _held(cache)
        assert sorted(sizes) == ids.tolist() and cache.held_bytes == sum(sizes.values())
        assert cache.digest == digest(ids) and cache.held == ids.size


# ----------------------------------------------------------------------------- a kiosk's day against the session

CLIENT_BUDGET = 400_000  # bytes: a fraction of the demo store, so the server's mirror evicts as views change


@pytest.fixture(scope="module")
def demo(demo_store):
    store = SceneStore.open(demo_store)
    yield {store.index.name: store}
    store.close()


class Kiosk:
    """One client cache over a day of connections to sessions (sans-I/O), with acks that may lag or be lost."""

    def __init__(self, scenes) -> None:
        self.scenes = scenes
        self.index = next(iter(scenes.values())).index
        self.cache = ResidentCache(CLIENT_BUDGET)
        self.now = 0.0
        self.pending: list[Ack] = []
        self.session: Session | None = None
        self.welcome: Welcome | None = None
        self.resent = 0
        self.deltas = 0
        self.welcomes: list[Welcome] = []

    def hello(self, session: Session, resume: bool) -> None:
        held = self.cache.held_reps()
        hello = Hello(protocol=PROTOCOL_VERSION, scene=self.index.name, viewport=[320, 180],
                      target_frame_time=0.05, predict=False, cache_bytes=CLIENT_BUDGET,
                      resume=Resume(session=self.welcome.session, token=self.welcome.token) if resume else None,
                      held=pack_held(held) if self.welcome is not None else None)
        out = session.receive(encode(hello), self.now)
        welcome = next(m for m in out if isinstance(m, Welcome))
        assert welcome.held == held.size if self.welcome is not None else welcome.held == 0
        for ping in (m for m in out if isinstance(m, Ping)):
            session.receive(encode(Pong(id=ping.id, sent=ping.sent, t=self.now)), self.now)
        self.session, self.welcome = session, welcome
        self.welcomes.append(welcome)
        self.pending = []  # acks of the old connection died with it

    def look(self, key: int, jitter: np.ndarray, lag: int) -> None:
        """Stand at tour key ``key`` (moved by ``jitter``) for one selection; acks reach the server ``lag`` late."""
        s = self.session
        self.now += 1.0
        k = self.index.tour[key % len(self.index.tour)]
        s.receive(encode(Camera(t=self.now, eye=(np.asarray(k["eye"]) + jitter).tolist(), forward=k["forward"],
                                up=k["up"])), self.now)
        for _ in range(10):  # pings may fall due before the selection
            out = [decode_server(encode(m)) for m in s.poll(max(self.now, s.next_deadline() or self.now))]
            for ping in (m for m in out if isinstance(m, Ping)):
                s.receive(encode(Pong(id=ping.id, sent=ping.sent, t=self.now)), self.now)
            got = [m for m in out if isinstance(m, Delta)]
            if got:
                break
        for delta in got:
            self.deltas += 1
            self.resent += int(self.cache.holds(np.asarray([a.rep for a in delta.add], np.int64)).sum())
            changes = self.cache.apply(delta)
            assert self.cache.held_bytes <= CLIENT_BUDGET  # after every delta, all day
            # ... and under the server's own budget once it planned a delta, even one smaller than what the
            # hello's manifest held (a restarted server configured tighter evicts the difference at once).
            assert self.cache.held_bytes <= s.mirror.budget
            c = self.cache
            self.pending.append(Ack(seq=delta.seq, t=self.now, rejected=changes.rejected, held=c.held,
                                    held_bytes=c.held_bytes, digest=c.digest))
        while len(self.pending) > lag:
            assert s.receive(encode(self.pending.pop(0)), self.now) == []

    def settle(self) -> None:
        """Deliver the acks in flight; then the server's mirror is exactly what the cache holds."""
        while self.pending:
            assert self.session.receive(encode(self.pending.pop(0)), self.now) == []
        ids = np.flatnonzero(self.session.mirror.resident)
        assert ids.tolist() == self.cache.held_reps().tolist()


looks = st.tuples(st.integers(0, 1000), st.tuples(*[st.floats(-20, 20)] * 3), st.integers(0, 2))
events = st.one_of(
    st.tuples(st.just("look"), looks),
    st.tuples(st.just("resume"), st.booleans()),  # a replica that restores the snapshot; deltas in flight lost?
    st.tuples(st.just("restart"), st.sampled_from([None, 150_000, 1 << 30])),  # a server that knows nothing
    st.tuples(st.just("settle"), st.none()),
)


@settings(max_examples=12, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture,
                                                                 HealthCheck.too_slow])
@given(st.lists(events, min_size=5, max_size=40))
def test_a_days_cuts_resumes_and_restarts_keep_the_cache_under_budget_and_resend_nothing(demo, day) -> None:
    kiosk = Kiosk(demo)
    kiosk.hello(Session(demo, "day-0", stopwatch=time.perf_counter), resume=False)
    for n, (kind, arg) in enumerate(day, 1):
        if kind == "look":
            key, jitter, lag = arg
            kiosk.look(key, np.asarray(jitter), lag)
        elif kind == "settle":
            kiosk.settle()
        elif kind == "resume":
            old = kiosk.session
            if not arg:
                kiosk.settle()
            blob = old.snapshot()  # what the old replica last saved
            s = Session(demo, old.id, stopwatch=time.perf_counter, token=secrets.token_urlsafe(24))
            s.fence = kiosk.welcome.token
            s.restore(blob)
            kiosk.hello(s, resume=True)
            assert kiosk.welcome.resumed
        else:
            config = SessionConfig() if arg is None else SessionConfig(cache_bytes=arg)
            kiosk.hello(Session(demo, f"day-{n}", config, stopwatch=time.perf_counter), resume=True)
            assert not kiosk.welcome.resumed  # it never saw the session: a fresh one, on the held manifest
    kiosk.look(0, np.zeros(3), 0)
    kiosk.settle()
    assert kiosk.resent == 0  # no delta of any session sent what the cache held
    assert kiosk.cache.held_bytes <= CLIENT_BUDGET and kiosk.cache.refused_full == 0
