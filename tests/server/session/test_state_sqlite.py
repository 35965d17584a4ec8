"""The SQLite session store saves on the caller's thread when the file is free, and waits on a thread when not."""

from __future__ import annotations

import asyncio
import concurrent.futures
import sqlite3

import pytest

from server.state import SqliteStateStore, StateStoreError


def test_a_free_file_is_saved_without_a_thread(tmp_path):
    path = str(tmp_path / "state.db")
    SqliteStateStore.create(path)
    store = SqliteStateStore(path)

    async def go():
        loop = asyncio.get_running_loop()
        hops = []
        loop.set_default_executor(_Counting(hops))
        assert await store.save("a", "t" * 16, b"one", ttl=60.0)
        assert not await store.save("a", "x" * 16, b"stolen", ttl=60.0)  # fenced alike on this path
        assert hops == []
        assert await store.load("a") == ("t" * 16, b"one")  # a load still goes to a thread
        assert len(hops) == 1
        await store.close()

    asyncio.run(go())


def test_a_save_while_another_process_writes_waits_on_a_thread_not_on_the_loop(tmp_path):
    """Another connection (as another worker) holds the write lock: the save neither fails nor blocks the loop;
    it completes once the lock is released."""
    path = str(tmp_path / "state.db")
    SqliteStateStore.create(path)
    store = SqliteStateStore(path)
    other = sqlite3.connect(path, isolation_level=None, check_same_thread=False)
    other.execute("BEGIN IMMEDIATE")

    async def go():
        loop = asyncio.get_running_loop()
        hops = []
        loop.set_default_executor(_Counting(hops))
        saving = asyncio.ensure_future(store.save("b", "u" * 16, b"after the other", ttl=60.0))
        ticks = 0
        while ticks < 20:  # the loop runs while the save waits for the lock
            await asyncio.sleep(0)
            ticks += 1
        assert not saving.done() and len(hops) == 1
        other.execute("COMMIT")
        assert await saving
        assert await store.load("b") == ("u" * 16, b"after the other")
        await store.close()
        with pytest.raises(StateStoreError, match="closed"):
            await store.save("c", "v" * 16, b"late", ttl=60.0)

    asyncio.run(go())
    other.close()


class _Counting(concurrent.futures.ThreadPoolExecutor):
    """The loop's default executor, counting the calls handed to it."""

    def __init__(self, hops: list) -> None:
        super().__init__(max_workers=2)
        self.hops = hops

    def submit(self, fn, /, *args, **kwargs):
        self.hops.append(fn)
        return super().submit(fn, *args, **kwargs)
