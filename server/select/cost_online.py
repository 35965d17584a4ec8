"""The cost model fitted online from measured frames: robust recursive least squares and a ladder of models.

``CostModel`` (cost.py) either follows one number (Zach's c_vertex) or is fitted
offline (F&S). Here F&S's coefficients are fitted on the server from every frame
report as it arrives, and only as much model is used as the machine needs:

* ``RobustRLS`` (rls.py) — recursive least squares on relative error with exponential
  forgetting (follows drift), Huber weights against a running robust scale
  (single-frame spikes barely move it), a persistent-change detector (a machine
  that really got slower is followed within a few frames), non-negative
  coefficients, and a covariance bounded in directions the frames never excite
  (algorithms never drawn do not wind up).
* ``OnlineCostModel`` — three models fitted in parallel on every frame,
  "vertex" (c_v·ΣV) ⊂ "draw" (c0 + Σ C2_r·V_r + C0·D + c_splat·S) ⊂ "stages"
  (c0 + max(Σ C1_r·F_r + C2_r·V_r, Σ C3_r·P_r) + C0·D + c_splat·S). Each predicts
  each frame before it learns from it (prequential, so the error is truly held
  out); the simplest model whose recent held-out error is within ``within`` of
  the best one's is used.

Nothing here reads a clock or does I/O: the session passes the reported numbers in.
"""

from __future__ import annotations

import copy
import math
from collections import deque
from itertools import islice

import numpy as np

from . import kernels
from .cost import ALGORITHM_SCALE
from .cost_fold import fold_frames, queue_of
from .rls import RESCALE_SHARE, RobustRLS
from .snapshot import dump_fields, load_fields

__all__ = ["OnlineCostModel", "MODELS"]

#: The ladder, simplest first.
MODELS = ("vertex", "draw", "stages")
#: Prior spread of the secondary terms (c0, C1, C0, c_splat) as a share of the frame they alone could explain.
SECONDARY = 0.25
#: A regime change: the chosen model off by more than REGIME_ERROR (relative) on each of the last REGIME_FRAMES
#: frames, and by more than REGIME_RATIO × another model's error on each, switches to the best at once.
REGIME_FRAMES, REGIME_ERROR, REGIME_RATIO = 2, 0.3, 3.0
#: Frames a batch model keeps unfolded at most (a session that stops selecting still folds its reports).
BATCH_MAX = 64
#: Frames a side of the stages model is "young": over-predicting the whole frame, it is scaled down to it.
YOUNG = 10
#: Relative margin by which the fill side must exceed the geometry side to take a frame: a side's first frame
#: makes both explain it exactly, and rounding (the compiled fold sums in another order) must not decide a tie.
TIE = 1e-9
#: No frame costs less than the fixed overhead c0, so c0 is bounded by the lightest frame measured — with a
#: slack of LEAST_SLACK, as the overhead itself is noisy (the mean overhead of a stretch of empty frames is up
#: to twice its lightest) — a bound that rises by LEAST_RISE a frame (doubling in about 700 frames), as
#: old evidence of a faster machine fades.
LEAST_SLACK, LEAST_RISE = 2.0, 1e-3


def _alg_scale(r: int) -> np.ndarray:
    return np.array([ALGORITHM_SCALE[min(j, len(ALGORITHM_SCALE) - 1)] for j in range(r)])


