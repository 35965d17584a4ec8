"""The scene store: one SQLite file per scene, and its index as numpy arrays.

Why SQLite: one file to copy, random access to any representation's blob from
several threads, and a schema that says what the file holds. The store keeps
each representation's geometry exactly as it goes on the wire
(``proto.geometry``), so the server streams blobs without re-encoding them.

Level convention: **level 0 is the coarsest**; levels increase with detail and
an object's last level is its full detail (Funkhouser & Séquin's "highest
LOD"). Object ids are 0..n-1; representation ids are 0..m-1 in (object, level)
order, so a representation's id is its row in the index arrays and an
object's representations are ``rep_first[o] + arange(rep_count[o])``.

Objects come in four kinds (``KINDS``): ``mesh`` (a discrete LOD chain; may
hang under an HLOD node), ``hlod`` (an inner node of a building hierarchy,
carrying a merged proxy of its subtree), ``terrain`` (a quadtree patch), and
``trees`` (a group of ≤ 64 tree instances drawn as point splats at a continuous
resolution x ∈ [0, 1]). Hierarchies are parent links; a parent's id is always
less than its children's, so one pass in id order visits parents first.

Schema (version ``SCHEMA_VERSION``; ``PRAGMA application_id`` marks the file)::

    meta(key TEXT PRIMARY KEY, value TEXT)             JSON values: schema_version, name, bounds,
                                                        tour, start, class_names, generator, seed,
                                                        created, origin, crs, viewpoints, sources
    objects(id INTEGER PRIMARY KEY, name TEXT, class INTEGER, kind INTEGER, parent INTEGER,
            lo_x, lo_y, lo_z, hi_x, hi_y, hi_z REAL)    box of each object over all its levels
    representations(id INTEGER PRIMARY KEY, object INTEGER, level INTEGER, faces INTEGER,
                    vertices INTEGER, error REAL, bytes INTEGER, geometry BLOB,
                    morph BLOB NULL)                    morph: ``proto.morph`` map of this level's
                                                        vertices onto the previous level's
    models(id INTEGER PRIMARY KEY, name TEXT, points INTEGER, radius REAL,
           lo_x, lo_y, lo_z, hi_x, hi_y, hi_z REAL, geometry BLOB)
                                                        tree models as prefix-ordered point sets
                                                        (``proto.points``), shared by tree groups

A ``trees`` object's representation holds its instance list
(``proto.points.encode_instances``); its ``vertices`` count is the group's
splats at x = 1 and its ``faces`` count is 0.

Writing is atomic (``SceneWriter``): the file is built under a temporary name
in the target's directory and renamed over the target only when complete.
"""

from __future__ import annotations

import json
import os
import sqlite3
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable, Mapping, Sequence

import msgpack
import numpy as np

from proto.geometry import encode_geometry
from proto.morph import encode_morph
from proto.messages import Pose, TourKey

__all__ = [
    "SCHEMA_VERSION", "APPLICATION_ID", "KINDS", "MESH", "HLOD", "TERRAIN", "TREES",
    "StoreError", "SceneIndex", "SceneStore", "SceneWriter", "object_box",
]

SCHEMA_VERSION = 2
#: ``PRAGMA application_id`` of a walkstream store ("WkSt"), so foreign SQLite files are told apart.
APPLICATION_ID = 0x576B5374
#: Object kinds, by their id in the ``kind`` column.
KINDS = ("mesh", "hlod", "terrain", "trees")
MESH, HLOD, TERRAIN, TREES = range(4)

