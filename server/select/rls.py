"""Robust recursive least squares: the estimator behind every rung of the online cost model.

Least squares of relative error (a budget is a relative matter: fast and slow
frames count alike), updated one frame at a time with forgetting so it follows
a machine that drifts; Huber weights against a running robust scale so one
spike barely moves it; Page's CUSUM so a machine that really changed is followed
at once; coefficients kept in a box (θ ≥ 0) and a covariance kept bounded in
directions no frame excites.

Nothing here reads a clock or does I/O.
"""

from __future__ import annotations

import math
import statistics
from collections import deque

import numpy as np

from .snapshot import dump_fields, load_fields

__all__ = ["RobustRLS", "RESCALE_SHARE", "BOX_TIE"]

#: How far (in scaled units, where the coefficients are about 1) a coordinate may lie past its bound and still count
#: as on it in ``RobustRLS._project``: a term never excited sits at its bound give or take rounding, and taking that
#: for out of the box pins it in the same solve as a coordinate truly out, so the answer turned on rounding's sign.
BOX_TIE = 1e-12

#: A detected change rescales the coefficients that explain — or at their prior's magnitude would explain — at
#: least this share of the surprising frame.
RESCALE_SHARE = 0.05


class RobustRLS:
    """Huber-weighted recursive least squares of relative error, with forgetting, θ ≥ 0 and bounded covariance.

    Model y ≈ x·θ. Each row is divided by y, so the residual e = 1 − x·θ / y is the relative error:
    fast and slow frames count alike (a budget is a relative matter), and a slow spike's residual
    is below 1 however slow it is.

    mean, scale : (k,) prior coefficients and their prior standard deviation (> 0). Internally
        φ = θ / scale, so rows are O(1) whatever the units (1e-7 s per vertex, 1e-3 s per frame).
    forgetting : λ in (0, 1]; a frame weighs λ^age — memory ≈ 1 / (1 − λ) frames — for the terms that explain
        all of it: each term forgets at 1 − (1 − λ)·share, its share of the frame (vector forgetting), so a
        term the frames do not exercise keeps what it knew.
    noise : the relative residual the prior is weighed against: P = Cov / noise² starts at
        I / noise² (the prior's own uncertainty) and no coordinate's variance may exceed it, so a
        direction no frame excites (an algorithm never drawn) stays at its prior instead of growing
        as λ^−n; the cap scales rows and columns (D P D), which keeps P positive semi-definite.
    huber : Huber's c in robust standard deviations (1.345: 95 % efficient on Gaussian noise).
    window, floor : the robust scale σ is 1.4826 · median |e| of the last ``window`` residuals, ≥ floor.
    slack, threshold, clip : change detection, Page's two-sided CUSUM of e / σ clipped to ±clip. A
        spike adds at most clip − slack (2), so ``threshold`` 8 needs five in a row; a machine that
        got 2× slower trips it in five frames, a ramp once its bias has grown. Then θ is rescaled by the
        measured/predicted ratio the last ``keep`` surprising frames all agree on (the one nearest 1),
        the frame gets full weight and P is re-opened by ``reopen`` of the prior's, so the change is
        followed at once instead of at the pace of forgetting and down-weighted residuals.
    """

    def __init__(self, mean, scale, forgetting: float = 0.97, noise: float = 0.05, huber: float = 1.345,
                 window: int = 15, floor: float = 0.005, slack: float = 0.5, threshold: float = 8.0,
                 clip: float = 2.5, keep: int = 4, reopen: float = 0.05) -> None:
        scale = np.array(scale, np.float64).reshape(-1)
        mean = np.array(mean, np.float64).reshape(-1)
        if not (0 < forgetting <= 1) or not (noise > 0):
            raise ValueError(f"forgetting must be in (0, 1] and noise > 0, got {forgetting}, {noise}")
        if mean.shape != scale.shape or not (np.isfinite(mean).all() and np.isfinite(scale).all()
                                             and (scale > 0).all()):
            raise ValueError("mean and scale must be finite, of one length, scale > 0")
        self.k = mean.size
        self.forgetting, self.huber, self.floor, self.reopen = forgetting, huber, floor, reopen
        self.slack, self.threshold, self.clip = slack, threshold, clip
        self.cap = 1.0 / noise**2
        self.scale = scale
        self.phi = np.maximum(mean, 0.0) / scale
        #: (k,) bounds on θ (0 and inf: none), a box the projection keeps θ in.
        self.lower, self.upper = np.zeros(self.k), np.full(self.k, np.inf)
        self.P = np.eye(self.k) * self.cap
        self.residuals: deque[float] = deque(maxlen=window)
        self.updates = 0
        self.changes = 0
        self._hi = self._lo = 0.0
        self._up: deque[float] = deque(maxlen=keep)  # measured/predicted over the current excursions
        self._down: deque[float] = deque(maxlen=keep)

    @property
    def theta(self) -> np.ndarray:
        """(k,) current coefficients, all ≥ 0."""
        return self.phi * self.scale

    def predict(self, x: np.ndarray) -> float:
        return float(np.dot(np.asarray(x, np.float64), self.theta))

    def robust_scale(self) -> float:
        """Robust standard deviation of the recent relative residuals (inf until there are five)."""
        if len(self.residuals) < 5:
            return math.inf
        return max(self.floor, 1.4826 * statistics.median(abs(e) for e in self.residuals))

    def reset(self, index, mean, scale) -> None:
        """Start coordinates afresh at ``mean`` ± ``scale``, decoupled from the rest (used when a
        regressor is first excited, so its prior is on the scale of the frame that excites it)."""
        index = np.atleast_1d(np.asarray(index, np.int64))
        self.scale[index] = np.maximum(np.broadcast_to(np.asarray(scale, np.float64), index.shape), 1e-300)
        mean = np.broadcast_to(np.asarray(mean, np.float64), index.shape)
        self.phi[index] = np.maximum(mean, 0.0) / self.scale[index]
        self.P[index, :] = 0.0
        self.P[:, index] = 0.0
        self.P[index, index] = self.cap

    def update(self, x: np.ndarray, y: float, rescale: np.ndarray | None = None) -> float:
        """Fold in one row (x, y > 0); returns its relative residual before the update. O(k²).

        ``rescale``: (k,) bool, the coordinates a detected change rescales (default: those explaining at least
        ``RESCALE_SHARE`` of the frame) — a caller that masks terms out of the row (one side of a max) names
        the masked ones that still share in the frame's cost.
        A row that would make the state non-finite (absurd magnitudes) is dropped: returns nan."""
        with np.errstate(over="ignore", invalid="ignore"):
            b = np.asarray(x, np.float64) * self.scale / y
            e0 = e = 1.0 - float(b @ self.phi)
        if not (math.isfinite(e) and np.isfinite(b).all()):
            return math.nan
        saved = self.phi.copy(), self.P.copy(), self._hi, self._lo
        sigma = self.robust_scale()
        c = self.huber * sigma
        w = min(1.0, c / abs(e)) if e else 1.0
        # Page's CUSUM on the clipped standardised residual: a spike adds at most clip − slack, so only a
        # run of them (or a step, or a ramp's growing bias) reaches the threshold.
        u = float(np.clip(e / sigma, -self.clip, self.clip)) if math.isfinite(sigma) else 0.0
        self._hi, self._lo = max(0.0, self._hi + u - self.slack), max(0.0, self._lo - u - self.slack)
        ratio = 1.0 / max(1.0 - e, 1e-3)  # measured / predicted
        for total, ratios, side in ((self._hi, self._up, e > c), (self._lo, self._down, e < -c)):
            if total <= 0:
                ratios.clear()
            elif side:  # only the surprising frames of the excursion say by how much the machine changed
                ratios.append(ratio)
        change = max(self._hi, self._lo) > self.threshold
        # Each term's share of this frame: b_j · φ_j is the part of the frame its coefficient explains (at the
        # prior's magnitude at least, so a coefficient projected to 0 can still be re-learnt).
        share = np.minimum(np.abs(b) * np.maximum(self.phi, 1.0), 1.0)
        if change:
            # A machine that got slower (or faster) is so at everything these frames do: rescale the
            # coefficients by the measured/predicted ratio the last frames of the excursion all agree on
            # (the one nearest 1, so a spike among them does not set it) — those that explain at least
            # ``RESCALE_SHARE`` of the frame, as near-empty frames say nothing of the cost per vertex — and
            # let the data refine them. Both sides of a max-of-stages model move (the caller's ``rescale``),
            # not only the one that happens to be the larger.
            ratios = np.array(self._up if self._hi > self._lo else self._down)
            if ratios.size:
                ratio = float(np.clip(ratios[np.argmin(np.abs(np.log(ratios)))], 0.1, 10.0))
                if rescale is None:
                    # At the prior's magnitude at least: a term priced near 0 (splats before any were seen)
                    # is the likeliest culprit of a frame it has a large part in, not one to spare.
                    rescale = b * np.maximum(self.phi, 1.0) >= RESCALE_SHARE * max(float(b @ self.phi), 1e-300)
                self.phi[rescale] *= ratio
            self._hi = self._lo = 0.0
            self._up.clear()
            self._down.clear()
            e, w = 1.0 - float(b @ self.phi), 1.0
            self.changes += 1
        # Forgetting per coordinate, at the rate the frame informs it (vector forgetting): a term the frames
        # do not exercise keeps what it knew. With one λ for all, a long stretch of near-empty frames lets
        # the per-vertex cost random-walk on their noise, and the first heavy frames after overrun the
        # prediction.
        inflate = 1.0 / np.sqrt(1.0 - (1.0 - self.forgetting) * share)
        self.P *= np.outer(inflate, inflate)
        pb = self.P @ b
        g = w * pb / (1.0 + w * float(b @ pb))
        self.phi += g * e
        self.P -= np.outer(g, pb)
        self.P = (self.P + self.P.T) * 0.5  # kept exactly symmetric
        if change:
            self.P[np.diag_indices(self.k)] += self.reopen * self.cap
        d = np.diag(self.P)
        if (d > self.cap).any():
            f = np.sqrt(self.cap / np.maximum(d, self.cap))
            self.P *= np.outer(f, f)
        theta = self.theta
        if (theta < self.lower).any() or (theta > self.upper).any():
            self._project()
        if not (np.isfinite(self.phi).all() and np.isfinite(self.P).all()):
            self.phi, self.P, self._hi, self._lo = saved
            return math.nan
        self.residuals.append(e0)
        self.updates += 1
        return e0

    def _project(self) -> None:
        """lower ≤ θ ≤ upper (lower ≥ 0): a coordinate out of the box goes to its bound and the others move by
        their conditional mean given that (projection in the P⁻¹ metric), so a correlated term takes up what
        the clamped one explained instead of the fit losing it (a plain clamp was much slower to converge on
        the stages model)."""
        lo, hi = np.maximum(self.lower, 0.0) / self.scale, self.upper / self.scale
        active = np.zeros(self.k, bool)
        bound = np.zeros(self.k)
        for _ in range(self.k):
            low, high = self.phi < lo - BOX_TIE, self.phi > hi + BOX_TIE
            if not (low.any() or high.any()):
                break
            bound[low], bound[high] = lo[low], hi[high]
            active |= low | high
            a = np.flatnonzero(active)
            shift = np.linalg.lstsq(self.P[np.ix_(a, a)], self.phi[a] - bound[a], rcond=None)[0]
            self.phi -= self.P[:, a] @ shift
            self.phi[a] = bound[a]
        np.clip(self.phi, lo, np.maximum(hi, lo), out=self.phi)

    # ------------------------------------------------------------------ snapshot

    #: The fields a snapshot holds.
    STATE = ("k", "forgetting", "huber", "floor", "reopen", "slack", "threshold", "clip", "cap", "scale", "phi", "P",
             "residuals", "updates", "changes", "_hi", "_lo", "_up", "_down")

    def to_state(self) -> dict:
        return dump_fields(self, self.STATE)

    def from_state(self, state, what: str = "rls") -> None:
        """Take in ``to_state``'s data, checked against this estimator's shapes; ValueError (unchanged) if not."""
        load_fields(self, state, self.STATE, what)
