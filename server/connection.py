"""One websocket's side of the service: the connection's controls and the task that reads its frames.

The reader stamps, counts and rate-limits each incoming frame and queues it for
the session loop (``server.app``). What waits is bounded twice: in messages by
the inbox's length, and in bytes by ``ReplicaLimits.inbox_bytes`` — past that
the reader stops taking frames from the transport, uvicorn stops reading the
socket, and TCP pushes back on a sender that outpaces its session. A frame the
rate or byte bucket refuses is dropped here, never queued.
"""

from __future__ import annotations

import asyncio
import time
from collections import deque

from fastapi import WebSocket, WebSocketDisconnect

from proto.errors import ERROR_CODES
from proto.messages import Error

from .limits import RateGuard, ReplicaLimits
from .metrics import Metrics
from .session import Session

__all__ = ["Connection", "Inbox", "read_frames", "error", "SOCKET_GONE", "GONE", "WAKE", "CLOSE_POLICY"]

#: The inbox's markers: the socket ended; wake the loop (a close was requested).
GONE = object()
WAKE = object()

CLOSE_POLICY = 1008
#: What a send or receive on a socket that went away raises.
SOCKET_GONE = (WebSocketDisconnect, RuntimeError, OSError)


def error(code: str, detail: str = "") -> Error:
    return Error(code=code, message=detail or ERROR_CODES[code])


class Inbox:
    """A bounded queue between a connection's reader and its session loop, awaited with a deadline.

    What ``asyncio.wait_for(queue.get(), timeout)`` does, without its cost: on Python 3.11 that starts a task
    for every ``get``, and the loop waits on it once for every message of every session. Here a wait is one
    future and one timer. One consumer (the session loop) and one producer that may wait (the reader).
    """

    def __init__(self, maxsize: int) -> None:
        self.maxsize = int(maxsize)
        self._items: deque = deque()
        self._getter: asyncio.Future | None = None
        self._putter: asyncio.Future | None = None

    def __len__(self) -> int:
        return len(self._items)

    def empty(self) -> bool:
        return not self._items

    def put_nowait(self, item) -> None:
        """Queue ``item``; raises ``asyncio.QueueFull`` when ``maxsize`` items wait."""
        if len(self._items) >= self.maxsize:
            raise asyncio.QueueFull
        self._items.append(item)
        _wake(self._getter)

    async def put(self, item) -> None:
        """Queue ``item``, first waiting while the inbox is full."""
        while len(self._items) >= self.maxsize:
            self._putter = asyncio.get_running_loop().create_future()
            try:
                await self._putter
            finally:
                self._putter = None
        self.put_nowait(item)

    def get_nowait(self):
        """The oldest item; raises ``asyncio.QueueEmpty`` when there is none."""
        if not self._items:
            raise asyncio.QueueEmpty
        item = self._items.popleft()
        _wake(self._putter)
        return item

    async def get(self, timeout: float, default=None):
        """The oldest item, waiting at most ``timeout`` seconds for one; ``default`` if none came."""
        if not self._items:
            loop = asyncio.get_running_loop()
            self._getter = waiter = loop.create_future()
            timer = loop.call_later(max(0.0, timeout), _wake, waiter)
            try:
                await waiter
            finally:
                timer.cancel()
                self._getter = None
            if not self._items:
                return default
        return self.get_nowait()


def _wake(waiter: asyncio.Future | None) -> None:
    if waiter is not None and not waiter.done():
        waiter.set_result(None)


