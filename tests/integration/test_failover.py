"""A client given several server URLs fails over when its server dies, draws on meanwhile, and is sent nothing it holds.

Real parts: ``walkstream serve`` child processes (``bench.demo.ServerProcess``),
sharing session state through a real ``redis-server`` where a test says so, and
the real headless client. A server is killed with SIGKILL (no goodbye to its
clients), as when its machine dies.
"""

from __future__ import annotations

import math
import socket
import threading
import time
from pathlib import Path
from urllib.parse import urlsplit

import numpy as np
import pytest

from bench.demo import ServerProcess
from client.connection import Backoff, ClientError, open_patiently
from client.records import ClientRun
from proto import PROTOCOL_VERSION
from proto.messages import Hello

from .test_client_resume import _finish, _run_in_thread, _Watcher

BUDGET = 600_000  # bytes: the client cache's budget, a fraction of the demo store, so it binds


def _start(stores: list[Path], n: int, **kw) -> list[ServerProcess]:
    """``n`` servers started side by side (replica names r0, r1, … when they share Redis)."""
    made: list = [None] * n

    def start(i: int) -> None:
        try:
            made[i] = ServerProcess(stores, **(dict(kw, replica=f"r{i}") if kw.get("redis") else kw))
        except BaseException as exc:  # handed to the fixture's thread
            made[i] = exc

    threads = [threading.Thread(target=start, args=(i,)) for i in range(n)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(120)
    if not all(isinstance(m, ServerProcess) for m in made):
        for m in made:
            if isinstance(m, ServerProcess):
                m.close()
        raise RuntimeError(f"a server did not start: {made!r}")
    return made


@pytest.fixture
def shared_pair(demo_store, redis_url):
    """Two servers of the demo scene that keep session state in one Redis: either resumes the other's session."""
    pair = _start([demo_store], 2, redis=redis_url)
    yield pair
    for s in pair:
        s.close()


@pytest.fixture
def separate_pair(demo_store):
    """Two servers of the demo scene, each with its own in-memory state: neither knows the other's sessions."""
    pair = _start([demo_store], 2)
    yield pair
    for s in pair:
        s.close()


def _netloc(url: str) -> str:
    return urlsplit(url).netloc


def _dead_url() -> str:
    """A loopback websocket URL nothing listens on (connecting is refused at once)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    return f"ws://127.0.0.1:{port}/ws"


def _kill_when_streaming(server: ServerProcess, watcher: _Watcher, thread: threading.Thread) -> int:
    """Once deltas are drawn, SIGKILL ``server``; the number of frames drawn by then."""
    assert watcher.streaming.wait(60), f"no delta was drawn; server log: {server.log[-20:]}"
    assert thread.is_alive()
    server.kill()
    return len(watcher.frames)


def _drawn_throughout(run: ClientRun) -> None:
    """Every frame since the first delta drew the held scene, with no gap in the frames across the outage."""
    streaming = [f for f in run.frames if f.seq >= 0]
    empty = [(round(f.t, 3), f.seq, f.draws, f.governor_down, f.governor_up) for f in streaming if f.triangles == 0]
    lost = [(round(r.lost_at, 3), round(r.resumed_at, 3)) for r in run.reconnects]
    assert streaming and not empty, (f"a frame drew nothing while the server was gone: (t, seq, draws, governor "
                                     f"down, up) {empty[:10]} of {len(streaming)}; outages {lost}")
    t = np.array([f.t for f in run.frames])
    assert np.max(np.diff(t)) < 0.5, f"the frame loop stalled for {np.max(np.diff(t)):.2f} s"


def _nothing_resent(run: ClientRun) -> None:
    r = run.reconnects[-1]
    assert r.held > 0 and r.welcome_held == r.held  # the server took the whole manifest as held
    assert run.resent == 0  # nothing the cache held was sent again
    assert run.deltas_per_connection[-1] > 0  # and deltas flowed on the new connection
    assert run.peak_cache_bytes <= BUDGET


def test_a_killed_server_hands_the_session_to_the_next_url(shared_pair) -> None:
    first, second = shared_pair
    watcher = _Watcher(seq=2)
    thread, out = _run_in_thread([first.url, second.url], watcher, duration=8.0, reconnect_timeout=math.inf,
                                 cache_bytes=BUDGET)
    _kill_when_streaming(first, watcher, thread)
    run = _finish(thread, out, 60)

    assert run.errors == [] and run.close_reason is None
    assert _netloc(run.url) == _netloc(first.url)
    assert len(run.reconnects) == 1
    r = run.reconnects[0]
    assert _netloc(r.url) == _netloc(second.url), r
    assert r.attempts == 2  # the dead server first (it refuses at once), then the next URL
    assert r.resumed and r.session == run.welcome.session  # the second server loaded the session from Redis
    assert 0 <= r.resumed_at - r.lost_at < 2.0
    _nothing_resent(run)
    _drawn_throughout(run)
    seqs = np.array([f.seq for f in run.frames])
    assert np.all(np.diff(seqs) >= 0) and seqs[-1] > max(f.seq for f in run.frames if f.t < r.lost_at)


def test_a_server_that_never_saw_the_session_starts_afresh_on_the_held_manifest(separate_pair) -> None:
    first, second = separate_pair
    watcher = _Watcher(seq=2)
    thread, out = _run_in_thread([first.url, second.url], watcher, duration=6.0, reconnect_timeout=math.inf,
                                 cache_bytes=BUDGET)
    _kill_when_streaming(first, watcher, thread)
    run = _finish(thread, out, 60)

    assert run.errors == [] and run.close_reason is None
    assert len(run.reconnects) == 1
    r = run.reconnects[0]
    assert _netloc(r.url) == _netloc(second.url)
    assert not r.resumed and r.session != run.welcome.session
    _nothing_resent(run)
    _drawn_throughout(run)


def test_with_every_server_gone_the_client_draws_on_and_returns_to_a_restarted_one(shared_pair, demo_store,
                                                                                 redis_url) -> None:
    """Both servers die; frames go on from the cache; a server restarted on the second's port resumes the session."""
    first, second = shared_pair
    watcher = _Watcher(seq=2)
    thread, out = _run_in_thread([first.url, second.url], watcher, duration=25.0, reconnect_timeout=math.inf,
                                 cache_bytes=BUDGET)
    _kill_when_streaming(first, watcher, thread)
    second.kill()
    assert watcher.more(30).wait(30), "the client stopped drawing while every server was gone"
    restarted = ServerProcess([demo_store], redis=redis_url, replica="r1b", port=second.port)
    try:
        assert watcher.more(60).wait(30)
        run = _finish(thread, out, 60)
    finally:
        restarted.close()

    assert run.errors == [] and run.close_reason is None
    assert len(run.reconnects) == 1
    r = run.reconnects[0]
    assert _netloc(r.url) == _netloc(second.url)
    assert r.attempts > 2  # rounds over both dead URLs, spaced by the backoff, until the restart answered
    assert r.resumed and r.session == run.welcome.session
    t = np.array([f.t for f in run.frames])
    assert np.sum((t > r.lost_at) & (t < r.resumed_at)) >= 30  # drawn from the cache during the outage
    _nothing_resent(run)
    _drawn_throughout(run)


# ----------------------------------------------------------------------------- opening on several URLs


@pytest.fixture(scope="module")
def live(demo_store):
    server = ServerProcess([demo_store])
    yield server
    server.close()


def _hello() -> Hello:
    return Hello(protocol=PROTOCOL_VERSION, scene="demo", viewport=[160, 90], predict=False, morph=False)


def test_open_passes_over_an_unreachable_url_to_the_next(live) -> None:
    dead = _dead_url()
    tried: list[tuple[str, int]] = []
    opened = open_patiently([dead, live.url], _hello(), 5.0, 10.0, on_attempt=lambda u, n: tried.append((u, n)))
    try:
        assert opened.url == live.url and opened.attempts == 2 and opened.welcome.session
        assert tried == [(dead, 1), (live.url, 2)]
    finally:
        opened.ws.close()


def test_open_without_waiting_fails_at_once_when_no_server_answers() -> None:
    t0 = time.monotonic()
    with pytest.raises(ClientError, match="cannot connect"):
        open_patiently([_dead_url(), _dead_url()], _hello(), 5.0, 60.0)
    assert time.monotonic() - t0 < 5.0  # one round, not the 60 s of patience


def test_open_waiting_for_unreachable_servers_backs_off_until_out_of_patience() -> None:
    tried: list[float] = []
    backoff = Backoff(base=0.05, cap=0.2, random=lambda: 1.0 - 1e-12)  # the longest wait of each round
    with pytest.raises(ClientError, match="within 1 s"):
        open_patiently([_dead_url(), _dead_url()], _hello(), 1.0, 1.0, wait_unreachable=True, backoff=backoff,
                       on_attempt=lambda u, n: tried.append(time.monotonic()))
    rounds = np.array(tried[::2])
    assert len(tried) % 2 == 0 and len(rounds) >= 4  # every round dials both URLs
    # The second URL is dialled at once after the first; rounds are spaced by the backoff (which grows to its cap).
    gaps = np.diff(rounds)
    assert np.all(gaps >= 0.045) and gaps[-1] >= 0.19


def test_an_endless_wait_ends_when_stopped() -> None:
    stop = threading.Event()
    out: dict = {}

    def wait() -> None:
        try:
            open_patiently([_dead_url()], _hello(), 1.0, math.inf, wait_unreachable=True, stop=stop)
        except ClientError as exc:
            out["error"] = exc

    thread = threading.Thread(target=wait, daemon=True)
    thread.start()
    thread.join(1.0)
    assert thread.is_alive()  # patience is infinite: it is still dialling
    stop.set()
    thread.join(10.0)
    assert not thread.is_alive() and "stopped" in str(out["error"])
