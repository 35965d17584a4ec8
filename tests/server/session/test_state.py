"""Session state that survives a connection: snapshot, restore, resume, ``held`` manifests, and the two stores.

A real session is driven in-process by a real client cache (``ResidentCache``)
along the scene's tour — poses every 0.1 s, pings answered, deltas applied and
acked, frames reported — then snapshotted and restored into a new session the
way another replica would, and the client resumes on it with what it holds.
The stores run against a real redis-server (the ``redis_url`` fixture).
"""

from __future__ import annotations

import asyncio
import socket
import subprocess
import sys
import time
import zlib

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from client.cache import ResidentCache
from proto.tour import Tour
from proto import PROTOCOL_VERSION
from proto.codec import decode_server, encode
from proto.manifest import digest, pack_held
from proto.messages import (Ack, AlgorithmTerms, Camera, Delta, Error, FrameReport, Hello, Ping, Pong, Resume,
                            Welcome)
from server.scene.store import SceneStore
from server.session import Session, SessionConfig, SessionState
from server.state import (MemoryStateStore, RedisStateStore, SqliteStateStore, StateStoreError, open_state_store,
                          unpack_snapshot)

STEP = 0.1  # seconds between camera poses (the predictor keeps ~1 s of them)


@pytest.fixture(scope="module")
def denhaag(denhaag_store):
    store = SceneStore.open(denhaag_store)
    yield {store.index.name: store}
    store.close()


@pytest.fixture(scope="module")
def demo(demo_store):
    store = SceneStore.open(demo_store)
    yield {store.index.name: store}
    store.close()


def _held_ids(cache: ResidentCache) -> np.ndarray:
    return np.asarray(sorted(cache.resident) + sorted(cache.groups), np.int64)


def _hello(scenes, **kw) -> Hello:
    name = next(iter(scenes))
    return Hello(protocol=PROTOCOL_VERSION, scene=name, viewport=[640, 360], target_frame_time=0.05,
                 solver="mixed", algorithms=["flat", "lit"], **kw)


class Client:
    """A client without GL: follows the tour, answers pings, applies and acks deltas into a real cache."""

    def __init__(self, scenes, cache: ResidentCache | None = None) -> None:
        self.index = next(iter(scenes.values())).index
        self.tour = Tour(self.index.tour)
        self.cache = cache or ResidentCache()
        self.deltas: list[Delta] = []
        self.sent_again: list[int] = []  # adds of reps the cache held when the delta arrived
        self.t = 0.0
        self.frame = 0

    def handle(self, session: Session, messages) -> list:
        welcomes = []
        for m in map(decode_server, map(encode, messages)):  # through the wire format, as over a socket
            if isinstance(m, Ping):
                assert session.receive(encode(Pong(id=m.id, sent=m.sent, t=self.t)), self.t) == []
            elif isinstance(m, Delta):
                self.deltas.append(m)
                self.sent_again += [a.rep for a in m.add if a.rep in self.cache]
                changes = self.cache.apply(m)
                c = self.cache
                ack = Ack(seq=m.seq, t=self.t, rejected=changes.rejected, held=c.held, held_bytes=c.held_bytes,
                          digest=c.digest)
                assert session.receive(encode(ack), self.t) == []
            elif isinstance(m, Error):
                raise AssertionError(f"error frame: {m}")
            else:
                welcomes.append(m)
        return welcomes

    def run(self, session: Session, seconds: float) -> None:
        """Poses every STEP s (client clock = server clock here), polls at deadlines, a frame report per pose."""
        end = self.t + seconds
        while self.t < end - 1e-9:
            self.t = round(self.t + STEP, 6)
            eye, forward, up = self.tour.pose_at(self.t)
            session.receive(encode(Camera(t=self.t, eye=eye.tolist(), forward=forward.tolist(), up=up.tolist())),
                            self.t)
            while (deadline := session.next_deadline()) is not None and deadline <= self.t:
                self.handle(session, session.poll(self.t))
            if self.deltas:
                v = int(self.cache.vertices)
                self.frame += 1
                report = FrameReport(frame=self.frame, t=self.t, time=0.004 + 2e-7 * v + 1e-4 * (self.frame % 3),
                                     triangles=int(self.cache.triangles), vertices=v, draws=8,
                                     selection=self.deltas[-1].seq, pixels=50_000,
                                     terms=AlgorithmTerms(triangles=[int(self.cache.triangles), 0],
                                                          vertices=[v, 0], pixels=[50_000, 0], draws=[8, 0]))
                session.receive(encode(report), self.t)


