"""The headless client: connect, follow the tour, apply deltas, draw, measure, report.

One thread owns the GL context and the websocket's sending side (the main
loop); a background thread only receives and decodes frames onto a queue. The
main loop never sleeps: between frames it waits on that queue until the next
frame is due, so a delta that arrives while the client is idle is decoded and
uploaded then — always outside the timed fence of a frame.

Per frame, in order: pose for ``t`` → ``Camera`` → apply queued deltas → draw
the current selection (fenced) → ``FrameReport`` → ``FrameRecord``.
"""

from __future__ import annotations

import queue
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Sequence, Union

from websockets.exceptions import ConnectionClosed, InvalidHandshake, InvalidURI
from websockets.sync.client import ClientConnection, connect

from proto.camera import NEAR, far_plane
from proto.codec import decode_server, encode
from proto.errors import ProtocolError
from proto.messages import PROTOCOL_VERSION, Camera, Delta, Error, FrameReport, Hello, Welcome

from .cache import ResidentCache
from .navigation import Tour
from .renderer import Renderer

__all__ = ["ClientError", "ClientRun", "FrameRecord", "run_client"]

CLIENT_NAME = "walkstream-client/0.1"


class ClientError(RuntimeError):
    """The session could not be opened (refused, timed out, unreachable)."""


@dataclass(frozen=True)
class FrameRecord:
    """One frame as the client saw it; ``seq`` is the delta whose selection was drawn (-1: none).

    ``cost_coeff``, ``budget`` and ``predicted_cost`` come from the last applied
    delta (0 before any); ``upload_time`` is the decode + upload time (s) spent
    since the previous frame, outside the fence.
    """

    frame: int
    t: float
    time: float
    triangles: int
    vertices: int
    draws: int
    seq: int
    cost_coeff: float
    budget: float
    predicted_cost: float
    upload_time: float = 0.0


@dataclass
class ClientRun:
    """What one run produced.

    errors : ``Error`` frames from the server, plus server frames this client could not decode
    rejected : geometry payloads the client refused (their reps were never resident)
    skipped : selected reps left undrawn because they were not resident
    close_reason : why the connection ended early, ``None`` if the client ended it
    """

    welcome: Welcome
    frames: list[FrameRecord] = field(default_factory=list)
    errors: list[Error] = field(default_factory=list)
    deltas_received: int = 0
    bytes_received: int = 0
    rejected: list[ProtocolError] = field(default_factory=list)
    skipped: int = 0
    close_reason: str | None = None


@dataclass(frozen=True)
class _Closed:
    reason: str


_Item = Union[Delta, Error, Welcome, _Closed]


def _as_error(exc: ProtocolError, what: str) -> Error:
    return Error(code=exc.code, message=f"{what}: {exc.message}"[:4096])


def _receive(ws: ClientConnection, inbox: "queue.Queue[_Item]", counter: list[int]) -> None:
    """Background thread: frames → decoded messages on ``inbox``; ends with a ``_Closed``."""
    reason = "server closed the connection"
    try:
        for data in ws:
            counter[0] += len(data)
            try:
                inbox.put(decode_server(data))  # type: ignore[arg-type]
            except ProtocolError as exc:
                inbox.put(_as_error(exc, "client could not decode a server frame"))
    except ConnectionClosed as exc:
        reason = f"connection lost: {exc}"
    except Exception as exc:  # a local bug in the receiver must still end the run
        reason = f"receiver failed: {type(exc).__name__}: {exc}"
    inbox.put(_Closed(reason))


def _handshake(ws: ClientConnection, hello: Hello, timeout: float) -> tuple[Welcome, int]:
    ws.send(encode(hello))
    try:
        data = ws.recv(timeout=timeout)
    except TimeoutError:
        raise ClientError(f"no welcome from the server within {timeout:g} s") from None
    except ConnectionClosed as exc:
        raise ClientError(f"the server closed the connection before welcoming: {exc}") from None
    try:
        msg = decode_server(data)  # type: ignore[arg-type]
    except ProtocolError as exc:
        raise ClientError(f"the server's first frame does not decode: {exc}") from None
    if isinstance(msg, Error):
        raise ClientError(f"the server refused the session: {msg.code}: {msg.message}")
    if not isinstance(msg, Welcome):
        raise ClientError(f"expected a welcome, the server sent a {msg.type}")
    if msg.protocol != PROTOCOL_VERSION:
        raise ClientError(f"server speaks protocol {msg.protocol}, this client {PROTOCOL_VERSION}")
    return msg, len(data)


