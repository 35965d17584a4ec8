"""The fair selection pool serves the session that spent least first, and accounts what each spent."""

from __future__ import annotations

import asyncio
import threading
import time

import pytest

from server.fair import FairPool


def _burn(seconds: float) -> None:
    end = time.thread_time() + seconds
    while time.thread_time() < end:
        pass


def test_the_session_that_spent_more_is_served_last():
    pool = FairPool(1, clock=lambda: 0.0)  # no decay: the charges stand as they are
    order: list[str] = []
    gate = threading.Event()

    async def main() -> None:
        await pool.run("hog", _burn, 0.05)  # the hog has spent 50 ms of CPU
        blocker = asyncio.ensure_future(pool.run("other", gate.wait))
        while not pool._queue == []:  # the worker took the blocker
            await asyncio.sleep(0)
        jobs = [asyncio.ensure_future(pool.run(key, order.append, key)) for key in ("hog", "hog", "calm", "new")]
        await asyncio.sleep(0)
        gate.set()
        await asyncio.gather(blocker, *jobs)

    try:
        asyncio.run(main())
    finally:
        pool.shutdown()
    assert order == ["calm", "new", "hog", "hog"]  # queued first, the hog still comes after both
    assert pool.total("hog") >= 0.05 and pool.spent("hog") >= 0.05


def test_charges_decay_and_errors_reach_the_caller():
    now = [0.0]
    pool = FairPool(2, half_life=1.0, clock=lambda: now[0])

    def fail() -> None:
        raise ValueError("no")

    async def main() -> None:
        await pool.run("a", _burn, 0.02)
        with pytest.raises(ValueError):
            await pool.run("a", fail)

    try:
        asyncio.run(main())
        before = pool.spent("a")
        now[0] = 2.0  # two half-lives later
        assert pool.spent("a") == pytest.approx(before / 4, rel=1e-6)
        pool.forget("a")
        assert pool.total("a") == 0.0
    finally:
        pool.shutdown()