_TABLES = {
    "meta": "CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT NOT NULL)",
    "objects": (
        "CREATE TABLE objects (id INTEGER PRIMARY KEY, name TEXT NOT NULL, class INTEGER NOT NULL, "
        "kind INTEGER NOT NULL, parent INTEGER NOT NULL, lo_x REAL, lo_y REAL, lo_z REAL, hi_x REAL, hi_y REAL, hi_z REAL)"
    ),
    "representations": (
        "CREATE TABLE representations (id INTEGER PRIMARY KEY, object INTEGER NOT NULL, "
        "level INTEGER NOT NULL, faces INTEGER NOT NULL, vertices INTEGER NOT NULL, "
        "error REAL NOT NULL, bytes INTEGER NOT NULL, geometry BLOB NOT NULL, morph BLOB)"
    ),
    "models": (
        "CREATE TABLE models (id INTEGER PRIMARY KEY, name TEXT NOT NULL, points INTEGER NOT NULL, "
        "radius REAL NOT NULL, lo_x REAL, lo_y REAL, lo_z REAL, hi_x REAL, hi_y REAL, hi_z REAL, "
        "geometry BLOB NOT NULL)"
    ),
}
_META_KEYS = ("schema_version", "name", "bounds", "tour", "start", "class_names")
#: Blobs fetched per SELECT in ``geometries`` (SQLite's default variable limit is 999+).
_CHUNK = 500


class StoreError(Exception):
    """A scene store cannot be opened, read or written; the message names the file."""


@dataclass
class SceneIndex:
    """Everything about a scene but its geometry, as a structure of arrays.

    Objects (n of them, ids 0..n-1):
        object_lo, object_hi : (n, 3) float32 — box over all levels (≈ full detail), world space
        object_class         : (n,) int16 — index into ``class_names``
        object_kind          : (n,) int8 — index into ``KINDS`` (mesh, hlod, terrain, trees)
        object_parent        : (n,) int32 — parent object in its hierarchy, −1 for a root or a
                               free object; always less than the object's own id
        object_depth         : (n,) int16 — 0 for roots
        child_ptr, child_ids : CSR children: the children of o are child_ids[child_ptr[o]:child_ptr[o+1]]
        rep_first            : (n,) int32 — id of the object's level 0 (coarsest)
        rep_count            : (n,) int32 — number of levels; the last is full detail
    Representations (m of them, ids 0..m-1, in (object, level) order):
        rep_object   : (m,) int32
        rep_level    : (m,) int16 — 0 coarsest … rep_count-1 full detail
        rep_faces    : (m,) int32 — triangles
        rep_vertices : (m,) int32
        rep_error    : (m,) float32 — object-space geometric error against full detail
                       (metres; 0 at full detail, non-increasing with level)
        rep_bytes    : (m,) int32 — size of the geometry payload
        rep_morph    : (m,) bool — a morph map onto the previous level is stored
    Tree models (M of them), shared by ``trees`` objects:
        model_points : (M,) int32 — splats at full resolution
        model_radius : (M,) float32 — splat radius at full resolution (model space)
        model_lo, model_hi : (M, 3) float32 — model-space boxes
    Scene:
        bounds : (2, 3) float64 — [min, max] over all objects
        tour   : list of {"t", "eye", "forward", "up"} (``proto.messages.TourKey`` fields)
        start  : {"eye", "forward", "up"}
        meta   : every meta value, decoded from JSON
    """

    name: str
    bounds: np.ndarray
    object_lo: np.ndarray
    object_hi: np.ndarray
    object_class: np.ndarray
    class_names: list[str]
    object_kind: np.ndarray
    object_parent: np.ndarray
    object_depth: np.ndarray
    child_ptr: np.ndarray
    child_ids: np.ndarray
    rep_first: np.ndarray
    rep_count: np.ndarray
    rep_object: np.ndarray
    rep_level: np.ndarray
    rep_faces: np.ndarray
    rep_vertices: np.ndarray
    rep_error: np.ndarray
    rep_bytes: np.ndarray
    rep_morph: np.ndarray
    model_points: np.ndarray
    model_radius: np.ndarray
    model_lo: np.ndarray
    model_hi: np.ndarray
    tour: list[dict]
    start: dict
    meta: dict

    @property
    def n_objects(self) -> int:
        return int(self.object_lo.shape[0])

    @property
    def n_representations(self) -> int:
        return int(self.rep_object.shape[0])

    def children(self, o: int) -> np.ndarray:
        """Ids of object ``o``'s children (empty for a leaf)."""
        return self.child_ids[self.child_ptr[o] : self.child_ptr[o + 1]]

    @property
    def leaf(self) -> np.ndarray:
        """(n,) bool — objects without children."""
        return np.diff(self.child_ptr) == 0

    @property
    def flat(self) -> np.ndarray:
        """(n,) bool — the objects a flat (non-hierarchical) selection draws: triangle-mesh leaves.

        Together they cover the whole scene at full detail: every building, every
        finest terrain patch; HLOD proxies and coarse patches only stand in for them.
        Tree groups need the splat renderer and the mixed solver, so they are left out.
        """
        return self.leaf & (self.object_kind != TREES)

    @property
    def height(self) -> int:
        """Levels of the deepest hierarchy (1 for a scene without hierarchies)."""
        return int(self.object_depth.max()) + 1 if self.n_objects else 0


