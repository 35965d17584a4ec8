"""The selections of a worker process, polled in batches: those that fall due together run as one tick.

Each session's loop hands its due poll to the ticker and awaits its frames. A
tick takes every poll queued by then (least-spent session first, as the fair
pool orders single jobs), culls and projects their selections in one compiled
pass over all their cameras (``session.batch.cull_due``), then polls, encodes and
snapshots each session in turn and hands its frames back at once — the first
session's delta does not wait for the last one's. Under light load a tick holds
one poll; under heavy load the polls that queued while the previous tick ran.

CPU is charged to each session as it was spent (its own poll, encoding and
snapshot, and its share of the shared pass), so the fair pool's order and
``/sessions``' figures stay per session.
"""

from __future__ import annotations

import asyncio
import threading
import time
from typing import Callable

from .fair import FairPool, settle
from .session import Session
from .session.batch import cull_due

__all__ = ["Ticker"]


class Ticker:
    """fair : the pool the ticks run on (and whose spend orders them); work(session, now, culled) → result of one
    session's poll (run in the tick's thread); limit : the most polls one tick takes; observe(n) : told the size
    of every tick (the metrics)."""

    def __init__(self, fair: FairPool, work: Callable, limit: int = 64,
                 observe: Callable[[int], None] | None = None) -> None:
        self.fair, self.work, self.limit, self.observe = fair, work, int(limit), observe
        self._lock = threading.Lock()
        self._queue: list[tuple[Session, asyncio.AbstractEventLoop, asyncio.Future]] = []
        self._running = False
        self.ticks = 0
        self.polls = 0
        self.largest = 0  # the most polls one tick held

    async def poll(self, session: Session):
        """``work(session, now, culled)`` in the next tick (``now``: the tick's start, server clock)."""
        loop = asyncio.get_running_loop()
        future = loop.create_future()
        with self._lock:
            self._queue.append((session, loop, future))
            start, self._running = not self._running, True
        if start:
            asyncio.ensure_future(self.fair.run("ticker", self._drain))
        return await future

    def _drain(self) -> None:
        """Ticks until nothing is queued (in a pool thread)."""
        while True:
            with self._lock:
                if not self._queue:
                    self._running = False
                    return
                queued = sorted(self._queue, key=lambda q: self.fair.spent(q[0].id))
                batch, rest = queued[: self.limit], queued[self.limit:]
                self._queue = rest
            self._tick(batch)

    def _tick(self, batch) -> None:
        now = time.monotonic()
        self.ticks += 1
        self.polls += len(batch)
        self.largest = max(self.largest, len(batch))
        if self.observe is not None:
            self.observe(len(batch))
        began = time.thread_time()
        try:
            culled = cull_due([s for s, _, _ in batch], now)
        except Exception:  # the shared pass failed: each session polls alone (and fails alone, if it must)
            culled = [None] * len(batch)
        share = (time.thread_time() - began) / len(batch)
        for (session, loop, future), c in zip(batch, culled):
            began = time.thread_time()
            try:
                result, error = self.work(session, now, c), None
            except BaseException as exc:  # handed to the awaiting coroutine
                result, error = None, exc
            self.fair.charge(session.id, time.thread_time() - began + share)
            try:
                loop.call_soon_threadsafe(settle, future, result, error)
            except RuntimeError:  # the loop is closed: nobody waits for this any more
                pass

