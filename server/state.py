"""Session state that outlives a connection: its serialized form and the stores that keep it.

A client that loses its connection reconnects — to this replica or any other —
with the ``session`` and ``token`` its welcome gave it. The replica loads the
session's snapshot (``Session.snapshot``: msgpack of the cost model, camera
history, clock, pipeline counters and the client-cache mirror, a few
kilobytes) from a ``StateStore`` and the session carries on, sending nothing the
client already holds.

Three stores: ``MemoryStateStore`` (one process, the default),
``SqliteStateStore`` (a file every worker process of a replica opens: the
embedded shared store, no server needed) and ``RedisStateStore`` (shared by
replicas, ``--redis URL``). All expire a snapshot ``ttl`` seconds after its
last save, so an abandoned session costs nothing for long.

What goes into a snapshot is each part's own business: every part of a
session that outlives a connection has ``to_state`` / ``from_state``
(``select.snapshot`` writes and checks the fields). Here the whole is only
packed, stamped with its format and version, unpacked and checked for size and
stamp, and kept — fenced, so a replica that lost a session cannot overwrite the
state of the one that took it over.
"""

from __future__ import annotations

import asyncio
import math
import re
import sqlite3
import threading
import time
import urllib.parse
from typing import Callable, Protocol, runtime_checkable

import msgpack

__all__ = [
    "StateStore",
    "StateStoreError",
    "MemoryStateStore",
    "RedisStateStore",
    "SqliteStateStore",
    "open_state_store",
    "SNAPSHOT_FORMAT",
    "SNAPSHOT_VERSION",
    "pack_snapshot",
    "unpack_snapshot",
]

#: What a session token looks like (proto ``Resume.token``).
TOKEN = re.compile(r"[A-Za-z0-9_\-]{16,128}")
SNAPSHOT_FORMAT = "walkstream.session"
SNAPSHOT_VERSION = 1
#: A snapshot is kilobytes; anything this large is not one of ours (and is not unpacked).
MAX_SNAPSHOT_BYTES = 16 * 1024 * 1024


# --------------------------------------------------------------------------- stores


class StateStoreError(RuntimeError):
    """The state store cannot be used (Redis unreachable, refused the command, ...)."""


@runtime_checkable
class StateStore(Protocol):
    """Where session snapshots live between connections; async because the FastAPI handler awaits it."""

    async def save(self, session_id: str, token: str, blob: bytes, ttl: float, fence: str | None = None) -> bool:
        """Store the snapshot under ``token`` unless the stored one is another's: only when no state is stored,
        or it is stored under ``token`` or ``fence`` (the token this owner resumed from). A resume rotates the
        token, so a replica that has not yet noticed its dead connection cannot overwrite the new owner's
        state. Returns whether it was stored."""
        ...

    async def load(self, session_id: str) -> tuple[str, bytes] | None: ...

    async def delete(self, session_id: str) -> None: ...

    async def close(self) -> None: ...


def _check_ttl(ttl: float) -> float:
    ttl = float(ttl)
    if not (math.isfinite(ttl) and ttl > 0):
        raise ValueError(f"ttl must be a positive number of seconds, got {ttl!r}")
    return ttl


class MemoryStateStore(StateStore):
    """Snapshots in a dict, each dropped ``ttl`` seconds after its last save (``clock`` injected for tests).

    Only the replica that saved a snapshot can resume it: the embedded default.
    Expired entries are swept at most once per ``sweep`` seconds of the clock,
    so a server that sees many sessions come and go does not grow without bound.
    """

    def __init__(self, clock: Callable[[], float] = time.monotonic, sweep: float = 1.0) -> None:
        self._clock = clock
        self._items: dict[str, tuple[str, bytes, float]] = {}  # id → (token, blob, expires at)
        self._sweep = float(sweep)
        self._next_sweep = -math.inf

    def __len__(self) -> int:
        now = self._clock()
        return sum(1 for _, _, at in self._items.values() if at > now)

    async def save(self, session_id: str, token: str, blob: bytes, ttl: float, fence: str | None = None) -> bool:
        now = self._clock()
        held = self._items.get(session_id)
        if held is not None and held[2] > now and held[0] not in (token, fence):
            return False  # another owner took the session over
        self._items[session_id] = (str(token), bytes(blob), now + _check_ttl(ttl))
        if now >= self._next_sweep:
            self._next_sweep = now + self._sweep
            for key in [k for k, (_, _, at) in self._items.items() if at <= now]:
                del self._items[key]
        return True

    async def load(self, session_id: str) -> tuple[str, bytes] | None:
        item = self._items.get(session_id)
        if item is None:
            return None
        token, blob, at = item
        if at <= self._clock():
            del self._items[session_id]
            return None
        return token, blob

    async def delete(self, session_id: str) -> None:
        self._items.pop(session_id, None)

    async def close(self) -> None:
        self._items.clear()


