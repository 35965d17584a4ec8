"""Opening hours of a kiosk: when it is open, what its screen does when closed, when it restarts itself.

Pure: the caller passes the local wall-clock time (a ``datetime``; naive or
aware, its wall time is what counts). Times of day are "HH:MM"; a close
earlier than the open runs past midnight (open 18:00, close 02:00), and
open == close means always open.

Every time of day is reduced to seconds since midnight, and the state follows
from which boundary came last: the kiosk is open when the last open time lies
nearer in the past than the last close time. That one rule covers closing past
midnight without a special case, and says how long ago the state changed,
which the fade between the open and the closed screen needs.

Closed, the screen either dims (``closed="dim"``: the attract loop goes on,
slower and darkened, so the kiosk still looks alive and the watchdog still sees
frames) or goes black (``closed="black"``: frames are still drawn, all black).
The change fades over ``FADE_S`` rather than snapping.

``restart_at`` names a time of day at which a long-running kiosk exits with
``RESTART_STATUS`` (the systemd unit's ``RestartForceExitStatus``) to start
afresh: a nightly restart clears whatever a day of running has accumulated.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from datetime import datetime, timedelta

__all__ = ["Hours", "Screen", "CLOSED_LOOKS", "DIM", "DIM_RATE", "FADE_S", "RESTART_STATUS", "parse_time_of_day"]

DAY = 86_400
#: Brightness of the dimmed screen outside opening hours (a factor on the drawn colour).
DIM = 0.25
#: Speed of the attract loop on the dimmed screen, as a factor on its playing time.
DIM_RATE = 0.25
#: Seconds over which the screen fades between its open and closed looks.
FADE_S = 60.0
#: The exit status that asks systemd for a restart (``RestartForceExitStatus=75`` in the unit; EX_TEMPFAIL).
RESTART_STATUS = 75
#: What the screen does outside opening hours: its brightness and the attract loop's rate.
CLOSED_LOOKS = {"dim": (DIM, DIM_RATE), "black": (0.0, 0.0)}

_HHMM = re.compile(r"(\d{2}):(\d{2})")


def parse_time_of_day(value: str, name: str) -> int:
    """Seconds since midnight of ``value`` ("HH:MM", 00:00 to 23:59); ``ValueError`` naming ``name`` otherwise."""
    m = _HHMM.fullmatch(value) if isinstance(value, str) else None
    if m is None or int(m[1]) > 23 or int(m[2]) > 59:
        raise ValueError(f"{name}: must be a time of day HH:MM (00:00 to 23:59), got {value!r}")
    return int(m[1]) * 3600 + int(m[2]) * 60


def _second_of_day(now: datetime) -> float:
    return now.hour * 3600 + now.minute * 60 + now.second + now.microsecond / 1e6


@dataclass(frozen=True)
class Screen:
    """What the runner applies to a frame: whether the kiosk is open, the brightness and the attract loop's rate.

    brightness : factor on the drawn colour in [0, 1] (0: black)
    rate : factor on the attract loop's playing time (1: normal speed; 0: stands still)
    """

    open: bool
    brightness: float
    rate: float


@dataclass(frozen=True)
class Hours:
    """A kiosk's schedule (the config's ``[schedule]``); see the module's docstring."""

    open: str = "00:00"
    close: str = "00:00"
    closed: str = "dim"
    restart_at: str = ""
    fade_s: float = FADE_S
    _open_s: int = field(init=False, repr=False, compare=False)
    _close_s: int = field(init=False, repr=False, compare=False)
    _restart_s: int | None = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "_open_s", parse_time_of_day(self.open, "open"))
        object.__setattr__(self, "_close_s", parse_time_of_day(self.close, "close"))
        if self.closed not in CLOSED_LOOKS:
            raise ValueError(f"closed: must be one of {', '.join(CLOSED_LOOKS)}, got {self.closed!r}")
        restart = parse_time_of_day(self.restart_at, "restart_at") if self.restart_at != "" else None
        object.__setattr__(self, "_restart_s", restart)
        if not (isinstance(self.fade_s, (int, float)) and 0 <= self.fade_s <= 3600):
            raise ValueError(f"fade_s: must lie in [0, 3600] seconds, got {self.fade_s!r}")

    @property
    def always_open(self) -> bool:
        return self._open_s == self._close_s

    def _since(self, now: datetime) -> tuple[bool, float]:
        """(open now, seconds since the last open or close boundary)."""
        t = _second_of_day(now)
        since_open = (t - self._open_s) % DAY
        since_close = (t - self._close_s) % DAY
        if self.always_open:
            return True, float("inf")
        return (since_open < since_close), min(since_open, since_close)

    def is_open(self, now: datetime) -> bool:
        """Whether the kiosk is open at local time ``now``: open ≤ now < close, across midnight if need be."""
        return self._since(now)[0]

    def screen(self, now: datetime) -> Screen:
        """The screen at ``now``: full brightness and speed when open, the closed look when closed, faded between."""
        is_open, since = self._since(now)
        closed = CLOSED_LOOKS[self.closed]
        look = (1.0, 1.0) if is_open else closed
        before = closed if is_open else (1.0, 1.0)
        w = 1.0 if self.fade_s == 0 or since >= self.fade_s else since / self.fade_s
        return Screen(is_open, before[0] + w * (look[0] - before[0]), before[1] + w * (look[1] - before[1]))

    def brightness(self, now: datetime) -> float:
        """The screen's brightness factor at ``now`` (``screen(now).brightness``)."""
        return self.screen(now).brightness

    def next_restart(self, started: datetime) -> datetime | None:
        """The first ``restart_at`` strictly after ``started`` (same tzinfo), or None when no restart is set."""
        if self._restart_s is None:
            return None
        h, rem = divmod(self._restart_s, 3600)
        at = started.replace(hour=h, minute=rem // 60, second=0, microsecond=0)
        return at if at > started else at + timedelta(days=1)

    def restart_due(self, started: datetime, now: datetime) -> bool:
        """True once ``restart_at`` has come round since ``started``: the kiosk then exits with ``RESTART_STATUS``."""
        at = self.next_restart(started)
        return at is not None and now >= at
