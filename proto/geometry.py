"""Geometry payloads: the one encoding used both in the scene store and on the wire.

A representation is stored exactly as it is sent, so the server streams blobs
without re-encoding them. Positions are quantized to 16 bits inside the
object's box (the same box for every level of an object, so that levels line up
for geomorphing) and the buffers go through meshoptimizer's codecs, which
exploit the vertex-cache order that ``encode_geometry`` establishes first
(``order_for_gpu``; callers with per-vertex data apply it themselves and pass
``reorder=False``).

Colours travel with the geometry: an optional per-vertex RGB8 buffer (``cb``),
the appearance the source gave (``server.scene.palette``, ``server.scene.colours``).
A mesh whose faces differ in colour has its vertices split where colours meet, so a
per-vertex colour is a per-face colour too. Payloads without ``cb`` (colourless
objects, stores built before colours) decode with ``Geometry.colours`` None.

A textured representation also carries texture coordinates (``tb``, per vertex,
quantized to 16 bits in their own box, since they may repeat past [0, 1]) and its
own base-colour texture (``tx``, a PNG: ``proto.texture``), so a coarser level
carries a smaller texture and every byte count sees it. UVs follow OpenGL's
convention (v = 0 at the image's bottom row); the texture's rows are top-down,
as the image stores them. The two come together or not at all; payloads without
them decode with ``Geometry.uv`` and ``Geometry.texture`` None.

Payload (a msgpack map)::

    enc  "mq16"                      encoding tag
    nv   int                         vertex count
    nf   int                         triangle count
    lo   [x, y, z] float             box minimum (object space = world space here)
    ext  [x, y, z] float             box extent (> 0 on every axis)
    vb   bytes                       meshopt vertex buffer, nv × 4 uint16 (x, y, z, 0)
    ib   bytes                       meshopt index buffer, 3·nf uint32
    cb   bytes, optional             meshopt vertex buffer, nv × 4 uint8 (r, g, b, 255)
    tb   bytes, optional             meshopt vertex buffer, nv × 2 uint16 (u, v) quantized in the UV box
    tlo  [u, v] float, with tb       UV box minimum
    text [u, v] float, with tb       UV box extent (> 0)
    tx   bytes, with tb              the base-colour texture, PNG (RGB)
    tw   int, with tx                its width in pixels (1..4096)
    th   int, with tx                its height in pixels (1..4096)
"""

from __future__ import annotations

from dataclasses import dataclass

import meshoptimizer
import msgpack
import numpy as np

from .errors import ProtocolError
from .texture import MAX_TEXTURE_SIDE, decode_texture, encode_texture

__all__ = ["ENCODING", "MAX_VERTICES", "MAX_FACES", "Geometry", "order_for_gpu", "encode_geometry", "decode_geometry"]

ENCODING = "mq16"
MAX_VERTICES = 1 << 22
MAX_FACES = 1 << 23
_QMAX = 65535.0


@dataclass(frozen=True)
class Geometry:
    """Decoded triangle geometry.

    positions : (nv, 3) float32, world space
    indices   : (nf, 3) uint32, every entry < nv
    colours   : (nv, 3) uint8 RGB per vertex, or None (the object has no colour of its own)
    uv        : (nv, 2) float32 texture coordinates (v up), or None (no texture)
    texture   : (h, w, 3) uint8 RGB base-colour texture, rows top-down, or None
    """

    positions: np.ndarray
    indices: np.ndarray
    colours: np.ndarray | None = None
    uv: np.ndarray | None = None
    texture: np.ndarray | None = None

    @property
    def vertices(self) -> int:
        return int(self.positions.shape[0])

    @property
    def faces(self) -> int:
        return int(self.indices.shape[0])


def quantize(positions: np.ndarray, lo: np.ndarray, ext: np.ndarray) -> np.ndarray:
    """(n, 3) float → (n, 4) uint16, the fourth lane zero (meshopt wants 4-byte multiples)."""
    q = np.zeros((positions.shape[0], 4), dtype=np.uint16)
    scaled = (np.asarray(positions, np.float64) - lo) / ext * _QMAX
    q[:, :3] = np.clip(np.rint(scaled), 0, _QMAX).astype(np.uint16)
    return q


def dequantize(q: np.ndarray, lo: np.ndarray, ext: np.ndarray) -> np.ndarray:
    """(n, 4) uint16 → (n, 3) float32."""
    return (lo + q[:, :3].astype(np.float64) * (ext / _QMAX)).astype(np.float32)