class Connection:
    """One websocket's session and the loop's controls: its inbox, a close request, when it was last heard."""

    def __init__(self, ws: WebSocket, session: Session, now: float, address: str = "unknown") -> None:
        self.ws = ws
        self.session = session
        self.address = address
        self.inbox = Inbox(maxsize=256)
        self.inbox_bytes = 0  # bytes of the frames waiting in ``inbox``
        self.drained = asyncio.Event()  # set when the loop takes a frame out: the reader may queue again
        self.reads_paused = 0  # times the reader stopped reading because ``inbox_bytes`` were waiting
        self.bad_frames = 0
        self.closing: tuple[str, int, str] | None = None  # (error code, close code, message)
        self.done = asyncio.Event()
        self.last_heard = now
        self.last_save = -1e18
        self.opened = now
        self.send_since: float | None = None  # when the pending send began (None: not sending)
        self.slot = False  # a hello within the session limit is being opened: it holds a slot meanwhile
        self.resumed = False
        self.refused_resume: str | None = None  # the scene of a session this connection could not resume into
        self.gone = False  # the reader saw the socket end but could not queue that
        self.heartbeat = None  # the session's last heartbeat the fleet has been told of

    def request_close(self, code: str, close_code: int, message: str = "") -> None:
        """Ask the session loop to send ``Error(code)`` and close; it acts at its next wake."""
        if self.closing is None:
            self.closing = (code, close_code, message or ERROR_CODES[code])
        try:
            self.inbox.put_nowait(WAKE)
        except asyncio.QueueFull:
            pass  # the loop is busy with queued frames and checks ``closing`` before each

    def taken(self, size: int) -> None:
        """The loop took a frame of ``size`` bytes out of the inbox: the reader may queue again."""
        self.inbox_bytes -= size
        self.drained.set()

    def info(self, now: float) -> dict:
        try:
            stats = self.session.stats
        except Exception:  # read while a worker changes the session: report what is certain
            stats = {"session": self.session.id, "state": self.session.state.value}
        return {
            **stats,
            "address": self.address,
            "bad_frames": self.bad_frames,
            "resumed": self.resumed,
            "connected_s": round(now - self.opened, 3),
            "idle_s": round(now - self.last_heard, 3),
            "send_wait_s": 0.0 if self.send_since is None else round(now - self.send_since, 3),
            "waiting_bytes": self.inbox_bytes,
            "reads_paused": self.reads_paused,
        }


async def read_frames(ws: WebSocket, conn: Connection, guard: RateGuard, limits: ReplicaLimits,
                      metrics: Metrics) -> None:
    """Move ``ws``'s frames into ``conn.inbox`` as ``(data, arrival time, bytes)`` until the socket ends."""
    try:
        while True:
            msg = await ws.receive()
            if msg["type"] == "websocket.disconnect":
                break
            # Stamped on arrival: a pong's round trip must not include a selection it waited behind.
            # It counts as heard only once the session accepted it (the loop sets ``last_heard``).
            t = time.monotonic()
            metrics.messages_in.inc()
            data = msg.get("bytes")
            data = data if data is not None else (msg.get("text") or "")
            size = len(data)
            verdict = guard.check(t, size)
            if verdict == RateGuard.PASS:
                if conn.inbox_bytes and conn.inbox_bytes + size > limits.inbox_bytes:
                    conn.reads_paused += 1
                    while conn.inbox_bytes and conn.inbox_bytes + size > limits.inbox_bytes:
                        conn.drained.clear()
                        await conn.drained.wait()
                conn.inbox_bytes += size
                await conn.inbox.put((data, t, size))
                continue
            metrics.refused.labels("rate").inc()
            if verdict == RateGuard.CLOSE:
                metrics.refused.labels("abuse").inc()
                conn.request_close("rate_limited", CLOSE_POLICY,
                                   f"more than {limits.rate:g} messages/s for {limits.abuse_close:g} s; closing")
                break
            if verdict == RateGuard.ANSWER:
                await conn.inbox.put(error("rate_limited", f"more than {limits.rate:g} messages/s "
                                                           f"(burst {limits.burst:g}); dropped"))
    except SOCKET_GONE:
        pass
    finally:
        # Never block here: a full inbox means the loop is busy and will see the socket gone on its send.
        try:
            conn.inbox.put_nowait(GONE)
        except asyncio.QueueFull:
            conn.gone = True
