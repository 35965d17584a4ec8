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

A lost connection does not end the run: the frame loop keeps drawing what is
resident while a background thread redials (backoff 50 ms → 500 ms, for at
most ``reconnect_timeout`` s) with a hello that resumes the session by its
token and carries the held manifest (``proto.manifest.pack_held``), so the
server sends nothing the cache already holds. The run's client id goes in the
URL's query (``client=<id>``) so a load balancer hashing on it keeps the client
on one replica.
"""

from __future__ import annotations

import gc
import queue
import threading
import time
import uuid
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterator, Sequence, Union
from urllib.parse import parse_qsl, urlencode, urlsplit, urlunsplit

import numpy as np
from websockets.exceptions import ConnectionClosed, ConnectionClosedOK, InvalidHandshake, InvalidURI
from websockets.sync.client import ClientConnection, connect

from proto.camera import NEAR, far_plane
from proto.codec import decode_server, encode
from proto.errors import ProtocolError
from proto.manifest import pack_held
from proto.messages import (
    MAX_HELD_BYTES, PROTOCOL_VERSION, Ack, AlgorithmTerms, Camera, Delta, Error, FrameReport, Hello, Ping, Pong,
    Resume, Welcome,
)

from .cache import ResidentCache
from .navigation import Navigator, Tour
from .renderer import Renderer
from .schedule import Schedule
from .splats import SplatLayer

__all__ = ["ClientError", "ClientRun", "FrameRecord", "Reconnect", "run_client"]

CLIENT_NAME = "walkstream-client/0.1"
#: Redial backoff: the first retry after 50 ms, doubling to at most 500 ms.
BACKOFF = (0.05, 0.5)
#: Seconds a close handshake may take; a lost link must not hold the client up for longer.
CLOSE_TIMEOUT = 2.0
#: Refusals no retry can change: a resume is not attempted again after one of these.
FINAL_CODES = frozenset({"closed", "version", "invalid", "unknown_solver", "unknown_scene"})


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
    bytes: int = 0  # bytes of the deltas applied since the previous frame (as received: framed, maybe compressed)
    compute: float = 0.0  # the server's selection time of the latest delta applied (s)


@dataclass(frozen=True)
class FrameTrace:
    """What one frame drew, enough to draw it again: per object its key (level-0 rep id), continuous
    level, rep and morph weight (all schedule rows, drawn or not), the camera, and — aligned with the
    reps actually drawn (``rep[drawn]``) — their rendering algorithm; the tree groups and resolutions."""

    t: float
    key: "np.ndarray"
    level: "np.ndarray"
    rep: "np.ndarray"
    weight: "np.ndarray"
    eye: "np.ndarray | None" = None
    forward: "np.ndarray | None" = None
    up: "np.ndarray | None" = None
    drawn: "np.ndarray | None" = None  # (n,) bool: the rows the cache held, hence drawn
    algorithm: "np.ndarray | None" = None  # (drawn,) index into proto.messages.ALGORITHMS, or None (all flat)
    vegetation: "np.ndarray | None" = None  # (g,) tree-group reps drawn
    resolution: "np.ndarray | None" = None  # (g,) their resolution x in (0, 1]


@dataclass(frozen=True)
class Reconnect:
    """One lost connection and its recovery (times on the client clock, s).

    resumed : the server continued the old session (False: a fresh session that adopted the held manifest)
    held : representations the hello's held manifest named; welcome_held : how many the server took as held
    """

    lost_at: float
    resumed_at: float
    resumed: bool
    held: int
    welcome_held: int
    session: str = ""
    attempts: int = 1
    reason: str = ""


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
    client_id : the run's stable id, sent as ``client=<id>`` in the URL's query (a load balancer hashes it)
    reconnects : every lost connection the run recovered from, in order
    resent : representations a delta added that the cache already held then (0 when resumes work)
    adds_after_reconnect : representations added by deltas after the first reconnect
    bytes_per_connection : bytes received over each connection, in order (their sum is ``bytes_received``)
    deltas_per_connection : deltas received over each connection, in order
    attempts : hellos it took to open the session (more than one when the server was ``busy``)
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
    client_id: str = ""
    reconnects: list[Reconnect] = field(default_factory=list)
    resent: int = 0
    adds_after_reconnect: int = 0
    bytes_per_connection: list[int] = field(default_factory=list)
    deltas_per_connection: list[int] = field(default_factory=list)
    attempts: int = 1


@dataclass(frozen=True)
class _Closed:
    reason: str


@dataclass(frozen=True)
class _Arrived:
    delta: Delta
    t: float  # client time of arrival
    nbytes: int = 0  # the frame's size on the wire


@dataclass(frozen=True)
class _Redialled:
    """The reconnector's success: a welcomed websocket, ready for a receiver thread."""

    ws: ClientConnection
    welcome: Welcome
    nbytes: int
    attempts: int