def safe_box(lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Box minimum and a strictly positive extent (flat objects get a tiny one)."""
    lo = np.asarray(lo, np.float64)
    ext = np.asarray(hi, np.float64) - lo
    ext = np.where(ext > 1e-9, ext, 1e-6)
    return lo, ext


def order_for_gpu(positions: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The reordering ``encode_geometry`` applies by default, done ahead of time.

    Faces are reordered for the post-transform vertex cache (meshoptimizer's
    ``optimize_vertex_cache``), then vertices are renumbered in first-use order
    (``optimize_vertex_fetch``); vertices no face uses are dropped. Both make
    the meshopt codecs (and the GPU) work well. A mesh in this order encodes
    with ``encode_geometry(..., reorder=False)`` exactly as ``encode_geometry``
    would encode the original, and its vertex ids are the ones stored — which
    is what per-vertex data such as morph maps (``proto.morph``) must refer to.

    positions : (n, 3) float
    faces     : (m, 3) int, every entry < n, m > 0
    Returns (positions (n', 3) float64, faces (m, 3) int64, new_of_old (n,) int64),
    where ``new_of_old[v]`` is vertex v's new id, or −1 if v is unused.
    """
    positions = np.asarray(positions, dtype=np.float64)
    faces = np.asarray(faces)
    nv = positions.shape[0]
    if positions.ndim != 2 or positions.shape[1] != 3 or nv == 0:
        raise ValueError(f"positions must be (n, 3) with n > 0, got {positions.shape}")
    if faces.ndim != 2 or faces.shape[1] != 3 or faces.shape[0] == 0:
        raise ValueError(f"faces must be (m, 3) with m > 0, got {faces.shape}")
    if int(faces.min()) < 0 or int(faces.max()) >= nv:
        raise ValueError(f"face indices must lie in 0..{nv - 1}")
    flat = np.ascontiguousarray(faces, dtype=np.uint32).reshape(-1)
    cached = np.zeros_like(flat)
    meshoptimizer.optimize_vertex_cache(cached, flat, flat.size, nv)
    remap = np.zeros(nv, dtype=np.uint32)
    used = int(meshoptimizer.optimize_vertex_fetch_remap(remap, cached, cached.size, nv))
    new_of_old = remap.astype(np.int64)
    new_of_old[remap == np.iinfo(np.uint32).max] = -1
    old_of_new = np.empty(used, dtype=np.int64)
    kept = new_of_old >= 0
    old_of_new[new_of_old[kept]] = np.flatnonzero(kept)
    return positions[old_of_new], new_of_old[cached].reshape(-1, 3), new_of_old


def encode_geometry(
    positions: np.ndarray,
    faces: np.ndarray,
    box_lo: np.ndarray | None = None,
    box_hi: np.ndarray | None = None,
    *,
    reorder: bool = True,
    colours: np.ndarray | None = None,
    uv: np.ndarray | None = None,
    texture: np.ndarray | bytes | None = None,
) -> bytes:
    """Encode a triangle mesh into a payload.

    positions : (nv, 3) float
    faces     : (nf, 3) int, every entry < nv
    box_lo, box_hi : (3,) float — the quantization box; defaults to the mesh's own
        bounds. Pass the object's box so that all levels of one object share it.
    reorder   : put faces and vertices in GPU order first (``order_for_gpu``; unused
        vertices are dropped). With ``reorder=False`` the payload holds the vertices
        and faces exactly in the given order (unused vertices included), so stored
        vertex ids are the caller's — pass a mesh already in GPU order.
    colours   : (nv, 3) uint8 RGB per vertex, or None for a colourless payload
    uv        : (nv, 2) float texture coordinates, with ``texture``; or None
    texture   : (h, w, 3) uint8 RGB rows top-down, or its PNG bytes (``proto.texture``); with ``uv``
    """
    positions = np.asarray(positions, dtype=np.float64)
    faces = np.asarray(faces)
    nv, nf = positions.shape[0], faces.shape[0]
    if positions.ndim != 2 or positions.shape[1] != 3 or nv == 0:
        raise ValueError(f"positions must be (n, 3) with n > 0, got {positions.shape}")
    if faces.ndim != 2 or faces.shape[1] != 3 or nf == 0:
        raise ValueError(f"faces must be (m, 3) with m > 0, got {faces.shape}")
    if not np.isfinite(positions).all():
        raise ValueError("positions contain NaN or infinity")
    if int(faces.min()) < 0:
        raise ValueError(f"face index {int(faces.min())} is negative")
    if int(faces.max()) >= nv:
        raise ValueError(f"face index {int(faces.max())} out of range for {nv} vertices")
    if colours is not None:
        colours = np.asarray(colours)
        if colours.shape != (nv, 3) or colours.dtype != np.uint8:
            raise ValueError(f"colours must be ({nv}, 3) uint8, got {colours.dtype} {colours.shape}")
    if (uv is None) != (texture is None):
        raise ValueError("uv and texture come together: a payload has both or neither")
    if uv is not None:
        uv = np.asarray(uv, np.float64)
        if uv.shape != (nv, 2) or not np.isfinite(uv).all():
            raise ValueError(f"uv must be ({nv}, 2) finite, got {uv.shape}")
    if box_lo is None or box_hi is None:
        box_lo, box_hi = positions.min(axis=0), positions.max(axis=0)
    lo, ext = safe_box(box_lo, box_hi)
    if reorder:
        positions, faces, new_of_old = order_for_gpu(positions, faces)
        kept = new_of_old >= 0
        if colours is not None:
            reordered = np.empty((positions.shape[0], 3), np.uint8)
            reordered[new_of_old[kept]] = colours[kept]
            colours = reordered
        if uv is not None:
            moved = np.empty((positions.shape[0], 2), np.float64)
            moved[new_of_old[kept]] = uv[kept]
            uv = moved
    flat = np.ascontiguousarray(faces, dtype=np.uint32).reshape(-1)
    q = quantize(positions, lo, ext)
    nv = q.shape[0]
    payload = {
        "enc": ENCODING,
        "nv": int(nv),
        "nf": int(nf),
        "lo": [float(x) for x in lo],
        "ext": [float(x) for x in ext],
        "vb": meshoptimizer.encode_vertex_buffer(q, nv, q.itemsize * 4),
        "ib": meshoptimizer.encode_index_buffer(flat, flat.size, nv),
    }
    if colours is not None:
        rgba = np.full((nv, 4), 255, np.uint8)
        rgba[:, :3] = colours
        payload["cb"] = meshoptimizer.encode_vertex_buffer(rgba, nv, 4)
    if uv is not None:
        payload.update(_encode_uv(uv, texture))
    return msgpack.packb(payload, use_bin_type=True)


def _encode_uv(uv: np.ndarray, texture: np.ndarray | bytes) -> dict:
    """The payload's texture fields for uv (nv, 2) float and an RGB texture (or its PNG)."""
    if isinstance(texture, (bytes, bytearray)):
        png = bytes(texture)
        height, width = decode_texture(png, *_png_size(png)).shape[:2]  # a bad PNG fails here, not at the client
    else:
        png = encode_texture(texture)
        height, width = np.asarray(texture).shape[:2]
    if max(width, height) > MAX_TEXTURE_SIDE:
        raise ValueError(f"texture {width}×{height} has a side over {MAX_TEXTURE_SIDE} px")
    ulo, uext = safe_box(uv.min(axis=0), uv.max(axis=0))
    q = np.clip(np.rint((uv - ulo) / uext * _QMAX), 0, _QMAX).astype(np.uint16)
    q = np.ascontiguousarray(q)
    return {"tb": meshoptimizer.encode_vertex_buffer(q, q.shape[0], 4),
            "tlo": [float(x) for x in ulo], "text": [float(x) for x in uext],
            "tx": png, "tw": int(width), "th": int(height)}


def _png_size(png: bytes) -> tuple[int, int]:
    """(width, height) from a PNG's header; ValueError if it has none."""
    import io

    from PIL import Image

    try:
        with Image.open(io.BytesIO(png), formats=["PNG"]) as image:
            return image.size
    except Exception as exc:
        raise ValueError(f"texture bytes are not a PNG: {exc}") from None


def _field(payload: dict, name: str, kind: type | tuple[type, ...]) -> object:
    if name not in payload:
        raise ProtocolError("bad_geometry", f"geometry payload lacks '{name}'")
    value = payload[name]
    if not isinstance(value, kind) or isinstance(value, bool):
        raise ProtocolError("bad_geometry", f"geometry field '{name}' has type {type(value).__name__}")
    return value


def _vec3(payload: dict, name: str, n: int = 3) -> np.ndarray:
    value = _field(payload, name, list)
    if len(value) != n or not all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in value):
        raise ProtocolError("bad_geometry", f"geometry field '{name}' must be {('two', 'three')[n - 2]} numbers")
    arr = np.asarray(value, np.float64)
    if not np.isfinite(arr).all():
        raise ProtocolError("bad_geometry", f"geometry field '{name}' is not finite")
    return arr


