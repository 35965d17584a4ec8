"""The client's side of the websocket: opening a session, receiving, and redialling a lost link.

A background thread (``_receive``) only receives and decodes frames onto the
frame loop's queue: it answers a ``ping`` at once with a ``pong`` (the server
measures the round trip and this clock's offset from it) and stamps each delta
with its arrival time (``Arrived``), which the frame loop acks once the delta
is applied. It ends with a ``Closed``.

A lost connection does not end the run: while the frame loop keeps drawing
what is resident, ``Link.redial`` starts a background thread that reconnects
(backoff 50 ms → 500 ms, for at most ``reconnect_timeout`` s) with a hello that
resumes the session by its token and carries the held manifest
(``proto.manifest.pack_held``), so the server sends nothing the cache already
holds; it reports a ``Redialled`` or a ``GaveUp`` on the same queue. The run's
client id goes in the URL's query (``with_client``) so a load balancer hashing
on it keeps the client on one replica.
"""

from __future__ import annotations

import queue
import threading
import time
from dataclasses import dataclass
from typing import Union
from urllib.parse import parse_qsl, urlencode, urlsplit, urlunsplit

import numpy as np
from websockets.exceptions import ConnectionClosed, ConnectionClosedOK, InvalidHandshake, InvalidURI
from websockets.sync.client import ClientConnection, connect

from proto.codec import decode_server, encode
from proto.errors import ProtocolError
from proto.manifest import pack_held
from proto.messages import MAX_HELD_BYTES, PROTOCOL_VERSION, Delta, Error, Hello, Ping, Pong, Resume, Welcome

__all__ = ["ClientError", "Arrived", "Closed", "Redialled", "GaveUp", "Item", "Link", "open_patiently",
           "with_client", "BACKOFF", "CLOSE_TIMEOUT", "FINAL_CODES"]

#: Redial backoff: the first retry after 50 ms, doubling to at most 500 ms.
BACKOFF = (0.05, 0.5)
#: Seconds a close handshake may take; a lost link must not hold the client up for longer.
CLOSE_TIMEOUT = 2.0
#: Refusals no retry can change: a resume is not attempted again after one of these.
FINAL_CODES = frozenset({"closed", "version", "invalid", "unknown_solver", "unknown_scene"})


class ClientError(RuntimeError):
    """The session could not be opened (refused, timed out, unreachable)."""


@dataclass(frozen=True)
class Closed:
    """The receiver's last item: the connection ended, and why."""

    reason: str


@dataclass(frozen=True)
class Arrived:
    """A delta as the receiver got it, stamped with its arrival; the frame loop applies and acks it."""

    delta: Delta
    t: float  # client time of arrival
    nbytes: int = 0  # the frame's size on the wire


@dataclass(frozen=True)
class Redialled:
    """The reconnector's success: a welcomed websocket, ready for a receiver thread."""

    ws: ClientConnection
    welcome: Welcome
    nbytes: int
    attempts: int


@dataclass(frozen=True)
class GaveUp:
    """The reconnector's failure: ``error`` is None when the server ended the session on purpose."""

    reason: str
    error: Error | None


Item = Union[Arrived, Error, Welcome, Closed, Redialled, GaveUp]


class _Refused(ClientError):
    """The server answered the hello with an ``error`` frame."""

    def __init__(self, error: Error) -> None:
        super().__init__(f"the server refused the session: {error.code}: {error.message}")
        self.error = error


def _as_error(exc: ProtocolError, what: str) -> Error:
    return Error(code=exc.code, message=f"{what}: {exc.message}"[:4096])


