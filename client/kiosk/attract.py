"""Attract, visitor, countdown: who drives the kiosk's camera, as a state machine over an injected clock.

::

    attract ──any input──▶ visitor ──idle_s without input──▶ countdown ──countdown_s──▶ attract
                              ▲                                  │
                              └────────────any input─────────────┘

While nobody touches the kiosk it plays its attract loop (the tour playlist). Any input — a tap, a drag, a
key — hands the camera to the visitor from where it is. After ``idle_s`` without input a countdown warns
("Touch to continue", with the seconds left; WCAG 2.2.1 asks for at least 20 s to answer such a warning),
and when it runs out the kiosk returns to the attract loop in the default language with its panels closed.
Input during the countdown cancels it.

Pure: every call takes ``now`` (seconds on any monotonic clock; the runner passes client time), and the
times are exact — the countdown starts at ``last input + idle_s`` and the attract loop at
``last input + idle_s + countdown_s``, however late ``tick`` is called. The states are the first three
of ``proto.messages.KIOSK_STATES``; "closed" and "reconnecting" are the runner's to report.
"""

from __future__ import annotations

import math

from proto.messages import KIOSK_STATES

__all__ = ["AttractMachine", "ATTRACT", "VISITOR", "COUNTDOWN", "reported_state"]

ATTRACT, VISITOR, COUNTDOWN = KIOSK_STATES[:3]


class AttractMachine:
    """The kiosk's state at the latest ``now`` it was given; ``input`` and ``tick`` return the transitions
    they made, as (state entered, time it was entered) pairs in order."""

    def __init__(self, idle_s: float, countdown_s: float, now: float = 0.0) -> None:
        if not (idle_s > 0 and countdown_s > 0):
            raise ValueError(f"idle_s and countdown_s must be positive, got {idle_s!r}, {countdown_s!r}")
        self.idle_s, self.countdown_s = float(idle_s), float(countdown_s)
        self.state = ATTRACT
        self.since = float(now)
        """When the current state was entered."""
        self.last_input: float | None = None
        """When the latest input came (None: none yet)."""
        self._now = float(now)

    def _clock(self, now: float) -> float:
        self._now = max(self._now, float(now))  # time never runs back
        return self._now

    def input(self, now: float) -> list[tuple[str, float]]:
        """A visitor touched, dragged or pressed a key: the visitor drives from here (the countdown, if any, is
        cancelled)."""
        out = self.tick(now)
        now = self._now
        self.last_input = now
        if self.state != VISITOR:
            self.state, self.since = VISITOR, now
            out.append((VISITOR, now))
        return out

    def tick(self, now: float) -> list[tuple[str, float]]:
        """Advance to ``now``: a visitor idle for ``idle_s`` gets the countdown, a countdown that ran out the
        attract loop."""
        now = self._clock(now)
        out: list[tuple[str, float]] = []
        if self.state == VISITOR and self.last_input is not None and now - self.last_input >= self.idle_s:
            self.state, self.since = COUNTDOWN, self.last_input + self.idle_s
            out.append((COUNTDOWN, self.since))
        if self.state == COUNTDOWN and now >= self.since + self.countdown_s:
            self.state, self.since = ATTRACT, self.since + self.countdown_s
            out.append((ATTRACT, self.since))
        return out

    def seconds_left(self, now: float) -> int | None:
        """Whole seconds the countdown shows at ``now`` (rounded up; None when not counting down)."""
        if self.state != COUNTDOWN:
            return None
        return max(0, math.ceil(self.since + self.countdown_s - max(now, self._now) - 1e-9))


def reported_state(state: str, *, link_up: bool, open_now: bool) -> str:
    """What the heartbeat says: "closed" outside the open hours, "reconnecting" while the server is lost
    (the kiosk still draws), else the machine's state."""
    if not open_now:
        return "closed"
    if not link_up:
        return "reconnecting"
    return state
