"""The selections of a worker process, polled in batches: those that fall due together run as one tick.

Each session's loop hands its due poll to the ticker and awaits its frames. A
tick takes every poll queued by then (least-spent session first: a session that
selects far more often or far more expensively than its neighbours waits behind
them), culls and projects their selections in one compiled pass over all their
cameras (``session.batch.cull_due``), then polls, encodes and snapshots each
session in turn and hands its frames back at once — the first session's delta
does not wait for the last one's. Under light load a tick holds one poll; under
heavy load the polls that queued while the previous tick ran.

Ticks run on the event loop's own thread, yielding to it between two polls so
the frames handed back go out at once and the sockets are read. The work is
Python and numba holding the GIL either way; a tick in a pool thread only added
the hop to it and back and the GIL's hand-offs between two busy threads.

CPU is charged to each session as it was spent (its own poll, encoding and
snapshot, and its share of the shared pass), so the order of the next tick and
``/sessions``' figures stay per session.
"""

from __future__ import annotations

import asyncio
import time
from typing import Callable

from .fair import FairPool
from .session import Session
from .session.batch import cull_due

__all__ = ["Ticker"]


class Ticker:
    """fair : the ledger whose spend orders each tick (and is charged by it); work(session, now, culled) →
    result of one session's poll; limit : the most polls one tick takes; observe(n) : told the size of every
    tick (the metrics)."""

    def __init__(self, fair: FairPool, work: Callable, limit: int = 64,
                 observe: Callable[[int], None] | None = None) -> None:
        self.fair, self.work, self.limit, self.observe = fair, work, int(limit), observe
        self._queue: list[tuple[Session, asyncio.Future]] = []
        self._running = False
        self._task: asyncio.Task | None = None  # the draining task (the loop holds tasks only weakly)
        self.ticks = 0
        self.polls = 0
        self.largest = 0  # the most polls one tick held

    async def poll(self, session: Session):
        """``work(session, now, culled)`` in the next tick (``now``: the tick's start, server clock)."""
        future = asyncio.get_running_loop().create_future()
        self._queue.append((session, future))
        if not self._running:
            # The task starts after the callbacks ready now: polls that fell due in the same pass of the
            # loop join its first tick.
            self._running = True
            self._task = asyncio.ensure_future(self._drain())
        return await future

    async def _drain(self) -> None:
        """Ticks until nothing is queued."""
        try:
            while self._queue:
                queued = sorted(self._queue, key=lambda q: self.fair.spent(q[0].id))
                batch, self._queue = queued[: self.limit], queued[self.limit:]
                await self._tick(batch)
        finally:
            self._running = False
            for _, future in self._queue:  # cancelled mid-tick (the server stops): nobody is left waiting
                future.cancel()
            self._queue = []

    async def _tick(self, batch) -> None:
        now = time.monotonic()
        self.ticks += 1
        self.polls += len(batch)
        self.largest = max(self.largest, len(batch))
        if self.observe is not None:
            self.observe(len(batch))
        began = time.thread_time()
        try:
            culled = cull_due([s for s, _ in batch], now)
        except Exception:  # the shared pass failed: each session polls alone (and fails alone, if it must)
            culled = [None] * len(batch)
        share = (time.thread_time() - began) / len(batch)
        for (session, future), c in zip(batch, culled):
            began = time.thread_time()
            try:
                result, error = self.work(session, now, c), None
            except Exception as exc:  # handed to the awaiting coroutine
                result, error = None, exc
            self.fair.charge(session.id, time.thread_time() - began + share)
            if not future.done():  # its session may have gone meanwhile
                if error is not None:
                    future.set_exception(error)
                else:
                    future.set_result(result)
            await asyncio.sleep(0)  # its frames go out before the next session's poll
