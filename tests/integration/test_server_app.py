"""The server application against real processes: limits, admin, metrics, backpressure and resume.

Every test talks to ``walkstream serve`` in its own process (``ServerProcess``)
over a real loopback websocket, as a client would. Waits are on messages,
closes or server-reported state, each bounded by a timeout; nothing sleeps.
"""

from __future__ import annotations

import socket
import time

import httpx
import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from prometheus_client.parser import text_string_to_metric_families
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect

from bench.demo import ServerProcess
from proto import PROTOCOL_VERSION
from proto.codec import decode_server, encode
from proto.manifest import pack_held
from proto.messages import Ack, Camera, Delta, Error, Hello, Ping, Pong, Resume, Welcome  # noqa: F401
from server.limits import ReplicaLimits, RateGuard, TokenBucket

# ----------------------------------------------------------------------------- helpers


class Peer:
    """A scripted client: says hello, answers pings, acks deltas and keeps what it holds."""

    def __init__(self, url: str, scene: str = "demo", *, pong: bool = True, **hello) -> None:
        self.ws = connect(url, max_size=None, open_timeout=10, compression=None, legacy=True)
        self.t0 = time.monotonic()
        self.pong = pong
        self.held: set[int] = set()
        self.deltas: list[Delta] = []
        self.errors: list[Error] = []
        fields = dict(protocol=PROTOCOL_VERSION, scene=scene, viewport=[320, 180], target_frame_time=0.05)
        self.ws.send(encode(Hello(**{**fields, **hello})))
        self.welcome: Welcome = self.expect(Welcome)

    def now(self) -> float:
        return time.monotonic() - self.t0

    def recv(self, timeout: float = 10.0):
        msg = decode_server(self.ws.recv(timeout=timeout))
        if isinstance(msg, Ping) and self.pong:
            self.ws.send(encode(Pong(id=msg.id, sent=msg.sent, t=self.now())))
        elif isinstance(msg, Delta):
            self.deltas.append(msg)
            self.held.difference_update(msg.drop)
            self.held.update(a.rep for a in msg.add)
            self.ws.send(encode(Ack(seq=msg.seq, t=self.now())))
        elif isinstance(msg, Error):
            self.errors.append(msg)
        return msg

    def expect(self, kind, timeout: float = 15.0):
        """Receive until a message of ``kind`` arrives (answering what comes before it)."""
        end = time.monotonic() + timeout
        while True:
            msg = self.recv(max(0.01, end - time.monotonic()))
            if isinstance(msg, kind):
                return msg
            if isinstance(msg, Error) and kind is not Error:
                raise AssertionError(f"server refused: {msg}")

    def camera(self, pose: dict) -> None:
        self.ws.send(encode(Camera(t=self.now(), **pose)))

    def hang_up(self) -> None:
        """Drop the connection without a closing handshake, as a lost network does."""
        self.ws.socket.shutdown(socket.SHUT_RDWR)
        self.ws.close()

    def close(self) -> None:
        self.ws.close()


def _start(store) -> dict:
    from server.scene.store import SceneStore

    with SceneStore.open(store) as s:
        return dict(s.index.start)


def _health(srv) -> dict:
    return httpx.get(srv.http + "/health", timeout=10).json()


def _wait_sessions(srv, n: int) -> None:
    """Until the server has forgotten all but ``n`` sessions (it notices hang-ups on its own), bounded."""
    for _ in range(3000):
        if _health(srv)["sessions"] <= n:
            return
    raise AssertionError(f"the server still has {_health(srv)['sessions']} sessions, expected {n}")


def _metrics(srv) -> dict[tuple, float]:
    text = httpx.get(srv.http + "/metrics", timeout=10).text
    out = {}
    for family in text_string_to_metric_families(text):
        for sample in family.samples:
            out[(sample.name, tuple(sorted(sample.labels.items())))] = sample.value
    return out


def _closed_with(ws, timeout: float = 10.0) -> tuple[list, int]:
    """Messages received until the server closed the socket, and its close code."""
    seen = []
    end = time.monotonic() + timeout
    try:
        while True:
            seen.append(decode_server(ws.recv(timeout=max(0.01, end - time.monotonic()))))
    except ConnectionClosed as exc:
        return seen, exc.rcvd.code if exc.rcvd else 1006


# ----------------------------------------------------------------------------- the main server


@pytest.fixture(scope="module")
def server(demo_store):
    # A small kernel send buffer, so a client that does not read blocks the server's sends soon.
    args = ["--max-sessions", "2", "--rate", "20", "--burst", "10", "--idle-timeout", "30", "--send-buffer", "65536"]
    with ServerProcess([demo_store], extra=args, replica="test-a") as srv:
        yield srv


