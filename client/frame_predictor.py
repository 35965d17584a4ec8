"""The frame governor's prediction of a frame's time from the units it draws (the ladder's: vertices).

A frame costs a part no ladder step changes — clearing and finishing the frame,
the draws, the pixels, the objects without steps — and a part that grows with
the geometry the steps add. In the ladder's units (vertices), t = s · (α + U):
s the machine's seconds per unit now, α the fixed part in units.

- s follows the machine at once: the median of the last three frames'
  t / (α + U), so one slow frame alone does not move it and two in a row do.
- α is a property of the scene and the renderer, not of the machine's speed
  (a slower machine scales both parts): the least-squares line of t on U over
  the last ``window`` frames gives it as intercept ÷ slope, refitted only while
  the frames' units vary enough to tell the two apart — which the governor's
  own steps provide.

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


class _Track:
    """One predictor t = s · (α + U) with its own running s and held-out errors."""

    def __init__(self, window: int) -> None:
        self.alpha = 0.0
        self.rates: deque = deque(maxlen=3)
        self.errors: deque = deque(maxlen=window)
        self.s: float | None = None

    def predict(self, units: float) -> float | None:
        return None if self.s is None else self.s * (self.alpha + units)

    def observe(self, time: float, units: float) -> None:
        guess = self.predict(units)
        if guess is not None and guess > 0:
            self.errors.append(abs(guess / time - 1.0))
        self.rates.append(time / max(self.alpha + units, 1e-12))
        self.s = sorted(self.rates)[len(self.rates) // 2] if len(self.rates) != 2 else sum(self.rates) / 2

    def error(self) -> float:
        return sum(self.errors) / len(self.errors) if self.errors else float("inf")


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
        self.misses = 0  # frames in a row the prediction missed by more than ``jump``

    def _choose(self) -> str:
        """"offset" where it has earned it (enough frames, clearly smaller held-out error), else "ratio"."""
        if len(self.offset.errors) >= self.least and len(self.ratio.errors) >= self.least \
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
        self.misses = self.misses + 1 if guess is not None and abs(guess / time - 1.0) > self.jump else 0
        if self.misses >= 2:
            # The machine changed speed: its frames before and after would bend the line. The fixed part in
            # units does not change with the speed, so it is kept; the line is fitted afresh from here.
            self.times.clear()
            self.units.clear()
        self.ratio.observe(time, units)
        self.offset.observe(time, units)
        self.times.append(float(time))
        self.units.append(float(units))
        if len(self.units) >= self.least:
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
                "frames": len(self.ratio.errors)}


def _finite(x: float) -> float | None:
    return round(x, 4) if np.isfinite(x) else None
