"""The peer's fault versus ours (the h11 split).

``ProtocolError`` is a *remote* error: the other side sent something we refuse.
It carries a stable machine-readable ``code`` and a human sentence, and becomes
an ``error`` frame; the session goes on. Anything else raised while handling a
message is a local bug and is logged loudly.
"""

from __future__ import annotations

__all__ = ["ProtocolError", "ERROR_CODES"]

#: Every code a peer can receive in an ``error`` frame.
ERROR_CODES = {
    "bad_msgpack": "the frame is not valid msgpack",
    "too_large": "the frame exceeds the size limit",
    "not_binary": "text frames are not accepted; send msgpack in binary frames",
    "unknown_type": "the message type is not part of the protocol",
    "invalid": "a field is missing, of the wrong type, out of range or not finite",
    "version": "the protocol version is not supported",
    "unknown_scene": "no scene of that name is served here",
    "unknown_solver": "no solver of that name exists",
    "unknown_tour": "the scene has no tour of that name",
    "bad_state": "the message is not allowed in the session's current state",
    "bad_geometry": "a geometry payload does not decode",
    "bad_walkable": "a walkable grid does not decode",
    "bad_held": "the hello's held manifest does not decode or names representations the scene lacks",
    "rate_limited": "the session sent more messages per second than allowed; the message was dropped",
    "busy": "this replica serves as many sessions as it may; try another or later",
    "no_hello": "the connection did not say a valid hello in time; it is closed",
    "bad_frames": "the connection sent too many frames that were refused; it is closed",
    "solver_refused": "that solver is for measurement only and this replica does not offer it to clients",
    "idle": "nothing was heard from the client for too long; the session is closed",
    "closed": "an administrator closed the session",
    "internal": "the server failed; the session may go on",
}


class ProtocolError(Exception):
    """A message from the peer was refused."""

    def __init__(self, code: str, message: str) -> None:
        if code not in ERROR_CODES:
            raise ValueError(f"unknown error code {code!r}")
        super().__init__(f"{code}: {message}")
        self.code = code
        self.message = message
