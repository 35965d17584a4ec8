"""msgpack codec with size limits: bytes in, validated messages out (and back).

The decoder is the only door into a session, so it refuses before it allocates:
the frame size is checked before unpacking, msgpack's own container limits
are set from it, and validation errors are turned into one readable sentence
naming the message type and the field.
"""

from __future__ import annotations

from typing import Mapping

import msgpack
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
]

#: Client frames are poses and reports: a few hundred bytes. 64 KiB is generous.
MAX_CLIENT_FRAME = 64 * 1024
#: Server frames carry geometry.
MAX_SERVER_FRAME = 256 * 1024 * 1024


def encode(message: BaseModel) -> bytes:
    """A message as one msgpack map (binary websocket frame)."""
    return msgpack.packb(message.model_dump(mode="python"), use_bin_type=True)


def _describe(kind: str, exc: ValidationError) -> str:
    parts = []
    for err in exc.errors()[:3]:
        where = ".".join(str(p) for p in err["loc"]) or kind
        parts.append(f"{kind}.{where}: {err['msg']}" if err["loc"] else f"{kind}: {err['msg']}")
    more = exc.error_count() - len(parts)
    return "; ".join(parts) + (f" (and {more} more)" if more > 0 else "")


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
        raise ProtocolError("bad_msgpack", f"frame does not decode: {type(exc).__name__}: {exc}"[:300]) from None
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
    """What the client calls on every incoming frame."""
    return decode(data, SERVER_TYPES, MAX_SERVER_FRAME)  # type: ignore[return-value]


def error_frame(exc: ProtocolError) -> Error:
    return Error(code=exc.code, message=exc.message)