def _table_names(conn: sqlite3.Connection) -> set[str]:
    return {r[0] for r in conn.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}


class SceneStore:
    """A scene store opened read-only: its ``index`` in memory, geometry blobs on demand.

    Thread-safe: the server's worker threads share one connection behind a lock.
    """

    def __init__(self, path: Path, conn: sqlite3.Connection, index: SceneIndex) -> None:
        self.path = path
        self.index = index
        self._conn: sqlite3.Connection | None = conn
        self._lock = threading.Lock()

    @classmethod
    def open(cls, path: str | os.PathLike[str]) -> "SceneStore":
        """Open ``path`` read-only and load its index; ``StoreError`` says what is wrong with it."""
        path = Path(path)
        if not path.is_file():
            raise StoreError(f"{path}: no such scene store")
        try:
            conn = sqlite3.connect(f"{path.resolve().as_uri()}?mode=ro", uri=True, check_same_thread=False)
        except sqlite3.Error as exc:
            raise StoreError(f"{path}: cannot open: {exc}") from None
        try:
            index = _load_index(path, conn)
        except BaseException:
            conn.close()
            raise
        return cls(path, conn, index)

    def geometry(self, rep: int) -> bytes:
        """The geometry payload (``proto.geometry``) of representation ``rep``."""
        return self.geometries([rep])[0]

    def geometries(self, reps: Iterable[int]) -> list[bytes]:
        """Payloads of several representations, in the order asked (a few SELECTs, not one per rep)."""
        return self._blobs("representations", "geometry", reps, self.index.n_representations)

    def morph(self, rep: int) -> bytes | None:
        """The ``proto.morph`` map of ``rep``'s vertices onto the previous level's (None if not stored)."""
        return self.morphs([rep])[0]

    def morphs(self, reps: Iterable[int]) -> list[bytes | None]:
        """Morph maps of several representations, in the order asked."""
        return self._blobs("representations", "morph", reps, self.index.n_representations, nullable=True)

    def model_geometries(self, models: Iterable[int]) -> list[bytes]:
        """Point payloads (``proto.points``) of tree models, in the order asked."""
        return self._blobs("models", "geometry", models, int(self.index.model_points.shape[0]))

    def _blobs(self, table: str, column: str, ids_in: Iterable[int], count: int,
               nullable: bool = False) -> list:
        ids = [int(r) for r in ids_in]
        what = "model" if table == "models" else "representation"
        bad = [r for r in ids if not 0 <= r < count]
        if bad:
            raise StoreError(f"{self.path}: unknown {what} id {bad[0]} (store has 0..{count - 1})")
        found: dict[int, bytes | None] = {}
        unique = sorted(set(ids))
        with self._lock:
            conn = self._connection()
            try:
                for i in range(0, len(unique), _CHUNK):
                    part = unique[i : i + _CHUNK]
                    marks = ",".join("?" * len(part))
                    for rid, blob in conn.execute(f"SELECT id, {column} FROM {table} WHERE id IN ({marks})", part):
                        found[rid] = None if blob is None else bytes(blob)
            except sqlite3.Error as exc:
                raise StoreError(f"{self.path}: cannot read {what} {column}: {exc}") from None
        missing = [r for r in unique if r not in found or (found[r] is None and not nullable)]
        if missing:
            raise StoreError(f"{self.path}: corrupt: {what} {missing[0]} has no {column}")
        return [found[r] for r in ids]

    def object_names(self) -> list[str]:
        """Names of objects 0..n-1 (for people and logs; kept out of the index)."""
        with self._lock:
            try:
                return [r[0] for r in self._connection().execute("SELECT name FROM objects ORDER BY id")]
            except sqlite3.Error as exc:
                raise StoreError(f"{self.path}: cannot read object names: {exc}") from None

    def _connection(self) -> sqlite3.Connection:
        if self._conn is None:
            raise StoreError(f"{self.path}: store is closed")
        return self._conn

    def close(self) -> None:
        with self._lock:
            if self._conn is not None:
                self._conn.close()
                self._conn = None

    def __enter__(self) -> "SceneStore":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _load_index(path: Path, conn: sqlite3.Connection) -> SceneIndex:
    """Check the file is a walkstream store of this schema version and read its index."""
    try:
        app_id = conn.execute("PRAGMA application_id").fetchone()[0]
        tables = _table_names(conn)
    except sqlite3.DatabaseError as exc:
        raise StoreError(f"{path}: not a walkstream store (not an SQLite database: {exc})") from None
    if app_id != APPLICATION_ID or "meta" not in tables:
        raise StoreError(f"{path}: not a walkstream store (SQLite file without walkstream's marker)")
    try:
        meta = {k: json.loads(v) for k, v in conn.execute("SELECT key, value FROM meta")}
    except (sqlite3.Error, ValueError) as exc:
        raise StoreError(f"{path}: corrupt: meta table unreadable: {exc}") from None
    version = meta.get("schema_version")
    if version != SCHEMA_VERSION:
        raise StoreError(f"{path}: schema version {version!r}, this program reads version {SCHEMA_VERSION}")
    for table in _TABLES:
        if table not in tables:
            raise StoreError(f"{path}: corrupt: missing table '{table}'")
    absent = [k for k in _META_KEYS if k not in meta]
    if absent:
        raise StoreError(f"{path}: corrupt: meta lacks {', '.join(absent)}")
    try:
        obj = conn.execute(
            "SELECT id, class, kind, parent, lo_x, lo_y, lo_z, hi_x, hi_y, hi_z FROM objects ORDER BY id"
        ).fetchall()
        rep = conn.execute(
            "SELECT id, object, level, faces, vertices, error, bytes, morph IS NOT NULL "
            "FROM representations ORDER BY id"
        ).fetchall()
        mod = conn.execute(
            "SELECT id, points, radius, lo_x, lo_y, lo_z, hi_x, hi_y, hi_z FROM models ORDER BY id"
        ).fetchall()
    except sqlite3.Error as exc:
        raise StoreError(f"{path}: corrupt: {exc}") from None
    o = np.array(obj, np.float64).reshape(-1, 10)
    r = np.array(rep, np.float64).reshape(-1, 8)
    md = np.array(mod, np.float64).reshape(-1, 9)
    if not np.array_equal(md[:, 0], np.arange(md.shape[0])):
        raise StoreError(f"{path}: corrupt: model ids are not 0..{md.shape[0] - 1}")
    n, m = o.shape[0], r.shape[0]
    if not np.array_equal(o[:, 0], np.arange(n)):
        raise StoreError(f"{path}: corrupt: object ids are not 0..{n - 1}")
    if not np.array_equal(r[:, 0], np.arange(m)):
        raise StoreError(f"{path}: corrupt: representation ids are not 0..{m - 1}")
    rep_object = r[:, 1].astype(np.int32)
    rep_level = r[:, 2].astype(np.int16)
    rep_count = np.bincount(rep_object, minlength=n).astype(np.int32) if m else np.zeros(n, np.int32)
    rep_first = (np.cumsum(rep_count) - rep_count).astype(np.int32)
    if (
        (m and (rep_object.min() < 0 or rep_object.max() >= n))
        or (np.diff(rep_object) < 0).any()
        or (rep_count == 0).any()
        or not np.array_equal(rep_level, np.arange(m) - np.repeat(rep_first, rep_count))
    ):
        raise StoreError(f"{path}: corrupt: representations are not levels 0..k-1 of each object in order")
    classes = o[:, 1].astype(np.int16)
    class_names = [str(c) for c in meta["class_names"]]
    if n and (classes.min() < 0 or classes.max() >= len(class_names)):
        raise StoreError(f"{path}: corrupt: object class outside class_names")
    kind = o[:, 2].astype(np.int8)
    if n and (kind.min() < 0 or kind.max() >= len(KINDS)):
        raise StoreError(f"{path}: corrupt: object kind outside 0..{len(KINDS) - 1}")
    parent = o[:, 3].astype(np.int32)
    bad = np.nonzero((parent < -1) | (parent >= np.arange(n)))[0]
    if bad.size:
        raise StoreError(f"{path}: corrupt: object {int(bad[0])} has parent {int(parent[bad[0]])} "
                         "(parents must precede their children)")
    depth = np.zeros(n, np.int16)
    up = parent.copy()
    while (up >= 0).any():  # pointer jumping: one vectorised step per hierarchy level
        depth += up >= 0
        up = np.where(up >= 0, parent[np.maximum(up, 0)], -1)
    child_ids = np.nonzero(parent >= 0)[0].astype(np.int32)
    child_ids = child_ids[np.argsort(parent[child_ids], kind="stable")]
    child_ptr = np.zeros(n + 1, np.int64)
    child_ptr[1:] = np.cumsum(np.bincount(parent[child_ids], minlength=n)) if child_ids.size else 0
    return SceneIndex(
        name=str(meta["name"]),
        bounds=np.asarray(meta["bounds"], np.float64).reshape(2, 3),
        object_lo=o[:, 4:7].astype(np.float32),
        object_hi=o[:, 7:10].astype(np.float32),
        object_class=classes,
        class_names=class_names,
        object_kind=kind,
        object_parent=parent,
        object_depth=depth,
        child_ptr=child_ptr,
        child_ids=child_ids,
        rep_first=rep_first,
        rep_count=rep_count,
        rep_object=rep_object,
        rep_level=rep_level,
        rep_faces=r[:, 3].astype(np.int32),
        rep_vertices=r[:, 4].astype(np.int32),
        rep_error=r[:, 5].astype(np.float32),
        rep_bytes=r[:, 6].astype(np.int32),
        rep_morph=r[:, 7].astype(bool),
        model_points=md[:, 1].astype(np.int32),
        model_radius=md[:, 2].astype(np.float32),
        model_lo=md[:, 3:6].astype(np.float32),
        model_hi=md[:, 6:9].astype(np.float32),
        tour=list(meta["tour"]),
        start=dict(meta["start"]),
        meta=meta,
    )