def _drive(scenes, seconds=3.0, session_id="s1"):
    session = Session(scenes, session_id, SessionConfig(), stopwatch=time.perf_counter)
    client = Client(scenes)
    (welcome,) = client.handle(session, session.receive(encode(_hello(scenes)), 0.0))
    client.run(session, seconds)
    return session, client, welcome


def test_snapshot_restore_resume_continues_and_sends_nothing_held(denhaag):
    s1, client, welcome = _drive(denhaag)
    assert welcome.token == s1.token and not welcome.resumed and welcome.held == 0
    assert s1.seq >= 3 and s1.acks == s1.seq and s1.frames > 10 and client.cache.held > 0
    assert s1.mirror_mismatch == 0
    assert s1.dirty
    blob = s1.snapshot()
    assert not s1.dirty
    assert len(blob) < 32 * 1024, len(blob)  # kilobytes: the mirror as bitsets, arrays as raw bytes
    assert unpack_snapshot(blob)["v"] == 1

    # Another replica: a new Session with the same id and token, the snapshot restored before the hello.
    s2 = Session(denhaag, s1.id, SessionConfig(), token=s1.token, stopwatch=time.perf_counter)
    s2.restore(blob)
    assert s2.state is SessionState.AWAIT_HELLO and not s2.dirty
    assert s2.seq == s1.seq and (s2.acks, s2.frames, s2.bytes_sent) == (s1.acks, s1.frames, s1.bytes_sent)
    assert s2.pipeline.pixel_scale == s1.pipeline.pixel_scale and s2.delivery.bandwidth == s1.delivery.bandwidth
    assert s2.cost.to_state() == s1.cost.to_state()  # every coefficient, covariance and history
    assert s2.cost.c_vertex == s1.cost.c_vertex and s2.cost.chosen == s1.cost.chosen
    for name, rung in s1.cost.rungs.items():
        np.testing.assert_array_equal(s2.cost.rungs[name].rls.theta, rung.rls.theta)
        np.testing.assert_array_equal(s2.cost.rungs[name].rls.P, rung.rls.P)

    # While away the client lost a few of its reps (say, the GPU dropped them): its held manifest is the truth.
    lost = _held_ids(client.cache)[::7]
    assert lost.size and all(client.cache.discard(int(r)) for r in lost)
    held = _held_ids(client.cache)
    hello = _hello(denhaag, resume=Resume(session=s1.id, token=s1.token), held=pack_held(held))
    (w2,) = client.handle(s2, s2.receive(encode(hello), client.t))
    assert isinstance(w2, Welcome) and w2.resumed and w2.token == s1.token and w2.session == s1.id
    assert w2.held == held.size
    assert tuple(s2.mirror.held) == (held.size, client.cache.held_bytes, digest(held))
    # The camera history carried over (the new hello's limits are its own).
    p1, p2 = s1.predictor, s2.predictor
    assert len(p1._t) >= 3
    np.testing.assert_array_equal(p2._t, p1._t)
    np.testing.assert_array_equal(p2._x, p1._x)
    assert (p2._speed_seen, p2._turn_seen) == (p1._speed_seen, p1._turn_seen)
    assert s2.dirty  # a resumed session has state worth saving again

    seq_before, sent_before = s1.seq, len(client.deltas)
    client.run(s2, 1.5)
    new = client.deltas[sent_before:]
    assert new, "the resumed session sent no delta"
    assert new[0].seq == seq_before + 1 and new[0].reset  # seq continues; the pipeline restarts with a reset
    assert [d.seq for d in new] == list(range(seq_before + 1, seq_before + 1 + len(new)))
    first_adds = {a.rep for a in new[0].add}
    assert not first_adds & set(held.tolist())  # nothing the client held is sent again ...
    assert client.sent_again == []  # ... in any delta since
    assert s2.mirror_mismatch == 0 and s2.mirror_checks == s1.mirror_checks + len(new)


