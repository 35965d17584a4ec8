"""A client's session: a sans-I/O state machine (``core``) over parts that own their state.

``core.Session`` handles the messages; ``timing`` decides when to select and
for which cameras; ``pipeline`` turns one selection into a delta; ``gate`` fits
it to the bytes the link carries in time; ``mirror`` follows what the client's
cache holds; ``table`` holds the arrays every session of a scene shares.
"""

from .config import TAIL_MIN_SHARE, SceneSource, SessionConfig, SessionState
from .core import Session

__all__ = ["Session", "SessionConfig", "SessionState", "SceneSource", "TAIL_MIN_SHARE"]
