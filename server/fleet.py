"""The fleet: every kiosk that reports to this server, whether it still draws, and what it last said.

Theory of operation. A kiosk's session sends a ``Heartbeat`` every
``interval`` seconds (proto ``Heartbeat``): frames drawn since it started, its
frame times, memory, cache and where its tour is. ``Fleet.heard`` records one;
``Fleet.closed`` marks the kiosks of a session that ended. The registry is keyed
by kiosk id, not by session: a kiosk that reconnects as a new session keeps its
row and its history, and one whose session ended stays listed, marked
disconnected, so a dead kiosk is visible rather than silently gone.

Alive means drawing: a kiosk is **stale** when its ``frames`` have not advanced
(in server time) for more than ``STALE_INTERVALS`` × its heartbeat interval. A
kiosk whose process hangs or is stopped sends nothing, so it never advances and
goes stale by the same rule; so does one that still sends heartbeats while its
renderer is stuck. A kiosk's first heartbeat counts as an advance (there is
nothing to compare it with yet).

Two live sessions that both report one kiosk id (two machines configured
alike, or a kiosk that dialled again before the server noticed its old
connection was dead) share the row — the newest heartbeat is shown — and the
row is marked ``duplicate`` while more than one of them reports.

Bounded: each kiosk keeps its last ``history`` heartbeats' figures and its last
``recent`` frame times; a disconnected kiosk is forgotten ``forget_after``
seconds after it was last heard, and at most ``keep_gone`` disconnected kiosks
are kept (the longest silent forgotten first). A session reports one kiosk id
(``Session`` refuses another), so live rows are at most the live sessions.

Pure: no clock and no I/O. The caller passes ``now`` (server seconds, one
monotonic clock) to every call; ``rows`` returns plain JSON-ready dicts whose
times are ages in seconds, so rows of several worker processes ``merge``.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

from proto.messages import Heartbeat

__all__ = ["Fleet", "Kiosk", "merge", "STALE_INTERVALS"]

#: A kiosk whose frames have not advanced for this many heartbeat intervals is stale.
STALE_INTERVALS = 2.0


@dataclass
class Kiosk:
    """One kiosk as the server knows it (server times in seconds)."""

    id: str
    session: str
    first_heard: float
    last: Heartbeat
    last_heard: float
    last_advance: float
    history: deque = field(default_factory=deque)  # (server time, frame_p95, fps, rss) per heartbeat
    recent: deque = field(default_factory=deque)  # the last frame times (s), oldest first
    heartbeats: int = 0
    restarts: int = 0  # heartbeats whose ``frames`` went back: the kiosk's process started again
    connected: bool = True
    gone_at: float | None = None  # when its last session ended (None while one is live)
    claims: dict = field(default_factory=dict)  # session id → when it last reported this kiosk (live only)

    def stale(self, now: float) -> bool:
        return now - self.last_advance > STALE_INTERVALS * self.last.interval

    def duplicate(self, now: float) -> bool:
        window = STALE_INTERVALS * self.last.interval
        return sum(1 for t in self.claims.values() if now - t <= window) > 1


class Fleet:
    """The kiosks heard from, by id.

    history : heartbeats' figures kept per kiosk (the sparklines' points)
    recent : frame times kept per kiosk (the last ``recent`` the heartbeats carried)
    keep_gone : disconnected kiosks kept at most
    forget_after : seconds after which a disconnected kiosk is forgotten
    """

    def __init__(self, history: int = 120, recent: int = 240, keep_gone: int = 64,
                 forget_after: float = 3600.0) -> None:
        for name, value in (("history", history), ("recent", recent)):
            if int(value) < 1:
                raise ValueError(f"Fleet {name} must be at least 1, got {value}")
        if int(keep_gone) < 0:
            raise ValueError(f"Fleet keep_gone must be at least 0, got {keep_gone}")
        if not forget_after > 0:
            raise ValueError(f"Fleet forget_after must be positive seconds, got {forget_after}")
        self.history, self.recent = int(history), int(recent)
        self.keep_gone, self.forget_after = int(keep_gone), float(forget_after)
        self.kiosks: dict[str, Kiosk] = {}

    def __len__(self) -> int:
        return len(self.kiosks)

    def heard(self, session: str, beat: Heartbeat, now: float) -> None:
        """Session ``session`` reported ``beat`` at server time ``now``."""
        k = self.kiosks.get(beat.kiosk)
        if k is None:
            k = self.kiosks[beat.kiosk] = Kiosk(
                beat.kiosk, session, now, beat, now, now, deque(maxlen=self.history), deque(maxlen=self.recent))
        else:
            if beat.frames != k.last.frames:
                k.last_advance = now
            if beat.frames < k.last.frames:
                k.restarts += 1
        k.session, k.last, k.last_heard = session, beat, now
        k.connected, k.gone_at = True, None
        k.claims[session] = now
        k.heartbeats += 1
        k.history.append((now, beat.frame_p95, beat.fps, beat.rss))
        k.recent.extend(beat.recent)
        self.prune(now)

    def closed(self, session: str, now: float) -> None:
        """Session ``session`` ended at ``now``: its kiosk is disconnected unless another session reports it."""
        for k in self.kiosks.values():
            if k.claims.pop(session, None) is not None and not k.claims:
                k.connected, k.gone_at = False, now
        self.prune(now)

    def prune(self, now: float) -> list[str]:
        """Forget disconnected kiosks past ``forget_after`` or beyond ``keep_gone``; return the ids forgotten."""
        gone = sorted((k for k in self.kiosks.values() if not k.connected), key=lambda k: k.last_heard)
        old = [k.id for k in gone if now - k.last_heard > self.forget_after]
        extra = [k.id for k in gone[: max(0, len(gone) - self.keep_gone)]]
        forgotten = list(dict.fromkeys(old + extra))
        for kid in forgotten:
            del self.kiosks[kid]
        return forgotten

    def rows(self, now: float) -> list[dict]:
        """Every kiosk as a JSON-ready dict (times as ages in seconds), sorted by id."""
        self.prune(now)
        return [self._row(k, now) for _, k in sorted(self.kiosks.items())]

    def _row(self, k: Kiosk, now: float) -> dict:
        b = k.last
        history = list(k.history)
        return {
            "kiosk": k.id,
            "session": k.session,
            "connected": k.connected,
            "stale": k.stale(now),
            "duplicate": k.duplicate(now),
            "state": b.state,
            "tour": b.tour,
            "stop": b.stop,
            "frames": b.frames,
            "fps": b.fps,
            "frame_p95": b.frame_p95,
            "rss": b.rss,
            "gpu_memory": b.gpu_memory,
            "cache_bytes": b.cache_bytes,
            "reconnects": b.reconnects,
            "interval": b.interval,
            "heartbeats": k.heartbeats,
            "restarts": k.restarts,
            "heard_s": round(now - k.last_heard, 3),
            "advanced_s": round(now - k.last_advance, 3),
            "listed_s": round(now - k.first_heard, 3),
            "gone_s": None if k.gone_at is None else round(now - k.gone_at, 3),
            "frame_times": list(k.recent),
            "frame_p95_history": [h[1] for h in history],
            "fps_history": [h[2] for h in history],
            "rss_history": [h[3] for h in history],
        }


def merge(parts: list[dict]) -> dict:
    """One replica's fleet from its workers' ``{"kiosks": rows, "sessions": rows}``.

    A kiosk listed by several workers (it moved when it reconnected, or two machines share its id) is shown
    by the connected one heard last; it is a duplicate when more than one worker has it connected and
    heard within its stale window.
    """
    by_id: dict[str, list[dict]] = {}
    sessions: list[dict] = []
    for part in parts:
        for row in part.get("kiosks", []):
            by_id.setdefault(row["kiosk"], []).append(row)
        sessions += part.get("sessions", [])
    kiosks = []
    for kid in sorted(by_id):
        rows = sorted(by_id[kid], key=lambda r: (not r["connected"], r["heard_s"]))
        best = dict(rows[0])
        live = [r for r in rows if r["connected"] and r["heard_s"] <= STALE_INTERVALS * r["interval"]]
        best["duplicate"] = best["duplicate"] or len(live) > 1
        kiosks.append(best)
    sessions.sort(key=lambda s: (str(s.get("kiosk") or "~"), str(s.get("session"))))
    return {"kiosks": kiosks, "sessions": sessions}
