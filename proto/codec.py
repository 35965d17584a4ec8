"""msgpack codec with size limits: bytes in, validated messages out (and back).

The decoder is the only door into a session, so it refuses before it allocates:
the frame size is checked before unpacking, msgpack's own container limits
are set from it, and validation errors are turned into one readable sentence
naming the message type and the field.
"""

from __future__ import annotations

import threading
from typing import Callable, Mapping

import msgpack
import zstandard
from pydantic import BaseModel, ValidationError

from .errors import ProtocolError
from .messages import CLIENT_TYPES, SERVER_TYPES, ClientMessage, Error, ServerMessage

__all__ = [
    "MAX_CLIENT_FRAME",
    "MAX_SERVER_FRAME",
    "encode",
    "decode",
    "decode_client",
    "decode_server",
    "error_frame",
    "ZSTD_MAGIC",
    "COMPRESS_ABOVE",
]

#: Client frames are poses and reports: a few hundred bytes. 64 KiB is generous.
MAX_CLIENT_FRAME = 64 * 1024
#: Server frames carry geometry.
MAX_SERVER_FRAME = 256 * 1024 * 1024


#: A server frame larger than this goes out as one zstd frame when that saves a tenth: many small meshes in a
#: delta share headers and structure their own codecs cannot see. A msgpack message is a map, whose first
#: byte is never zstd's magic's, so the client tells the two apart by the first four bytes.
COMPRESS_ABOVE = 4096
ZSTD_MAGIC = b"\x28\xb5\x2f\xfd"
_local = threading.local()  # zstd contexts are not thread-safe; selections encode in worker threads


def _zstd() -> tuple[zstandard.ZstdCompressor, zstandard.ZstdDecompressor]:
    pair = getattr(_local, "zstd", None)
    if pair is None:
        pair = _local.zstd = (zstandard.ZstdCompressor(level=3, write_content_size=True), zstandard.ZstdDecompressor())
    return pair


#: Fields whose items may come packed already (``encode``'s ``packed``): a delta's adds and tree models.
_SHARED_ITEMS = ("add", "models")


def encode(message: BaseModel, compress: bool = True,
           packed: Callable[[BaseModel], bytes | None] | None = None) -> bytes:
    """A message as one msgpack map (binary websocket frame); a large server message zstd-compressed.

    Client messages are never compressed: the server accepts only plain msgpack, so its
    decoder has no decompression to bound.

    ``packed(item)``: the msgpack bytes of an item of a list field (a delta's adds and tree models), when
    the caller has them already — many sessions are sent the same geometry, which is then packed once.
    msgpack is context-free, so the frame is byte for byte the one packed from scratch.
    """
    if packed is None or not any(getattr(message, f, None) for f in _SHARED_ITEMS):
        frame = msgpack.packb(message.model_dump(mode="python"), use_bin_type=True)
    else:
        frame = _splice(message, packed)
    if compress and len(frame) > COMPRESS_ABOVE and message.type in SERVER_TYPES:
        packed = _zstd()[0].compress(frame)
        if len(packed) < 0.9 * len(frame):
            return packed
    return frame


def _splice(message: BaseModel, packed: Callable[[BaseModel], bytes | None]) -> bytes:
    """``packb(message.model_dump())`` with the items of ``_SHARED_ITEMS`` taken from ``packed`` where it has them."""
    pack = msgpack.Packer(use_bin_type=True).pack
    fields = type(message).model_fields
    shared = [f for f in _SHARED_ITEMS if f in fields]
    rest = message.model_dump(mode="python", exclude=set(shared))
    parts = [_map_header(len(fields))]
    for name in fields:
        parts.append(pack(name))
        if name in shared:
            items = getattr(message, name)
            parts.append(_array_header(len(items)))
            for item in items:
                wire = packed(item)
                parts.append(wire if wire is not None else pack(item.model_dump(mode="python")))
        else:
            parts.append(pack(rest[name]))
    return b"".join(parts)


def _map_header(n: int) -> bytes:
    return bytes([0x80 | n]) if n < 16 else (b"\xde" + n.to_bytes(2, "big") if n < 1 << 16 else b"\xdf" + n.to_bytes(4, "big"))


def _array_header(n: int) -> bytes:
    return bytes([0x90 | n]) if n < 16 else (b"\xdc" + n.to_bytes(2, "big") if n < 1 << 16 else b"\xdd" + n.to_bytes(4, "big"))


