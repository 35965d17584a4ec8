"""The server's client-cache mirror against a real ``ResidentCache``: it never diverges, and when it does, it heals.

A session (sans-I/O) and a real cache play both ends of the wire: every delta
goes through msgpack into ``ResidentCache.apply`` and the cache's ack —
``rejected``, ``held``, ``held_bytes``, ``digest`` — comes back, optionally a
few deltas late, as over a link with deltas in flight. The mirror must equal
what the cache holds after every ack, under a budget that forces eviction, with
payloads corrupted in transit, with a client smaller than the server believes,
and after a divergence made behind the server's back (which a resync repairs).
Then the client's loop (without GL) and, last, the real websocket server with
the real headless client.
"""

from __future__ import annotations

import asyncio
import queue
import socket
import threading
import time
from collections import deque

import numpy as np
import pytest

from client.connection import Arrived
from client.frame_loop import FrameLoop
from client.records import ClientRun
from client.cache import ResidentCache
from proto import PROTOCOL_VERSION
from proto.codec import decode_client, decode_server, encode
from proto.manifest import digest
from proto.messages import Ack, Camera, Delta, Hello, Pong, Pose, Welcome
from proto.points import Instances, Points
from server.scene.index import TREES
from server.scene.store import SceneStore
from server.session import Session, SessionConfig

PRESSURE = 300_000  # bytes: a fraction of the demo store's ~1.9 MB, so the mirror evicts every few deltas


@pytest.fixture(scope="module")
def demo(demo_store):
    store = SceneStore.open(demo_store)
    yield {store.index.name: store}
    store.close()


@pytest.fixture(scope="module")
def denhaag(denhaag_store):
    store = SceneStore.open(denhaag_store)
    yield {store.index.name: store}
    store.close()


def _mirror(s: Session) -> tuple[int, int, int]:
    """(held, held_bytes, digest) of the mirror, recomputed from scratch (not from its running totals)."""
    ids = np.nonzero(s.mirror.resident)[0]
    return int(ids.size), int(s.mirror.table.rep_bytes[ids].sum()), digest(ids)


def _holding(cache: ResidentCache) -> tuple[int, int, int]:
    ids = np.asarray(sorted(cache.resident) + sorted(cache.groups), np.int64)
    return int(ids.size), int(sum(cache._bytes.values())), digest(ids)


class Pair:
    """A session and a real client cache; acks reach the server ``lag`` deltas after their delta arrived."""

    def __init__(self, scenes, *, config=None, hello_bytes=None, client_bytes=None, lag=0, solver="greedy",
                 tamper=None):
        self.s = Session(scenes, "mirror", config or SessionConfig(), stopwatch=time.perf_counter)
        self.index = next(iter(scenes.values())).index
        hello = Hello(protocol=PROTOCOL_VERSION, scene=self.index.name, viewport=[640, 360],
                      target_frame_time=0.05, predict=False, solver=solver, cache_bytes=hello_bytes)
        self.s.receive(encode(hello), 0.0)
        self.s.receive(encode(Pong(id=1, sent=0.0, t=0.0)), 0.0)  # one clock, no delay
        self.cache = ResidentCache(client_bytes)
        self.lag, self.tamper = lag, tamper
        self.pending: deque[Ack] = deque()
        self.deltas: list[Delta] = []
        self.acked: list[tuple[int, bool]] = []  # (seq, mirror == cache right after the ack) per delivered ack
        self.peak = 0
        self.now = 0.0

    def tour(self, rounds: int = 1, on_delta=None) -> None:
        """Follow the scene's tour, one key per second, a selection after each pose."""
        keys = self.index.tour * rounds
        for i, key in enumerate(keys):
            self.now = float(i)
            pose = {k: key[k] for k in ("eye", "forward", "up")}
            self.s.receive(encode(Camera(t=self.now, **pose)), self.now)
            for _ in range(10):  # pings may fall due before the selection
                out = [m for m in map(decode_server, map(encode, self.s.poll(max(self.now, self.s.next_deadline()))))
                       if isinstance(m, Delta)]
                if out:
                    break
            for delta in out:
                self.arrive(delta)
                if on_delta is not None:
                    on_delta(self, delta)

    def arrive(self, delta: Delta) -> None:
        if self.tamper is not None:
            delta = decode_server(encode(self.tamper(delta)))
        self.deltas.append(delta)
        changes = self.cache.apply(delta)
        self.peak = max(self.peak, self.cache.held_bytes)
        c = self.cache
        self.pending.append(Ack(seq=delta.seq, t=self.now, rejected=changes.rejected, held=c.held,
                                held_bytes=c.held_bytes, digest=c.digest))
        while len(self.pending) > self.lag:
            self.deliver()

    def deliver(self) -> None:
        ack = self.pending.popleft()
        assert self.s.receive(encode(ack), self.now) == []
        self.acked.append((ack.seq, not self.pending and _mirror(self.s) == _holding(self.cache)))

    def flush(self) -> None:
        while self.pending:
            self.deliver()

    def check_totals(self) -> None:
        """The session's running totals are what its mirror array says, and the cache's are what it holds."""
        assert tuple(self.s.mirror.held) == _mirror(self.s)
        assert (self.cache.held, self.cache.held_bytes, self.cache.digest) == _holding(self.cache)