def _redact(url: str) -> str:
    """The URL without its password, for error messages and logs."""
    parts = urllib.parse.urlsplit(url)
    if parts.password is None:
        return url
    host = parts.hostname or ""
    if parts.port is not None:
        host = f"{host}:{parts.port}"
    user = f"{parts.username}:***@" if parts.username else ":***@"
    return urllib.parse.urlunsplit((parts.scheme, user + host, parts.path, parts.query, parts.fragment))


class RedisStateStore(StateStore):
    """Snapshots in Redis, shared by every replica: one key per session, ``prefix + id``.

    The value is the msgpack pair [token, blob], written with one SET … PX so it
    expires on its own and token and blob never disagree. A Redis that cannot
    be reached raises ``StateStoreError`` naming the URL (password redacted).
    """

    def __init__(self, url: str, prefix: str = "walkstream:session:", timeout: float = 2.0) -> None:
        import redis.asyncio

        self.url = url
        self.prefix = prefix
        try:
            self._redis = redis.asyncio.from_url(url, socket_connect_timeout=timeout, socket_timeout=timeout)
        except ValueError as exc:
            raise StateStoreError(f"bad Redis URL {_redact(url)!r}: {exc}") from None

    def _key(self, session_id: str) -> str:
        return self.prefix + session_id

    async def _call(self, what: str, coro):
        import redis.exceptions

        try:
            return await coro
        except (redis.exceptions.ConnectionError, redis.exceptions.TimeoutError, OSError) as exc:
            raise StateStoreError(f"cannot reach Redis at {_redact(self.url)} to {what}: {exc}") from None
        except redis.exceptions.RedisError as exc:
            raise StateStoreError(f"Redis at {_redact(self.url)} refused to {what}: {exc}") from None

    async def ping(self) -> None:
        """Check that Redis answers (a server calls it at start, to fail early and clearly)."""
        await self._call("ping", self._redis.ping())

    #: SET … PX only if no token is stored or it is the token or the fence; the token also in a key of its own
    #: (Redis's cmsgpack cannot read msgpack's bin type), both written by one script, so atomically.
    _FENCED_SET = """
local cur = redis.call('GET', KEYS[2])
if cur and cur ~= ARGV[2] and cur ~= ARGV[3] then return 0 end
redis.call('SET', KEYS[1], ARGV[1], 'PX', ARGV[4])
redis.call('SET', KEYS[2], ARGV[2], 'PX', ARGV[4])
return 1
"""

    async def save(self, session_id: str, token: str, blob: bytes, ttl: float, fence: str | None = None) -> bool:
        ms = max(1, int(round(_check_ttl(ttl) * 1000)))
        value = msgpack.packb([str(token), bytes(blob)], use_bin_type=True)
        key = self._key(session_id)
        done = await self._call(f"save session {session_id}", self._redis.eval(
            self._FENCED_SET, 2, key, key + ":token", value, str(token), str(fence or token), ms))
        return bool(done)

    async def load(self, session_id: str) -> tuple[str, bytes] | None:
        value = await self._call(f"load session {session_id}", self._redis.get(self._key(session_id)))
        if value is None:
            return None
        try:
            token, blob = msgpack.unpackb(value, raw=False)
            if not isinstance(token, str) or not isinstance(blob, bytes):
                raise TypeError("not a [token, blob] pair")
        except Exception:  # a key of ours holding something else: as good as absent
            return None
        return token, blob

    async def delete(self, session_id: str) -> None:
        key = self._key(session_id)
        await self._call(f"delete session {session_id}", self._redis.delete(key, key + ":token"))

    async def close(self) -> None:
        await self._redis.aclose()


