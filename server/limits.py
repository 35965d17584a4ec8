"""What one replica allows: sessions, message rate, idleness, frame size, keepalive, worker threads.

The limits protect the replica and the other sessions from one client: a
flood is dropped (and answered, at most once a second) rather than queued, an
idle connection is closed rather than kept, and past ``max_sessions`` a new
connection is refused cleanly so a load balancer can try another replica.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field

__all__ = ["ReplicaLimits", "TokenBucket", "RateGuard", "WS_MAX_SIZE"]

#: Frames above this are refused by the websocket layer itself (close 1009); between
#: ``proto.codec.MAX_CLIENT_FRAME`` and this, the codec answers with a ``too_large`` error frame.
WS_MAX_SIZE = 1024 * 1024


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
    workers : threads of the selection pool
    state_ttl : seconds a saved session state is kept for a resume
    save_interval : the least seconds between two saves of one session's state after acks
    send_buffer : kernel send buffer per connection (bytes; None: the kernel's autotuning, up to
        tcp_wmem's maximum — megabytes per client). Smaller bounds the memory a slow client pins and
        makes backpressure reach its session sooner.
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
    workers: int = field(default_factory=_cpus)
    state_ttl: float = 300.0
    save_interval: float = 0.25
    send_buffer: int | None = None

    def __post_init__(self) -> None:
        def positive(name: str, low: float = 0.0, high: float = math.inf) -> None:
            value = getattr(self, name)
            if not isinstance(value, (int, float)) or isinstance(value, bool) or not math.isfinite(value):
                raise ValueError(f"{name} must be a finite number, got {value!r}")
            if not low < value <= high:
                raise ValueError(f"{name} must lie in ({low:g}, {high:g}], got {value!r}")

        for name in ("max_sessions", "workers", "max_message"):
            if not isinstance(getattr(self, name), int) or isinstance(getattr(self, name), bool):
                raise ValueError(f"{name} must be an integer, got {getattr(self, name)!r}")
        positive("max_sessions", 0, 1_000_000)
        positive("workers", 0, 1024)
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

    def take(self, now: float) -> bool:
        """True if a message arriving at ``now`` may pass (and spend its token)."""
        self.tokens = min(self.burst, self.tokens + (now - self.at) * self.rate)
        self.at = now
        if self.tokens >= 1.0 - 1e-9:  # a client exactly at the rate must not lose to rounding
            self.tokens -= 1.0
            return True
        return False


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
        self.abuse_since: float | None = None
        self.last_drop = -math.inf
        self.last_answer = -math.inf
        self.dropped = 0

    def check(self, now: float) -> str:
        if self.bucket.take(now):
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
