"""Fault tests against the real scale-out topology: Redis, two replicas, nginx, the real headless client.

Needs Debian's ``redis-server`` and ``nginx`` (``scripts/bootstrap.sh`` installs them); without them these
tests FAIL, they do not skip: the topology is part of the product. The cluster is ``bench.cluster.Cluster``,
running ``deploy/nginx.conf`` — the file docker-compose.yml mounts.

The issue asks for ``tc netem`` in a network namespace. This machine's kernel has namespaces but no
``sch_netem`` (``tc qdisc add ... netem`` fails: "qdisc kind unknown"), so latency, jitter, loss and cuts
come from ``bench.netem.DelayProxy``, a relay on loopback between the client and nginx.
"""

from __future__ import annotations

import os
import random
import socket
import threading
import time

import httpx
import numpy as np
import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st
from websockets.sync.client import connect

from bench.cluster import NGINX_TEMPLATE, Cluster, ClusterError, find_binary, render_nginx_conf
from bench.demo import WARMUP_S, summarize
from bench.netem import DelayProxy, Link, netem_available
from client.app import run_client

from .killed import ClientUnderKill
from proto import PROTOCOL_VERSION
from proto.codec import decode_server, encode
from proto.messages import Camera, Delta, Hello, Resume, Welcome

ROOT = NGINX_TEMPLATE.parents[1]
VIEWPORT = (320, 180)


@pytest.fixture(scope="module")
def native_parts() -> None:
    """Fail (not skip) with the fix when the native parts of the topology are missing."""
    for name in ("redis-server", "nginx"):
        try:
            find_binary(name)
        except ClusterError as exc:
            pytest.fail(str(exc))


@pytest.fixture(scope="module")
def cluster(native_parts, demo_store, auditorium_store):
    with Cluster([demo_store, auditorium_store], replicas=2, tau=0.5) as c:
        yield c


@pytest.fixture
def echo_server():
    """A TCP echo server on loopback (the far end of the proxy in the proxy's own tests)."""
    srv = socket.create_server(("127.0.0.1", 0))
    conns: list[socket.socket] = []

    def serve() -> None:
        while True:
            try:
                conn, _ = srv.accept()
            except OSError:
                return
            conns.append(conn)
            threading.Thread(target=echo, args=(conn,), daemon=True).start()

    def echo(conn: socket.socket) -> None:
        try:
            while data := conn.recv(65536):
                conn.sendall(data)
        except OSError:
            pass
        finally:
            conn.close()

    threading.Thread(target=serve, daemon=True).start()
    yield srv.getsockname()[1]
    srv.close()
    for c in conns:
        c.close()


def _rtt(sock: socket.socket) -> float:
    t0 = time.perf_counter()
    sock.sendall(b"p")
    assert sock.recv(16) == b"p"
    return time.perf_counter() - t0


# ---------------------------------------------------------------------------------------- the topology's files


def test_compose_describes_the_topology_the_tests_start():
    compose = yaml.safe_load((ROOT / "docker-compose.yml").read_text())
    services = compose["services"]
    servers = sorted(name for name in services if name.startswith("server"))
    assert {"redis", "nginx"} <= set(services) and len(servers) == 2
    assert services["redis"]["image"].startswith("redis:7")
    nginx = services["nginx"]
    assert "./deploy/nginx.conf:/etc/nginx/nginx.conf:ro" in nginx["volumes"] and "8080:80" in nginx["ports"]
    template = NGINX_TEMPLATE.read_text()
    for name in servers:
        svc = services[name]
        command = " ".join(svc["command"])
        assert "walkstream serve /data/*.db" in command and "--port 8765" in command
        assert "--redis redis://redis:6379/0" in command and "--replica" in command
        assert "WALKSTREAM_ADMIN_TOKEN" in svc["environment"] and "/health" in " ".join(svc["healthcheck"]["test"])
        assert f"server {name}:8765 " in template  # nginx's upstream names every replica compose starts
    assert template.count("server server") == len(servers)
    assert (ROOT / "deploy" / "Dockerfile").read_text().startswith("# A walkstream server replica")

    # The tests' nginx runs the same file, with only addresses, ports, paths, user and workers rewritten.
    rendered = render_nginx_conf(template, ["127.0.0.1:1001", "127.0.0.1:1002"], 1234, ROOT / "tmp")
    for directive in ("hash $arg_client consistent;", "proxy_http_version 1.1;", "proxy_set_header Upgrade $http_upgrade;",
                      "proxy_set_header Connection $connection_upgrade;", "proxy_next_upstream error timeout;",
                      "proxy_read_timeout 1h;", "proxy_buffering off;"):
        assert directive in template and directive in rendered
    assert "server 127.0.0.1:1001 max_fails=1 fail_timeout=10s;" in rendered and "listen 127.0.0.1:1234;" in rendered
    assert "server1" not in rendered and "/var/" not in rendered