def _vec3(v: Sequence[float]) -> list[float]:
    out = [float(x) for x in v]
    if len(out) != 3:
        raise ValueError(f"expected three numbers, got {v!r}")
    return out


def _pose_dict(pose: Any, with_t: bool) -> dict:
    """A pose (pydantic ``Pose``/``TourKey`` or mapping) as a plain JSON-ready dict of floats."""
    get = (lambda k: pose[k]) if isinstance(pose, Mapping) else (lambda k: getattr(pose, k))
    d = {k: _vec3(get(k)) for k in ("eye", "forward", "up")}
    return {"t": float(get("t")), **d} if with_t else d


class SceneWriter:
    """Builds a scene store atomically: nothing appears at ``path`` unless ``commit`` succeeds.

    The rows go into a temporary file in ``path``'s directory (same file
    system, so the final ``os.replace`` is atomic); an exception inside the
    ``with`` block, or ``abort()``, deletes it and leaves any existing store at
    ``path`` untouched. Leaving the ``with`` block normally commits.

        with SceneWriter("garden.db", name="garden") as w:
            w.add_object("rock_0", "rock", levels, errors)
            w.set_tour(keys)
    """

    def __init__(self, path: str | os.PathLike[str], *, name: str | None = None, generator: str = "",
                 seed: int | None = None, class_names: Sequence[str] = ()) -> None:
        """path: the store to make; name: the scene's name (default: the file's stem);
        generator, seed: recorded in meta; class_names: class ids to fix in this order
        (classes first seen in ``add_object`` are appended)."""
        self.path = Path(path)
        self.name = name if name is not None else self.path.stem
        self.generator = generator
        self.seed = seed
        self._classes: dict[str, int] = {c: i for i, c in enumerate(dict.fromkeys(class_names))}
        self._n_objects = 0
        self._n_reps = 0
        self._n_models = 0
        self._extra: dict[str, Any] = {}
        self._lo = np.full(3, np.inf)
        self._hi = np.full(3, -np.inf)
        self._tour: list[dict] = []
        self._start: dict | None = None
        self._done = False
        directory = self.path.parent if str(self.path.parent) else Path(".")
        try:
            fd, tmp = tempfile.mkstemp(prefix=f".{self.path.name}.", suffix=".tmp", dir=directory)
        except OSError as exc:
            raise StoreError(f"{self.path}: cannot create a temporary file beside it: {exc}") from None
        os.close(fd)
        self._tmp = Path(tmp)
        try:
            self._conn = sqlite3.connect(self._tmp)
            self._conn.execute("PRAGMA journal_mode = OFF")
            self._conn.execute("PRAGMA synchronous = OFF")
            self._conn.execute(f"PRAGMA application_id = {APPLICATION_ID}")
            self._conn.execute(f"PRAGMA user_version = {SCHEMA_VERSION}")
            for ddl in _TABLES.values():
                self._conn.execute(ddl)
        except sqlite3.Error as exc:
            self.abort()
            raise StoreError(f"{self.path}: cannot build store: {exc}") from None

    @property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """(lo, hi) over the objects added so far."""
        return self._lo.copy(), self._hi.copy()

    @property
    def temporary_path(self) -> Path:
        """Where the store is being built (deleted on abort, renamed on commit)."""
        return self._tmp

    def add_object(self, name: str, cls: str, levels: Sequence[tuple[np.ndarray, np.ndarray]],
                   errors: Sequence[float], *, kind: int = MESH, parent: int = -1,
                   morphs: Sequence[np.ndarray | None] | None = None, reorder: bool = True) -> int:
        """Encode and add one object's levels; returns its id.

        levels : [(positions (n_k, 3) float, faces (m_k, 3) int), ...] coarsest → finest;
                 the last is full detail; one box (``object_box``) quantizes every level
        errors : geometric error of each level against full detail, same order
        morphs : per level, None or the (n_k,) map of its vertices onto level k−1's
                 (then the levels must already be in GPU order: pass ``reorder=False``)
        """
        self._check_open()
        if len(levels) == 0 or len(levels) != len(errors):
            raise ValueError(f"object {name!r}: {len(levels)} levels but {len(errors)} errors")
        if morphs is not None and reorder and any(m is not None for m in morphs):
            raise ValueError(f"object {name!r}: morph maps need levels in stored order (reorder=False)")
        lo, hi = object_box(levels)
        blobs = [encode_geometry(p, f, lo, hi, reorder=reorder) for p, f in levels]
        encoded = None
        if morphs is not None:
            encoded = [None if m is None else encode_morph(m, levels[k - 1][0].shape[0])
                       for k, m in enumerate(morphs)]
        return self.add_encoded(name, cls, lo, hi, errors, blobs, kind=kind, parent=parent, morphs=encoded)

    def add_encoded(self, name: str, cls: str, lo: np.ndarray, hi: np.ndarray, errors: Sequence[float],
                    blobs: Sequence[bytes], *, kind: int = MESH, parent: int = -1,
                    morphs: Sequence[bytes | None] | None = None,
                    counts: Sequence[tuple[int, int]] | None = None) -> int:
        """Add one object whose levels are already encoded, coarsest → finest; returns its id.

        For builders that encode in worker processes. Face and vertex counts
        are read from triangle payloads (``proto.geometry``), so they are what
        the client will draw; other payloads (a tree group's instance list)
        pass ``counts`` as (vertices, faces) per level.
        lo, hi : (3,) float — the object's box: it bounds the object's payloads and, in a hierarchy,
                 its whole subtree (so culling a node culls its descendants)
        kind   : one of ``MESH, HLOD, TERRAIN, TREES``
        parent : an object already added (its id), or −1
        morphs : per level, None or an encoded ``proto.morph`` map onto the previous level
        """
        self._check_open()
        k = len(blobs)
        if k == 0 or len(errors) != k:
            raise ValueError(f"object {name!r}: {k} levels but {len(errors)} errors")
        if not 0 <= kind < len(KINDS):
            raise ValueError(f"object {name!r}: kind {kind} is not one of 0..{len(KINDS) - 1}")
        if not -1 <= parent < self._n_objects:
            raise ValueError(f"object {name!r}: parent {parent} is not an object added before it")
        if morphs is not None and (len(morphs) != k or morphs[0] is not None):
            raise ValueError(f"object {name!r}: morphs must give one entry per level, None for level 0")
        if counts is None:
            counts = [_payload_counts(b) for b in blobs]
        elif len(counts) != k:
            raise ValueError(f"object {name!r}: {k} levels but {len(counts)} counts")
        morphs = morphs if morphs is not None else [None] * k
        cls_id = self._classes.setdefault(cls, len(self._classes))
        oid = self._n_objects
        lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
        if not (np.isfinite(lo).all() and np.isfinite(hi).all() and (hi >= lo).all()):
            raise ValueError(f"object {name!r}: box {lo.tolist()}..{hi.tolist()} is not finite and ordered")
        try:
            self._conn.execute(
                "INSERT INTO objects VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                (oid, name, cls_id, int(kind), int(parent), *map(float, lo), *map(float, hi)),
            )
            self._conn.executemany(
                "INSERT INTO representations VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?)",
                [
                    (self._n_reps + i, oid, i, int(counts[i][1]), int(counts[i][0]), float(errors[i]),
                     len(blobs[i]), sqlite3.Binary(blobs[i]),
                     None if morphs[i] is None else sqlite3.Binary(morphs[i]))
                    for i in range(k)
                ],
            )
        except sqlite3.Error as exc:
            raise StoreError(f"{self.path}: cannot add object {name!r}: {exc}") from None
        self._n_objects += 1
        self._n_reps += k
        self._lo, self._hi = np.minimum(self._lo, lo), np.maximum(self._hi, hi)
        return oid

    def add_model(self, name: str, blob: bytes, points: int, radius: float, lo: np.ndarray,
                  hi: np.ndarray) -> int:
        """Add a tree model's point payload (``proto.points``); returns its id for instance lists."""
        self._check_open()
        mid = self._n_models
        try:
            self._conn.execute(
                "INSERT INTO models VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                (mid, name, int(points), float(radius), *map(float, np.asarray(lo).reshape(3)),
                 *map(float, np.asarray(hi).reshape(3)), sqlite3.Binary(blob)),
            )
        except sqlite3.Error as exc:
            raise StoreError(f"{self.path}: cannot add model {name!r}: {exc}") from None
        self._n_models += 1
        return mid

    def set_meta(self, **values: Any) -> None:
        """Extra JSON meta values (origin, crs, viewpoints, sources, …), written on commit."""
        self._check_open()
        reserved = set(_META_KEYS) | {"generator", "seed", "created"}
        clash = reserved & set(values)
        if clash:
            raise ValueError(f"meta keys {sorted(clash)} are set by the writer itself")
        json.dumps(values)  # fail now, not at commit
        self._extra.update(values)

    def set_tour(self, keys: Iterable[Any]) -> None:
        """The scene's camera tour: ``TourKey`` objects or {"t", "eye", "forward", "up"} mappings.

        Each key is validated as a ``proto.messages.TourKey`` now, so a store
        never holds a tour the server could not put in a ``Welcome``.
        """
        tour = [_pose_dict(k, with_t=True) for k in keys]
        for key in tour:
            TourKey.model_validate(key)
        self._tour = tour

    def set_start(self, pose: Any) -> None:
        """Where a session starts: a ``Pose`` or {"eye", "forward", "up"} mapping (validated)."""
        start = _pose_dict(pose, with_t=False)
        Pose.model_validate(start)
        self._start = start

    def commit(self) -> Path:
        """Write meta, close, and rename the finished file onto ``path``; returns ``path``."""
        self._check_open()
        if self._n_objects == 0:
            self.abort()
            raise StoreError(f"{self.path}: refusing to write a store without objects")
        start = self._start
        if start is None and self._tour:
            start = {k: v for k, v in self._tour[0].items() if k != "t"}
        elif start is None:
            start = _default_start(self._lo, self._hi)
        meta = {
            "schema_version": SCHEMA_VERSION,
            "name": self.name,
            "bounds": [self._lo.tolist(), self._hi.tolist()],
            "tour": self._tour,
            "start": start,
            "class_names": list(self._classes),
            "generator": self.generator,
            "seed": self.seed,
            "created": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
            **self._extra,
        }
        try:
            self._conn.executemany("INSERT INTO meta VALUES (?, ?)", [(k, json.dumps(v)) for k, v in meta.items()])
            self._conn.commit()
            self._conn.close()
            os.chmod(self._tmp, 0o644)  # mkstemp made it private; a store is meant to be shared
            with open(self._tmp, "rb+") as f:
                os.fsync(f.fileno())  # the rename must not land before the data
            os.replace(self._tmp, self.path)
        except (sqlite3.Error, OSError) as exc:
            self.abort()
            raise StoreError(f"{self.path}: cannot write store: {exc}") from None
        self._done = True
        return self.path

    def abort(self) -> None:
        """Discard the build: close and delete the temporary file. Safe to call twice."""
        if self._done:
            return
        self._done = True
        conn = getattr(self, "_conn", None)
        if conn is not None:
            conn.close()
        self._tmp.unlink(missing_ok=True)

    def _check_open(self) -> None:
        if self._done:
            raise StoreError(f"{self.path}: writer already committed or aborted")

    def __enter__(self) -> "SceneWriter":
        return self

    def __exit__(self, exc_type: type | None, exc: BaseException | None, tb: object) -> None:
        if exc_type is not None:
            self.abort()
        elif not self._done:
            self.commit()