class SqliteStateStore(StateStore):
    """Snapshots in one SQLite file that every worker process of a replica opens (WAL: readers never wait).

    A fenced save is one ``BEGIN IMMEDIATE`` transaction: read the stored token, write only if it is ours, the
    fence or expired — so two workers racing for a session cannot both win, as with Redis's script. Expiry is
    on the wall clock (``clock``), the one all processes share; expired rows are swept at most once per
    ``sweep`` seconds by each process. The calls run in threads: a save waiting on another process's
    transaction never blocks the event loop. State is ephemeral (a lost machine loses its sessions anyway),
    so commits are not synced to disk.

    A save is first tried on the caller's thread with a second connection that never waits (busy timeout 0):
    the transaction itself is a few tens of µs, the hop to a thread and back costs twice that in CPU, and a
    session saves about once a second. Only when another process holds the file does it go to a thread.
    """

    def __init__(self, path: str, clock: Callable[[], float] = time.time, sweep: float = 5.0,
                 timeout: float = 5.0) -> None:
        self.path = str(path)
        self._clock = clock
        self._sweep, self._next_sweep = float(sweep), -math.inf
        self._lock = threading.Lock()  # one connection per store object, used by one thread at a time
        self._quick_lock = threading.Lock()  # the connection that never waits, tried on the caller's thread
        self._quick: sqlite3.Connection | None = None
        try:
            self._db = sqlite3.connect(self.path, timeout=timeout, check_same_thread=False, isolation_level=None)
            self._setup(self._db, time.monotonic() + timeout)
            self._quick = sqlite3.connect(self.path, timeout=0.0, check_same_thread=False, isolation_level=None)
            self._quick.execute("PRAGMA synchronous=OFF")
        except sqlite3.Error as exc:
            raise StateStoreError(f"cannot open the session-state file {self.path}: {exc}") from None

    @classmethod
    def create(cls, path: str, timeout: float = 5.0) -> None:
        """Make the file (WAL, the table) and close it: the supervisor does this before its workers open it."""
        store = cls(path, timeout=timeout)
        store._close()

    @staticmethod
    def _setup(db: sqlite3.Connection, deadline: float) -> None:
        """WAL and the table, as workers opening one new file at once can both ask. The schema is written under
        ``BEGIN IMMEDIATE`` (a writer waits its turn in the busy handler); the switch to WAL needs the file to
        itself and SQLite reports a lock at once rather than wait, so it is asked again until ``deadline``."""
        delay = 0.002
        while True:
            try:
                db.execute("PRAGMA journal_mode=WAL")
                break
            except sqlite3.OperationalError as exc:
                if "locked" not in str(exc) or time.monotonic() + delay > deadline:
                    raise
                time.sleep(delay)  # another process holds the file for its own switch: a few ms
                delay = min(2 * delay, 0.1)
        db.execute("PRAGMA synchronous=OFF")
        db.execute("BEGIN IMMEDIATE")
        db.execute("CREATE TABLE IF NOT EXISTS sessions (id TEXT PRIMARY KEY, token TEXT NOT NULL, "
                   "blob BLOB NOT NULL, expires REAL NOT NULL)")
        db.execute("COMMIT")

    async def _run(self, what: str, fn, *args):
        def call():
            with self._lock:
                if self._db is None:
                    raise StateStoreError(f"the session-state file {self.path} is closed")
                try:
                    return fn(self._db, *args)
                except sqlite3.Error as exc:
                    raise StateStoreError(f"the session-state file {self.path} refused to {what}: {exc}") from None

        return await asyncio.get_running_loop().run_in_executor(None, call)

    def _save(self, db, session_id: str, token: str, blob: bytes, ttl: float, fence: str | None) -> bool:
        now = self._clock()
        db.execute("BEGIN IMMEDIATE")
        try:
            row = db.execute("SELECT token, expires FROM sessions WHERE id = ?", (session_id,)).fetchone()
            if row is not None and row[1] > now and row[0] not in (token, fence):
                db.execute("ROLLBACK")
                return False  # another owner took the session over
            db.execute("INSERT OR REPLACE INTO sessions (id, token, blob, expires) VALUES (?, ?, ?, ?)",
                       (session_id, str(token), bytes(blob), now + ttl))
            if now >= self._next_sweep:
                self._next_sweep = now + self._sweep
                db.execute("DELETE FROM sessions WHERE expires <= ?", (now,))
            db.execute("COMMIT")
        except BaseException:
            if db.in_transaction:
                db.execute("ROLLBACK")
            raise
        return True

    async def save(self, session_id: str, token: str, blob: bytes, ttl: float, fence: str | None = None) -> bool:
        ttl = _check_ttl(ttl)
        done = self._save_now(session_id, token, blob, ttl, fence)
        if done is not None:
            return done
        return await self._run(f"save session {session_id}", self._save, session_id, token, blob, ttl, fence)

    def _save_now(self, session_id: str, token: str, blob: bytes, ttl: float, fence: str | None) -> bool | None:
        """The save on this thread if the file is free this instant; None if it would have to wait."""
        if not self._quick_lock.acquire(blocking=False):
            return None
        try:
            if self._quick is None:
                return None  # closed: the waiting path says so
            return self._save(self._quick, session_id, token, blob, ttl, fence)
        except sqlite3.OperationalError as exc:
            if "locked" in str(exc) or "busy" in str(exc):
                return None  # another process's transaction: wait for it on a thread
            raise StateStoreError(f"the session-state file {self.path} refused to save session {session_id}: "
                                  f"{exc}") from None
        except sqlite3.Error as exc:
            raise StateStoreError(f"the session-state file {self.path} refused to save session {session_id}: "
                                  f"{exc}") from None
        finally:
            self._quick_lock.release()

    def _load(self, db, session_id: str):
        row = db.execute("SELECT token, blob FROM sessions WHERE id = ? AND expires > ?",
                         (session_id, self._clock())).fetchone()
        return None if row is None else (row[0], bytes(row[1]))

    async def load(self, session_id: str) -> tuple[str, bytes] | None:
        return await self._run(f"load session {session_id}", self._load, session_id)

    async def delete(self, session_id: str) -> None:
        await self._run(f"delete session {session_id}",
                        lambda db: db.execute("DELETE FROM sessions WHERE id = ?", (session_id,)))

    async def close(self) -> None:
        self._close()

    def _close(self) -> None:
        with self._lock:
            if self._db is not None:
                self._db.close()
                self._db = None
        with self._quick_lock:
            if self._quick is not None:
                self._quick.close()
                self._quick = None


