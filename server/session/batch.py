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

from ..select.selection import cull_many
from .core import Session

__all__ = ["poll_many", "cull_due"]


def cull_due(sessions: Sequence[Session], now: float) -> list:
    """The selections due at ``now``, framed (each session's cameras for its interval), culled and projected
    together — one compiled pass over every camera of every session of a scene view; per session what to
    hand its ``poll`` (None: nothing due, or it culls alone)."""
    return cull_many([s.selection_request(now) for s in sessions])


def poll_many(sessions: Sequence[Session], now: float) -> list[list[BaseModel]]:
    """Poll every session at ``now``; each one's messages to send, in the order given. The shared pass first
    (``cull_due``), then each session prices its visible options, solves and builds its delta as alone."""
    return [s.poll(now, c) for s, c in zip(sessions, cull_due(sessions, now))]
