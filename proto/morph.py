"""Geomorphs on the wire: vertex maps between levels, and the ramps a schedule is made of.

A morph map gives, for each vertex of a level, the vertex of the next coarser level it morphs to.

Stored next to a level's geometry and sent with it, so the client can blend
level k toward level k − 1 (``server.scene.lod``). Vertex ids are the stored
ones (``proto.geometry`` payloads, GPU order) of both levels.

Payload (a msgpack map)::

    enc   "mm1"      encoding tag
    n     int        entries: vertices of the finer level
    nc    int        vertices of the coarser level; every entry is < nc
    data  bytes      meshoptimizer index-sequence codec over the n entries (uint32)

The index-sequence codec (zigzag deltas against recent values, then a byte
coder) suits maps from edge collapses, whose entries repeat and move little:
it packs them tighter than zstd over the raw uint16/uint32 entries.

A schedule makes every object's level a piecewise-linear function of time; its
pieces are ramps (``ramp_levels``, one ``Morphs`` row each). ``LevelRamps`` is
the table of one ramp per object that the server's scheduler (``server.select.morph``)
plans with and the client's executor (``client.schedule``) draws from.
"""

from __future__ import annotations

from dataclasses import dataclass

import meshoptimizer
import msgpack
import numpy as np

from .errors import ProtocolError
from .geometry import MAX_VERTICES

__all__ = ["MORPH_ENCODING", "encode_morph", "decode_morph", "ramp_levels", "LevelRamps"]

MORPH_ENCODING = "mm1"


def encode_morph(vertex_map: np.ndarray, n_coarse: int) -> bytes:
    """Encode a morph map.

    vertex_map : (n,) int, 0 ≤ entry < n_coarse, n ≥ 1 — vertex v of the finer
                 level morphs to vertex ``vertex_map[v]`` of the coarser one
    n_coarse   : vertices of the coarser level
    Raises ValueError on a malformed map (a local bug, not the peer's).
    """
    m = np.asarray(vertex_map)
    if m.ndim != 1 or m.size == 0 or not np.issubdtype(m.dtype, np.integer):
        raise ValueError(f"a morph map must be a non-empty 1-d integer array, got {m.dtype} {m.shape}")
    n_coarse = int(n_coarse)
    if not 0 < n_coarse <= MAX_VERTICES or m.size > MAX_VERTICES:
        raise ValueError(f"morph map of {m.size} entries onto {n_coarse} vertices exceeds 1..{MAX_VERTICES}")
    if int(m.min()) < 0 or int(m.max()) >= n_coarse:
        raise ValueError(f"morph map entries must lie in 0..{n_coarse - 1}, got {int(m.min())}..{int(m.max())}")
    seq = np.ascontiguousarray(m, dtype=np.uint32)
    data = meshoptimizer.encode_index_sequence(seq, seq.size, n_coarse)
    return msgpack.packb({"enc": MORPH_ENCODING, "n": int(seq.size), "nc": n_coarse, "data": bytes(data)},
                         use_bin_type=True)


def _count(payload: dict, name: str) -> int:
    value = payload.get(name)
    if not isinstance(value, int) or isinstance(value, bool):
        raise ProtocolError("bad_geometry", f"morph field '{name}' is missing or not an integer")
    if not 0 < value <= MAX_VERTICES:
        raise ProtocolError("bad_geometry", f"morph field '{name}' = {value} outside 1..{MAX_VERTICES}")
    return value