def open_state_store(url: str | None) -> StateStore:
    """None (or "" / "memory://") → ``MemoryStateStore``; "sqlite:///path" → ``SqliteStateStore``;
    "redis://…", "rediss://…", "unix://…" → ``RedisStateStore``."""
    if url is None or url in ("", "memory", "memory://"):
        return MemoryStateStore()
    scheme = urllib.parse.urlsplit(url).scheme
    if scheme in ("redis", "rediss", "unix"):
        return RedisStateStore(url)
    if scheme == "sqlite":
        path = url[len("sqlite://"):]
        if not path or path == "/":
            raise ValueError(f"a sqlite state store names its file: sqlite:///path/to/state.db, got {url!r}")
        return SqliteStateStore(path)
    raise ValueError(f"unknown state store {_redact(url)!r}: give a redis://host:port/db URL, a "
                     "sqlite:///path/state.db file, or none for memory")


# --------------------------------------------------------------------------- snapshot codec


def pack_snapshot(state: dict) -> bytes:
    """msgpack of a snapshot dict, stamped with the format name and version."""
    return msgpack.packb({"format": SNAPSHOT_FORMAT, "v": SNAPSHOT_VERSION, **state}, use_bin_type=True)


def unpack_snapshot(blob: bytes) -> dict:
    """The dict ``pack_snapshot`` wrote; ValueError for anything else (garbage, another format or version)."""
    if not isinstance(blob, (bytes, bytearray, memoryview)):
        raise ValueError(f"a session snapshot is bytes, got {type(blob).__name__}")
    if len(blob) > MAX_SNAPSHOT_BYTES:
        raise ValueError(f"a session snapshot of {len(blob)} bytes is too large to be one")
    try:
        state = msgpack.unpackb(bytes(blob), raw=False, strict_map_key=True)
    except Exception as exc:  # msgpack raises several types on garbage
        raise ValueError(f"not a session snapshot: {exc}") from None
    if not isinstance(state, dict) or state.get("format") != SNAPSHOT_FORMAT:
        raise ValueError("not a session snapshot (no format stamp)")
    if state.get("v") != SNAPSHOT_VERSION:
        raise ValueError(f"session snapshot version {state.get('v')!r}; this server reads {SNAPSHOT_VERSION}")
    return state
