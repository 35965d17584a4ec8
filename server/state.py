"""Session state that outlives a connection: its serialized form and the stores that keep it.

A client that loses its connection reconnects — to this replica or any other —
with the ``session`` and ``token`` its welcome gave it. The replica loads the
session's snapshot (``Session.snapshot``: msgpack of the cost model, camera
history, clock, pipeline counters and the client-cache mirror, a few
kilobytes) from a ``StateStore`` and the session carries on, sending nothing the
client already holds.

Two stores: ``MemoryStateStore`` (one process, the default) and
``RedisStateStore`` (shared by replicas, ``--redis URL``). Both expire a
snapshot ``ttl`` seconds after its last save, so an abandoned session costs
nothing for long.

The codec here reads and writes the attributes of the algorithm objects
(``CostModel``, ``OnlineCostModel``, ``Predictor``, ``ClockSync``,
``Delivery``) rather than teaching each of them to serialize itself: those
modules stay pure, and the snapshot format lives in one place. Restoring goes
*into* a freshly built object, whose attributes say what type and shape each
value must have, so a corrupt or foreign blob is refused (ValueError) instead
of producing a session that fails later.
"""

from __future__ import annotations

import math
import re
import time
import urllib.parse
from collections import deque
from typing import Any, Callable, Protocol, runtime_checkable

import msgpack
import numpy as np

__all__ = [
    "StateStore",
    "StateStoreError",
    "MemoryStateStore",
    "RedisStateStore",
    "open_state_store",
    "SNAPSHOT_FORMAT",
    "SNAPSHOT_VERSION",
    "pack_snapshot",
    "unpack_snapshot",
    "save_attrs",
    "load_attrs",
    "cost_state",
    "load_cost",
    "predictor_state",
    "load_predictor",
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


def open_state_store(url: str | None) -> StateStore:
    """None (or "" / "memory://") → ``MemoryStateStore``; "redis://…", "rediss://…", "unix://…" → ``RedisStateStore``."""
    if url is None or url in ("", "memory", "memory://"):
        return MemoryStateStore()
    scheme = urllib.parse.urlsplit(url).scheme
    if scheme in ("redis", "rediss", "unix"):
        return RedisStateStore(url)
    raise ValueError(f"unknown state store {_redact(url)!r}: give a redis://host:port/db URL, or none for memory")


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


_PLAIN = {int, float, bool, str, type(None)}


def _enc(value: Any) -> Any:
    """One attribute as msgpack-able data: arrays (and deques) as raw bytes with dtype and shape."""
    if type(value) in _PLAIN:
        return value
    if isinstance(value, deque):
        value = np.asarray(list(value)) if value else np.zeros(0)
    if isinstance(value, np.ndarray):
        a = np.ascontiguousarray(value)
        return {"nd": a.dtype.str, "shape": list(a.shape), "b": a.tobytes()}
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, tuple):
        return list(value)
    return value


def _array(value: Any, name: str) -> np.ndarray:
    if not (isinstance(value, dict) and set(value) == {"nd", "shape", "b"}):
        raise ValueError(f"{name}: expected an array")
    try:
        dtype = np.dtype(value["nd"])
        shape = tuple(int(s) for s in value["shape"])
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name}: bad array header: {exc}") from None
    if dtype.kind not in "biuf" or any(s < 0 for s in shape):
        raise ValueError(f"{name}: bad array header")
    b = value["b"]
    if not isinstance(b, bytes) or len(b) != dtype.itemsize * math.prod(shape):
        raise ValueError(f"{name}: array payload does not match its shape")
    return np.frombuffer(b, dtype).reshape(shape).copy()


def _dec(value: Any, current: Any, name: str, variable: bool) -> Any:
    """``value`` decoded as the type and shape of ``current`` (the fresh object's attribute); ValueError if not."""
    if isinstance(current, np.ndarray):
        a = _array(value, name)
        if a.dtype != current.dtype or a.shape[1:] != current.shape[1:] or (not variable and a.shape != current.shape):
            raise ValueError(f"{name}: expected {current.dtype} {current.shape}, got {a.dtype} {a.shape}")
        if a.dtype.kind == "f" and not np.isfinite(a).all():
            raise ValueError(f"{name}: not finite")
        return a
    if isinstance(current, deque):
        a = _array(value, name)
        if a.dtype.kind == "f" and not np.isfinite(a).all():
            raise ValueError(f"{name}: not finite")
        items = a.tolist() if a.ndim == 1 else [tuple(row) for row in a.tolist()]
        if current.maxlen is not None and len(items) > current.maxlen:
            raise ValueError(f"{name}: {len(items)} items, at most {current.maxlen}")
        return deque(items, maxlen=current.maxlen)
    if isinstance(current, bool):
        if not isinstance(value, bool):
            raise ValueError(f"{name}: expected a bool")
        return value
    if isinstance(current, (int, float, np.integer, np.floating)):
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ValueError(f"{name}: expected a number")
        if isinstance(value, float) and not math.isfinite(value) and value != current:
            raise ValueError(f"{name}: not finite")  # (-inf "never yet" markers stay allowed)
        return float(value) if isinstance(current, (float, np.floating)) else value
    if isinstance(current, str):
        if not isinstance(value, str):
            raise ValueError(f"{name}: expected a string")
        return value
    if isinstance(current, list):
        if not isinstance(value, list) or len(value) != len(current):
            raise ValueError(f"{name}: expected a list of {len(current)}")
        return [_dec(v, c, f"{name}[{i}]", variable) for i, (v, c) in enumerate(zip(value, current))]
    if isinstance(current, dict):
        if not isinstance(value, dict):
            raise ValueError(f"{name}: expected a map")
        return value
    if current is None:  # optional: None, a finite number or an array
        if value is None:
            return None
        if isinstance(value, dict):
            return _array(value, name)
        if isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value):
            return float(value)
        raise ValueError(f"{name}: expected None, a number or an array")
    raise ValueError(f"{name}: cannot restore a {type(current).__name__}")


