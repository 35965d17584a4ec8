"""The client's side of the websocket: opening a session, receiving, and redialling a lost link.

A background thread (``_receive``) only receives and decodes frames onto the
frame loop's queue: it answers a ``ping`` at once with a ``pong`` (the server
measures the round trip and this clock's offset from it) and stamps each delta
with its arrival time (``Arrived``), which the frame loop acks once the delta
is applied. It ends with a ``Closed``.

A lost connection does not end the run: while the frame loop keeps drawing
what is resident, ``Link.redial`` starts a background thread that reconnects
with a hello that resumes the session by its token and carries the held
manifest (``proto.manifest.pack_held``), so the server sends nothing the cache
already holds; it reports a ``Redialled`` or a ``GaveUp`` on the same queue.

A run may name several server URLs. Dialling goes in rounds: each round tries
every URL once, in turn, starting with the one last connected to (a blip of
the network finds the session where it was; a dead server refuses at once and
the next URL is tried without waiting); between rounds it waits a ``Backoff``
— exponential, capped, jittered so that a fleet of kiosks cut off together
does not redial in step. A server that shares session state (Redis) resumes
the session; one that does not know it starts a fresh one that adopts the
held manifest — either way nothing held is sent again. ``patience`` may be
infinite: a kiosk never gives up. The run's client id goes in each URL's query
(``with_client``) so a load balancer hashing on it keeps the client on one
replica.
"""

from __future__ import annotations

import logging
import math
import queue
import random
import threading
import time
from dataclasses import dataclass
from typing import Callable, Sequence, Union
from urllib.parse import parse_qsl, urlencode, urlsplit, urlunsplit

import numpy as np
from websockets.exceptions import ConnectionClosed, ConnectionClosedOK, InvalidHandshake, InvalidURI
from websockets.sync.client import ClientConnection, connect

from proto.codec import decode_server, encode
from proto.errors import ProtocolError
from proto.manifest import pack_held
from proto.messages import MAX_HELD_BYTES, PROTOCOL_VERSION, Delta, Error, Hello, Ping, Pong, Resume, Welcome

__all__ = ["ClientError", "Arrived", "Closed", "Redialled", "GaveUp", "Item", "Link", "Backoff", "open_patiently",
           "with_client", "as_urls", "BACKOFF", "CLOSE_TIMEOUT", "FINAL_CODES"]

log = logging.getLogger("walkstream.client")

#: Redial backoff between rounds of dialling: the first after 50 ms, doubling to at most 4 s. The cap bounds
#: how long a kiosk stays dark to a server that is back: the next round starts at most this long after it
#: returns, so deltas flow again within about 5 s of a network's return.
BACKOFF = (0.05, 4.0)
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
    """A dial's success: a welcomed websocket, ready for a receiver thread; ``url`` is the server that answered."""

    ws: ClientConnection
    welcome: Welcome
    nbytes: int
    attempts: int
    url: str = ""


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


def as_urls(urls: str | Sequence[str]) -> tuple[str, ...]:
    """One URL or several, as a non-empty tuple (``ValueError`` when there is none)."""
    out = (urls,) if isinstance(urls, str) else tuple(urls)
    if not out or not all(isinstance(u, str) and u for u in out):
        raise ValueError(f"urls: give one server URL or a non-empty list of them, got {urls!r}")
    return out


class Backoff:
    """How long to wait before each round of dialling: exponential, capped, jittered.

    Round 0 starts at once; before round ``r`` ≥ 1 the wait is drawn uniformly
    from [d/2, d] with d = min(cap, base · 2^(r−1)) ("equal jitter": never less
    than half the step, so a fleet spreads out without hammering). ``random``
    returns floats in [0, 1) — injected so tests can pin the draws.
    """

    def __init__(self, base: float = BACKOFF[0], cap: float = BACKOFF[1],
                 random: Callable[[], float] = random.random) -> None:
        if not (math.isfinite(base) and base > 0):
            raise ValueError(f"base: must be a positive number of seconds, got {base!r}")
        if not (math.isfinite(cap) and cap >= base):
            raise ValueError(f"cap: must be a number of seconds ≥ base ({base:g}), got {cap!r}")
        self.base, self.cap, self.random = base, cap, random

    def step(self, round: int) -> float:
        """The un-jittered wait before ``round`` (0 for round 0)."""
        if round <= 0:
            return 0.0
        return min(self.cap, self.base * 2.0 ** min(round - 1, 64))

    def wait(self, round: int) -> float:
        """Seconds to wait before ``round``: a draw from [step/2, step]."""
        d = self.step(round)
        return d * (0.5 + 0.5 * self.random()) if d else 0.0