def decode_morph(blob: bytes, n_fine: int | None = None, n_coarse: int | None = None) -> np.ndarray:
    """Decode and validate a morph map; returns (n,) uint32, every entry < nc.

    n_fine, n_coarse : when given, the vertex counts of the two levels the map
        must connect (from their geometry payloads).
    Any defect raises ``ProtocolError('bad_geometry', ...)``.
    """
    try:
        payload = msgpack.unpackb(blob, raw=False, strict_map_key=True)
    except Exception as exc:  # msgpack raises several unrelated types
        raise ProtocolError("bad_geometry", f"morph payload is not msgpack: {exc}") from None
    if not isinstance(payload, dict):
        raise ProtocolError("bad_geometry", "morph payload is not a map")
    if payload.get("enc") != MORPH_ENCODING:
        raise ProtocolError("bad_geometry", f"unknown morph encoding {payload.get('enc')!r}")
    n, nc = _count(payload, "n"), _count(payload, "nc")
    if n_fine is not None and n != n_fine:
        raise ProtocolError("bad_geometry", f"morph map has {n} entries for a level of {n_fine} vertices")
    if n_coarse is not None and nc != n_coarse:
        raise ProtocolError("bad_geometry", f"morph map targets {nc} vertices, the coarser level has {n_coarse}")
    data = payload.get("data")
    if not isinstance(data, bytes):
        raise ProtocolError("bad_geometry", "morph field 'data' is missing or not bytes")
    try:
        seq = meshoptimizer.decode_index_sequence(n, 4, data)
    except Exception as exc:
        raise ProtocolError("bad_geometry", f"morph data does not decode: {exc}") from None
    seq = np.frombuffer(np.ascontiguousarray(seq).tobytes(), dtype=np.uint32)
    if seq.size != n:
        raise ProtocolError("bad_geometry", f"morph data decodes to {seq.size} entries, expected {n}")
    if int(seq.max()) >= nc:
        raise ProtocolError("bad_geometry", f"morph entry {int(seq.max())} out of range for {nc} vertices")
    return seq


def ramp_levels(level_from, level_to, t0, t1, t: float) -> np.ndarray:
    """What a ``Morphs`` entry means: the level of a ramp level_from → level_to over [t0, t1) at time t.

    level_from before t0, level_to from t1 on, linear between (arrays broadcast).
    Both the server's scheduler and the client's executor read schedules through this.
    """
    t0 = np.asarray(t0, np.float64)
    t1 = np.asarray(t1, np.float64)
    span = t1 - t0
    f = np.where(span > 0, (t - t0) / np.where(span > 0, span, 1.0), (t >= t1).astype(np.float64))
    f = np.clip(f, 0.0, 1.0)
    level_from = np.asarray(level_from, np.float64)
    return level_from + (np.asarray(level_to, np.float64) - level_from) * f


@dataclass(frozen=True)
class LevelRamps:
    """Every object's level as one ramp, then steady: the ramp structure both ends of a schedule keep.

    key        : (p,) int64, sorted — the object (its level-0 representation id; for vegetation, its group's)
    level_from, level_to : (p,) float — the level ramps level_from → level_to over [t0, t1) and stays at level_to
    t0, t1     : (p,) float
    The names are the ``Morphs`` columns': a row of a delta's ramps is a row of this.
    """

    key: np.ndarray
    level_from: np.ndarray
    level_to: np.ndarray
    t0: np.ndarray
    t1: np.ndarray

    @classmethod
    def empty(cls) -> "LevelRamps":
        z = np.zeros(0)
        return cls(np.zeros(0, np.int64), z, z, z, z)

    @classmethod
    def steady(cls, key, level, t: float) -> "LevelRamps":
        """Objects (any order) held at ``level`` from t on; raises ValueError if an object appears twice."""
        key = np.asarray(key, np.int64)
        level = np.asarray(level, np.float64)
        order = np.argsort(key, kind="stable")
        key, level = key[order], level[order]
        if key.size > 1 and (np.diff(key) == 0).any():
            raise ValueError("an object appears twice in one selection")
        return cls(key, level, level.copy(), np.full(key.size, t), np.full(key.size, t))

    def at(self, t: float) -> np.ndarray:
        """(p,) float — every object's level at time t."""
        return ramp_levels(self.level_from, self.level_to, self.t0, self.t1, t)

    def override(self, key, level_from, level_to, t0, t1) -> "LevelRamps":
        """These rows with the given objects' ramps replaced (objects not here are added)."""
        key = np.asarray(key, np.int64)
        if key.size == 0:
            return self
        keep = ~np.isin(self.key, key)
        k = np.concatenate([self.key[keep], key])
        order = np.argsort(k, kind="stable")
        cat = lambda a, b: np.concatenate([np.asarray(a, np.float64)[keep], np.asarray(b, np.float64)])[order]
        return LevelRamps(k[order], cat(self.level_from, level_from), cat(self.level_to, level_to),
                          cat(self.t0, t0), cat(self.t1, t1))
