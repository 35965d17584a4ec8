"""Sessions polled together: the selections that fall due in one tick, as one batch.

A server holds many sessions of few scenes. What their selections share — the
scene — is worth doing once per tick rather than once per session; what they do
not share (each client's cameras, cost model, cache and history) stays each
session's own. ``poll_many(sessions, now)`` is ``[s.poll(now) for s in sessions]``
in its result, to the bit: batching changes what a tick costs, never what a
session is sent (``tests/server/session/test_batch.py`` runs one scripted session
alone and among fifty others and compares every frame).
"""

from __future__ import annotations

from typing import Sequence

from pydantic import BaseModel

from .core import Session

__all__ = ["poll_many"]


def poll_many(sessions: Sequence[Session], now: float) -> list[list[BaseModel]]:
    """Poll every session at ``now``; each one's messages to send, in the order given."""
    return [s.poll(now) for s in sessions]
