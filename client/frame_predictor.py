"""The frame governor's prediction of a frame's time from the units it draws (the ladder's: vertices).

A frame costs a part no ladder step changes — clearing and finishing the frame,
the draws, the pixels, the objects without steps — and a part that grows with
the geometry the steps add. In the ladder's units (vertices), t = s · (α + U):
s the machine's seconds per unit now, α the fixed part in units.

- s follows the machine at once: the last frame's t / (α + U), or the median
  of the last three's, whichever has the smaller held-out error over the
  window. Where a slow frame is followed by another more often than not (a
  machine whose slow stretches last a frame or two) the last frame predicts
  the next best; where frames scatter independently the median does, as it
  lets one slow frame pass.
- α is a property of the scene and the renderer, not of the machine's speed
  (a slower machine scales both parts): the least-squares line of t on U over
  the last ``window`` frames gives it as intercept ÷ slope, refitted only while
  the frames' units vary enough to tell the two apart — which the governor's
  own steps provide. A frame that misses its prediction by more than ``jump``
  waits for the next to say what it was: if that one misses the speed before
  it too, the machine changed speed and the line starts afresh; otherwise it
  was a stall.

Model no more than the frames justify: the simplest predictor, α = 0 (the time
per unit drawn, ``ratio``), is used unless the fitted one (``offset``) has a
mean held-out relative error below ``margin`` × the ratio's over the window.
The difference matters when the governor sheds: with a fixed part the ratio
predictor expects a step to save more than it does, and the frame reaches the
target only over several frames. Both predictors' errors are reported.

Pure numpy, no clocks.
"""

from __future__ import annotations

from collections import deque

import numpy as np

__all__ = ["FramePredictor"]

#: The median of the last three frames' rates is used instead of the last frame's only when its held-out error is
#: below this share of the last frame's.
MEDIAN_MARGIN = 0.9