@dataclass(frozen=True)
class _GaveUp:
    """The reconnector's failure: ``error`` is None when the server ended the session on purpose."""

    reason: str
    error: Error | None


_Item = Union[_Arrived, Error, Welcome, _Closed, _Redialled, _GaveUp]


class _Refused(ClientError):
    """The server answered the hello with an ``error`` frame."""

    def __init__(self, error: Error) -> None:
        super().__init__(f"the server refused the session: {error.code}: {error.message}")
        self.error = error


def _as_error(exc: ProtocolError, what: str) -> Error:
    return Error(code=exc.code, message=f"{what}: {exc.message}"[:4096])


def _with_client(url: str, client_id: str) -> str:
    """``url`` with ``client=<id>`` in its query (replacing any), for a load balancer's ``hash $arg_client``."""
    parts = urlsplit(url)
    query = [(k, v) for k, v in parse_qsl(parts.query, keep_blank_values=True) if k != "client"]
    return urlunsplit(parts._replace(query=urlencode(query + [("client", client_id)])))


def _receive(ws: ClientConnection, inbox: "queue.Queue[_Item]", counter: list[int], start: float,
             silence: float | None = None) -> None:
    """Background thread: frames → decoded messages on ``inbox``; pings answered here, at once.

    ``counter`` accumulates [bytes, pings, deltas] received.

    Ends with a ``_Closed``. ``start`` is the client clock's origin (monotonic s).
    ``silence``: a link that delivers nothing for this long (the server pings every
    second) is taken for dead — a cable pulled sends no FIN.
    """
    reason = "server closed the connection"
    try:
        while True:
            try:
                data = ws.recv(timeout=silence)
            except TimeoutError:
                reason = f"connection lost: nothing from the server for {silence:g} s"
                ws.close_socket()
                break
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
                counter[2] += 1
                inbox.put(_Arrived(msg, arrived, len(data)))
            else:
                inbox.put(msg)
    except ConnectionClosedOK:
        pass
    except ConnectionClosed as exc:
        reason = f"connection lost: {exc}"
    except Exception as exc:  # a local bug in the receiver must still end the run
        reason = f"receiver failed: {type(exc).__name__}: {exc}"
    inbox.put(_Closed(reason))


def _handshake(ws: ClientConnection, hello: Hello, timeout: float) -> tuple[Welcome, int]:
    try:
        ws.send(encode(hello))
    except ConnectionClosed:
        pass  # a refusing server (busy) may close at once: its error frame is still there to read
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
        raise _Refused(msg)
    if not isinstance(msg, Welcome):
        raise ClientError(f"expected a welcome, the server sent a {msg.type}")
    if msg.protocol != PROTOCOL_VERSION:
        raise ClientError(f"server speaks protocol {msg.protocol}, this client {PROTOCOL_VERSION}")
    return msg, len(data)


def _open(url: str, hello: Hello, timeout: float) -> tuple[ClientConnection, Welcome, int]:
    """Connect and say hello; a socket that is not welcomed is closed (``ClientError`` / ``_Refused``)."""
    try:
        ws = connect(url, max_size=None, open_timeout=timeout, close_timeout=CLOSE_TIMEOUT, legacy=True)
    except (OSError, InvalidURI, InvalidHandshake, TimeoutError) as exc:
        raise ClientError(f"cannot connect to {url}: {exc}") from None
    try:
        welcome, nbytes = _handshake(ws, hello, timeout)
    except BaseException:
        ws.close_socket()
        raise
    return ws, welcome, nbytes