@pytest.fixture()
def fresh(server):
    """Each test starts with no session left from the one before."""
    _wait_sessions(server, 0)
    return server


def test_health_names_the_replica(fresh):
    health = _health(fresh)
    assert health["replica"] == "test-a" and health["max_sessions"] == 2 and health["sessions"] == 0


def test_past_max_sessions_a_connection_is_refused_busy(fresh, demo_store):
    a, b = Peer(fresh.url), Peer(fresh.url)
    with connect(fresh.url, open_timeout=10) as third:
        seen, code = _closed_with(third)
    assert code == 1013 and len(seen) == 1 and isinstance(seen[0], Error) and seen[0].code == "busy"
    assert "2 sessions" in seen[0].message
    a.close()
    _wait_sessions(fresh, 1)
    c = Peer(fresh.url)  # room again
    assert c.welcome.session not in (a.welcome.session, b.welcome.session)
    assert _metrics(fresh)[("walkstream_refused_total", (("reason", "busy"),))] >= 1
    b.close()
    c.close()


def test_a_flood_is_answered_rate_limited_once_and_the_other_session_goes_on(fresh, demo_store):
    start = _start(demo_store)
    calm, flood = Peer(fresh.url), Peer(fresh.url)
    for p in (calm, flood):
        p.camera(start)
        p.expect(Delta)
    before = _metrics(fresh).get(("walkstream_refused_total", (("reason", "rate"),)), 0.0)
    for _ in range(60):  # 60 poses at once: the burst (10) passes, most of the rest are dropped
        flood.camera(start)
    refusal = flood.expect(Error)
    assert refusal.code == "rate_limited" and "20" in refusal.message
    # One answer for the whole flood (at most one per second), and the session itself goes on.
    flood.expect(Delta)
    flood.expect(Delta)
    assert [e.code for e in flood.errors] == ["rate_limited"]
    dropped = _metrics(fresh)[("walkstream_refused_total", (("reason", "rate"),))] - before
    assert 40 <= dropped <= 55  # the burst less what the hello, pose and pongs before it took
    # The calm session never noticed.
    n = len(calm.deltas)
    calm.expect(Delta)
    calm.expect(Delta)
    assert len(calm.deltas) >= n + 2 and calm.errors == []
    calm.close()
    flood.close()


def test_admin_endpoints_need_the_token(fresh):
    assert httpx.get(fresh.http + "/sessions", timeout=10).status_code == 401
    bad = {"Authorization": "Bearer " + "x" * len(fresh.admin_token)}
    assert httpx.get(fresh.http + "/sessions", headers=bad, timeout=10).status_code == 401
    assert httpx.delete(fresh.http + "/sessions/abc", headers=bad, timeout=10).status_code == 401
    peer = Peer(fresh.url)
    ok = httpx.get(fresh.http + "/sessions", headers=fresh.admin_headers, timeout=10)
    assert ok.status_code == 200 and [s["session"] for s in ok.json()] == [peer.welcome.session]
    missing = httpx.delete(fresh.http + "/sessions/nobody", headers=fresh.admin_headers, timeout=10)
    assert missing.status_code == 404
    for path in ("/health", "/scenes", "/metrics"):  # these stay open
        assert httpx.get(fresh.http + path, timeout=10).status_code == 200
    peer.close()


def test_delete_closes_the_named_session_only(fresh, demo_store):
    start = _start(demo_store)
    doomed, other = Peer(fresh.url), Peer(fresh.url)
    for p in (doomed, other):
        p.camera(start)
        p.expect(Delta)
    sid = doomed.welcome.session
    answer = httpx.delete(f"{fresh.http}/sessions/{sid}", headers=fresh.admin_headers, timeout=10)
    assert answer.status_code == 200 and answer.json() == {"session": sid, "closed": True}
    seen, code = _closed_with(doomed.ws)
    errors = [m for m in seen if isinstance(m, Error)]
    assert code == 1000 and [e.code for e in errors] == ["closed"]
    listed = httpx.get(fresh.http + "/sessions", headers=fresh.admin_headers, timeout=10).json()
    assert [s["session"] for s in listed] == [other.welcome.session]
    n = len(other.deltas)
    other.expect(Delta)  # the other session streams on
    assert len(other.deltas) == n + 1 and other.errors == []
    other.close()