@pytest.mark.perf
def test_a_snapshot_costs_little_more_than_packing_its_plain_data(denhaag):
    """Snapshots are taken after acks on the serving path: gathering the parts' state must cost about what
    msgpack takes to pack the same data as a plain dict (measured here, on the same machine, not a figure)."""
    s1, _, _ = _drive(denhaag, session_id="perf")
    plain = unpack_snapshot(s1.snapshot())

    def fastest(f, n: int = 20) -> float:
        took = []
        for _ in range(n):
            began = time.perf_counter()
            f()
            took.append(time.perf_counter() - began)
        return min(took)

    reference = fastest(lambda: msgpack.packb(plain, use_bin_type=True))
    assert fastest(s1.snapshot) < 100 * reference


def test_resume_without_held_uses_the_snapshot_mirror(denhaag):
    s1, client, _ = _drive(denhaag, seconds=2.0, session_id="s3")
    blob = s1.snapshot()
    s2 = Session(denhaag, s1.id, token=s1.token, stopwatch=time.perf_counter)
    s2.restore(blob)
    (w,) = client.handle(s2, s2.receive(encode(_hello(denhaag, resume=Resume(session=s1.id, token=s1.token))),
                                         client.t))
    assert w.resumed and w.held == client.cache.held
    np.testing.assert_array_equal(s2.mirror.resident, s1.mirror.resident)
    n = len(client.deltas)
    client.run(s2, 1.0)
    assert len(client.deltas) > n and client.sent_again == [] and s2.mirror_mismatch == 0


def test_a_resume_from_an_older_save_numbers_on_after_the_clients_last_delta(denhaag):
    """Saves are at most once a second, so the state a replica resumes from may predate the last deltas the
    client applied: their numbers must not be used again (the client would take a later delta for an old one)."""
    s1, client, _ = _drive(denhaag, seconds=1.0, session_id="s5")
    blob, saved_seq = s1.snapshot(), s1.seq
    client.run(s1, 1.5)  # deltas sent after the save, then the replica dies
    assert s1.seq > saved_seq and client.cache.seq == s1.seq
    for told, numbered_after in ((client.cache.seq, s1.seq), (None, saved_seq)):
        s2 = Session(denhaag, s1.id, token=s1.token, stopwatch=time.perf_counter)
        s2.restore(blob)
        hello = _hello(denhaag, resume=Resume(session=s1.id, token=s1.token, seq=told),
                       held=pack_held(_held_ids(client.cache)))
        (w,) = client.handle(s2, s2.receive(encode(hello), client.t))
        assert w.resumed
        n = len(client.deltas)
        client.run(s2, 1.0)
        assert client.deltas[n:] and client.deltas[n].seq == numbered_after + 1 and client.deltas[n].reset
        assert client.sent_again == [] and s2.mirror_mismatch == 0


def test_a_fresh_session_with_held_sends_none_of_it(denhaag):
    _, client, _ = _drive(denhaag, seconds=2.0, session_id="s4")
    held = _held_ids(client.cache)
    pose_t = client.t

    def first_delta(hello_kw) -> tuple[Welcome, Delta]:
        s = Session(denhaag, "fresh", SessionConfig(), stopwatch=time.perf_counter)
        c = Client(denhaag, cache=None)
        c.t = pose_t - STEP
        (w,) = c.handle(s, s.receive(encode(_hello(denhaag, **hello_kw)), 0.0))
        c.run(s, STEP)
        return w, c.deltas[0]

    w, delta = first_delta({"held": pack_held(held)})
    assert not w.resumed and w.held == held.size and len(w.token) >= 16
    assert delta.add == [] or not {a.rep for a in delta.add} & set(held.tolist())
    # Without the manifest the same first delta would have re-sent some of it: the check above has teeth.
    _, plain = first_delta({})
    assert {a.rep for a in plain.add} & set(held.tolist())


