"""The connection's inbox: FIFO, bounded, and a get that waits at most its timeout."""

import asyncio

import pytest

from server.connection import Inbox

MISSING = object()


def run(coro):
    return asyncio.run(coro)


def test_items_come_out_in_order_and_none_is_lost():
    async def main():
        box = Inbox(maxsize=8)
        for i in range(5):
            box.put_nowait(i)
        assert len(box) == 5
        return [await box.get(10.0, MISSING) for _ in range(5)], box.empty()

    items, empty = run(main())
    assert items == [0, 1, 2, 3, 4] and empty


def test_get_returns_the_default_when_nothing_arrives_in_time():
    async def main():
        box = Inbox(maxsize=4)
        loop = asyncio.get_running_loop()
        began = loop.time()
        got = await box.get(0.01, MISSING)
        return got, loop.time() - began, box._getter

    got, waited, getter = run(main())
    assert got is MISSING
    assert waited >= 0.009
    assert getter is None  # nothing left behind for a later put to wake


def test_a_put_wakes_a_waiting_get_before_its_timeout():
    async def main():
        box = Inbox(maxsize=4)
        loop = asyncio.get_running_loop()
        getter = asyncio.ensure_future(box.get(3600.0, MISSING))
        while box._getter is None:  # the get is waiting
            await asyncio.sleep(0)
        began = loop.time()
        box.put_nowait("frame")
        return await getter, loop.time() - began

    got, waited = run(main())
    assert got == "frame" and waited < 60.0


def test_a_negative_timeout_is_an_immediate_default():
    async def main():
        return await Inbox(maxsize=1).get(-5.0, MISSING)

    assert run(main()) is MISSING


def test_a_full_inbox_refuses_put_nowait_and_holds_put_until_an_item_is_taken():
    async def main():
        box = Inbox(maxsize=2)
        box.put_nowait("a")
        box.put_nowait("b")
        with pytest.raises(asyncio.QueueFull):
            box.put_nowait("c")
        putter = asyncio.ensure_future(box.put("c"))
        while box._putter is None:  # the put is waiting for room
            await asyncio.sleep(0)
        assert not putter.done() and len(box) == 2
        first = box.get_nowait()
        await putter
        return first, [box.get_nowait(), box.get_nowait()]

    first, rest = run(main())
    assert first == "a" and rest == ["b", "c"]


def test_get_nowait_on_an_empty_inbox_raises():
    with pytest.raises(asyncio.QueueEmpty):
        Inbox(maxsize=1).get_nowait()


def test_a_cancelled_get_leaves_the_inbox_usable():
    async def main():
        box = Inbox(maxsize=4)
        getter = asyncio.ensure_future(box.get(3600.0, MISSING))
        while box._getter is None:
            await asyncio.sleep(0)
        getter.cancel()
        with pytest.raises(asyncio.CancelledError):
            await getter
        box.put_nowait(1)
        return await box.get(1.0, MISSING)

    assert run(main()) == 1