# ---------------------------------------------------------------------------------------- the delaying proxy


@settings(max_examples=200, deadline=None)
@given(
    gaps=st.lists(st.floats(0.0, 0.05), min_size=1, max_size=60),
    latency=st.floats(0.0, 0.1),
    jitter_frac=st.floats(0.0, 1.0),
    loss=st.sampled_from([0.0, 0.01, 0.3, 1.0]),
    seed=st.integers(0, 2**32 - 1),
)
def test_link_keeps_order_and_delays_within_its_bounds(gaps, latency, jitter_frac, loss, seed):
    link = Link(latency, latency * jitter_frac, loss, rto=0.2, seed=seed)
    arrivals = np.cumsum(gaps)
    delivered = np.array([link.deliver_at(float(t)) for t in arrivals])
    assert np.all(np.diff(delivered) >= 0)  # TCP never reorders
    assert np.all(delivered >= arrivals + latency - link.jitter - 1e-12)
    # No chunk waits longer than the slowest chunk up to it (its own bad luck or a lost one ahead of it).
    worst = np.maximum.accumulate(arrivals) + latency + link.jitter + 0.2
    assert np.all(delivered <= worst + 1e-12)
    if loss == 1.0:
        assert link.lost == len(gaps) and np.all(delivered >= arrivals + latency - link.jitter + 0.2 - 1e-12)


def test_netem_is_probed_not_assumed():
    """The kernel here lacks sch_netem: the probe says so (and cleans up its namespace) rather than crashing."""
    available = netem_available()
    assert isinstance(available, bool)
    import subprocess

    names = subprocess.run(["ip", "netns", "list"], capture_output=True, text=True).stdout
    assert "walkstream-probe" not in names


def test_proxy_adds_the_latency_and_loss_it_claims(echo_server):
    with DelayProxy("127.0.0.1", echo_server, latency=0.03) as proxy:
        with socket.create_connection(("127.0.0.1", proxy.port)) as s:
            s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            rtts = [_rtt(s) for _ in range(5)]
        assert 0.06 <= min(rtts) and max(rtts) < 0.06 + 0.03, rtts  # one way 30 ms, each way
        assert proxy.bytes_up == proxy.bytes_down == 5
    with DelayProxy("127.0.0.1", echo_server, latency=0.01, loss=1.0, rto=0.05) as proxy:
        with socket.create_connection(("127.0.0.1", proxy.port)) as s:
            rtt = _rtt(s)
        assert 2 * (0.01 + 0.05) <= rtt < 2 * (0.01 + 0.05) + 0.05 and proxy.lost >= 2  # one RTO each way


def test_proxy_relays_every_byte_in_order_through_jitter_and_loss(echo_server):
    rng = random.Random(7)
    payload = bytes(rng.getrandbits(8) for _ in range(300_000))
    with DelayProxy("127.0.0.1", echo_server, latency=0.005, jitter=0.005, loss=0.05, rto=0.02, seed=1,
                    chunk=4096) as proxy:
        with socket.create_connection(("127.0.0.1", proxy.port)) as s:
            got = bytearray()

            def read() -> None:
                while len(got) < len(payload):
                    data = s.recv(65536)
                    if not data:
                        return
                    got.extend(data)

            reader = threading.Thread(target=read)
            reader.start()
            for i in range(0, len(payload), 3000):  # many small writes: many chunks, each delayed on its own
                s.sendall(payload[i:i + 3000])
            reader.join(30)
        assert bytes(got) == payload
        assert proxy.lost > 0 and proxy.bytes_up == proxy.bytes_down == len(payload)


def test_proxy_cut_resets_both_sides_and_restore_heals(echo_server):
    with DelayProxy("127.0.0.1", echo_server, latency=0.001) as proxy:
        s = socket.create_connection(("127.0.0.1", proxy.port))
        _rtt(s)
        assert proxy.wait_for(lambda p: p.connections == 1, 5)
        assert proxy.cut() == 1 and proxy.connections == 0
        with pytest.raises(OSError):  # the relayed connection is gone: reset, as a dead path leaves it
            s.sendall(b"x")
            if not s.recv(16):
                raise ConnectionResetError("closed")
        s.close()
        with pytest.raises(OSError):  # and new ones are refused while cut
            with socket.create_connection(("127.0.0.1", proxy.port)) as s2:
                s2.sendall(b"x")
                if not s2.recv(16):
                    raise ConnectionResetError("closed")
        assert proxy.refused >= 1
        proxy.restore()
        with socket.create_connection(("127.0.0.1", proxy.port)) as s3:
            assert _rtt(s3) < 1.0
        assert proxy.accepted == 2