class _Track:
    """One predictor t = s · (α + U) with its own held-out errors, for each of its two speeds s (the last
    frame's rate, the median of the last three's), and the one in force."""

    SPEEDS = ("last", "median")

    def __init__(self, window: int) -> None:
        self.alpha = 0.0
        self.rates: deque = deque(maxlen=3)
        self.speeds: dict[str, float] = {}
        self.errors: dict[str, deque] = {k: deque(maxlen=window) for k in self.SPEEDS}
        self.speed = "last"

    @property
    def s(self) -> float | None:
        return self.speeds.get(self.speed)

    def predict(self, units: float, speed: str | None = None) -> float | None:
        s = self.speeds.get(speed or self.speed)
        return None if s is None else s * (self.alpha + units)

    def rate(self, time: float, units: float) -> float:
        return time / max(self.alpha + units, 1e-12)

    def observe(self, time: float, units: float) -> None:
        for k in self.SPEEDS:
            guess = self.predict(units, k)
            if guess is not None and guess > 0:
                self.errors[k].append(abs(guess / time - 1.0))
        self.rates.append(self.rate(time, units))
        r = sorted(self.rates)
        self.speeds = {"last": self.rates[-1], "median": r[len(r) // 2] if len(r) != 2 else sum(r) / 2}
        # The median takes over only where it is clearly better: ties and too few frames keep the last frame's
        # rate, the simpler of the two.
        if len(self.errors["median"]) >= 8 and self.error("median") < MEDIAN_MARGIN * self.error("last"):
            self.speed = "median"
        else:
            self.speed = "last"

    def error(self, speed: str | None = None) -> float:
        e = self.errors[speed or self.speed]
        return sum(e) / len(e) if e else float("inf")


class FramePredictor:
    """Seconds of a frame that draws ``U`` units: the ratio predictor, or the one with a fixed part.

    window : frames the fixed part is fitted over and the errors are scored over
    margin : the fitted predictor is used only when its mean held-out error is below this × the ratio's
    spread : least coefficient of variation of the window's units for a refit (below it the line is noise)
    least : frames before the fixed part is fitted and before the predictors are compared
    jump : a relative miss that, two frames in a row, says the machine's speed changed
    """

    def __init__(self, window: int = 48, margin: float = 0.7, spread: float = 0.03, least: int = 16,
                 jump: float = 0.3) -> None:
        if not (window >= 8 and 0 < margin <= 1 and spread > 0 and 1 <= least <= window and jump > 0):
            raise ValueError(f"bad predictor settings window={window} margin={margin} spread={spread} least={least} "
                             f"jump={jump}")
        self.margin, self.spread, self.least, self.jump = float(margin), float(spread), int(least), float(jump)
        self.ratio = _Track(window)
        self.offset = _Track(window)
        self.times: deque = deque(maxlen=window)
        self.units: deque = deque(maxlen=window)
        self.chosen = "ratio"  # the predictor in force (``_choose``, after each frame)
        self.missed = False  # the last frame missed its prediction by more than ``jump`` ...
        self.before: float | None = None  # ... and the speed in force before the first of such frames in a row

    def _choose(self) -> str:
        """"offset" where it has earned it (enough frames, clearly smaller held-out error), else "ratio"."""
        if len(self.offset.errors["last"]) >= self.least and len(self.ratio.errors["last"]) >= self.least \
                and self.offset.error() < self.margin * self.ratio.error():
            return "offset"
        return "ratio"

    def _track(self) -> _Track:
        return self.offset if self.chosen == "offset" else self.ratio

    @property
    def rate(self) -> float | None:
        """Seconds per unit now (the chosen predictor's s), None before a frame was measured."""
        return self._track().s

    @property
    def alpha(self) -> float:
        """The chosen predictor's fixed part, in units."""
        return self._track().alpha

    def predict(self, units: float) -> float | None:
        """Seconds of a frame of ``units``, None before a frame was measured."""
        return self._track().predict(units)

    def units_for(self, seconds: float) -> float | None:
        """The units a frame of ``seconds`` may draw (possibly ≤ 0: not even the fixed part fits)."""
        track = self._track()
        s = track.s
        return None if s is None or s <= 0 else seconds / s - track.alpha

    def observe(self, time: float, units: float) -> None:
        """A frame of ``units`` took ``time`` s: score both predictors on it, then learn from it."""
        if not (time > 0 and units > 0 and np.isfinite(time) and np.isfinite(units)):
            return
        guess = self.predict(units)
        if self.missed and self.before is not None and self.times:
            old = self.before * (self.alpha + units)
            if abs(old / time - 1.0) > self.jump:
                # This frame misses the speed before the last frame too: the machine changed speed, and the frames
                # before would bend the line. The fixed part in units does not change with the speed, so it is
                # kept; the line starts afresh from the last frame.
                keep = (self.times[-1], self.units[-1])
                self.times.clear()
                self.units.clear()
                self.times.append(keep[0])
                self.units.append(keep[1])
        miss = guess is not None and abs(guess / time - 1.0) > self.jump
        if miss and not self.missed:
            self.before = self.rate
        self.missed = miss
        self.ratio.observe(time, units)
        self.offset.observe(time, units)
        self.times.append(float(time))
        self.units.append(float(units))
        if len(self.units) >= self.least and not miss:  # (a frame that missed waits for the next to say what it was)
            self._refit()
        self.chosen = self._choose()

    def _refit(self) -> None:
        u = np.fromiter(self.units, float)
        t = np.fromiter(self.times, float)
        if u.std() < self.spread * u.mean():
            return
        slope, intercept = np.polyfit(u, t, 1)
        if slope > 0:
            # The fixed part is no more than the lightest frame's time holds.
            self.offset.alpha = float(np.clip(intercept / slope, 0.0, t.min() / slope))

    def report(self) -> dict:
        """Both predictors' mean held-out relative errors, the fixed part fitted, and which is in force."""
        return {"chosen": self.chosen, "ratio_error": _finite(self.ratio.error()),
                "offset_error": _finite(self.offset.error()), "offset_alpha": self.offset.alpha,
                "speed": self._track().speed, "last_error": _finite(self._track().error("last")),
                "median_error": _finite(self._track().error("median")), "frames": len(self.ratio.errors["last"])}


def _finite(x: float) -> float | None:
    return round(x, 4) if np.isfinite(x) else None
