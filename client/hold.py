"""The line a session asks the frame governor to hold, and the ledger of frames that says how to hold it.

A line is a share of all frames within a bound × target. Steering every frame
to bound ÷ (that share's quantile of measured ÷ predicted) holds it frame by
frame, but a frame the budget does not bind — everything the ladder offers
fits below the aim — is almost never over the bound, and spends none of the
line's allowance. Over a run with such frames the allowance they leave is
spent on the frames the budget binds: those may be steered by a lower quantile
(``Ledger.quantile``), which spends more of the time asked for where the
picture needs it, and the run as a whole still holds its line.

Pure numpy, no clocks.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["Hold", "Ledger", "STRICT", "SKELETON"]


@dataclass(frozen=True)
class Hold:
    """The line a session asks the governor to hold: at least ``share`` of frames within ``bound`` × target.

    On a machine whose frames scatter, holding a tail costs mean frame time: the governor steers the predicted
    frame to ``bound`` ÷ (the ``share`` quantile of measured ÷ predicted), so a stricter line leaves more of
    the time asked for unspent. The line is the user's choice; the default is the promise's.
    """

    share: float
    bound: float

    def __post_init__(self) -> None:
        if not (0.5 <= self.share < 1 and 1.0 <= self.bound <= 1.5):
            raise ValueError(f"a hold line needs a share in [0.5, 1) and a bound in [1, 1.5]: "
                             f"got {self.share:g} of frames within {self.bound:g} × target")

    @classmethod
    def parse(cls, text: str) -> "Hold":
        """``"p99:1.1"``: 99 % of frames within 1.1 × target. ValueError naming what is wrong."""
        head, sep, tail = str(text).strip().partition(":")
        try:
            if not (sep and head[:1] in "pP" and head[1:]):
                raise ValueError
            share, bound = float(head[1:]) / 100.0, float(tail)
        except ValueError:
            raise ValueError(f"a hold line is pNN:BOUND, e.g. p99:1.1 (99 % of frames within 1.1 × target); "
                             f"got {text!r}") from None
        return cls(share, bound)

    def __str__(self) -> str:
        return f"p{self.share * 100:g}:{self.bound:g}"


#: The promise: at most 1 % of frames over 1.1 × target (the evaluation's ``governor_over`` line).
STRICT = Hold(0.99, 1.1)
#: The walking skeleton's line, which ``walkstream demo`` reports against: 95 % within 1.3 × target.
SKELETON = Hold(0.95, 1.3)


class Ledger:
    """The last ``size`` measured frames under a line: which the budget bound, and which went over its bound.

    margin : the share of the line's allowance the bound frames are steered to use (the rest is the ledger's
    own error: a quantile taken over a few hundred ratios, and a future that may bind more than the past)
    least : frames before the ledger says anything (until then every frame counts as bound)
    """

    def __init__(self, line: Hold, size: int = 4096, margin: float = 0.8, least: int = 256) -> None:
        if not (size >= 8 and 0 < margin <= 1 and 1 <= least <= size):
            raise ValueError(f"bad ledger settings size={size} margin={margin} least={least}")
        self.line, self.margin, self.least = line, float(margin), int(least)
        self.bound = np.zeros(int(size), bool)
        self.over = np.zeros(int(size), bool)
        self.frames = 0
        self._bound = self._over = self._free_over = 0  # running counts over the ring

    def record(self, bound: bool, over: bool) -> None:
        """One measured frame: whether the budget bound it, and whether it went over the line's bound."""
        i = self.frames % self.bound.size
        if self.frames >= self.bound.size:
            self._bound -= int(self.bound[i])
            self._over -= int(self.over[i])
            self._free_over -= int(self.over[i] and not self.bound[i])
        self.bound[i], self.over[i] = bool(bound), bool(over)
        self._bound += int(bound)
        self._over += int(over)
        self._free_over += int(over and not bound)
        self.frames += 1

    @property
    def counted(self) -> int:
        return min(self.frames, self.bound.size)

    def bound_share(self) -> float:
        """The share of the counted frames the budget bound (1 until ``least`` frames are counted)."""
        return self._bound / self.counted if self.counted >= self.least else 1.0

    def over_share(self) -> float:
        """The share of the counted frames over the line's bound."""
        return self._over / self.counted if self.counted else 0.0

    def quantile(self) -> float:
        """The quantile of measured ÷ predicted that a bound frame is steered by: the line's own share while
        every frame binds, lower as fewer do, never below a tenth of the way from the line's share to none;
        and the line's own share again while the frames counted are over the line already.

        The bound frames get the allowance (× ``margin``) less what the free frames used: a frame taken for
        free is over when the view turned onto more than the prediction knew, and that is spent whatever the
        bound frames do."""
        allowance = 1.0 - self.line.share
        if self.counted < self.least or self.over_share() > allowance:
            return self.line.share
        left = self.margin * allowance - self._free_over / self.counted
        q = 1.0 - max(left, 0.0) / max(self.bound_share(), 1e-9)
        return float(np.clip(q, max(0.5, 1.0 - 10.0 * allowance), self.line.share))

    def report(self) -> dict:
        """The ledger's figures: the share of frames bound and over, and the quantile in force."""
        return {"line": str(self.line), "frames": self.counted, "bound_share": round(self.bound_share(), 4),
                "over_share": round(self.over_share(), 4), "quantile": round(self.quantile(), 4)}
