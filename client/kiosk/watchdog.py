"""The kiosk's word to systemd (``sd_notify``): ready once it draws, alive only while its frames advance.

A service can be "running" while its screen shows nothing: a wedged GL driver,
a frame loop stuck on a lock. So the watchdog is fed by the frame counter, not
by a timer: the runner calls ``Watchdog.frame(frames_drawn, now)`` every frame,
and ``WATCHDOG=1`` goes out at most every ``interval`` s (half of the unit's
``WatchdogSec``, as ``sd_watchdog_enabled(3)`` advises) and never when no frame
was drawn since the last one. Frames that stop advancing starve the watchdog,
and systemd kills and restarts the kiosk ``WatchdogSec`` later.

``READY=1`` goes out with the first frame drawn (the unit is ``Type=notify``).
Until then — a kiosk booting before its server is reachable — ``waiting``
keeps extending systemd's start timeout (``EXTEND_TIMEOUT_USEC``) while the
caller is demonstrably alive (it is dialling). ``STATUS=`` carries the state
and frame rate for ``systemctl status``; ``STOPPING=1`` goes out on exit.

Pure logic: the sender (``sdnotify.SystemdNotifier.notify``) and the clock are
the caller's. Outside systemd (no ``NOTIFY_SOCKET``) ``from_environ`` gives a
watchdog that sends nothing.
"""

from __future__ import annotations

import math
import os
from typing import Callable, Mapping

__all__ = ["Watchdog", "EXTEND_S"]

#: Seconds each ``waiting`` call extends systemd's start timeout by; sent again after half of it.
EXTEND_S = 30.0


class Watchdog:
    """Readiness, watchdog pings and status for systemd, driven by the frames drawn.

    notify : sends one notification (newline-separated ``KEY=value`` lines); None: send nothing
    interval : seconds between watchdog pings at most (``WatchdogSec`` / 2); None: no watchdog asked for
    extend : seconds by which ``waiting`` extends the start timeout each time
    """

    def __init__(self, notify: Callable[[str], None] | None, interval: float | None, *,
                 extend: float = EXTEND_S) -> None:
        if interval is not None and not (math.isfinite(interval) and interval > 0):
            raise ValueError(f"interval: must be a positive number of seconds, got {interval!r}")
        if not (math.isfinite(extend) and extend > 0):
            raise ValueError(f"extend: must be a positive number of seconds, got {extend!r}")
        self.notify, self.interval, self.extend = notify, interval, extend
        self.ready = False
        self.pings = 0  # WATCHDOG=1 sent
        self._frames = 0  # frames drawn at the last ping (or at READY)
        self._pinged = -math.inf  # when the last ping (or READY) went out
        self._extended = -math.inf  # when the start timeout was last extended
        self._state = ""  # the state the last STATUS= named

    @classmethod
    def from_environ(cls, environ: Mapping[str, str] | None = None, pid: int | None = None, *,
                     extend: float = EXTEND_S) -> "Watchdog":
        """The watchdog systemd asked for: ``NOTIFY_SOCKET``, ``WATCHDOG_USEC`` and ``WATCHDOG_PID`` of ``environ``.

        No ``NOTIFY_SOCKET``: a watchdog that sends nothing. ``WATCHDOG_PID``
        naming another process (the variables were inherited): no pings.
        """
        env = os.environ if environ is None else environ
        if not env.get("NOTIFY_SOCKET"):
            return cls(None, None, extend=extend)
        interval = None
        usec, owner = env.get("WATCHDOG_USEC", ""), env.get("WATCHDOG_PID", "")
        if usec.isdigit() and int(usec) > 0 and (not owner or owner == str(os.getpid() if pid is None else pid)):
            interval = int(usec) / 2e6
        import sdnotify  # here, not at the top: only a kiosk under systemd needs it

        notifier = sdnotify.SystemdNotifier()
        return cls(notifier.notify, interval, extend=extend)

    @property
    def enabled(self) -> bool:
        return self.notify is not None

    def _send(self, lines: list[str], status: str | None, state: str = "") -> str:
        if status is not None:
            lines.append(f"STATUS={status}")
            self._state = state
        message = "\n".join(lines)
        assert self.notify is not None
        self.notify(message)
        return message

    def frame(self, frames: int, now: float, state: str = "", fps: float | None = None) -> str | None:
        """Call once per frame with the frames drawn so far; returns the notification sent, if any.

        READY=1 with the first frame; then WATCHDOG=1 when ``interval`` s have
        passed since the last and ``frames`` has grown since; STATUS= alone when
        ``state`` changed in between.
        """
        if self.notify is None:
            return None
        status = state and (f"{state}, {fps:.1f} fps, {frames} frames" if fps is not None
                            else f"{state}, {frames} frames")
        if not self.ready:
            if frames <= 0:
                return None
            self.ready, self._frames, self._pinged = True, frames, now
            lines = ["READY=1"]
            if self.interval is not None:
                lines.append("WATCHDOG=1")
                self.pings += 1
            return self._send(lines, status or "drawing", state)
        if self.interval is not None and frames > self._frames and now - self._pinged >= self.interval:
            self._frames, self._pinged = frames, now
            self.pings += 1
            return self._send(["WATCHDOG=1"], status or None, state)
        if state and state != self._state:
            return self._send([], status, state)
        return None

    def waiting(self, now: float, status: str) -> str | None:
        """Before the first frame: say what the kiosk waits for and extend systemd's start timeout (rate-limited)."""
        if self.notify is None or self.ready or now - self._extended < self.extend / 2:
            return None
        self._extended = now
        return self._send([f"EXTEND_TIMEOUT_USEC={int(self.extend * 1e6)}"], status)

    def stopping(self, status: str = "stopping") -> str | None:
        """On the way out (including the nightly restart): STOPPING=1."""
        if self.notify is None:
            return None
        return self._send(["STOPPING=1"], status)
