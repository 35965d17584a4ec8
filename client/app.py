"""The headless client: connect, follow the tour, apply deltas, draw, measure, report.

One thread owns the GL context and the websocket's sending side (the main
loop); a background thread only receives and decodes frames onto a queue. The
main loop never sleeps: between frames it waits on that queue until the next
frame is due, so a delta that arrives while the client is idle is decoded and
uploaded then — always outside the timed fence of a frame.

Per frame, in order: pose for ``t`` → ``Camera`` → apply queued deltas → the
schedule's representations and morph weights for ``t`` → draw them (fenced) →
``FrameReport`` → ``FrameRecord``.

The receiver thread answers a ``ping`` at once with a ``pong`` (the server
measures the round trip and this clock's offset from it) and stamps each delta
with its arrival time, which the main loop acks once the delta is applied.
"""

from __future__ import annotations

import queue
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Sequence, Union

import numpy as np
from websockets.exceptions import ConnectionClosed, InvalidHandshake, InvalidURI
from websockets.sync.client import ClientConnection, connect

from proto.camera import NEAR, far_plane
from proto.codec import decode_server, encode
from proto.errors import ProtocolError
from proto.messages import PROTOCOL_VERSION, Ack, AlgorithmTerms, Camera, Delta, Error, FrameReport, Hello, Ping, Pong, Welcome

from .cache import ResidentCache
from .navigation import Navigator, Tour
from .renderer import Renderer
from .schedule import Schedule
from .splats import SplatLayer

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
    morphs: int = 0
    pixels: int = 0
    splats: int = 0
    gpu_time: float | None = None
    cpu_time: float = 0.0
    prepare_time: float = 0.0
    terms: dict | None = None  # per rendering algorithm: triangles, vertices, pixels, draws (lists)


@dataclass(frozen=True)
class FrameTrace:
    """What one frame drew, per object: keys (level-0 rep ids), continuous levels, reps and morph weights."""

    t: float
    key: "np.ndarray"
    level: "np.ndarray"
    rep: "np.ndarray"
    weight: "np.ndarray"


