"""The systemd watchdog is fed only while frames advance; over a real notify socket, as systemd would receive it."""

from __future__ import annotations

import os
import shutil
import socket
import tempfile
import uuid
from pathlib import Path
from typing import Iterator

import pytest
from hypothesis import given
from hypothesis import strategies as st

from client.kiosk.watchdog import EXTEND_S, Watchdog


class NotifySocket:
    """A unix datagram socket bound where systemd's would be, collecting what arrives (as systemd does)."""

    def __init__(self, address: str) -> None:
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind("\0" + address[1:] if address.startswith("@") else address)
        self.sock.setblocking(False)
        self.address = address

    def received(self) -> list[dict[str, str]]:
        """Every datagram sent since the last call, each as its KEY=value lines (datagrams are queued at once)."""
        out = []
        while True:
            try:
                data = self.sock.recv(4096)
            except BlockingIOError:
                return out
            out.append(dict(line.split("=", 1) for line in data.decode().split("\n")))

    def close(self) -> None:
        self.sock.close()


@pytest.fixture
def notify_socket(monkeypatch) -> Iterator[NotifySocket]:
    folder = tempfile.mkdtemp(prefix="sdn")  # short: a unix socket's path has ~100 bytes
    sock = NotifySocket(str(Path(folder) / "notify"))
    monkeypatch.setenv("NOTIFY_SOCKET", sock.address)
    monkeypatch.setenv("WATCHDOG_USEC", "2000000")  # WatchdogSec=2: a ping at most every second
    monkeypatch.setenv("WATCHDOG_PID", str(os.getpid()))
    yield sock
    sock.close()
    shutil.rmtree(folder, ignore_errors=True)


def test_frames_advancing_feed_the_watchdog_and_stalled_frames_do_not(notify_socket: NotifySocket) -> None:
    dog = Watchdog.from_environ()
    assert dog.enabled and dog.interval == 1.0

    dog.frame(0, 0.0)  # nothing drawn yet: not ready
    assert notify_socket.received() == []
    dog.frame(1, 0.1, state="attract", fps=20.0)
    (ready,) = notify_socket.received()
    assert ready["READY"] == "1" and ready["WATCHDOG"] == "1" and ready["STATUS"].startswith("attract, 20.0 fps")

    for i in range(2, 60):  # 20 fps for ~3 s: a ping each second, no more
        dog.frame(i, 0.1 + 0.05 * (i - 1), state="attract", fps=20.0)
    pings = notify_socket.received()
    assert [m.get("WATCHDOG") for m in pings] == ["1", "1"]

    dog.frame(59, 4.0, state="attract", fps=20.0)  # the frames drawn since the last ping are still owed one
    assert [m.get("WATCHDOG") for m in notify_socket.received()] == ["1"]
    for k in range(1, 101):  # the frame counter stops: 10 s without a ping, however often frame() is called
        dog.frame(59, 4.0 + 0.1 * k, state="attract", fps=0.0)
    assert notify_socket.received() == []

    dog.frame(60, 14.1, state="attract", fps=20.0)  # frames advance again: fed at once
    assert [m.get("WATCHDOG") for m in notify_socket.received()] == ["1"]

    dog.stopping()
    assert notify_socket.received() == [{"STOPPING": "1", "STATUS": "stopping"}]


def test_an_abstract_notify_socket_works_too(monkeypatch) -> None:
    sock = NotifySocket(f"@walkstream-test-{uuid.uuid4().hex}")
    try:
        monkeypatch.setenv("NOTIFY_SOCKET", sock.address)
        monkeypatch.delenv("WATCHDOG_USEC", raising=False)
        dog = Watchdog.from_environ()
        assert dog.enabled and dog.interval is None  # no WatchdogSec: ready and status, never a ping
        dog.frame(1, 0.0)
        for i in range(2, 50):
            dog.frame(i, float(i))
        assert sock.received() == [{"READY": "1", "STATUS": "drawing"}]
    finally:
        sock.close()


def test_waiting_for_a_server_extends_the_start_timeout_until_the_first_frame(notify_socket: NotifySocket) -> None:
    dog = Watchdog.from_environ()
    for k in range(61):  # dialling for a minute, a call a second
        dog.waiting(float(k), "connecting to ws://server/ws")
    extended = notify_socket.received()
    assert len(extended) == 61 // int(EXTEND_S / 2) + 1  # at most every EXTEND_S / 2
    assert all(m["EXTEND_TIMEOUT_USEC"] == str(int(EXTEND_S * 1e6)) for m in extended)
    dog.frame(1, 61.0)
    assert "READY" in notify_socket.received()[0]
    assert dog.waiting(200.0, "connecting") is None and notify_socket.received() == []


def test_outside_systemd_nothing_is_sent(monkeypatch) -> None:
    monkeypatch.delenv("NOTIFY_SOCKET", raising=False)
    dog = Watchdog.from_environ()
    assert not dog.enabled
    assert dog.frame(1, 0.0) is None and dog.waiting(0.0, "x") is None and dog.stopping() is None


def test_a_watchdog_meant_for_another_process_is_not_fed(monkeypatch) -> None:
    env = {"NOTIFY_SOCKET": "/nonexistent/notify", "WATCHDOG_USEC": "2000000", "WATCHDOG_PID": "1"}
    assert Watchdog.from_environ(env, pid=4242).interval is None
    assert Watchdog.from_environ(env, pid=1).interval == 1.0


@given(st.floats(0.05, 5.0), st.lists(st.tuples(st.integers(0, 3), st.floats(0.001, 2.0)), min_size=1,
                                      max_size=200))
def test_a_ping_goes_out_exactly_when_frames_advanced_and_the_interval_passed(interval: float, steps) -> None:
    sent: list[str] = []
    dog = Watchdog(sent.append, interval)
    frames, now = 0, 0.0
    last = None  # (frames, time) of the last ping
    for more, dt in steps:
        frames, now = frames + more, now + dt
        before = len(sent)
        dog.frame(frames, now)
        pinged = len(sent) > before and "WATCHDOG=1" in sent[-1].split("\n")
        if last is None:
            assert pinged == (frames > 0)  # the first frame: READY with its ping
            if frames > 0:
                assert sent[-1].split("\n")[0] == "READY=1"
        else:
            assert pinged == (frames > last[0] and now - last[1] >= interval)
        if pinged:
            last = (frames, now)
    assert sum("READY=1" in m for m in sent) == (1 if frames > 0 else 0)
    assert dog.pings == sum("WATCHDOG=1" in m for m in sent)


def test_a_state_change_updates_the_status_without_feeding_the_watchdog() -> None:
    sent: list[str] = []
    dog = Watchdog(sent.append, 10.0)
    dog.frame(1, 0.0, state="attract", fps=20.0)
    dog.frame(1, 0.5, state="reconnecting", fps=20.0)
    assert sent[-1] == "STATUS=reconnecting, 20.0 fps, 1 frames"
    dog.frame(1, 0.6, state="reconnecting", fps=20.0)
    assert len(sent) == 2 and dog.pings == 1


@pytest.mark.parametrize("kw, field", [({"interval": 0.0}, "interval"), ({"interval": float("nan")}, "interval"),
                                       ({"interval": 1.0, "extend": -1.0}, "extend")])
def test_bad_settings_are_refused_naming_the_field(kw: dict, field: str) -> None:
    with pytest.raises(ValueError, match=f"^{field}: "):
        Watchdog(None, **kw)