def test_bad_held_is_refused_and_the_session_goes_on(denhaag):
    n = next(iter(denhaag.values())).index.n_representations
    bomb = zlib.compress(b"\xff" * (4 << 20), 9)
    assert len(bomb) < 48 * 1024
    for bad in (b"not zlib at all", bomb, pack_held(np.array([n])), zlib.compress(b"\x01")[:-3]):
        s = Session(denhaag, "bad", stopwatch=time.perf_counter)
        out = s.receive(encode(_hello(denhaag, held=bad)), 0.0)
        assert [type(m) for m in out] == [Error] and out[0].code == "bad_held", out
        assert s.state is SessionState.AWAIT_HELLO and s.hello is None and s.errors == 1
        w = s.receive(encode(_hello(denhaag, held=pack_held(np.array([0, n - 1])))), 0.0)[0]
        assert isinstance(w, Welcome) and w.held == 2 and s.state is SessionState.ACTIVE


def test_bad_held_on_a_resume_keeps_the_restored_state(denhaag):
    s1, client, _ = _drive(denhaag, seconds=1.5, session_id="s5")
    s2 = Session(denhaag, s1.id, token=s1.token, stopwatch=time.perf_counter)
    s2.restore(s1.snapshot())
    resume = Resume(session=s1.id, token=s1.token)
    out = s2.receive(encode(_hello(denhaag, resume=resume, held=b"garbage")), client.t)
    assert out[0].code == "bad_held" and s2.seq == s1.seq
    w = s2.receive(encode(_hello(denhaag, resume=resume, held=pack_held(_held_ids(client.cache)))), client.t)[0]
    assert w.resumed and w.held == client.cache.held and s2.seq == s1.seq


def test_a_hello_that_does_not_resume_starts_afresh(denhaag):
    s1, _, _ = _drive(denhaag, seconds=1.0, session_id="s6")
    blob = s1.snapshot()
    for resume in (None, Resume(session=s1.id, token="x" * 32)):
        s2 = Session(denhaag, s1.id, token=s1.token, stopwatch=time.perf_counter)
        s2.restore(blob)
        assert s2.seq == s1.seq
        w = s2.receive(encode(_hello(denhaag, resume=resume)), 0.0)[0]
        assert isinstance(w, Welcome) and not w.resumed and w.held == 0
        assert s2.seq == 0 and s2.frames == 0 and s2.cost.frames == 0 and w.token == s1.token


def test_restore_refuses_garbage_and_foreign_blobs(denhaag, demo):
    s1, _, _ = _drive(denhaag, seconds=1.0, session_id="s7")
    blob = s1.snapshot()
    state = msgpack.unpackb(blob)

    def variant(**changes) -> bytes:
        return msgpack.packb({**state, **changes})

    mirror = dict(state["mirror"])
    mirror["held"] = [mirror["held"][0] + 1, *mirror["held"][1:]]
    cost = dict(state["cost"], kind="zach")
    bad = [
        b"", b"\x00garbage\xff" * 10, blob[: len(blob) // 2], msgpack.packb([1, 2, 3]), msgpack.packb({"a": 1}),
        variant(v=99), variant(session="someone-else"), variant(scene="nowhere"), variant(n_reps=1),
        variant(mirror=mirror), variant(cost=cost), variant(fields={**state["fields"], "seq": "seven"}),
        variant(predictor={**state["predictor"], "_x": state["predictor"]["_t"]}),
    ]
    for b in bad:
        s = Session(denhaag, s1.id, token=s1.token, stopwatch=time.perf_counter)
        with pytest.raises(ValueError):
            s.restore(b)
        assert s.seq == 0 and s.cost.frames == 0 and s._restored is None  # untouched
    with pytest.raises(ValueError, match="not served"):
        Session(demo, s1.id, stopwatch=time.perf_counter).restore(blob)


def test_the_snapshot_format_holds_zach_cost_models_too(denhaag):
    config = SessionConfig(cost_model="zach")
    s1 = Session(denhaag, "z", config, stopwatch=time.perf_counter)
    client = Client(denhaag)
    client.handle(s1, s1.receive(encode(_hello(denhaag)), 0.0))
    client.run(s1, 1.0)
    assert s1.cost.updates > 0
    s2 = Session(denhaag, "z", config, token=s1.token, stopwatch=time.perf_counter)
    s2.restore(s1.snapshot())
    assert s2.cost.c_vertex == s1.cost.c_vertex and s2.cost.updates == s1.cost.updates
    with pytest.raises(ValueError, match="zach"):
        Session(denhaag, "z", SessionConfig(), token=s1.token, stopwatch=time.perf_counter).restore(s1.snapshot())


def test_dirty_follows_what_is_worth_saving(denhaag):
    s = Session(denhaag, "d", stopwatch=time.perf_counter)
    assert not s.dirty
    with pytest.raises(RuntimeError):
        s.snapshot()
    client = Client(denhaag)
    client.handle(s, s.receive(encode(_hello(denhaag)), 0.0))
    assert s.dirty
    s.snapshot()
    assert not s.dirty
    s.receive(encode(Camera(t=0.05, eye=[0.0, 0.0, 10.0], forward=[1.0, 0.0, 0.0], up=[0.0, 0.0, 1.0])), 0.05)
    assert not s.dirty  # a pose alone is not worth a save
    client.run(s, 0.5)
    assert s.seq >= 1 and s.dirty


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.data())
def test_the_mirror_after_hello_is_the_held_set(demo, data):
    index = next(iter(demo.values())).index
    n = int(index.n_representations)
    ids = np.asarray(sorted(data.draw(st.sets(st.integers(0, n - 1), max_size=n))), np.int64)
    cache_bytes = data.draw(st.sampled_from([None, 1 << 16]))  # a budget smaller than the set: kept anyway
    s = Session(demo, "h", stopwatch=time.perf_counter)
    w = s.receive(encode(_hello(demo, held=pack_held(ids), cache_bytes=cache_bytes)), 0.0)[0]
    rep_bytes = np.asarray(index.rep_bytes, np.int64)
    assert isinstance(w, Welcome) and w.held == ids.size
    np.testing.assert_array_equal(np.flatnonzero(s.mirror.resident), ids)
    np.testing.assert_array_equal(np.flatnonzero(s.mirror.sent), ids)
    assert tuple(s.mirror.held) == (ids.size, int(rep_bytes[ids].sum()), digest(ids))