def _open_patiently(url: str, hello: Hello, timeout: float,
                    patience: float) -> tuple[ClientConnection, Welcome, int, int]:
    """``_open``, retried with backoff for up to ``patience`` s while the server answers ``busy``; + attempts made."""
    deadline = time.monotonic() + patience
    delay, attempts = BACKOFF[0], 0
    while True:
        attempts += 1
        try:
            return (*_open(url, hello, timeout), attempts)
        except _Refused as exc:
            if exc.error.code != "busy" or time.monotonic() + delay > deadline:
                raise
        time.sleep(delay)  # backoff before the next attempt, not synchronisation
        delay = min(2 * delay, BACKOFF[1])


def _redial(url: str, hello: Hello, timeout: float, patience: float, inbox: "queue.Queue[_Item]",
            stop: threading.Event) -> None:
    """Background thread: reconnect with ``hello`` (backoff 50 → 500 ms) until welcomed or ``patience`` s pass.

    Puts one ``_Redialled`` or ``_GaveUp`` on ``inbox`` — nothing if ``stop`` is
    set first (the run ended; a socket won meanwhile is closed here).
    """
    deadline = time.monotonic() + patience
    delay, attempts, last = BACKOFF[0], 0, "no attempt made"
    while not stop.is_set():
        attempts += 1
        try:
            ws, welcome, nbytes = _open(url, hello, max(0.05, min(timeout, deadline - time.monotonic())))
        except _Refused as exc:
            if exc.error.code == "closed":
                inbox.put(_GaveUp(f"the server closed the session: {exc.error.message}", None))
                return
            if exc.error.code == "bad_held" and hello.held is not None:
                hello = hello.model_copy(update={"held": None})  # resume without it rather than not at all
            elif exc.error.code in FINAL_CODES:
                inbox.put(_GaveUp(f"cannot resume: {exc}", exc.error))
                return
            last = str(exc)
        except ClientError as exc:
            last = str(exc)
        except Exception as exc:  # a local bug must still end the wait
            last = f"{type(exc).__name__}: {exc}"
        else:
            if stop.is_set():
                ws.close_socket()
                return
            inbox.put(_Redialled(ws, welcome, nbytes, attempts))
            return
        if time.monotonic() + delay >= deadline:
            message = f"could not reconnect within {patience:g} s ({attempts} attempts); last: {last}"
            inbox.put(_GaveUp(message, Error(code="connection_lost", message=message[:4096])))
            return
        stop.wait(delay)
        delay = min(2 * delay, BACKOFF[1])


class _Link:
    """The connection side of a run: the current websocket and its receiver, and how to get another.

    ``hello`` is the run's first hello; a redial adds ``resume`` (the session and
    token of the last welcome) and ``held``. ``patience`` is ``reconnect_timeout``.
    """

    def __init__(self, url: str, hello: Hello, start: float, *, timeout: float, patience: float,
                 silence: float | None) -> None:
        self.url, self.hello, self.start = url, hello, start
        self.timeout, self.patience, self.silence = timeout, patience, silence
        self.ws: ClientConnection | None = None
        self.welcome: Welcome | None = None
        self.counter = [0, 0, 0]  # bytes received, pings answered and deltas received on the current connection
        self.receiver: threading.Thread | None = None
        self.redialler: threading.Thread | None = None
        self.stop = threading.Event()
        self.lost_at = 0.0
        self.reason = ""
        self.held = 0  # representations the pending redial's manifest names

    def attach(self, ws: ClientConnection, welcome: Welcome, nbytes: int, inbox: "queue.Queue[_Item]") -> None:
        """Make ``ws`` the current connection and start its receiver."""
        self.ws, self.welcome, self.counter = ws, welcome, [nbytes, 0, 0]
        self.receiver = threading.Thread(target=_receive, args=(ws, inbox, self.counter, self.start, self.silence),
                                         name="ws-receive", daemon=True)
        self.receiver.start()

    @property
    def can_redial(self) -> bool:
        return self.patience > 0 and self.welcome is not None and bool(self.welcome.token)

    def redial(self, held: np.ndarray, now: float, reason: str, inbox: "queue.Queue[_Item]") -> None:
        """Start the background redial, resuming the last welcome's session with ``held`` as the manifest."""
        assert self.welcome is not None
        self.lost_at, self.reason, self.ws = now, reason, None
        blob = pack_held(held)
        self.held = int(held.size) if len(blob) <= MAX_HELD_BYTES else 0
        hello = self.hello.model_copy(update={
            "resume": Resume(session=self.welcome.session, token=self.welcome.token),
            "held": blob if self.held or held.size == 0 else None,
        })
        self.stop.clear()
        self.redialler = threading.Thread(target=_redial, args=(self.url, hello, self.timeout, self.patience, inbox,
                                                                self.stop), name="ws-redial", daemon=True)
        self.redialler.start()

    def close(self) -> None:
        """End the run's side: stop a redial, close the socket, wait for the threads (bounded)."""
        self.stop.set()
        if self.redialler is not None:
            self.redialler.join(self.timeout + CLOSE_TIMEOUT)
        if self.ws is not None:
            try:
                self.ws.close()
            except Exception:  # closing a dead link: the socket goes either way
                self.ws.close_socket()
        if self.receiver is not None:
            self.receiver.join(self.timeout)