def test_metrics_expose_the_names_and_the_counters_move(fresh, demo_store):
    names = {name for name, _ in _metrics(fresh)}
    for name in ("walkstream_sessions", "walkstream_selection_seconds_bucket", "walkstream_selection_cpu_seconds_count",
                 "walkstream_bytes_out_total", "walkstream_messages_in_total", "process_cpu_seconds_total"):
        assert name in names, name
    before = _metrics(fresh)
    peer = Peer(fresh.url)
    peer.camera(_start(demo_store))
    peer.expect(Delta)
    peer.ws.send(msgpack.packb({"type": "camera", "t": 0.0, "eye": [0.0, float("nan"), 0.0], "forward": [0, 1, 0],
                                "up": [0, 0, 1]}))
    assert peer.expect(Error).code == "invalid"
    after = _metrics(fresh)
    assert after[("walkstream_sessions", ())] == 1
    assert after[("walkstream_bytes_out_total", ())] > before[("walkstream_bytes_out_total", ())] + 1000
    assert after[("walkstream_messages_in_total", ())] >= before[("walkstream_messages_in_total", ())] + 3
    key = ("walkstream_errors_total", (("code", "invalid"),))
    assert after[key] == before.get(key, 0.0) + 1
    assert after[("walkstream_selection_seconds_count", ())] >= before[("walkstream_selection_seconds_count", ())] + 1
    assert after[("walkstream_selection_cpu_seconds_count", ())] >= 1
    assert after[("walkstream_resumes_total", (("outcome", "fresh"),))] >= 1
    peer.close()


def test_a_client_that_never_reads_stalls_only_itself(fresh, demo_store):
    """One client stops reading its socket; the server's sends to it block, and another client's deltas still flow."""
    start = _start(demo_store)
    # A tiny receive buffer and a one-frame queue: the stalled client's side soon holds nothing more.
    raw = socket.create_connection(("127.0.0.1", fresh.port))
    raw.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    stalled = connect(fresh.url, sock=raw, max_size=None, max_queue=1, compression=None, open_timeout=10,
                      legacy=True)
    stalled.send(encode(Hello(protocol=PROTOCOL_VERSION, scene="demo", viewport=[1920, 1080], target_frame_time=2.0,
                              morph=False, predict=False)))
    stalled.send(encode(Camera(t=0.0, **start)))
    reader = Peer(fresh.url)
    reader.camera(start)
    reader.expect(Delta)

    def stalled_entry():
        listed = httpx.get(fresh.http + "/sessions", headers=fresh.admin_headers, timeout=10).json()
        return next(s for s in listed if s["session"] != reader.welcome.session)

    # Its first delta (a megabyte: full detail on a big viewport) is more than the buffers between it and the
    # server hold, so a send to it soon waits; the reader goes on receiving meanwhile. Bounded in count.
    for _ in range(200):
        if stalled_entry()["send_wait_s"] >= 0.5:
            break
        reader.recv(timeout=5)
    else:
        raise AssertionError("the server never blocked on the client that does not read")
    # While that send waits, the reader's deltas arrive at their usual pace.
    stuck = stalled_entry()
    tau = reader.welcome.tau
    n = len(reader.deltas)
    began = time.monotonic()
    for _ in range(3):
        reader.expect(Delta, timeout=3 * tau + 2)
    took = time.monotonic() - began
    assert len(reader.deltas) >= n + 3 and took < 3 * tau + 2.0 and reader.errors == []
    later = stalled_entry()
    assert later["session"] == stuck["session"] and later["send_wait_s"] >= stuck["send_wait_s"] + 0.5 * took
    reader.close()
    stalled.socket.shutdown(socket.SHUT_RDWR)
    stalled.close()


def test_a_dropped_connection_resumes_without_geometry_sent_again(fresh, demo_store):
    start = _start(demo_store)
    first = Peer(fresh.url)
    assert first.welcome.token and first.welcome.resumed is False
    first.camera(start)
    first.expect(Delta)
    first.expect(Delta)
    held = sorted(first.held)
    assert held
    sid, token = first.welcome.session, first.welcome.token
    before = _metrics(fresh)
    first.hang_up()

    again = Peer(fresh.url, resume=Resume(session=sid, token=token), held=pack_held(np.array(held)))
    # Resumed, under a new token: the old one no longer resumes (a stale owner's saves are fenced off).
    assert again.welcome.resumed is True and again.welcome.session == sid and again.welcome.token != token
    assert again.welcome.held == len(held)
    again.camera(start)
    for _ in range(3):
        delta = again.expect(Delta)
        added = {a.rep for a in delta.add}
        assert not added & set(held), sorted(added & set(held))
    after = _metrics(fresh)
    key = ("walkstream_resumes_total", (("outcome", "resumed"),))
    assert after[key] == before.get(key, 0.0) + 1
    again.close()