#: Longest field name an error sentence repeats: a peer's unknown key may be 64 KiB long.
_MAX_LOC = 64


def _describe(kind: str, exc: ValidationError) -> str:
    """At most three errors, each field name clipped, so the sentence always fits an ``Error`` frame."""
    parts = []
    for err in exc.errors(include_url=False, include_input=False)[:3]:
        where = ".".join(_clip(str(p)) for p in err["loc"]) or kind
        parts.append(f"{kind}.{where}: {err['msg'][:256]}" if err["loc"] else f"{kind}: {err['msg'][:256]}")
    more = exc.error_count() - len(parts)
    return "; ".join(parts) + (f" (and {more} more)" if more > 0 else "")


def _clip(name: str) -> str:
    return name if len(name) <= _MAX_LOC else name[:_MAX_LOC] + "…"


def _undecodable(data, exc: Exception, from_client: bool) -> str:
    """Why a frame is not msgpack, in words a peer's developer can act on (msgpack's own are often empty)."""
    name = type(exc).__name__
    if from_client and bytes(data[:4]) == ZSTD_MAGIC:
        return "compressed frames are not accepted: send plain msgpack (only the server compresses)"
    if name == "StackError":
        return "frame does not decode: it nests maps or arrays too deeply"
    if name == "ExtraData":
        return "frame does not decode: bytes follow the first msgpack object (one message per frame)"
    if not data:
        return "frame does not decode: it is empty"
    detail = str(exc).strip()
    if name == "FormatError" or not detail:
        return f"frame does not decode: it is not msgpack (starts with bytes {bytes(data[:8]).hex(' ')})"
    return f"frame does not decode: {name}: {detail}"


def decode(data: bytes, types: Mapping[str, type[BaseModel]], max_size: int) -> BaseModel:
    """Decode one frame into a message of one of ``types``; refuse with ``ProtocolError``."""
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise ProtocolError("not_binary", "expected a binary frame")
    if len(data) > max_size:
        raise ProtocolError("too_large", f"frame of {len(data)} bytes exceeds the limit of {max_size}")
    try:
        obj = msgpack.unpackb(
            data,
            raw=False,
            strict_map_key=True,
            max_str_len=max_size,
            max_bin_len=max_size,
            max_array_len=max_size,
            max_map_len=max_size,
            max_ext_len=0,
        )
    except Exception as exc:  # ExtraData, FormatError, StackError, ValueError, UnicodeDecodeError ...
        raise ProtocolError("bad_msgpack", _undecodable(data, exc, types is CLIENT_TYPES)[:300]) from None
    if not isinstance(obj, dict):
        raise ProtocolError("invalid", f"a message is a map with a 'type' field, got {type(obj).__name__}")
    kind = obj.get("type")
    if not isinstance(kind, str):
        raise ProtocolError("invalid", "message lacks a string 'type' field")
    cls = types.get(kind)
    if cls is None:
        known = ", ".join(sorted(types))
        raise ProtocolError("unknown_type", f"unknown message type {kind[:64]!r}; expected one of {known}")
    try:
        return cls.model_validate(obj)
    except ValidationError as exc:
        raise ProtocolError("invalid", _describe(kind, exc)) from None


def decode_client(data: bytes) -> ClientMessage:
    """What the server calls on every incoming frame."""
    return decode(data, CLIENT_TYPES, MAX_CLIENT_FRAME)  # type: ignore[return-value]


def decode_server(data: bytes) -> ServerMessage:
    """What the client calls on every incoming frame (plain msgpack, or zstd of it)."""
    if isinstance(data, (bytes, bytearray, memoryview)) and bytes(data[:4]) == ZSTD_MAGIC:
        try:
            size = zstandard.frame_content_size(data)
        except zstandard.ZstdError as exc:
            raise ProtocolError("bad_msgpack", f"compressed frame has no valid header: {exc}"[:300]) from None
        if size < 0 or size > MAX_SERVER_FRAME:
            raise ProtocolError("too_large", f"compressed frame declares {size} bytes; the limit is {MAX_SERVER_FRAME}")
        try:
            data = _zstd()[1].decompress(data, max_output_size=size)
        except zstandard.ZstdError as exc:
            raise ProtocolError("bad_msgpack", f"compressed frame does not inflate: {exc}"[:300]) from None
    return decode(data, SERVER_TYPES, MAX_SERVER_FRAME)  # type: ignore[return-value]


def error_frame(exc: ProtocolError) -> Error:
    return Error(code=exc.code, message=exc.message)
