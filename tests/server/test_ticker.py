"""A tick polls the least-spent session first, hands each its frames before the next one's poll, and keeps
one session's failure its own."""

from __future__ import annotations

import asyncio

import pytest

from server.fair import FairPool
from server.ticker import Ticker


class _Due:
    """A session whose selection is due but culls alone (``selection_request`` gives nothing to share)."""

    def __init__(self, id: str) -> None:
        self.id = id

    def selection_request(self, now: float):
        return None


def _run(ticker: Ticker, ids: tuple[str, ...]) -> list:
    got: list = []

    async def one(session_id: str) -> None:
        try:
            got.append((session_id, await ticker.poll(_Due(session_id))))
        except ValueError as exc:
            got.append((session_id, exc))

    async def main() -> None:
        await asyncio.gather(*(one(i) for i in ids))

    asyncio.run(main())
    return got


def test_the_polls_due_together_run_as_one_tick_least_spent_first_each_handed_back_at_once():
    fair = FairPool(0, clock=lambda: 0.0)  # no decay: the charges stand as they are
    fair.charge("hog", 0.5)
    polled: list[str] = []

    def work(session, now, culled):
        polled.append(session.id)
        return list(polled)  # what had been polled when this session's poll ran

    ticker = Ticker(fair, work)
    got = _run(ticker, ("hog", "calm", "new"))
    assert polled == ["calm", "new", "hog"]  # queued first, the hog still comes after both
    assert (ticker.ticks, ticker.largest, ticker.polls) == (1, 3, 3)
    # Each session had its result before the next one was polled: the first delta never waits for the last.
    assert got == [("calm", ["calm"]), ("new", ["calm", "new"]), ("hog", ["calm", "new", "hog"])]
    assert fair.total("calm") > 0 and fair.spent("hog") > 0.5  # each charged what its poll spent


def test_a_failing_poll_fails_its_own_session_only():
    def work(session, now, culled):
        if session.id == "bad":
            raise ValueError("no scene")
        return session.id

    got = dict(_run(Ticker(FairPool(0), work), ("a", "bad", "b")))
    assert got["a"] == "a" and got["b"] == "b"
    assert isinstance(got["bad"], ValueError) and "no scene" in str(got["bad"])


def test_a_ledger_without_workers_refuses_to_run_jobs():
    async def main() -> None:
        await FairPool(0).run("a", lambda: None)

    with pytest.raises(RuntimeError, match="no workers"):
        asyncio.run(main())