def object_box(levels: Sequence[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    """Box (lo (3,), hi (3,) float64) of an object over all its levels.

    It is the full-detail box in spirit, but quadric simplification places
    vertices where the error is least, which can be a few centimetres outside
    the full-detail box; quantizing in the full-detail box would clamp them.
    One box for all levels keeps levels aligned for geomorphing, and the
    stored box bounds every level, so culling with it is conservative.
    """
    lo = np.min([np.asarray(p, np.float64).min(axis=0) for p, _ in levels], axis=0)
    hi = np.max([np.asarray(p, np.float64).max(axis=0) for p, _ in levels], axis=0)
    return lo, hi


def _payload_counts(blob: bytes) -> tuple[int, int]:
    """(vertices, faces) from a geometry payload's header."""
    head = msgpack.unpackb(blob, raw=False)
    return int(head["nv"]), int(head["nf"])


def _default_start(lo: np.ndarray, hi: np.ndarray) -> dict:
    """A pose outside the scene's box looking at its centre, for stores built without a tour."""
    centre = (lo + hi) / 2
    eye = centre + np.array([0.0, -1.0, 0.5]) * float(np.linalg.norm(hi - lo))
    return {"eye": eye.tolist(), "forward": (centre - eye).tolist(), "up": [0.0, 0.0, 1.0]}