@dataclass
class ClientRun:
    """What one run produced.

    errors : ``Error`` frames from the server, plus server frames this client could not decode
    rejected : geometry payloads the client refused (their reps were never resident)
    skipped : per frame, scheduled representations left undrawn because they were not resident (summed)
    late : schedules that arrived after their window opened (rebased so nothing jumped)
    unmorphed : morphing draws made at full detail for want of morph targets
    trace : with ``trace=True``, every frame's drawn levels and weights
    refused_full : representations refused because they would have taken the cache over its budget
    peak_cache_bytes : the most payload bytes the cache held after any delta
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
    late: int = 0
    unmorphed: int = 0
    pings: int = 0
    trace: list[FrameTrace] = field(default_factory=list)
    refused_full: int = 0
    peak_cache_bytes: int = 0


@dataclass(frozen=True)
class _Closed:
    reason: str


@dataclass(frozen=True)
class _Arrived:
    delta: Delta
    t: float  # client time of arrival


_Item = Union[_Arrived, Error, Welcome, _Closed]


def _as_error(exc: ProtocolError, what: str) -> Error:
    return Error(code=exc.code, message=f"{what}: {exc.message}"[:4096])


def _receive(ws: ClientConnection, inbox: "queue.Queue[_Item]", counter: list[int], start: float) -> None:
    """Background thread: frames → decoded messages on ``inbox``; pings answered here, at once.

    Ends with a ``_Closed``. ``start`` is the client clock's origin (monotonic s).
    """
    reason = "server closed the connection"
    try:
        for data in ws:
            arrived = time.monotonic() - start
            counter[0] += len(data)
            try:
                msg = decode_server(data)  # type: ignore[arg-type]
            except ProtocolError as exc:
                inbox.put(_as_error(exc, "client could not decode a server frame"))
                continue
            if isinstance(msg, Ping):
                counter[1] += 1
                ws.send(encode(Pong(id=msg.id, sent=msg.sent, t=time.monotonic() - start)))
            elif isinstance(msg, Delta):
                inbox.put(_Arrived(msg, arrived))
            else:
                inbox.put(msg)
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

    def __init__(self, run: ClientRun, renderer: Renderer, inbox: "queue.Queue[_Item]",
                 ws: ClientConnection | None = None, cache_bytes: int | None = None) -> None:
        self.run, self.renderer, self.inbox, self.ws = run, renderer, inbox, ws
        self.cache = ResidentCache(cache_bytes)  # the Hello's cache_bytes: the server's mirror keeps to it
        self.splats = None  # the splat layer (client.splats) for tree groups and models, when there is one
        self.schedule = Schedule()
        self.vegetation = Schedule(continuous=True)
        # Rendering algorithm per object key, as (switch time, sorted keys, algorithms) from each delta:
        # a delta's algorithms govern from its t0, like its selection.
        self._algorithms: list[tuple[float, np.ndarray, np.ndarray]] = []
        self.last: Delta | None = None
        self.upload_time = 0.0
        self.closed = False

    def handle(self, item: _Item) -> None:
        if isinstance(item, _Arrived):
            delta = item.delta
            self.run.deltas_received += 1
            t0 = time.perf_counter()
            changes = self.cache.apply(delta)
            for rep in changes.frees:
                self.renderer.free(rep)
            for rep, geometry in changes.uploads:
                self.renderer.upload(rep, geometry, object_id=self.cache.resident[rep].object)
            if self.splats is not None:
                for model, points in changes.models:
                    self.splats.add_model(model, points)
                for rep in changes.group_frees:
                    self.splats.free_group(rep)
                for rep, instances in changes.groups:
                    self.splats.add_group(rep, instances)
            self.run.refused_full = self.cache.refused_full
            self.run.peak_cache_bytes = max(self.run.peak_cache_bytes, self.cache.held_bytes)
            m, scheduled = delta.morphs, delta
            held = self.cache.holds(np.asarray(m.rep, np.int64))
            if not held.all():  # a ramp to a rep the cache lacks (refused, or beyond the budget) can't be drawn
                keep = np.nonzero(held)[0].tolist()
                cols = {k: [getattr(m, k)[i] for i in keep] for k in ("rep", "level_from", "level_to", "t0", "t1")}
                scheduled = delta.model_copy(update={"morphs": m.model_copy(update=cols)})
            self._schedule(scheduled, item.t)
            self.upload_time += time.perf_counter() - t0
            self.last = delta
            if self.ws is not None:
                try:
                    cache = self.cache  # what it holds now, so the server can check its mirror
                    self.ws.send(encode(Ack(seq=delta.seq, t=item.t, rejected=changes.rejected, held=cache.held,
                                            held_bytes=cache.held_bytes, digest=cache.digest)))
                except ConnectionClosed as exc:
                    self.closed, self.run.close_reason = True, f"connection lost while acking: {exc}"
        elif isinstance(item, Error):
            self.run.errors.append(item)
        elif isinstance(item, _Closed):
            self.closed = True
            self.run.close_reason = item.reason
        else:
            self.run.errors.append(Error(code="bad_state", message=f"unexpected {item.type} during the session"))

    def _schedule(self, delta: Delta, arrived: float) -> None:
        """Hand the delta's schedule to the executors and build the morph targets it will draw."""
        reps, levels = self.cache.levels(delta.selection)
        if delta.algorithm:
            sel = np.asarray(delta.selection, np.int64)
            alg = np.asarray(delta.algorithm, np.int64)[np.isin(sel, reps)]  # aligned with ``reps``
            keys = reps - levels.astype(np.int64)
            order = np.argsort(keys, kind="stable")
            gen = (delta.t0, keys[order], alg[order])
            if delta.reset or delta.start is None:
                self._algorithms = [gen]
            else:
                self._algorithms = [g for g in self._algorithms if g[0] < delta.t0][-1:] + [gen]
        elif delta.reset or delta.start is None:
            self._algorithms = []
        m = delta.morphs
        to = np.asarray(m.level_to, np.float64)
        key = np.asarray(m.rep, np.int64) - to.astype(np.int64)
        start = delta.t0 if delta.start is None else delta.start
        late = self.schedule.apply(start, delta.t0, reps - levels.astype(np.int64), levels,
                                   (key, np.asarray(m.level_from), to, np.asarray(m.t0), np.asarray(m.t1)),
                                   reset=delta.reset or delta.start is None, now=arrived)
        self.run.late += int(late)
        r = delta.ramps
        self.vegetation.apply(start, delta.t0, np.asarray(delta.vegetation, np.int64), np.asarray(delta.resolution),
                              (np.asarray(r.rep, np.int64), np.asarray(r.level_from), np.asarray(r.level_to),
                               np.asarray(r.t0), np.asarray(r.t1)),
                              reset=delta.reset or delta.start is None, now=arrived)
        # Every level a ramp passes through is drawn morphed from the one below it.
        lo = np.minimum(np.asarray(m.level_from), to)
        hi = np.maximum(np.asarray(m.level_from), to)
        for k0, a, b in zip(key.tolist(), lo.tolist(), hi.tolist()):
            for level in range(int(a) + 1, int(b) + 1):
                rep = k0 + level
                if rep in self.cache and not self.renderer.has_morph_target(rep):
                    targets = self.cache.morph_targets(rep)
                    if targets is not None:
                        self.renderer.set_morph_target(rep, targets)

    def drawn(self, t: float):
        """Representations, morph weights and the full schedule rows to draw at client time t."""
        self.schedule.advance(t)
        d = self.schedule.at(t)
        here = self.cache.holds(d.rep)
        self.run.skipped += int((~here).sum())
        return d, d.rep[here], d.weight[here]

    def algorithms(self, keys: np.ndarray, t: float) -> np.ndarray | None:
        """(s,) rendering algorithm of each object key at time t (the latest delta governing by then), or None."""
        while len(self._algorithms) > 1 and self._algorithms[1][0] <= t:
            self._algorithms.pop(0)
        if not self._algorithms:
            return None
        _, k, a = self._algorithms[0]
        if k.size == 0:
            return np.zeros(keys.size, np.int64)
        pos = np.minimum(np.searchsorted(k, keys), k.size - 1)
        return np.where(k[pos] == keys, a[pos], 0)

    def vegetation_at(self, t: float) -> None:
        """Give the splat layer the tree groups and resolutions the vegetation schedule draws at t."""
        if self.splats is None:
            return
        self.vegetation.advance(t)
        v = self.vegetation.at(t)
        x = np.clip(np.asarray(v.level, np.float64), 0.0, 1.0)
        keep = x > 0
        self.splats.set_resolutions(np.asarray(v.key, np.int64)[keep], x[keep])

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
    predict: bool = True,
    morph: bool = True,
    trace: bool = False,
    window: bool = False,
    navigate: str = "tour",
    false_colour: bool = False,
    algorithms: Sequence[str] = ("flat", "lit", "textured"),
    cache_bytes: int | None = None,
) -> ClientRun:
    """Run one session for ``duration`` seconds of frames and return what happened.

    ``max_fps`` paces frames like a display's refresh would (None: as fast as
    possible); ``timeout`` bounds connecting and waiting for the welcome.
    ``predict`` and ``morph`` ask the server for path prediction and geomorphing;
    ``trace`` records every frame's drawn levels and weights in ``ClientRun.trace``.
    ``window`` shows the frames in a window (``client.window``; ends early when
    it is closed) and ``navigate`` ("tour", "fly", "walk") says who moves the
    camera there: the scene's tour, or the user (``client.navigation.Navigator``,
    whose limits go out in the ``Hello``). ``false_colour`` sets ``Renderer.false_colour``.
    ``algorithms`` are the rendering algorithms offered to the selection (``proto.messages.ALGORITHMS``);
    ``cache_bytes`` is the client cache's budget (payload bytes), kept by both ends.
    Raises ``ClientError`` if the session cannot be opened, ``client.window.WindowError``
    if the window cannot.
    """
    if navigate not in ("tour", "fly", "walk"):
        raise ValueError(f"navigate must be tour, fly or walk, got {navigate!r}")
    if navigate != "tour" and not window:
        raise ValueError("interactive navigation (fly, walk) needs window=True")
    width, height = (int(v) for v in viewport)
    view = None
    if window:
        from .window import Window

        view = Window(width, height)
        try:
            renderer = Renderer(width, height, fov_y=fov_y, ctx=view.ctx)
        except BaseException:
            view.release()
            raise
    else:
        renderer = Renderer(width, height, fov_y=fov_y, backend=backend)
    if false_colour:
        setattr(renderer, "false_colour", True)
    navigator = Navigator(mode=navigate) if navigate != "tour" else None
    limits = {} if navigator is None else {"max_speed": navigator.max_speed, "max_turn": navigator.max_turn}
    if view is not None:
        view.controller = navigator
    start = time.monotonic()  # the client clock: every t is seconds since here
    loop: _Loop | None = None
    try:
        try:
            ws = connect(url, max_size=None, open_timeout=timeout)
        except (OSError, InvalidURI, InvalidHandshake, TimeoutError) as exc:
            raise ClientError(f"cannot connect to {url}: {exc}") from None
        with ws:
            hello = Hello(
                protocol=PROTOCOL_VERSION, scene=scene, viewport=[width, height], fov_y=fov_y,
                target_frame_time=target_frame_time, solver=solver, client=CLIENT_NAME, predict=predict, morph=morph,
                algorithms=list(algorithms), cache_bytes=cache_bytes, **limits,
            )
            welcome, nbytes = _handshake(ws, hello, timeout)
            counter = [nbytes, 0]
            run = ClientRun(welcome=welcome)
            inbox: queue.Queue[_Item] = queue.Queue()
            receiver = threading.Thread(target=_receive, args=(ws, inbox, counter, start), name="ws-receive",
                                        daemon=True)
            receiver.start()
            loop = _Loop(run, renderer, inbox, ws, cache_bytes=cache_bytes)
            loop.splats = SplatLayer(renderer.ctx)
            _frames(ws, loop, welcome, start, duration, 1.0 / max_fps if max_fps else 0.0, on_frame, trace,
                    window=view, navigator=navigator)
            if screenshot is not None:
                renderer.save_png(screenshot)
        receiver.join(timeout)
        while True:  # late arrivals: count them, record errors, apply nothing
            try:
                item = inbox.get_nowait()
            except queue.Empty:
                break
            if isinstance(item, _Arrived):
                run.deltas_received += 1
            elif isinstance(item, Error):
                run.errors.append(item)
        run.bytes_received = counter[0]
        run.pings = counter[1]
        run.rejected = list(loop.cache.rejected)
        run.unmorphed = renderer.unmorphed
        return run
    finally:
        if loop is not None and loop.splats is not None:
            loop.splats.release()
        renderer.release()
        if view is not None:
            view.release()