class _OutOfPatience(ClientError):
    """No server welcomed the hello within the patience (or the dial was stopped)."""


def _dial(urls: tuple[str, ...], first: int, hello: Hello, timeout: float, patience: float, backoff: Backoff,
          stop: threading.Event, *, wait_unreachable: bool, final: Callable[[str], bool],
          on_attempt: Callable[[str, int], None] | None = None) -> Redialled:
    """Dial ``urls`` in rounds (each from ``urls[first]``, in turn) until one welcomes ``hello``.

    A ``busy`` answer, an unreachable server (when ``wait_unreachable``) or a
    ``bad_held`` (the hello is sent on without its manifest) move on to the next
    URL; a refusal whose code is ``final`` takes that URL out of the rotation,
    and raises ``_Refused`` once no URL is left — at once for ``closed``: an
    administrator ended the session on purpose. Raises ``_OutOfPatience`` when
    the next round would start after ``patience`` s (or ``stop`` is set), and,
    without ``wait_unreachable``, ``ClientError`` after a round in which no
    server answered at all.
    """
    deadline = time.monotonic() + patience
    n = len(urls)
    order = [(first + k) % n for k in range(n)]
    out: set[int] = set()  # URLs whose refusal no retry can change
    attempts, rnd, last = 0, 0, "no attempt made"
    while not stop.is_set():
        answered = False
        for i in order:
            if i in out or stop.is_set():
                continue
            attempts += 1
            if on_attempt is not None:
                on_attempt(urls[i], attempts)
            left = deadline - time.monotonic()
            try:
                ws, welcome, nbytes = _open(urls[i], hello, max(0.05, min(timeout, left)))
            except _Refused as exc:
                answered = True
                code = exc.error.code
                if code == "closed":
                    raise
                if code == "bad_held" and hello.held is not None:
                    hello = hello.model_copy(update={"held": None})  # resume without it rather than not at all
                elif code != "busy" and final(code):
                    out.add(i)
                    if len(out) == n:
                        raise
                last = f"{urls[i]}: {exc}"
            except ClientError as exc:
                last = str(exc)
            except Exception as exc:  # a local bug must still end the wait
                last = f"{urls[i]}: {type(exc).__name__}: {exc}"
            else:
                if stop.is_set():
                    ws.close_socket()
                    break
                return Redialled(ws, welcome, nbytes, attempts, urls[i])
        if stop.is_set():
            break
        if not answered and not wait_unreachable:
            raise ClientError(last)
        rnd += 1
        if rnd & (rnd - 1) == 0:  # rounds 1, 2, 4, 8, …: a long outage leaves a trace, not a flood
            log.warning("no server welcomed the session (round %d, %d attempts); last: %s", rnd, attempts, last)
        delay = backoff.wait(rnd)
        if time.monotonic() + delay >= deadline:
            raise _OutOfPatience(f"no server welcomed the session within {patience:g} s "
                                 f"({attempts} attempts); last: {last}")
        stop.wait(delay)
    raise _OutOfPatience(f"stopped after {attempts} attempts; last: {last}")


def open_patiently(urls: str | Sequence[str], hello: Hello, timeout: float, patience: float, *,
                   wait_unreachable: bool = False, backoff: Backoff | None = None,
                   stop: threading.Event | None = None,
                   on_attempt: Callable[[str, int], None] | None = None) -> Redialled:
    """Open the session on the first of ``urls`` to welcome ``hello``, dialling in rounds for up to ``patience`` s.

    A ``busy`` server is retried (after the others) with ``backoff`` between
    rounds; any other refusal is final for that server; an unreachable one is passed over, and a round in which no server
    answered raises ``ClientError`` — unless ``wait_unreachable`` (a kiosk that
    boots before its server), which keeps dialling. ``patience`` may be
    ``math.inf``; ``stop`` ends such a wait (``ClientError``). ``on_attempt(url,
    attempts)`` is called before each dial (e.g. to tell systemd the start is
    still going). Returns the welcomed connection, how many dials it took and
    which URL answered.
    """
    try:
        return _dial(as_urls(urls), 0, hello, timeout, patience, backoff or Backoff(), stop or threading.Event(),
                     wait_unreachable=wait_unreachable, final=lambda code: True, on_attempt=on_attempt)
    except _OutOfPatience as exc:
        raise ClientError(str(exc)) from None


