"""The wire contract between walkstream's server and client.

``messages`` defines every message (and the rendering algorithms, ``ALGORITHMS``),
``codec`` turns them into msgpack frames and back with size limits and
validation, ``geometry`` and ``points`` encode meshes and tree splats the same
way for the scene store and the wire, ``morph`` the morph maps and the ramp
structure of a schedule (``LevelRamps``), ``camera`` the view conventions,
``manifest`` the held-set digest, and ``errors`` holds the error codes.
"""

from .errors import ERROR_CODES, ProtocolError
from .messages import PROTOCOL_VERSION

__all__ = ["PROTOCOL_VERSION", "ProtocolError", "ERROR_CODES"]
