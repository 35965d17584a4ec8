"""The kiosk left alone: the runner's hooks wired to opening hours, the systemd watchdog, rotated logs and
URL failover; a status file for whoever watches the process; synthetic visitors for the soak.

``UnattendedHooks`` is what ``walkstream kiosk`` runs with. ``StatusFile`` and
``SyntheticVisitors`` are per-frame callbacks (``run_kiosk(on_frame=...)``):
the first writes what the kiosk is doing to a JSON file (atomically, twice a
second) for ``walkstream bench soak``; the second stands in for visitors who
touch the screen, walk a little and leave, from a seeded random source.
"""

from __future__ import annotations

import faulthandler
import json
import logging
import math
import os
import random
import sys
import time
from datetime import datetime
from pathlib import Path
from typing import TYPE_CHECKING, Callable

import numpy as np

from ..connection import Link
from .hours import RESTART_STATUS, Hours
from .logs import setup_logging
from .run import KioskHooks
from .watchdog import Watchdog

if TYPE_CHECKING:
    from proto.messages import Hello

    from ..records import FrameRecord
    from .config import KioskConfig
    from .director import Director

__all__ = ["UnattendedHooks", "StatusFile", "SyntheticVisitors", "chain"]

log = logging.getLogger("walkstream.kiosk")


class UnattendedHooks(KioskHooks):
    """Opening hours and the nightly restart, the watchdog fed while frames advance, rotated logs, failover.

    ``now`` gives the local wall-clock time (the opening hours are local); ``watchdog`` defaults to what
    systemd asked for in the environment.
    """

    def __init__(self, *, now: Callable[[], datetime] = datetime.now, watchdog: Watchdog | None = None) -> None:
        self.now = now
        self.watchdog = watchdog
        self.hours: Hours | None = None
        self.started_at: datetime | None = None
        self._fps = _Rate()

    def started(self, config: "KioskConfig") -> None:
        k, s = config.kiosk, config.schedule
        if k.log_file:
            setup_logging(k.log_file, k.log_max_mb, k.log_backups)
        faulthandler.enable()  # the watchdog's SIGABRT then leaves a traceback in the journal
        self.hours = Hours(s.open, s.close, s.closed, s.restart_at)
        self.started_at = self.now()
        if self.watchdog is None:
            self.watchdog = Watchdog.from_environ()

    def make_link(self, url: str, hello: "Hello", start: float, *, timeout: float, patience: float,
                  silence: float | None, config: "KioskConfig") -> Link:
        """A link that redials every server of the config in turn, starting with the one that answered."""
        urls = list(config.kiosk.servers)
        first = urls.index(url) if url in urls else 0
        return Link(urls[first:] + urls[:first], hello, start, timeout=timeout, patience=patience, silence=silence)

    def frame(self, frames: int, wall: float) -> None:
        if self.watchdog is not None:
            mono = time.monotonic()
            self.watchdog.frame(frames, mono, state="drawing", fps=self._fps.update(frames, mono))

    def closed(self, wall: float) -> str | None:
        assert self.hours is not None
        return None if self.hours.is_open(datetime.fromtimestamp(wall)) else self.hours.closed

    def exit_status(self, wall: float) -> int | None:
        assert self.hours is not None and self.started_at is not None
        if self.hours.restart_due(self.started_at, datetime.fromtimestamp(wall)):
            log.info("the nightly restart: exiting with %d for systemd to start the kiosk again", RESTART_STATUS)
            return RESTART_STATUS
        return None

    def stopped(self, status: int) -> None:
        if self.watchdog is not None:
            self.watchdog.stopping("nightly restart" if status == RESTART_STATUS else "stopping")


class _Rate:
    """Frames per second over the last few seconds (for the watchdog's status line)."""

    def __init__(self, every: float = 2.0) -> None:
        self.every, self.at, self.frames, self.value = every, -math.inf, 0, 0.0

    def update(self, frames: int, now: float) -> float:
        if now - self.at >= self.every:
            if math.isfinite(self.at):
                self.value = (frames - self.frames) / (now - self.at)
            self.at, self.frames = now, frames
        return self.value


