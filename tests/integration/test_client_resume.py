"""The client survives a lost connection: it redials, resumes its session and is sent nothing it holds.

Real parts: the real server (``walkstream serve`` in a child process), the real
headless client, and ``bench.netem.DelayProxy`` between them — a TCP relay on
loopback whose ``cut()`` resets the connection (both sides) the way a vanished
network path does, while the server process lives on.
"""

from __future__ import annotations

import threading
import time
from pathlib import Path
from typing import Iterator
from urllib.parse import parse_qsl, urlsplit

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from bench.demo import ServerProcess
from bench.netem import DelayProxy
from client.app import run_client
from client.connection import with_client
from client.records import ClientRun, FrameRecord

VIEW = (160, 90)
ADMIN = "resume-test-admin-token"


def _port(server: ServerProcess) -> int:
    return int(server.http.rsplit(":", 1)[1])


@pytest.fixture(scope="module")
def servers(demo_store: Path) -> Iterator[tuple[ServerProcess, ServerProcess]]:
    """Two independent servers of the demo scene (each its own in-memory state), started side by side.

    The first has admin endpoints (``ADMIN``); the second serves one session at a time
    (``--max-sessions 1``), so it can say ``busy``.
    """
    made: list = [None, None]

    def start(i: int, extra: list[str]) -> None:
        try:
            made[i] = ServerProcess([demo_store], extra=extra)
        except BaseException as exc:  # handed to the fixture's thread
            made[i] = exc

    modes = (["--admin-token", ADMIN], ["--max-sessions", "1"])
    threads = [threading.Thread(target=start, args=(i, extra)) for i, extra in enumerate(modes)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(120)
    try:
        for m in made:
            if not isinstance(m, ServerProcess):
                raise RuntimeError(f"a server did not start: {m!r}")
        yield made[0], made[1]
    finally:
        for m in made:
            if isinstance(m, ServerProcess):
                m.close()


class _Watcher:
    """Frames as they come (``on_frame``), with an event once the client draws its ``seq``-th delta."""

    def __init__(self, seq: int = 1) -> None:
        self.seq = seq
        self.frames: list[FrameRecord] = []
        self.stamps: list[float] = []  # monotonic time of each frame, to order two runs' frames
        self.streaming = threading.Event()
        self.drawn = threading.Event()  # set once ``until`` frames have been drawn
        self.until: int | None = None

    def __call__(self, record: FrameRecord) -> None:
        self.frames.append(record)
        self.stamps.append(time.monotonic())
        if record.seq >= self.seq:
            self.streaming.set()
        if self.until is not None and len(self.frames) >= self.until:
            self.drawn.set()

    def more(self, n: int) -> threading.Event:
        """An event set once ``n`` more frames have been drawn."""
        self.drawn.clear()
        self.until = len(self.frames) + n
        return self.drawn


def _run_in_thread(url: str, watcher: _Watcher, **kw) -> tuple[threading.Thread, dict]:
    out: dict = {}

    def main() -> None:
        try:
            out["run"] = run_client(url, "demo", viewport=VIEW, target_frame_time=0.03, max_fps=30.0,
                                    on_frame=watcher, timeout=5.0, **kw)
        except BaseException as exc:  # handed to the test's thread
            out["error"] = exc

    thread = threading.Thread(target=main, name="client-under-test", daemon=True)
    thread.start()
    return thread, out


def _finish(thread: threading.Thread, out: dict, timeout: float) -> ClientRun:
    thread.join(timeout)
    assert not thread.is_alive(), "the client run did not end"
    if "error" in out:
        raise out["error"]
    return out["run"]


def _cut_when_streaming(proxy: DelayProxy, watcher: _Watcher, thread: threading.Thread, server: ServerProcess,
                        retarget: int | None = None, outage: int = 0) -> None:
    """Once deltas are drawn, reset the connection; keep refusing redials until ``outage`` more frames are drawn."""
    assert watcher.streaming.wait(30), f"no delta was drawn before the cut; server log: {server.log[-20:]}"
    assert thread.is_alive()
    drawn = watcher.more(outage)
    assert proxy.cut() == 1  # the client's one websocket, reset on both sides
    if outage:
        assert drawn.wait(20), "the client stopped drawing while its connection was down"
    if retarget is not None:
        proxy.target_port = retarget  # the next connection reaches another server
    proxy.restore()


def _frames_go_on(run: ClientRun, during: int = 0) -> None:
    """Frames before the loss, ``during`` frames or more while the link was down, and frames after the resume."""
    r = run.reconnects[-1]
    t = np.array([f.t for f in run.frames])
    assert np.any(t < r.lost_at) and np.sum(t > r.resumed_at) >= 10
    assert np.sum((t > r.lost_at) & (t < r.resumed_at)) >= during


def test_cut_connection_resumes_the_session_and_resends_nothing(servers) -> None:
    with DelayProxy("127.0.0.1", _port(servers[0])) as proxy:
        watcher = _Watcher(seq=2)
        thread, out = _run_in_thread(f"ws://{proxy.address}/ws", watcher, duration=4.0)
        _cut_when_streaming(proxy, watcher, thread, servers[0], outage=3)  # redials are refused for 3 frames
        run = _finish(thread, out, 30)

    assert run.errors == [] and run.close_reason is None
    assert len(run.reconnects) == 1 and proxy.accepted >= 2
    r = run.reconnects[0]
    assert r.resumed, f"the server did not resume the session: {r}"
    assert r.session == run.welcome.session
    assert 0 <= r.resumed_at - r.lost_at < 2.0
    assert r.held > 0 and r.welcome_held == r.held  # the server took the whole manifest as held
    assert run.resent == 0  # nothing the cache held was sent again
    # The frame loop drew on from what was resident while it redialled. Redials were refused for 3 frames
    # after the cut, but the client notices the loss (lost_at) a frame or so after the cut itself.
    _frames_go_on(run, during=1)
    # Deltas kept coming on the new connection, numbered on from the old one's.
    assert len(run.deltas_per_connection) == 2 and all(n > 0 for n in run.deltas_per_connection)
    seqs = np.array([f.seq for f in run.frames])
    assert np.all(np.diff(seqs) >= 0)
    assert seqs[-1] > max(f.seq for f in run.frames if f.t < r.lost_at)
    assert len(run.bytes_per_connection) == 2 and sum(run.bytes_per_connection) == run.bytes_received
    assert all(n > 0 for n in run.bytes_per_connection)


def test_resume_refused_starts_a_fresh_session_that_keeps_the_cache(servers) -> None:
    """The second server never saw the session (its own memory store): a fresh session, built on the manifest."""
    first, second = servers
    with DelayProxy("127.0.0.1", _port(first)) as proxy:
        watcher = _Watcher(seq=2)
        thread, out = _run_in_thread(f"ws://{proxy.address}/ws", watcher, duration=4.0)
        _cut_when_streaming(proxy, watcher, thread, first, retarget=_port(second))
        run = _finish(thread, out, 30)

    assert run.errors == [] and run.close_reason is None
    assert len(run.reconnects) == 1
    r = run.reconnects[0]
    assert not r.resumed and r.session != run.welcome.session
    assert r.held > 0 and r.welcome_held == r.held
    assert run.resent == 0  # the held manifest spared it everything it had
    assert len(run.deltas_per_connection) == 2 and run.deltas_per_connection[1] > 0
    assert 0 <= r.resumed_at - r.lost_at < 2.0
    _frames_go_on(run)


def test_reconnect_timeout_zero_ends_the_run_on_loss(servers) -> None:
    with DelayProxy("127.0.0.1", _port(servers[0])) as proxy:
        watcher = _Watcher(seq=1)
        thread, out = _run_in_thread(f"ws://{proxy.address}/ws", watcher, duration=20.0, reconnect_timeout=0)
        _cut_when_streaming(proxy, watcher, thread, servers[0])
        run = _finish(thread, out, 15)  # well before the 20 s it was asked for

    assert run.reconnects == [] and proxy.accepted == 1
    assert run.close_reason is not None and "connection lost" in run.close_reason
    assert [e.code for e in run.errors] == ["connection_lost"]
    assert "reconnect_timeout=0" in run.errors[0].message
    assert run.frames[-1].t < 15.0


@given(st.dictionaries(st.text("abcxyz_", min_size=1, max_size=6), st.text(max_size=8), max_size=4),
       st.uuids())
def test_client_id_goes_in_the_query_and_keeps_the_rest(query: dict, uid) -> None:
    from urllib.parse import urlencode

    url = "ws://host:1/ws" + ("?" + urlencode(query) if query else "")
    out = with_client(url, uid.hex)
    parts = urlsplit(out)
    pairs = parse_qsl(parts.query, keep_blank_values=True)
    assert (parts.scheme, parts.netloc, parts.path) == ("ws", "host:1", "/ws")
    assert [v for k, v in pairs if k == "client"] == [uid.hex]
    assert {k: v for k, v in pairs if k != "client"} == {k: v for k, v in query.items() if k != "client"}
    assert with_client(out, uid.hex) == out  # idempotent: a redial does not stack ids


def test_busy_server_is_retried_on_first_connect(servers) -> None:
    """A replica at its session limit answers ``busy``; the client retries until a place frees up."""
    server = servers[1]  # one session at a time
    holder, blocked = _Watcher(seq=1), _Watcher(seq=1)
    first, out1 = _run_in_thread(server.url, holder, duration=3.0)
    assert holder.streaming.wait(30)
    second, out2 = _run_in_thread(server.url, blocked, duration=1.0, reconnect_timeout=10)
    run1 = _finish(first, out1, 30)
    run2 = _finish(second, out2, 30)
    assert run1.errors == [] and run2.errors == [] and run1.attempts == 1
    assert run2.attempts > 1  # refused (busy) while the first held the only place, then retried
    assert blocked.stamps and blocked.stamps[0] > holder.stamps[-1]  # it only got in once the first had left
    assert run2.welcome.session != run1.welcome.session


def test_admin_close_ends_the_run_without_redialling(servers) -> None:
    """``closed`` (an administrator ended the session) is final: no redial, no error, the reason kept."""
    import httpx

    server = servers[0]
    with DelayProxy("127.0.0.1", _port(server)) as proxy:
        watcher = _Watcher(seq=1)
        thread, out = _run_in_thread(f"ws://{proxy.address}/ws", watcher, duration=20.0)
        assert watcher.streaming.wait(30)
        auth = {"Authorization": f"Bearer {ADMIN}"}
        live = httpx.get(f"{server.http}/sessions", headers=auth, timeout=10).json()
        assert len(live) == 1, live
        answer = httpx.delete(f"{server.http}/sessions/{live[0]['session']}", headers=auth, timeout=10)
        assert answer.status_code == 200 and answer.json()["closed"] is True
        run = _finish(thread, out, 15)
    assert run.reconnects == [] and proxy.accepted == 1 and run.errors == []
    assert run.close_reason is not None and run.close_reason.startswith("the server closed the session")
    assert run.frames[-1].t < 15.0