class _Rung:
    """One model of the ladder: its RLS, how a frame becomes its row, and its coefficients in the full layout.

    Frames and coefficients share the layout z = [1, F (R), V (R), P (R), D, S] (F&S's terms per
    algorithm, draws, splats), so one formula (``_frame``) predicts for every model.
    """

    def __init__(self, name: str, r: int, c_vertex: float, forgetting: float, window: int) -> None:
        self.name, self.r = name, r
        c2 = c_vertex * _alg_scale(r)
        n = 3 * r + 3
        if name == "vertex":  # θ = [c_v]; a splat is one point vertex
            self.cols, mean = None, np.array([c_vertex])
            self.main, self.blocks = [np.array([0])], []
        elif name == "draw":  # θ = [c0, C2 (R), C0, c_splat]
            self.cols = np.concatenate([[0], 1 + r + np.arange(r), [n - 2, n - 1]])
            mean = np.concatenate([[0.0], c2, [0.0, 0.0]])
            self.main = self.blocks = [1 + np.arange(r)]
        else:  # θ = z layout: [c0, C1 (R), C2 (R), C3 (R), C0, c_splat]
            self.cols = np.arange(n)
            mean = np.concatenate([[0.0], np.zeros(r), c2, np.zeros(r), [0.0, 0.0]])
            self.blocks = [1 + np.arange(r), 1 + r + np.arange(r), 1 + 2 * r + np.arange(r)]
            self.main = self.blocks[1:]
        self.alg = _alg_scale(r)
        self.rls = RobustRLS(mean, np.maximum(mean, c_vertex), forgetting=forgetting)
        self.seen = np.zeros(mean.size, bool)
        self.errors: deque[float] = deque(maxlen=window)
        self.fill: deque[bool] = deque(maxlen=window)
        self.sides = [0, 0]  # frames given to the geometry side, to the fill side
        self._num = self._den = 0.0
        self._lam = forgetting
        self._full: np.ndarray | None = None  # ``full()`` until the coefficients move

    #: The fields a snapshot holds (its RLS's come with it).
    STATE = ("seen", "errors", "fill", "sides", "_num", "_den", "_lam")

    def to_state(self) -> dict:
        return {**dump_fields(self, self.STATE), "rls": self.rls.to_state()}

    def from_state(self, state, what: str = "rung") -> None:
        """Take in ``to_state``'s data; ValueError (rung unchanged) if it does not fit this rung."""
        trial = copy.deepcopy(self)
        load_fields(trial, state, self.STATE, what)
        trial.rls.from_state(state.get("rls"), f"{what}.rls")
        trial._full = None
        self.__dict__.update(trial.__dict__)

    def theta(self) -> np.ndarray:
        """Coefficients in force: an algorithm never drawn follows those drawn (scaled by ALGORITHM_SCALE),
        so it is neither priced out of the selection by a stale prior nor free."""
        th = self.rls.theta
        for blk in self.blocks:
            seen = self.seen[blk]
            if seen.any() and not seen.all():
                th[blk[~seen]] = np.mean(th[blk[seen]] / self.alg[seen]) * self.alg[~seen]
        return th

    def full(self) -> np.ndarray:
        if self._full is None:
            th, r = self.theta(), self.r
            c = np.zeros(3 * r + 3)
            if self.cols is None:
                c[1 + r : 1 + 2 * r] = c[-1] = th[0]
            else:
                c[self.cols] = th
            self._full = c
        return self._full

    def row(self, z: np.ndarray) -> np.ndarray:
        r = self.r
        return np.array([z[1 + r : 1 + 2 * r].sum() + z[-1]]) if self.cols is None else z[self.cols]

    def observe(self, t: float, z: np.ndarray, least: float = math.inf, light: bool = False) -> None:
        """Fold in one frame; ``least`` bounds c0 (no frame costs less than the overhead). On a ``light`` frame
        (measured and predicted far under the budget) only c0 learns: the per-unit prices are held."""
        rls = self.rls
        if self.cols is not None:
            rls.upper[0] = least
        if light:
            hold = np.arange(1 if self.cols is not None else 0, rls.k)
            rls.lower[hold] = rls.upper[hold] = rls.theta[hold]
        try:
            self._observe(t, z)
        finally:
            if light:
                rls.lower[hold], rls.upper[hold] = 0.0, np.inf

    def _observe(self, t: float, z: np.ndarray) -> None:
        x = self.row(z)
        fresh = (x > 0) & ~self.seen
        if fresh.any():
            self._first(t, x, fresh)
            self._full = None
        fill = False
        if self.name == "stages":
            # F&S's max, fitted piecewise (EM-style, as ``CostModel.fit``): the frame goes to the side
            # predicted larger, the other side's terms are masked out of its row; c0, C0 and c_splat are
            # shared by both sides, so one estimator over the joint vector fits both with them.
            r = self.r
            geo, fil = slice(1, 1 + 2 * r), slice(1 + 2 * r, 1 + 3 * r)
            c = self.full()
            g, f = float(c[geo] @ z[geo]), float(c[fil] @ z[fil])
            fill = f > g * (1.0 + TIE)
            self.sides[fill] += 1
            if self.sides[fill] <= YOUNG and max(g, f) > t:
                # Both sides start above the truth (each alone explaining the first frame) and the
                # larger is the one corrected, so each comes down onto the frames it bounds — the fill
                # side gets data when frames are fill-bound. While young, a side predicting more than the
                # whole frame is scaled down to it: a linear step that large would overshoot below 0 and
                # the non-negative projection would hand the frame to c0.
                self.rls.phi[fil if fill else geo] *= t / max(g, f)
                self._full = None
            # A change rescales both sides (a machine slower at geometry is slower at fill too): every term
            # with a share of the whole, unmasked frame.
            whole = x * c[self.cols]
            rescale = x * np.maximum(c[self.cols], self.rls.scale) >= RESCALE_SHARE * max(
                float(whole[[0, *range(1, 1 + 2 * r), -2, -1]].sum()), 1e-300)
            x = x.copy()
            x[geo if fill else fil] = 0.0
        else:
            rescale = None
        self.fill.append(fill)
        self.rls.update(x, t, rescale)
        self._full = None
        c = self.full()
        self._num = self._lam * self._num + _frame(c, z, self.r) - c[0]
        self._den = self._lam * self._den + z[1 + self.r : 1 + 2 * self.r].sum() + z[-1]

    def _first(self, t: float, x: np.ndarray, fresh: np.ndarray) -> None:
        """Put newly excited coordinates on the scale of the frame: t / x_j is the coefficient that alone
        would explain it. A main term (per vertex, per pixel) starts there — as a block, t / Σx — or, if its
        block has data already, where the block puts it; its spread is that much. A secondary term (c0,
        per face, per draw, per splat) stays at its prior ± a quarter of it, so the first, nearly collinear
        frames shape the main terms instead of loading everything onto c0."""
        th = self.theta()
        mean = th.copy()
        spread = np.full(th.size, SECONDARY)
        for blk in self.main:
            spread[blk] = 1.0
            if fresh[blk].any() and not self.seen[blk].any():
                mean[blk] = t / x[blk].sum()
        idx = np.flatnonzero(fresh)
        self.rls.reset(idx, mean[idx], spread[idx] * t / x[idx])
        self.seen |= fresh

    def c_vertex(self) -> float:
        if self.cols is None or self._den <= 0:
            return float(self.full()[1 + self.r])
        return self._num / self._den