@pytest.mark.parametrize("lag", [0, 3])
def test_the_mirror_equals_the_client_after_every_ack(demo, lag):
    p = Pair(demo, lag=lag)
    p.tour()
    p.flush()
    s = p.s
    assert len(p.deltas) >= 30 and s.acks == len(p.deltas)
    assert s.mirror_checks == len(p.deltas) and s.mirror_mismatch == 0 and s.resyncs == 0
    if lag == 0:
        assert all(ok for _, ok in p.acked)  # after every ack, not just at the end
    assert p.acked[-1][1] and p.cache.held > 0
    p.check_totals()
    st = s.stats
    assert (st["resident"], st["held_bytes"]) == (p.cache.held, p.cache.held_bytes)
    assert st["evicted"] == st["over_budget"] == st["refused"] == 0


def test_under_pressure_the_client_never_holds_more_than_its_budget(demo):
    p = Pair(demo, hello_bytes=PRESSURE, client_bytes=PRESSURE, lag=1)
    evicting = []
    p.tour(rounds=2, on_delta=lambda pair, d: evicting.append(len(d.drop) > 0))
    p.flush()
    s = p.s
    assert s.cache_budget == PRESSURE and s.stats["cache_budget"] == PRESSURE
    assert p.peak <= PRESSURE  # after every delta
    assert s.evicted > 0 and sum(len(d.drop) for d in p.deltas) == s.evicted
    assert sum(evicting) >= len(evicting) // 5  # eviction every few deltas, not once
    assert s.over_budget > 0  # at this budget the selection alone sometimes does not fit: sent as far as it goes
    assert p.cache.refused_full == 0 and s.refused == 0  # the server never sent more than fits
    assert s.mirror_checks == len(p.deltas) and s.mirror_mismatch == 0 and s.resyncs == 0
    assert p.acked[-1][1]
    p.check_totals()
    # What was sent in each delta fit, in priority order: the selection before the rest.
    for d in p.deltas:
        assert sum(len(a.geometry) for a in d.add) <= PRESSURE


def test_the_budget_is_the_smaller_of_the_clients_and_the_servers(demo):
    assert Pair(demo, config=SessionConfig(cache_bytes=200_000), hello_bytes=1 << 30).s.cache_budget == 200_000
    assert Pair(demo, config=SessionConfig(cache_bytes=1 << 30), hello_bytes=200_000).s.cache_budget == 200_000
    assert Pair(demo, config=SessionConfig(cache_bytes=300_000)).s.cache_budget == 300_000