# ----------------------------------------------------------------------------- stores


class FakeClock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def test_memory_store_expires_and_deletes():
    async def go():
        clock = FakeClock()
        store = open_state_store(None)
        assert isinstance(store, MemoryStateStore)
        store = MemoryStateStore(clock=clock)
        await store.save("a", "t" * 16, b"one", ttl=10.0)
        await store.save("b", "u" * 16, b"two", ttl=30.0)
        assert await store.load("a") == ("t" * 16, b"one") and len(store) == 2
        clock.now += 9.9
        assert await store.load("a") == ("t" * 16, b"one")
        await store.save("a", "t" * 16, b"one again", ttl=10.0)  # a save renews the lease
        clock.now += 9.9
        assert await store.load("a") == ("t" * 16, b"one again")
        clock.now += 0.2
        assert await store.load("a") is None and len(store) == 1
        await store.delete("b")
        assert await store.load("b") is None and await store.load("never") is None
        await store.save("c", "v" * 16, b"3", ttl=1.0)
        clock.now += 5.0
        await store.save("d", "w" * 16, b"4", ttl=1.0)  # sweeps what expired
        assert "c" not in store._items
        with pytest.raises(ValueError):
            await store.save("e", "x" * 16, b"", ttl=0)
        await store.close()

    asyncio.run(go())


def test_redis_store_saves_loads_expires_and_deletes(redis_url):
    import redis

    async def go():
        store = open_state_store(redis_url)
        assert isinstance(store, RedisStateStore)
        await store.ping()
        blob = bytes(range(256)) * 40
        await store.save("sess1", "tok" * 8, blob, ttl=30.0)
        assert await store.load("sess1") == ("tok" * 8, blob)
        await store.save("sess1", "tok" * 8, b"newer", ttl=30.0)
        assert await store.load("sess1") == ("tok" * 8, b"newer")
        assert await store.load("nobody") is None
        await store.save("sess2", "tok" * 8, b"short", ttl=0.5)
        await store.close()

    asyncio.run(go())
    raw = redis.Redis.from_url(redis_url)
    try:
        assert 0 < raw.pttl("walkstream:session:sess1") <= 30_000  # Redis itself expires it
        assert 0 < raw.pttl("walkstream:session:sess2") <= 500
    finally:
        raw.close()

    async def gone():
        store = RedisStateStore(redis_url, prefix="other:")
        assert await store.load("sess1") is None  # the prefix namespaces keys
        store = RedisStateStore(redis_url)
        await store.delete("sess1")
        assert await store.load("sess1") is None
        await store.close()

    asyncio.run(gone())


