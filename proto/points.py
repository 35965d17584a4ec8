"""Point and instance payloads: tree models as prefix-ordered splats, tree groups as instance lists.

Like ``proto.geometry`` a payload is stored exactly as it is sent. Points are
never reordered: their order is the model's LOD (every prefix is a coarser
model, ``server.scene.points``), so a client may draw or even receive only a
prefix. Positions are quantized to 16 bits in the model's box with the splat
radius as float16 in the fourth lane; normals are octahedral int8 pairs; every
buffer goes through meshoptimizer's vertex codec (strides multiple of 4). That
decoder accepts a stream with a wrong vertex count (it repeats or drops
vertices) and decodes most bit flips to other data, so every payload carries a
CRC-32 of its counts, box and raw buffers, checked after decoding.

Point payload (a msgpack map)::

    enc  "pq16"
    n    int                  point count
    lo   [x, y, z] float      box minimum
    ext  [x, y, z] float      box extent (> 0 on every axis)
    pb   bytes                meshopt, n × 4 uint16 (x, y, z, radius as float16 bits)
    nb   bytes                meshopt, n × 4 int8 (octahedral u, v, 0, 0)
    cb   bytes                meshopt, n × 4 uint8 (r, g, b, 0)
    crc  int                  zlib.crc32 of n (int64), lo, ext (float64) and the raw pb, nb, cb

Instance payload::

    enc  "inst"
    k    int                  instance count
    ib   bytes                meshopt, k × uint32 model ids
    mb   bytes                meshopt, k × 12 float32: rows 0–2 of the 4 × 4 model→world
                              matrix, row-major (row 3 is 0 0 0 1)
    crc  int                  zlib.crc32 of k (int64) and the raw ib, mb
"""

from __future__ import annotations

from dataclasses import dataclass

import zlib

import meshoptimizer
import msgpack
import numpy as np

from .errors import ProtocolError
from .geometry import _vec3, dequantize, quantize, safe_box

__all__ = ["ENCODING", "INSTANCES", "MAX_POINTS", "MAX_INSTANCES", "Points", "Instances", "encode_points",
           "decode_points", "encode_instances", "decode_instances", "oct_encode", "oct_decode"]

ENCODING = "pq16"
INSTANCES = "inst"
MAX_POINTS = 1 << 22
MAX_INSTANCES = 1 << 20
_F16_MAX = 65504.0


@dataclass(frozen=True)
class Points:
    """Decoded splats, in stored (prefix) order.

    positions : (n, 3) float32, model space
    normals   : (n, 3) float32, unit
    colors    : (n, 3) uint8
    radius    : (n,) float32 ≥ 0, the splat radius of the prefix ending at each point
    """

    positions: np.ndarray
    normals: np.ndarray
    colors: np.ndarray
    radius: np.ndarray

    def __len__(self) -> int:
        return int(self.positions.shape[0])


@dataclass(frozen=True)
class Instances:
    """Decoded instance list: model (k,) uint32 and matrix (k, 4, 4) float32 (model → world)."""

    model: np.ndarray
    matrix: np.ndarray

    def __len__(self) -> int:
        return int(self.model.shape[0])


def oct_encode(normals: np.ndarray) -> np.ndarray:
    """(n, 3) unit vectors → (n, 2) int8 octahedral coordinates (zero vectors → +z)."""
    v = np.asarray(normals, np.float64)
    s = np.abs(v).sum(axis=1, keepdims=True)
    v = np.where(s > 0, v / np.where(s > 0, s, 1), [0.0, 0.0, 1.0])
    u, w = v[:, 0], v[:, 1]
    fold = v[:, 2] < 0
    u2 = np.where(fold, (1 - np.abs(w)) * np.where(u >= 0, 1, -1), u)
    w2 = np.where(fold, (1 - np.abs(u)) * np.where(w >= 0, 1, -1), w)
    return np.clip(np.rint(np.column_stack([u2, w2]) * 127), -127, 127).astype(np.int8)


def oct_decode(e: np.ndarray) -> np.ndarray:
    """(n, 2) int8 octahedral coordinates → (n, 3) float32 unit vectors."""
    f = np.asarray(e, np.float64) / 127.0
    u, w = f[:, 0], f[:, 1]
    z = 1 - np.abs(u) - np.abs(w)
    t = np.maximum(-z, 0)
    u = u - np.where(u >= 0, t, -t)
    w = w - np.where(w >= 0, t, -t)
    v = np.column_stack([u, w, z])
    return (v / np.linalg.norm(v, axis=1, keepdims=True)).astype(np.float32)


def _crc(*parts: object) -> int:
    crc = 0
    for part in parts:
        crc = zlib.crc32(np.ascontiguousarray(part).tobytes(), crc)
    return crc