def _redial(urls: tuple[str, ...], first: int, hello: Hello, timeout: float, patience: float, backoff: Backoff,
            inbox: "queue.Queue[Item]", stop: threading.Event) -> None:
    """Background thread: ``_dial`` with ``hello`` until welcomed, every URL in turn, for ``patience`` s.

    Puts one ``Redialled`` or ``GaveUp`` on ``inbox`` — nothing if ``stop`` is
    set first (the run ended; a socket won meanwhile is closed here).
    """
    try:
        won = _dial(urls, first, hello, timeout, patience, backoff, stop, wait_unreachable=True,
                    final=FINAL_CODES.__contains__)
    except _Refused as exc:
        if exc.error.code == "closed":
            inbox.put(GaveUp(f"the server closed the session: {exc.error.message}", None))
        else:
            inbox.put(GaveUp(f"cannot resume: {exc}", exc.error))
        return
    except ClientError as exc:
        if not stop.is_set():
            message = f"could not reconnect: {exc}"
            inbox.put(GaveUp(message, Error(code="connection_lost", message=message[:4096])))
        return
    inbox.put(won)


class Link:
    """The connection side of a run: the current websocket and its receiver, and how to get another.

    ``urls`` are the servers to dial, in turn (one URL or several); ``url`` is
    the one the current (or last) connection went to. ``hello`` is the run's
    first hello; a redial adds ``resume`` (the session and token of the last
    welcome) and ``held``. ``patience`` is ``reconnect_timeout`` (``math.inf``:
    never give up); ``backoff`` spaces the rounds of redialling.
    """

    def __init__(self, urls: str | Sequence[str], hello: Hello, start: float, *, timeout: float, patience: float,
                 silence: float | None, backoff: Backoff | None = None) -> None:
        self.urls = as_urls(urls)
        self.current = 0  # index in ``urls`` of the current (or last) connection's server
        self.hello, self.start = hello, start
        self.timeout, self.patience, self.silence = timeout, patience, silence
        self.backoff = backoff or Backoff()
        self.ws: ClientConnection | None = None
        self.welcome: Welcome | None = None
        self.counter = [0, 0, 0]  # bytes received, pings answered and deltas received on the current connection
        self.receiver: threading.Thread | None = None
        self.redialler: threading.Thread | None = None
        self.stop = threading.Event()
        self.lost_at = 0.0
        self.reason = ""
        self.held = 0  # representations the pending redial's manifest names

    @property
    def url(self) -> str:
        return self.urls[self.current]

    def attach(self, ws: ClientConnection, welcome: Welcome, nbytes: int, inbox: "queue.Queue[Item]",
               url: str | None = None) -> None:
        """Make ``ws`` (a connection to ``url``, one of ``urls``) the current connection and start its receiver."""
        if url is not None:
            self.current = self.urls.index(url)
        self.ws, self.welcome, self.counter = ws, welcome, [nbytes, 0, 0]
        self.receiver = threading.Thread(target=_receive, args=(ws, inbox, self.counter, self.start, self.silence),
                                         name="ws-receive", daemon=True)
        self.receiver.start()

    @property
    def can_redial(self) -> bool:
        return self.patience > 0 and self.welcome is not None and bool(self.welcome.token)

    def redial(self, held: np.ndarray, seq: int, now: float, reason: str, inbox: "queue.Queue[Item]") -> None:
        """Start the background redial, resuming the last welcome's session with ``held`` as the manifest and
        ``seq`` as the last delta applied (-1: none).

        It dials the last server first, then the others in turn.
        """
        assert self.welcome is not None
        self.lost_at, self.reason, self.ws = now, reason, None
        blob = pack_held(held)
        self.held = int(held.size) if len(blob) <= MAX_HELD_BYTES else 0
        hello = self.hello.model_copy(update={
            "resume": Resume(session=self.welcome.session, token=self.welcome.token,
                             seq=seq if seq >= 0 else None),
            "held": blob if self.held or held.size == 0 else None,
        })
        self.stop.clear()
        self.redialler = threading.Thread(target=_redial, args=(self.urls, self.current, hello, self.timeout,
                                                                self.patience, self.backoff, inbox, self.stop),
                                          name="ws-redial", daemon=True)
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
