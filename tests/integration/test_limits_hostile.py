"""What a hostile or careless client may make a replica hold: real ``walkstream serve``, real sockets.

A connection holds no session slot until its hello and is closed if it says
none in time, however many (refused) frames it sends; refused frames are
counted and end the connection; one address may hold only so many
connections; a frame above the protocol's limit is refused from its header.
Waits are on closes and server-reported state, each bounded; nothing sleeps.
"""

from __future__ import annotations

import time

import httpx
import pytest
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect

from bench.demo import ServerProcess
from proto import PROTOCOL_VERSION
from proto.codec import MAX_CLIENT_FRAME, decode_server, encode
from proto.messages import Error, Hello, Welcome
from server.limits import RateGuard, ReplicaLimits, remote_address

HELLO_TIMEOUT = 1.0


@pytest.fixture(scope="module")
def server(demo_store):
    args = ["--max-sessions", "2", "--hello-timeout", str(HELLO_TIMEOUT), "--max-bad-frames", "4",
            "--max-per-address", "3", "--trusted-proxy", "127.0.0.1"]
    with ServerProcess([demo_store], extra=args) as srv:
        yield srv


def _health(srv) -> dict:
    return httpx.get(srv.http + "/health", timeout=10).json()


def _until_closed(ws, timeout: float = 10.0, poke: bytes | None = None, every: float = 0.2):
    """Messages until the server closes ``ws`` and its close code; ``poke`` is sent every ``every`` s meanwhile."""
    seen = []
    end = time.monotonic() + timeout
    try:
        next_poke = time.monotonic()
        while time.monotonic() < end:
            if poke is not None and time.monotonic() >= next_poke:
                next_poke += every
                try:
                    ws.send(poke)
                except ConnectionClosed:
                    poke = None  # closed: what the server said before closing is still to be read
            try:
                seen.append(decode_server(ws.recv(timeout=max(0.01, min(end, next_poke) - time.monotonic()))))
            except TimeoutError:
                continue
    except ConnectionClosed as exc:
        return seen, exc.rcvd.code if exc.rcvd else 1006
    raise AssertionError(f"not closed within {timeout} s; seen {seen}")


def _hello(**fields) -> bytes:
    return encode(Hello(**{"protocol": PROTOCOL_VERSION, "scene": "demo", "viewport": [64, 64], **fields}))


def _wait_connections(srv, n: int) -> dict:
    for _ in range(3000):
        health = _health(srv)
        if health["connections"] <= n:
            return health
    raise AssertionError(f"still {health}")


def test_no_slot_without_a_hello_and_refused_frames_do_not_keep_one(server):
    _wait_connections(server, 0)
    with connect(server.url, open_timeout=10) as a, connect(server.url, open_timeout=10) as b:
        health = _health(server)
        assert health["connections"] == 2 and health["sessions"] == 0 and health["pending"] == 2
        # Both slots of this replica are free while they idle: a real client gets a session.
        with connect(server.url, open_timeout=10) as good:
            good.send(_hello())
            assert isinstance(decode_server(good.recv(timeout=10)), Welcome)
            assert _health(server)["sessions"] == 1
        began = time.monotonic()
        # One bad byte every 0.5 s (two or three before the timeout): refused frames never count as being heard.
        seen, code = _until_closed(a, poke=b"\xc1", every=0.5)
        waited = time.monotonic() - began
        assert code == 1008 and isinstance(seen[-1], Error) and seen[-1].code == "no_hello"
        assert HELLO_TIMEOUT * 0.5 <= waited < HELLO_TIMEOUT + 3
        seen, code = _until_closed(b)
        assert code == 1008 and seen[-1].code == "no_hello"


def test_refused_frames_past_the_limit_close_the_connection(server):
    _wait_connections(server, 0)
    with connect(server.url, open_timeout=10) as ws:
        ws.send(_hello())
        assert isinstance(decode_server(ws.recv(timeout=10)), Welcome)
        seen, code = _until_closed(ws, poke=b"\xc1", every=0.05)
    codes = [m.code for m in seen if isinstance(m, Error)]
    assert code == 1008 and codes[-1] == "bad_frames" and codes.count("bad_msgpack") == 5