class _Loop:
    """The main loop's state: cache, renderer, inbox and the run being recorded."""

    def __init__(self, run: ClientRun, renderer: Renderer, inbox: "queue.Queue[_Item]") -> None:
        self.run, self.renderer, self.inbox = run, renderer, inbox
        self.cache = ResidentCache()
        self.last: Delta | None = None
        self.upload_time = 0.0
        self.closed = False

    def handle(self, item: _Item) -> None:
        if isinstance(item, Delta):
            self.run.deltas_received += 1
            t0 = time.perf_counter()
            to_upload, to_free = self.cache.apply(item)
            for rep in to_free:
                self.renderer.free(rep)
            for rep, geometry in to_upload:
                self.renderer.upload(rep, geometry, object_id=self.cache.resident[rep].object)
            self.upload_time += time.perf_counter() - t0
            self.last = item
        elif isinstance(item, Error):
            self.run.errors.append(item)
        elif isinstance(item, _Closed):
            self.closed = True
            self.run.close_reason = item.reason
        else:
            self.run.errors.append(Error(code="bad_state", message=f"unexpected {item.type} during the session"))

    def pump(self, deadline: float | None) -> None:
        """Handle queued messages; with a deadline, wait for more until it (monotonic s)."""
        while not self.closed:
            try:
                if deadline is None:
                    item = self.inbox.get_nowait()
                else:
                    item = self.inbox.get(timeout=max(0.0, deadline - time.monotonic()))
            except queue.Empty:
                return
            self.handle(item)


def run_client(
    url: str,
    scene: str,
    *,
    duration: float,
    viewport: Sequence[int] = (640, 360),
    fov_y: float = 60.0,
    target_frame_time: float = 0.05,
    solver: str = "greedy",
    on_frame: Callable[[FrameRecord], None] | None = None,
    screenshot: Path | None = None,
    max_fps: float | None = 60.0,
    timeout: float = 10.0,
    backend: str | None = "egl",
) -> ClientRun:
    """Run one session for ``duration`` seconds of frames and return what happened.

    ``max_fps`` paces frames like a display's refresh would (None: as fast as
    possible); ``timeout`` bounds connecting and waiting for the welcome.
    Raises ``ClientError`` if the session cannot be opened.
    """
    width, height = (int(v) for v in viewport)
    renderer = Renderer(width, height, fov_y=fov_y, backend=backend)
    start = time.monotonic()  # the client clock: every t is seconds since here
    try:
        try:
            ws = connect(url, max_size=None, open_timeout=timeout)
        except (OSError, InvalidURI, InvalidHandshake, TimeoutError) as exc:
            raise ClientError(f"cannot connect to {url}: {exc}") from None
        with ws:
            hello = Hello(
                protocol=PROTOCOL_VERSION, scene=scene, viewport=[width, height], fov_y=fov_y,
                target_frame_time=target_frame_time, solver=solver, client=CLIENT_NAME,
            )
            welcome, nbytes = _handshake(ws, hello, timeout)
            counter = [nbytes]
            run = ClientRun(welcome=welcome)
            inbox: queue.Queue[_Item] = queue.Queue()
            receiver = threading.Thread(target=_receive, args=(ws, inbox, counter), name="ws-receive", daemon=True)
            receiver.start()
            loop = _Loop(run, renderer, inbox)
            _frames(ws, loop, welcome, start, duration, 1.0 / max_fps if max_fps else 0.0, on_frame)
            if screenshot is not None:
                renderer.save_png(screenshot)
        receiver.join(timeout)
        while True:  # late arrivals: count them, record errors, apply nothing
            try:
                item = inbox.get_nowait()
            except queue.Empty:
                break
            if isinstance(item, Delta):
                run.deltas_received += 1
            elif isinstance(item, Error):
                run.errors.append(item)
        run.bytes_received = counter[0]
        run.rejected = list(loop.cache.rejected)
        run.skipped = loop.cache.skipped
        return run
    finally:
        renderer.release()


def _frames(
    ws: ClientConnection,
    loop: _Loop,
    welcome: Welcome,
    start: float,
    duration: float,
    period: float,
    on_frame: Callable[[FrameRecord], None] | None,
) -> None:
    """The frame loop proper; returns after ``duration`` s or when the connection ends."""
    tour = Tour(welcome.tour) if welcome.tour else Tour([{"t": 0.0, **welcome.start.model_dump()}])
    bounds = welcome.bounds
    cache, renderer = loop.cache, loop.renderer
    first = time.monotonic()
    frame = 0
    while not loop.closed:
        now = time.monotonic()
        if now - first >= duration:
            break
        t = now - start
        eye, forward, up = tour.pose_at(t)
        try:
            ws.send(encode(Camera(t=t, eye=eye.tolist(), forward=forward.tolist(), up=up.tolist())))
            loop.pump(None)
            stats = renderer.draw(cache.selection, eye, forward, up, NEAR, far_plane(eye, bounds))
            ws.send(encode(FrameReport(
                frame=frame, t=t, time=min(max(stats.time, 1e-9), 60.0), triangles=stats.triangles,
                vertices=stats.vertices, draws=stats.draws, selection=cache.seq,
            )))
        except ConnectionClosed as exc:
            loop.closed, loop.run.close_reason = True, f"connection lost while sending: {exc}"
            break
        last = loop.last
        record = FrameRecord(
            frame=frame, t=t, time=stats.time, triangles=stats.triangles, vertices=stats.vertices,
            draws=stats.draws, seq=cache.seq, cost_coeff=last.cost_coeff if last else 0.0,
            budget=last.budget if last else 0.0, predicted_cost=last.predicted_cost if last else 0.0,
            upload_time=loop.upload_time,
        )
        loop.upload_time = 0.0
        loop.run.frames.append(record)
        if on_frame is not None:
            on_frame(record)
        frame += 1
        loop.pump(now + period if period > 0 else None)