def test_payloads_corrupted_in_transit_are_refused_and_the_mirror_follows(demo):
    corrupted: list[int] = []

    def tamper(delta: Delta) -> Delta:
        if delta.seq % 3 or not delta.add:
            return delta
        bad = delta.add[0].model_copy(update={"geometry": b"\xc1" + delta.add[0].geometry[1:]})
        corrupted.append(bad.rep)
        return delta.model_copy(update={"add": [bad, *delta.add[1:]]})

    p = Pair(demo, hello_bytes=PRESSURE, client_bytes=PRESSURE, lag=2, tamper=tamper)
    p.tour(rounds=2)
    p.flush()
    s = p.s
    assert len(corrupted) >= 5 and len(p.cache.rejected) == len(corrupted) == s.refused
    assert all(e.code == "bad_geometry" for e in p.cache.rejected)
    assert s.mirror_checks == len(p.deltas) and s.mirror_mismatch == 0 and s.resyncs == 0
    assert p.acked[-1][1]
    p.check_totals()
    # A refused rep is no longer in the mirror, so it is sent again when next needed.
    resent = {a.rep for d in p.deltas for a in d.add} & set(corrupted)
    assert any(sum(a.rep == r for d in p.deltas for a in d.add) > 1 for r in resent)


def test_a_client_smaller_than_the_server_believes_refuses_and_the_mirror_follows(demo):
    p = Pair(demo, client_bytes=PRESSURE, lag=1)  # the server believes its own 512 MB default
    p.tour(rounds=2)
    p.flush()
    s = p.s
    assert s.cache_budget > 100 * PRESSURE
    assert p.peak <= PRESSURE and p.cache.refused_full > 0
    assert s.refused == p.cache.refused_full and p.cache.rejected == []
    assert s.mirror_checks == len(p.deltas) and s.mirror_mismatch == 0 and s.resyncs == 0
    assert p.acked[-1][1]
    p.check_totals()