def _check(payload: dict, crc: int) -> None:
    value = payload.get("crc")
    if not isinstance(value, int) or isinstance(value, bool):
        raise ProtocolError("bad_geometry", "payload field 'crc' must be an integer")
    if value != crc:
        raise ProtocolError("bad_geometry", "payload checksum mismatch (damaged buffer or wrong count)")


def _meshopt(a: np.ndarray) -> bytes:
    a = np.ascontiguousarray(a)
    return meshoptimizer.encode_vertex_buffer(a, a.shape[0], a.itemsize * a.shape[1])


def encode_points(
    model: object = None,
    *,
    positions: np.ndarray | None = None,
    normals: np.ndarray | None = None,
    colors: np.ndarray | None = None,
    radius: np.ndarray | None = None,
    box_lo: np.ndarray | None = None,
    box_hi: np.ndarray | None = None,
) -> bytes:
    """Encode splats in their given order.

    model : anything with ``positions, normals, colors, radius`` and optionally
            ``lo, hi`` (a ``server.scene.points.PointModel``); keywords override its fields.
    positions (n, 3) float, normals (n, 3) float (normalised here), colors (n, 3) uint8,
    radius (n,) float ≥ 0 (stored as float16), box_lo/box_hi the quantization box
    (default: the points' bounds).
    """
    def pick(value: object, name: str) -> object:
        return value if value is not None else getattr(model, name, None)

    positions, normals = pick(positions, "positions"), pick(normals, "normals")
    colors, radius = pick(colors, "colors"), pick(radius, "radius")
    box_lo, box_hi = pick(box_lo, "lo"), pick(box_hi, "hi")
    if positions is None or normals is None or colors is None or radius is None:
        raise ValueError("encode_points needs positions, normals, colors and radius")
    p = np.asarray(positions, np.float64)
    nrm = np.asarray(normals, np.float64)
    col = np.asarray(colors)
    rad = np.asarray(radius, np.float64).reshape(-1)
    n = p.shape[0] if p.ndim == 2 else 0
    if p.ndim != 2 or p.shape[1] != 3 or not 0 < n <= MAX_POINTS:
        raise ValueError(f"positions must be (n, 3) with 0 < n ≤ {MAX_POINTS}, got {p.shape}")
    if nrm.shape != (n, 3) or col.shape != (n, 3) or rad.shape != (n,):
        raise ValueError(f"normals, colors and radius must match {n} points: {nrm.shape}, {col.shape}, {rad.shape}")
    if not (np.isfinite(p).all() and np.isfinite(nrm).all() and np.isfinite(rad).all()):
        raise ValueError("points contain NaN or infinity")
    if (rad < 0).any() or (rad > _F16_MAX).any():
        raise ValueError(f"radius must lie in 0..{_F16_MAX}")
    if col.dtype != np.uint8 and ((col < 0).any() or (col > 255).any()):
        raise ValueError("colors must lie in 0..255")
    if box_lo is None or box_hi is None:
        box_lo, box_hi = p.min(axis=0), p.max(axis=0)
    lo, ext = safe_box(np.minimum(box_lo, p.min(axis=0)), np.maximum(box_hi, p.max(axis=0)))
    q = quantize(p, lo, ext)
    q[:, 3] = rad.astype(np.float16).view(np.uint16)
    nb = np.zeros((n, 4), np.int8)
    nb[:, :2] = oct_encode(nrm)
    cb = np.zeros((n, 4), np.uint8)
    cb[:, :3] = col.astype(np.uint8)
    return msgpack.packb(
        {"enc": ENCODING, "n": int(n), "lo": [float(x) for x in lo], "ext": [float(x) for x in ext],
         "pb": _meshopt(q), "nb": _meshopt(nb), "cb": _meshopt(cb),
         "crc": _crc(np.int64(n), lo, ext, q, nb, cb)},
        use_bin_type=True,
    )


def _unpack(blob: bytes, enc: str) -> dict:
    if not isinstance(blob, (bytes, bytearray, memoryview)):
        raise ProtocolError("bad_geometry", f"payload has type {type(blob).__name__}")
    try:
        payload = msgpack.unpackb(blob, raw=False, strict_map_key=True)
    except Exception as exc:  # msgpack raises several unrelated types
        raise ProtocolError("bad_geometry", f"payload is not msgpack: {exc}") from None
    if not isinstance(payload, dict):
        raise ProtocolError("bad_geometry", "payload is not a map")
    if payload.get("enc") != enc:
        raise ProtocolError("bad_geometry", f"expected encoding {enc!r}, got {payload.get('enc')!r}")
    return payload