class StatusFile:
    """What the kiosk is doing, as one JSON object replaced atomically every ``every`` s of wall time.

    Fields: ``t`` (client time), ``wall``, ``frames``, ``deltas`` (received over every session), ``sessions``,
    ``reconnects``, ``connected``, ``state``, ``stop``, ``eye``, ``cache_bytes``, ``gpu_memory`` (null: the
    driver does not tell), ``out_of_bounds`` (frames whose eye was outside the kiosk's bounds).
    """

    def __init__(self, path: Path, bounds: np.ndarray | None, every: float = 0.5,
                 clock: Callable[[], float] = time.time) -> None:
        self.path, self.every, self.clock = Path(path), every, clock
        self.bounds = None if bounds is None else np.asarray(bounds, np.float64).reshape(2, 3)
        self.frames = self.out_of_bounds = 0
        self.deltas_before = 0  # deltas of the sessions before the current loop's
        self._loop = None
        self._written = -math.inf

    def __call__(self, record: "FrameRecord", director: "Director") -> None:
        self.frames += 1
        loop = director.loop
        if loop is not self._loop:
            if self._loop is not None:
                self.deltas_before += self._loop.run.deltas_received
            self._loop = loop
        eye = np.asarray(director._pose[0] if getattr(director, "_pose", None) is not None else np.zeros(3))
        navigator = getattr(director, "navigator", None)
        bounds = self.bounds if self.bounds is not None else getattr(navigator, "bounds", None)
        if bounds is not None and not (np.all(eye >= bounds[0] - 1e-6) and np.all(eye <= bounds[1] + 1e-6)):
            self.out_of_bounds += 1
        now = self.clock()
        if now - self._written < self.every:
            return
        self._written = now
        run = loop.run if loop is not None else None
        state = {
            "t": round(record.t, 3), "wall": now, "frames": self.frames,
            "deltas": self.deltas_before + (run.deltas_received if run is not None else 0),
            "reconnects": len(run.reconnects) if run is not None else 0, "connected": director.link_up,
            "state": director.state, "stop": director.stop, "eye": [round(float(v), 3) for v in eye],
            "cache_bytes": int(loop.cache.held_bytes) if loop is not None else 0,
            "gpu_memory": getattr(director, "gpu_memory", None),
            "out_of_bounds": self.out_of_bounds,
        }
        tmp = self.path.with_name(self.path.name + ".tmp")
        tmp.write_text(json.dumps(state))
        os.replace(tmp, self.path)


class SyntheticVisitors:
    """Visitors from a seeded random source: one arrives every so often, taps the screen or a button, walks
    and looks around for a while, then leaves — and the kiosk's idle countdown takes it back to its tours.

    Input goes through the director exactly as a window's events would (``tap``, ``key``, ``look``).
    """

    #: (shortest, longest) seconds between one visitor leaving and the next arriving.
    GAP = (20.0, 90.0)
    #: (shortest, longest) seconds a visitor stays.
    STAY = (5.0, 40.0)

    def __init__(self, seed: int) -> None:
        self.rng = random.Random(seed)
        self.next = self.rng.uniform(*self.GAP)  # client time the next visitor arrives
        self.leaves = -math.inf
        self.held: str | None = None
        self.change = 0.0

    def __call__(self, record: "FrameRecord", director: "Director") -> None:
        t, rng = record.t, self.rng
        if t >= self.next and t >= self.leaves:  # a visitor arrives
            self.leaves = t + rng.uniform(*self.STAY)
            self.next = self.leaves + rng.uniform(*self.GAP)
            w, h = director.layout.width, director.layout.height
            director.tap(rng.uniform(0.2, 0.8) * w, rng.uniform(0.2, 0.6) * h)
            self.change = t
        if t < self.leaves and t >= self.change:  # while here: walk, turn, look, now and then press a button
            if self.held is not None:
                director.key(self.held, False)
            self.held = rng.choice(["w", "w", "w", "a", "d", "s", None])
            if self.held is not None:
                director.key(self.held, True)
            director.look(rng.uniform(-80, 80), rng.uniform(-20, 20))
            if rng.random() < 0.15:
                b = rng.choice(director.layout.buttons(director.language))
                director.tap(b.x + b.w / 2, b.y + b.h / 2)
            self.change = t + rng.uniform(0.5, 3.0)
        elif t >= self.leaves and self.held is not None:  # gone: nothing stays pressed
            director.key(self.held, False)
            self.held = None


def chain(*callbacks: Callable | None) -> Callable | None:
    """One per-frame callback that calls each given one in turn (None when none is given)."""
    given = [c for c in callbacks if c is not None]
    if not given:
        return None

    def each(record, director) -> None:
        for c in given:
            c(record, director)

    return each


def exit_on_unexpected(exc: BaseException) -> int:
    """Log an unexpected failure with its traceback and say the one line; systemd restarts on status 1."""
    log.exception("the kiosk failed: %s", exc)
    print(f"error: {type(exc).__name__}: {exc} (the log has the traceback)", file=sys.stderr)
    return 1