def test_redis_store_resumes_a_session_across_replicas(redis_url, denhaag):
    """The app's path: save on one 'replica', load by id on another, check the token, restore, resume."""
    s1, client, _ = _drive(denhaag, seconds=1.5, session_id="r1")

    async def go():
        a, b = RedisStateStore(redis_url), RedisStateStore(redis_url)
        await a.save(s1.id, s1.token, s1.snapshot(), ttl=60.0)
        token, blob = await b.load(s1.id)
        await a.close()
        await b.close()
        return token, blob

    token, blob = asyncio.run(go())
    assert token == s1.token
    s2 = Session(denhaag, s1.id, token=token, stopwatch=time.perf_counter)
    s2.restore(blob)
    hello = _hello(denhaag, resume=Resume(session=s1.id, token=token), held=pack_held(_held_ids(client.cache)))
    (w,) = client.handle(s2, s2.receive(encode(hello), client.t))
    assert w.resumed and s2.seq == s1.seq


def test_unreachable_redis_is_a_clear_error():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]  # closed again: nothing listens there
    url = f"redis://:secret@127.0.0.1:{port}/0"

    async def go():
        store = RedisStateStore(url, timeout=1.0)
        try:
            with pytest.raises(StateStoreError, match=f"127.0.0.1:{port}") as err:
                await store.save("x", "t" * 16, b"", ttl=1.0)
            assert "secret" not in str(err.value)
            with pytest.raises(StateStoreError, match="cannot reach Redis"):
                await store.load("x")
        finally:
            await store.close()

    asyncio.run(go())
    with pytest.raises(ValueError, match="unknown state store"):
        open_state_store("mysql://db")


@pytest.mark.parametrize("kind", ["memory", "redis", "sqlite"])
def test_a_resumed_owner_fences_off_the_old_owners_late_saves(kind, request):
    """A resume rotates the token and saves under the new one, fenced by the old: the old replica, which has
    not yet noticed its dead connection, saves under the old token later — and must not overwrite."""

    async def go():
        if kind == "sqlite":
            store = open_state_store(f"sqlite:///{request.getfixturevalue('tmp_path')}/state.db")
        else:
            store = MemoryStateStore() if kind == "memory" else RedisStateStore(
                request.getfixturevalue("redis_url"), prefix="fence:")
        try:
            assert await store.save("s", "old-token-0123456789", b"v1", 60.0)  # the first owner
            assert await store.save("s", "old-token-0123456789", b"v2", 60.0)  # ... again, its own token
            # The new owner resumed with the old token and saves under its new one, fenced by the old.
            assert await store.save("s", "new-token-0123456789", b"v3", 60.0, fence="old-token-0123456789")
            assert await store.load("s") == ("new-token-0123456789", b"v3")
            # The old owner's late save (on noticing its disconnect) is refused and changes nothing.
            assert not await store.save("s", "old-token-0123456789", b"stale", 60.0)
            assert await store.load("s") == ("new-token-0123456789", b"v3")
            # A stranger's token never writes either; the owner's own saves go on.
            assert not await store.save("s", "someone-else-0123456", b"x", 60.0, fence="also-wrong-012345")
            assert await store.save("s", "new-token-0123456789", b"v4", 60.0)
            assert await store.load("s") == ("new-token-0123456789", b"v4")
            await store.delete("s")
            assert await store.load("s") is None
            assert await store.save("s", "anyone-after-delete-1", b"v5", 60.0)  # nothing stored: anyone may
        finally:
            await store.close()

    asyncio.run(go())


