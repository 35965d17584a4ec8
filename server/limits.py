"""What one replica allows: sessions, connections, message and byte rates, idleness, frame size, keepalive.

The limits protect the replica and the other sessions from one client: a
flood is dropped (and answered, at most once a second) rather than queued, an
idle connection is closed rather than kept, and past ``max_sessions`` a new
connection is refused cleanly so a load balancer can try another replica. A
connection holds no session slot until its hello: it must say one within
``hello_timeout``, frames the server refuses never count as being heard, and
past ``max_bad_frames`` refusals it is closed. ``max_per_address`` caps the
connections one remote host may hold open (behind a trusted proxy, the
address its ``X-Real-IP`` names).
"""

from __future__ import annotations

import ipaddress
import math
import os
from dataclasses import dataclass, field
from typing import Mapping

from proto.codec import MAX_CLIENT_FRAME

__all__ = ["ReplicaLimits", "TokenBucket", "RateGuard", "Admission", "WS_MAX_SIZE", "remote_address", "MEASUREMENT_SOLVERS"]

#: Solvers meant for measurement: unbounded in time, so clients get them only where the server allows it.
MEASUREMENT_SOLVERS = frozenset({"exact"})

#: Frames above the protocol's limit are refused by the websocket layer itself (close 1009) from their
#: header, before their payload is read or buffered.
WS_MAX_SIZE = MAX_CLIENT_FRAME


def _cpus() -> int:
    return os.cpu_count() or 1