def test_one_address_holds_only_so_many_connections_and_a_trusted_proxy_names_others(server):
    _wait_connections(server, 0)
    held = [connect(server.url, open_timeout=10, legacy=True) for _ in range(3)]
    try:
        with connect(server.url, open_timeout=10) as fourth:
            seen, code = _until_closed(fourth)
        assert code == 1008 and seen[-1].code == "busy" and "127.0.0.1" in seen[-1].message
        # Behind the trusted proxy (here: loopback) each client is its X-Real-IP.
        others = [connect(server.url, open_timeout=10, legacy=True, additional_headers={"X-Real-IP": f"203.0.113.{k}"})
                  for k in range(1, 4)]
        try:
            assert _health(server)["connections"] == 6
        finally:
            for ws in others:
                ws.close()
    finally:
        for ws in held:
            ws.close()


def test_a_frame_above_the_protocol_limit_is_refused_by_the_transport(server):
    _wait_connections(server, 0)
    with connect(server.url, open_timeout=10, max_size=None) as ws:
        ws.send(_hello())
        assert isinstance(decode_server(ws.recv(timeout=10)), Welcome)
        ws.send(b"\x00" * (MAX_CLIENT_FRAME + 1))
        seen, code = _until_closed(ws)
    assert code == 1009
    with connect(server.url, open_timeout=10) as ws:  # and the replica goes on serving
        ws.send(_hello())
        assert isinstance(decode_server(ws.recv(timeout=10)), Welcome)


def test_measurement_solvers_are_refused_unless_allowed(server, demo_store):
    _wait_connections(server, 0)
    with connect(server.url, open_timeout=10) as ws:
        ws.send(_hello(solver="exact"))
        refusal = decode_server(ws.recv(timeout=10))
        assert isinstance(refusal, Error) and refusal.code == "solver_refused" and "exact" in refusal.message
        ws.send(_hello(solver="greedy"))
        assert isinstance(decode_server(ws.recv(timeout=10)), Welcome)
    with ServerProcess([demo_store], extra=["--allow-measurement-solvers", "--docs"], admin_token=None) as srv:
        with connect(srv.url, open_timeout=10) as ws:
            ws.send(_hello(solver="exact"))
            assert isinstance(decode_server(ws.recv(timeout=10)), Welcome)
        schema = httpx.get(srv.http + "/openapi.json", timeout=10).json()
        assert "/health" in schema["paths"] and "/sessions" not in schema["paths"]
        assert not any(p.startswith("/sessions") for p in schema["paths"])


def test_http_on_the_websocket_path_and_no_docs_by_default(server):
    answer = httpx.get(server.http + "/ws", timeout=10)
    assert answer.status_code == 426 and "websocket" in answer.text and "ws://" in answer.text
    assert httpx.get(server.http + "/docs", timeout=10).status_code == 404
    assert httpx.get(server.http + "/openapi.json", timeout=10).status_code == 404


# ----------------------------------------------------------------------------- clock injected


def test_the_byte_bucket_bounds_bytes_beside_messages():
    limits = ReplicaLimits(rate=1000, burst=1000, byte_rate=100_000, byte_burst=MAX_CLIENT_FRAME * 2)
    guard = RateGuard(limits, now=0.0)
    passed = sum(guard.check(k * 0.001, 60_000) == RateGuard.PASS for k in range(1000))  # 60 MB/s for a second
    assert passed <= (2 * MAX_CLIENT_FRAME + 100_000) // 60_000 + 1
    small = RateGuard(limits, now=0.0)
    assert all(small.check(k * 0.01, 200) == RateGuard.PASS for k in range(300))  # within both rates