def decode_geometry(blob: bytes) -> Geometry:
    """Decode and validate a payload; any defect raises ``ProtocolError('bad_geometry', ...)``."""
    try:
        payload = msgpack.unpackb(blob, raw=False, strict_map_key=True)
    except Exception as exc:  # msgpack raises several unrelated types
        raise ProtocolError("bad_geometry", f"geometry payload is not msgpack: {exc}") from None
    if not isinstance(payload, dict):
        raise ProtocolError("bad_geometry", "geometry payload is not a map")
    if payload.get("enc") != ENCODING:
        raise ProtocolError("bad_geometry", f"unknown geometry encoding {payload.get('enc')!r}")
    nv = _field(payload, "nv", int)
    nf = _field(payload, "nf", int)
    if not 0 < nv <= MAX_VERTICES:
        raise ProtocolError("bad_geometry", f"vertex count {nv} outside 1..{MAX_VERTICES}")
    if not 0 < nf <= MAX_FACES:
        raise ProtocolError("bad_geometry", f"face count {nf} outside 1..{MAX_FACES}")
    lo, ext = _vec3(payload, "lo"), _vec3(payload, "ext")
    if (ext <= 0).any():
        raise ProtocolError("bad_geometry", "geometry box extent must be positive")
    vb = _field(payload, "vb", bytes)
    ib = _field(payload, "ib", bytes)
    try:
        q = meshoptimizer.decode_vertex_buffer(nv, 8, vb)
        idx = meshoptimizer.decode_index_buffer(3 * nf, 4, ib)
    except Exception as exc:
        raise ProtocolError("bad_geometry", f"geometry buffers do not decode: {exc}") from None
    q = np.frombuffer(np.ascontiguousarray(q).tobytes(), dtype=np.uint16).reshape(nv, 4)
    idx = np.frombuffer(np.ascontiguousarray(idx).tobytes(), dtype=np.uint32).reshape(nf, 3)
    if int(idx.max()) >= nv:
        raise ProtocolError("bad_geometry", f"index {int(idx.max())} out of range for {nv} vertices")
    uv, texture = _texture(payload, nv)
    return Geometry(positions=dequantize(q, lo, ext), indices=idx, colours=_colours(payload, nv), uv=uv,
                    texture=texture)