def save_attrs(obj: Any, names: tuple[str, ...], optional: bool = False) -> dict:
    """The named attributes of ``obj``; with ``optional`` those it lacks are left out (code that may evolve)."""
    return {n: _enc(getattr(obj, n)) for n in names if not optional or hasattr(obj, n)}


def load_attrs(obj: Any, state: Any, names: tuple[str, ...], what: str, optional: bool = False,
               variable: tuple[str, ...] = ()) -> None:
    """Set the named attributes of ``obj`` from ``save_attrs``' dict, checked against their current values.

    All are decoded before any is set, so a bad blob leaves ``obj`` as it was.
    """
    if not isinstance(state, dict):
        raise ValueError(f"{what}: expected a map")
    out = {}
    for n in names:
        if not hasattr(obj, n):
            if optional:
                continue
            raise ValueError(f"{what}: has no {n}")
        if n not in state:
            if optional:
                continue
            raise ValueError(f"{what}.{n} is missing")
        out[n] = _dec(state[n], getattr(obj, n), f"{what}.{n}", n in variable)
    for n, v in out.items():
        setattr(obj, n, v)


# -- the algorithm objects

_ZACH = ("c_vertex", "alpha", "min_vertices", "updates", "algorithms", "c_poly", "c_vert", "c_pixel", "c_draw",
         "fitted")
_ONLINE = ("algorithms", "within", "window", "min_frames", "recent", "hold", "chosen", "frames", "_pending",
           "_count", "_faces", "_verts", "_lam", "least")
_RUNG = ("seen", "errors", "fill", "sides", "_num", "_den", "_lam")
_RLS = ("k", "forgetting", "huber", "floor", "reopen", "slack", "threshold", "clip", "cap", "scale", "phi", "P",
        "residuals", "updates", "changes", "_hi", "_lo", "_up", "_down")
_PREDICTOR = ("window", "gap", "half_life", "teleport_speed", "teleport_turn", "min_speed", "min_turn", "resets",
              "_t", "_x", "_floor", "_a", "_b", "_speed_seen", "_turn_seen")
CLOCK = ("_samples", "_guess")
DELIVERY = ("bandwidth", "min_bytes", "_rates", "last")


def cost_state(cost: Any) -> dict:
    """A ``CostModel`` ("zach") or ``OnlineCostModel`` ("online") as plain data: every coefficient and history."""
    from .select.cost_online import OnlineCostModel

    if isinstance(cost, OnlineCostModel):
        rungs = {name: {**save_attrs(r, _RUNG), "rls": save_attrs(r.rls, _RLS)} for name, r in cost.rungs.items()}
        return {"kind": "online", **save_attrs(cost, _ONLINE), "rungs": rungs}
    return {"kind": "zach", **save_attrs(cost, _ZACH)}


def load_cost(cost: Any, state: Any) -> None:
    """Put ``cost_state``'s data into ``cost``, a fresh model of the same kind; ValueError if it does not fit."""
    from .select.cost_online import MODELS, OnlineCostModel

    if not isinstance(state, dict):
        raise ValueError("cost: expected a map")
    kind = "online" if isinstance(cost, OnlineCostModel) else "zach"
    if state.get("kind") != kind:
        raise ValueError(f"cost: the snapshot's model is {state.get('kind')!r}, this server's {kind!r}")
    if kind == "zach":
        load_attrs(cost, state, _ZACH, "cost")
        return
    rungs = state.get("rungs")
    if not isinstance(rungs, dict) or set(rungs) != set(cost.rungs):
        raise ValueError(f"cost: expected the rungs {sorted(cost.rungs)}")
    for name in (state.get("chosen"), state.get("_pending")):
        if name not in MODELS:
            raise ValueError(f"cost: unknown model {name!r}")
    # Decode into copies first so a bad rung leaves the model untouched.
    import copy

    trial = copy.deepcopy(cost)
    load_attrs(trial, state, _ONLINE, "cost")
    for name, rung in trial.rungs.items():
        load_attrs(rung, rungs[name], _RUNG, f"cost.{name}")
        load_attrs(rung.rls, rungs[name].get("rls"), _RLS, f"cost.{name}.rls")
        rung._full = None
    cost.__dict__.update(trial.__dict__)


def predictor_state(p: Any) -> dict:
    """A ``Predictor``'s history (recent poses and their fit) and the motion it has seen."""
    if hasattr(p, "_fit"):
        p._fit()  # the fit is lazy: bring it up to the poses held
    return save_attrs(p, _PREDICTOR)


def load_predictor(p: Any, state: Any) -> None:
    """Put ``predictor_state``'s data into ``p`` (a fresh ``Predictor``; its limits stay its own)."""
    import copy

    trial = copy.copy(p)
    load_attrs(trial, state, _PREDICTOR, "predictor", variable=("_t", "_x"))
    if trial._t.shape[0] != trial._x.shape[0] or (trial._t.size and np.any(np.diff(trial._t) < 0)):
        raise ValueError("predictor: times and poses do not match")
    p.__dict__.update(trial.__dict__)