def _frame(c: np.ndarray, z: np.ndarray, r: int) -> float:
    """Frame seconds for one z-layout frame: c0 + max(C1·F + C2·V, C3·P) + C0·D + c_splat·S."""
    geometry = c[1 : 1 + 2 * r] @ z[1 : 1 + 2 * r]
    fill = c[1 + 2 * r : 1 + 3 * r] @ z[1 + 2 * r : 1 + 3 * r]
    return float(c[0] + max(geometry, fill) + c[-2] * z[-2] + c[-1] * z[-1])


class OnlineCostModel:
    """F&S's cost model fitted online from frame reports, no more complex than the machine needs.

    algorithms : R, rendering algorithms (0 flat, 1 lit, 2 textured)
    c_vertex : first guess, seconds per vertex (what is predicted before any frame)
    forgetting : λ of every estimator; 0.97 remembers ~33 frames (0.5–1.6 s at 20–60 fps)
    within : a simpler model is used while its held-out error is within this share of the best one's (0.30: see
             below why not less)
    window : frames of held-out error each model keeps for ``report`` (60: 1–3 s)
    min_frames : frames before anything but "vertex" may be chosen

    Selection rule. Every model predicts every frame before it learns from it; its score is the MEAN
    relative error |pred − t| / t of those predictions over the last window / 3 frames (20: the models
    forget with a memory of ~33 frames, so older errors describe older fits, and a model that has
    converged is chosen within ~1 s). The mean, because it counts every frame — a model wrong only on
    the 20 % of frames that are fill-bound pays for them, which a median hides, and those are the frames
    that break the budget — and it is steadier than a p95, which over 20–60 frames is decided by one to
    three frames, often spikes no model predicts. The chosen model is the simplest one whose score is
    ≤ (1 + within) · the best score. Hysteresis, so it does not flap: going down to a simpler model also
    needs that over the whole window (a second of geometry-bound frames between fill-bound ones does
    not make "draw" enough); going up needs the chosen model's recent errors to be above the
    candidate's beyond the noise (paired over the same frames, t > 1.5: a model stuck below the machine's
    needs costs budget overruns, one above it only redundant terms); and a switch needs the same
    answer window / 12 (5) frames in a row — except on a regime change (``_regime_change``: the chosen
    model off by over 30 % on two frames running, each time 3× another's), which takes the best of those
    frames at once. Before ``min_frames`` frames: "vertex".

    Why ``within`` is 0.30. A richer model is not harmless when its extra terms are not identified: the
    frames of a session are held to the budget, so their c0, draws, vertices and pixels rise and fall
    together, and a richer model can fit them as well as the simplest one while pricing vertices at half
    the machine's rate and the rest as draws or fill. The solver then buys exactly what that model
    underprices, and the next selection overruns. On a real renderer, models that were equally right
    differ in their 20-frame score by 10–20 % from noise alone, so a margin of 10 % handed the session to
    such a model every few seconds; 30 % keeps the simplest until a richer one is clearly better, which a
    fill-bound scene still makes it.
    """

    def __init__(self, algorithms: int = 3, c_vertex: float = 2e-7, forgetting: float = 0.97, within: float = 0.30,
                 window: int = 60, min_frames: int = 10, batch: bool = False) -> None:
        if algorithms < 1 or not (math.isfinite(c_vertex) and c_vertex > 0) or not within >= 0 or window < 1:
            raise ValueError("algorithms ≥ 1, c_vertex > 0, within ≥ 0 and window ≥ 1 are needed")
        self.algorithms, self.within, self.window, self.min_frames = algorithms, within, window, min_frames
        self.rungs = {name: _Rung(name, algorithms, c_vertex, forgetting, window) for name in MODELS}
        self.chosen = "vertex"
        self.frames = 0
        self._ratios: deque[float] = deque(maxlen=100)  # measured ÷ predicted by the chosen model, held out
        #: Frames shorter than this, measured and predicted, do not count in ``tail_ratio`` (the session sets a
        #: share of its target): on a near-empty view the overhead's noise is a large share of a small frame.
        #: Nor do they move a model's per-unit prices (per vertex, face, pixel, draw, splat), only its c0: a
        #: renderer costs less per triangle at light loads than at the budget's, so prices learnt on a long
        #: stretch of light frames would underprice the next heavy view and its first frames would overrun
        #: the budget. A model whose prediction is not light (one pricing the work too high) still learns
        #: from light frames.
        self.tail_min_time = 0.0
        self.recent = max(1, window // 3)
        self.hold = max(1, window // 12)
        self._pending, self._count = "vertex", 0
        self._faces = self._verts = 0.0  # forgetful sums: faces per vertex, for ``predict`` (given no faces)
        self._lam = forgetting
        #: The lightest frame measured (empty ones too), rising by LEAST_RISE a frame: c0 ≤ LEAST_SLACK × it. On a
        #: tour whose frames all carry about the same load, c0 and the per-vertex cost are collinear and the
        #: held-out error cannot tell a model that puts nearly the whole frame in c0 (c_vert ≈ 0) from the
        #: right one, until the first larger selection costs far more than its prediction.
        self.least = math.inf
        #: Frames are checked as they come and folded when the model is next read: a session reads it once per
        #: selection, and folds the reports of one τ in one compiled pass (``cost_fold``), not one by one.
        self.batch = batch
        self._queue: list[tuple[float, np.ndarray, bool]] = []

    # ------------------------------------------------------------------ feeding it

    def observe(self, time: float, triangles: np.ndarray, vertices: np.ndarray, pixels: np.ndarray,
                draws: np.ndarray, splats: int = 0) -> bool:
        """Fold in one frame: measured seconds and what was drawn per algorithm ((R,) arrays).

        Returns whether it was used: non-finite, negative or absurd figures (counts in (0, 1e-6) or
        above 1e15), times under 1 ns (≤ 0 included) and frames that drew nothing (no vertices, no
        splats) are refused. Arrays of the wrong size raise ValueError. A ``batch`` model checks the
        frame now and folds it at the next read of the model (``flush``).
        """
        checked = self._check(time, triangles, vertices, pixels, draws, splats)
        if checked is None:
            return False
        self._queue.append(checked)
        if not self.batch or len(self._queue) >= BATCH_MAX:
            self.flush()
        return not checked[2]

    def _check(self, time, triangles, vertices, pixels, draws, splats):
        """(time, z row, drew nothing) of a frame worth folding, or None; ValueError for arrays of the wrong size.
        A frame report's dozen numbers are checked as Python floats: numpy's per-call cost is the most of it."""
        r = self.algorithms
        cols = []
        for name, a in (("triangles", triangles), ("vertices", vertices), ("pixels", pixels), ("draws", draws)):
            a = [float(x) for x in a] if isinstance(a, (list, tuple)) else np.asarray(a, np.float64).ravel().tolist()
            if len(a) != r:
                raise ValueError(f"{name} must have {r} entries (one per algorithm), got {len(a)}")
            cols.append(a)
        try:
            time, splats = float(time), float(splats)
        except (TypeError, ValueError):
            return None
        row = [1.0, *cols[0], *cols[1], *cols[2], sum(cols[3]), splats]
        if not (math.isfinite(time) and time >= 1e-9):
            return None  # no frame takes less than a nanosecond
        for x in row:
            # Counts, not numerical dust (which would put a coefficient's scale at infinity); NaN fails too.
            if not (x == 0.0 or 1e-6 <= x <= 1e15):
                return None
        return time, np.array(row), sum(cols[1]) + splats <= 0

    def flush(self) -> None:
        """Fold the frames checked but not yet folded, in order: in one compiled pass (``cost_fold``) for a
        ``batch`` model once the kernels are ready, else one by one (the reference)."""
        if not self._queue:
            return
        queue, self._queue = self._queue, []
        ready = kernels.compiled() if self.batch else None
        if ready is not None:
            fold_frames(self, np.array([q[0] for q in queue]), np.stack([q[1] for q in queue]),
                        np.array([q[2] for q in queue], np.uint8), ready.fold.fold, MODELS, LEAST_SLACK, LEAST_RISE)
            return
        for time, z, empty in queue:
            self._fold(time, z, empty)

    def _fold(self, time: float, z: np.ndarray, empty: bool) -> None:
        r = self.algorithms
        self.least = min(time, self.least * (1.0 + LEAST_RISE))  # an empty frame is the overhead alone
        if empty:
            return
        predicted = _frame(self.rungs[self.chosen].full(), z, r)
        if predicted > 0 and max(predicted, time) >= self.tail_min_time:
            self._ratios.append(time / predicted)  # the chosen model's held-out ratio, for ``tail_ratio``
        for rung in self.rungs.values():
            guess = _frame(rung.full(), z, r)
            rung.errors.append(abs(guess - time) / time)  # held out: before it learns
            rung.observe(time, z, LEAST_SLACK * self.least, light=max(guess, time) < self.tail_min_time)
        self._faces = self._lam * self._faces + z[1 : 1 + r].sum()
        self._verts = self._lam * self._verts + z[1 + r : 1 + 2 * r].sum()
        self.frames += 1
        self._select()

    def observe_frame(self, time: float, vertices: int, terms=None, splats: int = 0) -> bool:
        """``FrameCostModel.observe_frame``: ``observe`` with the frame's terms, ``update`` without them."""
        if terms is None:
            return self.update(time, vertices)
        return self.observe(time, *terms, splats)

    def tail_ratio(self, q: float = 0.95, least: int = 20, cap: float = 1.5, floor: float = 1.0) -> float:
        """The q-quantile of measured ÷ predicted frame time over recent frames (held out), at least ``floor``
        (1 by default: a budget for the tail never exceeds the mean's; below 1, it corrects a model that prices
        frames too high).

        A budget divided by it makes the q-th percentile frame, not the average one, meet the target:
        the machine's own noise (a shared CPU, a driver's stalls) is then part of what is budgeted.
        ``cap`` until ``least`` frames are known — an uncalibrated model is as likely to under- as to
        overestimate, and the first selection of a heavy scene is otherwise its worst frames; at most ``cap``
        afterwards, so one stalled stretch cannot starve the picture."""
        self.flush()
        if len(self._ratios) < least:
            return float(cap)
        return float(np.clip(np.quantile(np.fromiter(self._ratios, float), q), floor, cap))

    def update(self, time: float, vertices: int) -> bool:
        """``CostModel.update``: only the time and the vertices are known (flat, no draws, no pixels)."""
        v, zero = np.zeros(self.algorithms), np.zeros(self.algorithms)
        try:
            v[0] = float(vertices)
        except (TypeError, ValueError):
            return False
        return self.observe(time, zero, v, zero, zero)

    @property
    def updates(self) -> int:
        """``CostModel.updates``: frames used."""
        self.flush()
        return self.frames

    def scores(self, frames: int | None = None) -> dict:
        """Each model's mean held-out relative error over its last ``frames`` (default window / 3) frames."""
        n = frames or self.recent
        return {name: math.fsum(islice(r.errors, max(0, len(r.errors) - n), None)) / min(n, len(r.errors))
                if r.errors else math.inf for name, r in self.rungs.items()}

    def _select(self) -> None:
        if self.frames < self.min_frames:
            target = "vertex"
        elif self._regime_change():
            # The chosen model fails outright on the last frames while another predicts them: the scene's
            # regime changed (a heavy view after a stretch of near-empty ones, where every model fitted the
            # overhead alike and the simplest was kept). Take the best of those frames now, not after the hold — the
            # next selection is priced by it.
            last = self.scores(REGIME_FRAMES)
            self.chosen, self._count = min(last, key=last.get), 0
            return
        else:
            recent, whole = self.scores(), self.scores(self.window)
            limit, limit_whole = (1.0 + self.within) * min(recent.values()), (1.0 + self.within) * min(whole.values())
            at = MODELS.index(self.chosen)

            def passes(n: str) -> bool:
                # Going down also needs the whole window: a simpler model is not adopted because the last
                # frames happened to need no more (a second of geometry-bound frames between fill-bound ones).
                return recent[n] <= limit and (MODELS.index(n) >= at or whole[n] <= limit_whole)

            target = next((n for n in MODELS if passes(n)), min(recent, key=recent.get))
            if MODELS.index(target) > at and not self._worse(self.chosen, target):
                target = self.chosen  # going up needs the chosen model to be worse beyond the noise
        if target == self.chosen:
            self._count = 0
            return
        self._count = self._count + 1 if target == self._pending else 1
        self._pending = target
        if self._count >= self.hold:
            self.chosen, self._count = target, 0

    def _regime_change(self) -> bool:
        """The chosen model's held-out error on each of the last ``REGIME_FRAMES`` frames is over
        ``REGIME_ERROR`` and over ``REGIME_RATIO`` × another model's."""
        mine = list(islice(self.rungs[self.chosen].errors, max(0, len(self.rungs[self.chosen].errors) - REGIME_FRAMES),
                           None))
        if len(mine) < REGIME_FRAMES or min(mine) <= REGIME_ERROR:
            return False
        for name, rung in self.rungs.items():
            theirs = list(islice(rung.errors, max(0, len(rung.errors) - REGIME_FRAMES), None))
            if name != self.chosen and len(theirs) == REGIME_FRAMES and all(
                    a > REGIME_RATIO * b for a, b in zip(mine, theirs)):
                return True
        return False

    def _worse(self, a: str, b: str) -> bool:
        """Whether model a's recent held-out errors are above b's beyond the noise: a paired t > 1.5 over the
        same frames (two 20-frame means at 3 % noise differ by ~15 % by chance alone)."""
        ea, eb = self.rungs[a].errors, self.rungs[b].errors
        n = min(self.recent, len(ea))
        if n < 2:
            return True
        d = np.subtract(list(islice(ea, len(ea) - n, None)), list(islice(eb, len(eb) - n, None)))
        return bool(d.mean() > 1.5 * d.std(ddof=1) / math.sqrt(n))

    # ------------------------------------------------------------------ snapshot

    #: The fields a snapshot holds, besides the rungs.
    STATE = ("algorithms", "within", "window", "min_frames", "recent", "hold", "chosen", "frames", "_pending",
             "_count", "_faces", "_verts", "_lam", "least")

    def to_state(self) -> dict:
        """Every coefficient, covariance and history, as plain data (``from_state`` reads it back); frames checked
        but not yet folded go as they are (a snapshot does not fold them: a session saves more often than it
        selects)."""
        rungs = {name: rung.to_state() for name, rung in self.rungs.items()}
        out = {"kind": "online", **dump_fields(self, self.STATE), "rungs": rungs}
        if self._queue:
            out["queue"] = [[t, z.tolist(), empty] for t, z, empty in self._queue]
        return out

    def from_state(self, state) -> None:
        """Take in ``to_state``'s data; ValueError (model unchanged) if it is of another kind or does not fit."""
        if not isinstance(state, dict):
            raise ValueError("cost: expected a map")
        if state.get("kind") != "online":
            raise ValueError(f"cost: the snapshot's model is {state.get('kind')!r}, this server's 'online'")
        rungs = state.get("rungs")
        if not isinstance(rungs, dict) or set(rungs) != set(self.rungs):
            raise ValueError(f"cost: expected the rungs {sorted(self.rungs)}")
        for name in (state.get("chosen"), state.get("_pending")):
            if name not in MODELS:
                raise ValueError(f"cost: unknown model {name!r}")
        queue = queue_of(state.get("queue", []), 3 * self.algorithms + 3, BATCH_MAX)
        trial = copy.deepcopy(self)  # a bad rung leaves the model untouched
        trial._queue = []
        load_fields(trial, state, self.STATE, "cost")
        for name, rung in trial.rungs.items():
            rung.from_state(rungs[name], f"cost.{name}")
        trial._queue = queue
        self.__dict__.update(trial.__dict__)

    # ------------------------------------------------------------------ using it

    @property
    def overhead(self) -> float:
        """The chosen model's fixed seconds per frame (c0); 0 for "vertex"."""
        self.flush()
        return float(self.rungs[self.chosen].full()[0])

    @property
    def c_vertex(self) -> float:
        """Effective seconds per vertex of the chosen model: its recent predicted frame times without the
        overhead over the vertices (and splats) drawn — exactly c_v for "vertex". With it, c_vertex ·
        vertices + ``overhead`` is the frame time for callers that know only vertices."""
        return self.rungs[self.chosen].c_vertex()

    def _terms(self) -> tuple:
        self.flush()
        c, r = self.rungs[self.chosen].full(), self.algorithms
        return c[0], c[1 : 1 + r], c[1 + r : 1 + 2 * r], c[1 + 2 * r : 1 + 3 * r], c[-2], c[-1]

    def tuple_coefficients(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
        """(R,) C1, C2, C3 per algorithm and C0 per draw of the chosen model: ``predict_terms``' coefficients."""
        _, c1, c2, c3, c_draw, _ = self._terms()
        return c1, c2, c3, float(c_draw)

    def predict_terms(self, faces, vertices, pixels, algorithm=0, draws=1.0) -> np.ndarray:
        """Seconds per tuple, without the frame overhead, broadcasting like ``CostModel.predict_terms``:
        max(C1[R]·faces + C2[R]·vertices, C3[R]·pixels) + C0·draws — F&S's per-object cost."""
        alg = np.asarray(algorithm, np.int64)
        if alg.size and (alg.min() < 0 or alg.max() >= self.algorithms):
            raise ValueError(f"algorithm index out of range 0..{self.algorithms - 1}")
        _, c1, c2, c3, c_draw, _ = self._terms()
        geometry = c1[alg] * np.asarray(faces, np.float64) + c2[alg] * np.asarray(vertices, np.float64)
        fill = c3[alg] * np.asarray(pixels, np.float64)
        return np.maximum(geometry, fill) + c_draw * np.asarray(draws, np.float64)

    def predict(self, vertices) -> np.ndarray:
        """``CostModel.predict``: flat algorithm, one draw each, no pixels; faces at the ratio seen so far."""
        self.flush()
        v = np.asarray(vertices, np.float64)
        ratio = self._faces / self._verts if self._verts > 0 else 0.0
        return self.predict_terms(ratio * v, v, 0.0, 0, 1.0)

    def splat_cost(self, splats) -> np.ndarray:
        """Seconds for that many splats (c_splat · N; a group's c_tree is its draw)."""
        return self._terms()[-1] * np.asarray(splats, np.float64)

    def predict_frame(self, triangles, vertices, pixels, draws, splats=0) -> float:
        """Whole-frame seconds under the chosen model, overhead included; (R,) arrays as ``observe``."""
        self.flush()
        r = self.algorithms
        parts = [np.broadcast_to(np.asarray(a, np.float64).reshape(-1), (r,)) for a in (triangles, vertices, pixels)]
        z = np.concatenate([[1.0], *parts, [np.asarray(draws, np.float64).sum(), float(splats)]])
        return _frame(self.rungs[self.chosen].full(), z, r)

    def report(self) -> dict:
        """The chosen model, why (every model's held-out p50/p95/mean and score), and the coefficients."""
        self.flush()
        r = self.algorithms
        scores = self.scores()
        best = min(scores, key=scores.get)
        models = {}
        for name, rung in self.rungs.items():
            e = np.array(rung.errors)
            c = rung.full()
            coef = ({"c_vertex": float(c[1 + r])} if name == "vertex" else
                    {"c0": float(c[0]), "c_poly": c[1 : 1 + r].tolist(), "c_vert": c[1 + r : 1 + 2 * r].tolist(),
                     "c_pixel": c[1 + 2 * r : 1 + 3 * r].tolist(), "c_draw": float(c[-2]), "c_splat": float(c[-1])})
            if name == "draw":
                del coef["c_poly"], coef["c_pixel"]
            models[name] = {
                "p50": float(np.median(e)) if e.size else math.nan,
                "p95": float(np.quantile(e, 0.95)) if e.size else math.nan,
                "mean": float(e.mean()) if e.size else math.nan,
                "score": scores[name],
                "frames": int(e.size),
                "changes": rung.rls.changes,
                "coefficients": coef,
            }
            if name == "stages":
                models[name]["fill_bound"] = float(np.mean(rung.fill)) if rung.fill else 0.0
        limit = (1.0 + self.within) * scores[best]
        if self.frames < self.min_frames:
            why = f"{self.frames} < {self.min_frames} frames: the vertex model until the others are measured"
        else:
            why = (f"{self.chosen}: held-out score {scores[self.chosen]:.2%}, best {best} {scores[best]:.2%}, "
                   f"limit (1 + {self.within:g}) × best = {limit:.2%}"
                   + "".join(f"; {n} {scores[n]:.2%} is over it" for n in MODELS[: MODELS.index(self.chosen)]
                             if scores[n] > limit)
                   + (f"; {self._pending} asked for {self._count}/{self.hold} frames" if self._count else ""))
        return {"chosen": self.chosen, "why": why, "frames": self.frames, "within": self.within,
                "least_frame": self.least if math.isfinite(self.least) else None,
                "rule": f"simplest model whose mean held-out relative error over the last {self.recent} frames is "
                        f"≤ (1 + within) × the best's (going down: over the last {self.window} too; going up: the "
                        f"chosen one worse by a paired t > 1.5), asked for {self.hold} frames in a row",
                "models": models}
