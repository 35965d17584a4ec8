"""Selection workers shared fairly: the session that has spent the least CPU lately is served first.

Every job is charged to a key (a session) by the thread CPU time it took; a
key's charge decays with a half-life, so a session that selects far more
often or far more expensively than the others waits behind them — its
neighbours' deltas stay on time while it is served with what is left over.
Each key's decayed spend is readable (``/sessions``, the hostile benchmark).
"""

from __future__ import annotations

import asyncio
import math
import threading
import time
from typing import Any, Callable, Hashable

__all__ = ["FairPool", "settle"]


class FairPool:
    """``workers`` threads running submitted jobs least-spent key first (ties: first come, first served).

    With no workers it is the ledger alone: what each key spent, charged by whoever ran the work (the
    server's ticker, which orders its ticks by it).
    """

    def __init__(self, workers: int, *, half_life: float = 5.0, clock: Callable[[], float] = time.monotonic,
                 name: str = "walkstream-fair") -> None:
        self.half_life = float(half_life)
        self._clock = clock
        self._cond = threading.Condition()
        self._queue: list[tuple[int, Hashable, Callable, tuple, asyncio.AbstractEventLoop, asyncio.Future]] = []
        self._spent: dict[Hashable, tuple[float, float]] = {}  # key -> (decayed CPU seconds, when)
        self._total: dict[Hashable, float] = {}  # key -> CPU seconds, all told
        self._seq = 0
        self._closed = False
        self._threads = [threading.Thread(target=self._work, name=f"{name}-{i}", daemon=True) for i in range(workers)]
        for t in self._threads:
            t.start()

    def spent(self, key: Hashable) -> float:
        """``key``'s decayed CPU seconds now."""
        with self._cond:
            return self._decayed(key, self._clock())

    def total(self, key: Hashable) -> float:
        """``key``'s CPU seconds since it was first charged (until ``forget``)."""
        with self._cond:
            return self._total.get(key, 0.0)

    def charge(self, key: Hashable, cpu: float) -> None:
        """Charge ``key`` CPU seconds spent for it outside this pool's own jobs (a batch's share)."""
        with self._cond:
            now = self._clock()
            self._spent[key] = (self._decayed(key, now) + cpu, now)
            self._total[key] = self._total.get(key, 0.0) + cpu

    def forget(self, key: Hashable) -> None:
        with self._cond:
            self._spent.pop(key, None)
            self._total.pop(key, None)

    async def run(self, key: Hashable, fn: Callable[..., Any], *args: Any) -> Any:
        """Run ``fn(*args)`` on a worker when ``key``'s turn comes; its result (or exception)."""
        loop = asyncio.get_running_loop()
        future = loop.create_future()
        with self._cond:
            if self._closed or not self._threads:
                raise RuntimeError("the pool is shut down" if self._closed else "the pool has no workers")
            self._seq += 1
            self._queue.append((self._seq, key, fn, args, loop, future))
            self._cond.notify()
        return await future

    def shutdown(self) -> None:
        with self._cond:
            self._closed = True
            dropped, self._queue = self._queue, []
            self._cond.notify_all()
        for _, _, _, _, loop, future in dropped:
            loop.call_soon_threadsafe(settle, future, None, RuntimeError("the pool is shut down"))
        for t in self._threads:
            t.join(timeout=30)

    # ------------------------------------------------------------------ workers

    def _decayed(self, key: Hashable, now: float) -> float:
        value, at = self._spent.get(key, (0.0, now))
        return value * math.exp2(-(now - at) / self.half_life)

    def _next(self):
        """The queued job whose key spent least (the lock is held)."""
        now = self._clock()
        best = min(range(len(self._queue)), key=lambda i: (self._decayed(self._queue[i][1], now), self._queue[i][0]))
        return self._queue.pop(best)

    def _work(self) -> None:
        while True:
            with self._cond:
                while not self._queue and not self._closed:
                    self._cond.wait()
                if self._closed:
                    return
                _, key, fn, args, loop, future = self._next()
            began = time.thread_time()
            result, error = None, None
            try:
                result = fn(*args)
            except BaseException as exc:  # handed to the awaiting coroutine
                error = exc
            cpu = time.thread_time() - began
            with self._cond:
                now = self._clock()
                self._spent[key] = (self._decayed(key, now) + cpu, now)
                self._total[key] = self._total.get(key, 0.0) + cpu
            try:
                loop.call_soon_threadsafe(settle, future, result, error)
            except RuntimeError:  # the loop is closed: nobody waits for this any more
                pass


def settle(future: asyncio.Future, result: Any, error: BaseException | None) -> None:
    """Hand a job's result (or exception) to the coroutine awaiting ``future`` (on its loop's thread)."""
    if future.done():
        return
    if error is not None:
        future.set_exception(error)
    else:
        future.set_result(result)