class _Loop:
    """The main loop's state: cache, renderer, inbox and the run being recorded.

    ``ws`` is the sending side (anything with ``send(bytes)``), None while the link
    is down; ``link`` (when given) redials a lost connection.
    """

    def __init__(self, run: ClientRun, renderer: Renderer, inbox: "queue.Queue[_Item]",
                 ws: ClientConnection | None = None, cache_bytes: int | None = None, link: _Link | None = None,
                 start: float = 0.0) -> None:
        self.run, self.renderer, self.inbox, self.ws, self.link = run, renderer, inbox, ws, link
        self.start = start
        self.cache = ResidentCache(cache_bytes)  # the Hello's cache_bytes: the server's mirror keeps to it
        self.splats = None  # the splat layer (client.splats) for tree groups and models, when there is one
        self.schedule = Schedule()
        self.vegetation = Schedule(continuous=True)
        # Rendering algorithm per object key, as (switch time, sorted keys, algorithms) from each delta:
        # a delta's algorithms govern from its t0, like its selection.
        self._algorithms: list[tuple[float, np.ndarray, np.ndarray]] = []
        self.last: Delta | None = None
        self.upload_time = 0.0
        self.applied_bytes = 0  # bytes of deltas applied since the last frame record
        self.drawn_vegetation: tuple[np.ndarray, np.ndarray] = (np.zeros(0, np.int64), np.zeros(0))
        self.closed = False
        self.failing = False  # a send failed: the receiver is ending, its _Closed is on the way

    def send(self, msg) -> None:
        """Send on the current connection; a failure shuts it down so its receiver reports the loss."""
        ws = self.ws
        if ws is None or self.failing:
            return
        try:
            ws.send(encode(msg))
        except (ConnectionClosed, OSError) as exc:
            if self.link is None:
                self.closed, self.run.close_reason = True, f"connection lost while sending: {exc}"
                return
            self.failing = True
            ws.close_socket()

    def handle(self, item: _Item) -> None:
        if isinstance(item, _Arrived):
            delta = item.delta
            self.run.deltas_received += 1
            self.applied_bytes += item.nbytes
            t0 = time.perf_counter()
            if delta.add:
                added = np.fromiter((a.rep for a in delta.add), np.int64, len(delta.add))
                self.run.resent += int(self.cache.holds(added).sum())
                if self.run.reconnects:
                    self.run.adds_after_reconnect += len(delta.add)
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
            cache = self.cache  # what it holds now, so the server can check its mirror
            self.send(Ack(seq=delta.seq, t=item.t, rejected=changes.rejected, held=cache.held,
                          held_bytes=cache.held_bytes, digest=cache.digest))
        elif isinstance(item, Error):
            if item.code == "closed":  # an administrator ended the session: the run ends, no redial
                self.closed, self.run.close_reason = True, f"the server closed the session: {item.message}"
            else:
                self.run.errors.append(item)
        elif isinstance(item, _Closed):
            self._lost(item.reason)
        elif isinstance(item, _Redialled):
            self._resumed(item)
        elif isinstance(item, _GaveUp):
            self.closed, self.run.close_reason = True, item.reason
            if item.error is not None:
                self.run.errors.append(item.error)
        else:
            self.run.errors.append(Error(code="bad_state", message=f"unexpected {item.type} during the session"))

    def _lost(self, reason: str) -> None:
        """The current connection ended while the run has time left: redial, or end the run saying why."""
        link = self.link
        self.ws, self.failing = None, False
        if link is None:
            self.closed, self.run.close_reason = True, reason
            return
        self._count(link.counter)
        now = time.monotonic() - self.start
        if not link.can_redial:
            link.ws = None
            why = ("reconnecting is off (reconnect_timeout=0)" if link.patience <= 0
                   else "the server offers no resume (its welcome carried no token)")
            self.closed, self.run.close_reason = True, reason
            self.run.errors.append(Error(code="connection_lost",
                                         message=f"{reason} at t={now:.2f} s; {why}"[:4096]))
            return
        link.redial(self.cache._ids.copy(), now, reason, self.inbox)

    def _count(self, counter: list[int]) -> None:
        """Fold one finished connection's counters into the run."""
        self.run.bytes_per_connection.append(counter[0])
        self.run.pings += counter[1]
        self.run.deltas_per_connection.append(counter[2])

    def _resumed(self, item: _Redialled) -> None:
        """A redial was welcomed: the new connection carries on the session (or a fresh one that kept the cache)."""
        link = self.link
        assert link is not None
        w = item.welcome
        self.run.reconnects.append(Reconnect(
            lost_at=link.lost_at, resumed_at=time.monotonic() - self.start, resumed=w.resumed, held=link.held,
            welcome_held=w.held, session=w.session, attempts=item.attempts, reason=link.reason))
        link.attach(item.ws, w, item.nbytes, self.inbox)
        self.ws = item.ws

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
        self.drawn_vegetation = (np.asarray(v.key, np.int64)[keep], x[keep])
        self.splats.set_resolutions(*self.drawn_vegetation)

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
    reconnect_timeout: float = 10.0,
    silence_timeout: float | None = 10.0,
    tour: "Sequence[dict] | None" = None,
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
    A lost connection is redialled for up to ``reconnect_timeout`` s (0: never; the run
    then ends with a ``connection_lost`` error), resuming the session by its token with
    the cache's held manifest, while frames go on from what is resident; a link
    silent for ``silence_timeout`` s (None: no limit) counts as lost. A ``busy`` server
    is retried as long on the first connect too.
    ``tour`` (keys ``{t, eye, forward, up}``, as ``proto.messages.TourKey``) replaces the
    tour the server's welcome carries: evaluations drive the camera along paths of their own.
    Raises ``ClientError`` if the session cannot be opened, ``client.window.WindowError``
    if the window cannot.
    """
    if navigate not in ("tour", "fly", "walk"):
        raise ValueError(f"navigate must be tour, fly or walk, got {navigate!r}")
    if navigate != "tour" and not window:
        raise ValueError("interactive navigation (fly, walk) needs window=True")
    if tour is not None and navigate != "tour":
        raise ValueError("a tour and interactive navigation exclude each other")
    if tour is not None:
        tour = list(tour)
        Tour(tour)  # raises ValueError now, before connecting, on a malformed tour
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
    client_id = uuid.uuid4().hex
    url = _with_client(url, client_id)
    loop: _Loop | None = None
    try:
        hello = Hello(
            protocol=PROTOCOL_VERSION, scene=scene, viewport=[width, height], fov_y=fov_y,
            target_frame_time=target_frame_time, solver=solver, client=CLIENT_NAME, predict=predict, morph=morph,
            algorithms=list(algorithms), cache_bytes=cache_bytes, **limits,
        )
        ws, welcome, nbytes, attempts = _open_patiently(url, hello, timeout, max(0.0, reconnect_timeout))
        link = _Link(url, hello, start, timeout=timeout, patience=reconnect_timeout, silence=silence_timeout)
        run = ClientRun(welcome=welcome, client_id=client_id, attempts=attempts)
        inbox: queue.Queue[_Item] = queue.Queue()
        link.attach(ws, welcome, nbytes, inbox)
        loop = _Loop(run, renderer, inbox, ws, cache_bytes=cache_bytes, link=link, start=start)
        try:
            loop.splats = SplatLayer(renderer.ctx)
            with _quiet_collector():
                _frames(loop, welcome, start, duration, 1.0 / max_fps if max_fps else 0.0, on_frame, trace,
                        window=view, navigator=navigator, tour_keys=tour)
            if screenshot is not None:
                renderer.save_png(screenshot)
        finally:
            link.close()
        while True:  # late arrivals: count them, record errors, apply nothing
            try:
                item = inbox.get_nowait()
            except queue.Empty:
                break
            if isinstance(item, _Arrived):
                run.deltas_received += 1
            elif isinstance(item, Error) and item.code != "closed":
                run.errors.append(item)
            elif isinstance(item, _Redialled):  # won just as the run ended
                item.ws.close_socket()
        if link.ws is not None:  # the last connection was still up when the run ended
            loop._count(link.counter)
        run.bytes_received = sum(run.bytes_per_connection)
        run.rejected = list(loop.cache.rejected)
        run.unmorphed = renderer.unmorphed
        return run
    finally:
        if loop is not None and loop.splats is not None:
            loop.splats.release()
        renderer.release()
        if view is not None:
            view.release()


@contextmanager
def _quiet_collector() -> Iterator[None]:
    """Keep the cyclic garbage collector off the frame loop's critical path.

    A full (generation 2) collection scans every tracked object — the imported libraries' tens of thousands —
    and took 35–45 ms in a 30 s auditorium run: one frame of it doubled. Everything alive when the loop
    starts is frozen (``gc.freeze``), so later collections scan only what the run itself made; it is
    unfrozen afterwards, so what becomes garbage later is collected again as usual.
    """
    gc.collect()
    gc.freeze()
    try:
        yield
    finally:
        gc.unfreeze()


def _frames(
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
    tour_keys: list[dict] | None = None,
) -> None:
    """The frame loop proper; returns after ``duration`` s, when the connection ends or the window closes.

    With a ``navigator`` the user's input moves the camera, from the welcome's start pose.
    """
    if tour_keys is not None:
        tour = Tour(tour_keys)
    else:
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
        # While the link is down, sends are skipped and frames go on from what is resident.
        loop.send(Camera(t=t, eye=eye.tolist(), forward=forward.tolist(), up=up.tolist()))
        loop.pump(None)
        rows, reps, weights = loop.drawn(t)
        here = cache.holds(rows.rep)
        loop.vegetation_at(t)
        layers = (loop.splats,) if loop.splats is not None else ()
        drawn_algorithms = loop.algorithms(rows.key[here], t)
        stats = renderer.draw(reps, eye, forward, up, NEAR, far_plane(eye, bounds), weights=weights,
                              algorithms=drawn_algorithms, levels=rows.level[here],
                              layers=layers)
        terms = stats.terms
        loop.send(FrameReport(
            frame=frame, t=t, time=min(max(stats.time, 1e-9), 60.0), triangles=stats.triangles,
            vertices=stats.vertices, draws=stats.draws, selection=cache.seq, pixels=stats.pixels,
            splats=stats.splats, gpu_time=None if stats.gpu_time is None else min(stats.gpu_time, 60.0),
            cpu_time=min(stats.cpu_time, 60.0),
            terms=None if terms is None else AlgorithmTerms(
                triangles=terms.triangles, vertices=terms.vertices, pixels=terms.pixels, draws=terms.draws),
        ))
        last = loop.last
        record = FrameRecord(
            frame=frame, t=t, time=stats.time, triangles=stats.triangles, vertices=stats.vertices,
            draws=stats.draws, seq=cache.seq, cost_coeff=last.cost_coeff if last else 0.0,
            budget=last.budget if last else 0.0, predicted_cost=last.predicted_cost if last else 0.0,
            upload_time=loop.upload_time, morphs=stats.morphs, pixels=stats.pixels, splats=stats.splats,
            gpu_time=stats.gpu_time, cpu_time=stats.cpu_time, prepare_time=stats.prepare_time,
            terms=None if terms is None else {"triangles": list(terms.triangles), "vertices": list(terms.vertices),
                                              "pixels": list(terms.pixels), "draws": list(terms.draws)},
            bytes=loop.applied_bytes, compute=last.compute if last else 0.0,
        )
        if trace:
            veg, res = loop.drawn_vegetation
            loop.run.trace.append(FrameTrace(
                t, rows.key, rows.level, rows.rep, rows.weight, eye=np.asarray(eye, np.float64).copy(),
                forward=np.asarray(forward, np.float64).copy(), up=np.asarray(up, np.float64).copy(), drawn=here,
                algorithm=None if drawn_algorithms is None else np.asarray(drawn_algorithms, np.int64),
                vegetation=veg, resolution=res))
        loop.upload_time = 0.0
        loop.applied_bytes = 0
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