def _frames(
    ws: ClientConnection,
    loop: _Loop,
    welcome: Welcome,
    start: float,
    duration: float,
    period: float,
    on_frame: Callable[[FrameRecord], None] | None,
    trace: bool = False,
    *,
    window=None,
    navigator: Navigator | None = None,
) -> None:
    """The frame loop proper; returns after ``duration`` s, when the connection ends or the window closes.

    With a ``navigator`` the user's input moves the camera, from the welcome's start pose.
    """
    tour = Tour(welcome.tour) if welcome.tour else Tour([{"t": 0.0, **welcome.start.model_dump()}])
    if navigator is not None:
        navigator.place(welcome.start)
        tour = navigator
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
            rows, reps, weights = loop.drawn(t)
            here = cache.holds(rows.rep)
            loop.vegetation_at(t)
            layers = (loop.splats,) if loop.splats is not None else ()
            stats = renderer.draw(reps, eye, forward, up, NEAR, far_plane(eye, bounds), weights=weights,
                                  algorithms=loop.algorithms(rows.key[here], t), levels=rows.level[here],
                                  layers=layers)
            terms = stats.terms
            ws.send(encode(FrameReport(
                frame=frame, t=t, time=min(max(stats.time, 1e-9), 60.0), triangles=stats.triangles,
                vertices=stats.vertices, draws=stats.draws, selection=cache.seq, pixels=stats.pixels,
                splats=stats.splats, gpu_time=None if stats.gpu_time is None else min(stats.gpu_time, 60.0),
                cpu_time=min(stats.cpu_time, 60.0),
                terms=None if terms is None else AlgorithmTerms(
                    triangles=terms.triangles, vertices=terms.vertices, pixels=terms.pixels, draws=terms.draws),
            )))
        except ConnectionClosed as exc:
            loop.closed, loop.run.close_reason = True, f"connection lost while sending: {exc}"
            break
        last = loop.last
        record = FrameRecord(
            frame=frame, t=t, time=stats.time, triangles=stats.triangles, vertices=stats.vertices,
            draws=stats.draws, seq=cache.seq, cost_coeff=last.cost_coeff if last else 0.0,
            budget=last.budget if last else 0.0, predicted_cost=last.predicted_cost if last else 0.0,
            upload_time=loop.upload_time, morphs=stats.morphs, pixels=stats.pixels, splats=stats.splats,
            gpu_time=stats.gpu_time, cpu_time=stats.cpu_time, prepare_time=stats.prepare_time,
            terms=None if terms is None else {"triangles": list(terms.triangles), "vertices": list(terms.vertices),
                                              "pixels": list(terms.pixels), "draws": list(terms.draws)},
        )
        if trace:
            loop.run.trace.append(FrameTrace(t, rows.key, rows.level, rows.rep, rows.weight))
        loop.upload_time = 0.0
        loop.run.frames.append(record)
        if on_frame is not None:
            on_frame(record)
        frame += 1
        if window is not None:
            window.present(renderer)
            window.poll()
            if window.should_close:
                break
        loop.pump(now + period if period > 0 else None)
