"""A kiosk's side of the heartbeat protocol over a real websocket: hello, then a heartbeat every interval.

It draws nothing: ``frames`` advance by ``fps × interval`` per heartbeat while ``drawing`` is set. The
fleet tests stop its frames (``drawing.clear()``: a renderer that hangs while the process reports) or its
heartbeats (``beating.clear()``: a process that stopped, though its socket still answers pings), and watch
the server's fleet page notice. The real kiosk's SIGSTOP test polls ``/fleet.json`` the same way:
``kiosks[i]["stale"]`` for the row whose ``"kiosk"`` is its id.
"""

from __future__ import annotations

import threading
import time

from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect

from proto import PROTOCOL_VERSION
from proto.codec import decode_server, encode
from proto.messages import Error, Heartbeat, Hello, Ping, Pong, Welcome


class KioskStub:
    """A session that says hello on ``scene`` and reports as kiosk ``kiosk`` every ``interval`` seconds
    (in a thread of its own, which also answers the server's pings); ``close()`` ends it."""

    def __init__(self, url: str, kiosk: str, *, interval: float = 0.5, scene: str = "demo", fps: float = 60.0,
                 tour: str = "", stop: int = -1) -> None:
        self.kiosk, self.interval, self.fps, self.tour, self.stop = kiosk, interval, fps, tour, stop
        self.drawing, self.beating = threading.Event(), threading.Event()
        self.drawing.set()
        self.beating.set()
        self.frames = 0
        self.sent = 0
        self.errors: list[Error] = []
        self._t0 = time.monotonic()
        self._end = threading.Event()
        self.ws = connect(url, max_size=None, open_timeout=10, compression=None, legacy=True)
        self.ws.send(encode(Hello(protocol=PROTOCOL_VERSION, scene=scene, viewport=[320, 180])))
        while True:
            msg = decode_server(self.ws.recv(timeout=15))
            if isinstance(msg, Welcome):
                self.welcome = msg
                break
            if isinstance(msg, Error):
                raise AssertionError(f"the server refused the hello: {msg}")
        self._thread = threading.Thread(target=self._run, name=f"kiosk-{kiosk}", daemon=True)
        self._thread.start()

    @property
    def session(self) -> str:
        return self.welcome.session

    def heartbeat(self, **override) -> Heartbeat:
        """The heartbeat this kiosk would send now."""
        n = self.sent
        fields = dict(kiosk=self.kiosk, t=time.monotonic() - self._t0, interval=self.interval, state="attract",
                      frames=self.frames, fps=self.fps if self.drawing.is_set() else 0.0,
                      frame_p95=0.018 + 0.001 * (n % 5), recent=[0.015 + 0.001 * ((n + i) % 7) for i in range(12)],
                      rss=(200 << 20) + n * 4096, gpu_memory=None, cache_bytes=(32 << 20) + n, reconnects=1,
                      tour=self.tour, stop=self.stop)
        return Heartbeat(**{**fields, **override})

    def _run(self) -> None:
        due = time.monotonic()
        try:
            while not self._end.is_set():
                now = time.monotonic()
                if now >= due:
                    due = now + self.interval
                    if self.drawing.is_set():
                        self.frames += int(self.fps * self.interval)
                    if self.beating.is_set():
                        self.ws.send(encode(self.heartbeat()))
                        self.sent += 1
                try:
                    msg = decode_server(self.ws.recv(timeout=max(0.01, min(0.1, due - time.monotonic()))))
                except TimeoutError:
                    continue
                if isinstance(msg, Ping):
                    self.ws.send(encode(Pong(id=msg.id, sent=msg.sent, t=time.monotonic() - self._t0)))
                elif isinstance(msg, Error):
                    self.errors.append(msg)
        except ConnectionClosed:
            pass

    def close(self) -> None:
        self._end.set()
        self._thread.join(10)
        self.ws.close()

    def __enter__(self) -> "KioskStub":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