@dataclass(frozen=True)
class ReplicaLimits:
    """Per-replica limits (``walkstream serve`` options of the same names).

    max_sessions : websocket connections served at once; past it: Error("busy"), close 1013
    rate, burst : a session's token bucket (messages per second, and the most at once)
    rate_error_interval : seconds between two ``rate_limited`` answers to one session
    abuse_close : seconds of sustained flooding (a dropped message in every second) before close 1008
    idle_timeout : seconds without any client message before Error("idle") and close 1000
    max_message : bytes of the largest frame uvicorn accepts at all (close 1009 above it)
    ping_interval, ping_timeout : uvicorn's websocket keepalive pings (seconds)
    threads : threads of the pool that builds a hello's scene tables, restores and snapshots (per worker
        process); selections run in ticks on the event loop
    state_ttl : seconds a saved session state is kept for a resume
    save_interval : the least seconds between two saves of one session's state (after deltas, acks and frames).
        A resume sends nothing the client holds whatever the save's age (its hello names what it holds); what
        an older save loses is the cost model's and the predictor's last second of learning.
    send_buffer : kernel send buffer per connection (bytes; None: the kernel's autotuning, up to
        tcp_wmem's maximum — megabytes per client). Smaller bounds the memory a slow client pins and
        makes backpressure reach its session sooner.
    hello_timeout : seconds a new connection has to say a valid hello before it is closed
    max_bad_frames : refused frames one connection may send; the next closes it (1008)
    max_per_address : connections one remote address may hold open at once
    max_pending : connections without a hello yet, replica-wide, at once
    connect_rate, connect_burst : new connections one remote address may open (a token bucket per address:
        a client that reconnects after every refusal costs the replica a handshake each time)
    byte_rate, byte_burst : a connection's token bucket in bytes (per second, and the most at once)
    inbox_bytes : bytes of received frames a connection may have waiting for its session; past it the
        server stops reading that socket (TCP backpressure reaches the sender)
    trusted_proxies : addresses (or networks) of reverse proxies whose ``X-Real-IP`` (else the last ``X-Forwarded-For``)
        names the client's address
    allow_measurement_solvers : let clients ask for solvers meant for measurement only (``exact``)
    docs : serve the interactive API docs at /docs (their page loads its scripts from a public CDN)
    """

    max_sessions: int = 256
    rate: float = 200.0
    burst: float = 400.0
    rate_error_interval: float = 1.0
    abuse_close: float = 5.0
    idle_timeout: float = 60.0
    max_message: int = WS_MAX_SIZE
    ping_interval: float = 20.0
    ping_timeout: float = 20.0
    threads: int = field(default_factory=_cpus)
    state_ttl: float = 300.0
    save_interval: float = 1.0
    send_buffer: int | None = None
    hello_timeout: float = 5.0
    max_bad_frames: int = 16
    max_per_address: int = 32
    max_pending: int = 256
    connect_rate: float = 10.0
    connect_burst: float = 40.0
    byte_rate: float = 256 * 1024
    byte_burst: float = 4 * MAX_CLIENT_FRAME
    inbox_bytes: int = 4 * MAX_CLIENT_FRAME
    trusted_proxies: tuple[str, ...] = ()
    allow_measurement_solvers: bool = False
    docs: bool = False

    def __post_init__(self) -> None:
        def positive(name: str, low: float = 0.0, high: float = math.inf) -> None:
            value = getattr(self, name)
            if not isinstance(value, (int, float)) or isinstance(value, bool) or not math.isfinite(value):
                raise ValueError(f"{name} must be a finite number, got {value!r}")
            if not low < value <= high:
                raise ValueError(f"{name} must lie in ({low:g}, {high:g}], got {value!r}")

        for name in ("max_sessions", "threads", "max_message", "max_bad_frames", "max_per_address", "max_pending",
                     "inbox_bytes"):
            if not isinstance(getattr(self, name), int) or isinstance(getattr(self, name), bool):
                raise ValueError(f"{name} must be an integer, got {getattr(self, name)!r}")
        positive("max_sessions", 0, 1_000_000)
        positive("threads", 0, 1024)
        positive("max_message", 1024, 1 << 30)
        positive("rate", 0, 1e6)
        positive("burst", 0, 1e7)
        if self.burst < 1:
            raise ValueError(f"burst must be at least 1 message, got {self.burst!r}")
        positive("rate_error_interval", 0, 3600)
        positive("abuse_close", 0, 3600)
        positive("idle_timeout", 0, 86400)
        positive("ping_interval", 0, 3600)
        positive("ping_timeout", 0, 3600)
        positive("state_ttl", 0, 30 * 86400)
        positive("save_interval", 0, 3600)
        positive("hello_timeout", 0, 3600)
        positive("max_bad_frames", 0, 1_000_000)
        positive("max_per_address", 0, 1_000_000)
        positive("max_pending", 0, 1_000_000)
        positive("connect_rate", 0, 1e6)
        positive("connect_burst", 0, 1e7)
        if self.connect_burst < 1:
            raise ValueError(f"connect_burst must be at least 1 connection, got {self.connect_burst!r}")
        positive("byte_rate", 0, 1 << 34)
        positive("byte_burst", 0, 1 << 34)
        if self.byte_burst < self.max_message:
            raise ValueError(f"byte_burst must hold one largest frame ({self.max_message} bytes), "
                             f"got {self.byte_burst!r}")
        positive("inbox_bytes", 0, 1 << 34)
        if self.inbox_bytes < self.max_message:
            raise ValueError(f"inbox_bytes must hold one largest frame ({self.max_message} bytes), "
                             f"got {self.inbox_bytes!r}")
        for address in self.trusted_proxies:
            try:
                ipaddress.ip_network(address, strict=False)
            except ValueError:
                raise ValueError(f"trusted_proxies must be IP addresses or networks, got {address!r}") from None
        if self.send_buffer is not None:
            if not isinstance(self.send_buffer, int) or isinstance(self.send_buffer, bool):
                raise ValueError(f"send_buffer must be an integer, got {self.send_buffer!r}")
            positive("send_buffer", 4095, 1 << 30)


class TokenBucket:
    """``rate`` tokens a second, at most ``burst`` saved; one message takes one. Clock injected."""

    __slots__ = ("rate", "burst", "tokens", "at")

    def __init__(self, rate: float, burst: float, now: float) -> None:
        self.rate, self.burst = float(rate), float(burst)
        self.tokens, self.at = float(burst), now

    def take(self, now: float, amount: float = 1.0) -> bool:
        """True if ``amount`` (one message, or its bytes) arriving at ``now`` may pass (and spend its tokens)."""
        self.refill(now)
        if self.tokens >= amount - 1e-9:  # a client exactly at the rate must not lose to rounding
            self.tokens -= amount
            return True
        return False

    def refill(self, now: float) -> None:
        self.tokens = min(self.burst, self.tokens + (now - self.at) * self.rate)
        self.at = now


