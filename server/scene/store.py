"""The scene store: one SQLite file per scene, its schema, and reading it.

Why SQLite: one file to copy, random access to any representation's blob from
several threads, and a schema that says what the file holds. The store keeps
each representation's geometry exactly as it goes on the wire
(``proto.geometry``), so the server streams blobs without re-encoding them.

Opening a store (``SceneStore.open``) checks the file and loads its index into
memory (``server.scene.index.SceneIndex``, which explains object and
representation ids, levels and kinds); geometry blobs are read on demand.
``server.scene.writer.SceneWriter`` writes stores.

Schema (version ``SCHEMA_VERSION``; ``PRAGMA application_id`` marks the file)::

    meta(key TEXT PRIMARY KEY, value TEXT)             JSON values: schema_version, name, bounds,
                                                        tour, start, class_names, generator, seed,
                                                        created, origin, crs, viewpoints, sources
    objects(id INTEGER PRIMARY KEY, name TEXT, class INTEGER, kind INTEGER, parent INTEGER,
            lo_x, lo_y, lo_z, hi_x, hi_y, hi_z REAL)    box of each object over all its levels
    representations(id INTEGER PRIMARY KEY, object INTEGER, level INTEGER, faces INTEGER,
                    vertices INTEGER, error REAL, bytes INTEGER, geometry BLOB,
                    morph BLOB NULL, texels INTEGER NULL)
                                                        morph: ``proto.morph`` map of this level's
                                                        vertices onto the previous level's; texels:
                                                        width × height of the base-colour texture
                                                        the payload carries (0 none; the column is
                                                        absent from stores built before it: 0)
    models(id INTEGER PRIMARY KEY, name TEXT, points INTEGER, radius REAL,
           lo_x, lo_y, lo_z, hi_x, hi_y, hi_z REAL, geometry BLOB)
                                                        tree models as prefix-ordered point sets
                                                        (``proto.points``), shared by tree groups
    walkable(id INTEGER PRIMARY KEY (= 0), origin_x, origin_y, cell REAL, ny, nx INTEGER, ground BLOB)
                                                        optional: the walkable grid, heights zstd float32

A ``trees`` object's representation holds its instance list
(``proto.points.encode_instances``); its ``vertices`` count is the group's
splats at x = 1 and its ``faces`` count is 0. The ``kind`` column holds ids into ``server.scene.index.KINDS``.
"""

from __future__ import annotations

import json
import os
import sqlite3
import threading
from pathlib import Path
from typing import Iterable

import numpy as np
import zstandard

from proto.walkable import WalkableGrid
from proto.walkable import encode as walkable_encode

from .index import KINDS, SceneIndex, hierarchy

__all__ = ["SCHEMA_VERSION", "APPLICATION_ID", "TABLES", "OPTIONAL_TABLES", "META_KEYS", "StoreError", "SceneStore",
           "walkable_row"]

SCHEMA_VERSION = 2
#: ``PRAGMA application_id`` of a walkstream store ("WkSt"), so foreign SQLite files are told apart.
APPLICATION_ID = 0x576B5374

#: The tables' DDL, by table name: what ``SceneWriter`` creates and ``SceneStore.open`` requires.
TABLES = {
    "meta": "CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT NOT NULL)",
    "objects": (
        "CREATE TABLE objects (id INTEGER PRIMARY KEY, name TEXT NOT NULL, class INTEGER NOT NULL, "
        "kind INTEGER NOT NULL, parent INTEGER NOT NULL, lo_x REAL, lo_y REAL, lo_z REAL, hi_x REAL, hi_y REAL, hi_z REAL)"
    ),
    "representations": (
        "CREATE TABLE representations (id INTEGER PRIMARY KEY, object INTEGER NOT NULL, "
        "level INTEGER NOT NULL, faces INTEGER NOT NULL, vertices INTEGER NOT NULL, "
        "error REAL NOT NULL, bytes INTEGER NOT NULL, geometry BLOB NOT NULL, morph BLOB, texels INTEGER)"
    ),
    "models": (
        "CREATE TABLE models (id INTEGER PRIMARY KEY, name TEXT NOT NULL, points INTEGER NOT NULL, "
        "radius REAL NOT NULL, lo_x REAL, lo_y REAL, lo_z REAL, hi_x REAL, hi_y REAL, hi_z REAL, "
        "geometry BLOB NOT NULL)"
    ),
}
#: Optional tables: a store without them still opens (older builds); ``fidelity`` holds each
#: measured representation's method, area ratio, least silhouette IoU, FLIP (``server.scene.fidelity``)
#: and whether the area bound applies to it (``closed``; NULL in older builds: it did); ``walkable`` the
#: walkable grid (``server.scene.walkable``) in one row, its heights as zstd-compressed float32 (ny, nx).
OPTIONAL_TABLES = {
    "fidelity": (
        "CREATE TABLE fidelity (rep INTEGER PRIMARY KEY, method TEXT NOT NULL, area_ratio REAL NOT NULL, "
        "iou REAL NOT NULL, flip REAL, closed INTEGER)"
    ),
    "walkable": (
        "CREATE TABLE walkable (id INTEGER PRIMARY KEY CHECK (id = 0), origin_x REAL NOT NULL, "
        "origin_y REAL NOT NULL, cell REAL NOT NULL, ny INTEGER NOT NULL, nx INTEGER NOT NULL, "
        "ground BLOB NOT NULL)"
    ),
}
#: Meta keys every store has (``SceneWriter.commit`` writes them, ``SceneStore.open`` requires them).
META_KEYS = ("schema_version", "name", "bounds", "tour", "start", "class_names")
#: Blobs fetched per SELECT in ``geometries`` (SQLite's default variable limit is 999+).
_CHUNK = 500


