"""Writing a scene store: atomically, one object (all its levels) at a time.

Writing is atomic (``SceneWriter``): the file is built under a temporary name
in the target's directory and renamed over the target only when complete, so a
reader never sees a half-written store and a failed build leaves none behind.
The schema and the reader are in ``server.scene.store``.

Builders that encode in worker processes turn an object's levels into payloads
with ``encode_levels`` and hand them to ``SceneWriter.add_encoded``; the others
call ``SceneWriter.add_object``, which does both.
"""

from __future__ import annotations

import json
import os
import re
import sqlite3
import tempfile
import time
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping, Sequence

import msgpack
import numpy as np

from proto.geometry import encode_geometry
from proto.messages import Pose, TourKey
from proto.morph import encode_morph

from .index import KINDS, MESH
from .store import APPLICATION_ID, META_KEYS, OPTIONAL_TABLES, SCHEMA_VERSION, TABLES, SceneStore, StoreError, walkable_row
from .tour import TOUR_KINDS
from .walkable import walkable_grid

__all__ = ["SceneWriter", "encode_levels", "object_box", "TOUR_NAME"]

#: What a tour's name may be (``proto.messages.Name``: a client names it in its hello).
TOUR_NAME = re.compile(r"^[A-Za-z0-9_.\-]{1,128}$")


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
                 seed: int | None = None, class_names: Sequence[str] = (), walkable: bool = True) -> None:
        """path: the store to make; name: the scene's name (default: the file's stem);
        generator, seed: recorded in meta; class_names: class ids to fix in this order
        (classes first seen in ``add_object`` are appended); walkable: compute the walkable grid
        (``server.scene.walkable``) from the finished store and keep it in it."""
        self.path = Path(path)
        self.walkable = bool(walkable)
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
        self._tours: dict[str, dict] = {}  # name → {"kind", "keys"}
        self._default: str | None = None  # the name of ``_tour``
        self._maker: tuple[Callable, tuple[str, ...]] | None = None
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
            for ddl in (*TABLES.values(), *OPTIONAL_TABLES.values()):
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
        lo, hi, blobs, encoded = encode_levels(levels, morphs, reorder=reorder)
        return self.add_encoded(name, cls, lo, hi, errors, blobs, kind=kind, parent=parent, morphs=encoded)

    def add_encoded(self, name: str, cls: str, lo: np.ndarray, hi: np.ndarray, errors: Sequence[float],
                    blobs: Sequence[bytes], *, kind: int = MESH, parent: int = -1,
                    morphs: Sequence[bytes | None] | None = None,
                    counts: Sequence[tuple[int, int]] | None = None,
                    fidelity: Sequence[tuple[str, float, float, float] | None] | None = None) -> int:
        """Add one object whose levels are already encoded, coarsest → finest; returns its id.

        For builders that encode in worker processes. Face and vertex counts, and
        the texels of a level's texture, are read from triangle payloads
        (``proto.geometry``), so they are what the client will draw; other payloads
        (a tree group's instance list, untextured) pass ``counts`` as (vertices, faces) per level.
        lo, hi : (3,) float — the object's box: it bounds the object's payloads and, in a hierarchy,
                 its whole subtree (so culling a node culls its descendants)
        kind   : one of ``MESH, HLOD, TERRAIN, TREES``
        parent : an object already added (its id), or −1
        morphs : per level, None or an encoded ``proto.morph`` map onto the previous level
        fidelity : per level, None or (method, area ratio, silhouette IoU, FLIP[, closed]) as
                 measured against the finest level (``server.scene.fidelity``); closed: whether
                 the area bound applies (the finest level is closed)
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
            heads = [_payload_counts(b) for b in blobs]
            counts, texels = [h[:2] for h in heads], [h[2] for h in heads]
        elif len(counts) != k:
            raise ValueError(f"object {name!r}: {k} levels but {len(counts)} counts")
        else:
            texels = [0] * k
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
                "INSERT INTO representations (id, object, level, faces, vertices, error, bytes, geometry, morph, "
                "texels) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                [
                    (self._n_reps + i, oid, i, int(counts[i][1]), int(counts[i][0]), float(errors[i]),
                     len(blobs[i]), sqlite3.Binary(blobs[i]),
                     None if morphs[i] is None else sqlite3.Binary(morphs[i]), int(texels[i]))
                    for i in range(k)
                ],
            )
            if fidelity is not None:
                if len(fidelity) != k:
                    raise ValueError(f"object {name!r}: {k} levels but {len(fidelity)} fidelity entries")
                self._conn.executemany(
                    "INSERT INTO fidelity VALUES (?, ?, ?, ?, ?, ?)",
                    [(self._n_reps + i, str(q[0]), float(q[1]), float(q[2]),
                      None if not np.isfinite(q[3]) else float(q[3]), None if len(q) < 5 else int(bool(q[4])))
                     for i, q in enumerate(fidelity) if q is not None])
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
        reserved = set(META_KEYS) | {"generator", "seed", "created", "tours", "default_tour"}
        clash = reserved & set(values)
        if clash:
            raise ValueError(f"meta keys {sorted(clash)} are set by the writer itself")
        json.dumps(values)  # fail now, not at commit
        self._extra.update(values)

    def set_tour(self, keys: Iterable[Any], name: str = "scene", kind: str = "scene") -> None:
        """The scene's default tour, the one a client that names none is sent: ``TourKey`` objects or
        {"t", "eye", "forward", "up"} mappings, kept under ``name`` among the named tours too.

        Each key is validated as a ``proto.messages.TourKey`` now, so a store
        never holds a tour the server could not put in a ``Welcome``.
        """
        self.add_tour(name, kind, keys)
        self._tour = self._tours[name]["keys"]
        self._default = name

    def add_tour(self, name: str, kind: str, keys: Iterable[Any]) -> None:
        """A named tour beside the default one (``kind``: ``server.scene.tour.TOUR_KINDS``), keys as ``set_tour``."""
        if not isinstance(name, str) or not TOUR_NAME.match(name):
            raise ValueError(f"tour name {name!r}: 1 to 128 letters, digits, '_', '.' or '-'")
        if kind not in TOUR_KINDS:
            raise ValueError(f"tour {name!r}: kind {kind!r} is not one of {', '.join(TOUR_KINDS)}")
        tour = [_pose_dict(k, with_t=True) for k in keys]
        for key in tour:
            TourKey.model_validate(key)
        self._tours[name] = {"kind": kind, "keys": tour}

    def make_tours(self, make: Callable[[SceneStore], Mapping[str, Mapping[str, Any]]],
                   prefer: Sequence[str] = ()) -> None:
        """Tours made at commit from the finished store, after its walkable grid: ``make(store)`` returns
        {name: {"kind", "keys"}}; the first of ``prefer`` it makes becomes the default tour (in place of
        ``set_tour``'s, and the start pose with it unless ``set_start`` gave one)."""
        self._maker = (make, tuple(prefer))

    def _tour_meta(self) -> dict:
        """The meta values of the tours: ``tour`` (the default's keys), ``tours`` (name → kind, duration, keys),
        ``default_tour`` (the default's name)."""
        tours = {name: {"kind": t["kind"], "duration": _duration(t["keys"]), "keys": t["keys"]}
                 for name, t in self._tours.items()}
        return {"tour": self._tour, "tours": tours, "default_tour": self._default}

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
            **self._tour_meta(),
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
            if self.walkable:
                self._add_walkable()
            if self._maker is not None:
                self._add_made_tours(start_given=self._start is not None)
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

    def _add_walkable(self) -> None:
        """The walkable grid, computed from the store as written so far (read back as any reader would)."""
        with SceneStore.open(self._tmp) as store:
            grid = walkable_grid(store)
        self._conn.execute("INSERT INTO walkable VALUES (?, ?, ?, ?, ?, ?, ?)", walkable_row(grid))
        self._conn.commit()

    def _add_made_tours(self, start_given: bool) -> None:
        """The tours ``make_tours`` asked for, made from the store as written so far (its walkable grid read
        back, or computed if the writer keeps none); meta's tour values rewritten to hold them."""
        make, prefer = self._maker
        with SceneStore.open(self._tmp) as store:
            made = dict(make(store))
        for name, tour in made.items():
            self.add_tour(name, tour["kind"], tour["keys"])
        chosen = next((name for name in prefer if name in made), None)
        values = dict(self._tour_meta())
        if chosen is not None:
            self._tour, self._default = self._tours[chosen]["keys"], chosen
            values.update(tour=self._tour, default_tour=chosen)
            if not start_given:
                values["start"] = {k: v for k, v in self._tour[0].items() if k != "t"}
        self._conn.executemany("INSERT OR REPLACE INTO meta VALUES (?, ?)",
                               [(k, json.dumps(v)) for k, v in values.items()])
        self._conn.commit()

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


def encode_levels(levels: Sequence[tuple[np.ndarray, np.ndarray]],
                  morphs: Sequence[np.ndarray | None] | None = None, *, reorder: bool = True,
                  colours: Sequence[np.ndarray] | None = None,
                  uvs: Sequence[np.ndarray] | None = None, textures: Sequence[np.ndarray] | None = None,
                  ) -> tuple[np.ndarray, np.ndarray, list[bytes], list[bytes | None] | None]:
    """An object's levels as store payloads: (lo (3,), hi (3,) float64, geometry blobs, morph blobs).

    levels : [(positions (n_k, 3) float, faces (m_k, 3) int), ...] coarsest → finest, all
             quantized in one box (``object_box``)
    morphs : per level, None or the (n_k,) map of its vertices onto level k−1's (encoded as
             ``proto.morph``); None gives None for the morph blobs
    reorder: put each level in GPU order while encoding; morph maps index stored vertices, so
             levels that carry them must already be in that order (``reorder=False``)
    colours: per level, (n_k, 3) uint8 per vertex (``server.scene.colours``), or None: colourless
    uvs, textures : per level, (n_k, 2) float UVs and (s_k, s_k, 3) uint8 texture
             (``server.scene.texcoords``), or None: untextured
    """
    lo, hi = object_box(levels)
    if colours is not None and len(colours) != len(levels):
        raise ValueError(f"{len(levels)} levels but {len(colours)} colour arrays")
    if (uvs is None) != (textures is None) or (uvs is not None and not len(uvs) == len(textures) == len(levels)):
        raise ValueError(f"{len(levels)} levels need as many UV arrays and textures, or neither")
    blobs = [encode_geometry(p, f, lo, hi, reorder=reorder, colours=None if colours is None else colours[k],
                             uv=None if uvs is None else uvs[k], texture=None if textures is None else textures[k])
             for k, (p, f) in enumerate(levels)]
    encoded = None
    if morphs is not None:
        encoded = [None if m is None else encode_morph(m, levels[k - 1][0].shape[0])
                   for k, m in enumerate(morphs)]
    return lo, hi, blobs, encoded


def _duration(keys: Sequence[Mapping[str, Any]]) -> float:
    """Seconds of one loop of a tour's keys (0 for fewer than two)."""
    return float(keys[-1]["t"] - keys[0]["t"]) if len(keys) >= 2 else 0.0


def _payload_counts(blob: bytes) -> tuple[int, int, int]:
    """(vertices, faces, texels) from a geometry payload's header; texels: its texture's tw × th, 0 without one."""
    head = msgpack.unpackb(blob, raw=False)
    return int(head["nv"]), int(head["nf"]), int(head.get("tw", 0)) * int(head.get("th", 0))


def _default_start(lo: np.ndarray, hi: np.ndarray) -> dict:
    """A pose outside the scene's box looking at its centre, for stores built without a tour."""
    centre = (lo + hi) / 2
    eye = centre + np.array([0.0, -1.0, 0.5]) * float(np.linalg.norm(hi - lo))
    return {"eye": eye.tolist(), "forward": (centre - eye).tolist(), "up": [0.0, 0.0, 1.0]}
