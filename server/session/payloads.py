"""Geometry payloads read and encoded once per scene, their bytes shared by every session sent them.

A representation's add (``RepresentationAdd``: its ids, geometry payload and
morph map) is the same message for every session that lacks it. ``Payloads.of
(store)`` keeps, per scene store, each add built from the store once, and the
msgpack bytes of that add, packed once: a delta's frame is then its own small
fields packed around those bytes (``proto.codec.encode``'s ``packed``), with
neither a store read nor a re-encoding per session. The cache is bounded in
bytes (least recently used out first), so a scene larger than memory streams
as before; every session of a process shares it, from any thread.

``packed(message)`` answers for the adds this module built (by identity, while
they are cached), so ``encode(delta, packed=packed)`` is byte for byte
``encode(delta)``.
"""

from __future__ import annotations

import threading
import weakref
from collections import OrderedDict

import msgpack
import numpy as np

from proto.messages import ModelAdd, RepresentationAdd

from ..scene.index import TREES

__all__ = ["Payloads", "packed", "DEFAULT_MAX_BYTES"]

#: Payload bytes each scene's cache keeps (its adds' geometry and morph maps).
DEFAULT_MAX_BYTES = 256 * 1024 * 1024

#: id(message) → (the message, its msgpack bytes), for the messages the caches hold now. The entry holds the
#: message, so its id cannot pass to another object while the entry exists.
_PACKED: dict[int, tuple[object, bytes]] = {}
_PACKED_LOCK = threading.Lock()


def packed(message) -> bytes | None:
    """The msgpack bytes of an add or tree model this module built and still caches, else None."""
    entry = _PACKED.get(id(message))
    return entry[1] if entry is not None and entry[0] is message else None


def _forget(ids: set[int]) -> None:
    with _PACKED_LOCK:
        for i in ids:
            _PACKED.pop(i, None)
        ids.clear()


def _pack(message) -> bytes:
    return msgpack.packb(message.model_dump(mode="python"), use_bin_type=True)


class Payloads:
    """The adds of one scene store (``RepresentationAdd`` with and without morph maps, ``ModelAdd``), built once.

    store : the scene store (``geometries``, ``morphs``, ``model_geometries`` and its ``index``)
    max_bytes : payload bytes kept; the least recently used adds go first
    """

    def __init__(self, store, max_bytes: int = DEFAULT_MAX_BYTES) -> None:
        self.store = store
        self.max_bytes = int(max_bytes)
        index = store.index
        self._object = index.rep_object
        self._level = index.rep_level
        self._trees = index.object_kind[index.rep_object] == TREES
        self._has_morph = index.rep_morph
        # Each representation's morph-map bytes once its add with the map was built (0 before, and for those
        # without one): a delta's byte count is then a sum over an array, not over its adds.
        self.morph_bytes = np.zeros(len(index.rep_object), np.int64)
        self._adds: OrderedDict[tuple[int, bool], RepresentationAdd] = OrderedDict()
        self._models: list[ModelAdd] | None = None
        self._lock = threading.Lock()
        self.bytes = 0
        self.reads = 0  # store reads (one per batch of misses)
        self.hits = self.misses = 0
        self._ids: set[int] = set()  # ids this cache entered in _PACKED (forgotten with the cache)
        weakref.finalize(self, _forget, self._ids)

    @classmethod
    def of(cls, store) -> "Payloads":
        """The cache of ``store``: made at the first call for that store object, the same one afterwards."""
        with _OF_LOCK:
            try:
                found = _CACHES.get(store)
                if found is None:
                    found = _CACHES[store] = cls(store)
            except TypeError:  # a store that cannot be referred to weakly (a stand-in of tests) is not shared
                found = cls(store)
            return found

    def adds(self, reps, morph: bool) -> list[RepresentationAdd]:
        """The adds of ``reps`` (ids, in that order); with their morph maps where stored if ``morph``."""
        reps = [int(r) for r in reps]
        out: list[RepresentationAdd | None] = [None] * len(reps)
        missing: list[int] = []
        with self._lock:
            for i, r in enumerate(reps):
                add = self._adds.get((r, morph))
                if add is None:
                    missing.append(i)
                else:
                    self._adds.move_to_end((r, morph))
                    out[i] = add
            self.hits += len(reps) - len(missing)
            self.misses += len(missing)
        if missing:
            ids = sorted({reps[i] for i in missing})
            blobs = dict(zip(ids, self.store.geometries(ids)))
            with_map = [r for r in ids if morph and self._has_morph[r] and not self._trees[r]]
            maps = dict(zip(with_map, self.store.morphs(with_map))) if with_map else {}
            built = {r: RepresentationAdd(rep=r, object=int(self._object[r]), level=int(self._level[r]),
                                          geometry=blobs[r], morph=maps.get(r),
                                          kind="trees" if self._trees[r] else "mesh") for r in ids}
            wire = {r: _pack(a) for r, a in built.items()}
            with self._lock:
                self.reads += 1
                for r, add in built.items():
                    key = (r, morph)
                    held = self._adds.get(key)
                    if held is not None:  # another thread built it meanwhile: keep one
                        built[r] = held
                        continue
                    self._adds[key] = add
                    self.bytes += _size(add)
                    if add.morph:
                        self.morph_bytes[r] = len(add.morph)
                    self._enter(add, wire[r])
                self._evict()
            for i in missing:
                out[i] = built[reps[i]]
        return out  # type: ignore[return-value]

    def models(self) -> list[ModelAdd]:
        """Every tree model of the scene (sent once per session that draws trees)."""
        with self._lock:
            if self._models is not None:
                return self._models
        n = int(self.store.index.model_points.shape[0])
        models = [ModelAdd(model=i, points=b) for i, b in enumerate(self.store.model_geometries(range(n)))]
        with self._lock:
            if self._models is None:
                self._models = models
                for m in models:
                    self._enter(m, _pack(m))
            return self._models

    def _enter(self, message, wire: bytes) -> None:
        with _PACKED_LOCK:
            _PACKED[id(message)] = (message, wire)
        self._ids.add(id(message))

    def _evict(self) -> None:
        while self.bytes > self.max_bytes and len(self._adds) > 1:
            _, add = self._adds.popitem(last=False)
            self.bytes -= _size(add)
            self._ids.discard(id(add))
            with _PACKED_LOCK:
                _PACKED.pop(id(add), None)

    def close(self) -> None:
        """Forget every cached add (the store closes)."""
        with self._lock:
            _forget(self._ids)
            self._adds.clear()
            self._models = None
            self.bytes = 0


def _size(add: RepresentationAdd) -> int:
    return len(add.geometry) + (len(add.morph) if add.morph else 0)


#: store → its cache; an entry goes with its store.
_CACHES: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()
_OF_LOCK = threading.Lock()
