"""The arrays every session derives from a scene index, built once per scene and shared read-only.

A hello names a scene; what the session then needs of its index beyond the
index itself — the solvers' views of it (``selection.Scene``), each
representation's digest term, parent in the morph forest, object, kind and
first level — depends on the index alone (and, for the solvers' views, on the
server's importance weights). ``SceneTable.of(index)`` builds that once per
index object and hands every later session the same table: nothing in it is
written after it is built.
"""

from __future__ import annotations

import threading
import weakref
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from proto.manifest import mix

from ..scene.index import TREES
from ..select.benefit import importance_table
from ..select.morph import rep_parents
from ..select.selection import Scene

__all__ = ["SceneTable"]


def _frozen(a) -> np.ndarray:
    a = np.array(a)
    a.flags.writeable = False
    return a


@dataclass(frozen=True, eq=False)
class SceneTable:
    """Per-representation and per-object arrays of one scene index (m representations, n objects).

    index_ref : a weak reference to the index (the table must not keep a closed store's index alive)

    bounds : (2, 3) float64 — the scene's box
    rep_bytes : (m,) int64 — geometry payload size
    rep_mix : (m,) uint64 — each rep's digest term (``proto.manifest``), so mirror updates are XORs
    rep_trees : (m,) bool — the rep is a tree group (instances of shared models)
    rep_level, rep_object, rep_faces : (m,) int64
    rep_morph : (m,) bool — a morph map onto the previous level is stored
    rep_parent : (m,) int64 — parent in the forest of every hierarchy, −1 at a root (``morph.rep_parents``)
    rep_first_of : (m,) int64 — the id of the rep's object's level 0
    object_lo, object_hi : (n, 3) float64 — object boxes
    """

    index_ref: Callable[[], object]
    bounds: np.ndarray
    rep_bytes: np.ndarray
    rep_mix: np.ndarray
    rep_trees: np.ndarray
    rep_level: np.ndarray
    rep_object: np.ndarray
    rep_faces: np.ndarray
    rep_morph: np.ndarray
    rep_parent: np.ndarray
    rep_first_of: np.ndarray
    object_lo: np.ndarray
    object_hi: np.ndarray
    _scenes: dict = field(default_factory=dict, repr=False)
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False)

    @property
    def n_reps(self) -> int:
        return int(self.rep_bytes.size)

    @property
    def n_objects(self) -> int:
        return int(self.object_lo.shape[0])

    @classmethod
    def of(cls, index) -> "SceneTable":
        """The table of ``index``: built at the first call for that index object, the same one afterwards."""
        key = id(index)
        with _LOCK:
            held = _TABLES.get(key)
            if held is not None and held[0]() is index:
                return held[1]
        table = cls.build(index)
        try:
            ref = weakref.ref(index, lambda _, key=key: _TABLES.pop(key, None))
        except TypeError:  # an index that cannot be referred to weakly (a stand-in of tests) is not shared
            return table
        with _LOCK:
            held = _TABLES.get(key)
            if held is not None and held[0]() is index:
                return held[1]
            _TABLES[key] = (ref, table)
        return table

    @classmethod
    def build(cls, index) -> "SceneTable":
        rep_object = np.asarray(index.rep_object, np.int64)
        m = int(index.n_representations)
        return cls(
            index_ref=_ref(index),
            bounds=_frozen(np.asarray(index.bounds, np.float64)),
            rep_bytes=_frozen(np.asarray(index.rep_bytes, np.int64)),
            rep_mix=_frozen(mix(np.arange(m))),
            rep_trees=_frozen(np.asarray(index.object_kind, np.int64)[rep_object] == TREES),
            rep_level=_frozen(np.asarray(index.rep_level, np.int64)),
            rep_object=_frozen(rep_object),
            rep_faces=_frozen(np.asarray(index.rep_faces, np.int64)),
            rep_morph=_frozen(np.asarray(index.rep_morph, bool)),
            rep_parent=_frozen(rep_parents(index.rep_level, index.rep_object, index.object_parent,
                                           index.rep_first, index.rep_count)),
            rep_first_of=_frozen(np.asarray(index.rep_first, np.int64)[rep_object]),
            object_lo=_frozen(np.asarray(index.object_lo, np.float64)),
            object_hi=_frozen(np.asarray(index.object_hi, np.float64)),
        )

    def scene(self, importance: dict) -> Scene:
        """The solvers' views of the scene with these importance weights per class name (built once for each)."""
        index = self.index_ref()
        weights = importance_table(index.class_names, importance)
        key = None if weights is None else np.asarray(weights).tobytes()
        with self._lock:
            scene = self._scenes.get(key)
            if scene is None:
                scene = self._scenes[key] = Scene.of(index, weights)
        return scene


    def prepare(self, importance: dict, algorithms: int = 3) -> None:
        """Build now what sessions would otherwise build at their first hello or selection: the solvers' views
        with these importance weights and their option arrays for every count of offered algorithms (a
        server calls it as it opens its stores, so no session's first τ pays for the scene)."""
        from ..select.options import option_arrays

        scene = self.scene(importance)
        for view in (scene.flat, scene.hierarchy, scene.vegetation):
            if view is not None and view.n:
                for r in range(1, algorithms + 1):
                    option_arrays(view, np.zeros(1, np.int64), r)


def _ref(index) -> Callable[[], object]:
    try:
        return weakref.ref(index)
    except TypeError:
        return lambda: index


#: id(index) → (weak reference to the index, its table); an entry goes with its index.
_TABLES: dict[int, tuple[weakref.ref, SceneTable]] = {}
_LOCK = threading.Lock()