class RateGuard:
    """One session's rate limit: decides per message whether to pass, drop, answer, or close.

    A dropped message is answered with ``rate_limited`` at most once per
    ``rate_error_interval``; drops in every second for ``abuse_close`` seconds
    running are abuse, and the connection is closed.
    """

    PASS, DROP, ANSWER, CLOSE = "pass", "drop", "answer", "close"

    def __init__(self, limits: ReplicaLimits, now: float) -> None:
        self.limits = limits
        self.bucket = TokenBucket(limits.rate, limits.burst, now)
        self.bytes = TokenBucket(limits.byte_rate, limits.byte_burst, now)
        self.abuse_since: float | None = None
        self.last_drop = -math.inf
        self.last_answer = -math.inf
        self.dropped = 0

    def check(self, now: float, nbytes: int = 0) -> str:
        """The verdict on a message of ``nbytes`` arriving at ``now``: both buckets must pass it."""
        self.bytes.refill(now)
        if self.bytes.tokens >= nbytes - 1e-9 and self.bucket.take(now):
            self.bytes.tokens -= nbytes
            return self.PASS
        self.dropped += 1
        if now - self.last_drop > 1.0:  # a quiet second ends a streak of abuse
            self.abuse_since = now
        self.last_drop = now
        if now - self.abuse_since >= self.limits.abuse_close:
            return self.CLOSE
        if now - self.last_answer >= self.limits.rate_error_interval:
            self.last_answer = now
            return self.ANSWER
        return self.DROP


def _trusted(peer: str, trusted: tuple[str, ...]) -> bool:
    if not trusted:
        return False
    try:
        address = ipaddress.ip_address(peer)
    except ValueError:
        return False
    return any(address in ipaddress.ip_network(net, strict=False) for net in trusted)


def remote_address(peer: str | None, headers: Mapping[str, str], trusted: tuple[str, ...]) -> str:
    """The client's address: the socket's peer, or what a trusted proxy in front of us says it is."""
    peer = peer or "unknown"
    if not _trusted(peer, trusted):
        return peer
    claimed = headers.get("x-real-ip", "").strip()
    if not claimed:
        forwarded = [a.strip() for a in headers.get("x-forwarded-for", "").split(",") if a.strip()]
        claimed = forwarded[-1] if forwarded else ""
    try:
        return str(ipaddress.ip_address(claimed))
    except ValueError:
        return peer


class Admission:
    """Whether a new connection from an address may open: sessions, pending hellos, per-address count and rate.

    ``admit`` returns None (admitted: counted until ``release``) or (reason, sentence). Clock injected.
    """

    FORGET_ABOVE = 4096  # addresses remembered before those whose buckets refilled are forgotten

    def __init__(self, limits: ReplicaLimits) -> None:
        self.limits = limits
        self.open: dict[str, int] = {}
        self.opened: dict[str, TokenBucket] = {}

    def admit(self, address: str, now: float, sessions: int, pending: int) -> tuple[str, str] | None:
        lim = self.limits
        if sessions >= lim.max_sessions:
            return "busy", f"this replica serves its maximum of {lim.max_sessions} sessions; try another or later"
        bucket = self.opened.setdefault(address, TokenBucket(lim.connect_rate, lim.connect_burst, now))
        if len(self.opened) > self.FORGET_ABOVE:
            for key, b in list(self.opened.items()):
                if key != address and b.tokens + (now - b.at) * b.rate >= b.burst:
                    del self.opened[key]
        if not bucket.take(now):
            return "connect_rate", (f"{address} opens more than {lim.connect_rate:g} connections a second; "
                                    "wait before reconnecting")
        if self.open.get(address, 0) >= lim.max_per_address:
            return "address", f"{address} holds {lim.max_per_address} connections to this replica already, its maximum"
        if pending >= lim.max_pending:
            return "pending", f"{lim.max_pending} connections are waiting for their hello; try another replica or later"
        self.open[address] = self.open.get(address, 0) + 1
        return None

    def release(self, address: str) -> None:
        left = self.open.get(address, 0) - 1
        if left > 0:
            self.open[address] = left
        else:
            self.open.pop(address, None)