def test_a_wrong_token_or_unknown_session_gets_a_fresh_session(fresh):
    first = Peer(fresh.url)
    sid = first.welcome.session
    first.close()
    _wait_sessions(fresh, 0)
    before = _metrics(fresh)
    forged = Peer(fresh.url, resume=Resume(session=sid, token="A" * 32))
    assert forged.welcome.resumed is False and forged.welcome.session != sid
    forged.close()
    stranger = Peer(fresh.url, resume=Resume(session="nobody-here", token="B" * 32))
    assert stranger.welcome.resumed is False
    stranger.close()
    after = _metrics(fresh)
    for outcome in ("bad_token", "not_found"):
        key = ("walkstream_resumes_total", (("outcome", outcome),))
        assert after[key] == before.get(key, 0.0) + 1


# ----------------------------------------------------------------------------- idle, and no admin token


def test_an_idle_session_is_closed_and_admin_is_off_without_a_token(demo_store):
    with ServerProcess([demo_store], extra=["--idle-timeout", "1"], admin_token=None) as srv:
        refused = httpx.get(srv.http + "/sessions", timeout=10)
        assert refused.status_code == 403 and "--admin-token" in refused.json()["detail"]
        with connect(srv.url, open_timeout=10) as ws:
            ws.send(encode(Hello(protocol=PROTOCOL_VERSION, scene="demo", viewport=[64, 64])))
            began = time.monotonic()
            seen, code = _closed_with(ws, timeout=10)  # the welcome and pings come, then nothing is heard
            waited = time.monotonic() - began
        assert code == 1000 and isinstance(seen[0], Welcome)
        assert isinstance(seen[-1], Error) and seen[-1].code == "idle"
        assert 0.9 <= waited < 5.0
        assert _metrics(srv)[("walkstream_refused_total", (("reason", "idle"),))] == 1


def test_serve_refuses_an_unreachable_redis(demo_store):
    """``walkstream serve --redis`` with nothing listening: a clear error and exit 2, before serving anything."""
    from typer.testing import CliRunner

    from walkstream.cli import app

    with socket.socket() as s:  # a port nothing listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    done = CliRunner().invoke(app, ["serve", str(demo_store), "--port", "0", "--redis", f"redis://127.0.0.1:{port}/0"])
    assert done.exit_code == 2, done.output
    assert "unreachable" in done.stderr and f"127.0.0.1:{port}" in done.stderr and "serving" not in done.stdout


# ----------------------------------------------------------------------------- limits, clock injected


def test_limits_refuse_nonsense():
    for bad in (dict(max_sessions=0), dict(rate=-1), dict(burst=0.5), dict(idle_timeout=float("nan")),
                dict(threads=0), dict(max_sessions=2.5), dict(state_ttl=0)):
        with pytest.raises(ValueError):
            ReplicaLimits(**bad)
    assert ReplicaLimits().threads >= 1


@settings(max_examples=100, deadline=None)
@given(
    rate=st.floats(1.0, 500.0), burst=st.integers(1, 50),
    gaps=st.lists(st.floats(0.0, 0.2), min_size=1, max_size=300),
)
def test_the_bucket_passes_no_more_than_burst_plus_rate_times_time(rate, burst, gaps):
    bucket = TokenBucket(rate, burst, now=0.0)
    times = np.cumsum(gaps)
    passed = np.array([t for t in times if bucket.take(float(t))])
    # In any window [a, b] of arrivals, what passed is at most burst + rate · (b − a).
    for i in range(passed.size):
        span = passed[i:] - passed[i]
        count = np.arange(1, span.size + 1)
        assert np.all(count <= burst + rate * span + 1e-6)
    # And a client within the rate never loses a message.
    steady = TokenBucket(rate, burst, now=0.0)
    assert all(steady.take(k / rate) for k in range(1, 50))


def test_sustained_flooding_closes_and_a_pause_forgives():
    limits = ReplicaLimits(rate=10, burst=5, abuse_close=5.0, rate_error_interval=1.0)
    guard = RateGuard(limits, now=0.0)
    verdicts = [guard.check(k * 0.01) for k in range(100)]  # 100 messages in a second
    assert verdicts[:5] == [RateGuard.PASS] * 5
    assert verdicts.count(RateGuard.ANSWER) == 1 and RateGuard.CLOSE not in verdicts
    t, verdict = 1.0, None
    while verdict != RateGuard.CLOSE and t < 10:
        t += 0.01
        verdict = guard.check(t)
    assert verdict == RateGuard.CLOSE and 4.9 <= t <= 5.1
    calm = RateGuard(limits, now=0.0)
    for k in range(100):
        calm.check(k * 0.01)
    # A quiet two seconds ends the streak: flooding again starts the five seconds anew.
    assert all(calm.check(3.0 + k * 0.01) != RateGuard.CLOSE for k in range(300))
