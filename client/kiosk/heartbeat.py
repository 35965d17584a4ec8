"""The kiosk's heartbeat: what its renderer did since the last one, reported every ``interval`` seconds.

A service can be "healthy" while its screen shows nothing, so the heartbeat reports frames: how many were
drawn, how fast, the 95th percentile of their times, the last few for the fleet page's sparkline — beside
the process's memory, the cache's bytes, reconnects, and where the attract loop is (tour, stop, state).
``Meter`` is pure (frame times and the time in, a ``proto.messages.Heartbeat`` out); ``rss_bytes`` reads
the process's resident set from ``/proc``.
"""

from __future__ import annotations

import os
import resource
from collections import deque

import numpy as np

from proto.messages import Heartbeat

__all__ = ["Meter", "rss_bytes", "RECENT"]

#: Frame times the heartbeat carries for the sparkline.
RECENT = 60


def rss_bytes() -> int:
    """The process's resident set size now (bytes; ``/proc/self/statm``), else its peak (``getrusage``)."""
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, IndexError):
        return int(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss) * 1024


class Meter:
    """Counts frames and keeps their times; ``due`` says when a heartbeat is, ``beat`` makes it."""

    def __init__(self, kiosk: str, interval: float, start: float = 0.0) -> None:
        self.kiosk, self.interval = kiosk, float(interval)
        self.frames = 0
        self._since: list[float] = []  # frame times since the last heartbeat
        self._recent: deque[float] = deque(maxlen=RECENT)
        self._last = float(start)

    def frame(self, seconds: float) -> None:
        """A frame was drawn in ``seconds`` (its fenced time)."""
        s = min(max(float(seconds), 0.0), 60.0)
        self.frames += 1
        self._since.append(s)
        self._recent.append(s)

    def due(self, t: float) -> bool:
        return t - self._last >= self.interval

    def beat(self, t: float, *, state: str, rss: int = 0, cache_bytes: int = 0, reconnects: int = 0, tour: str = "",
             stop: int = -1, gpu_memory: int | None = None) -> Heartbeat:
        """The heartbeat for client time ``t`` (≥ 0); starts the next interval."""
        elapsed = max(t - self._last, 1e-9)
        times = np.asarray(self._since, np.float64)
        beat = Heartbeat(
            kiosk=self.kiosk, t=max(float(t), 0.0), interval=min(max(self.interval, 0.5), 600.0), state=state,
            frames=min(self.frames, 1 << 32), fps=min(times.size / elapsed, 10_000.0),
            frame_p95=float(np.percentile(times, 95)) if times.size else 0.0, recent=list(self._recent),
            rss=min(int(rss), 1 << 42), gpu_memory=gpu_memory, cache_bytes=min(int(cache_bytes), 1 << 42),
            reconnects=min(int(reconnects), 1 << 32), tour=tour[:128], stop=min(max(int(stop), -1), 1 << 16))
        self._since.clear()
        self._last = float(t)
        return beat