@pytest.mark.parametrize("lag", [0, 2])
def test_a_divergence_is_detected_and_healed_by_a_resync(demo, lag):
    p = Pair(demo, hello_bytes=PRESSURE, client_bytes=PRESSURE, lag=lag)
    marks: dict = {"resync": []}

    def meddle(pair: Pair, delta: Delta) -> None:
        if pair.s.resyncs > len(marks["resync"]):
            marks["resync"].append(delta)
        if delta.seq == 12:  # forget a rep behind the server's back, after acking delta 12
            held = sorted(pair.cache.resident)
            marks["forgot"] = held[len(held) // 2]
            assert pair.cache.discard(marks["forgot"])

    p.tour(rounds=2, on_delta=meddle)
    p.flush()
    s = p.s
    assert s.mirror_mismatch == 1 and s.resyncs == 1  # detected once, not again by acks already in flight
    (resync,) = marks["resync"]
    assert resync.seq == 13 + lag + 1  # ack 13 shows it, arriving after delta 13 + lag; the next delta heals
    sent_before = {a.rep for d in p.deltas if d.seq < resync.seq for a in d.add}
    assert set(resync.drop) | {a.rep for a in resync.add} >= sent_before  # everything the client may hold
    assert not set(resync.drop) & {a.rep for a in resync.add}
    assert len([seq for seq, _ in p.acked if seq >= resync.seq]) >= 10
    assert s.mirror_checks == len(p.deltas) - lag  # the acks in flight at the resync are not compared
    assert all(ok for seq, ok in p.acked if seq >= resync.seq) if lag == 0 else p.acked[-1][1]
    p.check_totals()
    assert p.peak <= PRESSURE and p.cache.refused_full == 0


def test_unknown_repeated_and_lost_acks_do_no_harm(demo):
    p = Pair(demo, hello_bytes=PRESSURE, client_bytes=PRESSURE, lag=0)
    p.tour()
    s = p.s
    before = (_mirror(s), s.mirror_checks, s.mirror_mismatch, s.resyncs, s.refused)
    last = next(d for d in reversed(p.deltas) if d.add)
    some = last.add[0].rep
    for ack in (Ack(seq=s.seq + 5, t=1.0, rejected=[some], held=0, held_bytes=0, digest=0),  # never sent
                Ack(seq=last.seq, t=1.0, rejected=[some], held=0, held_bytes=0, digest=0),  # a repeat
                Ack(seq=0, t=1.0, rejected=[some])):  # before the first delta
        assert s.receive(encode(ack), 50.0) == []
    assert (_mirror(s), s.mirror_checks, s.mirror_mismatch, s.resyncs, s.refused) == before and not s.mirror.resync
    # Deltas whose acks never come, then one whose record is gone (hundreds unacked): its refusals
    # cannot be placed, so the mirror is not trusted and the next delta resyncs.
    p.lag = 1_000
    p.tour()
    p.pending.clear()
    p.lag = 0
    seq = s.seq
    s.mirror._records.pop(seq)
    assert s.receive(encode(Ack(seq=seq, t=1.0, rejected=[some])), 50.0) == [] and s.mirror.resync
    p.tour()
    assert s.resyncs == 1 and s.mirror_mismatch == 0 and p.acked[-1][1]
    p.check_totals()


def test_tree_groups_and_models_stream_with_the_mixed_solver(denhaag):
    p = Pair(denhaag, solver="mixed", lag=1)
    p.tour()
    p.flush()
    index, s, cache = p.index, p.s, p.cache
    trees = [a for d in p.deltas for a in d.add if a.kind == "trees"]
    assert trees and all(index.object_kind[index.rep_object[a.rep]] == TREES for a in trees)
    assert all(a.morph is None for a in trees)
    meshes = [a for d in p.deltas for a in d.add if a.kind == "mesh"]
    assert all(index.object_kind[index.rep_object[a.rep]] != TREES for a in meshes)
    with_models = [d for d in p.deltas if d.models]
    assert len(with_models) == 1  # once per session ...
    n_models = int(index.model_points.shape[0])
    assert sorted(m.model for m in with_models[0].models) == list(range(n_models))
    first_trees = min(d.seq for d in p.deltas if any(a.kind == "trees" for a in d.add))
    assert with_models[0].seq == first_trees  # ... with the first tree group
    assert sorted(cache.models) == list(range(n_models))
    assert all(isinstance(m, Points) and len(m) == index.model_points[k] for k, m in cache.models.items())
    drawn = {r for d in p.deltas for r, x in zip(d.vegetation, d.resolution) if x > 0}
    assert drawn and set(cache.groups) <= drawn and cache.groups
    assert all(cache.groups[r].instances > 0 for r in cache.groups)
    assert cache.rejected == [] and s.mirror_mismatch == 0 and s.mirror_checks == len(p.deltas)
    assert p.acked[-1][1] and s.mirror.resident[list(cache.groups)].all()  # tree groups are in the mirror
    p.check_totals()


# ----------------------------------------------------------------------------- the client's loop, without GL


class _Renderer:
    def __init__(self) -> None:
        self.meshes: dict[int, int] = {}

    def reserve(self, vertices, indices) -> None:
        pass

    def upload(self, rep, geometry, object_id=None) -> None:
        self.meshes[rep] = object_id

    def free(self, rep) -> None:
        self.meshes.pop(rep, None)

    def has_morph_target(self, rep) -> bool:
        return True


class _Splats:
    def __init__(self) -> None:
        self.models: dict[int, Points] = {}
        self.groups: dict[int, Instances] = {}
        self.added = 0

    def add_model(self, model: int, points: Points) -> None:
        self.models[model] = points

    def add_group(self, rep: int, instances: Instances) -> None:
        self.groups[rep] = instances
        self.added += 1

    def free_group(self, rep: int) -> None:
        del self.groups[rep]


class _Socket:
    def __init__(self) -> None:
        self.sent: list[Ack] = []

    def send(self, data: bytes) -> None:
        self.sent.append(decode_client(data))


def test_the_loop_feeds_renderer_and_splats_and_acks_what_it_holds(denhaag):
    """``FrameLoop.handle``: meshes to the renderer, groups and models to the splat layer, the cache's state acked."""
    budget = int(denhaag["denhaag"].index.rep_bytes.sum()) // 2  # half the store: the mirror evicts, groups fit
    pair = Pair(denhaag, solver="mixed", hello_bytes=budget)
    welcome = Welcome(session="x", protocol=PROTOCOL_VERSION, scene="denhaag", bounds=pair.index.bounds.tolist(),
                      start=Pose(**pair.index.start), tau=0.5, solver="mixed")
    run, ws = ClientRun(welcome=welcome), _Socket()
    loop = FrameLoop(run, _Renderer(), queue.Queue(), ws, cache_bytes=budget)
    assert loop.splats is None
    loop.splats = _Splats()
    keys = pair.index.tour[:40]
    for i, key in enumerate(keys):
        pose = {k: key[k] for k in ("eye", "forward", "up")}
        pair.s.receive(encode(Camera(t=float(i), **pose)), float(i))
        for m in pair.s.poll(max(float(i), pair.s.next_deadline())):
            if isinstance(m, Delta):
                loop.handle(Arrived(decode_server(encode(m)), float(i)))
                for ack in ws.sent:
                    pair.s.receive(encode(ack), float(i))
                ws.sent.clear()
    cache = loop.cache
    assert set(loop.renderer.meshes) == set(cache.resident) and set(loop.splats.groups) == set(cache.groups)
    assert loop.splats.added and sorted(loop.splats.models) == list(range(int(pair.index.model_points.shape[0])))
    assert pair.s.mirror_checks == run.deltas_received and pair.s.mirror_mismatch == 0
    assert run.peak_cache_bytes <= budget and run.refused_full == 0 and pair.s.evicted > 0
    assert _mirror(pair.s) == _holding(cache)


# ----------------------------------------------------------------------------- end to end, real parts


@pytest.fixture(scope="module")
def live(demo_store):
    """The real FastAPI/uvicorn server in this process (so its sessions can be inspected), on a free port."""
    import uvicorn

    from server.app import WS_MAX_SIZE, create_app, load_scenes

    app = create_app(load_scenes([demo_store]), SessionConfig(cache_bytes=PRESSURE))
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    sock.bind(("127.0.0.1", 0))
    sock.listen(16)
    server = uvicorn.Server(uvicorn.Config(app, log_level="warning", ws_max_size=WS_MAX_SIZE))
    thread = threading.Thread(target=lambda: asyncio.run(server.serve(sockets=[sock])), daemon=True)
    thread.start()
    for _ in range(200):
        if server.started:
            break
        time.sleep(0.05)
    assert server.started
    yield app, f"ws://127.0.0.1:{sock.getsockname()[1]}/ws"
    server.should_exit = True
    thread.join(timeout=10)
    sock.close()


def test_end_to_end_the_mirror_holds_over_the_real_websocket_and_client(live):
    from client.app import run_client

    app, url = live
    seen: dict[str, Session] = {}

    def on_frame(rec) -> None:
        seen.update(dict(app.state.sessions))  # keep the session: the server forgets it on disconnect

    run = run_client(url, "demo", duration=10.0, viewport=(320, 180), target_frame_time=0.05, on_frame=on_frame)
    (session,) = seen.values()
    assert run.errors == [] and run.rejected == [] and run.close_reason is None
    assert run.deltas_received >= 6 and session.cache_budget == PRESSURE
    assert run.peak_cache_bytes <= PRESSURE and run.refused_full == 0  # the client never got more than fits
    assert session.evicted > 0  # the budget bit
    assert session.mirror_checks >= run.deltas_received - 3  # the last acks may still have been in flight
    assert session.mirror_mismatch == 0 and session.resyncs == 0
