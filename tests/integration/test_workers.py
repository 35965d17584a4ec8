"""One replica, several worker processes behind one port: connections spread over them, one /metrics and one
/sessions for all of them, and a worker killed mid-session hands its client to another with nothing re-sent."""

from __future__ import annotations

import contextlib
import os
import signal
import time

import httpx
import pytest
from websockets.sync.client import connect

from bench.demo import ServerProcess
from bench.loadtest.metrics import parse_metrics
from proto import PROTOCOL_VERSION
from proto.codec import decode_server, encode
from proto.messages import Hello, Welcome

from .killed import ClientUnderKill

VIEWPORT = (320, 180)


@pytest.fixture()
def replica(demo_store):
    with ServerProcess([demo_store], workers=2, extra=["--tau", "0.5"]) as srv:
        yield srv


def _sessions(srv) -> list[dict]:
    r = httpx.get(srv.http + "/sessions", headers=srv.admin_headers, timeout=10)
    r.raise_for_status()
    return r.json()


def test_workers_share_the_port_and_answer_for_each_other(replica):
    with contextlib.ExitStack() as open_sockets:
        for _ in range(12):
            ws = open_sockets.enter_context(connect(replica.url, max_size=None))
            ws.send(encode(Hello(protocol=PROTOCOL_VERSION, scene="demo", viewport=list(VIEWPORT))))
            assert isinstance(decode_server(ws.recv(timeout=10)), Welcome)
        rows = _sessions(replica)
        workers = {r["worker"] for r in rows}
        # The kernel spreads connections over both workers; any worker lists the replica's every session.
        assert len(rows) == 12 and len(workers) == 2, workers
        deadline = time.monotonic() + 5
        while True:  # each worker refreshes its share every half second
            scrape = parse_metrics(httpx.get(replica.http + "/metrics", timeout=10).text)
            if scrape.values.get("walkstream_sessions") == 12 or time.monotonic() > deadline:
                break
            time.sleep(0.2)
        assert scrape.values["walkstream_sessions"] == 12
        cpu = [parse_metrics(httpx.get(replica.http + "/metrics", timeout=10).text).values["walkstream_cpu_seconds"]
               for _ in range(4)]
        assert min(cpu) > 0.5  # both workers' start-up (stores, kernels) at least
        # A session closed by an administrator through whichever worker the request lands on.
        sid = rows[0]["session"]
        r = httpx.delete(f"{replica.http}/sessions/{sid}", headers=replica.admin_headers, timeout=10)
        assert r.status_code == 200 and r.json()["session"] == sid
        assert sid not in {s["session"] for s in _sessions(replica)}
        assert httpx.delete(f"{replica.http}/sessions/nobody", headers=replica.admin_headers,
                            timeout=10).status_code == 404


def test_a_killed_worker_hands_its_client_to_another_with_nothing_resent(replica):
    client = ClientUnderKill(replica.url, 6.0, VIEWPORT)
    assert client.mid.wait(60), "the client never drew its third selection"
    (mine,) = _sessions(replica)
    holder = mine["worker"]
    client.kill_seq = mine["selections"]
    os.kill(holder, signal.SIGKILL)
    assert client.moved.wait(20), "no new selection was drawn after the kill"
    (now,) = _sessions(replica)
    run = client.join(60)
    assert now["session"] == mine["session"] and now["worker"] != holder
    assert run.errors == [] and len(run.reconnects) == 1, (run.errors, run.reconnects)
    rc = run.reconnects[0]
    assert rc.resumed and rc.session == mine["session"] and rc.resumed_at - rc.lost_at <= 2.0, rc
    assert rc.welcome_held == rc.held > 0 and run.resent == 0
    # The supervisor put a new worker in the dead one's place.
    deadline = time.monotonic() + 60
    seen: set[int] = set()
    while len(seen - {holder}) < 2 and time.monotonic() < deadline:
        with httpx.Client(timeout=10) as http:  # a new connection each time: the kernel picks a worker afresh
            seen.add(http.get(replica.http + "/health").json()["worker"])
        time.sleep(0.05)
    assert len(seen - {holder}) == 2, seen
