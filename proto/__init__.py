"""The wire contract between walkstream's server and client.

``messages`` defines every message, ``codec`` turns them into msgpack frames and
back with size limits and validation, ``geometry`` encodes meshes the same way
for the scene store and the wire, and ``errors`` holds the error codes.
"""

from .errors import ERROR_CODES, ProtocolError
from .messages import PROTOCOL_VERSION

__all__ = ["PROTOCOL_VERSION", "ProtocolError", "ERROR_CODES"]