def test_sqlite_store_expires_and_is_shared_by_every_process_that_opens_it(tmp_path):
    path = tmp_path / "state.db"

    async def go():
        clock = FakeClock()
        clock.now = time.time()  # the wall clock's time: the other process below reads the real one
        store = SqliteStateStore(str(path), clock=clock, sweep=0.0)
        assert isinstance(open_state_store(f"sqlite:///{path}"), SqliteStateStore)
        await store.save("a", "t" * 16, b"one", ttl=10.0)
        clock.now += 9.9
        assert await store.load("a") == ("t" * 16, b"one")
        clock.now += 0.2
        assert await store.load("a") is None
        assert await store.save("a", "z" * 16, b"anyone may take an expired one", ttl=10.0)
        await store.save("b", "u" * 16, b"kept", ttl=100.0)
        await store.close()
        with pytest.raises(StateStoreError, match="closed"):
            await store.load("b")

    asyncio.run(go())
    # Another process opens the same file and sees what this one saved; its saves are fenced alike.
    code = (f"import asyncio; from server.state import SqliteStateStore as S\n"
            f"async def go():\n"
            f"    s = S({str(path)!r})\n"
            f"    assert await s.load('b') == ('u' * 16, b'kept')\n"
            f"    assert not await s.save('b', 'x' * 16, b'stolen', 60.0)\n"
            f"    assert await s.save('c', 'c' * 16, b'from the other process', 60.0)\n"
            f"    await s.close()\n"
            f"asyncio.run(go())")
    subprocess.run([sys.executable, "-c", code], check=True, timeout=60)

    async def back():
        store = SqliteStateStore(str(path))
        assert await store.load("c") == ("c" * 16, b"from the other process")
        assert await store.load("b") == ("u" * 16, b"kept")
        await store.close()

    asyncio.run(back())
    with pytest.raises(ValueError, match="names its file"):
        open_state_store("sqlite://")


def test_racing_workers_never_both_take_a_session(tmp_path):
    """Two processes resume the same session at once, each fenced by the old token: exactly one wins each round."""
    path = tmp_path / "state.db"
    code = ("import asyncio, sys; from server.state import SqliteStateStore as S\n"
            "async def go(me):\n"
            "    s = S(sys.argv[1]); won = 0\n"
            "    for i in range(200):\n"
            "        won += await s.save(f's{i}', me * 16, b'x', 60.0, fence='old-token-0123456')\n"
            "    print(won); await s.close()\n"
            "asyncio.run(go(sys.argv[2]))")

    async def first():
        store = SqliteStateStore(str(path))
        for i in range(200):
            await store.save(f"s{i}", "old-token-0123456", b"v0", 60.0)
        await store.close()

    asyncio.run(first())
    procs = [subprocess.Popen([sys.executable, "-c", code, str(path), me], stdout=subprocess.PIPE, text=True)
             for me in "ab"]
    won = [int(p.communicate(timeout=120)[0]) for p in procs]
    assert sum(won) == 200, won  # each session went to one of them, never to both

    async def check():
        store = SqliteStateStore(str(path))
        owners = {(await store.load(f"s{i}"))[0][0] for i in range(200)}
        await store.close()
        return owners

    assert asyncio.run(check()) <= {"a", "b"}


def test_workers_opening_one_new_file_at_once_all_open_it(tmp_path):
    """Worker processes start together and each opens the replica's state file: whichever comes first makes
    it (WAL, the table) and none of them fails on the other's lock. Four processes race for 40 new files."""
    code = ("import asyncio, sys; from server.state import SqliteStateStore as S\n"
            "async def go(me):\n"
            "    for i in range(40):\n"
            "        s = S(f'{sys.argv[1]}/f{i}.db')\n"
            "        assert await s.save(f'{me}{i}', me * 16, b'x', 60.0)\n"
            "        await s.close()\n"
            "asyncio.run(go(sys.argv[2]))")
    procs = [subprocess.Popen([sys.executable, "-c", code, str(tmp_path), me], stderr=subprocess.PIPE, text=True)
             for me in "abcd"]
    errors = [p.communicate(timeout=120)[1] for p in procs]
    assert [p.returncode for p in procs] == [0, 0, 0, 0], [e[-400:] for e in errors]

    async def check():
        store = SqliteStateStore(str(tmp_path / "f39.db"))
        found = [await store.load(f"{me}39") for me in "abcd"]
        await store.close()
        return found

    assert all(f is not None and f[1] == b"x" for f in asyncio.run(check()))