# ---------------------------------------------------------------------------------------- the cluster


def test_nginx_keeps_a_client_on_one_replica_and_spreads_clients(cluster):
    routes = {f"client-{k}": cluster.route(f"client-{k}") for k in range(16)}
    assert set(routes.values()) == {0, 1}  # both replicas serve
    for client, i in list(routes.items())[:6]:
        assert cluster.route(client) == i  # and a client always lands on the same one
        health = httpx.get(cluster.http + "/health", params={"client": client}, timeout=10).json()
        assert health["replica"] == f"r{i}" and health["status"] == "ok"
    with connect(cluster.url + "?client=client-0", max_size=None) as ws:  # websocket upgrade through nginx
        ws.send(encode(Hello(protocol=PROTOCOL_VERSION, scene="demo", viewport=list(VIEWPORT))))
        welcome = decode_server(ws.recv(timeout=10))
        assert isinstance(welcome, Welcome)
        assert cluster.which(welcome.session) == routes["client-0"]


def _open_and_get_a_delta(url: str, start: dict, resume: Resume | None = None) -> tuple[Welcome, list[Delta]]:
    with connect(url, max_size=None) as ws:
        ws.send(encode(Hello(protocol=PROTOCOL_VERSION, scene="demo", viewport=list(VIEWPORT), predict=False,
                             morph=False, resume=resume)))
        welcome = decode_server(ws.recv(timeout=10))
        assert isinstance(welcome, Welcome), welcome
        ws.send(encode(Camera(t=0.0, **start)))
        deltas = []
        while not deltas:
            msg = decode_server(ws.recv(timeout=10))
            if isinstance(msg, Delta):
                deltas.append(msg)
    return welcome, deltas


def test_a_session_saved_by_one_replica_resumes_on_the_other(cluster, demo_store):
    """(d) Two replicas, one Redis: what r0 saved, r1 loads."""
    import redis

    from server.scene.store import SceneStore

    with SceneStore.open(demo_store) as store:
        start = store.index.start
    r = redis.Redis.from_url(cluster.redis_url)
    r.config_set("notify-keyspace-events", "K$")  # tell us when a session's state is written
    events = r.pubsub()
    events.psubscribe("__keyspace@0__:walkstream:session:*")
    events.get_message(timeout=5)  # the subscription's confirmation
    first, deltas = _open_and_get_a_delta(cluster.replicas[0].url, start)
    assert first.token and not first.resumed and deltas[0].add
    key = f"walkstream:session:{first.session}"
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline:  # wait for the save after the delta (and on disconnect)
        msg = events.get_message(timeout=max(0.0, deadline - time.monotonic()))
        if msg and msg["type"] == "pmessage" and msg["channel"].decode().endswith(first.session):
            break
    assert r.exists(key), f"replica r0 saved nothing under {key}"
    events.close()

    again, _ = _open_and_get_a_delta(cluster.replicas[1].url, start, Resume(session=first.session, token=first.token))
    assert again.resumed and again.session == first.session
    # A wrong token is not a resume, on any replica.
    stranger, _ = _open_and_get_a_delta(cluster.replicas[1].url, start,
                                        Resume(session=first.session, token="x" * len(first.token)))
    assert not stranger.resumed and stranger.session != first.session
    r.close()


def _after(run, t0: float) -> list:
    return [f for f in run.frames if f.t > t0 and f.seq >= 0]


def test_a_dropped_connection_resumes_without_resending(cluster):
    """(b) Cut every connection between client and nginx, keep it cut until the client has redialled, restore."""
    with DelayProxy("127.0.0.1", cluster.port) as proxy:
        mid = threading.Event()

        def on_frame(rec) -> None:
            if rec.seq >= 3:
                mid.set()

        result: dict = {}
        worker = threading.Thread(target=lambda: result.update(run=run_client(
            f"ws://127.0.0.1:{proxy.port}/ws", "demo", duration=4.0, viewport=VIEWPORT, target_frame_time=0.05,
            on_frame=on_frame, reconnect_timeout=10.0)))
        worker.start()
        assert mid.wait(60), "the client never drew its third selection"
        assert proxy.cut() >= 1
        assert proxy.wait_for(lambda p: p.refused >= 1, 10), "the client did not redial"
        proxy.restore()
        worker.join(60)
    run = result["run"]
    assert run.errors == [] and len(run.reconnects) == 1, (run.errors, run.reconnects)
    rc = run.reconnects[0]
    assert rc.resumed and rc.session == run.welcome.session and rc.welcome_held == rc.held > 0
    assert run.resent == 0
    later = _after(run, rc.resumed_at)  # and it drew new selections after the resume
    assert len(later) >= 3 and max(f.seq for f in later) > max(f.seq for f in run.frames if f.t <= rc.lost_at)