def _count(payload: dict, name: str, top: int) -> int:
    value = payload.get(name)
    if not isinstance(value, int) or isinstance(value, bool):
        raise ProtocolError("bad_geometry", f"payload field '{name}' must be an integer")
    if not 0 < value <= top:
        raise ProtocolError("bad_geometry", f"count '{name}' = {value} outside 1..{top}")
    return value


def _buffer(payload: dict, name: str, count: int, stride: int, dtype: type) -> np.ndarray:
    value = payload.get(name)
    if not isinstance(value, bytes):
        raise ProtocolError("bad_geometry", f"payload field '{name}' must be bytes")
    try:
        raw = meshoptimizer.decode_vertex_buffer(count, stride, value)
    except Exception as exc:
        raise ProtocolError("bad_geometry", f"buffer '{name}' does not decode: {exc}") from None
    data = np.ascontiguousarray(raw).tobytes()
    if len(data) != count * stride:
        raise ProtocolError("bad_geometry", f"buffer '{name}' decodes to {len(data)} bytes, not {count * stride}")
    return np.frombuffer(data, dtype=dtype).reshape(count, -1)


def decode_points(blob: bytes) -> Points:
    """Decode and validate a point payload; any defect raises ``ProtocolError('bad_geometry', ...)``."""
    payload = _unpack(blob, ENCODING)
    n = _count(payload, "n", MAX_POINTS)
    lo, ext = _vec3(payload, "lo"), _vec3(payload, "ext")
    if (ext <= 0).any():
        raise ProtocolError("bad_geometry", "point box extent must be positive")
    q = _buffer(payload, "pb", n, 8, np.uint16)
    nb = _buffer(payload, "nb", n, 4, np.int8)
    cb = _buffer(payload, "cb", n, 4, np.uint8)
    _check(payload, _crc(np.int64(n), lo, ext, q, nb, cb))
    radius = q[:, 3].copy().view(np.float16).astype(np.float32)
    if not np.isfinite(radius).all() or (radius < 0).any():
        raise ProtocolError("bad_geometry", "point radius is negative or not finite")
    positions = dequantize(q, lo, ext)
    if not np.isfinite(positions).all():
        raise ProtocolError("bad_geometry", "point positions are not finite")
    return Points(positions=positions, normals=oct_decode(nb[:, :2]), colors=cb[:, :3].copy(), radius=radius)


def encode_instances(model_ids: np.ndarray, matrices: np.ndarray) -> bytes:
    """Encode a tree group's instances: model ids (k,) and model→world matrices (k, 4, 4)."""
    ids = np.asarray(model_ids).reshape(-1)
    m = np.asarray(matrices, np.float64)
    k = ids.shape[0]
    if not 0 < k <= MAX_INSTANCES:
        raise ValueError(f"instance count {k} outside 1..{MAX_INSTANCES}")
    if m.shape != (k, 4, 4):
        raise ValueError(f"matrices must be ({k}, 4, 4), got {m.shape}")
    if (ids < 0).any() or (ids > np.iinfo(np.uint32).max).any():
        raise ValueError("model ids must be non-negative 32-bit integers")
    rows = m[:, :3, :].astype(np.float32)
    if not np.isfinite(rows).all():
        raise ValueError("instance matrices contain NaN or infinity (or overflow float32)")
    id32, flat = ids.astype(np.uint32).reshape(-1, 1), rows.reshape(k, 12)
    return msgpack.packb(
        {"enc": INSTANCES, "k": int(k), "ib": _meshopt(id32), "mb": _meshopt(flat),
         "crc": _crc(np.int64(k), id32, flat)},
        use_bin_type=True,
    )


def decode_instances(blob: bytes, models: int | None = None) -> Instances:
    """Decode and validate an instance payload; ids must be < ``models`` when given.

    Any defect raises ``ProtocolError('bad_geometry', ...)``.
    """
    payload = _unpack(blob, INSTANCES)
    k = _count(payload, "k", MAX_INSTANCES)
    ids_raw = _buffer(payload, "ib", k, 4, np.uint32)
    flat = _buffer(payload, "mb", k, 48, np.float32)
    _check(payload, _crc(np.int64(k), ids_raw, flat))
    ids = ids_raw.reshape(-1).copy()
    rows = flat.reshape(k, 3, 4)
    if not np.isfinite(rows).all():
        raise ProtocolError("bad_geometry", "instance matrices are not finite")
    if models is not None and k and int(ids.max()) >= models:
        raise ProtocolError("bad_geometry", f"model id {int(ids.max())} out of range for {models} models")
    m = np.zeros((k, 4, 4), np.float32)
    m[:, :3, :] = rows
    m[:, 3, 3] = 1.0
    return Instances(model=ids, matrix=m)