def test_remote_address_trusts_only_the_named_proxy():
    headers = {"x-real-ip": "198.51.100.7", "x-forwarded-for": "10.0.0.1, 198.51.100.8"}
    assert remote_address("127.0.0.1", headers, ()) == "127.0.0.1"
    assert remote_address("127.0.0.1", headers, ("127.0.0.1",)) == "198.51.100.7"
    assert remote_address("127.0.0.1", {"x-forwarded-for": "10.0.0.1, 198.51.100.8"}, ("127.0.0.1",)) == "198.51.100.8"
    assert remote_address("127.0.0.1", {"x-real-ip": "not an address"}, ("127.0.0.1",)) == "127.0.0.1"
    with pytest.raises(ValueError):
        ReplicaLimits(trusted_proxies=("proxy.example",))
    with pytest.raises(ValueError):
        ReplicaLimits(inbox_bytes=10)


def test_a_trusted_proxy_may_be_a_network():
    assert remote_address("172.18.0.5", {"x-real-ip": "198.51.100.9"}, ("172.16.0.0/12",)) == "198.51.100.9"
    assert remote_address("10.1.0.5", {"x-real-ip": "198.51.100.9"}, ("172.16.0.0/12",)) == "10.1.0.5"


def test_a_resume_into_another_scene_is_refused_and_the_state_kept(demo_store, auditorium_store):
    from proto.messages import Ack, Camera, Delta, Ping, Pong, Resume
    from server.scene.inspect import inspect_store
    from server.scene.store import SceneStore

    with SceneStore.open(demo_store) as store:
        start = dict(store.index.start)
    with ServerProcess([demo_store, auditorium_store], admin_token=None) as srv:
        for shown in httpx.get(srv.http + "/scenes", timeout=10).json():  # counted as `inspect` counts
            path = demo_store if shown["name"] == "demo" else auditorium_store
            assert shown["triangles_full_detail"] == inspect_store(path)["triangles_full_detail"]
        with connect(srv.url, open_timeout=10) as ws:
            ws.send(_hello())
            welcome = decode_server(ws.recv(timeout=10))
            ws.send(encode(Camera(t=0.0, **start)))
            while True:  # until a delta is acked: the replica has saved the state
                msg = decode_server(ws.recv(timeout=15))
                if isinstance(msg, Ping):
                    ws.send(encode(Pong(id=msg.id, sent=msg.sent, t=0.1)))
                if isinstance(msg, Delta):
                    ws.send(encode(Ack(seq=msg.seq, t=0.2)))
                    break
        ask = Resume(session=welcome.session, token=welcome.token)
        with connect(srv.url, open_timeout=10) as ws:
            ws.send(_hello(scene="auditorium", resume=ask))
            refusal = decode_server(ws.recv(timeout=10))
            assert isinstance(refusal, Error) and refusal.code == "bad_state"
            assert "'demo'" in refusal.message and "'auditorium'" in refusal.message
            ws.send(_hello(scene="demo", resume=ask))  # the saved state was kept: the right scene resumes it
            again = decode_server(ws.recv(timeout=10))
            assert isinstance(again, Welcome) and again.resumed and again.session == welcome.session


def test_admission_counts_connections_and_reconnects_per_address():
    from server.limits import Admission

    admission = Admission(ReplicaLimits(max_sessions=4, max_per_address=2, connect_rate=1.0, connect_burst=3,
                                        max_pending=10))
    assert admission.admit("a", 0.0, 0, 0) is None and admission.admit("a", 0.0, 0, 1) is None
    assert admission.admit("a", 0.0, 0, 2)[0] == "address"  # two open: the third is refused ...
    assert admission.admit("b", 0.0, 0, 2) is None  # ... another address is not
    admission.release("a")
    assert admission.admit("a", 0.0, 0, 2)[0] == "connect_rate"  # three opened at once: the burst is spent
    assert admission.admit("a", 1.0, 0, 2) is None  # a second later, one more
    assert admission.admit("c", 1.0, 4, 0)[0] == "busy" and admission.admit("c", 1.0, 0, 10)[0] == "pending"