def _colours(payload: dict, nv: int) -> np.ndarray | None:
    """The optional per-vertex colours: (nv, 3) uint8, or None when the payload has none."""
    if "cb" not in payload:
        return None
    raw = _four_bytes_a_vertex(payload, "cb", nv, "colour")
    return np.frombuffer(raw, np.uint8).reshape(nv, 4)[:, :3].copy()


def _four_bytes_a_vertex(payload: dict, key: str, nv: int, what: str) -> bytes:
    """The meshopt vertex buffer ``payload[key]`` of nv × 4 bytes, decoded; ProtocolError naming ``what``."""
    buffer = _field(payload, key, bytes)
    try:
        decoded = meshoptimizer.decode_vertex_buffer(nv, 4, buffer)
    except Exception as exc:
        raise ProtocolError("bad_geometry", f"geometry {what} buffer does not decode: {exc}") from None
    raw = np.ascontiguousarray(decoded).tobytes()
    if len(raw) != 4 * nv:
        raise ProtocolError("bad_geometry", f"geometry {what} buffer holds {len(raw)} bytes, expected {4 * nv}")
    return raw


def _texture(payload: dict, nv: int) -> tuple[np.ndarray | None, np.ndarray | None]:
    """The optional UVs (nv, 2) float32 and texture (h, w, 3) uint8, or (None, None) when the payload has none."""
    present = [k for k in ("tb", "tx") if k in payload]
    if not present:
        return None, None
    if len(present) == 1:
        raise ProtocolError("bad_geometry", f"geometry payload has '{present[0]}' without "
                                            f"'{({'tb', 'tx'} - set(present)).pop()}'")
    ulo, uext = _vec3(payload, "tlo", 2), _vec3(payload, "text", 2)
    if (uext <= 0).any():
        raise ProtocolError("bad_geometry", "geometry UV box extent must be positive")
    raw = _four_bytes_a_vertex(payload, "tb", nv, "UV")
    uv = (ulo + np.frombuffer(raw, np.uint16).reshape(nv, 2).astype(np.float64) * (uext / _QMAX)).astype(np.float32)
    texture = decode_texture(_field(payload, "tx", bytes), _field(payload, "tw", int), _field(payload, "th", int))
    return uv, texture