def check_url(url: str) -> str:
    """``url`` if it can name a walkstream endpoint, else ``ClientError`` saying what is wrong with it."""
    try:
        parts = urlsplit(url)
        port = parts.port
    except ValueError as exc:
        raise ClientError(f"bad URL {url!r}: {exc}") from None
    if parts.scheme not in ("ws", "wss"):
        hint = f"; try {urlunsplit(parts._replace(scheme='ws' if parts.scheme != 'https' else 'wss'))!r}" \
            if parts.scheme in ("http", "https") else ""
        raise ClientError(f"bad URL {url!r}: the scheme must be ws:// or wss://{hint}")
    if not parts.hostname:
        raise ClientError(f"bad URL {url!r}: it names no host")
    if port == 0:
        raise ClientError(f"bad URL {url!r}: port 0 cannot be connected to")
    if not parts.path.rstrip("/").endswith("/ws"):
        fixed = urlunsplit(parts._replace(path=parts.path.rstrip("/") + "/ws"))
        raise ClientError(f"bad URL {url!r}: the server's websocket is at /ws; try {fixed!r}")
    return url


def with_client(url: str, client_id: str) -> str:
    """``url`` with ``client=<id>`` in its query (replacing any), for a load balancer's ``hash $arg_client``."""
    parts = urlsplit(url)
    query = [(k, v) for k, v in parse_qsl(parts.query, keep_blank_values=True) if k != "client"]
    return urlunsplit(parts._replace(query=urlencode(query + [("client", client_id)])))


def _receive(ws: ClientConnection, inbox: "queue.Queue[Item]", counter: list[int], start: float,
             silence: float | None = None) -> None:
    """Background thread: frames → decoded messages on ``inbox``; pings answered here, at once.

    ``counter`` accumulates [bytes, pings, deltas] received.

    Ends with a ``Closed``. ``start`` is the client clock's origin (monotonic s).
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
                inbox.put(Arrived(msg, arrived, len(data)))
            else:
                inbox.put(msg)
    except ConnectionClosedOK:
        pass
    except ConnectionClosed as exc:
        reason = f"connection lost: {exc}"
    except Exception as exc:  # a local bug in the receiver must still end the run
        reason = f"receiver failed: {type(exc).__name__}: {exc}"
    inbox.put(Closed(reason))


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


def open_patiently(url: str, hello: Hello, timeout: float,
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


def _redial(url: str, hello: Hello, timeout: float, patience: float, inbox: "queue.Queue[Item]",
            stop: threading.Event) -> None:
    """Background thread: reconnect with ``hello`` (backoff 50 → 500 ms) until welcomed or ``patience`` s pass.

    Puts one ``Redialled`` or ``GaveUp`` on ``inbox`` — nothing if ``stop`` is
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
                inbox.put(GaveUp(f"the server closed the session: {exc.error.message}", None))
                return
            if exc.error.code == "bad_held" and hello.held is not None:
                hello = hello.model_copy(update={"held": None})  # resume without it rather than not at all
            elif exc.error.code in FINAL_CODES:
                inbox.put(GaveUp(f"cannot resume: {exc}", exc.error))
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
            inbox.put(Redialled(ws, welcome, nbytes, attempts))
            return
        if time.monotonic() + delay >= deadline:
            message = f"could not reconnect within {patience:g} s ({attempts} attempts); last: {last}"
            inbox.put(GaveUp(message, Error(code="connection_lost", message=message[:4096])))
            return
        stop.wait(delay)
        delay = min(2 * delay, BACKOFF[1])


class Link:
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

    def attach(self, ws: ClientConnection, welcome: Welcome, nbytes: int, inbox: "queue.Queue[Item]") -> None:
        """Make ``ws`` the current connection and start its receiver."""
        self.ws, self.welcome, self.counter = ws, welcome, [nbytes, 0, 0]
        self.receiver = threading.Thread(target=_receive, args=(ws, inbox, self.counter, self.start, self.silence),
                                         name="ws-receive", daemon=True)
        self.receiver.start()

    @property
    def can_redial(self) -> bool:
        return self.patience > 0 and self.welcome is not None and bool(self.welcome.token)

    def redial(self, held: np.ndarray, now: float, reason: str, inbox: "queue.Queue[Item]") -> None:
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