def test_the_frame_budget_holds_over_a_slow_lossy_network(cluster):
    """(c) 40 ± 10 ms each way and 1 % loss (RTO 200 ms) between client and nginx: p95 ≤ 1.20 × target.

    ``tc netem`` is unavailable on this kernel (no sch_netem), so ``DelayProxy`` adds the delay and loss.
    The auditorium (2.5 M triangles in full, several times any budget on llvmpipe) binds at 640×360 and
    40 ms: the test checks that the selection was held by the budget (the median selection predicted at
    least 60 % of it), then that the frames kept to it.

    The server aims its 95th-percentile frame at the target (the cost model's tail ratio), so the bound
    is the spread of that aim, not a margin under it: without the client's governor, the p95 of 12 s of
    frames on this shared 2-core machine spread from 0.9 to 1.15 × target between identical runs.
    """
    target = 0.04
    with DelayProxy("127.0.0.1", cluster.port, latency=0.04, jitter=0.01, loss=0.01, seed=11) as proxy:
        run = run_client(f"ws://127.0.0.1:{proxy.port}/ws", "auditorium", duration=12.0, viewport=(640, 360),
                         target_frame_time=target)
        relayed, connections = proxy.bytes_down, proxy.accepted
    assert run.errors == [] and run.reconnects == []
    assert connections == 1 and relayed > 100_000  # everything came through the bad network
    summary = summarize(run, target)  # frames after the warm-up (WARMUP_S), drawn ones only
    assert summary.frames >= 30, summary
    frames = [f for f in run.frames if f.t >= WARMUP_S and f.seq >= 0]
    held = np.median([f.predicted_cost / f.budget for f in frames])
    assert held >= 0.6, (f"the selection was not held by the budget (predicted / budget {held:.2f}): nothing tested",
                         summary)
    load = os.getloadavg()[0]
    print(f"slow lossy: p95 {summary.p95_ms:.1f} ms, mean {summary.mean_ms:.1f} ms, max {summary.max_ms:.1f} ms")
    assert summary.p95_ms <= 1.20 * target * 1e3, (
        f"p95 {summary.p95_ms:.1f} ms > 1.20 × {target * 1e3:.0f} ms (mean {summary.mean_ms:.1f} ms, max "
        f"{summary.max_ms:.1f} ms; load average {load:.1f} on {os.cpu_count()} cores)")


def test_the_load_test_drives_the_cluster_and_sums_its_replicas(cluster):
    """``walkstream loadtest --url`` through nginx, ``--metrics`` naming each replica: the sessions of both
    replicas are counted, and so is the CPU of both (each replica's walkstream_cpu_seconds)."""
    from bench.loadtest.run import run_loadtest

    url = cluster.http.replace("http://", "ws://") + "/ws"
    s = run_loadtest(url=url, metrics=[r.http for r in cluster.replicas], scene="demo", clients=6, duration=5.0,
                     ramp=1.0, reference=0, admin_headers={"Authorization": f"Bearer {cluster.admin_token}"})
    assert s.sessions_opened == 6 and s.errors == {} and s.server_errors == {}
    assert s.mirror_checks and s.mirror_mismatch == 0  # the sessions of both replicas, from both /sessions
    assert s.server_cpu_s is not None and s.server_cpu_s > 0 and s.selections_due_share > 0.5


def test_a_killed_replica_hands_its_client_to_the_other_within_2s(cluster):
    """(a) SIGKILL the replica serving a client mid-session: it resumes on the other, nothing re-sent.

    Runs last: it leaves the cluster with one replica.
    """
    client = ClientUnderKill(cluster.url, 5.0, VIEWPORT)
    assert client.mid.wait(60), "the client never drew its third selection"
    # Ours is the newest session (earlier tests' connections may still be winding down).
    holder, mine = min(((i, s) for i, ss in cluster.sessions().items() for s in ss), key=lambda x: x[1]["connected_s"])
    session = mine["session"]
    client.kill_seq = mine["selections"]
    cluster.kill(holder)
    assert client.moved.wait(20), "no new selection was drawn after the kill"
    survivor = cluster.which(session)
    run = client.join(60)
    assert survivor == 1 - holder
    assert run.errors == [] and len(run.reconnects) == 1, (run.errors, run.reconnects)
    rc = run.reconnects[0]
    assert rc.resumed and rc.session == session and rc.resumed_at - rc.lost_at <= 2.0, rc
    assert rc.welcome_held == rc.held > 0 and run.resent == 0
    later = _after(run, rc.resumed_at)
    assert len(later) >= 3 and max(f.seq for f in later) > client.kill_seq