# ----------------------------------------------------------------------------- bytes waiting


def _raw_client(url: str, rcvbuf: int):
    """A websocket over a socket that reads nothing after the handshake (``rcvbuf`` bytes of receive buffer):
    (socket, sans-I/O protocol)."""
    import socket as socketlib

    from websockets.client import ClientProtocol
    from websockets.http11 import Response
    from websockets.uri import parse_uri

    uri = parse_uri(url)
    sock = socketlib.socket()
    sock.setsockopt(socketlib.SOL_SOCKET, socketlib.SO_RCVBUF, rcvbuf)
    sock.connect((uri.host, uri.port))
    sock.settimeout(10)
    proto = ClientProtocol(uri, max_size=None)
    proto.send_request(proto.connect())
    sock.sendall(b"".join(proto.data_to_send()))
    while not any(isinstance(e, Response) for e in proto.events_received()):
        data = sock.recv(256)  # the response's bytes only, as far as they come before the server's frames
        assert data, "the server closed during the handshake"
        proto.receive_data(data)
    assert proto.handshake_exc is None, proto.handshake_exc
    return sock, proto


def test_bytes_waiting_for_a_busy_session_stay_bounded_and_tcp_pushes_back(demo_store):
    """A client that never reads (its session blocks sending its first delta) and sends frames within the
    byte rate: the server reads at most ``inbox_bytes`` (256 KiB) ahead of its session, then stops reading
    that socket; a good client beside it is served."""
    import socket as socketlib

    from proto.messages import Camera
    from server.scene.store import SceneStore

    with SceneStore.open(demo_store) as store:
        start = dict(store.index.start)
    bound = ReplicaLimits().inbox_bytes
    frame = b"\x00" * (60 * 1024)
    with ServerProcess([demo_store], extra=["--send-buffer", "8192"]) as srv:
        sock, proto = _raw_client(srv.url, rcvbuf=4096)
        try:
            proto.send_binary(_hello(viewport=[640, 360]))
            proto.send_binary(encode(Camera(t=0.0, **start)))
            sock.sendall(b"".join(proto.data_to_send()))

            def row() -> dict:
                rows = httpx.get(srv.http + "/sessions", headers=srv.admin_headers, timeout=10).json()
                assert len(rows) == 1, rows
                return rows[0]

            for _ in range(3000):  # until the session is stuck sending its first delta to a client that reads none
                if row()["send_wait_s"] > 0.2:
                    break
            else:
                raise AssertionError(f"the session never blocked in a send: {row()}")
            sent = 0
            seen: list[dict] = []
            pushed_back = False
            end = time.monotonic() + 60
            next_send = time.monotonic()
            while time.monotonic() < end:
                if time.monotonic() >= next_send:  # 240 KiB/s: within the byte rate, so none is dropped
                    next_send += 0.25
                    proto.send_binary(frame)
                    out = b"".join(proto.data_to_send())
                    sock.settimeout(0.2)
                    try:
                        sock.sendall(out)
                        sent += len(frame)
                    except (socketlib.timeout, TimeoutError):
                        pushed_back = True  # the server's kernel buffer is full: TCP pushes back
                        break
                seen.append(row())
                assert seen[-1]["waiting_bytes"] <= bound, seen[-1]
                if seen[-1]["reads_paused"] >= 1 and sent >= 2 * bound:
                    break
            last = seen[-1]
            assert last["reads_paused"] >= 1, (sent, last)
            assert last["send_wait_s"] > 0 and last["selections"] <= 1, last  # still in its first delta's send
            assert max(r["waiting_bytes"] for r in seen) > bound - len(frame), "the bound was never approached"
            assert pushed_back or sent >= 2 * bound
            # A good client beside it: welcomed and sent its first delta.
            with connect(srv.url, open_timeout=10, max_size=None) as good:
                good.send(_hello())
                assert isinstance(decode_server(good.recv(timeout=10)), Welcome)
        finally:
            sock.close()