class StoreError(Exception):
    """A scene store cannot be opened, read or written; the message names the file."""


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
        self._walkable_lock = threading.Lock()  # one computation of a missing grid, however many ask
        self._walkable: tuple | None = None  # (grid, its wire bytes or None until asked for)

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

    def fidelity(self) -> dict[str, np.ndarray] | None:
        """Measured representations: rep, method, area_ratio, iou, flip (NaN: not rendered), closed
        (whether the area bound applies); None if unmeasured."""
        conn = self._connection()
        if "fidelity" not in _table_names(conn):
            return None
        has_closed = any(r[1] == "closed" for r in conn.execute("PRAGMA table_info(fidelity)"))
        rows = conn.execute("SELECT rep, method, area_ratio, iou, flip, " + ("closed" if has_closed else "NULL")
                            + " FROM fidelity ORDER BY rep").fetchall()
        return {
            "closed": np.array([r[5] is None or bool(r[5]) for r in rows], bool),
            "rep": np.array([r[0] for r in rows], np.int64),
            "method": np.array([r[1] for r in rows], object),
            "area_ratio": np.array([r[2] for r in rows], np.float64),
            "iou": np.array([r[3] for r in rows], np.float64),
            "flip": np.array([np.nan if r[4] is None else r[4] for r in rows], np.float64),
        }

    def walkable(self) -> WalkableGrid:
        """The scene's walkable grid (``server.scene.walkable``): as stored at build time, or — for a store
        built before grids were — computed on first use and kept in memory (the store stays read-only)."""
        with self._walkable_lock:
            if self._walkable is None:
                grid = self.stored_walkable()
                if grid is None:
                    from .walkable import walkable_grid

                    grid = walkable_grid(self)
                self._walkable = (grid, None)
            return self._walkable[0]

    def walkable_encoded(self) -> bytes:
        """``proto.walkable.encode`` of ``walkable()``, encoded once per open store (every welcome shares it)."""
        grid = self.walkable()
        with self._walkable_lock:
            if self._walkable[1] is None:
                self._walkable = (grid, walkable_encode(grid))
            return self._walkable[1]

    def stored_walkable(self) -> WalkableGrid | None:
        """The walkable grid as the build stored it; None for a store built before grids were (nothing computed)."""
        with self._lock:
            conn = self._connection()
            if "walkable" not in _table_names(conn):
                return None
            row = conn.execute("SELECT origin_x, origin_y, cell, ny, nx, ground FROM walkable WHERE id = 0").fetchone()
        if row is None:
            return None
        try:
            ny, nx = int(row[3]), int(row[4])
            raw = zstandard.ZstdDecompressor().decompress(row[5], max_output_size=4 * ny * nx)
            ground = np.frombuffer(raw, "<f4").reshape(ny, nx)
            return WalkableGrid(origin=(row[0], row[1]), cell=row[2], ground=ground)
        except (ValueError, zstandard.ZstdError) as exc:
            raise StoreError(f"{self.path}: corrupt: walkable grid: {exc}") from None

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


def walkable_row(grid: WalkableGrid) -> tuple:
    """The ``walkable`` table's row for ``grid`` (``SceneWriter`` inserts it, ``SceneStore.walkable`` reads it)."""
    ny, nx = grid.shape
    blob = zstandard.ZstdCompressor(level=9).compress(grid.ground.astype("<f4").tobytes())
    return (0, grid.origin[0], grid.origin[1], grid.cell, ny, nx, sqlite3.Binary(blob))


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
        raise StoreError(f"{path}: schema version {version!r}, this program reads version {SCHEMA_VERSION}; "
                         "rebuild it with `walkstream build`")
    for table in TABLES:
        if table not in tables:
            raise StoreError(f"{path}: corrupt: missing table '{table}'")
    absent = [k for k in META_KEYS if k not in meta]
    if absent:
        raise StoreError(f"{path}: corrupt: meta lacks {', '.join(absent)}")
    try:
        obj = conn.execute(
            "SELECT id, class, kind, parent, lo_x, lo_y, lo_z, hi_x, hi_y, hi_z FROM objects ORDER BY id"
        ).fetchall()
        # The texels column came after schema version 2's first stores: a store without it reads as
        # untextured (its textures still draw when asked for; the selection just does not prefer them),
        # which keeps every older store open instead of asking for a rebuild.
        has_texels = any(c[1] == "texels" for c in conn.execute("PRAGMA table_info(representations)"))
        rep = conn.execute(
            "SELECT id, object, level, faces, vertices, error, bytes, morph IS NOT NULL, "
            + ("COALESCE(texels, 0)" if has_texels else "0") + " FROM representations ORDER BY id"
        ).fetchall()
        mod = conn.execute(
            "SELECT id, points, radius, lo_x, lo_y, lo_z, hi_x, hi_y, hi_z FROM models ORDER BY id"
        ).fetchall()
    except sqlite3.Error as exc:
        raise StoreError(f"{path}: corrupt: {exc}") from None
    o = np.array(obj, np.float64).reshape(-1, 10)
    r = np.array(rep, np.float64).reshape(-1, 9)
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
    depth, child_ptr, child_ids = hierarchy(parent)
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
        rep_texels=r[:, 8].astype(np.int32),
        model_points=md[:, 1].astype(np.int32),
        model_radius=md[:, 2].astype(np.float32),
        model_lo=md[:, 3:6].astype(np.float32),
        model_hi=md[:, 6:9].astype(np.float32),
        tour=list(meta["tour"]),
        start=dict(meta["start"]),
        meta=meta,
    )
