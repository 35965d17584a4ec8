"""The client's clock as the server sees it: offset and round trip from pings, delivery time from acks.

A session's time base is the client's clock (its frames happen there). The
server pings; the client answers at once with its own time. For each pair the
offset is client − midpoint of the server's send and receive times, accurate to
half the asymmetry of the round trip, so the sample with the smallest round
trip among the recent ones is trusted (NTP's minimum-delay filter).

Acks say when a delta reached the client. Its delivery time less half a round
trip, over its size, measures the bandwidth the link gives this session; the
server uses both to choose an interval a schedule reaches in time.
"""

from __future__ import annotations

from collections import deque

import numpy as np

from .select.snapshot import dump_fields, load_fields

__all__ = ["ClockSync", "Delivery"]


class ClockSync:
    """Offset (client − server, s) and round trip (s) from the last ``keep`` ping/pong pairs."""

    def __init__(self, keep: int = 8) -> None:
        self._samples: deque[tuple[float, float]] = deque(maxlen=keep)  # (rtt, offset)
        self._guess: float | None = None
        self._best: tuple[float, float] | None = None  # min(_samples), kept: a session reads it at every poll

    def add(self, sent: float, client_t: float, received: float) -> None:
        """One ping sent at server time ``sent``, answered at client time ``client_t``, back at ``received``."""
        rtt = received - sent
        if not (np.isfinite(rtt) and rtt >= 0 and np.isfinite(client_t)):
            return
        self._samples.append((rtt, client_t - 0.5 * (sent + received)))
        self._best = min(self._samples)

    def observe(self, client_t: float, received: float) -> None:
        """A stamped client message: until a pong arrives, its stamp gives a first (late-biased) offset."""
        if self._guess is None and np.isfinite(client_t):
            self._guess = client_t - received

    @property
    def known(self) -> bool:
        return bool(self._samples)

    @property
    def offset(self) -> float:
        if self._samples:
            return self._min()[1]
        return self._guess if self._guess is not None else 0.0

    @property
    def rtt(self) -> float:
        return self._min()[0] if self._samples else 0.0

    def _min(self) -> tuple[float, float]:
        if self._best is None:
            self._best = min(self._samples)
        return self._best

    #: The fields a snapshot holds (a snapshot without them still loads).
    STATE = ("_samples", "_guess")

    def to_state(self) -> dict:
        return dump_fields(self, self.STATE)

    def from_state(self, state) -> None:
        """Take in ``to_state``'s data; ValueError (clock unchanged) if it does not fit."""
        load_fields(self, state, self.STATE, "clock", optional=True)
        self._best = None

    def client_time(self, server_now: float) -> float:
        return server_now + self.offset

    def server_time(self, client_t: float) -> float:
        return client_t - self.offset


class Delivery:
    """How long a delta takes from the start of its selection to the client: selection + rtt/2 + bytes / bandwidth.

    bandwidth starts at ``bandwidth`` bytes/s and follows the median of what
    recent acks of deltas of at least ``min_bytes`` imply; ``last`` is the last
    measured time from the start of a selection to the delta's arrival.
    """

    def __init__(self, bandwidth: float = 10e6, keep: int = 8, min_bytes: int = 16 * 1024) -> None:
        self.bandwidth = float(bandwidth)
        self.min_bytes = int(min_bytes)
        self._rates: deque[float] = deque(maxlen=keep)
        self._sent: dict[int, tuple[float, int]] = {}
        self.last: float | None = None  # the last measured delivery time (s)

    def sent(self, seq: int, server_now: float, nbytes: int, select_time: float = 0.0) -> None:
        """Delta ``seq`` of ``nbytes`` leaves; its selection started at ``server_now`` and took ``select_time``."""
        self._sent[seq] = (server_now, int(nbytes), float(select_time))
        if len(self._sent) > 64:  # acks that never came: forget the oldest
            self._sent.pop(min(self._sent))

    def acked(self, seq: int, client_t: float, clock: ClockSync) -> float | None:
        """Record the ack of delta ``seq``; returns its delivery time (s), or None for an unknown seq."""
        entry = self._sent.pop(seq, None)
        if entry is None:
            return None
        sent_at, nbytes, select_time = entry
        took = clock.server_time(client_t) - sent_at
        self.last = took
        transfer = took - select_time - 0.5 * clock.rtt
        if nbytes >= self.min_bytes:
            # A transfer too quick to see (a fast link, or estimates that overshoot) still says the link is fast:
            # counted as a millisecond, capped at 1 GB/s, rather than left at the first guess.
            self._rates.append(min(nbytes / max(transfer, 1e-3), 1e9))
            self.bandwidth = float(np.median(self._rates))
        return took

    def in_flight(self, server_now: float, max_age: float = 5.0) -> int:
        """Bytes of deltas sent less than ``max_age`` seconds ago and not yet acked: what still fills the link
        (older ones are taken as lost, so a client that stopped acking cannot stall the stream for ever)."""
        return int(sum(n for at, n, _ in self._sent.values() if server_now - at < max_age))

    def estimate(self, nbytes: float, clock: ClockSync) -> float:
        return 0.5 * clock.rtt + float(nbytes) / self.bandwidth

    #: The fields a snapshot holds: the link's figures, not the deltas in flight (a resume restarts them).
    STATE = ("bandwidth", "min_bytes", "_rates", "last")

    def to_state(self) -> dict:
        return dump_fields(self, self.STATE)

    def from_state(self, state) -> None:
        """Take in ``to_state``'s data; ValueError (delivery unchanged) if it does not fit."""
        load_fields(self, state, self.STATE, "delivery", optional=True)
